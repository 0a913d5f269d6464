//! `echomap-agent experiment cooperative` (Ulmschneider et al. 2021 §V, Fig. 5): per run, a crowd of users
//! builds a map on a server one after another; the reference user then runs with the map
//! version left by the first c users, for every c asked (0 = alone), and its MAE against
//! travelled distance is collected over the runs.
//!
//! Real data (`--dataset mrclam DIR`): each robot in turn is the reference; the other robots
//! build the map in order, and the reference robot runs alone and with their map.

use crate::crowd::{self, CrowdSpec, Source, User, UserResult};
use crate::eval::{percentile, signed_rank_p};
use crate::evaluate::{Curves, write_curves};
use crate::local_server::LocalServer;
use anyhow::{Context, Result};
use std::path::{Path, PathBuf};

/// Settings of one cooperative experiment.
#[derive(Debug, Clone)]
pub struct ExperimentSpec {
    pub exe: PathBuf,
    /// existing server (else one is started on loopback)
    pub server: Option<String>,
    pub token_file: Option<PathBuf>,
    pub runs: u64,
    pub first_seed: u64,
    pub parallel: usize,
    /// configuration keys of contributors and of the reference user (partial tables, see
    /// `config`; each agent adds its log's sensor profile beneath them)
    pub crowd_config: serde_json::Value,
    pub reference_config: serde_json::Value,
    pub out: PathBuf,
    pub progress: bool,
    /// the started loopback server's `--match-visibility-weight`, `--match-score` and
    /// `--merge-absorb-chi2`
    pub match_visibility_weight: f64,
    pub match_score: echomap_shared::matching::MatchScore,
    pub merge_absorb_chi2: f64,
}

/// One evaluated configuration: its label and the per-run `(traveled, mae, err)` series.
type Series = Vec<(f64, f64, f64)>;

/// One reference run: its error series and its absolute trajectory error (m).
type Reference = (Series, f64);

/// `ate_m` of a run directory's `summary.json`.
fn read_ate(dir: &Path) -> Result<f64> {
    let path = dir.join("summary.json");
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
    // NaN (no transform could be fitted) is written as null
    Ok(v.get("ate_m").and_then(|x| x.as_f64()).unwrap_or(f64::NAN))
}

/// Curves of a configuration's reference runs, with their trajectory errors.
fn curves_of(label: String, refs: Vec<Reference>) -> Curves {
    let (runs, ate): (Vec<Series>, Vec<f64>) = refs.into_iter().unzip();
    Curves::from_runs(label, &runs, Vec::new()).with_ate(ate)
}

fn read_track(dir: &Path) -> Result<Series> {
    let path = dir.join("track.csv");
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or("").split(',').collect();
    let col = |n: &str| header.iter().position(|h| *h == n);
    let (Some(tr), Some(mae), Some(err)) = (col("traveled_m"), col("mae_m"), col("err_m")) else {
        anyhow::bail!("{} lacks traveled_m/mae_m/err_m", path.display());
    };
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            let p = |k: usize| -> Result<f64> {
                f.get(k)
                    .and_then(|v| v.parse().ok())
                    .with_context(|| format!("bad row in {}: {l}", path.display()))
            };
            Ok((p(tr)?, p(mae)?, p(err)?))
        })
        .collect()
}

/// The server an experiment talks to, with one client for its own requests.
struct Server {
    url: String,
    token_file: Option<PathBuf>,
    client: crate::client::MapClient,
    rt: tokio::runtime::Runtime,
    local: Option<LocalServer>,
}

impl Server {
    fn open(spec: &ExperimentSpec) -> Result<Self> {
        let (url, token_file, local) = match &spec.server {
            Some(url) => (url.clone(), spec.token_file.clone(), None),
            None => {
                let (weight, score) = (spec.match_visibility_weight, spec.match_score);
                let absorb = spec.merge_absorb_chi2;
                let local = LocalServer::start_with(|c| {
                    c.match_visibility_weight = weight;
                    c.match_score = score;
                    c.merge_absorb_chi2 = absorb;
                })?;
                println!(
                    "map server on {} (SQLite {})",
                    local.url,
                    local.database.display()
                );
                (
                    local.url.clone(),
                    Some(local.token_file.clone()),
                    Some(local),
                )
            }
        };
        let (client, rt) = crate::remote::connect(&url, token_file.as_deref())?;
        Ok(Server {
            url,
            token_file,
            client,
            rt,
            local,
        })
    }

    /// Stops the loopback server, if this experiment started one.
    fn close(self) -> Result<()> {
        match self.local {
            Some(l) => l.stop(),
            None => Ok(()),
        }
    }
}

/// Builds a map from `users` on `map` and returns their results.
fn build_map(
    spec: &ExperimentSpec,
    s: &Server,
    map: &str,
    users: &[User],
    dir: &Path,
) -> Result<Vec<UserResult>> {
    s.rt.block_on(s.client.create_map(map))
        .with_context(|| format!("creating map {map:?}"))?;
    let cs = CrowdSpec {
        exe: spec.exe.clone(),
        server: s.url.clone(),
        map: map.to_owned(),
        token_file: s.token_file.clone(),
        // contributors build the map one after another (Ulmschneider et al. 2021 §V)
        parallel: 1,
        config: spec.crowd_config.clone(),
        out: dir.to_path_buf(),
        progress: spec.progress,
    };
    let results = crowd::run_crowd(&cs, users);
    std::fs::write(dir.join("crowd.md"), crowd::table(&results))?;
    Ok(results)
}

/// Saves version `v` of `map` as a prior file (None for v = 0).
fn save_version(s: &Server, map: &str, v: i64, path: &Path) -> Result<Option<PathBuf>> {
    if v == 0 {
        return Ok(None);
    }
    let p =
        s.rt.block_on(s.client.fetch_version(map, v))
            .with_context(|| format!("fetching {map:?} version {v}"))?;
    std::fs::write(path, &p.body)?;
    Ok(Some(path.to_path_buf()))
}

/// Runs the reference user once per (label, prior) in parallel batches; returns the series.
fn run_references(
    spec: &ExperimentSpec,
    reference: &User,
    jobs: &[(String, Option<PathBuf>)],
    dir: &Path,
) -> Vec<Result<Reference>> {
    let config =
        match crowd::write_config(&spec.reference_config, &dir.join("reference-config.json")) {
            Ok(path) => path,
            Err(e) => return jobs.iter().map(|_| Err(anyhow::anyhow!("{e:#}"))).collect(),
        };
    crowd::in_order(jobs, spec.parallel, |(label, prior)| {
        let d = dir.join(format!("reference-{label}"));
        let mut args = crowd::run_args(reference, &d, &config);
        if let Some(p) = prior {
            args.extend(["--prior".into(), p.display().to_string()]);
        }
        crowd::run_process(&spec.exe, &args, &d).and_then(|_| Ok((read_track(&d)?, read_ate(&d)?)))
    })
}

fn label_of(c: usize) -> String {
    if c == 0 {
        "single-user".into()
    } else {
        format!("c{c:02}")
    }
}

/// Final and mean MAE and the median ATE per configuration: a Markdown table.
fn results_table(all: &[Curves], header: &str) -> String {
    let mut s = format!(
        "| {header} | runs | final MAE median (m) | final 5th–95th (m) | mean MAE median (m) | mean MAE mean (m) | ATE median (m) |\n| --- | --- | --- | --- | --- | --- | --- |\n"
    );
    for c in all {
        s.push_str(&format!(
            "| {} | {} | {:.2} | {:.2}–{:.2} | {:.2} | {:.2} | {:.2} |\n",
            c.label,
            c.final_mae.len(),
            percentile(&c.final_mae, 0.5),
            percentile(&c.final_mae, 0.05),
            percentile(&c.final_mae, 0.95),
            percentile(&c.mean_mae, 0.5),
            c.mean_mae.iter().sum::<f64>() / c.mean_mae.len().max(1) as f64,
            percentile(&c.ate_m, 0.5),
        ));
    }
    s
}

/// The simulated experiment: `contributors` (sorted, may include 0) out of the scenario's
/// `users` tracks; the reference user walks `reference_track`.
pub fn cooperative_scenario(
    spec: &ExperimentSpec,
    scenario: &str,
    crowd_tracks: &[String],
    reference_track: &str,
    contributors: &[usize],
) -> Result<Vec<Curves>> {
    let max_c = contributors.iter().copied().max().unwrap_or(0);
    anyhow::ensure!(
        max_c <= crowd_tracks.len(),
        "{max_c} contributors asked, the scenario has {} user tracks",
        crowd_tracks.len()
    );
    let s = Server::open(spec)?;
    let mut per_c: Vec<Vec<Reference>> = vec![Vec::new(); contributors.len()];
    for run in 0..spec.runs {
        let seed = spec.first_seed + run;
        let dir = spec.out.join(format!("run-seed{seed}"));
        std::fs::create_dir_all(&dir)?;
        let map = format!("coop-{}-seed{seed}", sanitize(scenario));
        println!(
            "run {}/{} (seed {seed}): {max_c} contributors build map {map:?}",
            run + 1,
            spec.runs
        );
        let users: Vec<User> = crowd_tracks[..max_c]
            .iter()
            .enumerate()
            .map(|(k, t)| User {
                name: t.clone(),
                source: Source::Scenario {
                    scenario: scenario.to_owned(),
                    track: t.clone(),
                },
                seed: seed * 1000 + k as u64 + 1,
            })
            .collect();
        let results = build_map(spec, &s, &map, &users, &dir)?;
        print!("{}", crowd::table(&results));
        let mut jobs = Vec::new();
        for &c in contributors {
            let v = results[..c]
                .iter()
                .filter_map(|r| r.version)
                .max()
                .unwrap_or(0);
            let prior = save_version(&s, &map, v, &dir.join(format!("prior-c{c:02}.json")))?;
            anyhow::ensure!(
                c == 0 || prior.is_some(),
                "none of the first {c} contributors' uploads was accepted (run seed {seed})"
            );
            jobs.push((label_of(c), prior));
        }
        let reference = User {
            name: "reference".into(),
            source: Source::Scenario {
                scenario: scenario.to_owned(),
                track: reference_track.to_owned(),
            },
            seed,
        };
        println!("  reference user with {} priors …", jobs.len());
        for (k, r) in run_references(spec, &reference, &jobs, &dir)
            .into_iter()
            .enumerate()
        {
            let (series, ate) =
                r.with_context(|| format!("reference run {} (seed {seed})", jobs[k].0))?;
            println!(
                "  {:>11}: final MAE {:.2} m, ATE {ate:.2} m",
                jobs[k].0,
                series.last().map(|x| x.1).unwrap_or(f64::NAN)
            );
            per_c[k].push((series, ate));
        }
    }
    s.close()?;
    let all: Vec<Curves> = contributors
        .iter()
        .zip(per_c)
        .map(|(&c, runs)| curves_of(label_of(c), runs))
        .collect();
    finish(
        &all,
        &format!(
            "{scenario} / {reference_track}, {} runs: reference user vs contributors",
            spec.runs
        ),
        "contributors",
        &spec.out,
    )?;
    Ok(all)
}

fn sanitize(s: &str) -> String {
    let base = Path::new(s)
        .file_stem()
        .and_then(|x| x.to_str())
        .unwrap_or(s)
        .to_ascii_lowercase();
    let clean: String = base
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' {
                c
            } else {
                '-'
            }
        })
        .take(32)
        .collect();
    if clean.is_empty() { "x".into() } else { clean }
}

fn finish(all: &[Curves], title: &str, header: &str, out: &Path) -> Result<()> {
    write_curves(all, title, out)?;
    let table = results_table(all, header);
    std::fs::write(out.join("results.md"), &table)?;
    println!("\n{table}");
    println!(
        "wrote {} (curves <label>.csv, error.png/svg, summary.json, results.md)",
        out.display()
    );
    Ok(())
}

/// MRCLAM: each robot of `references` is the reference once; the other robots of `logs` (in
/// order) build a map, then the reference runs alone and with it.
pub fn cooperative_mrclam(
    spec: &ExperimentSpec,
    logs: &[(u32, PathBuf)],
    references: &[u32],
) -> Result<Vec<(u32, Curves, Curves)>> {
    let s = Server::open(spec)?;
    let mut out = Vec::new();
    for (reference_robot, reference_log) in logs.iter().filter(|(r, _)| references.contains(r)) {
        let mut alone = Vec::new();
        let mut with = Vec::new();
        for run in 0..spec.runs {
            let seed = spec.first_seed + run;
            let dir = spec
                .out
                .join(format!("robot{reference_robot}/run-seed{seed}"));
            std::fs::create_dir_all(&dir)?;
            let map = format!("coop-mrclam-ref{reference_robot}-seed{seed}");
            let users: Vec<User> = logs
                .iter()
                .filter(|(r, _)| r != reference_robot)
                .map(|(r, d)| User {
                    name: format!("robot{r}"),
                    source: Source::Log(d.clone()),
                    seed: seed * 1000 + *r as u64,
                })
                .collect();
            println!(
                "robot {reference_robot} as reference, seed {seed}: robots {} build map {map:?}",
                users
                    .iter()
                    .map(|u| u.name.trim_start_matches("robot"))
                    .collect::<Vec<_>>()
                    .join(",")
            );
            let results = build_map(spec, &s, &map, &users, &dir)?;
            print!("{}", crowd::table(&results));
            let v = results.iter().filter_map(|r| r.version).max().unwrap_or(0);
            let prior = save_version(&s, &map, v, &dir.join("prior.json"))?;
            let reference = User {
                name: format!("robot{reference_robot}"),
                source: Source::Log(reference_log.clone()),
                seed,
            };
            let jobs = vec![
                ("alone".to_string(), None),
                ("with-others".to_string(), prior),
            ];
            let mut r = run_references(spec, &reference, &jobs, &dir).into_iter();
            alone.push(r.next().expect("two jobs")?);
            with.push(r.next().expect("two jobs")?);
        }
        let a = curves_of(format!("robot{reference_robot}-alone"), alone);
        let w = curves_of(format!("robot{reference_robot}-with-others"), with);
        out.push((*reference_robot, a, w));
    }
    s.close()?;
    let all: Vec<Curves> = out
        .iter()
        .flat_map(|(_, a, w)| [a.clone(), w.clone()])
        .collect();
    let title = format!(
        "MRCLAM, {} runs: each robot alone and with the others' map",
        spec.runs
    );
    finish(&all, &title, "robot / prior", &spec.out)?;
    let paired = paired_table(&all)?;
    let path = spec.out.join("results.md");
    let table = std::fs::read_to_string(&path)?;
    std::fs::write(&path, format!("{table}\n{paired}"))?;
    println!("\n{paired}");
    write_robot_panels(&all, &title, &spec.out)?;
    Ok(out)
}

/// Per reference robot, the runs with the others' map against the same runs alone (paired by
/// run): the median of the differences (with − alone) of the mean and of the final MAE, how
/// many runs are lower with the map, and the exact two-sided Wilcoxon signed-rank p-value of
/// the differences. Curves are paired by label (`robotN-alone` with `robotN-with-others`),
/// runs in the order they were appended; a robot with unequal run counts is an error.
/// The absolute trajectory error (after the best rigid alignment of the whole track, which
/// takes out a frame turned before the first landmark) is paired the same way when every run
/// of both has one, "—" otherwise.
pub fn paired_table(all: &[Curves]) -> Result<String> {
    let mut s = String::from(
        "| robot | runs | mean MAE: median of with − alone (m) | lower with the map | signed-rank p | final MAE: median of with − alone (m) | lower with the map | signed-rank p | ATE: median of with − alone (m) | lower with the map | signed-rank p |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n",
    );
    for alone in all.iter().filter(|c| c.label.ends_with("-alone")) {
        let robot = alone.label.trim_end_matches("-alone");
        let Some(with) = all
            .iter()
            .find(|c| c.label == format!("{robot}-with-others"))
        else {
            continue;
        };
        anyhow::ensure!(
            alone.mean_mae.len() == with.mean_mae.len()
                && alone.final_mae.len() == with.final_mae.len(),
            "{robot}: {} runs alone, {} with the map",
            alone.mean_mae.len(),
            with.mean_mae.len()
        );
        let cols = |a: &[f64], w: &[f64]| {
            let d: Vec<f64> = w.iter().zip(a).map(|(w, a)| w - a).collect();
            let p = signed_rank_p(&d).map_or("—".to_string(), |p| format!("{p:.3}"));
            format!(
                "{:+.3} | {} of {} | {p}",
                percentile(&d, 0.5),
                d.iter().filter(|x| **x < 0.0).count(),
                d.len()
            )
        };
        let n = alone.mean_mae.len();
        let ate = if alone.ate_m.len() == n && with.ate_m.len() == n {
            cols(&alone.ate_m, &with.ate_m)
        } else {
            "— | — | —".to_string()
        };
        s.push_str(&format!(
            "| {robot} | {n} | {} | {} | {ate} |\n",
            cols(&alone.mean_mae, &with.mean_mae),
            cols(&alone.final_mae, &with.final_mae)
        ));
    }
    Ok(s)
}

/// `robots.png/svg` in `dir`: one panel per reference robot (curves labelled `robotN-…`),
/// its mean MAE alone and with the others' map with their 5th/95th percentiles.
pub fn write_robot_panels(all: &[Curves], title: &str, dir: &Path) -> Result<()> {
    use plotters::style::RGBColor;
    let mut panels: Vec<(String, Vec<crate::plot::Curve>)> = Vec::new();
    for c in all {
        let robot = c.label.split('-').next().unwrap_or(&c.label).to_string();
        let color = if c.label.ends_with("alone") {
            RGBColor(0, 0, 220)
        } else {
            RGBColor(220, 0, 0)
        };
        let pts = |v: &[f64]| {
            c.traveled_m
                .iter()
                .copied()
                .zip(v.iter().copied())
                .collect()
        };
        let curves = vec![
            (format!("{} mean MAE", c.label), color, pts(&c.mae_mean)),
            (format!("{} p95", c.label), color, pts(&c.mae_p95)),
            (format!("{} p5", c.label), color, pts(&c.mae_p5)),
        ];
        match panels.iter_mut().find(|p| p.0 == robot) {
            Some(p) => p.1.extend(curves),
            None => panels.push((robot, curves)),
        }
    }
    for ext in ["png", "svg"] {
        crate::plot::draw_panels(
            &format!("{title}: MAE (mean, 5th/95th percentiles)"),
            "MAE (m)",
            &panels,
            panels.len().min(3),
            &dir.join(format!("robots.{ext}")),
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_paired_table_pairs_each_robots_runs_alone_and_with_the_map() {
        // robot 1: three runs, each lower with the map by 0.1, 0.2, 0.3 m (mean MAE of a
        // run (0, e, 2e) over 0, 1, 2 m is e); robot 4: one run higher with the map
        let runs = |es: &[f64]| -> Vec<Vec<(f64, f64, f64)>> {
            es.iter()
                .map(|&e| vec![(0.0, 0.0, 0.0), (1.0, e, e), (2.0, 2.0 * e, e)])
                .collect()
        };
        let c = |l: &str, es: &[f64]| Curves::from_runs(l.to_string(), &runs(es), Vec::new());
        // robot 1's ATEs: lower with the map in two of three runs; robot 4 has none
        let all = vec![
            c("robot1-alone", &[0.5, 0.6, 0.7]).with_ate(vec![0.3, 0.3, 0.3]),
            c("robot1-with-others", &[0.4, 0.4, 0.4]).with_ate(vec![0.2, 0.25, 0.4]),
            c("robot4-alone", &[0.3]),
            c("robot4-with-others", &[0.5]),
        ];
        let t = paired_table(&all).unwrap();
        let rows: Vec<&str> = t.lines().skip(2).collect();
        assert_eq!(rows.len(), 2, "{t}");
        let cells =
            |r: &str| -> Vec<String> { r.split('|').map(|x| x.trim().to_string()).collect() };
        let r1 = cells(rows[0]);
        assert_eq!(r1[1], "robot1");
        assert_eq!(r1[2], "3");
        let median: f64 = r1[3].parse().unwrap();
        assert!((median + 0.2).abs() < 1e-3, "{t}");
        assert_eq!(r1[4], "3 of 3");
        assert_eq!(r1[5], "0.250");
        let ate: f64 = r1[9].parse().unwrap();
        assert!((ate + 0.05).abs() < 1e-9, "{t}");
        assert_eq!(r1[10], "2 of 3");
        let r4 = cells(rows[1]);
        assert_eq!((r4[1].as_str(), r4[4].as_str()), ("robot4", "0 of 1"));
        assert_eq!(r4[9], "—", "no ATE, no pairing");
        assert!(r4[3].parse::<f64>().unwrap() > 0.0);
        // unequal run counts are refused
        let bad = vec![
            c("robot1-alone", &[0.5, 0.6]),
            c("robot1-with-others", &[0.4]),
        ];
        assert!(paired_table(&bad).is_err());
    }

    #[test]
    fn robot_panels_group_the_curves_by_reference_robot() {
        let run = |e: f64| vec![vec![(0.0, 0.0, 0.0), (1.0, e, e), (2.0, 2.0 * e, e)]];
        let all: Vec<Curves> = [("robot1-alone", 0.5), ("robot1-with-others", 0.3)]
            .into_iter()
            .chain([("robot4-alone", 0.7), ("robot4-with-others", 0.6)])
            .map(|(l, e)| Curves::from_runs(l.to_string(), &run(e), Vec::new()))
            .collect();
        let dir = std::env::temp_dir().join(format!("echomap-panels-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        write_robot_panels(&all, "test", &dir).unwrap();
        assert!(std::fs::metadata(dir.join("robots.png")).unwrap().len() > 1000);
        let svg = std::fs::read_to_string(dir.join("robots.svg")).unwrap();
        // one panel caption per robot, each panel with both of its robot's curves
        for label in [
            "robot1",
            "robot4",
            "robot1-with-others mean MAE",
            "robot4-alone p95",
        ] {
            assert!(svg.contains(&format!("\n{label}\n")), "{label} missing");
        }
        assert!(write_robot_panels(&[], "test", &dir).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

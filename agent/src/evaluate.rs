//! `echomap-agent evaluate`: Monte-Carlo evaluation over seeds, as in Gentner et al. 2016
//! Fig. 8 and Ulmschneider et al. 2021 Fig. 5 — mean MAE, the RMSE over runs of the weighted-mean estimate, and 5th/95th
//! percentiles, per snapshot against the (true) travelled distance.

use crate::config::RunConfig;
use crate::eval::percentile;
use crate::filter::Association;
use crate::run::run_filter;
use crate::sim::simulate::{SimOptions, simulate};
use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};
use plotters::style::RGBColor;
use serde::{Deserialize, Serialize};

/// Error curves of one configuration over several runs (the experiment's `summary.json` holds
/// a list of them).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Curves {
    pub label: String,
    pub traveled_m: Vec<f64>,
    pub mae_mean: Vec<f64>,
    pub mae_p5: Vec<f64>,
    pub mae_p95: Vec<f64>,
    /// √(mean over runs of ‖p̂ − p‖²)
    pub rmse: Vec<f64>,
    pub final_mae: Vec<f64>,
    pub mean_mae: Vec<f64>,
    /// per run: absolute trajectory error (m) of the whole track, see `RunSummary::ate_m`
    pub ate_m: Vec<f64>,
    pub wall_s: Vec<f64>,
}

impl Curves {
    /// Builds the curves from per-run (traveled, mae, err) series of equal length.
    pub fn from_runs(label: String, runs: &[Vec<(f64, f64, f64)>], wall_s: Vec<f64>) -> Self {
        let n = runs.iter().map(|r| r.len()).min().unwrap_or(0);
        let col = |k: usize, f: &dyn Fn(&(f64, f64, f64)) -> f64| {
            runs.iter().map(|r| f(&r[k])).collect::<Vec<f64>>()
        };
        let mut c = Curves {
            label,
            traveled_m: Vec::with_capacity(n),
            mae_mean: Vec::with_capacity(n),
            mae_p5: Vec::with_capacity(n),
            mae_p95: Vec::with_capacity(n),
            rmse: Vec::with_capacity(n),
            final_mae: runs.iter().filter_map(|r| r.last().map(|x| x.1)).collect(),
            mean_mae: runs
                .iter()
                .map(|r| r.iter().map(|x| x.1).sum::<f64>() / r.len().max(1) as f64)
                .collect(),
            ate_m: Vec::new(),
            wall_s,
        };
        #[allow(clippy::needless_range_loop)] // k indexes every run at once
        for k in 0..n {
            let mae = col(k, &|x| x.1);
            let err = col(k, &|x| x.2);
            c.traveled_m.push(runs[0][k].0);
            c.mae_mean.push(mae.iter().sum::<f64>() / mae.len() as f64);
            c.mae_p5.push(percentile(&mae, 0.05));
            c.mae_p95.push(percentile(&mae, 0.95));
            c.rmse
                .push((err.iter().map(|e| e * e).sum::<f64>() / err.len() as f64).sqrt());
        }
        c
    }

    /// The same curves with the per-run absolute trajectory errors.
    pub fn with_ate(mut self, ate_m: Vec<f64>) -> Self {
        self.ate_m = ate_m;
        self
    }

    pub fn csv(&self) -> String {
        let mut s = String::from("traveled_m,mae_mean_m,mae_p5_m,mae_p95_m,rmse_m\n");
        for k in 0..self.traveled_m.len() {
            s.push_str(&format!(
                "{},{},{},{},{}\n",
                self.traveled_m[k], self.mae_mean[k], self.mae_p5[k], self.mae_p95[k], self.rmse[k]
            ));
        }
        s
    }

    pub fn max(v: &[f64]) -> f64 {
        v.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
    }
}

const COLORS: [RGBColor; 6] = [
    RGBColor(0, 0, 220),
    RGBColor(220, 0, 0),
    RGBColor(0, 150, 0),
    RGBColor(230, 120, 0),
    RGBColor(120, 0, 160),
    RGBColor(0, 150, 160),
];

/// Writes `<label>.csv` per configuration, `summary.json`, and `error.png/svg`,
/// `rmse.png/svg` into `dir`.
pub fn write_curves(all: &[Curves], title: &str, dir: &std::path::Path) -> Result<()> {
    std::fs::create_dir_all(dir)?;
    let mut mae_plot = Vec::new();
    let mut rmse_plot = Vec::new();
    for (i, c) in all.iter().enumerate() {
        std::fs::write(dir.join(format!("{}.csv", c.label)), c.csv())?;
        let color = COLORS[i % COLORS.len()];
        let pts = |v: &[f64]| {
            c.traveled_m
                .iter()
                .copied()
                .zip(v.iter().copied())
                .collect::<Vec<_>>()
        };
        mae_plot.push((format!("{} mean MAE", c.label), color, pts(&c.mae_mean)));
        mae_plot.push((format!("{} p95", c.label), color, pts(&c.mae_p95)));
        mae_plot.push((format!("{} p5", c.label), color, pts(&c.mae_p5)));
        rmse_plot.push((format!("{} RMSE", c.label), color, pts(&c.rmse)));
    }
    std::fs::write(dir.join("summary.json"), serde_json::to_string_pretty(all)?)?;
    for ext in ["png", "svg"] {
        crate::plot::draw_curves(
            &format!("{title}: MAE (mean, 5th/95th percentiles)"),
            "MAE (m)",
            &mae_plot,
            &dir.join(format!("error.{ext}")),
        )?;
        crate::plot::draw_curves(
            &format!("{title}: RMSE over runs"),
            "RMSE (m)",
            &rmse_plot,
            &dir.join(format!("rmse.{ext}")),
        )?;
    }
    Ok(())
}

/// What `evaluate` runs: M seeds of one track of a scenario, per association method.
#[derive(Debug, Clone)]
pub struct EvaluateSpec {
    pub scenario: crate::sim::Scenario,
    pub track: String,
    pub toa_only: bool,
    pub seeds: u64,
    pub first_seed: u64,
    /// association methods to compare (empty: the configuration's)
    pub compare: Vec<Association>,
    /// the filter's configuration (resolved against the scenario's sensor profile)
    pub config: RunConfig,
    pub out: std::path::PathBuf,
}

pub fn evaluate(a: &EvaluateSpec) -> Result<()> {
    let scenario = &a.scenario;
    let methods = if a.compare.is_empty() {
        vec![a.config.association.method]
    } else {
        a.compare.clone()
    };
    let bar = ProgressBar::new(a.seeds * methods.len() as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "evaluate [{elapsed_precise}] {wide_bar} {pos}/{len} runs {msg}",
        )
        .expect("static template"),
    );
    let mut all = Vec::new();
    for method in methods {
        let mut runs = Vec::new();
        let mut ate = Vec::new();
        let mut wall = Vec::new();
        for seed in a.first_seed..a.first_seed + a.seeds {
            bar.set_message(format!("{method:?} seed {seed}"));
            let sim = simulate(
                scenario,
                &a.track,
                SimOptions {
                    seed,
                    toa_only: a.toa_only,
                },
            )?;
            let v0 = sim.truth.poses.first().map(|p| p.speed_mps).unwrap_or(0.0);
            let mut cfg = a.config.filter_config(seed, v0);
            cfg.association = method;
            let start = std::time::Instant::now();
            let out = run_filter(&sim.log, Some(&sim.truth), cfg, false)?;
            wall.push(start.elapsed().as_secs_f64());
            ate.push(crate::output::track_ate(&out.rows, &sim.truth));
            runs.push(
                out.rows
                    .iter()
                    .filter_map(|r| r.truth.map(|t| (r.traveled_m, t.mae_m, t.err_m)))
                    .collect::<Vec<_>>(),
            );
            bar.inc(1);
        }
        let label = format!("{method:?}").to_lowercase();
        let c = Curves::from_runs(label, &runs, wall).with_ate(ate);
        println!(
            "{:>4}: max RMSE {:.2} m, max mean-MAE {:.2} m, final MAE median {:.2} m (5th {:.2}, 95th {:.2}), ATE median {:.2} m, wall {:.1} s/run",
            c.label,
            Curves::max(&c.rmse),
            Curves::max(&c.mae_mean),
            percentile(&c.final_mae, 0.5),
            percentile(&c.final_mae, 0.05),
            percentile(&c.final_mae, 0.95),
            percentile(&c.ate_m, 0.5),
            c.wall_s.iter().sum::<f64>() / c.wall_s.len().max(1) as f64
        );
        all.push(c);
    }
    bar.finish_and_clear();
    write_curves(
        &all,
        &format!(
            "{} / {}, {} runs, {} particles",
            scenario.name, a.track, a.seeds, a.config.particles
        ),
        &a.out,
    )?;
    println!("wrote {}", a.out.display());
    Ok(())
}

/// One recorded log with ground truth to evaluate, and the configuration resolved for it
/// (its own sensor profile and measured noise).
#[derive(Debug, Clone)]
pub struct LogCase {
    pub name: String,
    pub log: echomap_shared::log::MeasurementLog,
    pub truth: echomap_shared::log::GroundTruth,
    pub config: RunConfig,
}

/// One run of [`evaluate_logs`] (a row of `runs.csv`).
#[derive(Debug, Clone, Serialize)]
pub struct LogRun {
    pub log: String,
    pub seed: u64,
    pub mae_mean_m: f64,
    pub mae_final_m: f64,
    pub dead_reckoning_mean_m: f64,
    pub dead_reckoning_final_m: f64,
    /// mean MAE over dead reckoning's mean error
    pub ratio: f64,
    /// mean error of the reported position (`error_mean_m`) over dead reckoning's
    pub error_ratio: f64,
    pub coverage95: f64,
}

/// The share of runs and logs `evaluate --logs` reports.
#[derive(Debug, Clone, Serialize)]
pub struct LogsSummary {
    pub runs: Vec<LogRun>,
    /// per log: the mean over its runs of the ratio
    pub log_ratio: Vec<(String, f64)>,
    /// the median over logs of `log_ratio`
    pub median_ratio: f64,
    /// logs whose mean ratio is above 1 (worse than their own odometry)
    pub logs_above_1: usize,
    /// the same three for the error of the reported position (`error_ratio`)
    pub log_error_ratio: Vec<(String, f64)>,
    pub median_error_ratio: f64,
    pub logs_error_above_1: usize,
    /// mean over all runs of coverage95
    pub mean_coverage95: f64,
}

/// `evaluate --logs`: every log × seeds `first_seed..first_seed + seeds`, the filter's mean
/// error against dead reckoning from the same log's odometry; writes `runs.csv`,
/// `summary.json`, `results.md` and `ratio.png/svg` into `out`. Every log must carry speed
/// (dead reckoning needs it).
pub fn evaluate_logs(
    cases: &[LogCase],
    seeds: u64,
    first_seed: u64,
    out: &std::path::Path,
) -> Result<LogsSummary> {
    anyhow::ensure!(!cases.is_empty(), "no log to evaluate");
    anyhow::ensure!(seeds >= 1, "--seeds must be at least 1");
    for c in cases {
        anyhow::ensure!(
            c.log.header.speed,
            "{}: the log carries no speed, so it has no dead reckoning to compare with",
            c.name
        );
    }
    let bar = ProgressBar::new(seeds * cases.len() as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "evaluate [{elapsed_precise}] {wide_bar} {pos}/{len} runs {msg}",
        )
        .expect("static template"),
    );
    let mut runs = Vec::new();
    for c in cases {
        let v0 = c.truth.poses.first().map(|p| p.speed_mps).unwrap_or(0.0);
        for seed in first_seed..first_seed + seeds {
            bar.set_message(format!("{} seed {seed}", c.name));
            let out = run_filter(
                &c.log,
                Some(&c.truth),
                c.config.filter_config(seed, v0),
                false,
            )?;
            let s = crate::output::summarize(&out, &c.truth, &c.log);
            let dr = s.dead_reckoning_mean_m.unwrap_or(f64::NAN);
            runs.push(LogRun {
                log: c.name.clone(),
                seed,
                mae_mean_m: s.mae_mean_m,
                mae_final_m: s.mae_final_m,
                dead_reckoning_mean_m: dr,
                dead_reckoning_final_m: s.dead_reckoning_final_m.unwrap_or(f64::NAN),
                ratio: s.mae_mean_m / dr,
                error_ratio: s.error_mean_m / dr,
                coverage95: s.coverage95,
            });
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    let per_log: Vec<(String, Vec<f64>)> = cases
        .iter()
        .map(|c| {
            let v = runs.iter().filter(|r| r.log == c.name).map(|r| r.ratio);
            (c.name.clone(), v.collect())
        })
        .collect();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let log_ratio: Vec<(String, f64)> = per_log.iter().map(|(n, v)| (n.clone(), mean(v))).collect();
    let ratios: Vec<f64> = log_ratio.iter().map(|x| x.1).collect();
    let log_error_ratio: Vec<(String, f64)> = cases
        .iter()
        .map(|c| {
            let v: Vec<f64> = runs
                .iter()
                .filter(|r| r.log == c.name)
                .map(|r| r.error_ratio)
                .collect();
            (c.name.clone(), mean(&v))
        })
        .collect();
    let error_ratios: Vec<f64> = log_error_ratio.iter().map(|x| x.1).collect();
    let summary = LogsSummary {
        median_ratio: percentile(&ratios, 0.5),
        logs_above_1: ratios.iter().filter(|&&r| r > 1.0).count(),
        median_error_ratio: percentile(&error_ratios, 0.5),
        logs_error_above_1: error_ratios.iter().filter(|&&r| r > 1.0).count(),
        log_error_ratio,
        mean_coverage95: mean(&runs.iter().map(|r| r.coverage95).collect::<Vec<_>>()),
        log_ratio,
        runs,
    };
    std::fs::create_dir_all(out)?;
    let mut csv = String::from(
        "log,seed,mae_mean_m,mae_final_m,dead_reckoning_mean_m,dead_reckoning_final_m,ratio,coverage95,error_ratio\n",
    );
    for r in &summary.runs {
        csv.push_str(&format!(
            "{},{},{},{},{},{},{},{},{}\n",
            r.log,
            r.seed,
            r.mae_mean_m,
            r.mae_final_m,
            r.dead_reckoning_mean_m,
            r.dead_reckoning_final_m,
            r.ratio,
            r.coverage95,
            r.error_ratio
        ));
    }
    std::fs::write(out.join("runs.csv"), csv)?;
    std::fs::write(
        out.join("summary.json"),
        serde_json::to_string_pretty(&summary)?,
    )?;
    std::fs::write(out.join("results.md"), logs_markdown(&summary, cases))?;
    let particles = cases[0].config.particles;
    for ext in ["png", "svg"] {
        crate::plot::draw_ratios(
            &format!(
                "{} logs × {seeds} seeds, {particles} particles",
                cases.len()
            ),
            &per_log,
            &out.join(format!("ratio.{ext}")),
        )?;
    }
    Ok(summary)
}

/// The per-log table of [`evaluate_logs`] in Markdown.
fn logs_markdown(s: &LogsSummary, cases: &[LogCase]) -> String {
    let mut md = String::from(
        "| log | DR mean (m) | filter mean MAE per seed (m) | ratio per seed | mean ratio | error of the reported position / DR (mean) | coverage95 (mean) |\n| --- | --- | --- | --- | --- | --- | --- |\n",
    );
    for ((c, (_, ratio)), (_, error_ratio)) in
        cases.iter().zip(&s.log_ratio).zip(&s.log_error_ratio)
    {
        let runs: Vec<&LogRun> = s.runs.iter().filter(|r| r.log == c.name).collect();
        let join = |f: &dyn Fn(&LogRun) -> f64| {
            runs.iter()
                .map(|r| format!("{:.2}", f(r)))
                .collect::<Vec<_>>()
                .join(" / ")
        };
        let cov = runs.iter().map(|r| r.coverage95).sum::<f64>() / runs.len().max(1) as f64;
        md.push_str(&format!(
            "| {} | {:.2} | {} | {} | {:.2} | {:.2} | {:.2} |\n",
            c.name,
            runs.first()
                .map(|r| r.dead_reckoning_mean_m)
                .unwrap_or(f64::NAN),
            join(&|r| r.mae_mean_m),
            join(&|r| r.ratio),
            ratio,
            error_ratio,
            cov
        ));
    }
    md.push_str(&format!(
        "\nMedian over the {} logs of the mean ratio: **{:.2}**; logs above 1.0: **{}**; of the reported position's error: **{:.2}**, above 1.0: **{}**; mean coverage of the 95 % ellipse: {:.2}.\n",
        cases.len(),
        s.median_ratio,
        s.logs_above_1,
        s.median_error_ratio,
        s.logs_error_above_1,
        s.mean_coverage95
    ));
    md
}

//! `echomap-agent crowd`: many users as separate operating-system processes of
//! `echomap-agent run --server … --map …`, one after another (each getting the map left by
//! the previous ones, Ulmschneider et al. 2021 §V) or up to `--parallel K` at once. One spinner per process,
//! a summary table at the end; a failed process is reported and does not stop the others.

use anyhow::{Context, Result};
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// Where a user's measurements come from.
#[derive(Debug, Clone)]
pub enum Source {
    /// simulate this track of a scenario
    Scenario { scenario: String, track: String },
    /// a measurement-log directory (log.jsonl, truth.json)
    Log(PathBuf),
}

/// One agent process of a crowd.
#[derive(Debug, Clone)]
pub struct User {
    pub name: String,
    pub source: Source,
    pub seed: u64,
}

/// What every process of a crowd shares.
#[derive(Debug, Clone)]
pub struct CrowdSpec {
    /// the `echomap-agent` executable to launch
    pub exe: PathBuf,
    pub server: String,
    pub map: String,
    pub token_file: Option<PathBuf>,
    pub parallel: usize,
    /// configuration keys of every agent (a partial table, see `config`), handed to each
    /// process as a configuration file
    pub config: serde_json::Value,
    /// per-user output directories are created below this
    pub out: PathBuf,
    /// show spinners
    pub progress: bool,
}

/// Outcome of one agent process.
#[derive(Debug, Clone, Serialize)]
pub struct UserResult {
    pub user: String,
    pub seed: u64,
    pub ok: bool,
    pub error: Option<String>,
    pub mae_final_m: Option<f64>,
    pub mae_mean_m: Option<f64>,
    pub transmitters: Option<usize>,
    /// the map version its upload produced (None when rejected or failed)
    pub version: Option<i64>,
    /// `accepted (N inliers)` / `rejected: reason`
    pub upload: String,
    pub prior_matched_at_s: Option<f64>,
    pub wall_s: f64,
    pub dir: PathBuf,
}

/// Writes a partial configuration table as a file for `run --config`.
pub fn write_config(config: &serde_json::Value, path: &Path) -> Result<PathBuf> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    std::fs::write(path, serde_json::to_string_pretty(config)?)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(path.to_path_buf())
}

/// The `run` arguments of one user (without server flags).
pub fn run_args(user: &User, out: &Path, config: &Path) -> Vec<String> {
    let mut a: Vec<String> = vec!["run".into()];
    match &user.source {
        Source::Scenario { scenario, track } => {
            a.extend(["--scenario".into(), scenario.clone()]);
            a.extend(["--track".into(), track.clone()]);
        }
        Source::Log(dir) => a.extend(["--log".into(), dir.display().to_string()]),
    }
    a.extend(["--seed".into(), user.seed.to_string()]);
    a.extend(["--out".into(), out.display().to_string(), "--quiet".into()]);
    a.extend(["--config".into(), config.display().to_string()]);
    a
}

/// Runs one `echomap-agent` process with `args`, stdout and stderr into `dir/agent.log`.
pub fn run_process(exe: &Path, args: &[String], dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let log = std::fs::File::create(dir.join("agent.log"))?;
    let status = Command::new(exe)
        .args(args)
        .stdin(Stdio::null())
        .stdout(log.try_clone()?)
        .stderr(log)
        .status()
        .with_context(|| format!("starting {}", exe.display()))?;
    if status.success() {
        Ok(())
    } else {
        let text = std::fs::read_to_string(dir.join("agent.log")).unwrap_or_default();
        let last = text
            .lines()
            .rev()
            .find(|l| !l.trim().is_empty())
            .unwrap_or("")
            .to_owned();
        anyhow::bail!("exit {status}: {last}")
    }
}

fn read_json(path: &Path) -> Option<serde_json::Value> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

fn collect(user: &User, dir: &Path, outcome: Result<()>, wall_s: f64) -> UserResult {
    let summary = read_json(&dir.join("summary.json"));
    let upload = read_json(&dir.join("upload.json"));
    let f = |k: &str| summary.as_ref().and_then(|s| s[k].as_f64());
    let (version, upload_text) = match &upload {
        Some(u) if u["status"] == "accepted" => (
            u["response"]["version"].as_i64(),
            format!(
                "accepted ({} inliers, {} merged, {} added)",
                u["response"]["inliers"], u["response"]["merged"], u["response"]["added"]
            ),
        ),
        Some(u) => (
            None,
            format!(
                "rejected: {}",
                u["response"]["detail"].as_str().unwrap_or("?")
            ),
        ),
        None => (None, "—".into()),
    };
    UserResult {
        user: user.name.clone(),
        seed: user.seed,
        ok: outcome.is_ok(),
        error: outcome.err().map(|e| format!("{e:#}")),
        mae_final_m: f("mae_final_m"),
        mae_mean_m: f("mae_mean_m"),
        transmitters: summary
            .as_ref()
            .and_then(|s| s["transmitters"].as_u64())
            .map(|v| v as usize),
        version,
        upload: upload_text,
        prior_matched_at_s: f("prior_matched_at_s"),
        wall_s,
        dir: dir.to_path_buf(),
    }
}

/// `f` over `items` on at most `workers` threads, taken in order; results in item order.
pub fn in_order<T: Sync, R: Send>(
    items: &[T],
    workers: usize,
    f: impl Fn(&T) -> R + Sync,
) -> Vec<R> {
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<Option<R>>> = Mutex::new((0..items.len()).map(|_| None).collect());
    std::thread::scope(|s| {
        for _ in 0..workers.clamp(1, items.len().max(1)) {
            s.spawn(|| {
                loop {
                    let i = next.fetch_add(1, Ordering::SeqCst);
                    let Some(item) = items.get(i) else { break };
                    let r = f(item);
                    results.lock().expect("no panic holds the lock")[i] = Some(r);
                }
            });
        }
    });
    results
        .into_inner()
        .expect("no panic holds the lock")
        .into_iter()
        .map(|r| r.expect("every item ran"))
        .collect()
}

/// Runs the users in order, at most `spec.parallel` at once; results in user order.
pub fn run_crowd(spec: &CrowdSpec, users: &[User]) -> Vec<UserResult> {
    let multi = if spec.progress {
        MultiProgress::new()
    } else {
        MultiProgress::with_draw_target(indicatif::ProgressDrawTarget::hidden())
    };
    let style = ProgressStyle::with_template("{spinner} {prefix:>8} [{elapsed_precise}] {msg}")
        .expect("static template");
    let config = write_config(&spec.config, &spec.out.join("agent-config.json"));
    in_order(users, spec.parallel, |user| {
        let config = match &config {
            Ok(path) => path,
            Err(e) => {
                let dir = spec.out.join(&user.name);
                return collect(user, &dir, Err(anyhow::anyhow!("{e:#}")), 0.0);
            }
        };
        let bar = multi.add(ProgressBar::new_spinner());
        bar.set_style(style.clone());
        bar.set_prefix(user.name.clone());
        bar.set_message("running");
        bar.enable_steady_tick(Duration::from_millis(200));
        let dir = spec.out.join(&user.name);
        let mut args = run_args(user, &dir, config);
        args.extend([
            "--server".into(),
            spec.server.clone(),
            "--map".into(),
            spec.map.clone(),
            "--contributor".into(),
            user.name.clone(),
        ]);
        if let Some(t) = &spec.token_file {
            args.extend(["--token-file".into(), t.display().to_string()]);
        }
        let start = Instant::now();
        let outcome = run_process(&spec.exe, &args, &dir);
        let r = collect(user, &dir, outcome, start.elapsed().as_secs_f64());
        bar.finish_with_message(match (&r.error, r.mae_final_m) {
            (Some(e), _) => format!("FAILED: {e}"),
            (None, Some(m)) => format!("final MAE {m:.2} m, {}", r.upload),
            (None, None) => r.upload.clone(),
        });
        r
    })
}

fn opt(v: Option<f64>) -> String {
    v.map_or("—".into(), |x| format!("{x:.2}"))
}

/// The summary table (Markdown).
pub fn table(results: &[UserResult]) -> String {
    let mut s = String::from(
        "| user | seed | final MAE (m) | mean MAE (m) | transmitters | prior matched at (s) | version after upload | upload |\n| --- | --- | --- | --- | --- | --- | --- | --- |\n",
    );
    for r in results {
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} |\n",
            r.user,
            r.seed,
            opt(r.mae_final_m),
            opt(r.mae_mean_m),
            r.transmitters.map_or("—".into(), |v| v.to_string()),
            opt(r.prior_matched_at_s),
            r.version.map_or("—".into(), |v| v.to_string()),
            match &r.error {
                Some(e) => format!("FAILED: {}", e.replace('|', "/")),
                None => r.upload.replace('|', "/"),
            }
        ));
    }
    s
}

//! `echomap-load`: load benchmark of the map server on loopback.
//!
//! Starts `echomap-server` (the binary next to this one) as a child process on a temporary
//! SQLite file — or `--replicas N` processes on one `--database-url postgres://…` — seeds a map,
//! then measures
//! 1. `GET /v1/maps/{map}` of a 100-transmitter, 3-component map at `--connections`
//!    connections, and the same bytes from a static file server (`echomap-load serve-static`,
//!    tower-http `ServeDir`, also a child process) in the same run;
//! 2. contributions of 30-transmitter user maps from `--uploaders` concurrent uploaders;
//!
//! and reports throughput, p50/p99 latency and the server's peak RSS (`VmHWM`). With several
//! replicas, connection and uploader `i` use replica `i mod N`.

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use echomap_server::heads::ReplicaCache;
use echomap_server::synth;
use std::path::PathBuf;
use std::process::Stdio;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, Command};

// The load generator shares the cores with the server: keep its allocations cheap too.
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Debug, Parser)]
#[command(
    name = "echomap-load",
    version,
    about = "Load benchmark of echomap-server on loopback"
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Cmd>,
    /// seconds per measured phase
    #[arg(long, default_value_t = 10.0)]
    duration_s: f64,
    /// concurrent connections of the GET phase
    #[arg(long, default_value_t = 64)]
    connections: usize,
    /// concurrent uploaders of the contribution phase
    #[arg(long, default_value_t = 16)]
    uploaders: usize,
    /// transmitters of the served map
    #[arg(long, default_value_t = 100)]
    transmitters: usize,
    /// transmitters per uploaded user map
    #[arg(long, default_value_t = 30)]
    upload_transmitters: usize,
    /// maps the uploaders are spread over (uploader i writes map i mod K); merges of one
    /// map are serialized, different maps merge in parallel
    #[arg(long, default_value_t = 1)]
    maps: usize,
    /// database of the servers (default: a SQLite file in a temporary directory); a
    /// PostgreSQL database must be empty of `load-*` maps (use a fresh one per run)
    #[arg(long)]
    database_url: Option<String>,
    /// server processes on the one database (several need PostgreSQL)
    #[arg(long, default_value_t = 1)]
    replicas: usize,
    /// the servers' `--replica-cache` (PostgreSQL): `check` reads the head per GET, `listen`
    /// trusts the cache until a notification says the head moved
    #[arg(long, default_value_t = ReplicaCache::Check)]
    replica_cache: ReplicaCache,
    /// seed of the synthetic maps
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// serve a directory's files on 127.0.0.1:0 (the static baseline); prints the address
    ServeStatic { dir: PathBuf },
}

#[derive(Debug, Default)]
struct Phase {
    ok: u64,
    errors: u64,
    latencies_s: Vec<f64>,
    elapsed_s: f64,
}

impl Phase {
    fn percentile(&self, p: f64) -> f64 {
        let mut v = self.latencies_s.clone();
        v.sort_by(f64::total_cmp);
        if v.is_empty() {
            return f64::NAN;
        }
        v[((p / 100.0) * (v.len() - 1) as f64).round() as usize]
    }
    fn rate(&self) -> f64 {
        self.ok as f64 / self.elapsed_s
    }
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    match &cli.command {
        Some(Cmd::ServeStatic { dir }) => rt.block_on(serve_static(dir.clone())),
        None => rt.block_on(bench(&cli)),
    }
}

async fn serve_static(dir: PathBuf) -> Result<()> {
    let app = axum::Router::new().fallback_service(tower_http::services::ServeDir::new(dir));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    println!("static listening on http://{}", listener.local_addr()?);
    use std::io::Write;
    std::io::stdout().flush()?;
    axum::serve(listener, app).await?;
    Ok(())
}

fn sibling(name: &str) -> Result<PathBuf> {
    let me = std::env::current_exe()?;
    let p = me.with_file_name(name);
    if !p.exists() {
        bail!(
            "{} not found next to echomap-load; build the workspace first",
            p.display()
        );
    }
    Ok(p)
}

async fn spawn(cmd: &mut Command, prefix: &str) -> Result<(Child, String)> {
    let mut child = cmd.stdout(Stdio::piped()).kill_on_drop(true).spawn()?;
    let mut line = String::new();
    BufReader::new(child.stdout.take().context("stdout")?)
        .read_line(&mut line)
        .await?;
    let base = line
        .trim()
        .strip_prefix(prefix)
        .with_context(|| format!("unexpected first line {line:?}"))?
        .to_owned();
    Ok((child, base))
}

/// Peak resident set (`VmHWM`) of a process, MiB.
fn peak_rss_mib(pid: u32) -> Option<f64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// `connections` keep-alive connections, connection `i` to `urls[i mod N]`.
async fn get_phase(urls: &[String], connections: usize, duration: Duration) -> Result<Phase> {
    let stop = Instant::now() + duration;
    let mut tasks = Vec::new();
    for i in 0..connections {
        // one client per task: one keep-alive connection each
        let c = echomap_server::http::client_builder()
            .pool_max_idle_per_host(1)
            .build()?;
        let url = urls[i % urls.len()].clone();
        tasks.push(tokio::spawn(async move {
            let mut p = Phase::default();
            while Instant::now() < stop {
                let t = Instant::now();
                match c.get(&url).send().await {
                    Ok(r) if r.status().is_success() => match r.bytes().await {
                        Ok(_) => {
                            p.ok += 1;
                            p.latencies_s.push(t.elapsed().as_secs_f64());
                        }
                        Err(_) => p.errors += 1,
                    },
                    _ => p.errors += 1,
                }
            }
            p
        }));
    }
    collect(tasks, duration).await
}

async fn collect(tasks: Vec<tokio::task::JoinHandle<Phase>>, duration: Duration) -> Result<Phase> {
    let mut all = Phase {
        elapsed_s: duration.as_secs_f64(),
        ..Phase::default()
    };
    for t in tasks {
        let p = t.await?;
        all.ok += p.ok;
        all.errors += p.errors;
        all.latencies_s.extend(p.latencies_s);
    }
    Ok(all)
}

fn report(name: &str, p: &Phase) {
    println!(
        "{name:<28} {:>9.0} req/s  p50 {:>7.2} ms  p99 {:>7.2} ms  ({} ok, {} errors)",
        p.rate(),
        p.percentile(50.0) * 1e3,
        p.percentile(99.0) * 1e3,
        p.ok,
        p.errors
    );
}

async fn bench(cli: &Cli) -> Result<()> {
    let dir = tempfile::tempdir()?;
    let tokens: Vec<String> = (0..cli.uploaders.max(1))
        .map(|i| format!("load-token-{i:04}-0123456789"))
        .collect();
    let token_file = dir.path().join("tokens.txt");
    let mut text = String::from("load-operator-0123456789 operator *\n");
    for (i, t) in tokens.iter().enumerate() {
        text.push_str(&format!("{t} uploader-{i} *\n"));
    }
    std::fs::write(&token_file, text)?;
    let db = match &cli.database_url {
        Some(url) => url.clone(),
        None => dir.path().join("load.db").display().to_string(),
    };
    let replicas = cli.replicas.max(1);
    if replicas > 1
        && echomap_server::storage::Kind::of_url(&db) != echomap_server::storage::Kind::Postgres
    {
        bail!("--replicas {replicas} needs a shared database: --database-url postgres://…");
    }
    let mut servers = Vec::new();
    for _ in 0..replicas {
        servers.push(
            spawn(
                Command::new(sibling("echomap-server")?)
                    .args(["--listen", "127.0.0.1:0", "--database-url"])
                    .arg(&db)
                    .arg("--token-file")
                    .arg(&token_file)
                    .arg("--replica-cache")
                    .arg(cli.replica_cache.to_string())
                    .env("RUST_LOG", "warn")
                    .env("ECHOMAP_RATE_LIMIT", "1000000")
                    .env("ECHOMAP_RATE_BURST", "1000000"),
                "echomap-server listening on ",
            )
            .await?,
        );
    }
    let pids: Vec<u32> = servers
        .iter()
        .map(|(child, _)| child.id().context("server pid"))
        .collect::<Result<_>>()?;
    let bases: Vec<String> = servers.iter().map(|(_, base)| base.clone()).collect();
    let base = bases[0].clone();
    println!(
        "{replicas} server process(es) on {}",
        echomap_server::storage::redact(&db)
    );
    let c = echomap_server::http::client_builder().build()?;
    if c.get(format!("{base}/v1/maps/load-0"))
        .send()
        .await?
        .status()
        != 404
    {
        bail!("the database already holds the map load-0: give each run a fresh database");
    }
    let world = synth::world(cli.seed, cli.transmitters);
    let maps = cli.maps.max(1);
    for m in 0..maps {
        c.put(format!("{base}/v1/maps/load-{m}"))
            .bearer_auth("load-operator-0123456789")
            .send()
            .await?
            .error_for_status()?;
        let first = synth::contribution(synth::user_map(&world, cli.seed, 1.0, 0.05, 3), "seed");
        let r = c
            .post(format!("{base}/v1/maps/load-{m}/contributions"))
            .bearer_auth("load-operator-0123456789")
            .header("Idempotency-Key", "seed")
            .json(&first)
            .send()
            .await?;
        if r.status() != 201 {
            bail!("seeding failed: {} {}", r.status(), r.text().await?);
        }
    }
    let map_url = format!("{base}/v1/maps/load-0");
    let body = c.get(&map_url).send().await?.bytes().await?;
    println!(
        "served map: {} transmitters × 3 components, {} bytes",
        cli.transmitters,
        body.len()
    );
    let static_dir = dir.path().join("static");
    std::fs::create_dir_all(&static_dir)?;
    std::fs::write(static_dir.join("map.json"), &body)?;
    let (statik, static_base) = spawn(
        Command::new(std::env::current_exe()?)
            .arg("serve-static")
            .arg(&static_dir),
        "static listening on ",
    )
    .await?;
    let duration = Duration::from_secs_f64(cli.duration_s);

    println!(
        "GET phase: {} connections, {:.0} s each",
        cli.connections, cli.duration_s
    );
    let map_urls: Vec<String> = bases
        .iter()
        .map(|b| format!("{b}/v1/maps/load-0"))
        .collect();
    let get = get_phase(&map_urls, cli.connections, duration).await?;
    report("echomap-server GET map", &get);
    let rss_get: Vec<Option<f64>> = pids.iter().map(|&p| peak_rss_mib(p)).collect();
    let stat = get_phase(
        &[format!("{static_base}/map.json")],
        cli.connections,
        duration,
    )
    .await?;
    report("static file server (same bytes)", &stat);
    println!(
        "ratio echomap/static throughput: {:.2}",
        get.rate() / stat.rate()
    );
    drop(statik);

    println!(
        "upload phase: {} uploaders over {maps} map(s), {}-transmitter maps, {:.0} s",
        cli.uploaders, cli.upload_transmitters, cli.duration_s
    );
    let keep = (cli.upload_transmitters as f64 / cli.transmitters as f64).min(1.0);
    let counter = Arc::new(AtomicU64::new(0));
    let stop = Instant::now() + duration;
    let accepted = Arc::new(AtomicU64::new(0));
    let mut tasks = Vec::new();
    for (i, token) in tokens.iter().cloned().enumerate() {
        let (c, url, world, counter, accepted) = (
            echomap_server::http::client_builder().build()?,
            format!(
                "{}/v1/maps/load-{}/contributions",
                bases[i % replicas],
                i % maps
            ),
            world.clone(),
            counter.clone(),
            accepted.clone(),
        );
        tasks.push(tokio::spawn(async move {
            let mut p = Phase::default();
            while Instant::now() < stop {
                let n = counter.fetch_add(1, Ordering::Relaxed);
                let body = serde_json::to_vec(&synth::contribution(
                    synth::user_map(&world, 10_000 + n, keep, 0.1, 1),
                    &format!("load-{n}"),
                ))
                .expect("serializes");
                let t = Instant::now();
                let r = c
                    .post(&url)
                    .bearer_auth(&token)
                    .header("Idempotency-Key", format!("load-{n}"))
                    .header("content-type", "application/json")
                    .body(body)
                    .send()
                    .await;
                match r {
                    Ok(r) if r.status() == 201 || r.status() == 422 => {
                        if r.status() == 201 {
                            accepted.fetch_add(1, Ordering::Relaxed);
                        }
                        let _ = r.bytes().await;
                        p.ok += 1;
                        p.latencies_s.push(t.elapsed().as_secs_f64());
                    }
                    _ => p.errors += 1,
                }
            }
            p
        }));
    }
    let up = collect(tasks, duration).await?;
    report("contributions", &up);
    println!(
        "accepted {} of {} ({} merged versions)",
        accepted.load(Ordering::Relaxed),
        up.ok,
        accepted.load(Ordering::Relaxed)
    );
    // counters summed over the replicas
    let mut metrics = Vec::new();
    for b in &bases {
        metrics.push(c.get(format!("{b}/metrics")).send().await?.text().await?);
    }
    let value = |name: &str| -> f64 {
        metrics
            .iter()
            .map(|m| {
                m.lines()
                    .find(|l| l.starts_with(name))
                    .and_then(|l| l.split_whitespace().last())
                    .and_then(|v| v.parse::<f64>().ok())
                    .unwrap_or(0.0)
            })
            .sum()
    };
    let (sum, count) = (
        value("echomap_integrate_duration_seconds_sum"),
        value("echomap_integrate_duration_seconds_count"),
    );
    println!(
        "match + merge per contribution (server side, serialized per map): mean {:.2} ms",
        1e3 * sum / count
    );
    println!(
        "uploads per group commit: mean {:.1}",
        value("echomap_commit_batch_size_sum") / value("echomap_commit_batch_size_count")
    );
    for (i, &pid) in pids.iter().enumerate() {
        println!(
            "server {i} peak RSS: {:.1} MiB after the GET phase, {:.1} MiB after both",
            rss_get[i].unwrap_or(f64::NAN),
            peak_rss_mib(pid).unwrap_or(f64::NAN)
        );
    }
    drop(servers);
    Ok(())
}

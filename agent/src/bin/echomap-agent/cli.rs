//! Command line of `echomap-agent`: flags become the library's specs and configuration
//! layers here, and nowhere else.

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use echomap_agent::config::{self, ConfigFile, Layers, Preset, Resolved};
use echomap_agent::filter::{Association, PriorTracker};
use echomap_agent::mrclam::{ImportOptions, OdometryDelay};
use echomap_agent::radio::cir::Cir;
use echomap_agent::radio::estimate::{FrontEndConfig, front_end};
use echomap_agent::sim::channel::synthesize;
use echomap_agent::sim::simulate::{SimOptions, simulate, simulate_paths};
use echomap_agent::sim::{Scenario, load_scenario, user_tracks};
use echomap_agent::{demo, evaluate, files, mrclam, output, plot, remote};
use echomap_shared::SensorProfile;
use echomap_shared::log::{GroundTruth, MeasurementLog};
use echomap_shared::matching::{MatchConfig, MatchScore, match_maps};
use std::path::{Path, PathBuf};

#[derive(Debug, Parser)]
#[command(
    name = "echomap-agent",
    version,
    about = "echomap agent: simulate, run Channel-SLAM, evaluate"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// The main job: start a map server on loopback, let a crowd of agent processes build a
    /// map of the indoor scenario, run the reference user alone and with the crowd's map,
    /// print the results and write plots into --out (default out/demo).
    Demo(DemoArgs),
    /// Simulate one track of a scenario: writes log.jsonl and truth.json into --out.
    Simulate(SimulateArgs),
    /// Channel estimation: paths from a sampled channel (CIR) by SAGE, tracked over
    /// snapshots; writes log.jsonl with the estimator's sensor profile into --out.
    Estimate(EstimateArgs),
    /// Run single-user Channel-SLAM on a log (or a freshly simulated track); writes map.json,
    /// track.csv, summary.json and plots into --out.
    Run(Box<RunArgs>),
    /// The effective run configuration.
    #[command(subcommand)]
    Config(ConfigCommand),
    /// Run M seeds of a scenario track (simulate + filter) and report mean and 5th/95th
    /// percentile error curves against travelled distance.
    Evaluate(EvaluateArgs),
    /// Convert a real dataset into a measurement log + ground truth.
    #[command(subcommand)]
    Import(ImportCommand),
    /// Match a user map (agent frame) against a prior map (map frame): prints the transform
    /// map_from_agent, the correspondences and the score.
    Match(MatchArgs),
    /// Match and merge a user map into a prior map; writes the merged map.
    Merge(MergeArgs),
    /// Send a run's user map to the server again (the contribution a `run --server` kept in
    /// its output directory), e.g. after the server found it undecided.
    Upload(UploadArgs),
    /// Launch users as separate `echomap-agent run` processes against a map server.
    Crowd(CrowdArgs),
    /// Experiments of the papers.
    #[command(subcommand)]
    Experiment(ExperimentCommand),
    /// Draw a scenario (walls, scatterers, transmitter, tracks, virtual transmitters) as PNG
    /// or SVG, or write it as a JSON scenario file.
    Scenario(ScenarioArgs),
}

/// Where a run's measurements come from.
#[derive(Debug, Args)]
pub struct InputArgs {
    /// directory with log.jsonl (and truth.json when known)
    #[arg(long, conflicts_with = "scenario")]
    pub log: Option<PathBuf>,
    /// simulate this scenario's --track first (built-in `indoor`, `urban`, or a JSON file)
    #[arg(long)]
    pub scenario: Option<String>,
    /// track to simulate with --scenario
    #[arg(long, default_value = "reference")]
    pub track: String,
}

/// The layers of the run configuration above the log's sensor profile.
#[derive(Debug, Args)]
pub struct ConfigArgs {
    /// number of user particles [1000]
    #[arg(long)]
    pub particles: Option<usize>,
    /// data association of new tracks: off, ml, das [ml]
    #[arg(long)]
    pub association: Option<Association>,
    /// configuration file (TOML, or JSON): any subset of the keys `config print` shows
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// start from a preset: indoor, urban, mrclam (applied before the sensor profile)
    #[arg(long)]
    pub preset: Option<Preset>,
    /// set one configuration key, e.g. `--set motion.heading_noise_rad_per_sqrt_s=0.02`
    /// (repeatable; after the file)
    #[arg(long = "set", value_name = "KEY=VALUE", value_parser = config::parse_set)]
    pub set: Vec<(String, serde_json::Value)>,
}

impl ConfigArgs {
    /// Resolves the effective configuration over `sensor`.
    pub fn resolve(&self, sensor: Option<&SensorProfile>) -> Result<Resolved> {
        self.resolve_with(None, sensor)
    }

    /// Resolves the effective configuration for a log: its sensor profile, and the noise
    /// laws measured from it where the profile leaves them out.
    pub fn resolve_for_log(&self, log: &MeasurementLog) -> Result<Resolved> {
        let measured = config::measured_profile(log);
        self.resolve_with(measured.as_ref(), log.header.sensor.as_ref())
    }

    fn resolve_with(
        &self,
        measured: Option<&SensorProfile>,
        sensor: Option<&SensorProfile>,
    ) -> Result<Resolved> {
        let mut flags = Vec::new();
        if let Some(n) = self.particles {
            flags.push(("particles".to_string(), serde_json::json!(n)));
        }
        if let Some(a) = self.association {
            flags.push((
                "association.method".to_string(),
                serde_json::json!(a.name()),
            ));
        }
        flags.extend(self.set.iter().cloned());
        let file = self.config.as_deref().map(ConfigFile::read).transpose()?;
        Ok(config::resolve(&Layers {
            preset: self.preset,
            measured,
            sensor,
            file,
            flags,
        })?)
    }
}

#[derive(Debug, Args)]
pub struct RunArgs {
    #[command(flatten)]
    pub input: InputArgs,
    /// seed of the simulation and of the filter
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// output directory
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub config: ConfigArgs,
    /// a prior map (map frame) to match against and use: an `echomap.map.v1` file or a map
    /// document as served by GET /v1/maps/{map}
    #[arg(long, conflicts_with = "server")]
    pub prior: Option<PathBuf>,
    /// map server base URL: fetch the prior map at start, upload the user map at the end
    #[arg(long, env = "ECHOMAP_SERVER", requires = "map")]
    pub server: Option<String>,
    /// map name on the server
    #[arg(long, env = "ECHOMAP_MAP")]
    pub map: Option<String>,
    /// file holding the bearer token (first line that is not empty or a `#` comment)
    #[arg(long, env = "ECHOMAP_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
    /// label of this agent sent with the upload
    #[arg(long, default_value = "echomap-agent")]
    pub contributor: String,
    /// no progress bar
    #[arg(long)]
    pub quiet: bool,
}

#[derive(Debug, Subcommand)]
pub enum ConfigCommand {
    /// Print the configuration a `run` with the same flags would use, each value with where
    /// it came from (default, preset, sensor profile, file, flag). The output is a valid
    /// configuration file.
    Print(ConfigPrintArgs),
}

#[derive(Debug, Args)]
pub struct ConfigPrintArgs {
    #[command(flatten)]
    pub input: InputArgs,
    #[command(flatten)]
    pub config: ConfigArgs,
    /// print JSON (`{"config": …, "sources": {key: source}}`) instead of annotated TOML
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct SimulateArgs {
    /// built-in scenario (`indoor`, `urban`) or a path to a JSON scenario file
    #[arg(long, default_value = "indoor")]
    pub scenario: String,
    /// drop angles of arrival: simulate a single-antenna (ToA-only) receiver
    #[arg(long)]
    pub toa_only: bool,
    /// track of the scenario to walk
    #[arg(long, default_value = "reference")]
    pub track: String,
    /// seed of every random draw (same seed, same output)
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// output directory (created if missing)
    #[arg(long)]
    pub out: PathBuf,
    /// also write the sampled channel (cir.json + cir.npy: every path at every antenna, in
    /// noise), the input of `estimate`
    #[arg(long)]
    pub cir: bool,
}

#[derive(Debug, Args)]
pub struct EstimateArgs {
    /// directory with cir.json and cir.npy (and truth.json, copied along when present)
    pub cir_dir: PathBuf,
    /// output directory for log.jsonl (created if missing)
    #[arg(long)]
    pub out: PathBuf,
    /// leave out tracks followed for less than this many seconds (first to last detection)
    #[arg(long, default_value_t = echomap_agent::radio::estimate::DEFAULT_MIN_TRACK_S)]
    pub min_track_s: f64,
}

#[derive(Debug, Args)]
pub struct EvaluateArgs {
    /// built-in scenario or JSON file
    #[arg(long, default_value = "urban")]
    pub scenario: String,
    /// recorded logs with ground truth instead of a scenario (comma-separated directories
    /// with log.jsonl and truth.json): each log × seeds, the filter's mean error against
    /// dead reckoning from the log's own odometry (`runs.csv`, `results.md`, `ratio.png/svg`)
    #[arg(long, value_delimiter = ',', conflicts_with_all = ["track", "toa_only", "compare"])]
    pub logs: Vec<PathBuf>,
    #[arg(long, default_value = "reference")]
    pub track: String,
    #[arg(long)]
    pub toa_only: bool,
    /// number of seeds (runs)
    #[arg(long, default_value_t = 10)]
    pub seeds: u64,
    /// first seed; runs use first-seed, first-seed+1, …
    #[arg(long, default_value_t = 1)]
    pub first_seed: u64,
    /// association methods to compare (comma-separated: off, ml, das)
    #[arg(long, value_delimiter = ',')]
    pub compare: Vec<Association>,
    #[command(flatten)]
    pub config: ConfigArgs,
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Debug, Subcommand)]
pub enum ImportCommand {
    /// UTIAS MRCLAM: `import mrclam DIR --robot N --out DIR`
    Mrclam(MrclamArgs),
}

#[derive(Debug, Args)]
pub struct MrclamArgs {
    /// dataset directory (Barcodes.dat, Landmark_Groundtruth.dat, RobotN_*.dat)
    pub dir: PathBuf,
    /// robot 1–5
    #[arg(long)]
    pub robot: u32,
    /// start a new track id when a landmark has not been seen for this long (s)
    #[arg(long, default_value_t = 5.0)]
    pub track_gap: f64,
    /// snapshot rate (Hz)
    #[arg(long, default_value_t = 10.0)]
    pub rate: f64,
    /// how late the robot moves after the odometry's time stamps: `auto` estimates it from
    /// the landmark bearings (no ground truth), a number of seconds sets it, 0 keeps the time
    /// stamps as they are
    #[arg(long, default_value = "0")]
    pub odometry_delay: OdometryDelay,
    /// output directory (log.jsonl, truth.json)
    #[arg(long)]
    pub out: PathBuf,
}

/// Matching settings shared by `match` and `merge`.
#[derive(Debug, Args)]
pub struct MatchFlags {
    /// seed of the RANSAC draws
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// weight of the visibility term of the score (Ulmschneider et al. 2021 eq. 18); 0
    /// scores by location alone
    #[arg(long, default_value_t = 1.0, value_parser = non_negative)]
    pub visibility_weight: f64,
    /// how a hypothesis's inliers are scored: `msac` or `likelihood`
    #[arg(long, default_value_t = MatchScore::Msac)]
    pub score: MatchScore,
}

impl MatchFlags {
    fn config(&self) -> MatchConfig {
        MatchConfig::default()
            .with_visibility_weight(self.visibility_weight)
            .with_location_score(self.score.location_score())
    }
}

#[derive(Debug, Args)]
pub struct MatchArgs {
    /// user map (echomap.map.v1, agent frame)
    pub user: PathBuf,
    /// prior map (echomap.map.v1, map frame)
    pub prior: PathBuf,
    #[command(flatten)]
    pub matching: MatchFlags,
    /// one JSON object on stdout
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct MergeArgs {
    /// prior map (map frame)
    pub prior: PathBuf,
    /// user map (agent frame)
    pub user: PathBuf,
    #[command(flatten)]
    pub matching: MatchFlags,
    /// merged map (written only when the match is accepted or the prior is empty)
    #[arg(long)]
    pub out: PathBuf,
    /// merge an unmatched user transmitter into the nearest prior one within this squared
    /// Mahalanobis distance (x, y) instead of adding it (the server's `--merge-absorb-chi2`);
    /// 0: add every unmatched one
    #[arg(long, default_value_t = 0.0, value_parser = non_negative)]
    pub absorb_chi2: f64,
}

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// seed of the simulations and filters
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// number of contributing users (indoor tracks user01, user02, …)
    #[arg(long, default_value_t = 6)]
    pub users: usize,
    /// particles of every agent
    #[arg(long, default_value_t = 500)]
    pub particles: usize,
    /// output directory
    #[arg(long, default_value = "out/demo")]
    pub out: PathBuf,
}

#[derive(Debug, Args)]
pub struct UploadArgs {
    /// output directory of a `run --server` (holds contribution.json and upload.json)
    pub dir: PathBuf,
    /// map server base URL
    #[arg(long, env = "ECHOMAP_SERVER")]
    pub server: String,
    /// map name on the server
    #[arg(long, env = "ECHOMAP_MAP")]
    pub map: String,
    /// file holding the bearer token (first line that is not empty or a `#` comment)
    #[arg(long, env = "ECHOMAP_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub struct CrowdArgs {
    /// map server base URL
    #[arg(long, env = "ECHOMAP_SERVER")]
    pub server: String,
    /// map name (created if missing)
    #[arg(long, env = "ECHOMAP_MAP")]
    pub map: String,
    /// file holding the bearer token
    #[arg(long, env = "ECHOMAP_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
    /// built-in scenario or JSON file
    #[arg(long, default_value = "indoor")]
    pub scenario: String,
    /// number of users: the scenario's tracks other than `reference`, in order
    #[arg(long)]
    pub users: usize,
    /// run at most K agent processes at once (default 1: each user gets the map left by
    /// the previous ones)
    #[arg(long, default_value_t = 1)]
    pub parallel: usize,
    /// user k (1-based) runs with seed SEED·1000 + k
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// particles of every agent
    #[arg(long, default_value_t = 500)]
    pub particles: usize,
    /// configuration file for every agent (see `config print`)
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// output directory: one sub-directory per user, crowd.md, crowd.json
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Debug, Subcommand)]
pub enum ExperimentCommand {
    /// Ulmschneider et al. 2021 Fig. 5: the reference user's MAE with prior maps built by c
    /// contributors.
    Cooperative(Box<CooperativeArgs>),
    /// Calibration of map matching on dense random fields: unrelated pairs accepted and related
    /// pairs recovered, by transmitters per map and acceptance threshold ε; writes
    /// coincidence.csv, summary.md and false_accepts.svg into --out.
    Coincidence(CoincidenceArgs),
}

#[derive(Debug, Args)]
pub struct CoincidenceArgs {
    /// unrelated pairs per threshold (related pairs: a fifth as many)
    #[arg(long, default_value_t = 5000)]
    pub pairs: usize,
    /// seed of the first pair
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// acceptance thresholds ε (expected false alarms) to evaluate
    #[arg(long, value_delimiter = ',', default_value = "0.01,1,100")]
    pub thresholds: Vec<f64>,
    /// output folder
    #[arg(long, default_value = "out/coincidence")]
    pub out: PathBuf,
}

#[derive(Debug, Args)]
pub struct CooperativeArgs {
    /// built-in scenario or JSON file (simulated experiment)
    #[arg(long, default_value = "indoor", conflicts_with = "dataset")]
    pub scenario: String,
    /// numbers of contributors to evaluate (0 = single user)
    #[arg(long, value_delimiter = ',', default_value = "0,1,2,6,15,21")]
    pub contributors: Vec<usize>,
    /// runs (seeds) per configuration
    #[arg(long, default_value_t = 10)]
    pub runs: u64,
    /// first seed; run r uses seed first-seed + r
    #[arg(long, default_value_t = 1)]
    pub first_seed: u64,
    /// particles of the contributors
    #[arg(long, default_value_t = 300)]
    pub particles: usize,
    /// particles of the reference user
    #[arg(long, default_value_t = 1000)]
    pub reference_particles: usize,
    /// reference runs (one per c) at once
    #[arg(long, default_value_t = 2)]
    pub parallel: usize,
    /// real data instead: `mrclam DIR` (UTIAS MRCLAM; every robot is the reference once)
    #[arg(long, num_args = 2, value_names = ["KIND", "DIR"])]
    pub dataset: Vec<String>,
    /// weight of the visibility term when maps are matched, by the loopback server and by
    /// every agent; default 1, with `--dataset mrclam` 0 (a camera's detections depend on
    /// its heading)
    #[arg(long, value_parser = non_negative)]
    pub match_visibility_weight: Option<f64>,
    /// how matching hypotheses are scored, by the loopback server and by every agent:
    /// `msac` or `likelihood`; default `msac`, with `--dataset mrclam` `likelihood`
    #[arg(long)]
    pub match_score: Option<MatchScore>,
    /// the loopback server's `--merge-absorb-chi2` (default 0: off)
    #[arg(long, default_value_t = 0.0, value_parser = non_negative)]
    pub merge_absorb_chi2: f64,
    /// with --dataset mrclam: the robots that act as the reference, each in turn
    #[arg(long, value_delimiter = ',', default_value = "1,2,3,4,5")]
    pub references: Vec<u32>,
    /// with --dataset mrclam: the importer's `--odometry-delay` (`auto` or seconds)
    #[arg(long, default_value = "0")]
    pub odometry_delay: OdometryDelay,
    /// use this server instead of starting one on loopback
    #[arg(long, env = "ECHOMAP_SERVER")]
    pub server: Option<String>,
    /// token file for --server
    #[arg(long, env = "ECHOMAP_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
    /// configuration file for every agent (crowd and reference)
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// one configuration key for every agent (repeatable)
    #[arg(long = "set", value_name = "KEY=VALUE", value_parser = config::parse_set)]
    pub set: Vec<(String, serde_json::Value)>,
    /// one configuration key for the reference user's runs only (repeatable; last)
    #[arg(long = "reference-set", value_name = "KEY=VALUE", value_parser = config::parse_set)]
    pub reference_set: Vec<(String, serde_json::Value)>,
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Debug, Args)]
pub struct ScenarioArgs {
    /// built-in scenario (`indoor`, `urban`) or a path to a JSON scenario file
    #[arg(long, default_value = "indoor")]
    pub scenario: String,
    /// tracks to draw (comma-separated); default: all
    #[arg(long, value_delimiter = ',')]
    pub tracks: Vec<String>,
    /// track whose detectable virtual transmitters are drawn
    #[arg(long, default_value = "reference")]
    pub vtx_track: String,
    /// output file: .png or .svg draws the scenario, .json writes the scenario file
    #[arg(long)]
    pub out: PathBuf,
}

/// A finite number ≥ 0.
pub fn non_negative(s: &str) -> Result<f64, String> {
    let v: f64 = s.parse().map_err(|e| format!("{e}"))?;
    if v.is_finite() && v >= 0.0 {
        Ok(v)
    } else {
        Err(format!("must be a finite non-negative number, got {s}"))
    }
}

/// The log (and ground truth, when there is one) a run works on.
fn load_input(a: &InputArgs, seed: u64) -> Result<(MeasurementLog, Option<GroundTruth>)> {
    match (&a.log, &a.scenario) {
        (Some(dir), None) => files::read_log_dir(dir),
        (None, Some(s)) => {
            let scenario = load_scenario(s, false)?;
            let out = simulate(
                &scenario,
                &a.track,
                SimOptions {
                    seed,
                    toa_only: false,
                },
            )?;
            Ok((out.log, Some(out.truth)))
        }
        _ => bail!("give either --log DIR or --scenario S"),
    }
}

/// The configuration `config print` shows for an input, without simulating the whole track:
/// a log's (with its measured noise), a scenario's sensor profile's, or the bare one.
fn resolve_input(a: &InputArgs, config: &ConfigArgs) -> Result<Resolved> {
    match (&a.log, &a.scenario) {
        (Some(dir), None) => config.resolve_for_log(&files::read_log_dir(dir)?.0),
        (None, Some(s)) => {
            let scenario: Scenario = load_scenario(s, false)?;
            config.resolve(Some(&scenario.sensor_profile(scenario.receiver.aoa)))
        }
        (None, None) => config.resolve(None),
        _ => bail!("give either --log DIR or --scenario S"),
    }
}

pub fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Simulate(a) => {
            let scenario = load_scenario(&a.scenario, a.toa_only)?;
            let opts = SimOptions {
                seed: a.seed,
                toa_only: a.toa_only,
            };
            let (out, channel) = simulate_paths(&scenario, &a.track, opts, a.cir)?;
            files::write_log_dir(&out.log, &out.truth, &a.out)?;
            if let Some(paths) = channel {
                let aoa = scenario.receiver.aoa && !a.toa_only;
                let cir = synthesize(&scenario, &out.log, &paths, aoa, a.seed);
                cir.write(&a.out)?;
            }
            let comps: usize = out.log.snapshots.iter().map(|s| s.components.len()).sum();
            println!(
                "simulated {} / {}: {} snapshots, {:.1} components per snapshot, {} track ids → {}",
                scenario.name,
                a.track,
                out.log.snapshots.len(),
                comps as f64 / out.log.snapshots.len().max(1) as f64,
                out.truth.transmitters.len(),
                a.out.display()
            );
            Ok(())
        }
        Command::Run(a) => run_command(&a),
        Command::Estimate(a) => {
            if !(a.min_track_s.is_finite() && a.min_track_s >= 0.0) {
                bail!("--min-track-s must be a number of seconds ≥ 0");
            }
            let cir = Cir::read(&a.cir_dir)?;
            let cfg = FrontEndConfig {
                min_track_s: a.min_track_s,
                ..FrontEndConfig::default()
            };
            let (log, stats) = front_end(&cir, &cfg);
            files::write_log(&log, &a.out)?;
            let log_path = a.out.join("log.jsonl");
            let truth = a.cir_dir.join("truth.json");
            if truth.exists() && a.cir_dir.canonicalize()? != a.out.canonicalize()? {
                std::fs::copy(&truth, a.out.join("truth.json"))
                    .with_context(|| format!("copying {}", truth.display()))?;
            }
            plot::draw_waterfall(
                &cir,
                stats.noise_variance,
                &log,
                &a.out.join("waterfall.png"),
            )?;
            println!(
                "estimated {} snapshots: {:.1} paths per snapshot, {} tracks, noise variance {:.3} → {}",
                stats.snapshots,
                stats.paths_per_snapshot,
                stats.tracks,
                stats.noise_variance,
                log_path.display()
            );
            Ok(())
        }
        Command::Config(ConfigCommand::Print(a)) => {
            let r = resolve_input(&a.input, &a.config)?;
            if a.json {
                let sources: serde_json::Map<String, serde_json::Value> = r
                    .sources
                    .iter()
                    .map(|(k, s)| (k.clone(), s.to_string().into()))
                    .collect();
                let j = serde_json::json!({"config": r.config, "sources": sources});
                println!("{}", serde_json::to_string_pretty(&j)?);
            } else {
                print!("{}", r.annotated_toml());
            }
            Ok(())
        }
        Command::Import(ImportCommand::Mrclam(a)) => {
            let opts = ImportOptions {
                track_gap_s: a.track_gap,
                rate_hz: a.rate,
                odometry_delay: a.odometry_delay,
                ..ImportOptions::robot(a.robot)
            };
            let (log, truth) = mrclam::import(&a.dir, opts)?;
            let source = log.header.source.clone().unwrap_or_default();
            files::write_log_dir(&log, &truth, &a.out)?;
            println!("imported {source} → {}", a.out.display());
            Ok(())
        }
        Command::Match(a) => {
            let (user, prior) = (files::read_map(&a.user)?, files::read_map(&a.prior)?);
            let mut rng =
                <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(a.matching.seed);
            let r = match_maps(&user, &prior, &a.matching.config(), &mut rng);
            let j = files::match_json(&r, &user, &prior);
            if a.json {
                println!("{j}");
            } else {
                println!("{}", serde_json::to_string_pretty(&j)?);
            }
            Ok(())
        }
        Command::Merge(a) => merge_command(&a),
        Command::Upload(a) => remote::Remote::connect(&remote::RemoteSpec {
            server: a.server.clone(),
            map: a.map.clone(),
            token_file: a.token_file.clone(),
            contributor: String::new(),
        })?
        .upload_again(&a.dir),
        Command::Evaluate(a) if !a.logs.is_empty() => {
            let mut cases = Vec::new();
            for dir in &a.logs {
                let (log, truth) = files::read_log_dir(dir)?;
                let truth = truth.with_context(|| {
                    format!(
                        "{}: no truth.json, nothing to evaluate against",
                        dir.display()
                    )
                })?;
                let config = a.config.resolve_for_log(&log)?.config;
                let base = dir
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_else(|| dir.display().to_string());
                let taken = cases
                    .iter()
                    .filter(|c: &&evaluate::LogCase| c.name.starts_with(&base))
                    .count();
                let name = if taken == 0 {
                    base
                } else {
                    format!("{base}-{}", taken + 1)
                };
                cases.push(evaluate::LogCase {
                    name,
                    log,
                    truth,
                    config,
                });
            }
            let s = evaluate::evaluate_logs(&cases, a.seeds, a.first_seed, &a.out)?;
            for ((name, r), (_, e)) in s.log_ratio.iter().zip(&s.log_error_ratio) {
                println!(
                    "{name:>24}: mean MAE / dead reckoning's mean error {r:.2}, the reported position's {e:.2}"
                );
            }
            println!(
                "median over {} logs {:.2} ({:.2} for the reported position), logs above 1.0: {} ({}), mean coverage95 {:.2}; wrote {}",
                cases.len(),
                s.median_ratio,
                s.median_error_ratio,
                s.logs_above_1,
                s.logs_error_above_1,
                s.mean_coverage95,
                a.out.display()
            );
            Ok(())
        }
        Command::Evaluate(a) => {
            let scenario = load_scenario(&a.scenario, a.toa_only)?;
            let profile = scenario.sensor_profile(scenario.receiver.aoa);
            let config = a.config.resolve(Some(&profile))?.config;
            evaluate::evaluate(&evaluate::EvaluateSpec {
                scenario,
                track: a.track,
                toa_only: a.toa_only,
                seeds: a.seeds,
                first_seed: a.first_seed,
                compare: a.compare,
                config,
                out: a.out,
            })
        }
        Command::Demo(a) => demo::demo(&demo::DemoSpec {
            seed: a.seed,
            users: a.users,
            particles: a.particles,
            out: a.out,
        }),
        Command::Crowd(a) => crowd_command(&a),
        Command::Experiment(ExperimentCommand::Cooperative(a)) => cooperative_command(&a),
        Command::Experiment(ExperimentCommand::Coincidence(a)) => {
            let md = echomap_agent::coincidence::coincidence(
                &echomap_agent::coincidence::CoincidenceSpec {
                    pairs: a.pairs,
                    seed: a.seed,
                    thresholds: a.thresholds,
                    out: a.out.clone(),
                },
            )?;
            print!("{md}");
            println!("wrote {}", a.out.display());
            Ok(())
        }
        Command::Scenario(a) => {
            let scenario = load_scenario(&a.scenario, false)?;
            let ext = a
                .out
                .extension()
                .and_then(|e| e.to_str())
                .unwrap_or("")
                .to_ascii_lowercase();
            match ext.as_str() {
                "json" => {
                    std::fs::write(&a.out, serde_json::to_string_pretty(&scenario)?)
                        .with_context(|| format!("writing {}", a.out.display()))?;
                }
                "png" | "svg" => plot::draw_scenario(&scenario, &a.tracks, &a.vtx_track, &a.out)?,
                _ => bail!(
                    "--out must end in .png, .svg or .json, got {}",
                    a.out.display()
                ),
            }
            println!("wrote {}", a.out.display());
            Ok(())
        }
    }
}

fn run_command(a: &RunArgs) -> Result<()> {
    let (log, truth) = load_input(&a.input, a.seed)?;
    let resolved = a.config.resolve_for_log(&log)?;
    let cfg = &resolved.config;
    let measured = |key: &str| resolved.sources.get(key) == Some(&config::Source::Measured);
    let m = &cfg.measurement;
    let mut laws = Vec::new();
    if measured("measurement.distance_floor_m") {
        laws.push(format!(
            "distance σ = {:.3} ⊕ {:.3}·10^(−γ/20) m",
            m.distance_floor_m, m.distance_at_0db_m
        ));
    }
    if measured("measurement.aoa_floor_rad") {
        laws.push(format!(
            "angle σ = {:.4} ⊕ {:.4}·10^(−γ/20) rad",
            m.aoa_floor_rad, m.aoa_at_0db_rad
        ));
    }
    if !laws.is_empty() {
        println!("noise measured from the log's tracks: {}", laws.join(", "));
    }
    let initial_speed = truth
        .as_ref()
        .and_then(|t| t.poses.first())
        .map(|p| p.speed_mps)
        .unwrap_or(0.0);
    let filter_cfg = cfg.filter_config(a.seed, initial_speed);
    let remote = match &a.server {
        Some(server) => Some(remote::Remote::connect(&remote::RemoteSpec {
            server: server.clone(),
            map: a.map.clone().context("--server needs --map")?,
            token_file: a.token_file.clone(),
            contributor: a.contributor.clone(),
        })?),
        None => None,
    };
    let prior = match (&remote, &a.prior) {
        (Some(r), _) => Some(r.fetch_prior(&a.out)?),
        (None, Some(path)) => Some(files::read_prior(path)?),
        (None, None) => None,
    };
    let tracker = prior
        .filter(|p| !p.is_empty() && cfg.prior.use_in_filter)
        .map(|p| PriorTracker::new(p, cfg.prior_settings(), a.seed))
        .transpose()?;
    let progress = !a.quiet;
    let out = match tracker {
        Some(t) if cfg.prior.fallback => echomap_agent::run::run_filter_with_fallback(
            &log,
            truth.as_ref(),
            filter_cfg,
            progress,
            t,
        )?,
        t => echomap_agent::run::run_filter_with_prior(
            &log,
            truth.as_ref(),
            filter_cfg,
            progress,
            t,
        )?,
    };
    // the track and summary are written even when the map is not
    let written = output::write_run(&out, truth.as_ref(), &log, &a.out);
    std::fs::write(a.out.join("config.toml"), resolved.annotated_toml())
        .with_context(|| format!("writing {}", a.out.join("config.toml").display()))?;
    output::print_summary(&out, truth.as_ref(), &log);
    written?;
    if let Some(r) = &remote {
        let run = format!("{}-seed{}", a.input.track, a.seed);
        r.upload(&out, &run, &a.out)?;
    }
    Ok(())
}

fn merge_command(a: &MergeArgs) -> Result<()> {
    let (prior, user) = (files::read_map(&a.prior)?, files::read_map(&a.user)?);
    let (iso, pairs) = if prior.is_empty() {
        (nalgebra::Isometry2::identity(), Vec::new())
    } else {
        let mut rng =
            <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(a.matching.seed);
        let r = match_maps(&user, &prior, &a.matching.config(), &mut rng);
        if !r.accepted {
            bail!(
                "no match, nothing written: {}",
                r.reason.unwrap_or_default()
            );
        }
        (r.map_from_agent, r.correspondences)
    };
    let (merged, stats) = echomap_shared::merging::merge_maps(
        &prior,
        &user,
        &iso,
        &pairs,
        &echomap_shared::merging::MergeConfig::default().with_absorb_chi2(a.absorb_chi2),
    )?;
    std::fs::write(&a.out, merged.to_json_pretty())
        .with_context(|| format!("writing {}", a.out.display()))?;
    println!(
        "merged {} transmitters, added {}, kept {} → {} ({} transmitters)",
        stats.merged,
        stats.added,
        stats.kept,
        a.out.display(),
        merged.len()
    );
    Ok(())
}

/// A configuration file's keys as a partial table (empty without a file).
fn file_table(path: Option<&Path>) -> Result<serde_json::Value> {
    Ok(match path {
        Some(p) => ConfigFile::read(p)?.table,
        None => serde_json::json!({}),
    })
}

fn crowd_command(a: &CrowdArgs) -> Result<()> {
    use echomap_agent::crowd::{CrowdSpec, Source, User, run_crowd, table};
    let tracks = user_tracks(&a.scenario)?;
    anyhow::ensure!(
        a.users >= 1 && a.users <= tracks.len(),
        "--users must be 1..={} for scenario {:?}",
        tracks.len(),
        a.scenario
    );
    anyhow::ensure!(a.parallel >= 1, "--parallel must be at least 1");
    let mut agent_config = file_table(a.config.as_deref())?;
    config::insert_dotted(&mut agent_config, "particles", a.particles.into());
    let (client, rt) = remote::connect(&a.server, a.token_file.as_deref())?;
    rt.block_on(client.create_map(&a.map))
        .with_context(|| format!("creating map {:?}", a.map))?;
    let users: Vec<User> = tracks[..a.users]
        .iter()
        .enumerate()
        .map(|(k, t)| User {
            name: t.clone(),
            source: Source::Scenario {
                scenario: a.scenario.clone(),
                track: t.clone(),
            },
            seed: a.seed * 1000 + k as u64 + 1,
        })
        .collect();
    let spec = CrowdSpec {
        exe: std::env::current_exe()?,
        server: a.server.clone(),
        map: a.map.clone(),
        token_file: a.token_file.clone(),
        parallel: a.parallel,
        config: agent_config,
        out: a.out.clone(),
        progress: true,
    };
    std::fs::create_dir_all(&a.out)?;
    let results = run_crowd(&spec, &users);
    let t = table(&results);
    std::fs::write(a.out.join("crowd.md"), &t)?;
    std::fs::write(
        a.out.join("crowd.json"),
        serde_json::to_string_pretty(&results)?,
    )?;
    println!("{t}");
    let failed = results.iter().filter(|r| !r.ok).count();
    anyhow::ensure!(
        failed == 0,
        "{failed} of {} agent processes failed",
        results.len()
    );
    Ok(())
}

fn cooperative_command(a: &CooperativeArgs) -> Result<()> {
    use echomap_agent::experiment::{ExperimentSpec, cooperative_mrclam, cooperative_scenario};
    anyhow::ensure!(a.runs >= 1, "--runs must be at least 1");
    let mrclam_dir = match a.dataset.as_slice() {
        [] => None,
        [kind, dir] if kind == "mrclam" => Some(PathBuf::from(dir)),
        [kind, _] => bail!("--dataset: unknown kind {kind:?} (known: mrclam)"),
        _ => bail!("--dataset takes KIND DIR"),
    };
    for x in &a.references {
        anyhow::ensure!(
            (1..=5).contains(x),
            "--references: robot {x} is not one of 1…5"
        );
    }
    let mut contributors = a.contributors.clone();
    contributors.sort_unstable();
    contributors.dedup();
    let on_mrclam = mrclam_dir.is_some();
    // a camera's detections depend on its heading, and MRCLAM's layout nearly repeats
    // under a half turn: match by position alone, scored by the likelihood
    let weight = a
        .match_visibility_weight
        .unwrap_or(if on_mrclam { 0.0 } else { 1.0 });
    let score = a.match_score.unwrap_or(if on_mrclam {
        MatchScore::Likelihood
    } else {
        MatchScore::Msac
    });
    // every agent: the preset, the experiment's matching, the file, the --set keys
    let mut shared = if on_mrclam {
        config::difference_from_default(&Preset::Mrclam.config())
    } else {
        serde_json::json!({})
    };
    config::insert_dotted(&mut shared, "prior.visibility_weight", weight.into());
    config::insert_dotted(&mut shared, "prior.match_score", score.name().into());
    merge_table(&mut shared, &file_table(a.config.as_deref())?);
    for (k, v) in &a.set {
        config::insert_dotted(&mut shared, k, v.clone());
    }
    let with_particles = |n: usize, extra: &[(String, serde_json::Value)]| {
        let mut t = serde_json::json!({ "particles": n });
        merge_table(&mut t, &shared);
        for (k, v) in extra {
            config::insert_dotted(&mut t, k, v.clone());
        }
        t
    };
    let spec = ExperimentSpec {
        exe: std::env::current_exe().expect("the running executable"),
        server: a.server.clone(),
        token_file: a.token_file.clone(),
        runs: a.runs,
        first_seed: a.first_seed,
        parallel: a.parallel.max(1),
        crowd_config: with_particles(a.particles, &[]),
        reference_config: with_particles(a.reference_particles, &a.reference_set),
        out: a.out.clone(),
        progress: true,
        match_visibility_weight: weight,
        match_score: score,
        merge_absorb_chi2: a.merge_absorb_chi2,
    };
    // a bad key fails here, before any process starts
    for t in [&spec.crowd_config, &spec.reference_config] {
        config::resolve(&Layers {
            file: Some(ConfigFile {
                name: "the experiment's agent configuration".into(),
                table: t.clone(),
            }),
            ..Default::default()
        })?;
    }
    match mrclam_dir {
        None => {
            let tracks = user_tracks(&a.scenario)?;
            cooperative_scenario(&spec, &a.scenario, &tracks, "reference", &contributors)?;
        }
        Some(dir) => {
            let mut logs = Vec::new();
            for robot in 1..=5u32 {
                let d = a.out.join(format!("logs/robot{robot}"));
                let (log, truth) = mrclam::import(
                    &dir,
                    ImportOptions {
                        odometry_delay: a.odometry_delay,
                        ..ImportOptions::robot(robot)
                    },
                )?;
                if let Some(source) = &log.header.source {
                    tracing::info!("imported {source}");
                }
                files::write_log_dir(&log, &truth, &d)?;
                logs.push((robot, d));
            }
            cooperative_mrclam(&spec, &logs, &a.references)?;
        }
    }
    Ok(())
}

/// Copies every leaf of `from` into `into` (tables merged key by key).
fn merge_table(into: &mut serde_json::Value, from: &serde_json::Value) {
    fn walk(into: &mut serde_json::Value, from: &serde_json::Value, prefix: &str) {
        if let serde_json::Value::Object(m) = from {
            for (k, v) in m {
                let key = if prefix.is_empty() {
                    k.clone()
                } else {
                    format!("{prefix}.{k}")
                };
                if v.is_object() {
                    walk(into, v, &key);
                } else {
                    config::insert_dotted(into, &key, v.clone());
                }
            }
        }
    }
    walk(into, from, "");
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<Cli, clap::Error> {
        Cli::try_parse_from(std::iter::once("echomap-agent").chain(args.iter().copied()))
    }

    #[test]
    fn run_keeps_few_flags_and_takes_every_knob_through_the_configuration() {
        let cli = parse(&[
            "run",
            "--out",
            "o",
            "--particles",
            "300",
            "--set",
            "motion.heading_noise_rad_per_sqrt_s=0.02",
            "--set",
            "association.method=das",
        ])
        .unwrap();
        let Command::Run(a) = cli.command else {
            panic!("not run")
        };
        let r = a.config.resolve(None).unwrap();
        assert_eq!(r.config.particles, 300);
        assert_eq!(r.config.motion.heading_noise_rad_per_sqrt_s, 0.02);
        assert_eq!(r.config.association.method, Association::Das);
        // a knob that is no flag any more is refused with a hint
        let err = parse(&["run", "--out", "o", "--heading-noise", "0.02"]).unwrap_err();
        assert!(err.to_string().contains("--heading-noise"), "{err}");
        let err = parse(&["run", "--out", "o", "--set", "oops"]).unwrap_err();
        assert!(err.to_string().contains("KEY=VALUE"), "{err}");
    }

    #[test]
    fn the_mrclam_sensor_profile_gives_what_the_mrclam_settings_gave() {
        let profile = mrclam::sensor_profile();
        let cli = parse(&["run", "--out", "o"]).unwrap();
        let Command::Run(a) = cli.command else {
            panic!("not run")
        };
        let f = a
            .config
            .resolve(Some(&profile))
            .unwrap()
            .config
            .filter_config(1, 0.0);
        assert_eq!(f.heading_noise_rad_per_sqrt_s, 0.006);
        assert_eq!(f.heading_noise_rad_per_sqrt_rad, 0.11);
        assert_eq!(
            f.b_prior,
            echomap_agent::filter::BPrior::Zero { std_m: 0.05 }
        );
        assert_eq!(f.noise.distance_floor_m, 0.05);
        assert_eq!(f.noise.distance_at_0db_m, 0.6);
        assert_eq!(f.noise.aoa_floor_rad, 0.05);
        assert_eq!(f.association_p0, 1e-4);
        assert_eq!(f.association_gate, 30.0);
        assert_eq!(f.association_visibility_weight, 0.0);
        assert_eq!(f.prior_association_window, 1);
    }

    #[test]
    fn the_cooperative_experiment_hands_its_agents_a_checked_configuration() {
        let cli = parse(&[
            "experiment",
            "cooperative",
            "--out",
            "o",
            "--set",
            "prior.position_floor_m=0.3",
            "--reference-set",
            "prior.fuse_matched=false",
        ])
        .unwrap();
        let Command::Experiment(ExperimentCommand::Cooperative(a)) = cli.command else {
            panic!("not the experiment")
        };
        assert_eq!(a.reference_set.len(), 1);
        assert_eq!(a.set[0].1, serde_json::json!(0.3));
        let err = parse(&[
            "experiment",
            "cooperative",
            "--out",
            "o",
            "--match-visibility-weight=-1",
        ])
        .unwrap_err();
        assert!(err.to_string().contains("non-negative"), "{err}");
    }
}

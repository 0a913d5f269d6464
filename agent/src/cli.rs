//! Command-line interface of `echomap-agent` (kept in the library so tests reach it).

use crate::filter::{Association, BPrior, FilterConfig, NoiseModel};
use crate::sim::builtin;
use crate::sim::simulate::{SimOptions, simulate};
use crate::sim::{Scenario, SimOutput};
use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use echomap_server::config::{MatchScore, non_negative};
use echomap_shared::log::{GroundTruth, MeasurementLog};
use std::path::{Path, PathBuf};

#[derive(Debug, Parser)]
#[command(
    name = "echomap-agent",
    version,
    about = "echomap agent: simulate, run Channel-SLAM, evaluate",
    // a flag given twice takes its last value: the experiments put their defaults (e.g.
    // MRCLAM_RUN_ARGS) before the flags given after `--`, which then override them
    args_override_self = true
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Simulate one track of a scenario: writes log.jsonl and truth.json into --out.
    Simulate(SimulateArgs),
    /// Run single-user Channel-SLAM on a log (or a freshly simulated track); writes map.json,
    /// track.csv and plots into --out.
    Run(RunArgs),
    /// Run M seeds of a scenario track (simulate + filter) and report mean and 5th/95th
    /// percentile error curves against travelled distance (seed 002 Fig. 8).
    Evaluate(EvaluateArgs),
    /// Convert a real dataset into a measurement log + ground truth.
    #[command(subcommand)]
    Import(ImportCommand),
    /// Match a user map (agent frame) against a prior map (map frame): prints the transform
    /// map_from_agent, the correspondences and the score.
    Match(MatchArgs),
    /// Match and merge a user map into a prior map; writes the merged map.
    Merge(MergeArgs),
    /// The main job: start a map server on loopback, let a crowd of agent processes build a
    /// map of the indoor scenario, run the reference user alone and with the crowd's map,
    /// print the results and write plots into --out (default out/demo).
    Demo(DemoArgs),
    /// Launch users as separate `echomap-agent run` processes against a map server.
    Crowd(CrowdArgs),
    /// Experiments of the papers.
    #[command(subcommand)]
    Experiment(ExperimentCommand),
    /// Draw a scenario (walls, scatterers, transmitter, tracks, virtual transmitters) as PNG or SVG,
    /// or dump it as a JSON scenario file.
    Scenario(ScenarioArgs),
}

#[derive(Debug, Args)]
pub struct ScenarioSource {
    /// built-in scenario (`indoor`, `urban`) or a path to a JSON scenario file
    #[arg(long, default_value = "indoor")]
    pub scenario: String,
    /// drop angles of arrival: simulate a single-antenna (ToA-only) receiver
    #[arg(long)]
    pub toa_only: bool,
}

#[derive(Debug, Args)]
pub struct SimulateArgs {
    #[command(flatten)]
    pub source: ScenarioSource,
    /// track of the scenario to walk
    #[arg(long, default_value = "reference")]
    pub track: String,
    /// seed of every random draw (same seed, same output)
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// output directory (created if missing)
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Debug, Args)]
pub struct FilterArgs {
    /// number of user particles
    #[arg(long, default_value_t = 1000)]
    pub particles: usize,
    /// data association of new tracks with old transmitters
    #[arg(long, value_enum, default_value_t = Association::Ml)]
    pub association: Association,
    /// prior on a new transmitter's clock offset: `uniform` (b ∈ [0, d)) or `zero` (line of sight only)
    #[arg(long, default_value = "uniform")]
    pub b_prior: String,
    /// initial speed (m/s); default: from the ground truth when present, else 0
    #[arg(long)]
    pub initial_speed: Option<f64>,
    /// heading random walk of the motion model (rad/√s)
    #[arg(long, default_value_t = FilterConfig::default().heading_noise_rad_per_sqrt_s)]
    pub heading_noise: f64,
    /// heading noise per turned angle (rad/√rad), added in variance to --heading-noise: the
    /// wheel-odometry motion model (0: a gyroscope's random walk only)
    #[arg(long, default_value_t = FilterConfig::default().heading_noise_rad_per_sqrt_rad)]
    pub heading_noise_per_turn: f64,
    /// speed random walk of the motion model (m/s/√s)
    #[arg(long, default_value_t = FilterConfig::default().speed_noise_mps_per_sqrt_s)]
    pub speed_noise: f64,
    /// std of a measured speed (m/s), for logs that carry speed
    #[arg(long, default_value_t = FilterConfig::default().speed_measurement_std_mps)]
    pub speed_std: f64,
    /// distance noise floor the filter assumes (m)
    #[arg(long, default_value_t = NoiseModel::default().distance_floor_m)]
    pub distance_std: f64,
    /// AoA noise floor the filter assumes (rad)
    #[arg(long, default_value_t = NoiseModel::default().aoa_floor_rad)]
    pub aoa_std: f64,
    /// distance noise at an SNR of 0 dB (m), falling as 10^(−SNR/20) and added in variance to
    /// --distance-std
    #[arg(long, default_value_t = NoiseModel::default().distance_at_0db_m)]
    pub distance_at_0db: f64,
    /// AoA noise at an SNR of 0 dB (rad), as --distance-at-0db
    #[arg(long, default_value_t = NoiseModel::default().aoa_at_0db_rad)]
    pub aoa_at_0db: f64,
    /// likelihood level of "no association" (1/(m·rad); ToA-only 1/m): lower associates more readily
    #[arg(long, default_value_t = FilterConfig::default().association_p0)]
    pub association_p0: f64,
    /// χ² gate (squared Mahalanobis distance) of association candidates
    #[arg(long, default_value_t = FilterConfig::default().association_gate)]
    pub association_gate: f64,
    /// detections of a new track over which its association is decided (1: at the first)
    #[arg(long, default_value_t = FilterConfig::default().association_window)]
    pub association_window: usize,
    /// detections over which a new track's association is decided when a prior-map
    /// transmitter is among its candidates (1: at the first); default 30 with `--b-prior
    /// uniform`, 1 with `--b-prior zero` (no clock offset, so no unrelated transmitter on the
    /// ray fits a detection's range)
    #[arg(long)]
    pub prior_association_window: Option<usize>,
    /// a prior-map transmitter is no association candidate for a particle holding one of its
    /// own at least as tight within this squared Mahalanobis distance of it (χ² over x, y;
    /// 0: off)
    #[arg(long, default_value_t = FilterConfig::default().prior_shadow_chi2)]
    pub prior_shadow: f64,
    /// weight of the visibility term in association (seed 001 eq. 19), own and prior
    /// candidates alike: 1 the paper's term, 0 the measurement alone
    #[arg(long, default_value_t = FilterConfig::default().association_visibility_weight)]
    pub association_visibility_weight: f64,
    /// probability that a detection of a known transmitter is an outlier (0: off)
    #[arg(long, default_value_t = FilterConfig::default().outlier_probability)]
    pub outlier_probability: f64,
    /// density of an outlier over the measurement space (1/(m·rad); ToA-only 1/m)
    #[arg(long, default_value_t = FilterConfig::default().outlier_density)]
    pub outlier_density: f64,
}

impl FilterArgs {
    /// The filter configuration for one run.
    pub fn config(&self, seed: u64, initial_speed: f64) -> Result<FilterConfig> {
        let b_prior = match self.b_prior.as_str() {
            "uniform" => BPrior::Uniform,
            "zero" => BPrior::Zero { std_m: 0.05 },
            other => bail!("--b-prior must be `uniform` or `zero`, got {other:?}"),
        };
        anyhow::ensure!(self.particles >= 1, "--particles must be at least 1");
        anyhow::ensure!(self.association_p0 > 0.0, "--association-p0 must be > 0");
        anyhow::ensure!(
            self.association_window >= 1,
            "--association-window must be at least 1"
        );
        anyhow::ensure!(
            self.prior_association_window.is_none_or(|n| n >= 1),
            "--prior-association-window must be at least 1"
        );
        let prior_association_window = self.prior_association_window.unwrap_or(match b_prior {
            BPrior::Uniform => FilterConfig::default().prior_association_window,
            BPrior::Zero { .. } => 1,
        });
        anyhow::ensure!(
            (0.0..1.0).contains(&self.outlier_probability),
            "--outlier-probability must be in [0, 1), got {}",
            self.outlier_probability
        );
        for (flag, v) in [
            ("--heading-noise", self.heading_noise),
            ("--heading-noise-per-turn", self.heading_noise_per_turn),
            ("--speed-noise", self.speed_noise),
            ("--speed-std", self.speed_std),
            ("--outlier-density", self.outlier_density),
            ("--prior-shadow", self.prior_shadow),
            (
                "--association-visibility-weight",
                self.association_visibility_weight,
            ),
        ] {
            anyhow::ensure!(v.is_finite() && v >= 0.0, "{flag} must be ≥ 0, got {v}");
        }
        Ok(FilterConfig {
            particles: self.particles,
            seed,
            association: self.association,
            b_prior,
            initial_speed_mps: self.initial_speed.unwrap_or(initial_speed),
            heading_noise_rad_per_sqrt_s: self.heading_noise,
            heading_noise_rad_per_sqrt_rad: self.heading_noise_per_turn,
            association_p0: self.association_p0,
            association_gate: self.association_gate,
            association_window: self.association_window,
            prior_association_window,
            prior_shadow_chi2: self.prior_shadow,
            association_visibility_weight: self.association_visibility_weight,
            outlier_probability: self.outlier_probability,
            outlier_density: self.outlier_density,
            speed_noise_mps_per_sqrt_s: self.speed_noise,
            speed_measurement_std_mps: self.speed_std,
            noise: NoiseModel {
                distance_floor_m: self.distance_std,
                distance_at_0db_m: self.distance_at_0db,
                aoa_floor_rad: self.aoa_std,
                aoa_at_0db_rad: self.aoa_at_0db,
            },
            ..FilterConfig::default()
        })
    }
}

#[derive(Debug, Args)]
pub struct RunArgs {
    /// directory with log.jsonl (and truth.json when known); instead of --scenario
    #[arg(long, conflicts_with = "scenario")]
    pub log: Option<PathBuf>,
    /// simulate this scenario's --track first (built-in name or JSON file)
    #[arg(long)]
    pub scenario: Option<String>,
    /// track to simulate with --scenario
    #[arg(long, default_value = "reference")]
    pub track: String,
    /// single-antenna receiver (with --scenario)
    #[arg(long)]
    pub toa_only: bool,
    /// seed of the simulation and of the filter
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[command(flatten)]
    pub filter: FilterArgs,
    /// output directory
    #[arg(long)]
    pub out: PathBuf,
    /// no progress bar
    #[arg(long)]
    pub quiet: bool,
    /// a prior map (map frame) to match against and use: an `echomap.map.v1` file or a map
    /// document as served by GET /v1/maps/{map}; with --server the fetched map is used instead
    #[arg(long, conflicts_with = "server")]
    pub prior: Option<PathBuf>,
    /// seconds of log time between matching attempts against the prior map
    #[arg(long, default_value_t = crate::filter::PriorSettings::default().match_every_s)]
    pub match_every: f64,
    /// std (m) added to every prior transmitter's position covariance
    #[arg(long, default_value_t = crate::filter::PriorSettings::default().position_floor_m, value_parser = non_negative)]
    pub prior_floor: f64,
    /// std (m) added to every prior transmitter's clock offset: the crowd's offsets carry
    /// each contributor's own range bias (0: taken as they are)
    #[arg(long, default_value_t = crate::filter::PriorSettings::default().offset_floor_m, value_parser = non_negative)]
    pub prior_offset_floor: f64,
    /// how the matched transform's uncertainty enters the filter: K > 0 — every particle
    /// draws its own correction of the transform from the fit's spread, stds × K; 0 — every
    /// prior covariance is inflated by the spread instead
    #[arg(long, default_value_t = crate::filter::PriorSettings::default().transform_draws.unwrap_or(0.0), value_parser = non_negative)]
    pub transform_draws: f64,
    /// seconds at the start of the log whose detections anchor the matched transform (the
    /// pose is still known in the local frame then; 0: the match's own fit is used)
    #[arg(long, default_value_t = crate::filter::PriorSettings::default().anchor_window_s, value_parser = non_negative)]
    pub prior_anchor_s: f64,
    /// `true`: no transform is adopted before the anchor window (`--prior-anchor-s`) has
    /// closed, so the window's detections are placed from poses the prior has not pulled yet;
    /// default `false`
    #[arg(long, default_value_t = crate::filter::PriorSettings::default().hold_in_anchor_window, action = clap::ArgAction::Set)]
    pub prior_anchor_hold: bool,
    /// the pose uncertainty the anchor points carry at each detection, which does not
    /// average out over a transmitter's detections: `known` (default; alias `false`) — none,
    /// the pose counts as known; `particles` (alias `true`) — the particles' spread of
    /// position and heading; `odometry` — the dead-reckoning covariance since the start
    /// (the motion model's noise along the gyro and speed alone); `odometry-correlated` —
    /// that, with the points' errors correlated through the one dead reckoning and the
    /// transform fitted to their joint covariance (generalized least squares)
    #[arg(long, value_enum, default_value_t = crate::filter::PriorSettings::default().anchor_pose_uncertainty)]
    pub prior_anchor_pose: crate::filter::AnchorPose,
    /// `true`: the transform's uncertainty (what `--transform-draws` draws from, or what
    /// inflates the prior's covariances) is at least what the anchor points' covariances
    /// allow the anchored fit to know, not only what its residuals show; default `false`
    #[arg(long, default_value_t = crate::filter::PriorSettings::default().anchor_spread, action = clap::ArgAction::Set)]
    pub prior_anchor_spread: bool,
    /// `true`: prior transmitters that the match pairs with one of the agent's own are no
    /// candidates for new tracks (default `false`: every prior transmitter stays one)
    #[arg(long, default_value_t = crate::filter::PriorSettings::default().claim_matched, action = clap::ArgAction::Set)]
    pub claim_matched: bool,
    /// a transform is adopted (or replaces one it disagrees with) only after this many
    /// consecutive accepted matches agree on it (within 0.1 rad and 0.5 m); 1 (default)
    /// adopts the first accepted match
    #[arg(long, default_value_t = crate::filter::PriorSettings::default().confirmations, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub prior_confirmations: usize,
    /// `true`: when a transform that disagrees with the one in use replaces it, the
    /// transmitters started from prior copies under the old one are released (their position
    /// covariance widened by how far the new transform moves them); default `false`
    #[arg(long, default_value_t = crate::filter::PriorSettings::default().release_on_change, action = clap::ArgAction::Set)]
    pub prior_release: bool,
    /// prior transmitters with a reliability distance below this (m: how far the contributors
    /// walked while they saw it) are matched against but not offered to new tracks
    #[arg(long, default_value_t = crate::filter::PriorSettings::default().min_reliability_m, value_parser = non_negative)]
    pub prior_min_reliability: f64,
    /// `true`: every accepted match under the transform in use fuses each prior transmitter
    /// it pairs with one of the agent's own into that one (product of the two mixtures, the
    /// particle weighted by their agreement; pairs beyond the matcher's χ² gate are not
    /// fused), once per pair; default `false`
    #[arg(long, default_value_t = crate::filter::PriorSettings::default().fuse_matched, action = clap::ArgAction::Set)]
    pub prior_fuse_matched: bool,
    /// `true`: run the filter without the prior beside the one with it (same seed) and report,
    /// at every snapshot, the one under which the detections so far are the more likely
    /// (cumulative log evidence, a Bayes factor of the two models); the map of the one ahead
    /// at the end is written and uploaded; default `false`
    #[arg(long, default_value_t = false, action = clap::ArgAction::Set)]
    pub prior_fallback: bool,
    /// `false`: prior transmitters are offered to no new track (the prior is used for
    /// matching and, with `--prior-fuse-matched true`, fused into the matched own
    /// transmitters only); default `true`
    #[arg(long, default_value_t = crate::filter::PriorSettings::default().offer_to_new_tracks, action = clap::ArgAction::Set)]
    pub prior_candidates: bool,
    /// weight of the visibility term when the agent's map is matched against the prior (seed
    /// 001 eq. 18); 0 matches by transmitter positions alone (sensors whose detections depend
    /// on the heading, like MRCLAM's camera)
    #[arg(long, default_value_t = 1.0, value_parser = non_negative)]
    pub prior_visibility_weight: f64,
    /// how matching against the prior scores a hypothesis's inliers: `msac` or `likelihood`
    /// (a covariance scale fitted per hypothesis)
    #[arg(long, value_enum, default_value_t = MatchScore::Msac)]
    pub prior_match_score: MatchScore,
    /// with --server: fetch and upload, but do not use the prior map in the filter
    #[arg(long)]
    pub ignore_prior: bool,
    #[command(flatten)]
    pub server: ServerArgs,
}

impl RunArgs {
    /// How this run matches and uses a prior map; refuses a non-positive `--match-every` (the
    /// other flags' ranges are checked when they are parsed).
    pub fn prior_settings(&self) -> Result<crate::filter::PriorSettings> {
        let a = self;
        anyhow::ensure!(
            a.match_every > 0.0 && a.match_every.is_finite(),
            "--match-every must be a positive number of seconds"
        );
        Ok(crate::filter::PriorSettings {
            match_every_s: a.match_every,
            position_floor_m: a.prior_floor,
            offset_floor_m: a.prior_offset_floor,
            transform_draws: (a.transform_draws > 0.0).then_some(a.transform_draws),
            claim_matched: a.claim_matched,
            confirmations: a.prior_confirmations,
            release_on_change: a.prior_release,
            min_reliability_m: a.prior_min_reliability,
            fuse_matched: a.prior_fuse_matched,
            offer_to_new_tracks: a.prior_candidates,
            anchor_window_s: a.prior_anchor_s,
            hold_in_anchor_window: a.prior_anchor_hold,
            anchor_pose_uncertainty: a.prior_anchor_pose,
            anchor_spread: a.prior_anchor_spread,
            matching: echomap_shared::matching::MatchConfig::default()
                .with_visibility_weight(a.prior_visibility_weight)
                .with_location_score(a.prior_match_score.location_score()),
            ..Default::default()
        })
    }
}

/// Talking to a map server (`echomap-server`).
#[derive(Debug, Args)]
pub struct ServerArgs {
    /// map server base URL; fetch the prior map at start, upload the user map at the end
    #[arg(long, env = "ECHOMAP_SERVER", requires = "map")]
    pub server: Option<String>,
    /// map name on the server
    #[arg(long, env = "ECHOMAP_MAP")]
    pub map: Option<String>,
    /// file holding the bearer token (first line that is not empty or a `#` comment)
    #[arg(long, env = "ECHOMAP_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
    /// label of this agent/device sent with the upload
    #[arg(long, default_value = "echomap-agent")]
    pub contributor: String,
}

#[derive(Debug, Args)]
pub struct EvaluateArgs {
    /// built-in scenario or JSON file
    #[arg(long, default_value = "urban")]
    pub scenario: String,
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
    /// association methods to compare (comma-separated: off, ml, das); overrides --association
    #[arg(long, value_delimiter = ',', value_enum)]
    pub compare: Vec<Association>,
    #[command(flatten)]
    pub filter: FilterArgs,
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
    #[arg(long, default_value = MRCLAM_ODOMETRY_DELAY)]
    pub odometry_delay: crate::mrclam::OdometryDelay,
    /// output directory (log.jsonl, truth.json)
    #[arg(long)]
    pub out: PathBuf,
}

/// `import mrclam --odometry-delay` and `experiment cooperative --dataset mrclam
/// --odometry-delay` by default.
pub const MRCLAM_ODOMETRY_DELAY: &str = "0";

#[derive(Debug, Args)]
pub struct MatchArgs {
    /// user map (echomap.map.v1, agent frame)
    pub user: PathBuf,
    /// prior map (echomap.map.v1, map frame)
    pub prior: PathBuf,
    /// seed of the RANSAC draws
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// one JSON object on stdout
    #[arg(long)]
    pub json: bool,
    /// weight of the visibility term of eq. 18 in the score; 0 scores by location alone
    #[arg(long, default_value_t = 1.0, value_parser = non_negative)]
    pub visibility_weight: f64,
    /// how a hypothesis's inliers are scored: `msac` (1 − d²/gate each) or `likelihood` (a
    /// covariance scale fitted per hypothesis)
    #[arg(long, value_enum, default_value_t = MatchScore::Msac)]
    pub score: MatchScore,
}

#[derive(Debug, Args)]
pub struct MergeArgs {
    /// prior map (map frame)
    pub prior: PathBuf,
    /// user map (agent frame)
    pub user: PathBuf,
    /// seed of the RANSAC draws
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// merged map (written only when the match is accepted or the prior is empty)
    #[arg(long)]
    pub out: PathBuf,
    /// weight of the visibility term of eq. 18 in the matching score; 0: location alone
    #[arg(long, default_value_t = 1.0, value_parser = non_negative)]
    pub visibility_weight: f64,
    /// how a hypothesis's inliers are scored: `msac` or `likelihood`
    #[arg(long, value_enum, default_value_t = MatchScore::Msac)]
    pub score: MatchScore,
    /// merge an unmatched user transmitter into the nearest prior one within this squared
    /// Mahalanobis distance (x, y) instead of adding it (the server's `--merge-absorb-chi2`);
    /// 0: add every unmatched one
    #[arg(long, default_value_t = 0.0, value_parser = non_negative)]
    pub absorb_chi2: f64,
}

fn read_map(path: &Path) -> Result<echomap_shared::TransmitterMap> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    echomap_shared::TransmitterMap::from_json(&text)
        .with_context(|| format!("in {}", path.display()))
}

/// A prior map file: a bare `echomap.map.v1` map or a served map document.
pub fn read_prior(path: &Path) -> Result<echomap_shared::TransmitterMap> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    match echomap_shared::TransmitterMap::from_json(&text) {
        Ok(m) => Ok(m),
        Err(bare) => crate::client::parse_prior(&text)
            .map(|p| p.map)
            .map_err(|doc| {
                anyhow::anyhow!(
                    "{} is neither an echomap.map.v1 map ({bare}) nor a served map document ({doc})",
                    path.display()
                )
            }),
    }
}

/// JSON form of a match result (ids instead of indices).
pub fn match_json(
    r: &echomap_shared::matching::MatchResult,
    user: &echomap_shared::TransmitterMap,
    prior: &echomap_shared::TransmitterMap,
) -> serde_json::Value {
    let t = echomap_shared::Transform2::from_isometry(&r.map_from_agent);
    serde_json::json!({
        "accepted": r.accepted,
        "map_from_agent": t,
        "correspondences": r.correspondences.iter().map(|&(u, p)| [user.transmitters()[u].id.clone(), prior.transmitters()[p].id.clone()]).collect::<Vec<_>>(),
        "residuals_m": r.residuals_m,
        "inliers": r.inliers,
        "score": if r.score.is_finite() { r.score } else { 0.0 },
        "visibility_score": r.visibility_score,
        "iterations": r.iterations,
        "reason": r.reason,
    })
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
    /// output directory: one sub-directory per user, crowd.md, crowd.json
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Debug, Subcommand)]
pub enum ExperimentCommand {
    /// Seed 001 Fig. 5: the reference user's MAE with prior maps built by c contributors.
    Cooperative(CooperativeArgs),
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
    /// weight of the visibility term when maps are matched — by the loopback server it starts
    /// and in every agent (`run --prior-visibility-weight`); default 1, with `--dataset
    /// mrclam` 0 (a camera's detections depend on its heading, not only on the place)
    #[arg(long, value_parser = non_negative)]
    pub match_visibility_weight: Option<f64>,
    /// how hypotheses are scored when maps are matched — by the loopback server it starts
    /// (`--match-score`) and in every agent (`run --prior-match-score`): `msac` or
    /// `likelihood`; default `msac`, with `--dataset mrclam` `likelihood` (maps far tighter
    /// than their covariances in a layout that nearly repeats under a half turn)
    #[arg(long, value_enum)]
    pub match_score: Option<MatchScore>,
    /// the loopback server's `--merge-absorb-chi2`: an upload's unmatched transmitter within
    /// this squared Mahalanobis distance (x, y) of a map transmitter is merged into it instead
    /// of added; default 0 (off)
    #[arg(long, default_value_t = 0.0, value_parser = non_negative)]
    pub merge_absorb_chi2: f64,
    /// with --dataset mrclam: the robots that act as the reference, each in turn (the others
    /// build its map); default all five
    #[arg(long, value_delimiter = ',', default_value = "1,2,3,4,5")]
    pub references: Vec<u32>,
    /// with --dataset mrclam: the importer's `--odometry-delay` (`auto` or seconds)
    #[arg(long, default_value = MRCLAM_ODOMETRY_DELAY)]
    pub odometry_delay: crate::mrclam::OdometryDelay,
    /// use this server instead of starting one on loopback
    #[arg(long, env = "ECHOMAP_SERVER")]
    pub server: Option<String>,
    /// token file for --server
    #[arg(long, env = "ECHOMAP_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
    #[arg(long)]
    pub out: PathBuf,
    /// one extra word for the reference user's runs only, after those after `--` (which it
    /// overrides when it repeats one of them); repeat it per word, e.g.
    /// `--reference-arg=--prior-fuse-matched --reference-arg=true`
    #[arg(
        long = "reference-arg",
        allow_hyphen_values = true,
        value_name = "WORD"
    )]
    pub reference_run_args: Vec<String>,
    /// extra flags for every agent run (crowd and reference), after `--`, e.g.
    /// `-- --association-window 60`
    #[arg(last = true)]
    pub run_args: Vec<String>,
}

#[derive(Debug, Args)]
pub struct ScenarioArgs {
    #[command(flatten)]
    pub source: ScenarioSource,
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

/// Loads a built-in scenario by name or a JSON scenario file.
pub fn load_scenario(source: &ScenarioSource) -> Result<Scenario> {
    let mut s = match builtin::builtin(&source.scenario) {
        Some(s) => s,
        None => {
            let path = Path::new(&source.scenario);
            if !path.exists() {
                bail!(
                    "unknown scenario {:?}: not a built-in ({}) and no such file",
                    source.scenario,
                    builtin::NAMES.join(", ")
                );
            }
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            Scenario::from_json(&text)
                .with_context(|| format!("in scenario file {}", path.display()))?
        }
    };
    if source.toa_only {
        s.receiver.aoa = false;
    }
    Ok(s)
}

/// Writes `log.jsonl` and `truth.json` into `dir`.
pub fn write_sim_output(out: &SimOutput, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let log_path = dir.join("log.jsonl");
    let file = std::fs::File::create(&log_path)
        .with_context(|| format!("creating {}", log_path.display()))?;
    let mut w = std::io::BufWriter::new(file);
    out.log
        .write_to(&mut w)
        .with_context(|| format!("writing {}", log_path.display()))?;
    std::io::Write::flush(&mut w)?;
    let truth_path = dir.join("truth.json");
    std::fs::write(&truth_path, serde_json::to_string(&out.truth)?)
        .with_context(|| format!("writing {}", truth_path.display()))?;
    Ok(())
}

pub fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Simulate(a) => {
            let scenario = load_scenario(&a.source)?;
            let out = simulate(
                &scenario,
                &a.track,
                SimOptions {
                    seed: a.seed,
                    toa_only: a.source.toa_only,
                },
            )?;
            write_sim_output(&out, &a.out)?;
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
        Command::Run(a) => {
            let (log, truth) = load_run_input(&a)?;
            let initial_speed = truth
                .as_ref()
                .and_then(|t| t.poses.first())
                .map(|p| p.speed_mps)
                .unwrap_or(0.0);
            let cfg = a.filter.config(a.seed, initial_speed)?;
            let settings = a.prior_settings()?;
            let remote = crate::remote::Remote::from_args(&a.server)?;
            let prior = match (&remote, &a.prior) {
                (Some(r), _) => Some(r.fetch_prior(&a.out)?),
                (None, Some(path)) => Some(read_prior(path)?),
                (None, None) => None,
            };
            let tracker = prior
                .filter(|p| !p.is_empty() && !a.ignore_prior)
                .map(|p| crate::filter::PriorTracker::new(p, settings, a.seed));
            let tracker = tracker.transpose()?;
            let out = match tracker {
                Some(t) if a.prior_fallback => {
                    crate::run::run_filter_with_fallback(&log, truth.as_ref(), cfg, !a.quiet, t)?
                }
                t => crate::run::run_filter_with_prior(&log, truth.as_ref(), cfg, !a.quiet, t)?,
            };
            crate::output::write_run(&out, truth.as_ref(), &log, &a.out)?;
            crate::output::print_summary(&out, truth.as_ref(), &log);
            if let Some(r) = &remote {
                let run = format!("{}-seed{}", a.track, a.seed);
                r.upload(&out, &run, &a.out)?;
            }
            Ok(())
        }
        Command::Import(ImportCommand::Mrclam(a)) => {
            let opts = crate::mrclam::ImportOptions {
                robot: a.robot,
                track_gap_s: a.track_gap,
                rate_hz: a.rate,
                snr_db: 20.0,
                odometry_delay: a.odometry_delay,
            };
            let (log, truth) = crate::mrclam::import(&a.dir, opts)?;
            let source = log.header.source.clone().unwrap_or_default();
            write_sim_output(&crate::sim::SimOutput { log, truth }, &a.out)?;
            println!("imported {source} → {}", a.out.display());
            Ok(())
        }
        Command::Match(a) => {
            let (user, prior) = (read_map(&a.user)?, read_map(&a.prior)?);
            let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(a.seed);
            let cfg = echomap_shared::matching::MatchConfig::default()
                .with_visibility_weight(a.visibility_weight)
                .with_location_score(a.score.location_score());
            let r = echomap_shared::matching::match_maps(&user, &prior, &cfg, &mut rng);
            let j = match_json(&r, &user, &prior);
            if a.json {
                println!("{j}");
            } else {
                println!("{}", serde_json::to_string_pretty(&j)?);
            }
            Ok(())
        }
        Command::Merge(a) => {
            let (prior, user) = (read_map(&a.prior)?, read_map(&a.user)?);
            let (iso, pairs) = if prior.is_empty() {
                (nalgebra::Isometry2::identity(), Vec::new())
            } else {
                let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(a.seed);
                let cfg = echomap_shared::matching::MatchConfig::default()
                    .with_visibility_weight(a.visibility_weight)
                    .with_location_score(a.score.location_score());
                let r = echomap_shared::matching::match_maps(&user, &prior, &cfg, &mut rng);
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
        Command::Evaluate(a) => crate::evaluate::evaluate(&a),
        Command::Demo(a) => crate::demo::demo(&a),
        Command::Crowd(a) => crowd_command(&a),
        Command::Experiment(ExperimentCommand::Cooperative(a)) => cooperative_command(&a),
        Command::Scenario(a) => {
            let scenario = load_scenario(&a.source)?;
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
                "png" | "svg" => {
                    crate::plot::draw_scenario(&scenario, &a.tracks, &a.vtx_track, &a.out)?
                }
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

/// The log (and ground truth, when there is one) a `run` works on.
pub fn load_run_input(a: &RunArgs) -> Result<(MeasurementLog, Option<GroundTruth>)> {
    match (&a.log, &a.scenario) {
        (Some(dir), None) => {
            let log_path = dir.join("log.jsonl");
            let text = std::fs::read_to_string(&log_path)
                .with_context(|| format!("reading {}", log_path.display()))?;
            let log = MeasurementLog::parse(&text)
                .with_context(|| format!("in {}", log_path.display()))?;
            let truth_path = dir.join("truth.json");
            let truth = if truth_path.exists() {
                let text = std::fs::read_to_string(&truth_path)?;
                Some(
                    GroundTruth::parse(&text)
                        .map_err(anyhow::Error::msg)
                        .with_context(|| format!("in {}", truth_path.display()))?,
                )
            } else {
                None
            };
            Ok((log, truth))
        }
        (None, Some(s)) => {
            let scenario = load_scenario(&ScenarioSource {
                scenario: s.clone(),
                toa_only: a.toa_only,
            })?;
            let out = simulate(
                &scenario,
                &a.track,
                SimOptions {
                    seed: a.seed,
                    toa_only: a.toa_only,
                },
            )?;
            Ok((out.log, Some(out.truth)))
        }
        _ => bail!("give either --log DIR or --scenario S"),
    }
}

/// The scenario's user tracks: every track but `reference`, in order.
pub fn user_tracks(scenario: &str) -> Result<Vec<String>> {
    let s = load_scenario(&ScenarioSource {
        scenario: scenario.to_owned(),
        toa_only: false,
    })?;
    Ok(s.tracks
        .iter()
        .map(|t| t.name.clone())
        .filter(|n| n != "reference")
        .collect())
}

fn crowd_command(a: &CrowdArgs) -> Result<()> {
    use crate::crowd::{CrowdSpec, Source, User, run_crowd, table};
    let tracks = user_tracks(&a.scenario)?;
    anyhow::ensure!(
        a.users >= 1 && a.users <= tracks.len(),
        "--users must be 1..={} for scenario {:?}",
        tracks.len(),
        a.scenario
    );
    anyhow::ensure!(a.parallel >= 1, "--parallel must be at least 1");
    let (client, rt) = crate::remote::connect(&a.server, a.token_file.as_deref())?;
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
        run_args: vec!["--particles".into(), a.particles.to_string()],
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

/// Filter flags for MRCLAM (README: noise floors and the odometry's heading error measured
/// from the data, line of sight only).
pub const MRCLAM_RUN_ARGS: [&str; 18] = [
    "--heading-noise",
    "0.006",
    "--heading-noise-per-turn",
    "0.11",
    "--b-prior",
    "zero",
    "--distance-std",
    "0.05",
    // with the importer's SNR (20 dB at 1 m, −20 dB per decade): σ_d = 0.05 ⊕ 0.06·range, 1.5×
    // the range residual the data shows (≈ 0.04·range)
    "--distance-at-0db",
    "0.6",
    "--aoa-std",
    "0.05",
    "--association-p0",
    "1e-4",
    "--association-gate",
    "30",
    // the camera sees a landmark only when it faces it: the hex-cell visibility counts would
    // hold every landmark behind it as "not seen" there (README, session 20)
    "--association-visibility-weight",
    "0",
];

/// How the agents of the cooperative MRCLAM experiment use the crowd's map (README,
/// "Cooperative Channel-SLAM", sessions 23 and 24): the crowd fused into the matched own
/// transmitters and no prior copies for new tracks, its positions floored at 0.15 m, one
/// transform draw per particle, the transform anchored to the first 30 s of detections, and
/// (session 24) the run without the map beside the run with it, each snapshot reporting the
/// one that explains the detections better (session 25: a fusion counts by its Occam factor).
/// Over 20 paired runs (seeds 1–20) every robot is lower with the others' map by the median,
/// robots 1, 3, 4 and 5 beyond the spread; on fresh seeds 21–40 every robot is lower by the
/// median but only robot 3 beyond the spread (session 26). Session 27: the anchor points carry
/// the dead-reckoning pose covariance (`--prior-anchor-pose odometry`); on seeds 21–40 robots
/// 1, 2 and 3 are beyond the spread (4: p 0.09, 5 not: +0.006 m), on seeds 1–20 robots 2–5,
/// over all 40 robots 1–4 (robot 5 p 0.062).
pub const MRCLAM_PRIOR_ARGS: [&str; 14] = [
    "--prior-floor",
    "0.15",
    "--prior-fuse-matched",
    "true",
    "--prior-candidates",
    "false",
    "--transform-draws",
    "1",
    "--prior-anchor-s",
    "30",
    "--prior-fallback",
    "true",
    "--prior-anchor-pose",
    "odometry",
];

/// The cooperative experiment's matching visibility weight: as given, else 1 — and 0 on
/// MRCLAM, whose camera's detections depend on its heading, not only on the place.
fn match_visibility_weight(a: &CooperativeArgs) -> f64 {
    a.match_visibility_weight
        .unwrap_or(if a.dataset.is_empty() { 1.0 } else { 0.0 })
}

/// The cooperative experiment's matching score: as given, else MSAC — and the likelihood with
/// a fitted scale on MRCLAM (README, "Cooperative Channel-SLAM", session 13).
fn match_score(a: &CooperativeArgs) -> MatchScore {
    a.match_score.unwrap_or(if a.dataset.is_empty() {
        MatchScore::Msac
    } else {
        MatchScore::Likelihood
    })
}

fn cooperative_command(a: &CooperativeArgs) -> Result<()> {
    use crate::experiment::{ExperimentSpec, cooperative_mrclam, cooperative_scenario};
    anyhow::ensure!(a.runs >= 1, "--runs must be at least 1");
    let mut contributors = a.contributors.clone();
    contributors.sort_unstable();
    contributors.dedup();
    let weight = match_visibility_weight(a);
    for x in &a.references {
        anyhow::ensure!(
            (1..=5).contains(x),
            "--references: robot {x} is not one of 1…5"
        );
    }
    let score = match_score(a);
    let score_name = score
        .to_possible_value()
        .expect("no skipped variants")
        .get_name()
        .to_string();
    let weight_arg = [
        "--prior-visibility-weight".to_string(),
        weight.to_string(),
        "--prior-match-score".to_string(),
        score_name,
    ];
    let spec = |crowd: Vec<String>, reference: Vec<String>| ExperimentSpec {
        exe: std::env::current_exe().expect("the running executable"),
        server: a.server.clone(),
        token_file: a.token_file.clone(),
        runs: a.runs,
        first_seed: a.first_seed,
        parallel: a.parallel.max(1),
        crowd_args: [crowd, weight_arg.to_vec(), a.run_args.clone()].concat(),
        reference_args: [
            reference,
            weight_arg.to_vec(),
            a.run_args.clone(),
            a.reference_run_args.clone(),
        ]
        .concat(),
        out: a.out.clone(),
        progress: true,
        match_visibility_weight: weight,
        match_score: score,
        merge_absorb_chi2: a.merge_absorb_chi2,
    };
    let particles = |n: usize| vec!["--particles".to_string(), n.to_string()];
    match a.dataset.as_slice() {
        [] => {
            let tracks = user_tracks(&a.scenario)?;
            cooperative_scenario(
                &spec(particles(a.particles), particles(a.reference_particles)),
                &a.scenario,
                &tracks,
                "reference",
                &contributors,
            )?;
        }
        [kind, dir] if kind == "mrclam" => {
            let mut logs = Vec::new();
            for robot in 1..=5u32 {
                let d = a.out.join(format!("logs/robot{robot}"));
                let (log, truth) = crate::mrclam::import(
                    Path::new(dir),
                    crate::mrclam::ImportOptions {
                        robot,
                        track_gap_s: 5.0,
                        rate_hz: 10.0,
                        snr_db: 20.0,
                        odometry_delay: a.odometry_delay,
                    },
                )?;
                if let Some(source) = &log.header.source {
                    tracing::info!("imported {source}");
                }
                write_sim_output(&crate::sim::SimOutput { log, truth }, &d)?;
                logs.push((robot, d));
            }
            let extra: Vec<String> = MRCLAM_RUN_ARGS
                .iter()
                .chain(&MRCLAM_PRIOR_ARGS)
                .map(|s| s.to_string())
                .collect();
            let mut c = particles(a.particles);
            c.extend(extra.clone());
            let mut r = particles(a.reference_particles);
            r.extend(extra);
            cooperative_mrclam(&spec(c, r), &logs, &a.references)?;
        }
        [kind, _] => bail!("--dataset: unknown kind {kind:?} (known: mrclam)"),
        _ => bail!("--dataset takes KIND DIR"),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Parser)]
    struct Wrapper {
        #[command(flatten)]
        filter: FilterArgs,
    }

    fn prior_window(args: &[&str]) -> Result<usize> {
        let w = Wrapper::try_parse_from(std::iter::once("t").chain(args.iter().copied()))?;
        Ok(w.filter.config(1, 0.0)?.prior_association_window)
    }

    #[test]
    fn the_prior_association_window_follows_the_b_prior_unless_given() {
        let default = FilterConfig::default().prior_association_window;
        assert!(default > 1);
        assert_eq!(prior_window(&[]).unwrap(), default);
        assert_eq!(prior_window(&["--b-prior", "zero"]).unwrap(), 1);
        assert_eq!(
            prior_window(&["--b-prior", "zero", "--prior-association-window", "12"]).unwrap(),
            12
        );
        let err = prior_window(&["--prior-association-window", "0"]).unwrap_err();
        assert!(err.to_string().contains("at least 1"), "{err}");
    }

    #[test]
    fn the_prior_shadow_gate_is_off_unless_given_and_refuses_a_negative_one() {
        let shadow = |args: &[&str]| -> Result<f64> {
            let w = Wrapper::try_parse_from(std::iter::once("t").chain(args.iter().copied()))?;
            Ok(w.filter.config(1, 0.0)?.prior_shadow_chi2)
        };
        assert_eq!(shadow(&[]).unwrap(), 0.0);
        assert_eq!(shadow(&["--prior-shadow", "9.21"]).unwrap(), 9.21);
        let err = shadow(&["--prior-shadow=-1"]).unwrap_err();
        assert!(
            err.to_string().contains("--prior-shadow must be ≥ 0"),
            "{err}"
        );
    }

    #[test]
    fn association_weighs_visibility_fully_unless_told_and_not_on_mrclam() {
        let weight = |args: &[&str]| -> Result<f64> {
            let w = Wrapper::try_parse_from(std::iter::once("t").chain(args.iter().copied()))?;
            Ok(w.filter.config(1, 0.0)?.association_visibility_weight)
        };
        assert_eq!(weight(&[]).unwrap(), 1.0);
        assert_eq!(weight(&MRCLAM_RUN_ARGS).unwrap(), 0.0);
        let err = weight(&["--association-visibility-weight=-0.5"]).unwrap_err();
        assert!(
            err.to_string()
                .contains("--association-visibility-weight must be ≥ 0"),
            "{err}"
        );
    }

    #[test]
    fn the_cooperative_experiment_matches_mrclam_by_position_alone_unless_told() {
        let weight = |args: &[&str]| {
            let base = ["echomap-agent", "experiment", "cooperative", "--out", "o"];
            let cli = Cli::try_parse_from(base.iter().chain(args))?;
            let Command::Experiment(ExperimentCommand::Cooperative(a)) = cli.command else {
                panic!("not the cooperative experiment");
            };
            Ok::<f64, clap::Error>(match_visibility_weight(&a))
        };
        assert_eq!(weight(&[]).unwrap(), 1.0);
        assert_eq!(weight(&["--dataset", "mrclam", "d"]).unwrap(), 0.0);
        let score = |args: &[&str]| {
            let base = ["echomap-agent", "experiment", "cooperative", "--out", "o"];
            let cli = Cli::try_parse_from(base.iter().chain(args)).unwrap();
            let Command::Experiment(ExperimentCommand::Cooperative(a)) = cli.command else {
                panic!("not the cooperative experiment");
            };
            match_score(&a)
        };
        assert_eq!(score(&[]), MatchScore::Msac);
        assert_eq!(score(&["--dataset", "mrclam", "d"]), MatchScore::Likelihood);
        assert_eq!(
            score(&["--dataset", "mrclam", "d", "--match-score", "msac"]),
            MatchScore::Msac
        );
        let given = [
            "--dataset",
            "mrclam",
            "d",
            "--match-visibility-weight",
            "0.5",
        ];
        assert_eq!(weight(&given).unwrap(), 0.5);
        for bad in [
            "--match-visibility-weight=-1",
            "--match-visibility-weight=NaN",
        ] {
            let err = weight(&[bad]).unwrap_err();
            assert!(err.to_string().contains("non-negative"), "{err}");
        }
        let absorb = |args: &[&str]| {
            let base = ["echomap-agent", "experiment", "cooperative", "--out", "o"];
            match Cli::try_parse_from(base.iter().chain(args))?.command {
                Command::Experiment(ExperimentCommand::Cooperative(a)) => Ok(a.merge_absorb_chi2),
                _ => panic!("not the cooperative experiment"),
            }
        };
        assert_eq!(absorb(&[]).unwrap(), 0.0);
        assert_eq!(absorb(&["--merge-absorb-chi2", "9.21"]).unwrap(), 9.21);
        let err: clap::Error = absorb(&["--merge-absorb-chi2=-3"]).unwrap_err();
        assert!(err.to_string().contains("non-negative"), "{err}");
        let run = Cli::try_parse_from([
            "echomap-agent",
            "run",
            "--out",
            "o",
            "--prior-visibility-weight=-2",
        ]);
        assert!(run.unwrap_err().to_string().contains("non-negative"));
    }

    #[test]
    fn a_run_flag_given_after_the_mrclam_defaults_overrides_them() {
        let heading = |extra: &[&str]| {
            let mut args = vec!["echomap-agent", "run", "--out", "o"];
            args.extend_from_slice(&MRCLAM_RUN_ARGS);
            args.extend_from_slice(extra);
            match Cli::try_parse_from(args)?.command {
                Command::Run(r) => {
                    Ok::<f64, anyhow::Error>(r.filter.config(1, 0.0)?.heading_noise_rad_per_sqrt_s)
                }
                _ => panic!("not the run command"),
            }
        };
        let default = heading(&[]).unwrap();
        assert_eq!(heading(&["--heading-noise", "0.02"]).unwrap(), 0.02);
        assert_eq!(default.to_string(), MRCLAM_RUN_ARGS[1]);
        let err = heading(&["--heading-noise", "fast"]).unwrap_err();
        assert!(err.to_string().contains("--heading-noise"), "{err}");
    }

    #[test]
    fn the_mrclam_experiments_agents_fuse_the_anchored_crowd_unless_told_otherwise() {
        let run_args = |extra: &[&str]| {
            let mut args = vec!["echomap-agent", "run", "--out", "o"];
            args.extend_from_slice(&MRCLAM_RUN_ARGS);
            args.extend_from_slice(&MRCLAM_PRIOR_ARGS);
            args.extend_from_slice(extra);
            match Cli::try_parse_from(args)?.command {
                Command::Run(r) => Ok::<_, anyhow::Error>(r),
                _ => panic!("not the run command"),
            }
        };
        let settings = |extra: &[&str]| run_args(extra)?.prior_settings();
        let fallback = |extra: &[&str]| run_args(extra).unwrap().prior_fallback;
        assert!(fallback(&[]) && !fallback(&["--prior-fallback", "false"]));
        let plain = crate::filter::PriorSettings::default();
        let s = settings(&[]).unwrap();
        assert!(s.fuse_matched && !plain.fuse_matched);
        assert!(!s.offer_to_new_tracks && plain.offer_to_new_tracks);
        assert_eq!(s.position_floor_m, 0.15);
        assert_eq!(s.transform_draws, Some(1.0));
        assert_eq!(s.anchor_window_s, 30.0);
        assert_eq!(
            s.anchor_pose_uncertainty,
            crate::filter::AnchorPose::Odometry
        );
        assert_eq!(
            plain.anchor_pose_uncertainty,
            crate::filter::AnchorPose::Known
        );
        assert!(!s.anchor_spread);
        let s = settings(&["--prior-anchor-s", "0", "--prior-candidates", "true"]).unwrap();
        assert_eq!(s.anchor_window_s, 0.0);
        assert!(s.offer_to_new_tracks);
        let err = settings(&["--prior-offset-floor=-1"]).unwrap_err();
        assert!(err.to_string().contains("--prior-offset-floor"), "{err}");
        // the experiment's --reference-arg words reach the reference's runs only
        let cli = Cli::try_parse_from([
            "echomap-agent",
            "experiment",
            "cooperative",
            "--out",
            "o",
            "--reference-arg=--prior-fuse-matched",
            "--reference-arg",
            "false",
            "--",
            "--prior-floor",
            "0.3",
        ])
        .unwrap();
        let Command::Experiment(ExperimentCommand::Cooperative(a)) = cli.command else {
            panic!("not the cooperative experiment");
        };
        assert_eq!(a.reference_run_args, ["--prior-fuse-matched", "false"]);
        assert_eq!(a.run_args, ["--prior-floor", "0.3"]);
    }

    #[test]
    fn prior_release_is_off_unless_told() {
        let parse = |extra: &[&str]| {
            let mut args = vec!["echomap-agent", "run", "--out", "o"];
            args.extend_from_slice(extra);
            Cli::try_parse_from(args).map(|c| match c.command {
                Command::Run(a) => a.prior_release,
                _ => unreachable!(),
            })
        };
        assert!(!parse(&[]).unwrap());
        assert!(parse(&["--prior-release", "true"]).unwrap());
        assert!(parse(&["--prior-release", "maybe"]).is_err());
    }

    #[test]
    fn prior_reliability_floor_is_off_unless_told_and_not_negative() {
        let parse = |extra: &[&str]| {
            let mut args = vec!["echomap-agent", "run", "--out", "o"];
            args.extend_from_slice(extra);
            Cli::try_parse_from(args).map(|c| match c.command {
                Command::Run(a) => a.prior_min_reliability,
                _ => unreachable!(),
            })
        };
        assert_eq!(parse(&[]).unwrap(), 0.0);
        assert_eq!(parse(&["--prior-min-reliability", "2.5"]).unwrap(), 2.5);
        assert!(parse(&["--prior-min-reliability", "-1"]).is_err());
    }

    #[test]
    fn fusing_and_the_fallback_are_off_unless_told() {
        let parse = |extra: &[&str]| {
            let mut args = vec!["echomap-agent", "run", "--out", "o"];
            args.extend_from_slice(extra);
            Cli::try_parse_from(args).map(|c| match c.command {
                Command::Run(a) => (a.prior_fuse_matched, a.prior_fallback),
                _ => unreachable!(),
            })
        };
        assert_eq!(parse(&[]).unwrap(), (false, false));
        assert_eq!(
            parse(&["--prior-fuse-matched", "true"]).unwrap(),
            (true, false)
        );
        assert_eq!(parse(&["--prior-fallback", "true"]).unwrap(), (false, true));
        assert!(parse(&["--prior-fuse-matched", "yes please"]).is_err());
        assert!(parse(&["--prior-fallback", "1.0"]).is_err());
    }

    #[test]
    fn prior_transmitters_are_candidates_unless_told() {
        let parse = |extra: &[&str]| {
            let mut args = vec!["echomap-agent", "run", "--out", "o"];
            args.extend_from_slice(extra);
            Cli::try_parse_from(args).map(|c| match c.command {
                Command::Run(a) => a.prior_candidates,
                _ => unreachable!(),
            })
        };
        assert!(parse(&[]).unwrap());
        assert!(!parse(&["--prior-candidates", "false"]).unwrap());
        assert!(parse(&["--prior-candidates", "none"]).is_err());
    }

    #[test]
    fn prior_confirmations_default_to_one_and_refuse_zero() {
        let parse = |extra: &[&str]| {
            let mut args = vec!["echomap-agent", "run", "--out", "o"];
            args.extend_from_slice(extra);
            Cli::try_parse_from(args).map(|c| match c.command {
                Command::Run(a) => a.prior_confirmations,
                _ => unreachable!(),
            })
        };
        assert_eq!(parse(&[]).unwrap(), 1);
        assert_eq!(parse(&["--prior-confirmations", "3"]).unwrap(), 3);
        let err = parse(&["--prior-confirmations", "0"]).unwrap_err();
        assert!(err.to_string().contains("0 is not in 1.."), "{err}");
    }
}

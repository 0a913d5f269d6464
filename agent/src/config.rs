//! The configuration of a run: one typed, validated [`RunConfig`], resolved from layers.
//!
//! Each value comes from the last layer that sets it, in this order:
//!
//! 1. the built-in default ([`RunConfig::default`]);
//! 2. a preset, when one is asked for ([`Preset`]: typed constructors, e.g. how MRCLAM
//!    robots use a crowd's map);
//! 3. the noise laws measured from the log itself, when its sensor profile does not state
//!    them ([`measured_profile`], `echomap_shared::calibration`);
//! 4. the log's sensor profile ([`SensorProfile`], written by the simulator or importer that
//!    made the log): noise laws, line of sight only, heading-dependent detection, odometry
//!    noise;
//! 5. a configuration file (`run --config FILE`, TOML or JSON; any subset of the keys);
//! 6. flags (`--particles`, `--association`, `--set key=value`).
//!
//! [`resolve`] records where each value came from, which `echomap-agent config print` shows.
//! A key no layer knows, or a value of the wrong type or out of range, is an error that
//! names the key.

use crate::filter::{
    AnchorPose, Association, BPrior, FilterConfig, NoiseModel, PriorSettings, Proposal,
};
use echomap_shared::calibration;
use echomap_shared::log::MeasurementLog;
use echomap_shared::matching::{MatchConfig, MatchScore};
use echomap_shared::sensor::SensorProfile;
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value, json};
use std::collections::BTreeMap;
use std::fmt;
use std::path::Path;

/// Everything a run can be told, in units the names say. Every field has a default; a
/// configuration file may give any subset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunConfig {
    /// number of user particles
    pub particles: usize,
    /// independent filters the particles are split into; the run reports their equally
    /// weighted mixture, whose spread includes the scatter between them (1 = one filter)
    pub islands: usize,
    /// most Gaussian components per transmitter and particle (merged by Runnalls' rule
    /// above it): a compute budget, each component costs one cubature update per detection
    pub max_components: usize,
    pub motion: MotionConfig,
    pub measurement: MeasurementConfig,
    pub association: AssociationConfig,
    pub prior: PriorConfig,
}

/// The user's motion model (Gentner et al. 2016 eq. 15–17, with heading and speed).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MotionConfig {
    /// heading random walk (rad/√s)
    pub heading_noise_rad_per_sqrt_s: f64,
    /// heading noise per turned angle (rad/√rad), added in variance: a step's heading
    /// variance is `σ_t²·Δt + σ_r²·|ω·Δt|` (wheel odometry; 0 for a gyroscope)
    pub heading_noise_rad_per_sqrt_rad: f64,
    /// speed random walk when the log carries no speed (m/s/√s)
    pub speed_noise_mps_per_sqrt_s: f64,
    /// standard deviation of a measured speed (m/s), when the log carries speed
    pub speed_std_mps: f64,
    /// standard deviation of the gyroscope's constant bias (rad/s): every particle draws its
    /// own bias and turns by the gyro's rate minus it
    pub gyro_bias_std_rad_per_s: f64,
    /// standard deviation of the measured speed's constant relative scale error: every
    /// particle draws its own scale and moves by the measured speed times it
    pub speed_scale_std: f64,
    /// the known initial speed (m/s); unset: from the ground truth when there is one, else 0
    pub initial_speed_mps: Option<f64>,
    /// how each particle draws its motion noise: `informed` by the snapshot's detections of
    /// the transmitters it has mapped (FastSLAM 2.0), or from the `motion` model alone
    pub proposal: Proposal,
    /// keep the gauge of a map segment started after a silent stretch at dead reckoning's
    /// estimate, instead of letting resampling pick one particle's (see docs/model.md, "The
    /// gauge of a map segment")
    pub keep_gauge: bool,
}

/// What the filter assumes of the detections.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MeasurementConfig {
    /// distance noise floor (m): `σ_d = √(floor² + (at_0db·10^(−SNR/20))²)`
    pub distance_floor_m: f64,
    /// distance noise at an SNR of 0 dB (m)
    pub distance_at_0db_m: f64,
    /// angle-of-arrival noise floor (rad)
    pub aoa_floor_rad: f64,
    /// angle-of-arrival noise at an SNR of 0 dB (rad)
    pub aoa_at_0db_rad: f64,
    /// every path is line of sight: a new transmitter's clock offset starts at b ≈ 0
    /// (± 0.05 m) instead of anywhere in [0, d)
    pub line_of_sight_only: bool,
    /// probability that a detection of a known transmitter is an outlier (0: off)
    pub outlier_probability: f64,
    /// density of an outlier over the measurement space (1/(m·rad); ToA-only 1/m)
    pub outlier_density: f64,
    /// degrees of freedom of a Student-t error law whose scale is the noise law above
    /// (heavy-tailed errors); 0 = Gaussian
    pub noise_dof: f64,
    /// probability that a detection of a known transmitter comes from another member of
    /// its unresolved cluster: the same direction, a clock offset changed by a step of
    /// `jump_std_m` (0: off)
    pub jump_probability: f64,
    /// standard deviation of such a step of the clock offset (m)
    pub jump_std_m: f64,
    /// a track whose detections are gross errors k times in a row (εᵏ < 10⁻³) is taken to
    /// follow another path and starts again as a new track (needs `outlier_probability` > 0)
    pub switch_tracks: bool,
}

/// Data association of new tracks (Gentner et al. 2016 §5; Ulmschneider et al. 2021 eq. 19).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AssociationConfig {
    /// `off`, `ml` (maximum likelihood) or `das` (sampled)
    pub method: Association,
    /// likelihood level of "no association" (1/(m·rad); ToA-only 1/m): lower associates
    /// more readily
    pub p0: f64,
    /// χ² gate (squared Mahalanobis distance) of association candidates
    pub gate_chi2: f64,
    /// detections of a new track over which its association is decided (1: at the first)
    pub window: usize,
    /// detections over which it is decided when a prior-map transmitter is a candidate;
    /// unset: 1 with line-of-sight-only data, else 30
    pub prior_window: Option<usize>,
    /// weight of the visibility term (Ulmschneider et al. 2021 eq. 19): 1 the paper's term,
    /// 0 the measurement alone (sensors whose detections depend on the heading)
    pub visibility_weight: f64,
}

/// How a prior map (from a file or a server) is matched and used.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PriorConfig {
    /// seconds of log time between matching attempts
    pub match_every_s: f64,
    /// std (m) added to every prior transmitter's position covariance
    pub position_floor_m: f64,
    /// K > 0: every particle draws its own correction of the matched transform from the
    /// fit's spread, stds × K; 0: every prior covariance is inflated by the spread instead
    pub transform_draws: f64,
    /// seconds at the start of the log whose detections anchor the matched transform (0: off)
    pub anchor_window_s: f64,
    /// the pose uncertainty the anchor points carry: `known` or `odometry` (the
    /// dead-reckoning covariance since the start)
    pub anchor_pose: AnchorPose,
    /// fuse each prior transmitter a match pairs with one of the agent's own into that one
    pub fuse_matched: bool,
    /// prior transmitters are candidates for new tracks
    pub offer_to_new_tracks: bool,
    /// run the filter without the prior beside the one with it, and report at every
    /// snapshot the one the detections favour (twice the work)
    pub fallback: bool,
    /// weight of the visibility term when matching (Ulmschneider et al. 2021 eq. 18)
    pub visibility_weight: f64,
    /// how a matching hypothesis's inliers are scored: `msac` or `likelihood`
    pub match_score: MatchScore,
    /// use the prior map in the filter; false: a run with a server still fetches the prior
    /// map and uploads its own, but runs as if alone (a control for what the map gives)
    pub use_in_filter: bool,
}

/// The largest `max_components` a run accepts (a new transmitter starts with at most 24).
pub const MAX_COMPONENTS_LIMIT: usize = 64;

/// The outlier probability of a sensor that does not state one: real channel estimators
/// swap paths and misread identities now and then.
pub const DEFAULT_OUTLIER_PROBABILITY: f64 = 0.05;

impl Default for RunConfig {
    fn default() -> Self {
        let f = FilterConfig::default();
        let p = PriorSettings::default();
        RunConfig {
            particles: f.particles,
            islands: f.islands,
            max_components: f.max_components,
            motion: MotionConfig {
                heading_noise_rad_per_sqrt_s: f.heading_noise_rad_per_sqrt_s,
                heading_noise_rad_per_sqrt_rad: f.heading_noise_rad_per_sqrt_rad,
                speed_noise_mps_per_sqrt_s: f.speed_noise_mps_per_sqrt_s,
                speed_std_mps: f.speed_measurement_std_mps,
                gyro_bias_std_rad_per_s: f.gyro_bias_std_rad_per_s,
                speed_scale_std: f.speed_scale_std,
                initial_speed_mps: None,
                proposal: f.proposal,
                keep_gauge: f.keep_gauge,
            },
            measurement: MeasurementConfig {
                distance_floor_m: f.noise.distance_floor_m,
                distance_at_0db_m: f.noise.distance_at_0db_m,
                aoa_floor_rad: f.noise.aoa_floor_rad,
                aoa_at_0db_rad: f.noise.aoa_at_0db_rad,
                line_of_sight_only: false,
                // a log that says nothing of gross errors is taken to have them
                outlier_probability: DEFAULT_OUTLIER_PROBABILITY,
                outlier_density: f.outlier_density,
                noise_dof: 0.0,
                jump_probability: f.jump_probability,
                jump_std_m: f.jump_std_m,
                switch_tracks: f.switch_tracks,
            },
            association: AssociationConfig {
                method: f.association,
                p0: f.association_p0,
                gate_chi2: f.association_gate,
                window: f.association_window,
                prior_window: None,
                visibility_weight: f.association_visibility_weight,
            },
            prior: PriorConfig {
                match_every_s: p.match_every_s,
                position_floor_m: p.position_floor_m,
                transform_draws: p.transform_draws.unwrap_or(0.0),
                anchor_window_s: p.anchor_window_s,
                anchor_pose: p.anchor_pose_uncertainty,
                fuse_matched: p.fuse_matched,
                offer_to_new_tracks: p.offer_to_new_tracks,
                fallback: false,
                visibility_weight: p.matching.visibility_weight,
                match_score: MatchScore::Msac,
                use_in_filter: true,
            },
        }
    }
}

impl Default for MotionConfig {
    fn default() -> Self {
        RunConfig::default().motion
    }
}
impl Default for MeasurementConfig {
    fn default() -> Self {
        RunConfig::default().measurement
    }
}
impl Default for AssociationConfig {
    fn default() -> Self {
        RunConfig::default().association
    }
}
impl Default for PriorConfig {
    fn default() -> Self {
        RunConfig::default().prior
    }
}

/// Named starting points for kinds of data, applied before the sensor profile.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// the simulated indoor floor (the defaults)
    Indoor,
    /// the simulated urban walk (the defaults)
    Urban,
    /// UTIAS MRCLAM robots with a crowd's map: the crowd fused into the matched own
    /// transmitters and offered to no new track, its positions floored at 0.15 m, one
    /// transform draw per particle, the transform anchored to the first 30 s with the
    /// dead-reckoning pose covariance, the run without the map beside the run with it, and
    /// matching by the likelihood score (the measurements are in docs/results/cooperative.md)
    Mrclam,
}

impl Preset {
    pub const ALL: [Preset; 3] = [Preset::Indoor, Preset::Urban, Preset::Mrclam];

    pub fn name(self) -> &'static str {
        match self {
            Preset::Indoor => "indoor",
            Preset::Urban => "urban",
            Preset::Mrclam => "mrclam",
        }
    }

    /// The preset's configuration.
    pub fn config(self) -> RunConfig {
        match self {
            Preset::Indoor | Preset::Urban => RunConfig::default(),
            Preset::Mrclam => RunConfig::mrclam(),
        }
    }
}

impl std::str::FromStr for Preset {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Preset::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| format!("unknown preset {s:?} (known: indoor, urban, mrclam)"))
    }
}

impl RunConfig {
    /// See [`Preset::Mrclam`].
    pub fn mrclam() -> Self {
        let d = RunConfig::default();
        RunConfig {
            prior: PriorConfig {
                position_floor_m: 0.15,
                fuse_matched: true,
                offer_to_new_tracks: false,
                transform_draws: 1.0,
                anchor_window_s: 30.0,
                anchor_pose: AnchorPose::Odometry,
                fallback: true,
                match_score: MatchScore::Likelihood,
                ..d.prior
            },
            ..d
        }
    }

    /// Checks ranges; the error names the key.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |key: &str, why: String| {
            Err(ConfigError::Invalid {
                key: key.to_string(),
                why,
            })
        };
        if self.particles < 1 {
            return bad("particles", "must be at least 1".into());
        }
        if self.islands < 1 || self.islands > self.particles {
            return bad(
                "islands",
                format!("must be between 1 and the particles ({})", self.particles),
            );
        }
        if !(1..=MAX_COMPONENTS_LIMIT).contains(&self.max_components) {
            return bad(
                "max_components",
                format!("must be between 1 and {MAX_COMPONENTS_LIMIT}"),
            );
        }
        let m = &self.motion;
        let x = &self.measurement;
        let a = &self.association;
        let p = &self.prior;
        for (key, v) in [
            (
                "motion.heading_noise_rad_per_sqrt_s",
                m.heading_noise_rad_per_sqrt_s,
            ),
            (
                "motion.heading_noise_rad_per_sqrt_rad",
                m.heading_noise_rad_per_sqrt_rad,
            ),
            (
                "motion.speed_noise_mps_per_sqrt_s",
                m.speed_noise_mps_per_sqrt_s,
            ),
            ("motion.speed_std_mps", m.speed_std_mps),
            ("motion.gyro_bias_std_rad_per_s", m.gyro_bias_std_rad_per_s),
            ("motion.speed_scale_std", m.speed_scale_std),
            ("measurement.distance_floor_m", x.distance_floor_m),
            ("measurement.distance_at_0db_m", x.distance_at_0db_m),
            ("measurement.aoa_floor_rad", x.aoa_floor_rad),
            ("measurement.aoa_at_0db_rad", x.aoa_at_0db_rad),
            ("measurement.outlier_density", x.outlier_density),
            ("measurement.jump_std_m", x.jump_std_m),
            ("association.visibility_weight", a.visibility_weight),
            ("prior.position_floor_m", p.position_floor_m),
            ("prior.transform_draws", p.transform_draws),
            ("prior.anchor_window_s", p.anchor_window_s),
            ("prior.visibility_weight", p.visibility_weight),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(key, format!("must be a finite number ≥ 0, got {v}"));
            }
        }
        if let Some(v) = m.initial_speed_mps
            && !(v.is_finite() && v >= 0.0)
        {
            return bad(
                "motion.initial_speed_mps",
                format!("must be a finite number ≥ 0, got {v}"),
            );
        }
        if x.distance_floor_m == 0.0 && x.distance_at_0db_m == 0.0 {
            return bad(
                "measurement.distance_floor_m",
                "no distance noise at all".into(),
            );
        }
        if !(0.0..1.0).contains(&x.outlier_probability) {
            return bad(
                "measurement.outlier_probability",
                format!("must be in [0, 1), got {}", x.outlier_probability),
            );
        }
        if !(0.0..1.0).contains(&x.jump_probability) {
            return bad(
                "measurement.jump_probability",
                format!("must be in [0, 1), got {}", x.jump_probability),
            );
        }
        if !(x.noise_dof.is_finite() && x.noise_dof >= 0.0) {
            return bad(
                "measurement.noise_dof",
                format!(
                    "must be a finite number ≥ 0 (0: Gaussian), got {}",
                    x.noise_dof
                ),
            );
        }
        if !(a.p0.is_finite() && a.p0 > 0.0) {
            return bad("association.p0", format!("must be > 0, got {}", a.p0));
        }
        if !(a.gate_chi2.is_finite() && a.gate_chi2 > 0.0) {
            return bad(
                "association.gate_chi2",
                format!("must be > 0, got {}", a.gate_chi2),
            );
        }
        if a.window < 1 {
            return bad("association.window", "must be at least 1".into());
        }
        if a.prior_window == Some(0) {
            return bad("association.prior_window", "must be at least 1".into());
        }
        if !(p.match_every_s.is_finite() && p.match_every_s > 0.0) {
            return bad(
                "prior.match_every_s",
                format!(
                    "must be a positive number of seconds, got {}",
                    p.match_every_s
                ),
            );
        }
        Ok(())
    }

    /// The filter's settings for one run with `seed`; `initial_speed_mps` is used when the
    /// configuration leaves the initial speed unset (the ground truth's, or 0).
    pub fn filter_config(&self, seed: u64, initial_speed_mps: f64) -> FilterConfig {
        let (m, x, a) = (&self.motion, &self.measurement, &self.association);
        let defaults = FilterConfig::default();
        let b_prior = if x.line_of_sight_only {
            BPrior::Zero { std_m: 0.05 }
        } else {
            BPrior::Uniform
        };
        // one detection (a distance and an angle) cannot tell a prior transmitter from an
        // unrelated one on the same ray whose clock offset makes up the range, unless b = 0
        let prior_window = a.prior_window.unwrap_or(if x.line_of_sight_only {
            1
        } else {
            defaults.prior_association_window
        });
        FilterConfig {
            particles: self.particles,
            islands: self.islands,
            max_components: self.max_components,
            seed,
            association: a.method,
            b_prior,
            initial_speed_mps: m.initial_speed_mps.unwrap_or(initial_speed_mps),
            heading_noise_rad_per_sqrt_s: m.heading_noise_rad_per_sqrt_s,
            heading_noise_rad_per_sqrt_rad: m.heading_noise_rad_per_sqrt_rad,
            speed_noise_mps_per_sqrt_s: m.speed_noise_mps_per_sqrt_s,
            speed_measurement_std_mps: m.speed_std_mps,
            gyro_bias_std_rad_per_s: m.gyro_bias_std_rad_per_s,
            speed_scale_std: m.speed_scale_std,
            proposal: m.proposal,
            keep_gauge: m.keep_gauge,
            association_p0: a.p0,
            association_gate: a.gate_chi2,
            association_window: a.window,
            prior_association_window: prior_window,
            association_visibility_weight: a.visibility_weight,
            outlier_probability: x.outlier_probability,
            outlier_density: x.outlier_density,
            noise_dof: x.noise_dof,
            jump_probability: x.jump_probability,
            jump_std_m: x.jump_std_m,
            switch_tracks: x.switch_tracks,
            noise: NoiseModel {
                distance_floor_m: x.distance_floor_m,
                distance_at_0db_m: x.distance_at_0db_m,
                aoa_floor_rad: x.aoa_floor_rad,
                aoa_at_0db_rad: x.aoa_at_0db_rad,
            },
            ..defaults
        }
    }

    /// How this run matches and uses a prior map.
    pub fn prior_settings(&self) -> PriorSettings {
        let p = &self.prior;
        PriorSettings {
            match_every_s: p.match_every_s,
            position_floor_m: p.position_floor_m,
            transform_draws: (p.transform_draws > 0.0).then_some(p.transform_draws),
            anchor_window_s: p.anchor_window_s,
            anchor_pose_uncertainty: p.anchor_pose,
            fuse_matched: p.fuse_matched,
            offer_to_new_tracks: p.offer_to_new_tracks,
            matching: MatchConfig::default()
                .with_visibility_weight(p.visibility_weight)
                .with_location_score(p.match_score.location_score()),
            ..PriorSettings::default()
        }
    }
}

/// A configuration that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("unknown configuration key `{key}` (known here: {known})")]
    UnknownKey { key: String, known: String },
    #[error("configuration key `{key}` is a table; give one of its keys, e.g. `{key}.{example}`")]
    NotATable { key: String, example: String },
    #[error("configuration key `{key}`: {why}")]
    Invalid { key: String, why: String },
    #[error("{source_name}: {why}")]
    Unreadable { source_name: String, why: String },
}

/// Where a value of the effective configuration came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Source {
    Default,
    Preset(Preset),
    Measured,
    Sensor,
    File(String),
    Flag,
}

impl fmt::Display for Source {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Source::Default => write!(f, "default"),
            Source::Preset(p) => write!(f, "preset {}", p.name()),
            Source::Measured => write!(f, "measured from the log"),
            Source::Sensor => write!(f, "sensor profile"),
            Source::File(path) => write!(f, "file {path}"),
            Source::Flag => write!(f, "flag"),
        }
    }
}

/// A configuration file read into a partial table.
#[derive(Debug, Clone, PartialEq)]
pub struct ConfigFile {
    pub name: String,
    pub table: Value,
}

impl ConfigFile {
    /// Reads a TOML (`.toml`) or JSON (any other name) file of configuration keys.
    pub fn read(path: &Path) -> Result<Self, ConfigError> {
        let name = path.display().to_string();
        let unreadable = |why: String| ConfigError::Unreadable {
            source_name: name.clone(),
            why,
        };
        let text = std::fs::read_to_string(path).map_err(|e| unreadable(e.to_string()))?;
        let table: Value = if path.extension().is_some_and(|e| e == "toml") {
            let t: toml::Table = toml::from_str(&text).map_err(|e| unreadable(e.to_string()))?;
            serde_json::to_value(t).map_err(|e| unreadable(e.to_string()))?
        } else {
            serde_json::from_str(&text).map_err(|e| unreadable(e.to_string()))?
        };
        if !table.is_object() {
            return Err(unreadable(
                "a configuration file holds a table of keys".into(),
            ));
        }
        Ok(ConfigFile { name, table })
    }
}

/// The layers a run's configuration is resolved from (see the module doc).
#[derive(Debug, Clone, Default)]
pub struct Layers<'a> {
    pub preset: Option<Preset>,
    /// noise laws measured from the log ([`measured_profile`])
    pub measured: Option<&'a SensorProfile>,
    pub sensor: Option<&'a SensorProfile>,
    pub file: Option<ConfigFile>,
    /// `(dotted key, value)` pairs given as flags, in order
    pub flags: Vec<(String, Value)>,
}

/// The effective configuration and where each of its values came from.
#[derive(Debug, Clone)]
pub struct Resolved {
    pub config: RunConfig,
    /// dotted key → source, for every leaf
    pub sources: BTreeMap<String, Source>,
}

/// The noise laws of `log`'s detections measured from its own tracks
/// (`echomap_shared::calibration`), as a profile of the laws its sensor profile leaves out;
/// `None` when the profile states them all or the log is too short to measure.
pub fn measured_profile(log: &MeasurementLog) -> Option<SensorProfile> {
    let stated = log.header.sensor.as_ref();
    let has_distance = stated.is_some_and(|s| s.distance_m.is_some());
    let has_aoa = !log.header.aoa || stated.is_some_and(|s| s.aoa_rad.is_some());
    if has_distance && has_aoa {
        return None;
    }
    let m = calibration::measure_noise(log)?;
    let has_tail = stated.is_some_and(|s| s.noise_dof.is_some());
    let has_jumps = stated.is_some_and(|s| s.jump_probability.is_some());
    Some(SensorProfile {
        name: Some(format!(
            "measured from {} second differences along the log's tracks",
            m.samples
        )),
        distance_m: (!has_distance).then_some(m.distance_m),
        aoa_rad: if has_aoa { None } else { m.aoa_rad },
        // the laws are measured, so is how heavy their tails are
        noise_dof: (!has_tail).then_some(m.tail_dof),
        // and how often a track steps to another member of its cluster
        jump_probability: (!has_jumps).then(|| m.cluster_jumps.map_or(0.0, |j| j.probability)),
        jump_std_m: m.cluster_jumps.filter(|_| !has_jumps).map(|j| j.std_m),
        ..Default::default()
    })
}

/// The keys a sensor profile sets, as a partial table.
pub fn sensor_layer(p: &SensorProfile) -> Value {
    let mut t = json!({});
    let mut set = |key: &str, v: Value| {
        insert_dotted(&mut t, key, v);
    };
    if let Some(d) = p.distance_m {
        set("measurement.distance_floor_m", json!(d.floor));
        set("measurement.distance_at_0db_m", json!(d.at_0db));
    }
    if let Some(a) = p.aoa_rad {
        set("measurement.aoa_floor_rad", json!(a.floor));
        set("measurement.aoa_at_0db_rad", json!(a.at_0db));
    }
    if p.line_of_sight_only {
        set("measurement.line_of_sight_only", json!(true));
    }
    if p.heading_dependent_detection {
        set("association.visibility_weight", json!(0.0));
        set("prior.visibility_weight", json!(0.0));
    }
    if let Some(o) = p.odometry {
        if let Some(v) = o.heading_rad_per_sqrt_s {
            set("motion.heading_noise_rad_per_sqrt_s", json!(v));
        }
        if let Some(v) = o.heading_rad_per_sqrt_rad {
            set("motion.heading_noise_rad_per_sqrt_rad", json!(v));
        }
        if let Some(v) = o.speed_std_mps {
            set("motion.speed_std_mps", json!(v));
        }
        if let Some(v) = o.gyro_bias_rad_per_s {
            set("motion.gyro_bias_std_rad_per_s", json!(v));
        }
        if let Some(v) = o.speed_scale {
            set("motion.speed_scale_std", json!(v));
        }
    }
    if let Some(v) = p.new_transmitter_density {
        set("association.p0", json!(v));
    }
    if let Some(v) = p.jump_probability {
        set("measurement.jump_probability", json!(v));
    }
    if let Some(v) = p.jump_std_m {
        set("measurement.jump_std_m", json!(v));
    }
    if let Some(v) = p.outlier_probability {
        set("measurement.outlier_probability", json!(v));
    }
    if let Some(v) = p.gate_chi2 {
        set("association.gate_chi2", json!(v));
    }
    if let Some(v) = p.noise_dof {
        set("measurement.noise_dof", json!(v));
    }
    t
}

/// The keys in which `config` differs from the defaults, as a partial table.
pub fn difference_from_default(config: &RunConfig) -> Value {
    fn diff(a: &Value, d: &Value) -> Option<Value> {
        match (a, d) {
            (Value::Object(a), Value::Object(d)) => {
                let m: Map<String, Value> = a
                    .iter()
                    .filter_map(|(k, v)| diff(v, d.get(k)?).map(|x| (k.clone(), x)))
                    .collect();
                (!m.is_empty()).then_some(Value::Object(m))
            }
            _ => (a != d).then(|| a.clone()),
        }
    }
    let v = serde_json::to_value(config).expect("a RunConfig serializes");
    let d = serde_json::to_value(RunConfig::default()).expect("a RunConfig serializes");
    diff(&v, &d).unwrap_or_else(|| json!({}))
}

/// Sets `value` at a dotted `key` of the table `t`, creating tables on the way.
pub fn insert_dotted(t: &mut Value, key: &str, value: Value) {
    let mut node = t;
    let parts: Vec<&str> = key.split('.').collect();
    for part in &parts[..parts.len() - 1] {
        if !node.get(*part).is_some_and(Value::is_object) {
            node[*part] = json!({});
        }
        node = node.get_mut(*part).expect("just inserted");
    }
    node[parts[parts.len() - 1]] = value;
}

/// Parses a `--set key=value` flag: the value is read as JSON (numbers, `true`, `null`,
/// `"text"`), and as a string when it is not JSON (`association.method=das`).
pub fn parse_set(text: &str) -> Result<(String, Value), String> {
    let (key, value) = text
        .split_once('=')
        .ok_or_else(|| format!("expected KEY=VALUE, got {text:?}"))?;
    let key = key.trim();
    if key.is_empty() || key.split('.').any(str::is_empty) {
        return Err(format!("bad key {key:?} in {text:?}"));
    }
    let value = value.trim();
    let v = serde_json::from_str(value).unwrap_or_else(|_| Value::String(value.to_string()));
    Ok((key.to_string(), v))
}

fn apply(
    base: &mut Value,
    layer: &Value,
    prefix: &str,
    source: &Source,
    sources: &mut BTreeMap<String, Source>,
) -> Result<(), ConfigError> {
    let (Value::Object(base), Value::Object(layer)) = (base, layer) else {
        return Err(ConfigError::Invalid {
            key: prefix.to_string(),
            why: "expected a table".into(),
        });
    };
    for (k, v) in layer {
        let key = if prefix.is_empty() {
            k.clone()
        } else {
            format!("{prefix}.{k}")
        };
        let Some(slot) = base.get_mut(k) else {
            return Err(ConfigError::UnknownKey {
                key,
                known: base.keys().cloned().collect::<Vec<_>>().join(", "),
            });
        };
        if slot.is_object() {
            if !v.is_object() {
                let example = slot
                    .as_object()
                    .and_then(|o| o.keys().next().cloned())
                    .unwrap_or_default();
                return Err(ConfigError::NotATable { key, example });
            }
            apply(slot, v, &key, source, sources)?;
        } else {
            *slot = v.clone();
            sources.insert(key, source.clone());
        }
    }
    Ok(())
}

fn leaves(v: &Value, prefix: &str, out: &mut BTreeMap<String, Source>) {
    match v {
        Value::Object(m) => {
            for (k, x) in m {
                let key = if prefix.is_empty() {
                    k.clone()
                } else {
                    format!("{prefix}.{k}")
                };
                leaves(x, &key, out);
            }
        }
        _ => {
            out.insert(prefix.to_string(), Source::Default);
        }
    }
}

/// Resolves the effective configuration from its layers (see the module doc).
pub fn resolve(layers: &Layers<'_>) -> Result<Resolved, ConfigError> {
    let mut value = serde_json::to_value(RunConfig::default()).expect("a RunConfig serializes");
    let mut sources = BTreeMap::new();
    leaves(&value, "", &mut sources);
    if let Some(p) = layers.preset {
        let layer = difference_from_default(&p.config());
        apply(&mut value, &layer, "", &Source::Preset(p), &mut sources)?;
    }
    if let Some(m) = layers.measured {
        apply(
            &mut value,
            &sensor_layer(m),
            "",
            &Source::Measured,
            &mut sources,
        )?;
    }
    if let Some(s) = layers.sensor {
        apply(
            &mut value,
            &sensor_layer(s),
            "",
            &Source::Sensor,
            &mut sources,
        )?;
    }
    if let Some(f) = &layers.file {
        apply(
            &mut value,
            &f.table,
            "",
            &Source::File(f.name.clone()),
            &mut sources,
        )?;
    }
    for (key, v) in &layers.flags {
        let mut layer = json!({});
        insert_dotted(&mut layer, key, v.clone());
        apply(&mut value, &layer, "", &Source::Flag, &mut sources)?;
    }
    let config: RunConfig =
        serde_path_to_error::deserialize(value).map_err(|e| ConfigError::Invalid {
            key: e.path().to_string(),
            why: e.inner().to_string(),
        })?;
    config.validate()?;
    Ok(Resolved { config, sources })
}

impl Resolved {
    /// The configuration as TOML, each value with where it came from.
    pub fn annotated_toml(&self) -> String {
        let value = serde_json::to_value(&self.config).expect("a RunConfig serializes");
        let mut out = String::new();
        let mut tables = Vec::new();
        if let Value::Object(m) = &value {
            for (k, v) in m {
                if v.is_object() {
                    tables.push((k, v));
                } else {
                    self.line(&mut out, k, k, v);
                }
            }
            for (name, t) in tables {
                out.push_str(&format!("\n[{name}]\n"));
                if let Value::Object(m) = t {
                    for (k, v) in m {
                        self.line(&mut out, k, &format!("{name}.{k}"), v);
                    }
                }
            }
        }
        out
    }

    fn line(&self, out: &mut String, key: &str, dotted: &str, v: &Value) {
        let source = self
            .sources
            .get(dotted)
            .map(ToString::to_string)
            .unwrap_or_default();
        let text = match v {
            Value::Null => format!("# {key} unset"),
            Value::Number(n) if n.is_f64() => {
                let f = n.as_f64().unwrap_or_default();
                // TOML floats keep a decimal point
                if f.fract() == 0.0 && f.abs() < 1e15 {
                    format!("{key} = {f:.1}")
                } else {
                    format!("{key} = {f}")
                }
            }
            other => format!("{key} = {other}"),
        };
        out.push_str(&format!("{text:<48} # {source}\n"));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use echomap_shared::sensor::{NoiseLaw, OdometryNoise};

    fn flags(pairs: &[&str]) -> Vec<(String, Value)> {
        pairs.iter().map(|p| parse_set(p).unwrap()).collect()
    }

    #[test]
    fn a_log_that_states_no_noise_gets_it_measured_and_a_stated_law_wins() {
        use crate::sim::load_scenario;
        use crate::sim::simulate::{SimOptions, simulate};
        for (name, seed) in [("indoor", 1), ("urban", 2)] {
            let scenario = load_scenario(name, false).unwrap();
            let e = &scenario.estimator;
            let mut log = simulate(
                &scenario,
                "reference",
                SimOptions {
                    seed,
                    toa_only: false,
                },
            )
            .unwrap()
            .log;
            // the simulator states its laws: nothing to measure
            assert!(measured_profile(&log).is_none());
            log.header.sensor = None;
            let m = measured_profile(&log).expect("a whole track is enough to measure");
            let (d, a) = (m.distance_m.unwrap(), m.aoa_rad.unwrap());
            // the simulator's estimator floors (its profile states 1.5× them)
            assert!(
                (d.floor / e.distance_floor_m - 1.0).abs() < 0.1,
                "{name}: {d:?}"
            );
            assert!(
                (a.floor / e.aoa_floor_rad - 1.0).abs() < 0.1,
                "{name}: {a:?}"
            );
            // the simulator's errors are Gaussian, and measure so
            assert_eq!(m.noise_dof, Some(0.0), "{name}");
            // one detection in 25 eight floors long: tails a Gaussian cannot hold
            let mut heavy = log.clone();
            for (k, snap) in heavy.snapshots.iter_mut().enumerate() {
                for c in &mut snap.components {
                    if (k as u64 + c.track).is_multiple_of(25) {
                        c.d += 8.0 * e.distance_floor_m;
                    }
                }
            }
            let dof = measured_profile(&heavy).unwrap().noise_dof.unwrap();
            assert!((1.0..=10.0).contains(&dof), "{name}: ν = {dof}");
            let r = resolve(&Layers {
                measured: Some(&m),
                ..Default::default()
            })
            .unwrap();
            assert_eq!(r.config.measurement.distance_floor_m, d.floor);
            assert_eq!(r.config.measurement.noise_dof, 0.0);
            assert_eq!(r.sources["measurement.aoa_floor_rad"], Source::Measured);
            // each simulated track follows one virtual transmitter: (almost) no jumps
            let eta = r.config.measurement.jump_probability;
            assert!(eta < 1e-3, "{name}: η = {eta}");
            assert_eq!(r.sources["measurement.jump_probability"], Source::Measured);
            // a law the profile states beats the measured one; the other stays measured
            let stated = SensorProfile {
                distance_m: Some(NoiseLaw {
                    floor: 0.4,
                    at_0db: 0.2,
                }),
                ..Default::default()
            };
            log.header.sensor = Some(stated.clone());
            let m = measured_profile(&log).unwrap();
            assert!(m.distance_m.is_none() && m.aoa_rad.is_some());
            let r = resolve(&Layers {
                measured: Some(&m),
                sensor: Some(&stated),
                ..Default::default()
            })
            .unwrap();
            assert_eq!(r.config.measurement.distance_floor_m, 0.4);
            assert_eq!(r.sources["measurement.distance_floor_m"], Source::Sensor);
            assert_eq!(r.sources["measurement.aoa_floor_rad"], Source::Measured);
        }
    }

    #[test]
    fn the_defaults_are_the_filters_defaults() {
        // but for gross errors, which a log that says nothing is taken to have
        let r = resolve(&Layers::default()).unwrap();
        assert_eq!(r.config, RunConfig::default());
        assert_eq!(
            r.config.filter_config(1, 0.0),
            FilterConfig {
                outlier_probability: DEFAULT_OUTLIER_PROBABILITY,
                ..FilterConfig::default()
            }
        );
        assert!(r.sources.values().all(|s| *s == Source::Default));
        assert!(r.sources.contains_key("prior.match_score"));
        // a key given reaches the filter
        let r = resolve(&Layers {
            flags: flags(&["max_components=3"]),
            ..Default::default()
        })
        .unwrap();
        assert_eq!(r.config.filter_config(1, 0.0).max_components, 3);
    }

    #[test]
    fn a_profile_that_states_no_gross_errors_turns_the_outlier_term_off() {
        let profile = SensorProfile {
            outlier_probability: Some(0.0),
            ..Default::default()
        };
        let r = resolve(&Layers {
            sensor: Some(&profile),
            ..Default::default()
        })
        .unwrap();
        assert_eq!(r.config.measurement.outlier_probability, 0.0);
        assert_eq!(r.sources["measurement.outlier_probability"], Source::Sensor);
        let bad = SensorProfile {
            outlier_probability: Some(1.0),
            ..Default::default()
        };
        assert!(bad.validate().unwrap_err().contains("outlier_probability"));
    }

    #[test]
    fn later_layers_override_earlier_ones_and_say_so() {
        let profile = SensorProfile {
            distance_m: Some(NoiseLaw {
                floor: 0.05,
                at_0db: 0.6,
            }),
            line_of_sight_only: true,
            heading_dependent_detection: true,
            odometry: Some(OdometryNoise {
                heading_rad_per_sqrt_s: Some(0.006),
                ..Default::default()
            }),
            ..Default::default()
        };
        let file = ConfigFile {
            name: "my.toml".into(),
            table: json!({"measurement": {"distance_floor_m": 0.07}, "particles": 300}),
        };
        let r = resolve(&Layers {
            preset: Some(Preset::Mrclam),
            measured: None,
            sensor: Some(&profile),
            file: Some(file),
            flags: flags(&["particles=200", "association.method=das"]),
        })
        .unwrap();
        let c = &r.config;
        assert_eq!(c.particles, 200);
        assert_eq!(r.sources["particles"], Source::Flag);
        assert_eq!(c.measurement.distance_floor_m, 0.07);
        assert_eq!(
            r.sources["measurement.distance_floor_m"],
            Source::File("my.toml".into())
        );
        assert_eq!(c.measurement.distance_at_0db_m, 0.6);
        assert_eq!(r.sources["measurement.distance_at_0db_m"], Source::Sensor);
        assert_eq!(c.association.visibility_weight, 0.0);
        assert_eq!(c.association.method, Association::Das);
        assert!(c.prior.fuse_matched);
        assert_eq!(
            r.sources["prior.fuse_matched"],
            Source::Preset(Preset::Mrclam)
        );
        assert_eq!(r.sources["motion.speed_std_mps"], Source::Default);
        let f = c.filter_config(7, 0.5);
        assert_eq!(f.b_prior, BPrior::Zero { std_m: 0.05 });
        assert_eq!(f.prior_association_window, 1);
        assert_eq!(f.heading_noise_rad_per_sqrt_s, 0.006);
        assert_eq!((f.seed, f.initial_speed_mps), (7, 0.5));
        let printed = r.annotated_toml();
        assert!(printed.contains("[measurement]"), "{printed}");
        assert!(
            printed.lines().any(
                |l| l.starts_with("distance_at_0db_m = 0.6") && l.ends_with("# sensor profile")
            ),
            "{printed}"
        );
    }

    #[test]
    fn unknown_keys_bad_types_and_bad_ranges_are_named() {
        let err = |f: &[&str]| {
            resolve(&Layers {
                flags: flags(f),
                ..Default::default()
            })
            .unwrap_err()
            .to_string()
        };
        let e = err(&["motion.heading_nosie_rad_per_sqrt_s=0.1"]);
        assert!(e.contains("motion.heading_nosie_rad_per_sqrt_s"), "{e}");
        assert!(e.contains("heading_noise_rad_per_sqrt_s"), "{e}");
        assert!(err(&["prior=1"]).contains("is a table"));
        let e = err(&["particles=many"]);
        assert!(e.contains("particles"), "{e}");
        let e = err(&["association.method=best"]);
        assert!(e.contains("association.method"), "{e}");
        let e = err(&["measurement.outlier_probability=1.5"]);
        assert!(e.contains("measurement.outlier_probability"), "{e}");
        let e = err(&["particles=0"]);
        assert!(e.contains("at least 1"), "{e}");
        for bad in ["islands=0", "islands=2000"] {
            let e = err(&[bad, "particles=1000"]);
            assert!(e.contains("islands") && e.contains("between 1 and"), "{e}");
        }
        for bad in ["max_components=0", "max_components=65"] {
            let e = err(&[bad]);
            assert!(
                e.contains("max_components") && e.contains("between 1 and"),
                "{e}"
            );
        }
        let e = err(&["prior.match_every_s=0"]);
        assert!(e.contains("prior.match_every_s"), "{e}");
        assert!(parse_set("no-equals").is_err());
        assert!(parse_set("a..b=1").is_err());
    }

    #[test]
    fn a_printed_configuration_reads_back_as_the_same_configuration() {
        let r = resolve(&Layers {
            preset: Some(Preset::Mrclam),
            flags: flags(&["motion.initial_speed_mps=1.5", "particles=64"]),
            ..Default::default()
        })
        .unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.toml");
        std::fs::write(&path, r.annotated_toml()).unwrap();
        let again = resolve(&Layers {
            file: Some(ConfigFile::read(&path).unwrap()),
            ..Default::default()
        })
        .unwrap();
        assert_eq!(again.config, r.config);
        let json_path = dir.path().join("c.json");
        std::fs::write(&json_path, "[1, 2]").unwrap();
        let e = ConfigFile::read(&json_path).unwrap_err().to_string();
        assert!(e.contains("table of keys"), "{e}");
    }
}

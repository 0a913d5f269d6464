//! Filter settings with their defaults and units.

use serde::{Deserialize, Serialize};

/// Data-association method for new tracks (Gentner et al. 2016 §5).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Association {
    /// every new track is a new transmitter
    Off,
    /// maximum likelihood: the most likely of {old transmitters, none} (eq. 56)
    Ml,
    /// data association sampling: sampled in proportion to the likelihoods
    Das,
}

impl Association {
    /// The name used in flags and files.
    pub fn name(self) -> &'static str {
        match self {
            Association::Off => "off",
            Association::Ml => "ml",
            Association::Das => "das",
        }
    }
}

impl std::str::FromStr for Association {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        [Association::Off, Association::Ml, Association::Das]
            .into_iter()
            .find(|a| a.name() == s)
            .ok_or_else(|| format!("unknown association {s:?} (known: off, ml, das)"))
    }
}

impl std::fmt::Display for Association {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// How each particle draws its motion noise.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Proposal {
    /// from the motion model alone (Gentner et al. 2016; FastSLAM 1.0)
    Motion,
    /// from the motion model and the snapshot's detections of the transmitters the particle
    /// has mapped, linearized (FastSLAM 2.0; the importance ratio joins the weight)
    Informed,
}

impl Proposal {
    /// The name used in flags and files.
    pub fn name(self) -> &'static str {
        match self {
            Proposal::Motion => "motion",
            Proposal::Informed => "informed",
        }
    }
}

impl std::str::FromStr for Proposal {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        [Proposal::Motion, Proposal::Informed]
            .into_iter()
            .find(|a| a.name() == s)
            .ok_or_else(|| format!("unknown proposal {s:?} (known: motion, informed)"))
    }
}

impl std::fmt::Display for Proposal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Prior on a new transmitter's clock offset b.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BPrior {
    /// b ∈ [0, d) uniform: the transmitter lies anywhere on the ray up to range d (Gentner et al. 2016 §4.3)
    Uniform,
    /// b ≈ 0 with the given std (m): line-of-sight-only data such as MRCLAM landmarks
    Zero { std_m: f64 },
}

/// Measurement noise the filter assumes, as a function of the reported per-sample SNR γ (dB):
/// `σ = √(floor² + (at_0db · 10^(−γ/20))²)` — the shape of the CRLB (see docs/model.md).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NoiseModel {
    pub distance_floor_m: f64,
    pub distance_at_0db_m: f64,
    pub aoa_floor_rad: f64,
    pub aoa_at_0db_rad: f64,
}

impl Default for NoiseModel {
    /// 1.5× the simulator's default floors (model-mismatch margin) and its CRLB terms for
    /// 100 MHz, 64 samples and a 3×3 array.
    fn default() -> Self {
        NoiseModel {
            distance_floor_m: 0.375,
            distance_at_0db_m: 0.15,
            aoa_floor_rad: 6f64.to_radians(),
            aoa_at_0db_rad: 0.012,
        }
    }
}

impl NoiseModel {
    /// (σ_d in m, σ_θ in rad) at SNR `snr_db`.
    pub fn std(&self, snr_db: f64) -> (f64, f64) {
        let f = 10f64.powf(-snr_db / 20.0);
        (
            self.distance_floor_m.hypot(self.distance_at_0db_m * f),
            self.aoa_floor_rad.hypot(self.aoa_at_0db_rad * f),
        )
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FilterConfig {
    /// number of user particles
    pub particles: usize,
    /// independent particle filters ("islands", Vergé et al. 2015) the particles are split
    /// into; the run reports their equally weighted mixture (`crate::run`)
    pub islands: usize,
    /// seed of every random draw
    pub seed: u64,
    pub association: Association,
    /// heading random walk of the motion model (rad/√s); von Mises per step with κ = 1/(σ²·Δt)
    pub heading_noise_rad_per_sqrt_s: f64,
    /// heading noise that grows with the turn the gyro reports (rad/√rad): the variance of a
    /// step is `σ_t²·Δt + σ_r²·|ω·Δt|` — the wheel-odometry motion model, where the heading
    /// error comes from turning rather than from time (0 for a gyroscope's pure random walk)
    pub heading_noise_rad_per_sqrt_rad: f64,
    /// speed random walk when no speed is measured (m/s/√s)
    pub speed_noise_mps_per_sqrt_s: f64,
    /// how each particle draws its motion noise (`proposal`)
    pub proposal: Proposal,
    /// keep an open map segment's gauge through resampling (`super::gauge`)
    pub keep_gauge: bool,
    /// std of a measured speed (m/s), when the log carries speed
    pub speed_measurement_std_mps: f64,
    /// std of a constant gyroscope bias each particle draws (rad/s; 0 = none)
    pub gyro_bias_std_rad_per_s: f64,
    /// std of a constant relative scale error of the measured speed each particle draws
    pub speed_scale_std: f64,
    /// the known initial speed (m/s) (Gentner et al. 2016 §6.1: the initial state is known)
    pub initial_speed_mps: f64,
    /// spread of the initial speed over particles (m/s)
    pub initial_speed_std_mps: f64,
    pub noise: NoiseModel,
    pub b_prior: BPrior,
    /// spacing of initial components along the ray (m)
    pub init_spacing_m: f64,
    /// most components a new transmitter starts with
    pub init_max_components: usize,
    /// components below this weight are pruned (ρ of Gentner et al. 2016 §4.3)
    pub prune_weight: f64,
    /// most components per transmitter and particle (reduced by Runnalls merging). A
    /// compute budget, not a model parameter: every component costs one cubature update per
    /// detection; 8 takes 0.72× the time of 12 on the built-in urban track and estimates
    /// within its run-to-run spread by the medians but a little worse in most runs, 6 merges
    /// a young transmitter's ray into Gaussians too wide for the cubature update
    /// (docs/results/benchmarks.md, "Fewer components per transmitter")
    pub max_components: usize,
    /// resample when ESS < ratio × particles
    pub resample_ess_ratio: f64,
    /// likelihood of "no association" (density in 1/(m·rad); ToA-only: 1/m) — p₀ of Gentner et al. 2016 §5
    pub association_p0: f64,
    /// probability ε that a detection of a known transmitter is an outlier (a gross error of
    /// the channel estimator or the tracker), decided once per detection over the particle
    /// population (`Filter::weigh_detections`): an outlier weights no particle and moves no
    /// transmitter; 0 = every detection is taken as it is
    pub outlier_probability: f64,
    /// density λ of an outlier over the measurement space (1/(m·rad); ToA-only: 1/m)
    pub outlier_density: f64,
    /// probability η that a detection of a known transmitter comes from another member of
    /// its unresolved cluster (same direction, another clock offset), decided once per
    /// detection for the whole population like a gross error (`Filter::weigh_detections`)
    pub jump_probability: f64,
    /// standard deviation of the clock offset's step when it does (m)
    pub jump_std_m: f64,
    /// a run of gross errors makes a track a switch to another path (`Filter::switch_tracks`)
    pub switch_tracks: bool,
    /// degrees of freedom ν of a Student-t error law whose scale is the noise law (heavy
    /// tails: errors of many σ are rare but not impossible); 0 = Gaussian
    pub noise_dof: f64,
    /// squared Mahalanobis gate of an association candidate (χ², default 11.8 ≈ 99.7 % for 2 dof)
    pub association_gate: f64,
    /// detections of a new track over which its association with an old transmitter is
    /// decided (1 = at its first detection, Gentner et al. 2016 §5): with n > 1 the track starts as a
    /// tentative new transmitter, the gated old candidates are updated alongside it, and after
    /// n detections (or when the track ends) each particle compares the evidences
    /// ln p(z₁..zₙ | new) and ln p(z₁..zₙ | old j)
    pub association_window: usize,
    /// detections over which a new track's association is decided when a prior-map
    /// transmitter is among its candidates (1 = at its first detection, as for old ones).
    /// One detection (a distance and an angle) cannot tell a prior transmitter from an
    /// unrelated one on the same ray whose clock offset makes up the range; the detections
    /// that follow as the user moves can. The CLI uses 1 when b is known to be zero
    pub prior_association_window: usize,
    /// only old transmitters whose position std (√tr P_xy) is at most this are candidates (m)
    pub association_max_spread_m: f64,
    /// prior-map transmitters are association candidates only with at least this existence
    pub prior_min_existence: f64,
    /// exponent of the visibility term of association (Ulmschneider et al. 2021 eq. 19): a candidate's
    /// score is `ln p(z | candidate) + w·ln p_vis`, own and prior candidates alike (1: the
    /// paper's term; 0: by the measurement alone). The hex-cell counts assume a transmitter in
    /// range is seen from anywhere in the cell; a sensor whose detections depend on its heading
    /// (MRCLAM's camera) counts every landmark behind it as "not seen" there
    pub association_visibility_weight: f64,
    /// hexagon circumradius of the visibility grid (m)
    pub hex_size_m: f64,
    /// Beta prior pseudo-counts (ν, ν̄) of Ulmschneider et al. 2021 eq. 12
    pub visibility_prior: (f64, f64),
    /// a track stays alive this long without detection (s); set from the log header
    pub track_hold_s: f64,
    /// most components per transmitter in the exported map
    pub export_max_components: usize,
    /// standard deviation (m) added in quadrature to the x/y covariance of every exported
    /// component: the map is expressed relative to the estimated track, so it carries the
    /// track's error, which the per-particle Kalman covariances (conditional on each
    /// particle's track, and collapsed by resampling) do not; without it two users' maps of
    /// the same place disagree by 10–20 of their own standard deviations and cannot be matched
    pub export_position_floor_m: f64,
}

impl FilterConfig {
    /// Variance of the heading noise over one step of `dt` seconds turning at `gyro` rad/s:
    /// `σ_t²·Δt + σ_r²·|ω·Δt|` (rad²).
    pub fn heading_step_variance(&self, gyro: f64, dt: f64) -> f64 {
        self.heading_noise_rad_per_sqrt_s.powi(2) * dt
            + self.heading_noise_rad_per_sqrt_rad.powi(2) * (gyro * dt).abs()
    }
}

impl Default for FilterConfig {
    fn default() -> Self {
        FilterConfig {
            particles: 1000,
            islands: 1,
            seed: 1,
            association: Association::Ml,
            heading_noise_rad_per_sqrt_s: 0.03,
            heading_noise_rad_per_sqrt_rad: 0.0,
            speed_noise_mps_per_sqrt_s: 0.03,
            proposal: Proposal::Informed,
            keep_gauge: false,
            speed_measurement_std_mps: 0.05,
            // none unless the log's sensor profile states them: data-sheet priors (0.005 rad/s,
            // 3 %) on the ray-traced walks put three of nine above dead reckoning
            gyro_bias_std_rad_per_s: 0.0,
            speed_scale_std: 0.0,
            initial_speed_mps: 0.0,
            initial_speed_std_mps: 0.0,
            noise: NoiseModel::default(),
            b_prior: BPrior::Uniform,
            init_spacing_m: 2.0,
            init_max_components: 24,
            prune_weight: 1e-3,
            max_components: 12,
            resample_ess_ratio: 0.5,
            association_p0: 0.02,
            association_gate: 11.8,
            association_window: 1,
            prior_association_window: 30,
            outlier_probability: 0.0,
            outlier_density: 1.0 / (10.0 * std::f64::consts::TAU),
            jump_probability: 0.0,
            jump_std_m: 1.5,
            switch_tracks: false,
            noise_dof: 0.0,
            association_max_spread_m: 3.0,
            prior_min_existence: 0.5,
            association_visibility_weight: 1.0,
            hex_size_m: 2.0,
            visibility_prior: (1.0, 1.0),
            track_hold_s: 0.0,
            export_max_components: 4,
            export_position_floor_m: 0.5,
        }
    }
}

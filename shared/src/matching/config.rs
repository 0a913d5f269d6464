//! Settings and outcome of map matching, and the named choices of its score.

use super::*;

/// Matching settings; defaults in `Default`.
#[derive(Debug, Clone, PartialEq)]
pub struct MatchConfig {
    /// candidates need a position std √tr(P_xy) at most this (m); default 2.0
    pub max_position_std_m: f64,
    /// candidates need existence at least this; default 0.5
    pub min_existence: f64,
    /// a transformed user transmitter is an inlier of a prior one when the squared
    /// Mahalanobis distance of their positions (both covariances) is at most this; default
    /// 9.21 (χ², 2 dof, 99 %)
    pub inlier_gate_chi2: f64,
    /// and in any case no farther than this (m); default 3.0
    pub inlier_threshold_m: f64,
    /// accept only when the expected number of false alarms — hypotheses tried × the chance
    /// that unrelated maps fit at least as well (see `false_alarms`) — is below this; default 1e-2
    pub max_false_alarms: f64,
    /// pairwise distances of a triple must agree within this (m); default 1.5
    pub distance_tolerance_m: f64,
    /// clock-offset gate: |b_u − b_p| ≤ gate_sigma·√(σ_u² + σ_p²) + floor; defaults 3, 0.5 m
    pub b_gate_sigma: f64,
    /// the floor of the clock-offset gate (m)
    pub b_gate_floor_m: f64,
    /// accept only with at least this many inliers; default 5
    pub min_inliers: usize,
    /// RANSAC confidence for the adaptive number of draws; default 0.999
    pub confidence: f64,
    /// most user triples drawn; default 500
    pub max_iterations: usize,
    /// most prior triples tried per user triple; default 16
    pub max_hypotheses_per_sample: usize,
    /// nearly collinear inliers cannot tell a rotation from a mirror image: the best mirror
    /// image (an improper rigid motion) of the inlier pairs must fit worse than the match
    /// by at least this much summed squared Mahalanobis distance (χ², pair covariances);
    /// default 13.8 (the 99.9 % point of χ² with 2 degrees of freedom). Relative to the
    /// pairs' uncertainties, so a layout narrow in metres but wide against its position
    /// errors (MRCLAM's landmarks: minor-axis std 1.0 m) is accepted
    pub min_mirror_chi2: f64,
    /// use the visibility term of eq. 18; default true
    pub use_visibility: bool,
    /// weight of the visibility log-likelihood ratio in the score; default 1.0 (see
    /// [`MatchConfig::with_visibility_weight`])
    pub visibility_weight: f64,
    /// the user's seen/unseen counts of a cell are scaled to at most this many observations
    /// before they enter the visibility term: consecutive snapshots in one cell are not
    /// independent, and raw counts (hundreds) let the visibility term outweigh every
    /// location residual; default 1.0
    pub visibility_max_count: f64,
    /// standard deviation added isotropically (in quadrature) to every transmitter's position
    /// covariance: a filter's map is distorted by its track error, which the per-transmitter
    /// covariances (conditional on the particles' tracks) do not carry (m); default 0 (the
    /// agent's export already adds its floor, `export_position_floor_m`)
    pub position_floor_m: f64,
    /// how a hypothesis's inliers are scored (the location term of eq. 18); default
    /// [`LocationScore::Msac`]
    pub location_score: LocationScore,
}

/// The location term of a hypothesis's score.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LocationScore {
    /// MSAC: each inlier scores 1 − d²/gate (d² its squared Mahalanobis distance). Blind to
    /// how tight the inliers are when the covariances are wide: on MRCLAM, whose landmark
    /// layout nearly repeats under a half turn (0.4 m median misfit) while the maps carry the
    /// export's 0.5 m floor, the half turn's one extra loose inlier outscored the right
    /// transform's tight ones
    Msac,
    /// The log-likelihood ratio of the inliers against clutter, with the pair covariances
    /// scaled by a common factor k² fitted to the hypothesis: each inlier scores
    /// max(0, ln A − ln(2π·k²·√det S) − d²/(2k²)), A the area of the prior's candidates (the
    /// clutter density is 1/A), S the pair covariance, k ∈ [`min_scale`, 1] maximizing the
    /// sum. A map that fits an order of magnitude tighter than its covariances claim scores
    /// up to 2·ln(1/k) more per inlier than a loose fit with the same count. Not the
    /// default: on MRCLAM it matched 530 instead of 438 of 600 contributor-map pairs right,
    /// but on the end-to-end test's indoor triples (two walks of one track) the last agent's
    /// final error rose in all four (docs/results/cooperative.md)
    Likelihood {
        /// the least covariance scale the fit may take
        min_scale: f64,
    },
}

impl LocationScore {
    /// [`LocationScore::Likelihood`] with the scale bounded below by 0.1.
    pub const LIKELIHOOD: LocationScore = LocationScore::Likelihood { min_scale: 0.1 };
}

/// The named choice of [`LocationScore`] that settings files, flags and the server take.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MatchScore {
    /// MSAC: each inlier scores 1 − d²/gate
    #[default]
    Msac,
    /// the inliers' log-likelihood ratio against clutter with a covariance scale fitted to
    /// each hypothesis (tight fits win over loose ones with as many inliers)
    Likelihood,
}

impl MatchScore {
    /// The location term this choice stands for.
    pub fn location_score(self) -> LocationScore {
        match self {
            MatchScore::Msac => LocationScore::Msac,
            MatchScore::Likelihood => LocationScore::LIKELIHOOD,
        }
    }

    /// The name used in flags and files.
    pub fn name(self) -> &'static str {
        match self {
            MatchScore::Msac => "msac",
            MatchScore::Likelihood => "likelihood",
        }
    }
}

impl std::str::FromStr for MatchScore {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "msac" => Ok(MatchScore::Msac),
            "likelihood" => Ok(MatchScore::Likelihood),
            other => Err(format!(
                "unknown match score {other:?} (known: msac, likelihood)"
            )),
        }
    }
}

impl std::fmt::Display for MatchScore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl Default for MatchConfig {
    fn default() -> Self {
        MatchConfig {
            max_position_std_m: 2.0,
            min_existence: 0.5,
            inlier_gate_chi2: 9.21,
            inlier_threshold_m: 3.0,
            max_false_alarms: 1e-2,
            distance_tolerance_m: 1.5,
            b_gate_sigma: 3.0,
            b_gate_floor_m: 0.5,
            min_inliers: 5,
            confidence: 0.999,
            max_iterations: 2000,
            max_hypotheses_per_sample: 64,
            min_mirror_chi2: 13.8,
            use_visibility: true,
            visibility_weight: 1.0,
            visibility_max_count: 1.0,
            position_floor_m: 0.0,
            location_score: LocationScore::Msac,
        }
    }
}

impl MatchConfig {
    /// The settings with the visibility term weighted by `weight`; 0 scores hypotheses by
    /// location alone. Location alone suits sensors whose detections depend on the heading
    /// (a camera's field of view, MRCLAM): their seen/unseen counts per hexagon are not a
    /// property of the place, and on MRCLAM dataset 6 the term made the wrong transform win
    /// more often (docs/results/cooperative.md).
    pub fn with_visibility_weight(self, weight: f64) -> Self {
        MatchConfig {
            use_visibility: weight > 0.0,
            visibility_weight: weight,
            ..self
        }
    }

    /// The settings with the inliers scored by `score`.
    pub fn with_location_score(self, score: LocationScore) -> Self {
        MatchConfig {
            location_score: score,
            ..self
        }
    }
}

/// What the acceptance test concluded about two maps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MatchDecision {
    /// the maps share a part, under the transform found: merge
    Accepted,
    /// the overlap could have shown a common part, and it did not: the maps disagree where they
    /// overlap, or share nothing
    Rejected,
    /// the maps share too little to decide either way (too few transmitters in the overlap,
    /// or inliers nearly on a line): not merged; the user map is worth another try once the
    /// prior has grown
    Undecided,
}

impl MatchDecision {
    /// The decision's name as JSON and the HTTP API spell it.
    pub fn as_str(self) -> &'static str {
        match self {
            MatchDecision::Accepted => "accepted",
            MatchDecision::Rejected => "rejected",
            MatchDecision::Undecided => "undecided",
        }
    }
}

/// Outcome of matching.
#[derive(Debug, Clone, PartialEq)]
pub struct MatchResult {
    /// whether the match passed the acceptance test (`decision` is `Accepted`)
    pub accepted: bool,
    /// what the test concluded
    pub decision: MatchDecision,
    /// maps agent-frame coordinates into the map frame
    pub map_from_agent: Isometry2<f64>,
    /// (user index, prior index) into the maps' transmitter lists
    pub correspondences: Vec<(usize, usize)>,
    /// distance after transformation of each correspondence (m)
    pub residuals_m: Vec<f64>,
    /// number of inlier pairs
    pub inliers: usize,
    /// location score + visibility score of the chosen hypothesis
    pub score: f64,
    /// the visibility term of the score
    pub visibility_score: f64,
    /// why the match was rejected
    pub reason: Option<String>,
    /// RANSAC iterations run
    pub iterations: usize,
}

impl MatchResult {
    pub(super) fn refused(decision: MatchDecision, reason: String, iterations: usize) -> Self {
        MatchResult {
            accepted: false,
            decision,
            map_from_agent: Isometry2::identity(),
            correspondences: Vec::new(),
            residuals_m: Vec::new(),
            inliers: 0,
            score: f64::NEG_INFINITY,
            visibility_score: 0.0,
            reason: Some(reason),
            iterations,
        }
    }
}

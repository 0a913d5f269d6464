//! Map matching: the rigid transform `map_from_agent` and the transmitter correspondences
//! between a user map (agent frame) and a prior map (map frame), Ulmschneider et al. 2021 §III, Fig. 3.
//!
//! RANSAC over minimal samples of three transmitters. Beyond the paper's random draw from
//! both maps, the prior triple is found from the user triple by pairwise-distance
//! consistency (eq. 17 as a search): prior pairs whose distance agrees with the user pair's
//! within `distance_tolerance_m`, nearest first, both orderings; the third member is looked
//! up where the first two pairs put it. Pairs are gated by the frame-invariant clock offset
//! b. Each consistent triple gives a least-squares rigid transform (2D Kabsch without scale:
//! a proper rotation, so a mirror image never fits). LO-RANSAC: a hypothesis that does at
//! least as well as the best so far on a single pass is locally optimized — every pair
//! inside the χ² gate re-collected one-to-one and the transform re-estimated until the set is
//! stable. Hypotheses are scored by eq. 18: the location term p(H) — the inliers'
//! MSAC's truncated quadratic ([`LocationScore::Msac`], default) or the log-likelihood ratio
//! against clutter with a covariance scale fitted per hypothesis ([`LocationScore::Likelihood`]) —
//! plus the visibility term log p(M|H) — the user's transformed
//! visibility counts scored under the prior's Beta distributions (Beta-binomial), as a
//! log-likelihood ratio against an uninformative Beta(1, 1). The number of user triples drawn
//! adapts to the best inlier ratio and `confidence`. The chosen hypothesis is accepted by an
//! a-contrario test on its residuals (`false_alarms`, in the manner of ORSA).
//!
//! Complexity: O(P²) once for the prior pairs, binned by distance; per drawn triple O(k log k)
//! for the k prior pairs of consistent distance (at most `max_hypotheses_per_sample` tried), O(U) for each single-pass check with a uniform
//! grid of prior means, and O(U·iterations) for each local optimization.

use crate::hexgrid::HexGrid;
use crate::map::{Transmitter, TransmitterMap, transform_visibility};
use nalgebra::{Isometry2, Matrix2, Matrix3, Point2, Vector2, Vector3};
use rand::{Rng, RngExt};

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

/// Outcome of matching.
#[derive(Debug, Clone, PartialEq)]
pub struct MatchResult {
    /// whether the match passed the acceptance test
    pub accepted: bool,
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
    fn rejected(reason: String, iterations: usize) -> Self {
        MatchResult {
            accepted: false,
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

/// A matching candidate: index in its map, mean position, b and its std.
#[derive(Debug, Clone, Copy)]
struct Cand {
    index: usize,
    p: Point2<f64>,
    /// position covariance (x/y block)
    cov: nalgebra::Matrix2<f64>,
    b: f64,
    b_std: f64,
}

fn candidates(map: &TransmitterMap, cfg: &MatchConfig) -> Vec<Cand> {
    map.transmitters()
        .iter()
        .enumerate()
        .filter(|(_, t)| t.existence >= cfg.min_existence)
        .filter_map(|(index, t)| {
            let (m, p) = t.moments();
            ((p[(0, 0)] + p[(1, 1)]).sqrt() <= cfg.max_position_std_m).then(|| Cand {
                index,
                p: Point2::new(m.x, m.y),
                cov: p.fixed_view::<2, 2>(0, 0).into_owned()
                    + nalgebra::Matrix2::identity() * cfg.position_floor_m.powi(2),
                b: m.z,
                b_std: p[(2, 2)].max(0.0).sqrt(),
            })
        })
        .collect()
}

fn b_compatible(u: &Cand, p: &Cand, cfg: &MatchConfig) -> bool {
    (u.b - p.b).abs() <= cfg.b_gate_sigma * u.b_std.hypot(p.b_std) + cfg.b_gate_floor_m
}

/// Least-squares rigid transform (rotation + translation, no scale, det = +1) taking
/// `from` onto `to` (2D Kabsch/Umeyama). None for fewer than two distinct points.
pub fn fit_rigid(from: &[Point2<f64>], to: &[Point2<f64>]) -> Option<Isometry2<f64>> {
    let n = from.len();
    if n < 2 || n != to.len() {
        return None;
    }
    let cf = from.iter().fold(Vector2::zeros(), |a, p| a + p.coords) / n as f64;
    let ct = to.iter().fold(Vector2::zeros(), |a, p| a + p.coords) / n as f64;
    let (mut dot, mut cross) = (0.0, 0.0);
    for (f, t) in from.iter().zip(to) {
        let (a, b) = (f.coords - cf, t.coords - ct);
        dot += a.dot(&b);
        cross += a.x * b.y - a.y * b.x;
    }
    if dot.abs() + cross.abs() < 1e-12 {
        return None;
    }
    let angle = cross.atan2(dot);
    let rot = nalgebra::Rotation2::new(angle);
    let t = ct - rot * cf;
    Some(Isometry2::new(t, angle))
}

/// Maximum-likelihood rigid transform taking the points `from` onto `to` when pair i's
/// residual `toᵢ − (R·fromᵢ + t)` is Gaussian with covariance `R·Cᶠᵢ·Rᵀ + Cᵗᵢ` (the two
/// maps' position covariances): Gauss–Newton on (θ, t) from `init`, the pair covariances
/// re-rotated every iteration. Unlike [`fit_rigid`] a transmitter known to 0.1 m pulls the
/// fit harder than one known to 2 m, and only across its long axis. None when the normal
/// equations are singular (fewer than two pairs, or every covariance degenerate).
pub fn fit_rigid_weighted(
    from: &[(Point2<f64>, Matrix2<f64>)],
    to: &[(Point2<f64>, Matrix2<f64>)],
    init: Isometry2<f64>,
) -> Option<Isometry2<f64>> {
    weighted_gauss_newton(from, to, init).map(|(iso, _)| iso)
}

/// [`fit_rigid_weighted`] with the covariance of its estimate: the inverse of the
/// Gauss–Newton information `Σ Jᵢᵀ Wᵢ Jᵢ` at the solution, over (θ, t_x, t_y) — what the
/// pair covariances allow the fit to know if the pairs' errors are independent.
pub fn fit_rigid_weighted_cov(
    from: &[(Point2<f64>, Matrix2<f64>)],
    to: &[(Point2<f64>, Matrix2<f64>)],
    init: Isometry2<f64>,
) -> Option<(Isometry2<f64>, Matrix3<f64>)> {
    let (iso, normal) = weighted_gauss_newton(from, to, init)?;
    let (angle, t) = (iso.rotation.angle(), iso.translation.vector);
    let cov = normal(angle, t)?.0.cholesky()?.inverse();
    Some((iso, cov))
}

/// [`fit_rigid_weighted_cov`] when the errors of the `from` points are correlated: the
/// maximum-likelihood rigid transform for a joint Gaussian error of the stacked `from` points
/// with covariance `cov_from` (2n × 2n, x and y of point i at rows 2i and 2i + 1) and
/// independent errors `cov_to[i]` of the `to` points. Generalized least squares by
/// Gauss–Newton on (θ, t) from `init`, `cov_from` re-rotated every iteration; returns the
/// transform and the inverse of its information. With a block-diagonal `cov_from` it is
/// [`fit_rigid_weighted_cov`]. What the correlation is for: points placed from one robot's
/// dead-reckoned poses share that dead reckoning's drift, which does not average out over
/// them and cannot be told from the transform's own rotation — the generalized fit gives the
/// shared part its due weight once instead of once per point. None when the joint covariance
/// or the normal equations are singular or the sizes disagree.
pub fn fit_rigid_correlated(
    from: &[Point2<f64>],
    cov_from: &nalgebra::DMatrix<f64>,
    to: &[(Point2<f64>, Matrix2<f64>)],
    init: Isometry2<f64>,
) -> Option<(Isometry2<f64>, Matrix3<f64>)> {
    let n = from.len();
    if n < 2 || to.len() != n || cov_from.shape() != (2 * n, 2 * n) {
        return None;
    }
    let normal = |angle: f64, t: Vector2<f64>| -> Option<(Matrix3<f64>, Vector3<f64>)> {
        let rot = nalgebra::Rotation2::new(angle).into_inner();
        let mut sigma = cov_from.clone();
        let mut jac = nalgebra::DMatrix::<f64>::zeros(2 * n, 3);
        let mut r = nalgebra::DVector::<f64>::zeros(2 * n);
        for i in 0..n {
            for j in 0..n {
                let block = rot * sigma.fixed_view::<2, 2>(2 * i, 2 * j) * rot.transpose();
                sigma.fixed_view_mut::<2, 2>(2 * i, 2 * j).copy_from(&block);
            }
            let c = sigma.fixed_view::<2, 2>(2 * i, 2 * i) + to[i].1;
            sigma.fixed_view_mut::<2, 2>(2 * i, 2 * i).copy_from(&c);
            let q = rot * from[i].coords;
            let ri = to[i].0.coords - q - t;
            r.fixed_rows_mut::<2>(2 * i).copy_from(&ri);
            // ∂r/∂θ = −(d/dθ R)·from = −(−q_y, q_x); ∂r/∂t = −I
            jac.fixed_view_mut::<2, 3>(2 * i, 0)
                .copy_from(&nalgebra::Matrix2x3::new(q.y, -1.0, 0.0, -q.x, 0.0, -1.0));
        }
        let ch = sigma.cholesky()?;
        let wj = ch.solve(&jac);
        let h = jac.transpose() * &wj;
        let g = wj.transpose() * r;
        Some((
            Matrix3::from_iterator(h.iter().copied()),
            Vector3::new(g[0], g[1], g[2]),
        ))
    };
    let iso = gauss_newton(init, normal)?;
    let cov = normal(iso.rotation.angle(), iso.translation.vector)?
        .0
        .cholesky()?
        .inverse();
    Some((iso, cov))
}

/// Gauss–Newton on (θ, t) from `init` with the normal equations `normal(θ, t)` = (information,
/// gradient): at most 20 steps, until a step is below 1e-12. None when the information is not
/// positive definite or the result not finite.
fn gauss_newton(
    init: Isometry2<f64>,
    normal: impl Fn(f64, Vector2<f64>) -> Option<(Matrix3<f64>, Vector3<f64>)>,
) -> Option<Isometry2<f64>> {
    let (mut angle, mut t) = (init.rotation.angle(), init.translation.vector);
    for _ in 0..20 {
        let (h, g) = normal(angle, t)?;
        let step = h.cholesky()?.solve(&(-g));
        angle += step[0];
        t += Vector2::new(step[1], step[2]);
        if step.norm() < 1e-12 {
            break;
        }
    }
    (angle.is_finite() && t.iter().all(|v| v.is_finite())).then(|| Isometry2::new(t, angle))
}

/// The Gauss–Newton iteration of [`fit_rigid_weighted`]; also returns its normal equations
/// (information matrix and gradient at a given θ, t).
#[allow(clippy::type_complexity)]
fn weighted_gauss_newton<'a>(
    from: &'a [(Point2<f64>, Matrix2<f64>)],
    to: &'a [(Point2<f64>, Matrix2<f64>)],
    init: Isometry2<f64>,
) -> Option<(
    Isometry2<f64>,
    impl Fn(f64, Vector2<f64>) -> Option<(Matrix3<f64>, Vector3<f64>)> + 'a,
)> {
    if from.len() < 2 || from.len() != to.len() {
        return None;
    }
    let normal = move |angle: f64, t: Vector2<f64>| -> Option<(Matrix3<f64>, Vector3<f64>)> {
        let rot = nalgebra::Rotation2::new(angle).into_inner();
        let (mut h, mut g) = (Matrix3::<f64>::zeros(), Vector3::<f64>::zeros());
        for ((pf, cf), (pt, ct)) in from.iter().zip(to) {
            let q = rot * pf.coords;
            let r = pt.coords - q - t;
            let w = (rot * cf * rot.transpose() + ct).try_inverse()?;
            // ∂r/∂θ = −(d/dθ R)·from = −(−q_y, q_x); ∂r/∂t = −I
            let j = nalgebra::Matrix2x3::new(q.y, -1.0, 0.0, -q.x, 0.0, -1.0);
            h += j.transpose() * w * j;
            g += j.transpose() * w * r;
        }
        Some((h, g))
    };
    gauss_newton(init, normal).map(|iso| (iso, normal))
}

/// Uniform grid over the prior candidates' bounding box for radius queries, stored as
/// compressed rows (cell offsets into one index array). The cell is at least the query
/// radius and grows when the box would need more than a few cells per candidate.
struct Grid {
    cell: f64,
    x0: f64,
    y0: f64,
    nx: usize,
    ny: usize,
    /// `items[start[c]..start[c + 1]]` are the candidates in cell c, in index order
    start: Vec<u32>,
    items: Vec<u32>,
}

/// Bounding box (x0, y0, x1, y1) of candidate means; all zero for none.
fn bounds(cands: &[Cand]) -> (f64, f64, f64, f64) {
    if cands.is_empty() {
        return (0.0, 0.0, 0.0, 0.0);
    }
    cands.iter().fold(
        (
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ),
        |(x0, y0, x1, y1), c| (x0.min(c.p.x), y0.min(c.p.y), x1.max(c.p.x), y1.max(c.p.y)),
    )
}

impl Grid {
    fn new(cands: &[Cand], cell: f64) -> Self {
        let (x0, y0, x1, y1) = bounds(cands);
        let max_cells = 4 * cands.len() + 1024;
        let mut cell = cell;
        let dims = |cell: f64| {
            (
                ((x1 - x0) / cell).floor() as usize + 1,
                ((y1 - y0) / cell).floor() as usize + 1,
            )
        };
        while {
            let (nx, ny) = dims(cell);
            nx.saturating_mul(ny) > max_cells
        } {
            cell *= 2.0;
        }
        let (nx, ny) = dims(cell);
        let key = |p: &Point2<f64>| {
            let kx = (((p.x - x0) / cell).floor() as usize).min(nx - 1);
            let ky = (((p.y - y0) / cell).floor() as usize).min(ny - 1);
            ky * nx + kx
        };
        let mut start = vec![0u32; nx * ny + 1];
        for c in cands {
            start[key(&c.p) + 1] += 1;
        }
        for k in 1..start.len() {
            start[k] += start[k - 1];
        }
        let mut fill = start.clone();
        let mut items = vec![0u32; cands.len()];
        for (i, c) in cands.iter().enumerate() {
            let k = key(&c.p);
            items[fill[k] as usize] = i as u32;
            fill[k] += 1;
        }
        Grid {
            cell,
            x0,
            y0,
            nx,
            ny,
            start,
            items,
        }
    }

    /// Indices of the candidates within `r` (≤ the cell size) of `p`, in a fixed order.
    fn near(&self, p: &Point2<f64>, r: f64, cands: &[Cand], out: &mut Vec<usize>) {
        out.clear();
        let fx = ((p.x - self.x0) / self.cell).floor();
        let fy = ((p.y - self.y0) / self.cell).floor();
        if !(fx >= -1.0 && fy >= -1.0 && fx <= self.nx as f64 && fy <= self.ny as f64) {
            return; // farther than one cell from the box (or not finite)
        }
        let (kx, ky) = (fx as i64, fy as i64);
        let r2 = r * r;
        for y in (ky - 1).max(0)..=(ky + 1).min(self.ny as i64 - 1) {
            for x in (kx - 1).max(0)..=(kx + 1).min(self.nx as i64 - 1) {
                let c = y as usize * self.nx + x as usize;
                for &i in &self.items[self.start[c] as usize..self.start[c + 1] as usize] {
                    if (cands[i as usize].p - p).norm_squared() <= r2 {
                        out.push(i as usize);
                    }
                }
            }
        }
    }
}

/// All pairs of prior candidates, counting-sorted into distance bins of width ≥ the distance
/// tolerance: building is O(P²) without a sort, and a lookup sorts only its window.
struct PairBins {
    width: f64,
    /// `pairs[start[b]..start[b + 1]]` are the pairs of bin b: (distance, i, j), i < j
    start: Vec<u32>,
    pairs: Vec<(f64, u32, u32)>,
}

impl PairBins {
    /// At most this many bins (a far outlier widens them instead of allocating more).
    const MAX_BINS: usize = 1 << 16;

    fn new(p: &[Cand], tol: f64) -> Self {
        let mut all = Vec::with_capacity(p.len() * p.len().saturating_sub(1) / 2);
        let mut max_d: f64 = 0.0;
        for i in 0..p.len() {
            for j in (i + 1)..p.len() {
                let d = (p[i].p - p[j].p).norm();
                max_d = max_d.max(d);
                all.push((d, i as u32, j as u32));
            }
        }
        let width = tol.max(1e-3).max(max_d / (Self::MAX_BINS - 1) as f64);
        let bins = (max_d / width) as usize + 1;
        let bin = |d: f64| ((d / width) as usize).min(bins - 1);
        let mut start = vec![0u32; bins + 1];
        for &(d, _, _) in &all {
            start[bin(d) + 1] += 1;
        }
        for b in 1..start.len() {
            start[b] += start[b - 1];
        }
        let mut fill = start.clone();
        let mut pairs = vec![(0.0, 0, 0); all.len()];
        for x in all {
            let b = bin(x.0);
            pairs[fill[b] as usize] = x;
            fill[b] += 1;
        }
        PairBins {
            width,
            start,
            pairs,
        }
    }

    /// The pairs whose distance is within `tol` of `d`, nearest first (ties by index).
    fn window(&self, d: f64, tol: f64, out: &mut Vec<(f64, u32, u32)>) {
        out.clear();
        let bins = self.start.len() - 1;
        let bin = |x: f64| ((x.max(0.0) / self.width) as usize).min(bins - 1);
        let (lo, hi) = (bin(d - tol), bin(d + tol));
        let range = self.start[lo] as usize..self.start[hi + 1] as usize;
        out.extend(
            self.pairs[range]
                .iter()
                .filter(|x| (x.0 - d).abs() <= tol)
                .map(|&(x, i, j)| ((x - d).abs(), i, j)),
        );
        out.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    }
}

/// ln Γ(x) for x > 0 (Lanczos, g = 7, n = 9; relative error ~1e-15).
pub fn ln_gamma(x: f64) -> f64 {
    const G: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = G[0];
    let t = x + 7.5;
    for (i, g) in G.iter().enumerate().skip(1) {
        a += g / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

fn ln_beta(a: f64, b: f64) -> f64 {
    ln_gamma(a) + ln_gamma(b) - ln_gamma(a + b)
}

/// Visibility term of eq. 18 for one correspondence: Σ over the user's (transformed) cells
/// of ln BetaBinomial(k; n, α_p + 1, β_p + 1) − ln BetaBinomial(k; n, 1, 1), where k, n are
/// the user's seen / total counts and α_p, β_p the prior's counts in the same cell.
fn visibility_llr(
    user: &Transmitter,
    prior: &Transmitter,
    map_from_agent: &Isometry2<f64>,
    grid: &HexGrid,
    max_count: f64,
) -> f64 {
    if user.visibility.is_empty() || prior.visibility.is_empty() {
        return 0.0;
    }
    let moved = transform_visibility(&user.visibility, map_from_agent, grid);
    let mut llr = 0.0;
    for (cell, u) in &moved {
        if let Some(p) = prior.visibility.get(cell) {
            // at most `max_count` effective observations per cell (see MatchConfig)
            let n = u.alpha + u.beta;
            let scale = if n > max_count { max_count / n } else { 1.0 };
            let (k, m) = (u.alpha * scale, u.beta * scale);
            let (a, b) = (p.alpha + 1.0, p.beta + 1.0);
            llr += ln_beta(k + a, m + b)
                - ln_beta(a, b)
                - (ln_beta(k + 1.0, m + 1.0) - ln_beta(1.0, 1.0));
        }
    }
    llr
}

struct Hypothesis {
    iso: Isometry2<f64>,
    pairs: Vec<(usize, usize)>, // candidate indices (user, prior)
    residuals: Vec<f64>,
    /// per pair: the area of its uncertainty ellipse through the residual, π·d²·√det S (m²)
    ellipse_m2: Vec<f64>,
    loc_score: f64,
}

/// The squared Mahalanobis distance between user candidate `uc` (moved to `q`, covariance
/// `cov_u` rotated into the map frame) and prior candidate `pc`, when they are b-compatible
/// and inside the χ² gate.
fn gated(
    uc: &Cand,
    q: &Point2<f64>,
    cov_u: &nalgebra::Matrix2<f64>,
    pc: &Cand,
    cfg: &MatchConfig,
) -> Option<f64> {
    if !b_compatible(uc, pc, cfg) {
        return None;
    }
    let r = pc.p - q;
    let d2 = (cov_u + pc.cov).cholesky()?.solve(&r).dot(&r);
    (d2 <= cfg.inlier_gate_chi2).then_some(d2)
}

/// One-to-one inlier pairs `(user, prior)` under `iso`, greedy by Mahalanobis distance, sorted.
fn inlier_pairs(
    iso: &Isometry2<f64>,
    u: &[Cand],
    p: &[Cand],
    grid: &Grid,
    cfg: &MatchConfig,
) -> Vec<(usize, usize)> {
    let mut near = Vec::new();
    let mut cand_pairs: Vec<(f64, usize, usize)> = Vec::new();
    let rot = iso.rotation.to_rotation_matrix().into_inner();
    for (i, uc) in u.iter().enumerate() {
        let q = iso * uc.p;
        let cov_u = rot * uc.cov * rot.transpose();
        grid.near(&q, cfg.inlier_threshold_m, p, &mut near);
        for &j in &near {
            if let Some(d2) = gated(uc, &q, &cov_u, &p[j], cfg) {
                cand_pairs.push((d2, i, j));
            }
        }
    }
    cand_pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let (mut used_u, mut used_p) = (vec![false; u.len()], vec![false; p.len()]);
    let mut pairs = Vec::new();
    for (_, i, j) in cand_pairs {
        if !used_u[i] && !used_p[j] {
            used_u[i] = true;
            used_p[j] = true;
            pairs.push((i, j));
        }
    }
    pairs.sort_unstable();
    pairs
}

/// Pre-screen of a hypothesis: how many user candidates have some gated, b-compatible prior
/// candidate under `iso` (an upper bound of the one-to-one inlier count), or None as soon as
/// fewer than `need` remain possible.
fn quick_count(
    iso: &Isometry2<f64>,
    u: &[Cand],
    p: &[Cand],
    grid: &Grid,
    cfg: &MatchConfig,
    need: usize,
) -> Option<usize> {
    let mut near = Vec::new();
    let rot = iso.rotation.to_rotation_matrix().into_inner();
    let mut count = 0;
    for (i, uc) in u.iter().enumerate() {
        if count + (u.len() - i) < need {
            return None;
        }
        let q = iso * uc.p;
        grid.near(&q, cfg.inlier_threshold_m, p, &mut near);
        let cov_u = rot * uc.cov * rot.transpose();
        let hit = near
            .iter()
            .any(|&j| gated(uc, &q, &cov_u, &p[j], cfg).is_some());
        count += usize::from(hit);
    }
    (count >= need).then_some(count)
}

/// The visibility term of eq. 18 for the pairs of a hypothesis, times its weight (0 when
/// the term is off).
#[allow(clippy::too_many_arguments)]
fn visibility_score(
    iso: &Isometry2<f64>,
    pairs: &[(usize, usize)],
    user: &TransmitterMap,
    prior: &TransmitterMap,
    u: &[Cand],
    p: &[Cand],
    hex: &HexGrid,
    cfg: &MatchConfig,
) -> f64 {
    if !cfg.use_visibility {
        return 0.0;
    }
    pairs
        .iter()
        .map(|&(i, j)| {
            visibility_llr(
                &user.transmitters()[u[i].index],
                &prior.transmitters()[p[j].index],
                iso,
                hex,
                cfg.visibility_max_count,
            )
        })
        .sum::<f64>()
        * cfg.visibility_weight
}

/// How a given transform explains `user` against `prior`, scored as `match_maps` scores a
/// hypothesis (one-to-one inliers under the same gates, location + visibility term) but
/// without refitting it — to check whether an earlier match still holds and to compare it
/// with a new one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TransformScore {
    /// one-to-one inlier pairs under the transform
    pub inliers: usize,
    /// comparable with [`MatchResult::score`] of a match between the same two maps
    pub score: f64,
}

/// Scores `map_from_agent` on `user` against `prior` (see [`TransformScore`]).
pub fn score_transform(
    user: &TransmitterMap,
    prior: &TransmitterMap,
    map_from_agent: &Isometry2<f64>,
    cfg: &MatchConfig,
) -> TransformScore {
    let u = candidates(user, cfg);
    let p = candidates(prior, cfg);
    if u.is_empty() || p.is_empty() {
        return TransformScore {
            inliers: 0,
            score: 0.0,
        };
    }
    let grid = Grid::new(&p, cfg.inlier_threshold_m.max(1e-3));
    let pairs = inlier_pairs(map_from_agent, &u, &p, &grid, cfg);
    let (d2, sqrt_det) = pair_distances(map_from_agent, &pairs, &u, &p);
    let loc = location_score(&d2, &sqrt_det, ln_clutter_area(&p, cfg), cfg);
    let vis = visibility_score(
        map_from_agent,
        &pairs,
        user,
        prior,
        &u,
        &p,
        &prior.grid(),
        cfg,
    );
    TransformScore {
        inliers: pairs.len(),
        score: loc + vis,
    }
}

/// Per pair `(user, prior)` under `iso`: the squared Mahalanobis distance and √det of the
/// pair covariance `R·C_u·Rᵀ + C_p`.
fn pair_distances(
    iso: &Isometry2<f64>,
    pairs: &[(usize, usize)],
    u: &[Cand],
    p: &[Cand],
) -> (Vec<f64>, Vec<f64>) {
    let rot = iso.rotation.to_rotation_matrix().into_inner();
    pairs
        .iter()
        .map(|&(i, j)| {
            let r = p[j].p - iso * u[i].p;
            let s = rot * u[i].cov * rot.transpose() + p[j].cov;
            let d2 = s
                .cholesky()
                .map(|c| r.dot(&c.solve(&r)))
                .unwrap_or(f64::INFINITY);
            (d2, s.determinant().max(0.0).sqrt())
        })
        .unzip()
}

/// ln of the clutter area: the prior candidates' bounding box widened by the inlier
/// threshold on every side (as in `false_alarms`).
fn ln_clutter_area(p: &[Cand], cfg: &MatchConfig) -> f64 {
    let (x0, y0, x1, y1) = bounds(p);
    let m = 2.0 * cfg.inlier_threshold_m.max(1e-3);
    ((x1 - x0 + m) * (y1 - y0 + m)).ln()
}

/// The location term of a hypothesis (see [`LocationScore`]) from its inliers' squared
/// Mahalanobis distances `d2` and the √det of their pair covariances.
fn location_score(d2: &[f64], sqrt_det: &[f64], ln_area: f64, cfg: &MatchConfig) -> f64 {
    match cfg.location_score {
        LocationScore::Msac => d2
            .iter()
            .map(|d| 1.0 - (d / cfg.inlier_gate_chi2).min(1.0))
            .sum(),
        LocationScore::Likelihood { min_scale } => {
            let base: Vec<f64> = sqrt_det
                .iter()
                .map(|s| ln_area - (2.0 * std::f64::consts::PI * s.max(1e-300)).ln())
                .collect();
            let sum_at = |k2: f64| -> f64 {
                d2.iter()
                    .zip(&base)
                    .map(|(d, b)| (b - k2.ln() - d / (2.0 * k2)).max(0.0))
                    .sum()
            };
            // k on a log-spaced grid over [min_scale, 1], plus the untruncated optimum
            // k² = Σd²/(2n) when it lies inside
            const STEPS: usize = 32;
            let lo = min_scale.clamp(1e-3, 1.0).ln();
            let mut best = sum_at(1.0);
            for s in 0..STEPS {
                let k = (lo * s as f64 / STEPS as f64).exp();
                best = best.max(sum_at(k * k));
            }
            let n = d2.len().max(1) as f64;
            let k2 = d2.iter().sum::<f64>() / (2.0 * n);
            if k2.is_finite() && k2 >= (2.0 * lo).exp() && k2 <= 1.0 {
                best = best.max(sum_at(k2));
            }
            best
        }
    }
}

/// Collects one-to-one inlier pairs under `iso` (greedy by distance) and refits.
fn local_optimize(
    iso: Isometry2<f64>,
    u: &[Cand],
    p: &[Cand],
    grid: &Grid,
    ln_area: f64,
    cfg: &MatchConfig,
) -> Option<Hypothesis> {
    let mut iso = iso;
    let mut last: Vec<(usize, usize)> = Vec::new();
    for _ in 0..10 {
        let pairs = inlier_pairs(&iso, u, p, grid, cfg);
        if pairs.len() < 3 {
            return None;
        }
        let from: Vec<Point2<f64>> = pairs.iter().map(|&(i, _)| u[i].p).collect();
        let to: Vec<Point2<f64>> = pairs.iter().map(|&(_, j)| p[j].p).collect();
        iso = fit_rigid(&from, &to)?;
        // the least-squares fit starts the covariance-weighted one (ML under both maps'
        // position covariances)
        let from_cov: Vec<_> = pairs.iter().map(|&(i, _)| (u[i].p, u[i].cov)).collect();
        let to_cov: Vec<_> = pairs.iter().map(|&(_, j)| (p[j].p, p[j].cov)).collect();
        iso = fit_rigid_weighted(&from_cov, &to_cov, iso).unwrap_or(iso);
        if pairs == last {
            break;
        }
        last = pairs;
    }
    let residuals: Vec<f64> = last
        .iter()
        .map(|&(i, j)| (iso * u[i].p - p[j].p).norm())
        .collect();
    let (d2, sqrt_det) = pair_distances(&iso, &last, u, p);
    let loc_score = location_score(&d2, &sqrt_det, ln_area, cfg);
    let ellipse_m2 = d2
        .iter()
        .zip(&sqrt_det)
        .map(|(d, s)| std::f64::consts::PI * d * s)
        .collect();
    Some(Hypothesis {
        iso,
        pairs: last,
        residuals,
        ellipse_m2,
        loc_score,
    })
}

/// Matches `user` (agent frame) against `prior` (map frame). Deterministic for a given RNG
/// state; the RNG is only used to draw user triples.
pub fn match_maps(
    user: &TransmitterMap,
    prior: &TransmitterMap,
    cfg: &MatchConfig,
    rng: &mut impl Rng,
) -> MatchResult {
    let u = candidates(user, cfg);
    let p = candidates(prior, cfg);
    if u.len() < 3 || p.len() < 3 {
        return MatchResult::rejected(
            format!(
                "too few converged transmitters: {} in the user map, {} in the prior map (3 needed)",
                u.len(),
                p.len()
            ),
            0,
        );
    }
    // Prior pairs binned by distance, for consistent-pair lookup.
    let tol = cfg.distance_tolerance_m;
    let pairs = PairBins::new(&p, tol);
    let mut window: Vec<(f64, u32, u32)> = Vec::new();
    let grid = Grid::new(&p, cfg.inlier_threshold_m.max(1e-3));
    let ln_area = ln_clutter_area(&p, cfg);
    let hex = prior.grid();

    let mut best: Option<(f64, f64, Hypothesis)> = None;
    let mut best_count = 0usize;
    let mut third = Vec::new();
    let mut tests = 0usize;
    let mut needed = cfg.max_iterations;
    let mut it = 0;
    while it < needed.min(cfg.max_iterations) {
        it += 1;
        // draw a user triple with distinct members
        let a = rng.random_range(0..u.len());
        let mut b = rng.random_range(0..u.len() - 1);
        if b >= a {
            b += 1;
        }
        let mut c = rng.random_range(0..u.len() - 2);
        for x in [a.min(b), a.max(b)] {
            if c >= x {
                c += 1;
            }
        }
        let (ua, ub, uc) = (&u[a], &u[b], &u[c]);
        let dab = (ua.p - ub.p).norm();
        let dac = (ua.p - uc.p).norm();
        let dbc = (ub.p - uc.p).norm();
        if dab < tol || dac < tol || dbc < tol {
            continue; // degenerate triple
        }
        // prior pairs whose distance agrees with dab, nearest first
        pairs.window(dab, tol, &mut window);
        let mut tried = 0;
        for &(_, i, j) in &window {
            if tried >= cfg.max_hypotheses_per_sample {
                break;
            }
            let (i, j) = (i as usize, j as usize);
            for (pa, pb) in [(i, j), (j, i)] {
                if !b_compatible(ua, &p[pa], cfg) || !b_compatible(ub, &p[pb], cfg) {
                    continue;
                }
                // the third member must lie where the first two pairs put it
                let Some(two) = fit_rigid(&[ua.p, ub.p], &[p[pa].p, p[pb].p]) else {
                    continue;
                };
                grid.near(&(two * uc.p), tol, &p, &mut third);
                for &k in &third {
                    let pc = &p[k];
                    if k == pa || k == pb || !b_compatible(uc, pc, cfg) {
                        continue;
                    }
                    if ((p[pa].p - pc.p).norm() - dac).abs() > tol
                        || ((p[pb].p - pc.p).norm() - dbc).abs() > tol
                    {
                        continue;
                    }
                    tried += 1;
                    tests += 1;
                    let Some(iso) = fit_rigid(&[ua.p, ub.p, uc.p], &[p[pa].p, p[pb].p, pc.p])
                    else {
                        continue;
                    };
                    // the minimal sample itself must fit (a mirror image does not)
                    if [(ua, pa), (ub, pb), (uc, k)]
                        .iter()
                        .any(|(x, y)| (iso * x.p - p[*y].p).norm() > cfg.inlier_threshold_m)
                    {
                        continue;
                    }
                    // LO-RANSAC: local optimization only for hypotheses that do at least as
                    // well as the best so far on a single pass
                    let Some(count) = quick_count(&iso, &u, &p, &grid, cfg, best_count.max(3))
                    else {
                        continue;
                    };
                    best_count = count;
                    let Some(h) = local_optimize(iso, &u, &p, &grid, ln_area, cfg) else {
                        continue;
                    };
                    let vis = visibility_score(&h.iso, &h.pairs, user, prior, &u, &p, &hex, cfg);
                    let score = h.loc_score + vis;
                    if best.as_ref().is_none_or(|b| score > b.0) {
                        // adaptive iteration count from the inlier ratio of the best hypothesis
                        let w = (h.pairs.len() as f64 / u.len() as f64).min(1.0);
                        let p_good = w.powi(3);
                        if p_good > 0.0 && p_good < 1.0 {
                            needed =
                                ((1.0 - cfg.confidence).ln() / (1.0 - p_good).ln()).ceil() as usize;
                        } else if p_good >= 1.0 {
                            needed = it;
                        }
                        best = Some((score, vis, h));
                    }
                }
            }
        }
    }
    let Some((score, vis, h)) = best else {
        return MatchResult::rejected("no consistent transmitter triple found".into(), it);
    };
    let nfa = false_alarms(&h, &u, &p, cfg, tests.max(1));
    let mirror = mirror_excess_chi2(&h, &u, &p);
    let mut result = MatchResult {
        accepted: h.pairs.len() >= cfg.min_inliers
            && nfa <= cfg.max_false_alarms
            && mirror >= cfg.min_mirror_chi2,
        map_from_agent: h.iso,
        correspondences: h
            .pairs
            .iter()
            .map(|&(i, j)| (u[i].index, p[j].index))
            .collect(),
        residuals_m: h.residuals,
        inliers: h.pairs.len(),
        score,
        visibility_score: vis,
        reason: None,
        iterations: it,
    };
    if h.pairs.len() < cfg.min_inliers {
        result.reason = Some(format!(
            "only {} inliers, {} needed",
            result.inliers, cfg.min_inliers
        ));
    } else if mirror < cfg.min_mirror_chi2 {
        result.reason = Some(format!(
            "the {} inliers are nearly collinear: a mirror image fits them almost as well (χ² worse by {mirror:.1} < {})",
            result.inliers, cfg.min_mirror_chi2
        ));
    } else if !result.accepted {
        result.reason = Some(format!(
            "{} inliers could be chance in maps this dense (expected false alarms {nfa:.2e} > {:.0e})",
            result.inliers, cfg.max_false_alarms
        ));
    }
    result
}

/// Summed squared Mahalanobis distance of the inlier pairs under `iso`, each pair with the
/// covariance `R·C_u·Rᵀ + C_p` (`reflect`: the user points and covariances mirrored at the
/// x axis first).
fn pair_chi2(
    iso: &Isometry2<f64>,
    pairs: &[(usize, usize)],
    u: &[Cand],
    p: &[Cand],
    reflect: bool,
) -> f64 {
    let m = nalgebra::Matrix2::new(1.0, 0.0, 0.0, if reflect { -1.0 } else { 1.0 });
    let rot = iso.rotation.to_rotation_matrix().into_inner();
    pairs
        .iter()
        .map(|&(i, j)| {
            let q = iso * Point2::from(m * u[i].p.coords);
            let cov = rot * m * u[i].cov * m.transpose() * rot.transpose() + p[j].cov;
            let r = p[j].p - q;
            cov.cholesky()
                .map(|c| r.dot(&c.solve(&r)))
                .unwrap_or(f64::INFINITY)
        })
        .sum()
}

/// How much worse the best mirror image of the inlier pairs fits than the hypothesis itself
/// (χ² difference): the user points reflected at the x axis, then the least-squares proper
/// rigid fit onto their prior partners — together the best improper rigid motion.
fn mirror_excess_chi2(h: &Hypothesis, u: &[Cand], p: &[Cand]) -> f64 {
    let from: Vec<Point2<f64>> = h
        .pairs
        .iter()
        .map(|&(i, _)| Point2::new(u[i].p.x, -u[i].p.y))
        .collect();
    let to: Vec<Point2<f64>> = h.pairs.iter().map(|&(_, j)| p[j].p).collect();
    // None: every rotation fits equally well (e.g. a reflected square onto itself), so the
    // centroids aligned without rotation is as good as any
    let mirror = fit_rigid(&from, &to).unwrap_or_else(|| {
        let n = from.len().max(1) as f64;
        let cf = from.iter().fold(Vector2::zeros(), |a, q| a + q.coords) / n;
        let ct = to.iter().fold(Vector2::zeros(), |a, q| a + q.coords) / n;
        Isometry2::new(ct - cf, 0.0)
    });
    pair_chi2(&mirror, &h.pairs, u, p, true) - pair_chi2(&h.iso, &h.pairs, u, p, false)
}

/// Expected number of false alarms of a hypothesis (a-contrario test in the manner of ORSA,
/// Moisan & Stival 2004): how many of the `tests` hypotheses tried would, in maps without a
/// common part, fit at least as well by chance.
///
/// Null model: the prior candidates are spread uniformly over their bounding box (density ρ)
/// and independent of the user's. A user transmitter meets a chance partner at least as close
/// as inlier i (inside the ellipse of area e_i through its residual) and b-compatible with it
/// (fraction f_i of the prior candidates) with probability q_i = 1 − exp(−ρ·e_i·f_i). Sorting
/// the inliers by q, the three best are taken as the minimal sample: two pairs fix a rigid
/// transform and carry no evidence; the third was chosen among the prior transmitters whose
/// distances to the first two agree within `distance_tolerance_m`, so it counts with
/// q₃ = e₃ / (2·tol)². For j of the remaining inliers with q ≤ q_(3+j), the chance is the
/// Binomial tail P(X ≥ j), X ~ Bin(n − 3, q_(3+j)), n the user candidates the hypothesis
/// puts inside the prior's box. The false-alarm count is tests · (n − 3) · q₃ · min_j of
/// that tail (the factor n − 3 pays for choosing j).
fn false_alarms(h: &Hypothesis, u: &[Cand], p: &[Cand], cfg: &MatchConfig, tests: usize) -> f64 {
    let (x0, y0, x1, y1) = bounds(p);
    let margin = cfg.inlier_threshold_m;
    let (x0, x1, y0, y1) = (x0 - margin, x1 + margin, y0 - margin, y1 + margin);
    let density = p.len() as f64 / ((x1 - x0) * (y1 - y0));
    let inside = u
        .iter()
        .map(|c| h.iso * c.p)
        .filter(|q| q.x >= x0 && q.x <= x1 && q.y >= y0 && q.y <= y1)
        .count();
    let k = h.pairs.len();
    if k <= 3 {
        return f64::INFINITY;
    }
    let n = inside.max(k) - 3;
    let mut q: Vec<(f64, f64)> = h
        .pairs
        .iter()
        .zip(&h.ellipse_m2)
        .map(|(&(i, _), &e)| {
            let f =
                p.iter().filter(|c| b_compatible(&u[i], c, cfg)).count() as f64 / p.len() as f64;
            ((1.0 - (-density * e * f).exp()).clamp(1e-300, 1.0), e)
        })
        .collect();
    q.sort_by(|a, b| a.0.total_cmp(&b.0));
    // The third sample member was chosen among the prior transmitters whose distances to the
    // first two agree within the tolerance — a region of at least (2·tol)² — so only its fine
    // residual within that region is evidence.
    let ln_third = (q[2].1 / (4.0 * cfg.distance_tolerance_m.powi(2)))
        .clamp(1e-300, 1.0)
        .ln();
    let best_tail = (1..=k - 3)
        .map(|j| ln_binomial_tail(n, j, q[2 + j].0))
        .fold(0.0, f64::min);
    if std::env::var_os("ECHOMAP_NFA_DEBUG").is_some() {
        eprintln!(
            "nfa: tests {tests} n {n} k {k} density {density:.4} q {q:?} best {best_tail:.2}"
        );
    }
    tests as f64 * n as f64 * (ln_third + best_tail).exp()
}

/// ln P(X ≥ k) for X ~ Binomial(n, q), summed in log space.
fn ln_binomial_tail(n: usize, k: usize, q: f64) -> f64 {
    if k > n {
        return f64::NEG_INFINITY;
    }
    if q >= 1.0 {
        return 0.0;
    }
    let ln_c = |i: usize| {
        ln_gamma(n as f64 + 1.0) - ln_gamma(i as f64 + 1.0) - ln_gamma((n - i) as f64 + 1.0)
    };
    let ln_terms: Vec<f64> = (k..=n)
        .map(|i| ln_c(i) + i as f64 * q.ln() + (n - i) as f64 * (-q).ln_1p())
        .collect();
    let max = ln_terms.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    max + ln_terms.iter().map(|t| (t - max).exp()).sum::<f64>().ln()
}

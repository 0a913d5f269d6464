//! A prior map in the agent's local frame (Ulmschneider et al. 2021 §III): the crowd-sourced
//! map as the filter uses it once a match has put it into the agent's frame — its
//! transmitters offered as association candidates for new tracks (Ulmschneider et al. 2021
//! eq. 19), with the matched transform's uncertainty. [`super::prior::PriorTracker`] decides
//! when to (re)place it; the filter only reads it.

use super::model::{Comp, mixture_moments};
use super::srckf::SqrtGaussian;
use echomap_shared::map::TransmitterMap;
use echomap_shared::{Beta, HexCell, HexGrid};
use nalgebra::{Isometry2, Matrix3, Point2, Vector3};
use std::collections::{BTreeMap, BTreeSet};
use std::ops::AddAssign;

/// One prior-map transmitter, in the agent frame.
#[derive(Debug, Clone)]
pub struct PriorTx {
    /// its id in the prior map
    pub id: String,
    pub comps: Vec<Comp>,
    pub existence: f64,
    visibility: BTreeMap<HexCell, Beta>,
    /// the agent's own map already holds this transmitter (a correspondence of the match
    /// that placed the prior): it is no candidate for new tracks, which would otherwise
    /// start a second copy of a transmitter the agent still knows and take the prior's
    /// version instead of associating with its own when it sees it again
    pub claimed: bool,
    /// mean and covariance of its state (agent frame), for `FilterConfig::prior_shadow_chi2`
    pub moments: Option<(Vector3<f64>, Matrix3<f64>)>,
}

/// Uncertainty of an estimated rigid transform, for inflating what it carries: a point at
/// `p` (agent frame) gets `var_t·I + var_theta·‖p − centroid‖²·u⊥u⊥ᵀ` added to its position
/// covariance (u⊥ perpendicular to p − centroid) — the first-order covariance of a 2D rigid
/// least-squares fit with isotropic residuals.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TransformUncertainty {
    pub centroid: Point2<f64>,
    pub var_t: f64,
    pub var_theta: f64,
}

impl TransformUncertainty {
    /// From the agent-frame positions of a match's inliers and their residuals (m): residual
    /// variance σ² = Σr²/(n − 3) (at least `floor_m²`), var_t = σ²/n, var_θ = σ²/Σ‖pᵢ − c‖².
    pub fn from_fit(points: &[Point2<f64>], residuals_m: &[f64], floor_m: f64) -> Option<Self> {
        let n = points.len();
        if n < 3 || residuals_m.len() != n {
            return None;
        }
        let centroid = Point2::from(
            points
                .iter()
                .map(|p| p.coords)
                .sum::<nalgebra::Vector2<f64>>()
                / n as f64,
        );
        let spread: f64 = points.iter().map(|p| (p - centroid).norm_squared()).sum();
        let sigma2 = (residuals_m.iter().map(|r| r * r).sum::<f64>() / (n as f64 - 3.0).max(1.0))
            .max(floor_m * floor_m);
        (spread > 0.0).then(|| TransformUncertainty {
            centroid,
            var_t: sigma2 / n as f64,
            var_theta: sigma2 / spread,
        })
    }

    /// Raises the variances to at least those of a fit `map_from_agent` with covariance `cov`
    /// over (θ, t_x, t_y) (`fit_rigid_weighted_cov`): var_θ to `cov_θθ`, var_t to half the
    /// trace of the covariance of where the fit puts the centroid, `J cov Jᵀ` with
    /// J = [∂(R·c)/∂θ | I].
    pub fn widen_to_fit(&mut self, map_from_agent: &Isometry2<f64>, cov: &Matrix3<f64>) {
        let rc = map_from_agent.rotation * self.centroid.coords;
        let j = nalgebra::Matrix2x3::new(-rc.y, 1.0, 0.0, rc.x, 0.0, 1.0);
        let at_centroid = j * cov * j.transpose();
        self.var_theta = self.var_theta.max(cov[(0, 0)]);
        self.var_t = self.var_t.max(0.5 * at_centroid.trace());
    }

    /// The same spread with every variance multiplied by `factor²`.
    pub fn dispersed(&self, factor: f64) -> Self {
        TransformUncertainty {
            centroid: self.centroid,
            var_t: self.var_t * factor * factor,
            var_theta: self.var_theta * factor * factor,
        }
    }

    /// Std (m) of where the transform puts the point `at`: √(var_t + var_θ·‖at − c‖²).
    pub fn std_at(&self, at: &Point2<f64>) -> f64 {
        (self.var_t + self.var_theta * (at - self.centroid).norm_squared()).sqrt()
    }

    fn extra_cov(&self, at: &Point2<f64>) -> nalgebra::Matrix2<f64> {
        let d = at - self.centroid;
        let perp = nalgebra::Vector2::new(-d.y, d.x);
        nalgebra::Matrix2::identity() * self.var_t + perp * perp.transpose() * self.var_theta
    }
}

/// The prior map's transmitters expressed in the agent frame.
#[derive(Debug, Clone)]
pub struct Prior {
    pub agent_from_map: Isometry2<f64>,
    pub txs: Vec<PriorTx>,
    /// when set, every particle draws its own correction of `agent_from_map` from this
    /// spread (see `Filter::set_prior`) instead of the covariances being inflated by it
    pub spread: Option<TransformUncertainty>,
    grid: HexGrid,
    visibility_prior: (f64, f64),
}

impl Prior {
    /// Transforms `map` (map frame) into the agent frame, adding the transform's uncertainty
    /// (when given) to every component. Transmitters whose components are not usable as
    /// square-root Gaussians are left out.
    pub fn new(
        map: &TransmitterMap,
        agent_from_map: Isometry2<f64>,
        uncertainty: Option<&TransformUncertainty>,
        floor_m: f64,
        visibility_prior: (f64, f64),
    ) -> Self {
        let local = map.transformed(&agent_from_map);
        let txs = local
            .transmitters()
            .iter()
            .filter_map(|t| {
                let comps: Vec<Comp> = t
                    .components
                    .iter()
                    .filter_map(|c| {
                        let mut cov = c.cov;
                        cov[(0, 0)] += floor_m * floor_m;
                        cov[(1, 1)] += floor_m * floor_m;
                        if let Some(u) = uncertainty {
                            let extra = u.extra_cov(&Point2::new(c.mean.x, c.mean.y));
                            cov.fixed_view_mut::<2, 2>(0, 0).add_assign(&extra);
                        }
                        SqrtGaussian::from_cov(c.mean, &cov).map(|g| Comp {
                            weight: c.weight,
                            g,
                        })
                    })
                    .collect();
                if comps.len() != t.components.len() {
                    return None;
                }
                Some(PriorTx {
                    id: t.id.clone(),
                    moments: mixture_moments(&comps),
                    comps,
                    existence: t.existence,
                    visibility: t.visibility.clone(),
                    claimed: false,
                })
            })
            .collect();
        Prior {
            agent_from_map,
            txs,
            spread: None,
            grid: HexGrid::new(local.hex_size_m()),
            visibility_prior,
        }
    }

    /// Marks the prior transmitters with these ids (prior map ids) as held by the agent.
    pub fn claim<'a>(&mut self, ids: impl IntoIterator<Item = &'a str>) {
        let ids: BTreeSet<&str> = ids.into_iter().collect();
        for t in &mut self.txs {
            if ids.contains(t.id.as_str()) {
                t.claimed = true;
            }
        }
    }

    /// Visibility term of eq. 19 for prior transmitter `idx` at `at` (agent frame): the mean
    /// of Beta(α + ν, β + ν̄) of the prior's counts in that hexagon.
    pub fn visibility(&self, idx: usize, at: &Point2<f64>) -> f64 {
        let cell = self.grid.cell_of(at);
        let (a, b) = self.txs[idx]
            .visibility
            .get(&cell)
            .map(|b| (b.alpha, b.beta))
            .unwrap_or((0.0, 0.0));
        let (nu, nubar) = self.visibility_prior;
        (a + nu) / (a + b + nu + nubar)
    }
}

/// What the prior tracker decided after a filter step, for the filter to carry out
/// ([`super::Filter::apply_prior_update`]).
#[derive(Debug, Default)]
pub struct PriorUpdate {
    /// `Some(Some(p))`: use `p` from now on; `Some(None)`: stop using the prior (transmitters
    /// already taken over stay the particles' own); `None`: leave it as it is
    pub prior: Option<Option<Prior>>,
    /// `(track, index into the prior in use after `prior` is applied)` pairs whose prior
    /// transmitter is fused into the particles' own transmitter of that track
    pub fuse: Vec<(u64, usize)>,
    /// χ² gate of the fusion (the matcher's inlier gate)
    pub fuse_gate_chi2: f64,
}

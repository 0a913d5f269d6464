//! The RBGSPF core (Gentner et al. 2016 Algorithm 1): predict user particles, update every transmitter
//! mixture with its measurement, weight particles, associate new tracks, resample.
//!
//! Weights, in log space: component weights `w_c ∝ w_c · N(z; ẑ_c, P_zz,c)` (eq. 46) and
//! particle weights `w_i ∝ w_i · Σ_c w_c N(z; ẑ_c, P_zz,c)` over every measured transmitter
//! (eq. 45). Particles are processed in parallel with rayon; each particle draws from its own
//! ChaCha stream derived from (seed, step, particle index), and all reductions run in
//! particle order, so a run is identical for any thread count. Resampled particles share
//! unchanged transmitters through `Arc` (copy-on-write with `Arc::make_mut`).

use super::config::{Association, FilterConfig};
use super::model::{
    Comp, Pose, h_toa, h_toa_aoa, initialize, mixture_moments, residual_toa, residual_toa_aoa,
};
use super::prior_map::{Prior, PriorUpdate};
use super::srckf::{self, SqrtGaussian};
use super::visibility::Visibility;
use super::vonmises;
use echomap_shared::log::{Measurement, Snapshot};
use echomap_shared::mixture::{self, Component};
use echomap_shared::wrap_angle;
use nalgebra::{Matrix1, Matrix2, Matrix3, Point2, Vector1, Vector2, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rayon::prelude::*;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Arc;

/// One transmitter of one particle.
#[derive(Debug, Clone)]
pub struct TxState {
    /// dense index of the identity (the track that created it)
    pub identity: u32,
    pub comps: Vec<Comp>,
    /// distance this particle walked while the transmitter was visible (Ulmschneider et al. 2021 eq. 21)
    pub reliability_m: f64,
    /// started from a prior-map transmitter under the transform in use
    pub from_prior: bool,
    /// the detection it was started from (None for a prior copy): `Filter::fuse_prior`
    /// measures how much better the crowd's estimate is predicted now than by the wide
    /// mixture started then (the Occam factor of the fusion)
    pub birth: Option<Birth>,
}

/// The first detection of a transmitter and the particle's pose then: enough to rebuild the
/// mixture it started from (`initialize` is deterministic), at a few words per transmitter.
#[derive(Debug, Clone, Copy)]
pub struct Birth {
    pose: Pose,
    d: f64,
    aoa: Option<f64>,
    sd: f64,
    sa: f64,
}

impl Birth {
    fn of(pose: &Pose, m: &Meas) -> Self {
        let (sd, sa) = m.sigmas();
        Birth {
            pose: *pose,
            d: m.d(),
            aoa: m.aoa(),
            sd,
            sa,
        }
    }

    /// The wide mixture the transmitter started from.
    fn mixture(&self, cfg: &FilterConfig) -> Vec<Comp> {
        initialize(cfg, &self.pose, self.d, self.aoa, self.sd, self.sa)
    }
}

#[derive(Debug, Clone)]
pub struct Particle {
    pub pose: Pose,
    pub log_w: f64,
    pub txs: Vec<Arc<TxState>>,
    /// active track id → index into `txs`
    pub bound: Vec<(u64, u32)>,
    /// prior-map transmitters (indices into the prior) this particle has taken over
    pub prior_used: Vec<u32>,
    /// this particle's own draw of the prior's transform (a static parameter of the
    /// particle, drawn when the prior is set; None = the transform as matched)
    pub prior_frame: Option<FrameDelta>,
    /// new tracks whose association is still open (`association_window` > 1)
    pub pending: Vec<Pending>,
}

/// A new track on probation: bound to a tentative new transmitter (`slot`) while the gated
/// old and prior-map transmitters are updated with its detections alongside.
#[derive(Debug, Clone)]
pub struct Pending {
    track: u64,
    slot: u32,
    seen: usize,
    /// detections after which the association is decided
    window: usize,
    /// ln p(z₁..z_seen | new transmitter): ln p₀ for the first detection, then the tentative
    /// transmitter's predictive likelihoods
    ev_new: f64,
    cands: Vec<PendingCand>,
}

#[derive(Debug, Clone)]
struct PendingCand {
    source: CandSource,
    /// the candidate's mixture (agent frame) updated with the track's detections
    comps: Vec<Comp>,
    /// ln p(z₁..z_seen | candidate) including the visibility term of the first detection
    ev: f64,
}

/// What a pending track may turn out to be.
#[derive(Debug, Clone, Copy, PartialEq)]
enum CandSource {
    /// one of the particle's own transmitters (slot)
    Old(u32),
    /// a prior-map transmitter (index into the prior)
    Prior(u32),
}

/// A small rigid motion of the agent frame, `D(p) = c + R(δθ)·(p − c) + δt`: one particle's
/// correction of the matched transform `agent_from_map`, so that the prior transmitters sit at
/// `D(agent_from_map(p_map))` for that particle. Evaluating a prior transmitter from the
/// particle's pose equals evaluating the untransformed one from `D⁻¹(pose)` (ranges and
/// angles of arrival are invariant under a rigid motion of both), which costs nothing per
/// candidate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameDelta {
    pub centroid: Point2<f64>,
    pub d_theta: f64,
    pub d_t: Vector2<f64>,
}

impl FrameDelta {
    /// `D⁻¹` applied to a pose (position and heading).
    pub(crate) fn inverse_pose(&self, pose: &Pose) -> Pose {
        let (s, c) = (-self.d_theta).sin_cos();
        let (x, y) = (
            pose.x - self.centroid.x - self.d_t.x,
            pose.y - self.centroid.y - self.d_t.y,
        );
        Pose {
            x: self.centroid.x + c * x - s * y,
            y: self.centroid.y + s * x + c * y,
            heading: wrap_angle(pose.heading - self.d_theta),
            speed: pose.speed,
        }
    }

    /// `D` applied to a mixture: means moved, x/y covariance blocks rotated (b is invariant).
    pub(crate) fn apply(&self, comps: &[Comp]) -> Vec<Comp> {
        let (s, c) = self.d_theta.sin_cos();
        let r = nalgebra::Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0);
        comps
            .iter()
            .filter_map(|k| {
                let m = k.g.mean;
                let (x, y) = (m.x - self.centroid.x, m.y - self.centroid.y);
                let mean = nalgebra::Vector3::new(
                    self.centroid.x + c * x - s * y + self.d_t.x,
                    self.centroid.y + s * x + c * y + self.d_t.y,
                    m.z,
                );
                let cov = r * k.g.cov() * r.transpose();
                SqrtGaussian::from_cov(mean, &cov).map(|g| Comp {
                    weight: k.weight,
                    g,
                })
            })
            .collect()
    }
}

/// Identity of a transmitter: the track id that created it.
#[derive(Debug, Clone)]
pub struct Identity {
    pub track: u64,
}

/// Summary of one filter step.
#[derive(Debug, Clone, PartialEq)]
pub struct StepStats {
    pub t: f64,
    pub x: f64,
    pub y: f64,
    pub ess: f64,
    pub resampled: bool,
    pub transmitters: f64,
    pub components: f64,
    /// distance travelled by the weighted-mean estimate (m)
    pub traveled_m: f64,
    /// ln p(z₁..z_t): the summed log of every snapshot's evidence, the particles' mean
    /// likelihood of its detections (association included), plus for every fusion of a prior
    /// transmitter its Occam factor (see `Filter::fuse_prior`)
    pub log_evidence: f64,
}

#[derive(Debug)]
pub struct Filter {
    cfg: FilterConfig,
    aoa: bool,
    particles: Vec<Particle>,
    identities: Vec<Identity>,
    track_identity: HashMap<u64, u32>,
    /// time each track was last detected
    last_seen: HashMap<u64, f64>,
    visibility: Visibility,
    step: usize,
    prev_t: Option<f64>,
    traveled: f64,
    last_mean: Point2<f64>,
    log_evidence: f64,
    /// the prior map in the agent frame, once matched
    prior: Option<Arc<Prior>>,
}

/// Per-measurement noise factor and the measurement as a vector.
enum Meas {
    ToaAoa {
        z: Vector2<f64>,
        r_sqrt: Matrix2<f64>,
    },
    Toa {
        z: Vector1<f64>,
        r_sqrt: Matrix1<f64>,
    },
}

impl Meas {
    fn new(m: &Measurement, cfg: &FilterConfig, aoa: bool) -> Self {
        let (sd, sa) = cfg.noise.std(m.snr_db);
        match (aoa, m.aoa) {
            (true, Some(a)) => Meas::ToaAoa {
                z: Vector2::new(m.d, a),
                r_sqrt: Matrix2::new(sd, 0.0, 0.0, sa),
            },
            _ => Meas::Toa {
                z: Vector1::new(m.d),
                r_sqrt: Matrix1::new(sd),
            },
        }
    }

    fn sigmas(&self) -> (f64, f64) {
        match self {
            Meas::ToaAoa { r_sqrt, .. } => (r_sqrt[(0, 0)], r_sqrt[(1, 1)]),
            Meas::Toa { r_sqrt, .. } => (r_sqrt[(0, 0)], std::f64::consts::PI),
        }
    }

    /// Updates one component; returns the posterior and ln N(z; ẑ, P_zz).
    fn update(&self, pose: &Pose, g: &SqrtGaussian) -> Option<srckf::Updated> {
        match self {
            Meas::ToaAoa { z, r_sqrt } => {
                srckf::update(g, z, r_sqrt, |x| h_toa_aoa(pose, x), residual_toa_aoa)
            }
            Meas::Toa { z, r_sqrt } => {
                srckf::update(g, z, r_sqrt, |x| h_toa(pose, x), residual_toa)
            }
        }
    }

    /// `(ln N(z; ẑ, P_zz), squared Mahalanobis distance of the innovation)` without updating
    /// (for association likelihoods and gating).
    fn log_likelihood(&self, pose: &Pose, g: &SqrtGaussian) -> Option<(f64, f64)> {
        match self {
            Meas::ToaAoa { z, r_sqrt } => {
                let p = srckf::predict(
                    g,
                    |x| h_toa_aoa(pose, x),
                    residual_toa_aoa,
                    &(r_sqrt * r_sqrt.transpose()),
                );
                srckf::log_normal_and_mahalanobis(&residual_toa_aoa(z, &p.z_hat), &p.pzz)
            }
            Meas::Toa { z, r_sqrt } => {
                let p = srckf::predict(
                    g,
                    |x| h_toa(pose, x),
                    residual_toa,
                    &(r_sqrt * r_sqrt.transpose()),
                );
                srckf::log_normal_and_mahalanobis(&residual_toa(z, &p.z_hat), &p.pzz)
            }
        }
    }

    fn d(&self) -> f64 {
        match self {
            Meas::ToaAoa { z, .. } => z.x,
            Meas::Toa { z, .. } => z.x,
        }
    }

    fn aoa(&self) -> Option<f64> {
        match self {
            Meas::ToaAoa { z, .. } => Some(z.y),
            Meas::Toa { .. } => None,
        }
    }
}

fn log_sum_exp(v: impl Iterator<Item = f64> + Clone) -> f64 {
    let max = v.clone().fold(f64::NEG_INFINITY, f64::max);
    if max == f64::NEG_INFINITY {
        return max;
    }
    max + v.map(|x| (x - max).exp()).sum::<f64>().ln()
}

/// Updates a bound transmitter's mixture with one measurement and returns the log likelihood
/// of the measurement: ln Σ_c w_c N(z; ẑ_c, P_zz,c) (eq. 45–46), or with an outlier
/// probability ε > 0 the robust `ln((1 − ε)·L + ε·λ)`, where the mixture keeps its prior state
/// when the outlier term is the larger (a gross error then neither moves the transmitter nor
/// leaves only the particles that happen to fit it).
fn update_mixture(
    comps: &mut Vec<Comp>,
    meas: &Meas,
    pose: &Pose,
    cfg: &FilterConfig,
    merge_now: bool,
) -> f64 {
    let eps = cfg.outlier_probability;
    if eps <= 0.0 {
        return update_mixture_gaussian(comps, meas, pose, cfg, merge_now);
    }
    let prior = comps.clone();
    let ln_in = (1.0 - eps).ln() + update_mixture_gaussian(comps, meas, pose, cfg, merge_now);
    let ln_out = (eps * cfg.outlier_density).ln();
    if ln_out > ln_in {
        *comps = prior;
    }
    log_sum_exp([ln_in, ln_out].into_iter())
}

/// Updates every component of a mixture with one measurement (eq. 46) and returns the
/// log marginal likelihood ln Σ_c w_c N(z; ẑ_c, P_zz,c) (the factor of eq. 45).
fn update_mixture_gaussian(
    comps: &mut Vec<Comp>,
    meas: &Meas,
    pose: &Pose,
    cfg: &FilterConfig,
    merge_now: bool,
) -> f64 {
    // In place: each component's posterior replaces its prior; its log-likelihood goes to
    // `lls` (on the stack for up to 32 components; NaN marks a numerically degenerate
    // update, dropped below).
    let mut max_ll = f64::NEG_INFINITY;
    let mut lls = [0.0f64; 32];
    let small = comps.len() <= lls.len();
    let mut big: Vec<f64> = Vec::new();
    for (k, c) in comps.iter_mut().enumerate() {
        let ll = match meas.update(pose, &c.g) {
            Some(u) => {
                c.g = u.posterior;
                u.log_likelihood
            }
            None => f64::NAN,
        };
        if ll > max_ll {
            max_ll = ll;
        }
        if small {
            lls[k] = ll;
        } else {
            big.push(ll);
        }
    }
    if !max_ll.is_finite() {
        // Numerically degenerate (every update failed): the particle gets no support.
        return -1e3;
    }
    let lls = if small { &lls[..comps.len()] } else { &big[..] };
    // w_c ∝ w_c·N(z; ẑ_c, P_zz,c) (eq. 46) with one exp per component and one ln per
    // mixture: Σ_c w_c·exp(ll_c − max) is the marginal likelihood scaled by exp(−max)
    let mut sum = 0.0;
    for (c, ll) in comps.iter_mut().zip(lls) {
        c.weight = if ll.is_nan() {
            0.0
        } else {
            c.weight * (ll - max_ll).exp()
        };
        sum += c.weight;
    }
    // the best component has weight w·exp(0) > 0, so something is kept and sum > 0
    comps.retain(|c| c.weight > 0.0);
    for c in comps.iter_mut() {
        c.weight /= sum;
    }
    tidy(comps, cfg, merge_now);
    max_ll + sum.ln()
}

/// Pruning (ρ), merging of close components and the per-transmitter cap (Gentner et al. 2016 §4.3).
fn tidy(comps: &mut Vec<Comp>, cfg: &FilterConfig, merge_now: bool) {
    if comps.len() > 1 {
        let max_w = comps.iter().map(|c| c.weight).fold(0.0, f64::max);
        comps.retain(|c| c.weight >= cfg.prune_weight || c.weight == max_w);
        let total: f64 = comps.iter().map(|c| c.weight).sum();
        for c in comps.iter_mut() {
            c.weight /= total;
        }
    }
    let cap = if merge_now {
        1.max(close_cluster_count(comps))
    } else {
        usize::MAX
    };
    let cap = cap.min(cfg.max_components);
    if comps.len() > cap {
        let as_components: Vec<Component> = comps
            .iter()
            .map(|c| Component::new(c.weight, c.g.mean, c.g.cov()))
            .collect();
        let reduced = mixture::reduce(&as_components, cap);
        *comps = reduced
            .into_iter()
            .filter_map(|c| {
                SqrtGaussian::from_cov(c.mean, &c.cov).map(|g| Comp {
                    weight: c.weight,
                    g,
                })
            })
            .collect();
    }
}

/// Number of groups of components whose means lie within Mahalanobis distance 1 of each
/// other — merging down to this count removes duplicates that converged together.
fn close_cluster_count(comps: &[Comp]) -> usize {
    if comps.len() < 2 {
        return comps.len();
    }
    let mut leaders: Vec<usize> = Vec::new();
    for (i, c) in comps.iter().enumerate() {
        let close = leaders.iter().any(|&l| {
            let p = c.g.cov() + comps[l].g.cov();
            let d = c.g.mean - comps[l].g.mean;
            p.cholesky()
                .map(|ch| d.dot(&ch.solve(&d)) < 1.0)
                .unwrap_or(false)
        });
        if !close {
            leaders.push(i);
        }
    }
    leaders.len()
}

impl Filter {
    /// A filter whose particles all start at the local origin, heading +x, at the configured
    /// initial speed. `aoa` says whether the log carries angles of arrival.
    pub fn new(cfg: FilterConfig, aoa: bool) -> Self {
        let n = cfg.particles.max(1);
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
        let particles = (0..n)
            .map(|_| {
                let dv: f64 = rng.sample(StandardNormal);
                Particle {
                    pose: Pose {
                        x: 0.0,
                        y: 0.0,
                        heading: 0.0,
                        speed: (cfg.initial_speed_mps + cfg.initial_speed_std_mps * dv).max(0.0),
                    },
                    log_w: -(n as f64).ln(),
                    txs: Vec::new(),
                    bound: Vec::new(),
                    prior_used: Vec::new(),
                    prior_frame: None,
                    pending: Vec::new(),
                }
            })
            .collect();
        let visibility = Visibility::new(cfg.hex_size_m, cfg.visibility_prior);
        Filter {
            cfg,
            aoa,
            particles,
            identities: Vec::new(),
            track_identity: HashMap::new(),
            last_seen: HashMap::new(),
            visibility,
            step: 0,
            prev_t: None,
            traveled: 0.0,
            last_mean: Point2::origin(),
            log_evidence: 0.0,
            prior: None,
        }
    }

    /// Sets (or, with None, drops) the prior map offered to new tracks. Transmitters that
    /// particles already took over from an earlier prior stay theirs.
    ///
    /// When the prior carries a transform spread, every particle draws its own correction of
    /// the matched transform from it ([`FrameDelta`]): the transform becomes a static
    /// parameter of the particle, and the particles whose draw agrees with their own track
    /// (anchored at the known start) gain weight as they measure prior transmitters.
    pub fn set_prior(&mut self, prior: Option<Prior>) {
        let draws: Vec<Option<FrameDelta>> = match prior.as_ref().and_then(|p| p.spread) {
            Some(u) => {
                let mut rng = ChaCha8Rng::seed_from_u64(
                    self.cfg.seed ^ 0x5EED_F4A3_0000_0000 ^ self.step as u64,
                );
                (0..self.particles.len())
                    .map(|_| {
                        let n: [f64; 3] = std::array::from_fn(|_| rng.sample(StandardNormal));
                        Some(FrameDelta {
                            centroid: u.centroid,
                            d_theta: u.var_theta.sqrt() * n[0],
                            d_t: Vector2::new(n[1], n[2]) * u.var_t.sqrt(),
                        })
                    })
                    .collect()
            }
            None => vec![None; self.particles.len()],
        };
        for (p, d) in self.particles.iter_mut().zip(draws) {
            p.prior_frame = d;
        }
        self.prior = prior.map(Arc::new);
    }

    /// Carries out what the prior tracker decided; returns the particle-weighted number of
    /// fused pairs (0 without fusion).
    pub fn apply_prior_update(&mut self, update: PriorUpdate) -> f64 {
        if let Some(prior) = update.prior {
            self.set_prior(prior);
        }
        if update.fuse.is_empty() {
            0.0
        } else {
            self.fuse_prior(&update.fuse, update.fuse_gate_chi2)
        }
    }

    pub fn prior(&self) -> Option<&Prior> {
        self.prior.as_deref()
    }

    /// Fuses prior-map transmitters into the particles' own transmitters a match paired them
    /// with: `pairs` holds (track that created the own transmitter, index into the prior in
    /// use). The prior transmitter (agent frame, in the particle's own transform draw) is an
    /// independent estimate of the same state, so each own mixture becomes the product
    /// `Σ_ij w_i·w_j·N(m_j; m_i, P_i + P_j)·N(x; m_ij, P_ij)` and the particle weight takes the
    /// factor `ln Σ_ij w_i·w_j·N(m_j; m_i, P_i + P_j)` — particles whose map agrees with the
    /// crowd's gain. A pair whose factor is below the floor of `product_mixture` (the factor
    /// at the squared Mahalanobis distance `gate_chi2`) is not fused, and the particle gets that
    /// floor instead (a wrong pair neither pulls a transmitter nor leaves only the particles
    /// that happen to fit it). A fused prior transmitter is taken over: it is no candidate
    /// for the particle's new tracks. Returns the particle-weighted number of fused pairs.
    ///
    /// The filter's log evidence gains the fusion's Occam factor `ln Σ_p w_p·exp(Σ Δ)`: per
    /// fused pair `Δ = ln overlap(now) − ln overlap(at birth)`, the overlap with the crowd's
    /// estimate of the transmitter's mixture now and of the wide mixture its first detection
    /// started (`TxState::birth`). That ratio is p(detections since | crowd) / p(detections
    /// since): with the crowd's estimate as the transmitter's prior the detections after the
    /// first would have been predicted that much better (or worse). A pair beyond the gate
    /// counts `min(0, floor − ln overlap(at birth))`: evidence against the crowd, never for it.
    /// The raw factor itself is not evidence (it has units and does not compare models).
    pub fn fuse_prior(&mut self, pairs: &[(u64, usize)], gate_chi2: f64) -> f64 {
        let Some(prior) = self.prior.clone() else {
            return 0.0;
        };
        let ids: Vec<(u32, usize)> = pairs
            .iter()
            .filter(|(_, j)| *j < prior.txs.len())
            .filter_map(|(t, j)| self.track_identity.get(t).map(|&id| (id, *j)))
            .collect();
        let cfg = &self.cfg;
        let w_before = self.weights();
        // per particle: transmitters fused, and the log Occam factor of the pairs
        let fused: Vec<(usize, f64)> = self
            .particles
            .par_iter_mut()
            .map(|p| {
                let (mut n, mut occam) = (0, 0.0);
                for &(id, j) in &ids {
                    if p.prior_used.contains(&(j as u32)) {
                        continue;
                    }
                    let Some(slot) = p.txs.iter().position(|t| t.identity == id) else {
                        continue;
                    };
                    let theirs = match &p.prior_frame {
                        Some(d) => d.apply(&prior.txs[j].comps),
                        None => prior.txs[j].comps.clone(),
                    };
                    let Some((comps, ll, floor)) =
                        product_mixture(&p.txs[slot].comps, &theirs, gate_chi2)
                    else {
                        continue;
                    };
                    // how well the transmitter's first detection alone predicted the crowd's
                    // estimate (None for a copy: no Occam factor)
                    let at_birth = p.txs[slot]
                        .birth
                        .and_then(|b| product_mixture(&b.mixture(cfg), &theirs, f64::INFINITY))
                        .map(|(_, l, _)| l);
                    if ll < floor {
                        p.log_w += floor;
                        // beyond the gate the crowd disagrees: evidence against it, never for
                        occam += at_birth.map_or(0.0, |b| (floor - b).min(0.0));
                        continue;
                    }
                    p.log_w += ll;
                    occam += at_birth.map_or(0.0, |b| ll - b);
                    let tx = Arc::make_mut(&mut p.txs[slot]);
                    tx.comps = comps;
                    tidy(&mut tx.comps, cfg, true);
                    p.prior_used.push(j as u32);
                    n += 1;
                }
                (n, occam)
            })
            .collect();
        let occam = log_sum_exp(fused.iter().zip(&w_before).map(|((_, o), w)| w.ln() + o));
        if occam.is_finite() {
            self.log_evidence += occam;
        }
        let w = self.weights();
        fused.iter().zip(&w).map(|((n, _), w)| *n as f64 * w).sum()
    }

    /// Particle-weighted number of transmitters started from the prior under the transform
    /// in use (not released).
    pub fn prior_copies_held(&self) -> f64 {
        self.particles
            .iter()
            .zip(self.weights())
            .map(|(p, w)| w * p.txs.iter().filter(|t| t.from_prior).count() as f64)
            .sum()
    }

    /// Particle-weighted mean number of prior-map transmitters taken over.
    pub fn prior_transmitters_used(&self) -> f64 {
        self.particles
            .iter()
            .zip(self.weights())
            .map(|(p, w)| w * p.prior_used.len() as f64)
            .sum()
    }

    /// whether the log's measurements carry an angle of arrival
    pub fn has_aoa(&self) -> bool {
        self.aoa
    }

    pub fn config(&self) -> &FilterConfig {
        &self.cfg
    }

    pub fn particles(&self) -> &[Particle] {
        &self.particles
    }

    #[cfg(test)]
    pub(crate) fn particles_mut(&mut self) -> &mut [Particle] {
        &mut self.particles
    }

    pub fn identities(&self) -> &[Identity] {
        &self.identities
    }

    pub fn visibility(&self) -> &Visibility {
        &self.visibility
    }

    /// ln p(z₁..z_t) so far (see `StepStats::log_evidence`).
    pub fn log_evidence(&self) -> f64 {
        self.log_evidence
    }

    /// Normalized particle weights.
    pub fn weights(&self) -> Vec<f64> {
        self.weights_given(log_sum_exp(self.particles.iter().map(|p| p.log_w)))
    }

    /// The weights normalized by their log total `total`.
    fn weights_given(&self, total: f64) -> Vec<f64> {
        self.particles
            .iter()
            .map(|p| (p.log_w - total).exp())
            .collect()
    }

    /// MAE (Ulmschneider et al. 2021 eq. 27: Σ wᵢ‖p − pᵢ‖) and RMSE (√Σ wᵢ‖p − pᵢ‖²) against a true position.
    pub fn errors(&self, true_x: f64, true_y: f64) -> (f64, f64) {
        let w = self.weights();
        let (mut mae, mut mse) = (0.0, 0.0);
        for (p, w) in self.particles.iter().zip(&w) {
            let e = (p.pose.x - true_x).hypot(p.pose.y - true_y);
            mae += w * e;
            mse += w * e * e;
        }
        (mae, mse.sqrt())
    }

    fn particle_rng(&self, i: usize) -> ChaCha8Rng {
        let mut r = ChaCha8Rng::seed_from_u64(
            self.cfg.seed ^ (self.step as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15),
        );
        r.set_stream(i as u64);
        r
    }

    /// Ends the log: every association still open is decided on the detections it has
    /// (`association_window` > 1), as if its track ended here. Deterministic: each particle
    /// draws from its own stream of (seed, particle index).
    pub fn finish(&mut self) {
        if self.particles.iter().all(|p| p.pending.is_empty()) {
            return;
        }
        let cfg = &self.cfg;
        self.particles
            .par_iter_mut()
            .enumerate()
            .for_each(|(i, p)| {
                // the tracks still bound are the live ones (bound tracks were pruned to the
                // last snapshot's); a candidate bound to one of them is not free
                let live: BTreeSet<u64> = p.bound.iter().map(|(t, _)| *t).collect();
                let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed ^ 0xF1_E15E ^ ((i as u64) << 20));
                p.resolve_pending(cfg, &live, &mut rng, |_| true);
            });
    }

    /// Processes one snapshot.
    pub fn step(&mut self, snap: &Snapshot) -> StepStats {
        let dt = self.prev_t.map(|t| (snap.t - t).max(0.0)).unwrap_or(0.0);
        self.prev_t = Some(snap.t);
        // Register identities of new tracks (deterministic order) before the parallel part.
        for c in &snap.components {
            self.last_seen.insert(c.track, snap.t);
        }
        // Tracks alive now: detected within the log's hold time (this snapshot by default).
        let hold = self.cfg.track_hold_s + 1e-9;
        let current: BTreeSet<u64> = self
            .last_seen
            .iter()
            .filter(|(_, t)| snap.t - **t <= hold)
            .map(|(k, _)| *k)
            .collect();
        let mut fresh: BTreeSet<u64> = BTreeSet::new();
        for c in &snap.components {
            if !self.track_identity.contains_key(&c.track) {
                fresh.insert(c.track);
                let id = self.identities.len() as u32;
                self.identities.push(Identity { track: c.track });
                self.track_identity.insert(c.track, id);
            }
        }
        // Known tracks first; new ones in greedy order, strongest first. A track id always
        // names the same transmitter, also after gaps in its detection (sparse logs).
        let mut order: Vec<&Measurement> = snap.components.iter().collect();
        order.sort_by(|a, b| {
            let na = fresh.contains(&a.track);
            let nb = fresh.contains(&b.track);
            na.cmp(&nb)
                .then(b.snr_db.total_cmp(&a.snr_db))
                .then(a.track.cmp(&b.track))
        });
        let meas: Vec<(u64, Meas, u32)> = order
            .iter()
            .map(|m| {
                (
                    m.track,
                    Meas::new(m, &self.cfg, self.aoa),
                    self.track_identity[&m.track],
                )
            })
            .collect();
        let merge_now = self.step.is_multiple_of(10);
        // the weights' total before the detections: 1 unless something reweighted them since
        // the last snapshot, which is then not counted as evidence
        let before = log_sum_exp(self.particles.iter().map(|p| p.log_w));
        let rngs: Vec<ChaCha8Rng> = (0..self.particles.len())
            .map(|i| self.particle_rng(i))
            .collect();
        {
            let cfg = &self.cfg;
            let vis = &self.visibility;
            let prior = self.prior.as_deref();
            let speed = snap.speed;
            let gyro = snap.gyro;
            self.particles
                .par_iter_mut()
                .zip(rngs)
                .for_each(|(p, mut rng)| {
                    p.predict(cfg, gyro, speed, dt, &mut rng);
                    p.bound.retain(|(t, _)| current.contains(t));
                    if !p.pending.is_empty() {
                        p.resolve_pending(cfg, &current, &mut rng, |_| false);
                    }
                    let mut updated = vec![false; p.txs.len()];
                    for (track, m, identity) in &meas {
                        if let Some(&(_, idx)) = p.bound.iter().find(|(t, _)| t == track) {
                            let tx = Arc::make_mut(&mut p.txs[idx as usize]);
                            let ll = update_mixture(&mut tx.comps, m, &p.pose, cfg, merge_now);
                            p.log_w += ll;
                            if !updated[idx as usize] {
                                tx.reliability_m += p.pose.speed.abs() * dt;
                                updated[idx as usize] = true;
                            }
                            if let Some(pd) = p.pending.iter_mut().find(|pd| pd.track == *track) {
                                pd.seen += 1;
                                pd.ev_new += ll;
                                for c in &mut pd.cands {
                                    c.ev +=
                                        update_mixture(&mut c.comps, m, &p.pose, cfg, merge_now);
                                }
                            }
                        } else {
                            p.new_track(
                                cfg,
                                vis,
                                prior,
                                &current,
                                *track,
                                m,
                                *identity,
                                &mut rng,
                                &mut updated,
                                merge_now,
                                dt,
                            );
                        }
                    }
                    if !p.pending.is_empty() {
                        p.resolve_pending(cfg, &current, &mut rng, |pd| pd.seen >= pd.window);
                    }
                });
        }
        // Normalize, estimate, resample.
        let after = log_sum_exp(self.particles.iter().map(|p| p.log_w));
        if before.is_finite() {
            self.log_evidence += after - before;
        }
        let w = self.weights_given(after);
        let ess = 1.0 / w.iter().map(|x| x * x).sum::<f64>();
        let (mut mx, mut my) = (0.0, 0.0);
        for (p, w) in self.particles.iter().zip(&w) {
            mx += w * p.pose.x;
            my += w * p.pose.y;
        }
        let mean = Point2::new(mx, my);
        self.traveled += (mean - self.last_mean).norm();
        self.last_mean = mean;
        let ntx = self
            .particles
            .iter()
            .zip(&w)
            .map(|(p, w)| w * p.txs.len() as f64)
            .sum();
        let ncomp = self
            .particles
            .iter()
            .zip(&w)
            .map(|(p, w)| w * p.txs.iter().map(|t| t.comps.len()).sum::<usize>() as f64)
            .sum::<f64>();
        // A motion-only snapshot (no channel estimate) is no evidence of (in)visibility:
        // counting it as "not seen" would make a sensor slower than the snapshot rate (the
        // MRCLAM camera: estimates in 13–24 % of the 10 Hz snapshots) unlearn the visibility
        // of every transmitter it is not looking at right then.
        if snap.estimate {
            self.update_visibility(&w, &mean, &current);
        }
        let resampled = ess < self.cfg.resample_ess_ratio * self.particles.len() as f64;
        if resampled {
            self.resample(&w);
        } else {
            // the weights are those `after` totals (nothing reweighted them since)
            for p in &mut self.particles {
                p.log_w -= after;
            }
        }
        self.step += 1;
        StepStats {
            t: snap.t,
            x: mx,
            y: my,
            ess,
            resampled,
            transmitters: ntx,
            components: ncomp,
            traveled_m: self.traveled,
            log_evidence: self.log_evidence,
        }
    }

    /// Visibility bookkeeping along the mean track: an identity is "seen" when the track the
    /// majority of the weight binds to it is detected.
    fn update_visibility(&mut self, w: &[f64], mean: &Point2<f64>, current: &BTreeSet<u64>) {
        let mut votes: BTreeMap<(u64, u32), f64> = BTreeMap::new();
        for (p, w) in self.particles.iter().zip(w) {
            for (t, idx) in p.bound.iter().filter(|(t, _)| current.contains(t)) {
                *votes
                    .entry((*t, p.txs[*idx as usize].identity))
                    .or_insert(0.0) += w;
            }
        }
        let mut best: BTreeMap<u64, (u32, f64)> = BTreeMap::new();
        for ((t, id), v) in votes {
            let e = best.entry(t).or_insert((id, f64::NEG_INFINITY));
            if v > e.1 {
                *e = (id, v);
            }
        }
        let seen: BTreeSet<u32> = best
            .iter()
            .filter(|(t, _)| current.contains(t))
            .map(|(_, (id, _))| *id)
            .collect();
        for id in 0..self.identities.len() {
            self.visibility
                .observe(id, mean, seen.contains(&(id as u32)));
        }
    }

    /// Systematic resampling (one uniform draw; deterministic for the seed and step).
    fn resample(&mut self, w: &[f64]) {
        let n = self.particles.len();
        let mut rng =
            ChaCha8Rng::seed_from_u64(self.cfg.seed ^ 0xA5A5_5A5A_0F0F_F0F0 ^ self.step as u64);
        let u0: f64 = rng.random::<f64>() / n as f64;
        let mut picks = Vec::with_capacity(n);
        let mut cum = w[0];
        let mut j = 0;
        for k in 0..n {
            let u = u0 + k as f64 / n as f64;
            while u > cum && j + 1 < n {
                j += 1;
                cum += w[j];
            }
            picks.push(j);
        }
        // Copies share their transmitters (Arc); cloning and dropping thousands of particles
        // is reference counting on every transmitter, done on all workers.
        let ln_w = -(n as f64).ln();
        let old = std::mem::take(&mut self.particles);
        self.particles = picks
            .par_iter()
            .map(|&j| {
                let mut p = old[j].clone();
                p.log_w = ln_w;
                p
            })
            .collect();
        old.into_par_iter().for_each(drop);
    }
}

impl Particle {
    /// Motion model (Gentner et al. 2016 eq. 16–18 in position/heading/speed form): the heading turns by
    /// the gyro rate plus von Mises noise, the speed follows a random walk (or the measured
    /// speed), and the position moves along the mean heading of the interval.
    fn predict(
        &mut self,
        cfg: &FilterConfig,
        gyro: f64,
        speed: Option<f64>,
        dt: f64,
        rng: &mut ChaCha8Rng,
    ) {
        if dt <= 0.0 {
            return;
        }
        let var_h = cfg.heading_noise_rad_per_sqrt_s.powi(2) * dt
            + cfg.heading_noise_rad_per_sqrt_rad.powi(2) * (gyro * dt).abs();
        let sigma_h = var_h.sqrt();
        let kappa = if sigma_h > 0.0 {
            1.0 / (sigma_h * sigma_h)
        } else {
            f64::INFINITY
        };
        let mu = self.pose.heading + gyro * dt;
        let h_new = if kappa.is_finite() {
            vonmises::sample(mu, kappa, rng)
        } else {
            wrap_angle(mu)
        };
        let n: f64 = rng.sample(StandardNormal);
        self.pose.speed = match speed {
            // Unclamped: clipping the noise at zero would bias a standing user forward by
            // σ·0.4 m/s (0.02 m/s at the default σ — metres over a long stop on real data).
            Some(v) => v + cfg.speed_measurement_std_mps * n,
            None => (self.pose.speed + cfg.speed_noise_mps_per_sqrt_s * dt.sqrt() * n).max(0.0),
        };
        let h_mid = self.pose.heading + 0.5 * wrap_angle(h_new - self.pose.heading);
        self.pose.x += self.pose.speed * dt * h_mid.cos();
        self.pose.y += self.pose.speed * dt * h_mid.sin();
        self.pose.heading = h_new;
    }

    /// A track this particle has not bound yet: associate it with an old transmitter, a
    /// prior-map transmitter or none (Gentner et al. 2016 §5; Ulmschneider et al. 2021 eq. 19: visibility term × state
    /// likelihood). A track associated with a prior transmitter starts from that
    /// transmitter's mixture (agent frame) instead of the wide initialization.
    #[allow(clippy::too_many_arguments)]
    fn new_track(
        &mut self,
        cfg: &FilterConfig,
        vis: &Visibility,
        prior: Option<&Prior>,
        current: &BTreeSet<u64>,
        track: u64,
        m: &Meas,
        identity: u32,
        rng: &mut ChaCha8Rng,
        updated: &mut Vec<bool>,
        merge_now: bool,
        dt: f64,
    ) {
        #[derive(Clone, Copy)]
        enum Cand {
            Old(usize),
            Prior(usize),
        }
        let ln_p0 = cfg.association_p0.ln();
        let mut chosen: Option<Cand> = None;
        if cfg.association != Association::Off {
            let here = Point2::new(self.pose.x, self.pose.y);
            let cell = vis.grid().cell_of(&here);
            let mut cands: Vec<(Cand, f64)> = Vec::new();
            for (idx, tx) in self.txs.iter().enumerate() {
                // only transmitters not detected right now are candidates ("old", Gentner et al. 2016 §5)
                if self
                    .bound
                    .iter()
                    .any(|(t, b)| *b as usize == idx && current.contains(t))
                {
                    continue;
                }
                if let Some(ll) = candidate_log_likelihood(&tx.comps, &self.pose, m, cfg) {
                    let pv = vis.probability(tx.identity as usize, cell);
                    cands.push((
                        Cand::Old(idx),
                        ll + cfg.association_visibility_weight * pv.ln(),
                    ));
                }
            }
            if let Some(prior) = prior {
                let pose = self.prior_pose();
                let here = Point2::new(pose.x, pose.y);
                for (idx, ptx) in prior.txs.iter().enumerate() {
                    if ptx.existence < cfg.prior_min_existence
                        || ptx.claimed
                        || self.prior_used.contains(&(idx as u32))
                    {
                        continue;
                    }
                    if let Some(ll) = candidate_log_likelihood(&ptx.comps, &pose, m, cfg) {
                        let pv = prior.visibility(idx, &here);
                        cands.push((
                            Cand::Prior(idx),
                            ll + cfg.association_visibility_weight * pv.ln(),
                        ));
                    }
                }
            }
            let best_is_prior = cands
                .iter()
                .fold((false, ln_p0), |a, &(c, l)| {
                    if l > a.1 {
                        (matches!(c, Cand::Prior(_)), l)
                    } else {
                        a
                    }
                })
                .0;
            let own_deferred = cfg.association_window > 1
                && cands.iter().any(|(c, _)| matches!(c, Cand::Old(_)))
                && !best_is_prior;
            // A prior map holds many transmitters: one detection's distance and angle fit some
            // unrelated one on the same ray (its clock offset making up the range) often
            // enough, and a copy taken over that way pins the track to a wrong place. With a
            // prior window the decision waits until the detections have moved along the track.
            let prior_deferred = cfg.prior_association_window > 1
                && cands.iter().any(|(c, _)| matches!(c, Cand::Prior(_)));
            if own_deferred || prior_deferred {
                let window = if prior_deferred {
                    cfg.association_window.max(cfg.prior_association_window)
                } else {
                    cfg.association_window
                };
                // decide later: start as a tentative new transmitter, carry the candidates
                let cands = cands
                    .iter()
                    .filter_map(|&(c, l)| match c {
                        Cand::Old(i) => {
                            let mut comps = self.txs[i].comps.clone();
                            let _ = update_mixture(&mut comps, m, &self.pose, cfg, merge_now);
                            Some(PendingCand {
                                source: CandSource::Old(i as u32),
                                comps,
                                ev: l,
                            })
                        }
                        Cand::Prior(i) if prior_deferred => Some(PendingCand {
                            source: CandSource::Prior(i as u32),
                            comps: self.prior_copy(prior, i, m, cfg, merge_now),
                            ev: l,
                        }),
                        Cand::Prior(_) => None,
                    })
                    .collect();
                let birth = Birth::of(&self.pose, m);
                self.log_w += ln_p0;
                self.start_transmitter(identity, birth.mixture(cfg), track, updated, Some(birth));
                self.pending.push(Pending {
                    track,
                    slot: (self.txs.len() - 1) as u32,
                    seen: 1,
                    window,
                    ev_new: ln_p0,
                    cands,
                });
                return;
            }
            match cfg.association {
                Association::Ml => {
                    let best =
                        cands
                            .iter()
                            .copied()
                            .fold(
                                (None, ln_p0),
                                |a: (Option<Cand>, f64), b| {
                                    if b.1 > a.1 { (Some(b.0), b.1) } else { a }
                                },
                            );
                    self.log_w += best.1;
                    chosen = best.0;
                }
                Association::Das => {
                    let total =
                        log_sum_exp(cands.iter().map(|c| c.1).chain(std::iter::once(ln_p0)));
                    self.log_w += total;
                    let u: f64 = rng.random();
                    let mut acc = 0.0;
                    for (c, l) in &cands {
                        acc += (l - total).exp();
                        if u < acc {
                            chosen = Some(*c);
                            break;
                        }
                    }
                }
                Association::Off => {}
            }
        }
        match chosen {
            Some(Cand::Old(idx)) => {
                self.bound.push((track, idx as u32));
                let tx = Arc::make_mut(&mut self.txs[idx]);
                // The association factor already carries the likelihood; update the state only.
                let _ = update_mixture(&mut tx.comps, m, &self.pose, cfg, merge_now);
                if !updated[idx] {
                    tx.reliability_m += self.pose.speed.abs() * dt;
                    updated[idx] = true;
                }
            }
            Some(Cand::Prior(pidx)) => {
                let comps = self.prior_copy(prior, pidx, m, cfg, merge_now);
                self.prior_used.push(pidx as u32);
                self.start_transmitter(identity, comps, track, updated, None);
            }
            None => {
                let birth = Birth::of(&self.pose, m);
                if cfg.association == Association::Off {
                    self.log_w += ln_p0;
                }
                self.start_transmitter(identity, birth.mixture(cfg), track, updated, Some(birth));
            }
        }
    }

    /// Decides the open associations for which `due` holds or whose track has ended: ML
    /// takes the largest evidence among "new" and the candidates still free (not bound to
    /// another live track), DAS samples in proportion; the particle weight moves from the
    /// "new" evidence it carried to the chosen one. An associated track continues the old
    /// transmitter (with the window's detections) and its tentative transmitter is removed.
    fn resolve_pending(
        &mut self,
        cfg: &FilterConfig,
        current: &BTreeSet<u64>,
        rng: &mut ChaCha8Rng,
        due: impl Fn(&Pending) -> bool,
    ) {
        let mut k = 0;
        while k < self.pending.len() {
            let alive = current.contains(&self.pending[k].track);
            if alive && !due(&self.pending[k]) {
                k += 1;
                continue;
            }
            let pd = self.pending.swap_remove(k);
            let free: Vec<&PendingCand> = pd
                .cands
                .iter()
                .filter(|c| match c.source {
                    CandSource::Old(old) => !self
                        .bound
                        .iter()
                        .any(|(t, b)| *b == old && *t != pd.track && current.contains(t)),
                    CandSource::Prior(idx) => !self.prior_used.contains(&idx),
                })
                .collect();
            let chosen: Option<&PendingCand> = match cfg.association {
                Association::Das => {
                    let total =
                        log_sum_exp(free.iter().map(|c| c.ev).chain(std::iter::once(pd.ev_new)));
                    self.log_w += total - pd.ev_new;
                    let u: f64 = rng.random();
                    let mut acc = 0.0;
                    let mut pick = None;
                    for c in &free {
                        acc += (c.ev - total).exp();
                        if u < acc {
                            pick = Some(*c);
                            break;
                        }
                    }
                    pick
                }
                _ => {
                    let best = free
                        .iter()
                        .copied()
                        .filter(|c| c.ev > pd.ev_new)
                        .max_by(|a, b| a.ev.total_cmp(&b.ev));
                    if let Some(c) = best {
                        self.log_w += c.ev - pd.ev_new;
                    }
                    best
                }
            };
            let Some(c) = chosen else {
                continue;
            };
            let slot = pd.slot as usize;
            let old = match c.source {
                CandSource::Old(old) => old as usize,
                CandSource::Prior(idx) => {
                    // the tentative transmitter continues from the prior's copy
                    let prev = &self.txs[slot];
                    self.txs[slot] = Arc::new(TxState {
                        identity: prev.identity,
                        comps: c.comps.clone(),
                        reliability_m: prev.reliability_m,
                        from_prior: true,
                        birth: None,
                    });
                    self.prior_used.push(idx);
                    continue;
                }
            };
            let tentative = self.txs[slot].reliability_m;
            let prev = &self.txs[old];
            self.txs[old] = Arc::new(TxState {
                identity: prev.identity,
                comps: c.comps.clone(),
                reliability_m: prev.reliability_m + tentative,
                from_prior: prev.from_prior,
                birth: prev.birth,
            });
            for (t, b) in &mut self.bound {
                if *t == pd.track {
                    *b = old as u32;
                }
            }
            self.remove_slot(slot);
        }
    }

    /// Removes transmitter `slot`, renumbering what points behind it.
    fn remove_slot(&mut self, slot: usize) {
        self.txs.remove(slot);
        let fix = |i: &mut u32| {
            if *i as usize > slot {
                *i -= 1;
            }
        };
        for (_, b) in &mut self.bound {
            fix(b);
        }
        for pd in &mut self.pending {
            fix(&mut pd.slot);
            for c in &mut pd.cands {
                if let CandSource::Old(old) = &mut c.source {
                    fix(old);
                }
            }
        }
    }

    /// Prior transmitter `idx` updated with the detection `m` and placed in this particle's
    /// frame: the mixture a track starts from when it is taken over.
    fn prior_copy(
        &self,
        prior: Option<&Prior>,
        idx: usize,
        m: &Meas,
        cfg: &FilterConfig,
        merge_now: bool,
    ) -> Vec<Comp> {
        let prior = prior.expect("a prior candidate needs a prior");
        let mut comps = prior.txs[idx].comps.clone();
        let _ = update_mixture(&mut comps, m, &self.prior_pose(), cfg, merge_now);
        match &self.prior_frame {
            Some(d) => d.apply(&comps),
            None => comps,
        }
    }

    /// The pose from which this particle sees the prior's transmitters as the prior holds
    /// them: `D⁻¹(pose)` for its own transform draw.
    fn prior_pose(&self) -> Pose {
        match &self.prior_frame {
            Some(d) => d.inverse_pose(&self.pose),
            None => self.pose,
        }
    }

    /// A new transmitter of this particle, bound to `track`: from the detection `birth`, or
    /// (None) a prior copy.
    fn start_transmitter(
        &mut self,
        identity: u32,
        comps: Vec<Comp>,
        track: u64,
        updated: &mut Vec<bool>,
        birth: Option<Birth>,
    ) {
        self.txs.push(Arc::new(TxState {
            identity,
            comps,
            reliability_m: 0.0,
            from_prior: birth.is_none(),
            birth,
        }));
        self.bound.push((track, (self.txs.len() - 1) as u32));
        updated.push(true);
    }
}

/// The normalised product of two Gaussian mixtures over the same state, its log evidence
/// `ln Σ_ij w_i·w_j·N(m_j; m_i, P_i + P_j)`, and the floor of that evidence: the largest
/// `ln w_i·w_j − ½·ln|2π(P_i + P_j)|` less `gate_chi2 / 2`. None when no pair of components
/// gives a usable product.
pub(super) fn product_mixture(
    a: &[Comp],
    b: &[Comp],
    gate_chi2: f64,
) -> Option<(Vec<Comp>, f64, f64)> {
    let ln_2pi = (2.0 * std::f64::consts::PI).ln();
    let mut out: Vec<(f64, Vector3<f64>, Matrix3<f64>)> = Vec::new();
    let mut floor = f64::NEG_INFINITY;
    for ca in a {
        let pa = ca.g.cov();
        for cb in b {
            let s = pa + cb.g.cov();
            let Some(ch) = s.cholesky() else {
                continue;
            };
            let d = cb.g.mean - ca.g.mean;
            let ln_det = 2.0 * ch.l().diagonal().iter().map(|x| x.ln()).sum::<f64>();
            let ln_norm = ca.weight.ln() + cb.weight.ln() - 0.5 * (3.0 * ln_2pi + ln_det);
            floor = floor.max(ln_norm - 0.5 * gate_chi2);
            // K = P_a S⁻¹: mean m_a + K d, covariance P_a − K P_a
            let k = ch.solve(&pa).transpose();
            let mean = ca.g.mean + k * d;
            let cov = pa - k * pa;
            let cov = (cov + cov.transpose()) * 0.5;
            out.push((ln_norm - 0.5 * d.dot(&ch.solve(&d)), mean, cov));
        }
    }
    let total = log_sum_exp(out.iter().map(|o| o.0));
    if !total.is_finite() {
        return None;
    }
    let comps: Vec<Comp> = out
        .into_iter()
        .filter_map(|(l, mean, cov)| {
            SqrtGaussian::from_cov(mean, &cov).map(|g| Comp {
                weight: (l - total).exp(),
                g,
            })
        })
        .filter(|c| c.weight > 0.0)
        .collect();
    let sum: f64 = comps.iter().map(|c| c.weight).sum();
    if comps.is_empty() || sum <= 0.0 {
        return None;
    }
    let comps = comps
        .into_iter()
        .map(|c| Comp {
            weight: c.weight / sum,
            g: c.g,
        })
        .collect();
    Some((comps, total, floor))
}

/// Association log-likelihood `ln Σ_c w_c N(z; ẑ_c, P_zz,c)` of a candidate mixture, or None
/// when the candidate is not converged enough (position std above
/// `association_max_spread_m`) or fails the gates: the cheap 5σ gate on the mixture mean,
/// then the χ² gate `association_gate` on the innovation of its closest component.
fn candidate_log_likelihood(
    comps: &[Comp],
    pose: &Pose,
    m: &Meas,
    cfg: &FilterConfig,
) -> Option<f64> {
    let (sd, sa) = m.sigmas();
    if !gate(comps, pose, m, sd, sa, cfg.association_max_spread_m) {
        return None;
    }
    let terms: Vec<(f64, f64)> = comps
        .iter()
        .map(|c| match m.log_likelihood(pose, &c.g) {
            Some((l, d2)) => (c.weight.ln() + l, d2),
            None => (f64::NEG_INFINITY, f64::INFINITY),
        })
        .collect();
    let min_d2 = terms.iter().map(|t| t.1).fold(f64::INFINITY, f64::min);
    let ll = log_sum_exp(terms.iter().map(|t| t.0));
    (min_d2 <= cfg.association_gate && ll.is_finite()).then_some(ll)
}

/// Cheap gate before the cubature likelihood: the mixture's position std must be at most
/// `max_spread`, and the measured distance (and angle) must lie within 5σ of what its mean
/// predicts, σ including its spread.
fn gate(comps: &[Comp], pose: &Pose, m: &Meas, sd: f64, sa: f64, max_spread: f64) -> bool {
    let Some((mean, cov)) = mixture_moments(comps) else {
        return false;
    };
    let spread = cov.trace().max(0.0).sqrt();
    if (cov[(0, 0)] + cov[(1, 1)]).max(0.0).sqrt() > max_spread {
        return false;
    }
    let (dx, dy) = (mean.x - pose.x, mean.y - pose.y);
    let range = dx.hypot(dy);
    let d_pred = range + mean.z;
    if (d_pred - m.d()).abs() > 5.0 * (spread + sd) + 1.0 {
        return false;
    }
    if let Some(a) = m.aoa() {
        let a_pred = wrap_angle(dy.atan2(dx) - pose.heading);
        let tol = 5.0 * (sa + (spread / range.max(1.0)).min(std::f64::consts::PI)) + 0.1;
        if wrap_angle(a - a_pred).abs() > tol {
            return false;
        }
    }
    true
}

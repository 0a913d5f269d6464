//! Tracking a prior map while the agent runs (Ulmschneider et al. 2021 §III): the agent's own
//! map is matched against the crowd-sourced map, and an accepted match puts the crowd's
//! transmitters into the agent's frame as a [`Prior`].
//!
//! [`PriorTracker`] re-matches periodically: an accepted match (re)places the prior in the
//! filter with the newer transform; when matching fails and the transform in use no longer
//! has `min_inliers` agreeing transmitters in the agent's current map, the prior is dropped
//! (transmitters already taken over by particles stay, as the particles' own).

use super::config::FilterConfig;
pub use super::prior_map::{Prior, PriorTx, PriorUpdate, TransformUncertainty};
use super::rbpf::Filter;
use crate::filter::export::{export_map, track_of};
use anyhow::Result;
use echomap_shared::log::Snapshot;
use echomap_shared::map::TransmitterMap;
use echomap_shared::matching::{
    LocationScore, MatchConfig, MatchResult, fit_rigid_correlated, fit_rigid_weighted,
    fit_rigid_weighted_cov, match_maps, score_transform,
};
use nalgebra::{Isometry2, Matrix2, Matrix3, Point2, Vector2, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet};

/// The pose uncertainty an anchor-window detection carries (`PriorSettings::anchor_pose_uncertainty`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AnchorPose {
    /// none: the pose counts as known (the filter's weighted mean)
    Known,
    /// the particles' covariance of (x, y, heading) at the detection. The particles see
    /// the pose relative to their own maps: resampling on detections of transmitters that
    /// were themselves placed from the drifting track narrows their heading spread below
    /// the heading's error in the local frame (docs/results/cooperative.md, 2026-12-04)
    Particles,
    /// the dead-reckoning covariance since the first snapshot: the motion model's noise
    /// (`heading_noise_*`, the speed's) propagated along the gyro and speed alone, an upper
    /// bound on how far the pose can be off in the local frame whatever the detections say
    Odometry,
    /// `Odometry`, and the anchor points' errors correlated as the one dead reckoning makes
    /// them: detection j after detection i shares i's pose error carried forward,
    /// Cov(e_j, e_i) = Φ P_i with Φ = [[1, 0, −Δy], [0, 1, Δx], [0, 0, 1]] (Δ the walk
    /// between them: a heading error at i turns every later step). The anchored transform
    /// is then the generalized least-squares fit to the points' joint covariance
    /// (`fit_rigid_correlated`), which weighs the drift they share once — the earliest
    /// detections, made while the heading was still near the known start, decide the
    /// rotation — where `Odometry` counts it once per point
    OdometryCorrelated,
}

/// How often and how the agent matches its map against the prior.
#[derive(Debug, Clone)]
pub struct PriorSettings {
    /// seconds of log time between matching attempts; default 5 s
    pub match_every_s: f64,
    /// the first attempt not before this much log time has passed (s); default 5 s
    pub first_match_s: f64,
    /// floor of the residual std used for the transform's uncertainty (m); default 0.3
    pub residual_floor_m: f64,
    /// std added in quadrature to the x/y covariance of every prior transmitter (m): a
    /// crowd map is distorted by its contributors' track errors beyond its covariances;
    /// default 0.5
    pub position_floor_m: f64,
    /// how the transform's uncertainty enters the filter: `Some(k)` — every particle draws
    /// its own correction of the transform from the fit's spread with every std multiplied
    /// by k (the fit's σ comes from residuals and misses the drift the agent's map shares
    /// with its track, so the draws are dispersed); `None` — every prior covariance is
    /// inflated by the spread instead. Default `None`: with a perfect map the draws lowered
    /// the median final error on six seeds but made single runs worse (docs/results/cooperative.md)
    pub transform_draws: Option<f64>,
    /// the detections of the log's first this many seconds anchor the transform (s; 0 turns
    /// it off): the local frame is the agent's first pose, and only while its pose is still
    /// known in that frame do its measurements place a prior transmitter (range minus the
    /// prior's clock offset, along the angle of arrival) without the heading drift its map
    /// gathers before the first match. An accepted match's transform is refitted
    /// (covariance-weighted) to these anchor points of its correspondences when at least
    /// three agree. Needs angles of arrival. Default 0 (off): it lowered the first match's
    /// rotation error from 0.021 to 0.010 rad on eight seeds with a known map (unit test),
    /// but over the 10-run indoor cooperative experiment it gave no consistent gain (c21
    /// final MAE median 0.70 m against 0.67 m without; docs/results/cooperative.md)
    pub anchor_window_s: f64,
    /// whether and how the anchor points carry the agent's pose uncertainty at each
    /// detection (a covariance of x, y and heading, the heading's lever arm being the
    /// range): the detections of one transmitter are weighted by their total variance and
    /// its point's covariance bounds the pose errors for any correlation between them (they
    /// share the drift, so they do not average out). Default `Known`: the pose counts as
    /// known and the measurement noise averages down with every detection
    pub anchor_pose_uncertainty: AnchorPose,
    /// the transform's uncertainty is at least what the anchor points' covariances allow the
    /// anchored fit to know (the inverse of its information, `fit_rigid_weighted_cov`), not
    /// only what its residuals show: with `anchor_pose_uncertainty` the points carry the
    /// heading drift of the window, and a transform fitted to drifted points is no better
    /// known than they are. Enters through `transform_draws` or the prior's inflated
    /// covariances. Default false
    pub anchor_spread: bool,
    /// two transforms agree when their rotations differ by at most this (rad) and they put
    /// the inliers' centroid within `agree_m` of each other; defaults 0.1 rad, 0.5 m
    pub agree_rad: f64,
    pub agree_m: f64,
    /// every accepted match under the transform in use fuses each prior transmitter it pairs
    /// with one of the agent's own into that one, once per pair (`Filter::fuse_prior`; χ² gate
    /// of the matcher): the agent's transmitters it already knows gain the crowd's estimate
    /// instead of only its new tracks. Default false
    pub fuse_matched: bool,
    /// prior transmitters are candidates for new tracks (Ulmschneider et al. 2021 eq. 19). False leaves the
    /// crowd's transmitters to matching and (with `fuse_matched`) fusion only: no track starts
    /// from a prior copy. Default true
    pub offer_to_new_tracks: bool,
    pub matching: MatchConfig,
}

impl Default for PriorSettings {
    fn default() -> Self {
        PriorSettings {
            match_every_s: 5.0,
            first_match_s: 5.0,
            residual_floor_m: 0.3,
            position_floor_m: 0.5,
            transform_draws: None,
            anchor_window_s: 0.0,
            anchor_pose_uncertainty: AnchorPose::Known,
            anchor_spread: false,
            agree_rad: 0.1,
            agree_m: 0.5,
            fuse_matched: false,
            offer_to_new_tracks: true,
            matching: MatchConfig::default(),
        }
    }
}

/// One matching attempt during a run (written to `prior_matches.csv`).
#[derive(Debug, Clone, Serialize)]
pub struct MatchEvent {
    pub t: f64,
    pub accepted: bool,
    pub inliers: usize,
    /// rotation and translation of `map_from_agent` of this attempt
    pub angle_rad: f64,
    pub tx: f64,
    pub ty: f64,
    /// adopted | replaced | kept | dropped | none
    pub action: &'static str,
    /// anchor points the accepted transform was refitted to (0: the match's own fit)
    pub anchors: usize,
    /// rotation of the match's own fit, before any refit to anchor points
    pub match_angle_rad: f64,
    /// particle-weighted number of own transmitters the crowd's estimate was fused into
    /// (`PriorSettings::fuse_matched`)
    pub fused: f64,
    pub reason: String,
}

/// Periodic matching of the agent's map against a prior map (map frame).
#[derive(Debug, Clone)]
pub struct PriorTracker {
    map: TransmitterMap,
    settings: PriorSettings,
    seed: u64,
    next_t: Option<f64>,
    current: Option<Isometry2<f64>>,
    /// the spread the particles drew their transforms from (with `transform_draws`)
    spread: Option<TransformUncertainty>,
    /// time of the first snapshot
    t0: Option<f64>,
    /// per track, its detections inside the anchor window
    anchors: BTreeMap<u64, Vec<AnchorObs>>,
    /// the dead-reckoning covariance of (x, y, heading) and the time it is for
    /// (`AnchorPose::Odometry`)
    dead_reckoning: (Matrix3<f64>, f64),
    /// tracks whose transmitter had a prior transmitter fused in (`fuse_matched`)
    fused: BTreeSet<u64>,
    pub events: Vec<MatchEvent>,
}

/// A detection inside the anchor window, with the agent's weighted-mean pose then and the
/// particles' covariance of (x, y, heading) around it.
#[derive(Debug, Clone, Copy)]
struct AnchorObs {
    t: f64,
    x: f64,
    y: f64,
    heading: f64,
    pose_cov: Matrix3<f64>,
    d: f64,
    aoa: f64,
    /// measurement stds (m, rad) of the filter's noise model
    sd: f64,
    sa: f64,
}

/// A position with its covariance.
type PointCov = (Point2<f64>, Matrix2<f64>);

/// An anchor point: where a track's anchor-window detections put a prior transmitter, with
/// its marginal covariance; the part of it no other point shares (measurement noise, the
/// clock offset); and, per detection, how the pose error then moves the point.
struct AnchorPoint {
    point: PointCov,
    independent: Matrix2<f64>,
    loads: Vec<Load>,
}

/// One detection's share in an anchor point: the point moves by `arm · e` for a pose error e
/// of (x, y, heading) at time `t`, when the dead-reckoned pose was `at` with covariance
/// `pose_cov`.
struct Load {
    t: f64,
    at: Vector2<f64>,
    arm: nalgebra::Matrix2x3<f64>,
    pose_cov: Matrix3<f64>,
}

/// Covariance of the pose errors of two dead-reckoned poses: the later one carries the
/// earlier one's error forward, a heading error turning every step walked since,
/// Cov(e_later, e_earlier) = Φ P_earlier with Φ = [[1, 0, −Δy], [0, 1, Δx], [0, 0, 1]].
fn pose_cross_cov(a: &Load, b: &Load) -> Matrix3<f64> {
    let phi = |from: &Load, to: &Load| {
        let d = to.at - from.at;
        Matrix3::new(1.0, 0.0, -d.y, 0.0, 1.0, d.x, 0.0, 0.0, 1.0)
    };
    if a.t <= b.t {
        // Cov(e_a, e_b) = Cov(e_b, e_a)ᵀ = (Φ P_a)ᵀ
        (phi(a, b) * a.pose_cov).transpose()
    } else {
        phi(b, a) * b.pose_cov
    }
}

/// The joint covariance (2n × 2n) of anchor points placed from one dead-reckoned walk
/// (`AnchorPose::OdometryCorrelated`): Σᵢ Σⱼ arm_i Cov(e_i, e_j) arm_jᵀ over the detections
/// of the two points, plus each point's independent part on its own block.
fn joint_covariance(points: &[AnchorPoint]) -> nalgebra::DMatrix<f64> {
    let n = points.len();
    let mut joint = nalgebra::DMatrix::<f64>::zeros(2 * n, 2 * n);
    for k in 0..n {
        for l in k..n {
            let mut block = Matrix2::zeros();
            for a in &points[k].loads {
                for b in &points[l].loads {
                    block += a.arm * pose_cross_cov(a, b) * b.arm.transpose();
                }
            }
            if k == l {
                block = (block + block.transpose()) * 0.5 + points[k].independent;
            }
            joint.fixed_view_mut::<2, 2>(2 * k, 2 * l).copy_from(&block);
            joint
                .fixed_view_mut::<2, 2>(2 * l, 2 * k)
                .copy_from(&block.transpose());
        }
    }
    joint
}

/// A transform refitted to anchor points: the points (agent frame) and their residuals.
struct Anchored {
    map_from_agent: Isometry2<f64>,
    /// covariance of (θ, t_x, t_y) of the fit from the points' covariances (`anchor_spread`)
    fit_cov: Option<Matrix3<f64>>,
    points: Vec<Point2<f64>>,
    residuals_m: Vec<f64>,
}

/// The particle-weighted mean pose (circular mean of the headings) and the covariance of
/// (x, y, heading) around it (headings wrapped to the mean).
fn pose_moments(filter: &Filter) -> (Vector3<f64>, Matrix3<f64>) {
    let (mut x, mut y, mut c, mut s) = (0.0, 0.0, 0.0, 0.0);
    for (p, w) in filter.particles().iter().zip(filter.weights()) {
        x += w * p.pose.x;
        y += w * p.pose.y;
        c += w * p.pose.heading.cos();
        s += w * p.pose.heading.sin();
    }
    let mean = Vector3::new(x, y, s.atan2(c));
    let mut cov = Matrix3::zeros();
    for (p, w) in filter.particles().iter().zip(filter.weights()) {
        let e = Vector3::new(
            p.pose.x - mean.x,
            p.pose.y - mean.y,
            echomap_shared::wrap_angle(p.pose.heading - mean.z),
        );
        cov += e * e.transpose() * w;
    }
    (mean, cov)
}

impl PriorTracker {
    pub fn new(map: TransmitterMap, settings: PriorSettings, seed: u64) -> Result<Self> {
        Ok(PriorTracker {
            map,
            settings,
            seed,
            next_t: None,
            current: None,
            spread: None,
            t0: None,
            anchors: BTreeMap::new(),
            dead_reckoning: (Matrix3::zeros(), f64::NAN),
            fused: BTreeSet::new(),
            events: Vec::new(),
        })
    }

    /// `map_from_agent` in use, if any.
    pub fn current(&self) -> Option<&Isometry2<f64>> {
        self.current.as_ref()
    }

    /// Called after each filter step with its snapshot: records the anchor window's
    /// detections and matches when an attempt is due.
    ///
    /// Returns what the filter is to do — use a newly placed prior, drop it, fuse matched
    /// pairs — as a [`PriorUpdate`] for [`Filter::apply_prior_update`]; the tracker reads the
    /// filter but never changes it. Pass the particle-weighted number of fused pairs that
    /// the update gave back to [`PriorTracker::record_fused`].
    pub fn after_step(&mut self, filter: &Filter, snap: &Snapshot) -> Result<PriorUpdate> {
        let mut update = PriorUpdate::default();
        let t = snap.t;
        let t0 = *self.t0.get_or_insert(t);
        let in_window = filter.has_aoa()
            && self.settings.anchor_window_s > 0.0
            && t - t0 <= self.settings.anchor_window_s;
        if in_window {
            let (pose, particles_cov) = pose_moments(filter);
            let pose_cov = match self.settings.anchor_pose_uncertainty {
                AnchorPose::Odometry | AnchorPose::OdometryCorrelated => {
                    self.propagate_dead_reckoning(filter.config(), snap, pose.z);
                    self.dead_reckoning.0
                }
                _ => particles_cov,
            };
            for m in &snap.components {
                if let Some(aoa) = m.aoa {
                    let (sd, sa) = filter.config().noise.std(m.snr_db);
                    self.anchors.entry(m.track).or_default().push(AnchorObs {
                        t,
                        x: pose.x,
                        y: pose.y,
                        heading: pose.z,
                        pose_cov,
                        d: m.d,
                        aoa,
                        sd,
                        sa,
                    });
                }
            }
        }
        let next = *self
            .next_t
            .get_or_insert(t + self.settings.first_match_s.max(0.0));
        if t < next || self.map.is_empty() {
            return Ok(update);
        }
        self.next_t = Some(t + self.settings.match_every_s.max(1e-3));
        let user = export_map(filter)?;
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed ^ t.to_bits().rotate_left(17));
        let m = match_maps(&user, &self.map, &self.settings.matching, &mut rng);
        // A transform in use is only replaced by one that explains at least as much of the map
        // now: in a self-similar layout a wrong transform can pass the a-contrario test while
        // the one in use still fits better, and RANSAC need not find the mode in use again on
        // every attempt. "As much" is the matcher's own score under the likelihood score (a
        // half turn collects more but looser inliers, which that score is made to see), the
        // inlier count under MSAC (the rule measured with it; comparing MSAC scores instead
        // raised the e2e test's final error from 0.78 to 1.17 m).
        let in_use = self
            .current
            .map(|cur| score_transform(&user, &self.map, &cur, &self.settings.matching));
        let anchored = if m.accepted {
            self.anchor(&user, &m)
        } else {
            None
        };
        let anchors = anchored.as_ref().map_or(0, |a| a.points.len());
        let (fit, fit_cov, points, residuals) = match anchored {
            Some(a) => (a.map_from_agent, a.fit_cov, a.points, a.residuals_m),
            None => (
                m.map_from_agent,
                None,
                m.correspondences
                    .iter()
                    .map(|&(u, _)| {
                        let (mean, _) = user.transmitters()[u].moments();
                        Point2::new(mean.x, mean.y)
                    })
                    .collect(),
                m.residuals_m.clone(),
            ),
        };
        // With per-particle transform draws, a re-match that agrees with the transform in use
        // (every inlier within 3σ of the spread the particles drew from) leaves the draws be:
        // the particles' weights have already been choosing among them.
        let agrees = match (&self.current, &self.spread) {
            (Some(cur), Some(spread)) if m.accepted => points
                .iter()
                .all(|p| (fit * p - cur * p).norm() <= 3.0 * spread.std_at(p)),
            _ => false,
        };
        let centroid = (!points.is_empty()).then(|| {
            Point2::from(
                points.iter().map(|p| p.coords).sum::<Vector2<f64>>() / points.len() as f64,
            )
        });
        let same = |a: &Isometry2<f64>, b: &Isometry2<f64>| {
            echomap_shared::wrap_angle(a.rotation.angle() - b.rotation.angle()).abs()
                <= self.settings.agree_rad
                && centroid.is_none_or(|c| (a * c - b * c).norm() <= self.settings.agree_m)
        };
        let action = if agrees {
            "kept"
        } else if m.accepted
            && in_use.is_none_or(|cur| match self.settings.matching.location_score {
                LocationScore::Msac => m.inliers >= cur.inliers,
                LocationScore::Likelihood { .. } => m.score >= cur.score,
            })
        {
            let action = if self.current.is_some() {
                "replaced"
            } else {
                "adopted"
            };
            self.current = Some(fit);
            let mut unc =
                TransformUncertainty::from_fit(&points, &residuals, self.settings.residual_floor_m);
            if let (Some(u), Some(c)) = (unc.as_mut(), fit_cov) {
                u.widen_to_fit(&fit, &c);
            }
            // either the particles draw the transform from its (dispersed) spread, or the
            // prior covariances are inflated by it
            self.spread = self
                .settings
                .transform_draws
                .zip(unc)
                .map(|(k, u)| u.dispersed(k));
            let mut prior = Prior::new(
                &self.map,
                fit.inverse(),
                if self.spread.is_some() {
                    None
                } else {
                    unc.as_ref()
                },
                self.settings.position_floor_m,
                filter.config().visibility_prior,
            );
            prior.spread = self.spread;
            if !self.settings.offer_to_new_tracks {
                let ids: Vec<String> = prior.txs.iter().map(|t| t.id.clone()).collect();
                prior.claim(ids.iter().map(String::as_str));
            }
            update.prior = Some(Some(prior));
            action
        } else if let Some(still) = in_use {
            if still.inliers >= self.settings.matching.min_inliers {
                "kept"
            } else {
                self.current = None;
                self.spread = None;
                update.prior = Some(None);
                "dropped"
            }
        } else {
            "none"
        };
        // pairs of a match under the transform in use: fuse those not fused yet (indices into
        // the prior in use once the update is applied)
        let prior_in_use = match &update.prior {
            Some(placed) => placed.as_ref(),
            None => filter.prior(),
        };
        if self.settings.fuse_matched
            && m.accepted
            && self.current.as_ref().is_some_and(|cur| same(cur, &fit))
            && let Some(prior) = prior_in_use
        {
            let pairs: Vec<(u64, usize)> = m
                .correspondences
                .iter()
                .filter_map(|&(u, j)| {
                    let track = track_of(&user.transmitters()[u].id)?;
                    let id = &self.map.transmitters()[j].id;
                    let idx = prior.txs.iter().position(|t| &t.id == id)?;
                    (!self.fused.contains(&track)).then_some((track, idx))
                })
                .collect();
            if !pairs.is_empty() {
                self.fused.extend(pairs.iter().map(|(t, _)| *t));
                update.fuse = pairs;
                update.fuse_gate_chi2 = self.settings.matching.inlier_gate_chi2;
            }
        }
        let a = fit;
        self.events.push(MatchEvent {
            t,
            accepted: m.accepted,
            inliers: m.inliers,
            angle_rad: a.rotation.angle(),
            tx: a.translation.x,
            ty: a.translation.y,
            action,
            anchors,
            match_angle_rad: m.map_from_agent.rotation.angle(),
            fused: 0.0,
            reason: m.reason.unwrap_or_default(),
        });
        Ok(update)
    }

    /// Records on this step's matching attempt how many pairs (particle-weighted) the
    /// filter fused when it applied the attempt's update.
    pub fn record_fused(&mut self, fused: f64) {
        if let Some(e) = self.events.last_mut() {
            e.fused = fused;
        }
    }

    /// Advances the dead-reckoning covariance to `snap.t` (first call: zero, the initial pose
    /// is known): heading variance σ_t²·Δt + σ_r²·|ω·Δt| per step as in the motion model,
    /// the speed's variance (measured: σ_v², else the random walk's σ_v²·Δt) along the
    /// heading, and the heading's variance carried into the position by the Jacobian of
    /// x += v·Δt·(cos h, sin h) — `P ← F P Fᵀ + Q`.
    fn propagate_dead_reckoning(&mut self, cfg: &FilterConfig, snap: &Snapshot, heading: f64) {
        let (p, t_prev) = self.dead_reckoning;
        let dt = snap.t - t_prev;
        // the first snapshot (t_prev NaN) starts it at zero, the known initial pose
        if dt.is_nan() || dt <= 0.0 {
            self.dead_reckoning = (p, snap.t);
            return;
        }
        let v = snap.speed.unwrap_or(0.0);
        let var_v = if snap.speed.is_some() {
            cfg.speed_measurement_std_mps.powi(2)
        } else {
            cfg.speed_noise_mps_per_sqrt_s.powi(2) * dt
        };
        let var_h = cfg.heading_step_variance(snap.gyro, dt);
        let u = Vector3::new(heading.cos(), heading.sin(), 0.0);
        let f = Matrix3::new(
            1.0,
            0.0,
            -v * dt * heading.sin(),
            0.0,
            1.0,
            v * dt * heading.cos(),
            0.0,
            0.0,
            1.0,
        );
        let mut q = u * u.transpose() * (var_v * dt * dt);
        q[(2, 2)] += var_h;
        self.dead_reckoning = (f * p * f.transpose() + q, snap.t);
    }

    /// The point a track's anchor-window detections put a prior transmitter with clock offset
    /// `b` (variance `var_b`) at, and its covariance; None without a detection beyond `b`.
    /// Each detection gives `pose + (d − b)·(cos, sin)(heading + aoa)`. With the pose known
    /// (`AnchorPose::Known`) the points are averaged and the covariance is
    /// σ_d²/n + var(b) along the ray and r²·σ_θ²/n across it. With it, detection i also
    /// carries its pose covariance P_i = J S_i Jᵀ (J = [I | r·(−sin, cos)ᵀ]); the points are
    /// averaged with weights a_i ∝ 1 / tr(M_i + P_i), and the covariance is
    /// Σ a_i² M_i + Σ a_i P_i + var(b) along the ray: measurement noise M_i independent, the
    /// pose part bounded for any correlation (Cov(Σ a_i e_i) ⪯ Σ a_i Cov(e_i), a_i ≥ 0
    /// summing to one).
    fn anchor_point(&self, obs: &[AnchorObs], b: f64, var_b: f64) -> Option<AnchorPoint> {
        let obs: Vec<&AnchorObs> = obs.iter().filter(|o| o.d - b > 0.0).collect();
        if obs.is_empty() {
            return None;
        }
        let n = obs.len() as f64;
        // per detection: the point, its measurement covariance, its pose covariance and the
        // pose error's lever J
        let parts: Vec<_> = obs
            .iter()
            .map(|o| {
                let (r, phi) = (o.d - b, o.heading + o.aoa);
                let u = Vector2::new(phi.cos(), phi.sin());
                let perp = Vector2::new(-u.y, u.x);
                let m = u * u.transpose() * (o.sd * o.sd)
                    + perp * perp.transpose() * (r * r * o.sa * o.sa);
                let j = nalgebra::Matrix2x3::new(1.0, 0.0, r * perp.x, 0.0, 1.0, r * perp.y);
                let pose = j * o.pose_cov * j.transpose();
                (Vector2::new(o.x, o.y) + u * r, m, pose, j)
            })
            .collect();
        let from: Vector2<f64> = obs
            .iter()
            .map(|o| Vector2::new(o.x, o.y))
            .sum::<Vector2<f64>>()
            / n;
        if self.settings.anchor_pose_uncertainty == AnchorPose::Known {
            let q = parts.iter().map(|(q, ..)| q).sum::<Vector2<f64>>() / n;
            let dir = (q - from).try_normalize(1e-9)?;
            let perp = Vector2::new(-dir.y, dir.x);
            let sd2: f64 = obs.iter().map(|o| o.sd * o.sd).sum();
            let sa2: f64 = obs.iter().map(|o| o.sa * o.sa).sum();
            let r = obs.iter().map(|o| o.d - b).sum::<f64>() / n;
            let c = dir * dir.transpose() * (sd2 / (n * n) + var_b)
                + perp * perp.transpose() * (r * r * sa2 / (n * n));
            return Some(AnchorPoint {
                point: (Point2::from(q), c),
                independent: c,
                loads: Vec::new(),
            });
        }
        let inv: Vec<f64> = parts
            .iter()
            .map(|(_, m, p, _)| 1.0 / (m + p).trace().max(1e-12))
            .collect();
        let total: f64 = inv.iter().sum();
        let mut q = Vector2::zeros();
        let mut c = Matrix2::zeros();
        let mut independent = Matrix2::zeros();
        let mut loads = Vec::with_capacity(obs.len());
        for (((qi, m, p, j), w), o) in parts.iter().zip(&inv).zip(&obs) {
            let a = w / total;
            q += qi * a;
            c += m * (a * a) + p * a;
            independent += m * (a * a);
            loads.push(Load {
                t: o.t,
                at: Vector2::new(o.x, o.y),
                arm: j * a,
                pose_cov: o.pose_cov,
            });
        }
        let dir = (q - from).try_normalize(1e-9)?;
        c += dir * dir.transpose() * var_b;
        independent += dir * dir.transpose() * var_b;
        Some(AnchorPoint {
            point: (Point2::from(q), c),
            independent,
            loads,
        })
    }

    /// Refits the match's transform to the anchor points of its correspondences: for every
    /// agent transmitter (exported as `t<track>`) detected inside the anchor window, the
    /// point its detections put the corresponding prior transmitter at, range `d − b` (b the
    /// prior's clock offset) along the angle of arrival from the pose then, averaged over
    /// the detections; covariance σ_d²/n + var(b) along the ray and r²·σ_θ²/n across it. The
    /// prior side carries its position covariance plus `position_floor_m`. Pairs outside
    /// the matcher's χ² gate are dropped and the fit repeated; None below three pairs.
    fn anchor(&self, user: &TransmitterMap, m: &MatchResult) -> Option<Anchored> {
        let floor = Matrix2::identity() * self.settings.position_floor_m.powi(2);
        let mut pairs: Vec<(PointCov, PointCov)> = Vec::new();
        let mut points: Vec<AnchorPoint> = Vec::new();
        for &(u, j) in &m.correspondences {
            let Some(obs) = track_of(&user.transmitters()[u].id).and_then(|k| self.anchors.get(&k))
            else {
                continue;
            };
            let (mean, cov) = self.map.transmitters()[j].moments();
            let (b, var_b) = (mean.z.max(0.0), cov[(2, 2)].max(0.0));
            let Some(point) = self.anchor_point(obs, b, var_b) else {
                continue;
            };
            pairs.push((
                point.point,
                (
                    Point2::new(mean.x, mean.y),
                    cov.fixed_view::<2, 2>(0, 0).into_owned() + floor,
                ),
            ));
            points.push(point);
        }
        // a pair's squared Mahalanobis residual under a transform (None: singular)
        let d2 = |iso: &Isometry2<f64>, ((q, cq), (p, cp)): &(PointCov, PointCov)| {
            let rot = iso.rotation.to_rotation_matrix().into_inner();
            let r = p - iso * q;
            (rot * cq * rot.transpose() + cp)
                .cholesky()
                .map(|ch| r.dot(&ch.solve(&r)))
        };
        // every pass that changes anything drops a pair, so this ends
        let mut iso = m.map_from_agent;
        loop {
            if pairs.len() < 3 {
                return None;
            }
            let (from, to): (Vec<_>, Vec<_>) = pairs.iter().copied().unzip();
            iso = fit_rigid_weighted(&from, &to, iso)?;
            let keep: Vec<bool> = pairs
                .iter()
                .map(|pair| {
                    d2(&iso, pair).is_some_and(|d| d <= self.settings.matching.inlier_gate_chi2)
                })
                .collect();
            if keep.iter().all(|&k| k) {
                break;
            }
            let mut flags = keep.iter();
            pairs.retain(|_| *flags.next().unwrap_or(&false));
            let mut flags = keep.iter();
            points.retain(|_| *flags.next().unwrap_or(&false));
        }
        // the points' joint covariance and the generalized fit to it (gated on the marginals)
        let mut correlated_cov = None;
        if self.settings.anchor_pose_uncertainty == AnchorPose::OdometryCorrelated {
            let joint = joint_covariance(&points);
            let from: Vec<Point2<f64>> = pairs.iter().map(|((q, _), _)| *q).collect();
            let to: Vec<PointCov> = pairs.iter().map(|(_, p)| *p).collect();
            let (fit, cov) = fit_rigid_correlated(&from, &joint, &to, iso)?;
            iso = fit;
            correlated_cov = Some(cov);
        }
        let fit_cov = if correlated_cov.is_some() {
            correlated_cov.filter(|_| self.settings.anchor_spread)
        } else if self.settings.anchor_spread {
            let (from, to): (Vec<_>, Vec<_>) = pairs.iter().copied().unzip();
            fit_rigid_weighted_cov(&from, &to, iso).map(|(_, c)| c)
        } else {
            None
        };
        Some(Anchored {
            map_from_agent: iso,
            fit_cov,
            points: pairs.iter().map(|((q, _), _)| *q).collect(),
            residuals_m: pairs
                .iter()
                .map(|((q, _), (p, _))| (p - iso * q).norm())
                .collect(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::RngExt;

    #[test]
    fn the_anchor_point_trusts_a_detection_less_when_the_pose_was_uncertain() {
        // One transmitter 10 m ahead (x axis), seen twice from the origin: first while the
        // heading is known (std 0.01 rad), then when the filter's heading has drifted by
        // 0.2 rad and its particles spread by as much. The measured angle of arrival is the
        // true one both times, so the second detection lands 2 m off to the side.
        let obs = |heading: f64, heading_std: f64| AnchorObs {
            t: 0.0,
            x: 0.0,
            y: 0.0,
            heading,
            pose_cov: Matrix3::from_diagonal(&Vector3::new(1e-4, 1e-4, heading_std.powi(2))),
            d: 10.0,
            aoa: 0.0,
            sd: 0.05,
            sa: 0.05,
        };
        let (known, drifted) = (obs(0.0, 0.01), obs(0.2, 0.2));
        let truth = Vector2::new(10.0, 0.0);
        let empty = TransmitterMap::new(2.0, Vec::new()).unwrap();
        let point = |pose_unc: AnchorPose| {
            let settings = PriorSettings {
                anchor_pose_uncertainty: pose_unc,
                ..PriorSettings::default()
            };
            let tracker = PriorTracker::new(empty.clone(), settings, 1).unwrap();
            let (q, c) = tracker
                .anchor_point(&[known, drifted], 0.0, 0.0)
                .unwrap()
                .point;
            let e = q.coords - truth;
            (e.norm(), e.dot(&c.cholesky().unwrap().solve(&e)).sqrt())
        };
        let (err_off, maha_off) = point(AnchorPose::Known);
        let (err_on, maha_on) = point(AnchorPose::Particles);
        println!(
            "error {err_off:.3} m ({maha_off:.2} σ) pose known, {err_on:.3} m ({maha_on:.2} σ) with its uncertainty"
        );
        // the plain average sits halfway (≈ 1 m off) and claims ≈ 0.35 m across the ray
        assert!(err_off > 0.9 && maha_off > 2.0, "{err_off} {maha_off}");
        // the drifted detection is down-weighted and the covariance covers what is left
        assert!(
            err_on < err_off / 3.0 && maha_on < 1.0,
            "{err_on} {maha_on}"
        );
    }

    #[test]
    fn the_dead_reckoning_covariance_grows_as_a_heading_random_walk_predicts() {
        // Straight at v = 1 m/s along +x for T = 20 s, heading noise σ_t = 0.01 rad/√s, no
        // turn and a noise-free speed: the heading variance is σ_t²·T and the cross-track
        // variance the integral of v²·σ_t²·t, i.e. v²·σ_t²·T³/3; along the track only the
        // speed's (zero) noise.
        let cfg = FilterConfig {
            heading_noise_rad_per_sqrt_s: 0.01,
            heading_noise_rad_per_sqrt_rad: 0.3,
            speed_measurement_std_mps: 0.0,
            ..FilterConfig::default()
        };
        let empty = TransmitterMap::new(2.0, Vec::new()).unwrap();
        let settings = PriorSettings {
            anchor_pose_uncertainty: AnchorPose::Odometry,
            ..PriorSettings::default()
        };
        let mut tracker = PriorTracker::new(empty, settings, 1).unwrap();
        let dt = 0.01;
        for k in 0..=2000 {
            let snap = Snapshot {
                t: k as f64 * dt,
                gyro: 0.0,
                speed: Some(1.0),
                components: Vec::new(),
                estimate: true,
            };
            tracker.propagate_dead_reckoning(&cfg, &snap, 0.0);
        }
        let p = tracker.dead_reckoning.0;
        let (t, s2) = (20.0, 0.01f64.powi(2));
        println!(
            "var h {:.3e} y {:.4} x {:.1e}",
            p[(2, 2)],
            p[(1, 1)],
            p[(0, 0)]
        );
        assert!((p[(2, 2)] / (s2 * t) - 1.0).abs() < 1e-9, "{}", p[(2, 2)]);
        assert!(
            (p[(1, 1)] / (s2 * t.powi(3) / 3.0) - 1.0).abs() < 0.01,
            "{}",
            p[(1, 1)]
        );
        assert!(p[(0, 0)] < 1e-12, "{}", p[(0, 0)]);
        // a turn adds σ_r² per radian turned: a quarter turn in one second
        let turn = Snapshot {
            t: t + 1.0,
            gyro: std::f64::consts::FRAC_PI_2,
            speed: Some(0.0),
            components: Vec::new(),
            estimate: true,
        };
        tracker.propagate_dead_reckoning(&cfg, &turn, 0.0);
        let added = tracker.dead_reckoning.0[(2, 2)] - p[(2, 2)];
        let expected = s2 + 0.09 * std::f64::consts::FRAC_PI_2;
        assert!((added / expected - 1.0).abs() < 1e-9, "{added} {expected}");
    }

    #[test]
    fn later_dead_reckoned_poses_carry_the_earlier_error_forward() {
        // Monte-Carlo dead reckoning (heading noise only, σ_t = 0.005 rad/√s, small enough
        // for the first-order model): 10 s straight along +x at 1 m/s, then 10 s on a circle
        // at 0.1 rad/s. The empirical covariance of the pose errors at 6 s and 16 s is what
        // `pose_cross_cov` gives from the tracker's propagated covariance at 6 s and the walk
        // between — either way round.
        let sigma = 0.005;
        let cfg = FilterConfig {
            heading_noise_rad_per_sqrt_s: sigma,
            heading_noise_rad_per_sqrt_rad: 0.0,
            speed_measurement_std_mps: 0.0,
            ..FilterConfig::default()
        };
        let (dt, steps) = (0.05, 400);
        let gyro = |k: usize| if k * 2 < steps { 0.0 } else { 0.1 };
        let (i, j) = (120, 320);
        let empty = TransmitterMap::new(2.0, Vec::new()).unwrap();
        let settings = PriorSettings {
            anchor_pose_uncertainty: AnchorPose::Odometry,
            ..PriorSettings::default()
        };
        let mut tracker = PriorTracker::new(empty, settings, 1).unwrap();
        let (mut h, mut at) = (0.0f64, Vector2::<f64>::zeros());
        let mut loads = Vec::new();
        for k in 0..=steps {
            if k > 0 {
                h += gyro(k) * dt;
                at += Vector2::new(h.cos(), h.sin()) * dt;
            }
            let snap = Snapshot {
                t: k as f64 * dt,
                gyro: gyro(k),
                speed: Some(1.0),
                components: Vec::new(),
                estimate: true,
            };
            tracker.propagate_dead_reckoning(&cfg, &snap, h);
            if k == i || k == j {
                loads.push(Load {
                    t: snap.t,
                    at,
                    arm: nalgebra::Matrix2x3::zeros(),
                    pose_cov: tracker.dead_reckoning.0,
                });
            }
        }
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut gauss = move || {
            let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        };
        let draws = 4000;
        let (mut sum_i, mut sum_j, mut prod) =
            (Vector3::zeros(), Vector3::zeros(), Matrix3::zeros());
        let (mut sq_i, mut sq_j) = (Vector3::<f64>::zeros(), Vector3::<f64>::zeros());
        for _ in 0..draws {
            // the dead-reckoned walk with a heading random walk, less the true one
            let (mut h, mut dh) = (0.0f64, 0.0);
            let (mut err, mut at_i, mut at_j) = (
                Vector3::<f64>::zeros(),
                Vector3::<f64>::zeros(),
                Vector3::zeros(),
            );
            for k in 1..=steps {
                dh += sigma * dt.sqrt() * gauss();
                h += gyro(k) * dt;
                err.x += ((h + dh).cos() - h.cos()) * dt;
                err.y += ((h + dh).sin() - h.sin()) * dt;
                err.z = dh;
                if k == i {
                    at_i = err;
                }
                if k == j {
                    at_j = err;
                }
            }
            sum_i += at_i;
            sum_j += at_j;
            sq_i += at_i.component_mul(&at_i);
            sq_j += at_j.component_mul(&at_j);
            prod += at_j * at_i.transpose();
        }
        let n = draws as f64;
        let emp = (prod - sum_j * sum_i.transpose() / n) / (n - 1.0);
        let var_i = (sq_i - sum_i.component_mul(&sum_i) / n) / (n - 1.0);
        let var_j = (sq_j - sum_j.component_mul(&sum_j) / n) / (n - 1.0);
        let model = pose_cross_cov(&loads[1], &loads[0]);
        let swapped = pose_cross_cov(&loads[0], &loads[1]);
        println!("empirical {emp:.3e} model {model:.3e}");
        assert!((swapped - model.transpose()).norm() < 1e-15);
        for r in 0..3 {
            for c in 0..3 {
                // 5 % of the scale (the two errors' empirical stds) plus four Monte-Carlo
                // standard errors
                let scale = (var_j[r] * var_i[c]).sqrt();
                let tol = 0.05 * scale + 4.0 * scale / n.sqrt() + 1e-12;
                assert!(
                    (emp[(r, c)] - model[(r, c)]).abs() < tol,
                    "({r}, {c}): empirical {:.3e}, model {:.3e}",
                    emp[(r, c)],
                    model[(r, c)]
                );
            }
        }
    }

    #[test]
    fn the_transform_spread_is_widened_to_what_the_anchored_fit_knows() {
        // three points 10–15 m apart with tiny residuals: the residual-based spread is the
        // 0.3 m floor (σ_θ ≈ 0.02 rad); a fit whose rotation is known only to 0.1 rad (about
        // the origin of the agent frame) moves the centroid by 0.1·|R c|, and both must show
        let pts = [
            Point2::new(0.0, 0.0),
            Point2::new(20.0, 0.0),
            Point2::new(10.0, 15.0),
        ];
        let mut u = TransformUncertainty::from_fit(&pts, &[0.01; 3], 0.3).unwrap();
        let before = u;
        let fit = Isometry2::new(Vector2::new(5.0, 5.0), 0.4);
        let cov = Matrix3::from_diagonal(&Vector3::new(0.01, 1e-6, 1e-6));
        u.widen_to_fit(&fit, &cov);
        let lever = (fit.rotation * u.centroid.coords).norm();
        assert!((u.var_theta - 0.01).abs() < 1e-12, "{}", u.var_theta);
        assert!(
            (u.var_t - (0.01 * lever * lever + 2e-6) / 2.0).abs() < 1e-9,
            "{} {lever}",
            u.var_t
        );
        assert!(u.var_theta > before.var_theta && u.var_t > before.var_t);
        // a fit that knows more than the residuals show changes nothing
        let mut v = before;
        v.widen_to_fit(&fit, &(cov * 1e-6));
        assert_eq!(v, before);
    }
}

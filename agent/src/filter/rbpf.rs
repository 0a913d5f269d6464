//! The RBGSPF core (Gentner et al. 2016 Algorithm 1): predict user particles, update every transmitter
//! mixture with its measurement, weight particles, associate new tracks, resample.
//!
//! Weights, in log space: component weights `w_c ∝ w_c · N(z; ẑ_c, P_zz,c)` (eq. 46) and
//! particle weights `w_i ∝ w_i · Σ_c w_c N(z; ẑ_c, P_zz,c)` over every measured transmitter
//! (eq. 45). Particles are processed in parallel with rayon; each particle draws from its own
//! ChaCha stream derived from (seed, step, particle index), and all reductions run in
//! particle order, so a run is identical for any thread count. Resampled particles share
//! unchanged transmitters through `Arc` (copy-on-write with `Arc::make_mut`).
use super::config::FilterConfig;
use super::gauge::Gauge;
use super::model::Pose;
use super::particle::{Calibration, Identity, Particle, TxState};
use super::prior_map::Prior;
use super::truth::{TruthSummary, TruthTrack};
use super::update::{Meas, log_sum_exp};
use super::visibility::Visibility;
use echomap_shared::log::{Measurement, Snapshot};
use nalgebra::Point2;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rayon::prelude::*;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Arc;

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
    /// with the true pose given (`Filter::set_true_pose`): ln p(z_t | true track) −
    /// ln p(z_t | the particles), the snapshot's evidence for the true track, mapped by itself,
    /// over the filter's (see `TruthTrack`)
    pub truth_ll_ratio: Option<f64>,
}

#[derive(Debug, Clone)]
pub struct Filter {
    pub(super) cfg: FilterConfig,
    pub(super) aoa: bool,
    pub(super) particles: Vec<Particle>,
    pub(super) identities: Vec<Identity>,
    pub(super) track_identity: HashMap<u64, u32>,
    /// time each track was last detected
    pub(super) last_seen: HashMap<u64, f64>,
    pub(super) visibility: Visibility,
    pub(super) step: usize,
    pub(super) prev_t: Option<f64>,
    pub(super) traveled: f64,
    pub(super) last_mean: Point2<f64>,
    pub(super) log_evidence: f64,
    /// the prior map in the agent frame, once matched
    pub(super) prior: Option<Arc<Prior>>,
    /// detections of bound tracks decided to be gross errors so far
    pub(super) outliers: usize,
    /// detections of bound tracks decided to be jumps within an unresolved cluster so far
    pub(super) jumps: usize,
    /// per track, its latest detections decided to be gross errors in a row
    pub(super) gross_runs: BTreeMap<u64, usize>,
    /// tracks found to follow another path than the transmitter they were bound to so far
    pub(super) switches: usize,
    /// the true track run through the same model, when the true poses are given
    pub(super) truth: Option<TruthTrack>,
    /// map segments opened so far (`super::gauge`)
    pub(super) segments: u32,
    /// the segment new transmitters are born in (identities carry it)
    pub(super) segment: u32,
    /// segments no detection has tied to the anchored map yet, with their gauges
    pub(super) open: Vec<Gauge>,
}

/// `(p − m)ᵀ C⁻¹ (p − m)` of a position `p` under mean `m` and covariance `C = [xx, xy, yy]`;
/// infinite for a singular `C` unless `p = m`.
pub fn nees(mean: [f64; 2], cov: [f64; 3], x: f64, y: f64) -> f64 {
    let [sxx, sxy, syy] = cov;
    let (ex, ey) = (x - mean[0], y - mean[1]);
    let det = sxx * syy - sxy * sxy;
    if det <= 0.0 || det.is_nan() {
        return if ex == 0.0 && ey == 0.0 {
            0.0
        } else {
            f64::INFINITY
        };
    }
    (syy * ex * ex - 2.0 * sxy * ex * ey + sxx * ey * ey) / det
}

/// A bound track's detection as one particle saw it: the track, the log likelihood and the
/// transmitter before the update (restored if the detection turns out to be a gross error).
pub(super) type Detection = (u64, f64, Arc<TxState>);

/// What every particle sees of one snapshot (`Particle::observe`).
pub(super) struct StepInput<'a> {
    pub(super) cfg: &'a FilterConfig,
    pub(super) vis: &'a Visibility,
    pub(super) prior: Option<&'a Prior>,
    /// tracks alive now
    pub(super) current: &'a BTreeSet<u64>,
    /// known tracks first, then new ones: (track, measurement, identity)
    pub(super) meas: &'a [(u64, Meas, u32)],
    pub(super) gyro: f64,
    pub(super) speed: Option<f64>,
    pub(super) dt: f64,
    pub(super) merge_now: bool,
    /// bound tracks' detections wait for the population's gross-error decision
    pub(super) robust: bool,
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
                // drawn only when configured, so that a filter without them draws as before
                let odometry = Calibration {
                    gyro_bias: if cfg.gyro_bias_std_rad_per_s > 0.0 {
                        cfg.gyro_bias_std_rad_per_s * rng.sample::<f64, _>(StandardNormal)
                    } else {
                        0.0
                    },
                    speed_scale: if cfg.speed_scale_std > 0.0 {
                        1.0 + cfg.speed_scale_std * rng.sample::<f64, _>(StandardNormal)
                    } else {
                        1.0
                    },
                };
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
                    anchors: Vec::new(),
                    odometry,
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
            outliers: 0,
            jumps: 0,
            gross_runs: BTreeMap::new(),
            switches: 0,
            truth: None,
            segments: 0,
            segment: 0,
            open: Vec::new(),
        }
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

    /// Gives the true pose of the snapshot about to be processed: the true track
    /// (`super::truth`) follows it through the filter's model. Call before every `step`
    /// from the first on; it changes nothing in the particles or any estimate.
    pub fn set_true_pose(&mut self, pose: Pose) {
        match self.truth.as_mut() {
            Some(tt) => tt.pose = Some(pose),
            None => self.truth = Some(TruthTrack::new(&self.particles[0], pose)),
        }
    }

    /// What the true track says about the run so far; None without true poses.
    pub fn truth_summary(&self) -> Option<TruthSummary> {
        self.truth.as_ref().map(TruthTrack::summary)
    }

    /// Detections of bound tracks decided to be gross errors so far.
    pub fn outlier_detections(&self) -> usize {
        self.outliers
    }

    /// Detections of bound tracks decided to be jumps within an unresolved cluster so far.
    pub fn jump_detections(&self) -> usize {
        self.jumps
    }

    /// Tracks found so far to follow another path than the transmitter they were bound to
    /// (`Filter::switch_tracks`).
    pub fn track_switches(&self) -> usize {
        self.switches
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
    pub(super) fn weights_given(&self, total: f64) -> Vec<f64> {
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

    /// The particle cloud's weighted mean position and covariance `[xx, xy, yy]`.
    pub fn position_moments(&self) -> ([f64; 2], [f64; 3]) {
        let w = self.weights();
        let (mut mx, mut my) = (0.0, 0.0);
        for (p, w) in self.particles.iter().zip(&w) {
            mx += w * p.pose.x;
            my += w * p.pose.y;
        }
        let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
        for (p, w) in self.particles.iter().zip(&w) {
            let (dx, dy) = (p.pose.x - mx, p.pose.y - my);
            sxx += w * dx * dx;
            sxy += w * dx * dy;
            syy += w * dy * dy;
        }
        ([mx, my], [sxx, sxy, syy])
    }

    /// Normalized estimation error squared of a true position under the particle cloud's
    /// weighted mean and covariance, `(p − p̂)ᵀ Σ⁻¹ (p − p̂)`: at most 5.991 (χ² with 2
    /// degrees of freedom, 95 %) when the truth lies inside the 95 % ellipse the filter
    /// reports. Infinite for a cloud collapsed to a point away from the truth.
    pub fn position_nees(&self, true_x: f64, true_y: f64) -> f64 {
        let (mean, cov) = self.position_moments();
        nees(mean, cov, true_x, true_y)
    }

    pub(super) fn particle_rng(&self, i: usize) -> ChaCha8Rng {
        let mut r = self.step_rng();
        r.set_stream(i as u64);
        r
    }

    /// The step's generator before a stream is chosen: [`Self::particle_rng`] is it on
    /// stream `i`.
    fn step_rng(&self) -> ChaCha8Rng {
        ChaCha8Rng::seed_from_u64(
            self.cfg.seed ^ (self.step as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15),
        )
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
        // A silent stretch ends with detections of new tracks only: a new map segment.
        let hold = self.cfg.track_hold_s + 1e-9;
        if self.cfg.keep_gauge && !snap.components.is_empty() {
            let quiet = !self.last_seen.values().any(|t| snap.t - *t <= hold)
                && snap
                    .components
                    .iter()
                    .all(|c| !self.track_identity.contains_key(&c.track));
            self.open_segment(quiet);
        }
        // Register identities of new tracks (deterministic order) before the parallel part.
        for c in &snap.components {
            self.last_seen.insert(c.track, snap.t);
        }
        // Tracks alive now: detected within the log's hold time (this snapshot by default).
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
                self.identities.push(Identity {
                    track: c.track,
                    segment: self.segment,
                });
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
        // with an outlier probability, bound tracks' detections weight the particles only
        // once the population has decided they are no gross errors
        let robust = self.cfg.outlier_probability > 0.0;
        let w_before = if robust {
            self.weights_given(before)
        } else {
            Vec::new()
        };
        let truth_rng = self.particle_rng(usize::MAX);
        let input = StepInput {
            cfg: &self.cfg,
            vis: &self.visibility,
            prior: self.prior.as_deref(),
            current: &current,
            meas: &meas,
            gyro: snap.gyro,
            speed: snap.speed,
            dt,
            merge_now,
            robust,
        };
        // each particle's stream of the step's generator, set up on the workers
        let step_rng = self.step_rng();
        let detections: Vec<Vec<Detection>> = self
            .particles
            .par_iter_mut()
            .enumerate()
            .map(|(i, p)| {
                let mut rng = step_rng.clone();
                rng.set_stream(i as u64);
                p.observe(&input, &mut rng, None)
            })
            .collect();
        // the true track, when known, sees the snapshot as every particle does (its own
        // stream after the particles' ones), from the true pose
        let truth_detections = self.truth.as_mut().map(|tt| {
            let mut rng = truth_rng;
            tt.observe(&input, &mut rng)
        });
        let (outliers, jumps) = if robust {
            self.weigh_detections(detections, &w_before, &meas)
        } else {
            (BTreeSet::new(), BTreeSet::new())
        };
        // Normalize, estimate, resample.
        let after = log_sum_exp(self.particles.iter().map(|p| p.log_w));
        if before.is_finite() {
            self.log_evidence += after - before;
        }
        let truth_ll_ratio = match (self.truth.as_mut(), truth_detections) {
            (Some(tt), Some(ds)) if before.is_finite() => {
                Some(tt.settle(ds, &outliers, &jumps, &meas, &self.cfg, after - before))
            }
            _ => None,
        };
        if robust {
            self.switch_tracks(&meas, &outliers);
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
        // counted on the workers (one load per transmitter), summed here in particle order
        let counts: Vec<usize> = self
            .particles
            .par_iter()
            .map(|p| p.txs.iter().map(|t| t.comps.len()).sum())
            .collect();
        let ncomp = counts
            .iter()
            .zip(&w)
            .map(|(n, w)| w * *n as f64)
            .sum::<f64>();
        // A motion-only snapshot (no channel estimate) is no evidence of (in)visibility:
        // counting it as "not seen" would make a sensor slower than the snapshot rate (the
        // MRCLAM camera: estimates in 13–24 % of the 10 Hz snapshots) unlearn the visibility
        // of every transmitter it is not looking at right then.
        if snap.estimate {
            self.update_visibility(&w, &mean, &current);
        }
        self.tie_segment(&w, &current);
        let resampled = ess < self.cfg.resample_ess_ratio * self.particles.len() as f64;
        if resampled {
            self.resample(&w);
            self.restore_gauge();
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
            truth_ll_ratio,
        }
    }

    /// The gross-error decision of every bound track's detection, taken once for the whole
    /// population: whether a detection is an outlier is a property of the detection, shared
    /// by every hypothesis of the user's track, not of each particle. It is one when
    /// `ε·λ > (1 − ε)·Σᵢ wᵢ·Lᵢ`, the outlier's density against the population's predictive
    /// likelihood (`wᵢ` the weights before this snapshot, over the particles that hold the
    /// track); it then weights no particle and every particle's transmitter is restored to
    /// its state before the update. Deciding per particle instead, `(1 − ε)·Lᵢ + ε·λ`, excuses
    /// exactly the particles that are wrong and removes the pull back to the truth.
    ///
    /// With a jump probability η, a detection the test above takes for an outlier is next
    /// weighed as another member of its transmitter's unresolved cluster — the same direction,
    /// the clock offset stepped by N(0, σ_j²): `η·Σᵢ wᵢ·Lᵢʲ > ε·λ`, with `Lᵢʲ` each particle's
    /// likelihood under the widened clock offset, makes it a jump, which weighs every particle
    /// by `Lᵢʲ` and keeps each transmitter as updated under the jump.
    ///
    /// Returns the tracks decided to be outliers and those decided to be jumps.
    fn weigh_detections(
        &mut self,
        detections: Vec<Vec<Detection>>,
        w_before: &[f64],
        meas: &[(u64, Meas, u32)],
    ) -> (BTreeSet<u64>, BTreeSet<u64>) {
        let eps = self.cfg.outlier_probability;
        let ln_outlier = (eps * self.cfg.outlier_density).ln() - (1.0 - eps).ln();
        let mut outliers = decide(w_before, &detections, |ln_p| ln_outlier > ln_p);
        let eta = self.cfg.jump_probability;
        let mut jumped: Vec<Vec<Detection>> = vec![Vec::new(); detections.len()];
        let mut jumps = BTreeSet::new();
        if eta > 0.0 && !outliers.is_empty() {
            let cfg = &self.cfg;
            jumped = self
                .particles
                .par_iter()
                .zip(&detections)
                .map(|(p, ds)| p.jump_updates(ds, &outliers, meas, cfg))
                .collect();
            let ln_jump = (eps * self.cfg.outlier_density).ln() - eta.ln();
            jumps = decide(w_before, &jumped, |ln_p| ln_jump < ln_p);
            outliers.retain(|t| !jumps.contains(t));
            for js in &mut jumped {
                js.retain(|j| jumps.contains(&j.0));
            }
        }
        self.particles
            .par_iter_mut()
            .zip(detections)
            .zip(jumped)
            .for_each(|((p, ds), js)| p.settle(ds, &outliers, js));
        self.outliers += outliers.len();
        self.jumps += jumps.len();
        (outliers, jumps)
    }

    /// A track whose detections the population keeps deciding to be gross errors follows
    /// another path than the transmitter it is bound to: a tracker that continued one path
    /// into another (a weak path near a blocked line of sight going on as the line of sight,
    /// members of a cluster closer than the resolution), or a transmitter born from a few
    /// detections of one path and fed the other's since. Rejecting each of them leaves the
    /// transmitter where the wrong path put it and the track's information unused; weighing
    /// them would drag the user's pose to the wrong transmitter. Under the model's own
    /// gross-error law a path yields `k` in a row with probability `εᵏ`; once that falls
    /// below [`SWITCH_FALSE_ALARM`] the track is unbound in every particle (and the true
    /// track) and gets a new identity: its next detection is a new track's, associated with
    /// an old transmitter — the one it left, where the run of errors was chance — or born
    /// from the path it follows now. The transmitter it leaves stays in the map, unbound.
    fn switch_tracks(&mut self, meas: &[(u64, Meas, u32)], outliers: &BTreeSet<u64>) {
        let eps = self.cfg.outlier_probability;
        if !(self.cfg.switch_tracks && eps > 0.0 && eps < 1.0) {
            return;
        }
        let after = (SWITCH_FALSE_ALARM.ln() / eps.ln()).ceil().max(1.0) as usize;
        let mut switched = BTreeSet::new();
        for (track, _, _) in meas {
            if outliers.contains(track) {
                let run = self.gross_runs.entry(*track).or_insert(0);
                *run += 1;
                if *run >= after {
                    switched.insert(*track);
                }
            } else {
                self.gross_runs.remove(track);
            }
        }
        for track in &switched {
            self.gross_runs.remove(track);
            let id = self.identities.len() as u32;
            self.identities.push(Identity {
                track: *track,
                segment: self.segment,
            });
            self.track_identity.insert(*track, id);
        }
        if switched.is_empty() {
            return;
        }
        self.switches += switched.len();
        let unbind = |p: &mut Particle| p.bound.retain(|(t, _)| !switched.contains(t));
        self.particles.par_iter_mut().for_each(unbind);
        if let Some(tt) = self.truth.as_mut() {
            unbind(&mut tt.particle);
        }
    }

    /// Visibility bookkeeping along the mean track: an identity is "seen" when the track the
    /// majority of the weight binds to it is detected.
    pub(super) fn update_visibility(
        &mut self,
        w: &[f64],
        mean: &Point2<f64>,
        current: &BTreeSet<u64>,
    ) {
        // every particle's (particle, track, identity) read on the workers (one load per bound
        // transmitter) into one vector in particle order, the votes added here in that order
        let pairs: Vec<(usize, u64, u32)> = self
            .particles
            .par_iter()
            .enumerate()
            .flat_map_iter(|(i, p)| {
                p.bound
                    .iter()
                    .filter(|(t, _)| current.contains(t))
                    .map(move |(t, idx)| (i, *t, p.txs[*idx as usize].identity))
            })
            .collect();
        let mut votes: BTreeMap<(u64, u32), f64> = BTreeMap::new();
        for (i, t, id) in pairs {
            *votes.entry((t, id)).or_insert(0.0) += w[i];
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
    pub(super) fn resample(&mut self, w: &[f64]) {
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

/// The probability, under the gross-error law, of the run of gross errors after which a
/// track is taken to follow another path (`Filter::switch_tracks`): one track in a thousand
/// of those that hit such a run is switched by chance, and the association then binds it
/// back to the transmitter it left.
pub const SWITCH_FALSE_ALARM: f64 = 1e-3;

/// The tracks whose population predictive log likelihood `ln Σᵢ wᵢ·Lᵢ` (over the particles
/// that hold the track, `wᵢ` the weights before the snapshot) satisfies `test`; `per_particle`
/// holds each particle's detections with their log likelihoods `ln Lᵢ`.
fn decide(
    w_before: &[f64],
    per_particle: &[Vec<Detection>],
    test: impl Fn(f64) -> bool,
) -> BTreeSet<u64> {
    let mut predictive: BTreeMap<u64, Vec<f64>> = BTreeMap::new();
    for (&w, ds) in w_before.iter().zip(per_particle) {
        if w > 0.0 {
            for (track, ll, _) in ds {
                predictive.entry(*track).or_default().push(w.ln() + ll);
            }
        }
    }
    predictive
        .into_iter()
        .filter(|(_, v)| test(log_sum_exp(v.iter().copied())))
        .map(|(track, _)| track)
        .collect()
}

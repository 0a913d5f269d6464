//! The true track run through the filter's own model: a diagnostic for logs with ground truth.
//!
//! One extra particle follows the true poses, maps its transmitters from them with the same
//! updates, association and gross-error decisions as the particles, and never joins the
//! population (it is not weighted, resampled or counted in any estimate). Two figures come
//! out of it:
//!
//! - the **log Bayes factor** of the true track against the filter,
//!   `Σ_t [ln p(z_t | true track) − ln p(z_t | particles)]`. Positive: the data favour the
//!   true track, and the filter lost it — an estimator failure (degeneracy, a proposal that
//!   cannot reach it). Negative: the data favour the filter's wrong track over the truth —
//!   the radio model does not fit the data (a track that is no point transmitter), and no
//!   estimator of this model can do better;
//! - the **normalized innovation squared** of the detections of the transmitters the true
//!   track has mapped, per measurement dimension: about 1 when the model fits the data.

use super::config::FilterConfig;
use super::model::{Pose, mixture_moments};
use super::particle::Particle;
use super::rbpf::{Detection, StepInput};
use super::srckf::SqrtGaussian;
use super::update::Meas;
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeSet;

/// The true track and its tallies (see the module documentation).
#[derive(Debug, Clone)]
pub struct TruthTrack {
    pub(super) particle: Particle,
    /// the true pose of the snapshot about to be processed
    pub(super) pose: Option<Pose>,
    log_bayes_factor: f64,
    nis_sum: f64,
    nis_dims: f64,
}

/// What the true track says about a run (`Filter::truth_summary`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthSummary {
    /// Σ_t ln p(z_t | true track) − ln p(z_t | particles)
    pub log_bayes_factor: f64,
    /// mean normalized innovation squared per measurement dimension of the detections of
    /// transmitters the true track had mapped (1 for a model that fits); None before any
    pub nis_per_dim: Option<f64>,
}

impl TruthTrack {
    /// A true track starting at `pose` from a particle's initial state.
    pub(super) fn new(template: &Particle, pose: Pose) -> Self {
        let mut particle = template.clone();
        particle.pose = pose;
        particle.log_w = 0.0;
        particle.txs.clear();
        particle.bound.clear();
        particle.pending.clear();
        particle.prior_used.clear();
        particle.prior_frame = None;
        TruthTrack {
            particle,
            pose: Some(pose),
            log_bayes_factor: 0.0,
            nis_sum: 0.0,
            nis_dims: 0.0,
        }
    }

    /// The snapshot from the true pose set for it (`Particle::observe`); the innovation of
    /// every detection of a transmitter it has mapped is tallied first, against the
    /// mixture's moments. Its weight then holds this snapshot's log likelihood, less the
    /// returned detections that wait for the gross-error decision (`settle`).
    pub(super) fn observe(&mut self, inp: &StepInput, rng: &mut ChaCha8Rng) -> Vec<Detection> {
        let p = &mut self.particle;
        p.log_w = 0.0;
        let Some(pose) = self.pose.take() else {
            return Vec::new();
        };
        for (track, m, _) in inp.meas {
            if p.pending.iter().any(|pd| pd.track == *track) {
                continue;
            }
            let Some(&(_, idx)) = p.bound.iter().find(|(t, _)| t == track) else {
                continue;
            };
            let Some((mean, cov)) = mixture_moments(&p.txs[idx as usize].comps) else {
                continue;
            };
            let Some(g) = SqrtGaussian::from_cov(mean, &cov) else {
                continue;
            };
            if let Some((_, d2)) = m.log_likelihood(&pose, &g) {
                self.nis_sum += d2;
                self.nis_dims += if m.aoa().is_some() { 2.0 } else { 1.0 };
            }
        }
        p.observe(inp, rng, Some(pose))
    }

    /// Applies the population's gross-error decision to the true track's waiting detections
    /// (an outlier is restored, a jump within a cluster updates under the jump, the others
    /// weigh) and books the snapshot against the particles' evidence `population_ll`.
    pub(super) fn settle(
        &mut self,
        detections: Vec<Detection>,
        outliers: &BTreeSet<u64>,
        jumps: &BTreeSet<u64>,
        meas: &[(u64, Meas, u32)],
        cfg: &FilterConfig,
        population_ll: f64,
    ) -> f64 {
        let jumped = self.particle.jump_updates(&detections, jumps, meas, cfg);
        self.particle.settle(detections, outliers, jumped);
        let ratio = self.particle.log_w - population_ll;
        self.log_bayes_factor += ratio;
        ratio
    }

    pub(super) fn summary(&self) -> TruthSummary {
        TruthSummary {
            log_bayes_factor: self.log_bayes_factor,
            nis_per_dim: (self.nis_dims > 0.0).then(|| self.nis_sum / self.nis_dims),
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::filter::FilterConfig;
    use crate::run::{RunOutput, run_filter};
    use crate::sim::builtin::indoor;
    use crate::sim::simulate::{SimOptions, SimOutput, simulate};

    fn indoor_log(seed: u64) -> SimOutput {
        let options = SimOptions {
            seed,
            toa_only: false,
        };
        simulate(&indoor(), "reference", options).unwrap()
    }

    fn run(sim: &SimOutput, truth: bool, particles: usize, heading_noise: f64) -> RunOutput {
        let cfg = FilterConfig {
            particles,
            seed: 7,
            heading_noise_rad_per_sqrt_s: heading_noise,
            initial_speed_mps: 1.0,
            ..FilterConfig::default()
        };
        run_filter(&sim.log, truth.then_some(&sim.truth), cfg, false).unwrap()
    }

    fn summary(out: &RunOutput) -> super::TruthSummary {
        out.filter
            .truth_summary()
            .expect("a run with truth has a true track")
    }

    /// The true track is a bystander: the particles, their weights and every estimate are
    /// the same with it as without it.
    #[test]
    fn the_true_track_changes_nothing_in_the_run() {
        let sim = indoor_log(2);
        let with = run(&sim, true, 60, 0.03);
        let without = run(&sim, false, 60, 0.03);
        assert!(without.filter.truth_summary().is_none());
        assert_eq!(with.rows.len(), without.rows.len());
        for (a, b) in with.rows.iter().zip(&without.rows) {
            assert_eq!((a.x, a.y, a.ess), (b.x, b.y, b.ess), "t = {}", a.t);
            assert_eq!(a.log_evidence, b.log_evidence, "t = {}", a.t);
        }
        assert!(
            with.rows
                .iter()
                .all(|r| r.truth.unwrap().truth_ll_ratio.is_finite())
        );
    }

    /// On data drawn from the filter's own model the true track's innovations are within
    /// the stated noise (the simulator states 1.5 × its floors, so below 1 per dimension),
    /// and a filter that cannot follow the truth — one particle under a heading noise ten
    /// times the default — is told apart from one that follows it by the Bayes factor.
    #[test]
    fn the_bayes_factor_tells_a_filter_that_lost_the_truth() {
        for seed in [2, 3, 4] {
            let sim = indoor_log(seed);
            let good = run(&sim, true, 200, 0.03);
            let lost = run(&sim, true, 1, 0.3);
            let (g, l) = (summary(&good), summary(&lost));
            let nis = g.nis_per_dim.unwrap();
            assert!(
                nis > 0.2 && nis < 1.0,
                "seed {seed}: NIS per dimension {nis}"
            );
            let per_snapshot =
                |s: super::TruthSummary| s.log_bayes_factor / sim.log.snapshots.len() as f64;
            assert!(
                per_snapshot(l) > 2.0 && per_snapshot(l) > 10.0 * per_snapshot(g).abs(),
                "seed {seed}: ln Bayes factor per snapshot {} lost, {} following",
                per_snapshot(l),
                per_snapshot(g)
            );
        }
    }

    /// A log whose tracks switch to other paths halfway — what a tracker does when two
    /// paths cross — is no set of point transmitters: the true track's own map then
    /// mispredicts its detections, and the NIS says so.
    #[test]
    fn tracks_that_switch_paths_show_in_the_true_tracks_innovations() {
        for seed in [2, 3] {
            let clean = indoor_log(seed);
            let mut switched = indoor_log(seed);
            let half = switched.log.snapshots.len() / 2;
            for snap in &mut switched.log.snapshots[half..] {
                let ids: Vec<u64> = snap.components.iter().map(|c| c.track).collect();
                let n = ids.len();
                for (j, c) in snap.components.iter_mut().enumerate() {
                    c.track = ids[(j + 1) % n];
                }
            }
            let nis = |s: &SimOutput| summary(&run(s, true, 100, 0.03)).nis_per_dim.unwrap();
            let (a, b) = (nis(&clean), nis(&switched));
            assert!(
                b > 3.0 * a,
                "seed {seed}: NIS per dimension {a} clean, {b} switched"
            );
        }
    }
}

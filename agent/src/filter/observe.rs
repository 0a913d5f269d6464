//! One particle's share of a snapshot (Gentner et al. 2016 Algorithm 1, lines 2–8 for one
//! user particle): move, update every transmitter bound to a detected track, start or
//! associate the new tracks, decide the associations that are due.

use super::config::FilterConfig;
use super::model::Pose;
use super::particle::{Particle, TxState};
use super::rbpf::{Detection, StepInput};
use super::srckf::SqrtGaussian;
use super::update::{Meas, update_mixture};
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeSet;
use std::sync::Arc;

impl Particle {
    /// Processes one snapshot for this particle and returns the detections of bound tracks
    /// that wait for the population's gross-error decision (`StepInput::robust`); every
    /// other likelihood is already in the weight. With `at`, the particle is placed at that
    /// pose after the motion step instead of where it moved (the true track,
    /// `super::truth::TruthTrack`), and the motion step leaves its weight alone.
    pub(super) fn observe(
        &mut self,
        inp: &StepInput,
        rng: &mut ChaCha8Rng,
        at: Option<Pose>,
    ) -> Vec<Detection> {
        let cfg = inp.cfg;
        let mut detections = Vec::new();
        self.bound.retain(|(t, _)| inp.current.contains(t));
        let log_w = self.log_w;
        self.move_by(cfg, inp.gyro, inp.speed, inp.dt, inp.meas, rng);
        if let Some(pose) = at {
            self.pose = pose;
            self.log_w = log_w;
        }
        if !self.pending.is_empty() {
            self.resolve_pending(cfg, inp.current, rng, |_| false);
        }
        let mut updated = vec![false; self.txs.len()];
        for (track, m, identity) in inp.meas {
            if let Some(&(_, idx)) = self.bound.iter().find(|(t, _)| t == track) {
                // a track whose association is still open carries its evidence into that
                // decision and weights at once
                let saved = (inp.robust && !self.pending.iter().any(|pd| pd.track == *track))
                    .then(|| Arc::clone(&self.txs[idx as usize]));
                let tx = Arc::make_mut(&mut self.txs[idx as usize]);
                let ll = update_mixture(&mut tx.comps, m, &self.pose, cfg, inp.merge_now);
                match saved {
                    Some(saved) => detections.push((*track, ll, saved)),
                    None => self.log_w += ll,
                }
                if !updated[idx as usize] {
                    tx.reliability_m += self.pose.speed.abs() * inp.dt;
                    updated[idx as usize] = true;
                }
                if let Some(pd) = self.pending.iter_mut().find(|pd| pd.track == *track) {
                    pd.seen += 1;
                    pd.ev_new += ll;
                    for c in &mut pd.cands {
                        c.ev += update_mixture(&mut c.comps, m, &self.pose, cfg, inp.merge_now);
                    }
                }
            } else {
                self.new_track(
                    cfg,
                    inp.vis,
                    inp.prior,
                    inp.current,
                    *track,
                    m,
                    *identity,
                    rng,
                    &mut updated,
                    inp.merge_now,
                    inp.dt,
                );
            }
        }
        if !self.pending.is_empty() {
            self.resolve_pending(cfg, inp.current, rng, |pd| pd.seen >= pd.window);
        }
        detections
    }

    /// The detection of `track` as another member of its transmitter's unresolved cluster:
    /// the transmitter as it was before the detection (`saved`), every component's clock
    /// offset widened by a step of `cfg.jump_std_m`, then updated by the detection. Returns
    /// the detection's log likelihood under that hypothesis and the transmitter after it.
    fn jump_update(
        &self,
        saved: &Arc<TxState>,
        m: &Meas,
        cfg: &FilterConfig,
    ) -> (f64, Arc<TxState>) {
        let mut tx = TxState::clone(saved);
        let step = cfg.jump_std_m * cfg.jump_std_m;
        tx.comps.retain_mut(|c| {
            let mut cov = c.g.cov();
            cov[(2, 2)] += step;
            match SqrtGaussian::from_cov(c.g.mean, &cov) {
                Some(g) => {
                    c.g = g;
                    true
                }
                None => false,
            }
        });
        let ll = update_mixture(&mut tx.comps, m, &self.pose, cfg, false);
        (ll, Arc::new(tx))
    }

    /// [`Self::jump_update`] of each of this particle's waiting `detections` whose track is in
    /// `tracks`, as (track, log likelihood, transmitter after the jump).
    pub(super) fn jump_updates(
        &self,
        detections: &[Detection],
        tracks: &BTreeSet<u64>,
        meas: &[(u64, Meas, u32)],
        cfg: &FilterConfig,
    ) -> Vec<Detection> {
        detections
            .iter()
            .filter(|d| tracks.contains(&d.0))
            .filter_map(|(track, _, saved)| {
                let (_, m, _) = meas.iter().find(|x| x.0 == *track)?;
                let (ll, tx) = self.jump_update(saved, m, cfg);
                Some((*track, ll, tx))
            })
            .collect()
    }

    /// Applies the population's decision to this particle's waiting detections (`observe`):
    /// the transmitter of an outlier is restored to its state before the detection, that of
    /// a cluster jump replaced by its state under the jump (`jumped`: track, log likelihood,
    /// transmitter), and every detection but an outlier weighs.
    pub(super) fn settle(
        &mut self,
        detections: Vec<Detection>,
        outliers: &BTreeSet<u64>,
        mut jumped: Vec<Detection>,
    ) {
        for (track, ll, saved) in detections {
            let jump = jumped
                .iter()
                .position(|j| j.0 == track)
                .map(|k| jumped.swap_remove(k));
            if outliers.contains(&track) || jump.is_some() {
                // the slot as bound now: an association decided later in the step may have
                // removed a slot before it
                if let Some(&(_, slot)) = self.bound.iter().find(|(t, _)| *t == track) {
                    match jump {
                        Some((_, ll, mut tx)) => {
                            Arc::make_mut(&mut tx).reliability_m =
                                self.txs[slot as usize].reliability_m;
                            self.txs[slot as usize] = tx;
                            self.log_w += ll;
                        }
                        None => self.txs[slot as usize] = saved,
                    }
                }
            } else {
                self.log_w += ll;
            }
        }
    }
}

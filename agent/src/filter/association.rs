//! Data association of new tracks (Gentner et al. 2016 §5; Ulmschneider et al. 2021 eq. 19): a
//! track a particle has not bound yet continues one of its old transmitters, takes over a
//! prior-map transmitter or starts a new one — at once, or after a window of detections.

use super::config::{Association, FilterConfig};
use super::model::{Comp, Pose, mixture_moments};
use super::particle::{Birth, Particle, TxState};
use super::prior_map::Prior;
use super::update::{Meas, log_sum_exp, update_mixture};
use super::visibility::Visibility;
use echomap_shared::wrap_angle;
use nalgebra::Point2;
use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeSet;
use std::sync::Arc;

/// A new track on probation: bound to a tentative new transmitter (`slot`) while the gated
/// old and prior-map transmitters are updated with its detections alongside.
#[derive(Debug, Clone)]
pub struct Pending {
    pub(super) track: u64,
    pub(super) slot: u32,
    pub(super) seen: usize,
    /// detections after which the association is decided
    pub(super) window: usize,
    /// ln p(z₁..z_seen | new transmitter): ln p₀ for the first detection, then the tentative
    /// transmitter's predictive likelihoods
    pub(super) ev_new: f64,
    pub(super) cands: Vec<PendingCand>,
}

#[derive(Debug, Clone)]
pub(super) struct PendingCand {
    pub(super) source: CandSource,
    /// the candidate's mixture (agent frame) updated with the track's detections
    pub(super) comps: Vec<Comp>,
    /// ln p(z₁..z_seen | candidate) including the visibility term of the first detection
    pub(super) ev: f64,
}

/// What a pending track may turn out to be.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum CandSource {
    /// one of the particle's own transmitters (slot)
    Old(u32),
    /// a prior-map transmitter (index into the prior)
    Prior(u32),
}

impl Particle {
    /// A track this particle has not bound yet: associate it with an old transmitter, a
    /// prior-map transmitter or none (Gentner et al. 2016 §5; Ulmschneider et al. 2021 eq. 19: visibility term × state
    /// likelihood). A track associated with a prior transmitter starts from that
    /// transmitter's mixture (agent frame) instead of the wide initialization.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn new_track(
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
    pub(super) fn resolve_pending(
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
}

/// Association log-likelihood `ln Σ_c w_c N(z; ẑ_c, P_zz,c)` of a candidate mixture, or None
/// when the candidate is not converged enough (position std above
/// `association_max_spread_m`) or fails the gates: the cheap 5σ gate on the mixture mean,
/// then the χ² gate `association_gate` on the innovation of its closest component.
pub(super) fn candidate_log_likelihood(
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
pub(super) fn gate(
    comps: &[Comp],
    pose: &Pose,
    m: &Meas,
    sd: f64,
    sa: f64,
    max_spread: f64,
) -> bool {
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

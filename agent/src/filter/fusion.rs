//! The prior map inside the filter: setting it (with every particle's draw of the matched
//! transform) and fusing paired prior transmitters into the particles' own ones.

use super::particle::FrameDelta;
use super::prior_map::{Prior, PriorUpdate};
use super::rbpf::Filter;
use super::update::{log_sum_exp, product_mixture, tidy};
use nalgebra::Vector2;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rayon::prelude::*;
use std::sync::Arc;

impl Filter {
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
}

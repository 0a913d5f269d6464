//! Map merging (Ulmschneider et al. 2021 §IV): a user map, matched into the map frame, is merged into the
//! prior map. For each correspondence (j_u, j_p):
//! - relative reliabilities `d̄_u = d_u/(d_u + d_p)`, `d̄_p = d_p/(d_u + d_p)` (eq. 22; ½/½ when
//!   both are 0);
//! - state: the mixture `d̄_u·p_u + d̄_p·p_p` (eq. 23), reduced to ≤ K components by Runnalls
//!   merging;
//! - reliability `d_u + d_p` (eq. 24), existence `p_u·d̄_u + p_p·d̄_p` (eq. 25);
//! - visibility counts added after re-binning the user's cells into the map frame (eq. 26).
//!
//! Unmatched user transmitters are added (with their existence); unmatched prior
//! transmitters are kept; prior ids never change, new ids are made unique. Merging into an
//! empty prior returns the user map unchanged: it defines the map frame.
//!
//! Departure (optional, [`MergeConfig::absorb_chi2`]; off by default): an unmatched user
//! transmitter that is statistically the same place as a prior transmitter — its x, y within a
//! squared Mahalanobis distance of the prior's, under the sum of both covariances — is merged
//! into the nearest such transmitter by the same rule instead of being added. RANSAC takes at
//! most one correspondence per transmitter, so a landmark a user mapped twice (once per track
//! of it, when association did not close the loop) would otherwise enter the crowd's map as a
//! second copy on every upload (docs/results/cooperative.md, 2026-12-03).

use crate::map::{MapError, Transmitter, TransmitterMap};
use crate::mixture::{self, Component};
use nalgebra::Isometry2;
use std::collections::HashSet;

/// Merging settings.
#[derive(Debug, Clone, PartialEq)]
pub struct MergeConfig {
    /// most components per merged transmitter; default 4
    pub max_components: usize,
    /// an unmatched user transmitter within this squared Mahalanobis distance (x, y; 2 degrees
    /// of freedom, e.g. 9.21 for 99 %) of a prior transmitter is merged into the nearest one
    /// instead of being added; 0 (default) adds every unmatched transmitter (Ulmschneider et al. 2021)
    pub absorb_chi2: f64,
}

impl Default for MergeConfig {
    fn default() -> Self {
        MergeConfig {
            max_components: 4,
            absorb_chi2: 0.0,
        }
    }
}

impl MergeConfig {
    /// These settings with the absorption gate `chi2` (see [`MergeConfig::absorb_chi2`]).
    pub fn with_absorb_chi2(self, chi2: f64) -> Self {
        MergeConfig {
            absorb_chi2: chi2,
            ..self
        }
    }
}

/// The squared Mahalanobis distance of two transmitters' x, y (moments of each mixture).
fn xy_distance2(a: &Transmitter, b: &Transmitter) -> Option<f64> {
    let (ma, ca) = a.moments();
    let (mb, cb) = b.moments();
    mixture::xy_distance2((&ma, &ca), (&mb, &cb))
}

/// Counts of what a merge did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MergeStats {
    /// user transmitters merged into prior ones (matched, or absorbed)
    pub merged: usize,
    /// user transmitters added as new ones
    pub added: usize,
    /// prior transmitters left unchanged
    pub kept: usize,
    /// what the merged map left out to stay within the format's limits
    /// ([`crate::map::fit_to_limits`])
    pub pruned: crate::map::Pruned,
}

fn merge_pair(u: &Transmitter, p: &Transmitter, cfg: &MergeConfig) -> Transmitter {
    let total = u.reliability_m + p.reliability_m;
    let (du, dp) = if total > 0.0 {
        (u.reliability_m / total, p.reliability_m / total)
    } else {
        (0.5, 0.5)
    };
    let mut comps: Vec<Component> = Vec::with_capacity(u.components.len() + p.components.len());
    for (f, t) in [(du, u), (dp, p)] {
        if f > 0.0 {
            comps.extend(t.components.iter().map(|c| Component {
                weight: c.weight * f,
                ..c.clone()
            }));
        }
    }
    let mut comps = mixture::reduce(&comps, cfg.max_components.max(1));
    // the weights sum to du + dp = 1 up to rounding; normalize exactly
    mixture::normalize(&mut comps).expect("merged mixture has positive weight");
    let mut visibility = p.visibility.clone();
    for (cell, b) in &u.visibility {
        let e = visibility.entry(*cell).or_insert(crate::map::Beta {
            alpha: 0.0,
            beta: 0.0,
        });
        e.alpha += b.alpha;
        e.beta += b.beta;
    }
    Transmitter {
        id: p.id.clone(),
        components: comps,
        existence: (u.existence * du + p.existence * dp).clamp(0.0, 1.0),
        reliability_m: total,
        visibility,
    }
}

/// Merges `user` (agent frame) into `prior` (map frame) given `map_from_agent` and the
/// correspondences `(user index, prior index)` of an accepted match.
pub fn merge_maps(
    prior: &TransmitterMap,
    user: &TransmitterMap,
    map_from_agent: &Isometry2<f64>,
    correspondences: &[(usize, usize)],
    cfg: &MergeConfig,
) -> Result<(TransmitterMap, MergeStats), MapError> {
    if prior.is_empty() {
        return Ok((
            user.clone(),
            MergeStats {
                merged: 0,
                added: user.len(),
                kept: 0,
                pruned: Default::default(),
            },
        ));
    }
    let moved = user.transformed(map_from_agent);
    let mut out: Vec<Transmitter> = prior.transmitters().to_vec();
    let n_prior = out.len();
    let mut matched_user = vec![false; moved.len()];
    let mut touched = vec![false; n_prior];
    let mut merged = 0;
    for &(ui, pi) in correspondences {
        if ui >= moved.len() || pi >= n_prior || matched_user[ui] {
            continue;
        }
        matched_user[ui] = true;
        touched[pi] = true;
        out[pi] = merge_pair(&moved.transmitters()[ui], &out[pi], cfg);
        merged += 1;
    }
    let mut ids: HashSet<String> = out.iter().map(|t| t.id.clone()).collect();
    let mut added = 0;
    for (ui, t) in moved.transmitters().iter().enumerate() {
        if matched_user[ui] {
            continue;
        }
        if cfg.absorb_chi2 > 0.0 {
            // only prior transmitters are candidates: an upload never absorbs itself
            let nearest = (0..n_prior)
                .filter_map(|pi| Some((pi, xy_distance2(t, &out[pi])?)))
                .filter(|&(_, d2)| d2 <= cfg.absorb_chi2)
                .min_by(|a, b| a.1.total_cmp(&b.1));
            if let Some((pi, _)) = nearest {
                touched[pi] = true;
                out[pi] = merge_pair(t, &out[pi], cfg);
                merged += 1;
                continue;
            }
        }
        let mut t = t.clone();
        if ids.contains(&t.id) {
            let base = t.id.clone();
            let mut k = 2;
            while ids.contains(&format!("{base}~{k}")) {
                k += 1;
            }
            t.id = format!("{base}~{k}");
        }
        ids.insert(t.id.clone());
        out.push(t);
        added += 1;
    }
    let kept = touched.iter().filter(|&&t| !t).count();
    let pruned = crate::map::fit_to_limits(&mut out);
    let map = TransmitterMap::new(prior.hex_size_m(), out)?;
    Ok((
        map,
        MergeStats {
            merged,
            added,
            kept,
            pruned,
        },
    ))
}

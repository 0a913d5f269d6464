//! Export of the particle ensemble as an `echomap.map.v1` user map (local frame).
//!
//! Per transmitter identity j (Ulmschneider et al. 2021 §IV):
//! - existence `p_e = Σ_{i∈T_j} wᵢ` over the particles in which j exists, i.e. did not get
//!   associated into an older transmitter (eq. 20);
//! - reliability `d_rel = Σ_{i∈T_j} wᵢ·d_rel,i` (eq. 21);
//! - state: the particle-weighted mixture over those particles' components, first collapsed
//!   greedily (components within Mahalanobis distance 1 merge, moment-preserving, ≤ 32
//!   groups), then reduced by Runnalls merging to `export_max_components`;
//! - visibility: the evidence counts of the filter's hex grid.
//!
//! A map beyond the format's limits (transmitters, visibility cells) keeps what carries the
//! most evidence (`echomap_shared::map::fit_to_limits`).
//!
//! Particles that share a transmitter through resampling are counted once with their summed
//! weight, so the cost is driven by distinct transmitter states, not by the particle count.

use super::particle::TxState;
use super::rbpf::Filter;
use echomap_shared::map::{MapError, Transmitter, TransmitterMap};
use echomap_shared::mixture::{self, Component, merge_pair, symmetrize};
use nalgebra::Matrix3;
use std::collections::HashMap;

const MAX_GROUPS: usize = 32;

fn mahalanobis2(a: &Component, b: &Component) -> f64 {
    let d = a.mean - b.mean;
    (a.cov + b.cov)
        .cholesky()
        .map(|c| d.dot(&c.solve(&d)))
        .unwrap_or(f64::INFINITY)
}

/// Greedy moment-preserving grouping of a large pool of components.
fn collapse(mut pool: Vec<Component>) -> Vec<Component> {
    pool.sort_by(|a, b| b.weight.total_cmp(&a.weight));
    let mut groups: Vec<Component> = Vec::new();
    for c in pool {
        let nearest = groups
            .iter()
            .enumerate()
            .map(|(i, g)| (i, mahalanobis2(g, &c)))
            .min_by(|a, b| a.1.total_cmp(&b.1));
        match nearest {
            Some((i, d2)) if d2 < 1.0 || groups.len() >= MAX_GROUPS => {
                groups[i] = merge_pair(&groups[i], &c)
            }
            _ => groups.push(c),
        }
    }
    groups
}

/// Makes a covariance safely positive definite for the map contract. A covariance that no
/// jitter up to 10⁶ mends (non-finite entries) is returned as it is, for the map's validation
/// to refuse with its path, instead of looping.
fn spd(cov: &Matrix3<f64>) -> Matrix3<f64> {
    let mut c = symmetrize(cov);
    let mut jitter = 1e-9;
    while c.cholesky().is_none() && jitter <= 1e6 {
        c += Matrix3::identity() * jitter;
        jitter *= 10.0;
    }
    c
}

/// The id of the exported transmitter of track `track`.
pub fn transmitter_id(track: u64) -> String {
    format!("t{track}")
}

/// The id of the exported transmitter of identity `id`: [`transmitter_id`] of its track while
/// the track is bound to it, `t<track>.<identity>` for one a track left after a switch to
/// another path (`Filter::switch_tracks`), which no track names any more.
fn identity_id(filter: &Filter, id: usize) -> String {
    let track = filter.identities()[id].track;
    if filter.track_identity.get(&track) == Some(&(id as u32)) {
        transmitter_id(track)
    } else {
        format!("t{track}.{id}")
    }
}

/// The track an exported transmitter id names (inverse of [`transmitter_id`]; None for the
/// transmitter a track left behind).
pub fn track_of(id: &str) -> Option<u64> {
    id.strip_prefix('t').and_then(|k| k.parse().ok())
}

/// Builds the user map from the filter's current state.
pub fn export_map(filter: &Filter) -> Result<TransmitterMap, MapError> {
    let w = filter.weights();
    let n_id = filter.identities().len();
    // distinct transmitter states with their summed particle weight
    let mut distinct: Vec<HashMap<*const TxState, (f64, &TxState)>> = vec![HashMap::new(); n_id];
    for (p, wi) in filter.particles().iter().zip(&w) {
        for tx in &p.txs {
            let e = distinct[tx.identity as usize]
                .entry(std::sync::Arc::as_ptr(tx))
                .or_insert((0.0, tx));
            e.0 += wi;
        }
    }
    let cfg = filter.config();
    let mut transmitters = Vec::new();
    for (id, states) in distinct.iter().enumerate() {
        // deterministic order: by address is not stable across runs, so sort by content
        let mut states: Vec<(f64, &TxState)> = states.values().copied().collect();
        states.sort_by(|a, b| {
            b.0.total_cmp(&a.0).then_with(|| {
                let (ma, mb) = (a.1.comps[0].g.mean, b.1.comps[0].g.mean);
                ma.x.total_cmp(&mb.x)
                    .then(ma.y.total_cmp(&mb.y))
                    .then(ma.z.total_cmp(&mb.z))
            })
        });
        let existence: f64 = states.iter().map(|s| s.0).sum();
        if existence < 1e-6 {
            continue;
        }
        let reliability: f64 = states.iter().map(|(wi, tx)| wi * tx.reliability_m).sum();
        // particles whose weight underflowed to 0 contribute nothing (a zero-weight component
        // is not a valid map component)
        let pool: Vec<Component> = states
            .iter()
            .flat_map(|(wi, tx)| {
                tx.comps
                    .iter()
                    .map(move |c| Component::new(wi * c.weight / existence, c.g.mean, c.g.cov()))
            })
            .filter(|c| c.weight > 0.0)
            .collect();
        let mut comps = mixture::reduce(&collapse(pool), cfg.export_max_components.max(1));
        mixture::normalize(&mut comps).map_err(|_| MapError {
            path: format!("transmitters[t{}]", filter.identities()[id].track),
            kind: echomap_shared::map::MapErrorKind::Empty,
        })?;
        let floor = cfg.export_position_floor_m.powi(2);
        for c in &mut comps {
            c.cov[(0, 0)] += floor;
            c.cov[(1, 1)] += floor;
            c.cov = spd(&c.cov);
        }
        transmitters.push(Transmitter {
            id: identity_id(filter, id),
            components: comps,
            existence: existence.clamp(0.0, 1.0),
            reliability_m: reliability.max(0.0),
            visibility: filter.visibility().cells(id),
        });
    }
    // a long walk through rich multipath can leave more transmitters or visibility cells than
    // the format allows: keep those with the most evidence
    echomap_shared::map::fit_to_limits(&mut transmitters);
    TransmitterMap::new(cfg.hex_size_m, transmitters)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spd_mends_an_indefinite_covariance_and_gives_up_on_nan() {
        let indefinite = Matrix3::new(1.0, 2.0, 0.0, 2.0, 1.0, 0.0, 0.0, 0.0, 1.0);
        assert!(indefinite.cholesky().is_none());
        assert!(spd(&indefinite).cholesky().is_some());
        // a NaN covariance ends (and the map's validation refuses it) instead of looping
        let nan = Matrix3::identity() * f64::NAN;
        assert!(spd(&nan).iter().any(|v| v.is_nan()));
    }
}

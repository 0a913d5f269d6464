//! Version bodies stored as deltas. A merge keeps the prior's transmitters in place (matched
//! ones are replaced by their merge, Ulmschneider et al. 2021 eq. 22–26) and appends the unmatched user
//! transmitters, so version n differs from version n − 1 in the transmitters the upload
//! touched — about as many as the upload holds, not as many as the map. Inside a group
//! commit every version but the batch's last is stored as the changed transmitters only;
//! the last one (the map's head) is stored whole, so a version is at most one batch of
//! deltas away from a full body. Reading applies the deltas at the wire level
//! (`echomap.map.v1` documents, no re-validation) and yields byte for byte the document the
//! full body would have been.

use echomap_shared::map::TransmitterMap;
use echomap_shared::map::wire::{MapDoc, TransmitterDoc};
use serde::{Deserialize, Serialize};

pub const DELTA_FORMAT: &str = "echomap.map-delta.v1";

/// How a version body is stored (`versions.encoding`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    Full,
    Delta,
}

impl Encoding {
    pub fn as_str(self) -> &'static str {
        match self {
            Encoding::Full => "full",
            Encoding::Delta => "delta",
        }
    }
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Delta {
    format: String,
    /// transmitters of the parent version
    parent_transmitters: usize,
    /// (index, transmitter) of the parent's transmitters that changed
    replace: Vec<(usize, TransmitterDoc)>,
    /// transmitters after the parent's
    append: Vec<TransmitterDoc>,
}

/// The delta from `parent` to `next`, or None when `next` is not the parent with some
/// transmitters replaced and some appended (then store it whole).
pub fn encode(parent: &TransmitterMap, next: &TransmitterMap) -> Option<String> {
    let (p, n) = (parent.transmitters(), next.transmitters());
    if n.len() < p.len() || parent.hex_size_m() != next.hex_size_m() {
        return None;
    }
    let changed: Vec<usize> = (0..p.len()).filter(|&i| p[i] != n[i]).collect();
    let doc: MapDoc = next.clone().into();
    let mut txs: Vec<Option<TransmitterDoc>> = doc.transmitters.into_iter().map(Some).collect();
    let delta = Delta {
        format: DELTA_FORMAT.into(),
        parent_transmitters: p.len(),
        replace: changed
            .iter()
            .map(|&i| (i, txs[i].take().expect("each index once")))
            .collect(),
        append: txs
            .drain(p.len()..)
            .map(|t| t.expect("not taken"))
            .collect(),
    };
    serde_json::to_string(&delta).ok()
}

/// Applies `delta` to the parent document `parent` (both JSON), returning the new document.
pub fn apply(parent: &str, delta: &str) -> Result<String, String> {
    let mut doc: MapDoc =
        serde_json::from_str(parent).map_err(|e| format!("stored version body: {e}"))?;
    let d: Delta = serde_json::from_str(delta).map_err(|e| format!("stored delta: {e}"))?;
    if d.format != DELTA_FORMAT || d.parent_transmitters != doc.transmitters.len() {
        return Err(format!(
            "stored delta of format {:?} for {} transmitters does not fit a parent of {}",
            d.format,
            d.parent_transmitters,
            doc.transmitters.len()
        ));
    }
    for (i, t) in d.replace {
        *doc.transmitters
            .get_mut(i)
            .ok_or_else(|| format!("stored delta replaces transmitter {i} of a shorter map"))? = t;
    }
    doc.transmitters.extend(d.append);
    serde_json::to_string(&doc).map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use echomap_shared::map::{Beta, Transmitter};
    use echomap_shared::merging::{MergeConfig, merge_maps};
    use echomap_shared::mixture::Component;
    use nalgebra::{Isometry2, Matrix3, Vector3};
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use std::collections::BTreeMap;

    fn random_map(rng: &mut ChaCha8Rng, n: usize, tag: &str) -> TransmitterMap {
        let txs = (0..n)
            .map(|i| {
                let mut visibility = BTreeMap::new();
                visibility.insert(
                    echomap_shared::HexCell {
                        q: rng.random_range(-5..5),
                        r: rng.random_range(-5..5),
                    },
                    Beta {
                        alpha: rng.random::<f64>() * 9.0,
                        beta: rng.random::<f64>() * 9.0,
                    },
                );
                Transmitter {
                    id: format!("{tag}{i}"),
                    components: vec![Component::new(
                        1.0,
                        Vector3::new(
                            rng.random::<f64>() * 50.0,
                            rng.random::<f64>() * 50.0,
                            rng.random::<f64>() * 3.0,
                        ),
                        Matrix3::from_diagonal(&Vector3::new(0.1, 0.2, 0.3))
                            * (0.5 + rng.random::<f64>()),
                    )],
                    existence: rng.random::<f64>(),
                    reliability_m: rng.random::<f64>() * 100.0,
                    visibility,
                }
            })
            .collect();
        TransmitterMap::new(2.0, txs).unwrap()
    }

    #[test]
    fn a_merge_delta_restores_the_full_document_byte_for_byte() {
        for seed in 0..50 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let (n_prior, n_user) = (rng.random_range(1..60), rng.random_range(1..30));
            let prior = random_map(&mut rng, n_prior, "p");
            let user = random_map(&mut rng, n_user, "u");
            let pairs: Vec<(usize, usize)> = (0..user.len().min(prior.len()))
                .filter(|_| rng.random::<f64>() < 0.5)
                .map(|i| (i, prior.len() - 1 - i))
                .collect();
            let iso = Isometry2::new(nalgebra::Vector2::new(1.0, -2.0), 0.3);
            let (next, _) =
                merge_maps(&prior, &user, &iso, &pairs, &MergeConfig::default()).unwrap();
            let delta = encode(&prior, &next).expect("a merge is a delta");
            let full_prior = serde_json::to_string(&prior).unwrap();
            let full_next = serde_json::to_string(&next).unwrap();
            assert_eq!(
                apply(&full_prior, &delta).unwrap(),
                full_next,
                "seed {seed}"
            );
            // only what changed is stored
            assert!(delta.len() < full_next.len() || pairs.len() + user.len() >= prior.len());
        }
    }

    #[test]
    fn maps_that_are_not_a_merge_are_stored_whole_and_bad_deltas_are_errors() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let a = random_map(&mut rng, 10, "a");
        let b = random_map(&mut rng, 4, "b");
        assert!(encode(&a, &b).is_none(), "fewer transmitters: not a delta");
        let delta = encode(&b, &a).unwrap();
        let full_a = serde_json::to_string(&a).unwrap();
        // applied to the wrong parent: refused, not silently wrong
        assert!(apply(&full_a, &delta).is_err());
        assert!(apply(&full_a, "{}").is_err());
    }
}

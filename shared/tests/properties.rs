//! Property tests (proptest, fixed seed) of matching and merging: random maps of
//! 5–200 transmitters under a random rigid transform. The success-rate statistics over
//! thousands of seeded cases per setting are in `tests/matching.rs`; these check properties
//! that must hold for every case drawn.

use echomap_shared::map::{Beta, Transmitter, TransmitterMap};
use echomap_shared::matching::{MatchConfig, match_maps};
use echomap_shared::merging::{MergeConfig, merge_maps};
use echomap_shared::mixture::Component;
use echomap_shared::{HexCell, wrap_angle};
use nalgebra::{Isometry2, Matrix3, Point2, Vector2, Vector3};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngSeed};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeMap;

/// A map of the world points `pts` (map frame) seen from `agent_from_map`, each component
/// one Gaussian of std 0.15 m, mean displaced by `noise`.
fn map_of(
    pts: &[(f64, f64, f64, f64, f64)],
    agent_from_map: &Isometry2<f64>,
    prefix: &str,
) -> TransmitterMap {
    let s2 = 0.15f64 * 0.15;
    let txs = pts
        .iter()
        .enumerate()
        .map(|(i, &(x, y, b, nx, ny))| {
            let q = agent_from_map * Point2::new(x + nx, y + ny);
            let mut visibility = BTreeMap::new();
            visibility.insert(
                HexCell {
                    q: i as i32 % 7,
                    r: -(i as i32 % 5),
                },
                Beta {
                    alpha: 1.0 + (i % 3) as f64,
                    beta: (i % 2) as f64,
                },
            );
            Transmitter {
                id: format!("{prefix}{i}"),
                components: vec![Component::new(
                    1.0,
                    Vector3::new(q.x, q.y, b),
                    Matrix3::from_diagonal(&Vector3::new(s2, s2, s2)),
                )],
                existence: 0.5 + 0.5 * ((i * 7919) % 100) as f64 / 100.0,
                reliability_m: 5.0 + (i % 40) as f64,
                visibility,
            }
        })
        .collect();
    TransmitterMap::new(2.0, txs).unwrap()
}

/// World points on a jittered grid (spacing ≈ 8 m, so no two are confusable), 30 % with b > 0,
/// plus per-point noise of up to ±0.1 m for the user's view.
fn world(max: usize) -> impl Strategy<Value = Vec<(f64, f64, f64, f64, f64)>> {
    (5usize..=max).prop_flat_map(|n| {
        let side = (n as f64).sqrt().ceil() as usize;
        proptest::collection::vec(
            (
                -2.0..2.0f64,
                -2.0..2.0f64,
                0.0..1.0f64,
                -0.1..0.1f64,
                -0.1..0.1f64,
            ),
            n,
        )
        .prop_map(move |v| {
            v.into_iter()
                .enumerate()
                .map(|(i, (jx, jy, u, nx, ny))| {
                    let (gx, gy) = ((i % side) as f64 * 8.0, (i / side) as f64 * 8.0);
                    let b = if u < 0.3 { u * 100.0 } else { 0.0 };
                    (gx + jx, gy + jy, b, nx, ny)
                })
                .collect()
        })
    })
}

fn iso() -> impl Strategy<Value = Isometry2<f64>> {
    (-3.1..3.1f64, -200.0..200.0f64, -200.0..200.0f64)
        .prop_map(|(a, x, y)| Isometry2::new(Vector2::new(x, y), a))
}

fn config() -> Config {
    Config {
        cases: 96,
        rng_seed: RngSeed::Fixed(2026),
        failure_persistence: None,
        ..Config::default()
    }
}

proptest! {
    #![proptest_config(config())]

    /// Full overlap, small noise against the spacing: the transform is recovered within
    /// 0.02 rad and 0.3 m, and every correspondence is a true pair.
    #[test]
    fn full_overlap_recovers_the_transform(pts in world(200), truth in iso(), seed in 0u64..1000) {
        let exact: Vec<_> = pts.iter().map(|&(x, y, b, _, _)| (x, y, b, 0.0, 0.0)).collect();
        let prior = map_of(&exact, &Isometry2::identity(), "p");
        let user = map_of(&pts, &truth.inverse(), "u");
        let r = match_maps(&user, &prior, &MatchConfig::default(), &mut ChaCha8Rng::seed_from_u64(seed));
        prop_assert!(r.accepted, "rejected: {:?}", r.reason);
        let e = r.map_from_agent;
        prop_assert!(wrap_angle(e.rotation.angle() - truth.rotation.angle()).abs() < 0.02);
        // compare where both transforms put the user's centroid (the translation alone
        // depends on the frame's origin, far from the points)
        let c = user.transmitters().iter().map(|t| t.moments().0.xy()).sum::<Vector2<f64>>() / user.len() as f64;
        let d = (e * Point2::from(c) - truth * Point2::from(c)).norm();
        prop_assert!(d < 0.3, "centroid off by {d} m");
        prop_assert!(r.inliers >= pts.len() * 9 / 10);
        for &(u, p) in &r.correspondences {
            prop_assert_eq!(u, p, "wrong pair");
        }
    }

    /// Merging under any transform and any one-to-one correspondence set keeps the map
    /// valid: weights sum to 1, existence in [0, 1], prior ids kept and in place, sizes
    /// add up, reliabilities add, visibility counts are conserved, and it is deterministic.
    #[test]
    fn merge_keeps_the_map_valid(
        pts_p in world(60),
        pts_u in world(60),
        t in iso(),
        pick in proptest::collection::vec(any::<bool>(), 60),
    ) {
        let prior = map_of(&pts_p, &Isometry2::identity(), "p");
        let user = map_of(&pts_u, &Isometry2::identity(), "p"); // same ids on purpose
        let pairs: Vec<(usize, usize)> = (0..user.len().min(prior.len()))
            .filter(|&i| pick[i])
            .map(|i| (i, prior.len() - 1 - i))
            .collect();
        let (merged, stats) = merge_maps(&prior, &user, &t, &pairs, &MergeConfig::default()).unwrap();
        prop_assert_eq!(stats.merged, pairs.len());
        prop_assert_eq!(merged.len(), prior.len() + user.len() - pairs.len());
        // the result passes validation again
        let again_valid = TransmitterMap::new(merged.hex_size_m(), merged.transmitters().to_vec());
        prop_assert!(again_valid.is_ok());
        for tx in merged.transmitters() {
            let w: f64 = tx.components.iter().map(|c| c.weight).sum();
            prop_assert!((w - 1.0).abs() < 1e-9);
            prop_assert!((0.0..=1.0).contains(&tx.existence));
        }
        for (i, p) in prior.transmitters().iter().enumerate() {
            prop_assert_eq!(&merged.transmitters()[i].id, &p.id);
            let from_user = pairs.iter().find(|&&(_, pi)| pi == i).map(|&(ui, _)| &user.transmitters()[ui]);
            let expect = p.reliability_m + from_user.map_or(0.0, |u| u.reliability_m);
            prop_assert!((merged.transmitters()[i].reliability_m - expect).abs() < 1e-9);
        }
        let count = |m: &TransmitterMap| m.transmitters().iter().flat_map(|t| t.visibility.values()).map(|b| b.alpha + b.beta).sum::<f64>();
        prop_assert!((count(&merged) - count(&prior) - count(&user)).abs() < 1e-6);
        let (again, _) = merge_maps(&prior, &user, &t, &pairs, &MergeConfig::default()).unwrap();
        prop_assert_eq!(again, merged);
    }
}

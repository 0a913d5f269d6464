//! Matching and merging benchmarks on seeded synthetic maps.
//! Run: `cargo bench -p echomap-shared --bench matching`.

use criterion::{Criterion, criterion_group, criterion_main};
use echomap_shared::map::{Transmitter, TransmitterMap};
use echomap_shared::matching::{MatchConfig, match_maps};
use echomap_shared::merging::{MergeConfig, merge_maps};
use echomap_shared::mixture::Component;
use nalgebra::{Isometry2, Matrix3, Point2, Vector2, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::hint::black_box;

/// `shared` common transmitters plus `outliers` in each map; user map in another frame.
fn maps(
    shared: usize,
    outliers: usize,
    seed: u64,
) -> (TransmitterMap, TransmitterMap, Isometry2<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let side = ((shared + outliers) as f64).sqrt() * 8.0;
    let truth = Isometry2::new(Vector2::new(30.0, -12.0), 1.1);
    let inv = truth.inverse();
    let mk = |id: String, p: Point2<f64>, b: f64| Transmitter {
        id,
        components: vec![Component::new(
            1.0,
            Vector3::new(p.x, p.y, b),
            Matrix3::identity() * 0.0225,
        )],
        existence: 1.0,
        reliability_m: 20.0,
        visibility: Default::default(),
    };
    let (mut u, mut p) = (Vec::new(), Vec::new());
    for i in 0..shared + outliers {
        let w = Point2::new(rng.random::<f64>() * side, rng.random::<f64>() * side);
        let b = if rng.random::<f64>() < 0.3 {
            rng.random::<f64>() * 30.0
        } else {
            0.0
        };
        if i < shared {
            p.push(mk(format!("p{i}"), w, b));
            u.push(mk(format!("u{i}"), inv * w, b));
        } else {
            let w2 = Point2::new(rng.random::<f64>() * side, rng.random::<f64>() * side);
            p.push(mk(format!("p{i}"), w, b));
            u.push(mk(format!("u{i}"), inv * w2, b));
        }
    }
    (
        TransmitterMap::new(2.0, u).unwrap(),
        TransmitterMap::new(2.0, p).unwrap(),
        truth,
    )
}

fn bench(c: &mut Criterion) {
    let cfg = MatchConfig::default();
    let (u50, p50, _) = maps(25, 25, 1); // 50 vs 50, 50 % outliers
    // the timed cases must be real matches
    assert!(match_maps(&u50, &p50, &cfg, &mut ChaCha8Rng::seed_from_u64(1)).accepted);
    c.bench_function("match/50_vs_50_half_outliers", |b| {
        b.iter(|| {
            match_maps(
                black_box(&u50),
                black_box(&p50),
                &cfg,
                &mut ChaCha8Rng::seed_from_u64(1),
            )
        })
    });
    let (u500, p500, _) = maps(250, 250, 2);
    let r = match_maps(&u500, &p500, &cfg, &mut ChaCha8Rng::seed_from_u64(1));
    assert!(r.accepted && r.inliers >= 240, "{:?}", r.reason);
    let mut g = c.benchmark_group("match_large");
    g.sample_size(10);
    g.bench_function("500_vs_500_half_outliers", |b| {
        b.iter(|| {
            match_maps(
                black_box(&u500),
                black_box(&p500),
                &cfg,
                &mut ChaCha8Rng::seed_from_u64(1),
            )
        })
    });
    g.finish();
    let (u, p, truth) = maps(500, 0, 3);
    let pairs: Vec<(usize, usize)> = (0..500).map(|i| (i, i)).collect();
    c.bench_function("merge/500", |b| {
        b.iter(|| {
            merge_maps(
                black_box(&p),
                black_box(&u),
                &truth,
                &pairs,
                &MergeConfig::default(),
            )
            .unwrap()
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);

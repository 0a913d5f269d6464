//! Simulator benchmark: the whole urban reference track (≈1000 snapshots, 500 m at 10 m/s,
//! 20 Hz, 24 walls + 8 scatterers traced to second order) and the indoor reference track.
//! Run: `cargo bench -p echomap-agent --bench simulate`

use criterion::{Criterion, criterion_group, criterion_main};
use echomap_agent::sim::builtin;
use echomap_agent::sim::simulate::{SimOptions, simulate};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("simulate");
    g.sample_size(20);
    for name in ["urban", "indoor"] {
        let scn = builtin::builtin(name).unwrap();
        g.bench_function(format!("{name}/reference"), |b| {
            b.iter(|| {
                simulate(
                    black_box(&scn),
                    "reference",
                    SimOptions {
                        seed: 1,
                        toa_only: false,
                    },
                )
                .unwrap()
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

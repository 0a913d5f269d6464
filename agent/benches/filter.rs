//! Filter benchmarks: one square-root cubature component update (as the filter makes it), and whole filter steps on
//! the urban reference track (the first 200 snapshots = 10 s of data at 20 Hz) with 1000
//! and 4000 particles. Run: `cargo bench -p echomap-agent --bench filter`.
//! Real-time factor = 10 s / (median time of the 200-snapshot run).

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use echomap_agent::filter::model::{Pose, residual_toa_aoa, toa_aoa_images};
use echomap_agent::filter::srckf::{SqrtGaussian, predict_images, update_predicted};
use echomap_agent::filter::{Filter, FilterConfig};
use echomap_agent::sim::builtin;
use echomap_agent::sim::simulate::{SimOptions, simulate};
use nalgebra::{Matrix2, Matrix3, Vector2, Vector3};
use std::hint::black_box;

fn component_update(c: &mut Criterion) {
    let pose = Pose {
        x: 1.0,
        y: -2.0,
        heading: 0.3,
        speed: 1.0,
    };
    let g = SqrtGaussian::from_cov(
        Vector3::new(20.0, 5.0, 1.0),
        &Matrix3::from_diagonal(&Vector3::new(4.0, 1.0, 0.5)),
    )
    .unwrap();
    let z = Vector2::new(21.5, 0.05);
    let r = Matrix2::from_diagonal(&Vector2::new(0.3, 0.07));
    c.bench_function("srckf/component_update", |b| {
        b.iter(|| {
            // as the filter updates a component: the cubature images, then the update
            let g = black_box(&g);
            let p = predict_images(
                g,
                |pts| toa_aoa_images(&pose, pts),
                residual_toa_aoa,
                &(r * r.transpose()),
            );
            update_predicted(g, black_box(&z), &r, &p, residual_toa_aoa).unwrap()
        })
    });
}

fn filter_steps(c: &mut Criterion) {
    let out = simulate(
        &builtin::urban(),
        "reference",
        SimOptions {
            seed: 1,
            toa_only: false,
        },
    )
    .unwrap();
    let snaps = &out.log.snapshots[..200];
    let mut g = c.benchmark_group("filter/urban_200_snapshots");
    g.sample_size(10);
    for particles in [1000usize, 4000] {
        g.bench_with_input(
            BenchmarkId::from_parameter(particles),
            &particles,
            |b, &n| {
                b.iter(|| {
                    let cfg = FilterConfig {
                        particles: n,
                        seed: 1,
                        initial_speed_mps: 10.0,
                        ..FilterConfig::default()
                    };
                    let mut f = Filter::new(cfg, true);
                    for s in snaps {
                        black_box(f.step(s));
                    }
                })
            },
        );
    }
    g.finish();
}

criterion_group!(benches, component_update, filter_steps);
criterion_main!(benches);

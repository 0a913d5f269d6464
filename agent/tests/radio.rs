//! The channel estimator against its theory: a single path's delay and angle errors against
//! the Cramér–Rao bound, and two equal paths one inverse bandwidth apart. Seeded Monte Carlo
//! trials; the tolerances are stated with each test.

use echomap_agent::radio::array::{ArrayModel, uniform_circular};
use echomap_agent::radio::sage::{PathEstimate, SageConfig, SnapshotData, estimate};
use nalgebra::Complex;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// An 8-element uniform circular array at half-wavelength spacing, 1.5 GHz, sampled at the
/// bandwidth.
fn uca8() -> ArrayModel {
    let wavelength_m = 299_792_458.0 / 1.5e9;
    let radius_m = wavelength_m / (4.0 * (std::f64::consts::PI / 8.0).sin());
    ArrayModel {
        elements_m: uniform_circular(8, radius_m),
        wavelength_m,
        rho: 1.0,
    }
}

/// The samples of `paths` (delay, angle, amplitude) in unit-variance complex noise.
fn snapshot(
    model: &ArrayModel,
    samples: usize,
    paths: &[(f64, f64, Complex<f64>)],
    rng: &mut ChaCha8Rng,
) -> Vec<Complex<f64>> {
    let m = model.elements();
    let mut y = vec![Complex::new(0.0, 0.0); m * samples];
    for (e, x) in y.iter_mut().enumerate() {
        let re: f64 = rng.sample(StandardNormal);
        let im: f64 = rng.sample(StandardNormal);
        *x = Complex::new(re, im) * std::f64::consts::FRAC_1_SQRT_2;
        let (el, n) = (e / samples, e % samples);
        for &(tau, th, alpha) in paths {
            *x += alpha * model.steering(th)[el] * model.pulse(n as f64 - tau);
        }
    }
    y
}

/// The correlator's processing gain the per-sample SNRs below are taken before (64 samples,
/// as the simulator's estimator integrates).
const GAIN: f64 = 64.0;

#[test]
fn a_single_paths_errors_are_within_one_and_a_half_times_the_cramer_rao_bound() {
    let model = uca8();
    let samples = 64;
    let cfg = SageConfig::default();
    for snr_db in [0.0, 10.0, 20.0, 30.0] {
        let snr = 10f64.powf(snr_db / 10.0) * GAIN;
        let mut rng = ChaCha8Rng::seed_from_u64(7 + snr_db as u64);
        let trials = 300;
        let (mut se_tau, mut se_th, mut bound_tau, mut bound_th) = (0.0, 0.0, 0.0, 0.0);
        let mut missed = 0;
        for _ in 0..trials {
            let tau = 10.0 + 40.0 * rng.random::<f64>();
            let th = std::f64::consts::PI * (2.0 * rng.random::<f64>() - 1.0);
            let phase = std::f64::consts::TAU * rng.random::<f64>();
            let alpha = Complex::from_polar(snr.sqrt(), phase);
            let y = snapshot(&model, samples, &[(tau, th, alpha)], &mut rng);
            let found = estimate(&model, SnapshotData { data: &y, samples }, 1.0, &[], &cfg);
            let Some(p) = found
                .iter()
                .max_by(|a, b| a.statistic.total_cmp(&b.statistic))
            else {
                missed += 1;
                continue;
            };
            let (b_tau, b_th) = model.crb(samples, tau, th, snr);
            se_tau += (p.delay - tau).powi(2);
            se_th += echomap_shared::wrap_angle(p.aoa_rad - th).powi(2);
            bound_tau += b_tau * b_tau;
            bound_th += b_th * b_th;
        }
        let ratio_tau = (se_tau / bound_tau).sqrt();
        let ratio_th = (se_th / bound_th).sqrt();
        println!(
            "SNR {snr_db:>4} dB/sample: delay RMSE/CRB {ratio_tau:.3}, angle RMSE/CRB {ratio_th:.3}, CRB {:.4} samples {:.5} rad, missed {missed}/{trials}",
            (bound_tau / trials as f64).sqrt(),
            (bound_th / trials as f64).sqrt()
        );
        assert_eq!(missed, 0, "{snr_db} dB");
        assert!(ratio_tau <= 1.5, "{snr_db} dB: delay {ratio_tau}");
        assert!(ratio_th <= 1.5, "{snr_db} dB: angle {ratio_th}");
    }
}

#[test]
fn two_equal_paths_one_inverse_bandwidth_apart_are_resolved() {
    let model = uca8();
    let samples = 64;
    let cfg = SageConfig::default();
    let snr = 10f64.powf(10.0 / 10.0) * GAIN;
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let trials = 200;
    let mut resolved = 0;
    for _ in 0..trials {
        // 1/B apart (one sample at f_s = B), same angle: the delay alone must part them
        let tau = 20.0 + 20.0 * rng.random::<f64>();
        let th = std::f64::consts::PI * (2.0 * rng.random::<f64>() - 1.0);
        let p1 = std::f64::consts::TAU * rng.random::<f64>();
        let p2 = std::f64::consts::TAU * rng.random::<f64>();
        let truth = [
            (tau, th, Complex::from_polar(snr.sqrt(), p1)),
            (tau + 1.0, th, Complex::from_polar(snr.sqrt(), p2)),
        ];
        let y = snapshot(&model, samples, &truth, &mut rng);
        let found: Vec<PathEstimate> =
            estimate(&model, SnapshotData { data: &y, samples }, 1.0, &[], &cfg);
        // resolved: two estimates, each within a quarter of the separation of its own path
        let near = |t: f64| {
            found.iter().any(|p| {
                (p.delay - t).abs() < 0.25 && echomap_shared::wrap_angle(p.aoa_rad - th).abs() < 0.1
            })
        };
        if found.len() == 2 && near(tau) && near(tau + 1.0) {
            resolved += 1;
        }
    }
    println!("two equal paths 1/B apart at 10 dB/sample: {resolved}/{trials} resolved");
    assert!(resolved * 10 >= trials * 9, "{resolved}/{trials}");
}

#[test]
fn noise_alone_rarely_makes_a_path() {
    let model = uca8();
    let samples = 64;
    let cfg = SageConfig::default();
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let trials = 2000;
    let with_path = (0..trials)
        .filter(|_| {
            let y = snapshot(&model, samples, &[], &mut rng);
            !estimate(&model, SnapshotData { data: &y, samples }, 1.0, &[], &cfg).is_empty()
        })
        .count();
    // at most P_fa = 10⁻³ per snapshot: at most 2 expected in 2,000; 8 or more would happen
    // with probability 0.001 at that rate
    println!("noise alone: {with_path}/{trials} snapshots with a path");
    assert!(with_path < 8, "{with_path}/{trials}");
}

mod cir_files {
    use echomap_agent::radio::cir::{CIR_FORMAT, Cir, CirMeta, CirSnapshot};
    use nalgebra::Complex;
    use std::path::Path;

    fn small() -> Cir {
        let meta = CirMeta {
            format: CIR_FORMAT.to_string(),
            carrier_hz: 1.5e9,
            bandwidth_hz: 1e8,
            sample_rate_hz: 1e8,
            pulse: "sinc".to_string(),
            delay_origin_m: 0.0,
            samples: 5,
            elements_m: vec![[0.0, 0.0], [0.1, 0.0]],
            processing_gain: 64.0,
            noise_variance: None,
            snapshot_rate_hz: 10.0,
            speed: true,
            source: Some("test".into()),
            odometry: None,
            snapshots: (0..3)
                .map(|k| CirSnapshot {
                    t: k as f64 * 0.1,
                    gyro: 0.01 * k as f64,
                    speed: Some(1.0),
                })
                .collect(),
        };
        let data = (0..30)
            .map(|i| Complex::new(i as f32, -(i as f32) / 2.0))
            .collect();
        Cir { meta, data }
    }

    fn message(dir: &Path) -> String {
        Cir::read(dir).expect_err("must be refused").to_string()
    }

    #[test]
    fn a_cir_reads_back_as_written() {
        let dir = tempfile::tempdir().unwrap();
        let cir = small();
        cir.write(dir.path()).unwrap();
        assert_eq!(Cir::read(dir.path()).unwrap(), cir);
    }

    #[test]
    fn bad_cirs_are_refused_with_the_file_and_field_named() {
        let dir = tempfile::tempdir().unwrap();
        let cir = small();
        cir.write(dir.path()).unwrap();
        let npy = dir.path().join("cir.npy");
        let json = dir.path().join("cir.json");
        let good_npy = std::fs::read(&npy).unwrap();
        let good_json = std::fs::read_to_string(&json).unwrap();

        // a truncated sample file
        std::fs::write(&npy, &good_npy[..good_npy.len() - 7]).unwrap();
        let e = message(dir.path());
        assert!(e.contains("cir.npy"), "{e}");
        std::fs::write(&npy, &good_npy).unwrap();

        // a NaN sample: named by snapshot, element and sample
        let mut nan = cir.clone();
        nan.data[17] = Complex::new(f32::NAN, 0.0);
        let other = tempfile::tempdir().unwrap();
        nan.write(other.path()).unwrap();
        let e = message(other.path());
        assert!(
            e.contains("cir.npy") && e.contains("snapshot 1 element 1 sample 2"),
            "{e}"
        );

        // a shape that disagrees with the metadata
        let mut meta = cir.meta.clone();
        meta.samples = 6;
        std::fs::write(&json, serde_json::to_string(&meta).unwrap()).unwrap();
        let e = message(dir.path());
        assert!(e.contains("cir.npy") && e.contains("shape"), "{e}");

        // fields out of range or missing, each named
        for (edit, field) in [
            (
                ("\"sample_rate_hz\": 100000000.0", "\"sample_rate_hz\": 1.0"),
                "sample_rate_hz",
            ),
            (("\"pulse\": \"sinc\"", "\"pulse\": \"gauss\""), "pulse"),
            (
                ("\"format\": \"echomap.cir.v1\"", "\"format\": \"x\""),
                "format",
            ),
            (("\"carrier_hz\": 1500000000.0,", ""), "carrier_hz"),
        ] {
            let text = good_json.replace(edit.0, edit.1);
            assert_ne!(text, good_json, "{field}: the edit must apply");
            std::fs::write(&json, text).unwrap();
            let e = message(dir.path());
            assert!(e.contains("cir.json") && e.contains(field), "{field}: {e}");
        }
    }
}

/// The front end on the first 15 s of a simulated channel of the urban reference track: the
/// paths that stand apart from the others (SNR ≥ 0 dB) and how many of them it finds within
/// 0.5 m and 0.1 rad, with the log it wrote.
fn front_end_on_urban(
    scenario: &echomap_agent::sim::Scenario,
) -> (usize, usize, echomap_shared::log::MeasurementLog, usize) {
    use echomap_agent::radio::estimate::{FrontEndConfig, front_end};
    use echomap_agent::sim::channel::synthesize;
    use echomap_agent::sim::simulate::{SimOptions, simulate_paths};
    let (sim, paths) = simulate_paths(
        scenario,
        "reference",
        SimOptions {
            seed: 3,
            toa_only: false,
        },
        true,
    )
    .unwrap();
    let paths = paths.unwrap();
    let mut cir = synthesize(scenario, &sim.log, &paths, true, 3);
    let elements = cir.meta.elements_m.len();
    // the first 15 s keep the test short
    let keep = 150;
    let per = elements * cir.meta.samples;
    cir.meta.snapshots.truncate(keep);
    cir.data.truncate(keep * per);
    // every track, also those followed for less than the log's confirmation time: what the
    // estimator and tracker find
    let every = FrontEndConfig {
        min_track_s: 0.0,
        ..FrontEndConfig::default()
    };
    let (log, stats) = front_end(&cir, &every);
    let resolution_m = cir.meta.metres_per_sample();
    let (mut apart, mut found) = (0, 0);
    for (truth, est) in paths.iter().zip(&log.snapshots).take(keep) {
        for (i, c) in truth.iter().enumerate() {
            let alone = truth.iter().enumerate().all(|(j, o)| {
                i == j
                    || o.snr_db < c.snr_db - 10.0
                    || (o.distance_m - c.distance_m).abs() > resolution_m
            });
            if c.snr_db < 0.0 || !alone {
                continue;
            }
            apart += 1;
            found += usize::from(est.components.iter().any(|e| {
                (e.d - c.distance_m).abs() < 0.5
                    && echomap_shared::wrap_angle(e.aoa.unwrap() - c.aoa_rad).abs() < 0.1
            }));
        }
    }
    println!(
        "front end, urban reference, first {keep} snapshots, {elements} elements: {found}/{apart} paths that stand apart (SNR ≥ 0 dB) found within 0.5 m and 0.1 rad; {:.1} paths per snapshot, {} tracks",
        stats.paths_per_snapshot, stats.tracks
    );
    (found, apart, log, elements)
}

/// The front end on a simulated channel: the paths that stand apart from the others and are
/// as strong as the simulator's estimator model needs to report them are found again in
/// their sampled channel, close to where they are, under few track ids.
#[test]
fn the_front_end_finds_the_simulated_paths_in_their_sampled_channel() {
    let scenario = echomap_agent::sim::builtin::builtin("urban").unwrap();
    let (found, apart, log, elements) = front_end_on_urban(&scenario);
    assert_eq!(elements, 9);
    // measured 50/60 (2026-12-06); the guard leaves room for the multipath that
    // interferes with a path from more than one sample away
    assert!(apart >= 50, "{apart}");
    assert!(found * 4 >= apart * 3, "{found}/{apart}");
    let sensor = log.header.sensor.expect("the front end states its noise");
    assert!(sensor.distance_m.unwrap().at_0db > 0.0 && sensor.aoa_rad.unwrap().at_0db > 0.0);
}

/// The same with a uniform circular array of 8 elements: the simulator lays the elements out
/// on the circle, and the front end reads the layout from the CIR and finds the paths as well.
#[test]
fn the_front_end_finds_the_paths_with_a_circular_array_too() {
    use echomap_agent::sim::scenario::ArrayGeometry;
    let mut scenario = echomap_agent::sim::builtin::builtin("urban").unwrap();
    scenario.receiver.array_geometry = ArrayGeometry::Circular;
    scenario.receiver.array_elements = 8;
    scenario.validate().unwrap();
    let (found, apart, log, elements) = front_end_on_urban(&scenario);
    assert_eq!(elements, 8);
    assert!(apart >= 50, "{apart}");
    assert!(found * 4 >= apart * 3, "{found}/{apart}");
    let sensor = log.header.sensor.expect("the front end states its noise");
    assert!(
        !sensor.name.unwrap_or_default().is_empty(),
        "the front end names its sensor"
    );
    // the front end says how heavy its errors' tails are (0: Gaussian; over these first
    // 150 snapshots it measured 0, over the whole walk 2)
    let dof = sensor.noise_dof.expect("the front end states its tails");
    println!("front end, circular array: tails of a Student-t with ν = {dof}");
    assert!(dof == 0.0 || (1.0..=30.0).contains(&dof), "ν = {dof}");
    // the simulated odometry's description passes through the channel file: its gyroscope
    // has the scenario's bias (none), not the data-sheet default of a log that states nothing
    let odometry = sensor
        .odometry
        .expect("the simulator's odometry is passed on");
    assert_eq!(odometry.gyro_bias_rad_per_s, Some(0.0));
}

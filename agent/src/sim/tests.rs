//! Simulator tests: noise statistics over whole tracks, reproducibility, track-id semantics,
//! resolution, gyro, and rejection of bad scenarios.

use super::builtin::{indoor, urban};
use super::scenario::{Scenario, ScenarioError, Track};
use super::simulate::{SimOptions, simulate};
use echomap_shared::wrap_angle;
use std::collections::HashMap;

fn opts(seed: u64) -> SimOptions {
    SimOptions {
        seed,
        toa_only: false,
    }
}

/// Normalized residuals of distance and AoA against the ground truth, using the documented
/// noise law evaluated at each component's reported SNR.
fn normalized_residuals(scn: &Scenario, track: &str, seed: u64) -> (Vec<f64>, Vec<f64>) {
    let out = simulate(scn, track, opts(seed)).unwrap();
    let truth: HashMap<u64, [f64; 3]> = out
        .truth
        .transmitters
        .iter()
        .map(|t| (t.track, t.state))
        .collect();
    let (mut zd, mut za) = (Vec::new(), Vec::new());
    for (snap, pose) in out.log.snapshots.iter().zip(&out.truth.poses) {
        assert_eq!(snap.t, pose.t);
        for c in &snap.components {
            let v = truth[&c.track];
            let (dx, dy) = (v[0] - pose.x, v[1] - pose.y);
            let d_true = dx.hypot(dy) + v[2];
            let (sd, sa) = scn.noise_std(c.snr_db);
            zd.push((c.d - d_true) / sd);
            let a_true = wrap_angle(dy.atan2(dx) - pose.heading_rad);
            za.push(wrap_angle(c.aoa.unwrap() - a_true) / sa);
        }
    }
    (zd, za)
}

fn mean_std(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    (
        m,
        (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt(),
    )
}

#[test]
fn measurement_noise_matches_the_documented_law() {
    // Over whole tracks of both scenarios and several seeds: the residual
    // d − (‖p_user − p_vtx‖ + b), divided by the law's σ, has mean ≈ 0 and std ≈ 1.
    for (scn, seeds) in [(indoor(), [1u64, 2, 3]), (urban(), [4, 5, 6])] {
        let (mut zd, mut za) = (Vec::new(), Vec::new());
        for seed in seeds {
            let (d, a) = normalized_residuals(&scn, "reference", seed);
            zd.extend(d);
            za.extend(a);
        }
        assert!(
            zd.len() > 10_000,
            "{}: only {} components",
            scn.name,
            zd.len()
        );
        let (md, sd) = mean_std(&zd);
        let (ma, sa) = mean_std(&za);
        // With n > 10⁴ samples the standard error of the mean is < 0.01 and of the std < 0.01.
        assert!(md.abs() < 0.04, "{}: distance residual mean {md}", scn.name);
        assert!(
            (sd - 1.0).abs() < 0.04,
            "{}: distance residual std {sd}",
            scn.name
        );
        assert!(ma.abs() < 0.04, "{}: aoa residual mean {ma}", scn.name);
        assert!(
            (sa - 1.0).abs() < 0.04,
            "{}: aoa residual std {sa}",
            scn.name
        );
    }
}

#[test]
fn same_seed_same_bytes_different_seed_different_noise() {
    let scn = urban();
    let a = simulate(&scn, "reference", opts(7)).unwrap();
    let b = simulate(&scn, "reference", opts(7)).unwrap();
    let c = simulate(&scn, "reference", opts(8)).unwrap();
    assert_eq!(a.log.to_jsonl(), b.log.to_jsonl());
    assert_eq!(
        serde_json::to_string(&a.truth).unwrap(),
        serde_json::to_string(&b.truth).unwrap()
    );
    assert_ne!(a.log.to_jsonl(), c.log.to_jsonl());
    // the trajectory itself does not depend on the seed
    assert_eq!(a.truth.poses, c.truth.poses);
}

/// A minimal scenario: transmitter, optional walls, one straight track, no fading/losses.
fn simple(walls: Vec<super::scenario::Wall>, waypoints: Vec<[f64; 2]>) -> Scenario {
    let mut s = indoor();
    s.walls = walls;
    s.scatterers.clear();
    s.transmitter.position = [0.0, 10.0];
    s.transmitter.power_dbm = 0.0;
    s.estimator.fading_std_db = 0.0;
    s.estimator.track_loss_rate_hz = 0.0;
    s.tracks = vec![Track {
        name: "t".into(),
        speed_mps: 1.0,
        waypoints,
        turn_radius_m: 0.0,
    }];
    s
}

#[test]
fn a_blocked_and_regained_component_gets_a_new_track_id() {
    // The line of sight from (0,10) to the track y = 0 is blocked by a short wall at y = 5
    // while the user is near x = 0: id before ≠ id after, both the physical transmitter.
    let blocker = super::scenario::Wall {
        from: [-1.0, 5.0],
        to: [1.0, 5.0],
        reflection_loss_db: 3.0,
    };
    let scn = simple(vec![blocker], vec![[-10.0, 0.0], [10.0, 0.0]]);
    let out = simulate(&scn, "t", opts(1)).unwrap();
    let mut ids = Vec::new();
    let mut gaps = 0;
    let mut prev_present = true;
    for s in &out.log.snapshots {
        let present = !s.components.is_empty();
        if let Some(c) = s.components.first()
            && ids.last() != Some(&c.track)
        {
            ids.push(c.track);
        }
        if prev_present && !present {
            gaps += 1;
        }
        prev_present = present;
    }
    assert_eq!(gaps, 1);
    assert_eq!(ids.len(), 2, "ids {ids:?}");
    for t in &out.truth.transmitters {
        assert_eq!(t.kind, "physical");
    }
    assert_eq!(out.truth.transmitters.len(), 2);
}

#[test]
fn random_track_losses_renew_ids() {
    let mut scn = simple(vec![], vec![[-10.0, 0.0], [10.0, 0.0]]);
    scn.estimator.track_loss_rate_hz = 0.5;
    let out = simulate(&scn, "t", opts(3)).unwrap();
    // 20 s at 0.5 losses/s: expect about 10 renewals; with none, there would be one id.
    let ids = out.truth.transmitters.len();
    assert!((4..=20).contains(&ids), "{ids} ids");
}

/// Per track id: (first, last) snapshot index of its detections.
fn track_spans(out: &super::simulate::SimOutput) -> HashMap<u64, (usize, usize)> {
    let mut span = HashMap::new();
    for (k, s) in out.log.snapshots.iter().enumerate() {
        for m in &s.components {
            span.entry(m.track)
                .and_modify(|e: &mut (usize, usize)| e.1 = k)
                .or_insert((k, k));
        }
    }
    span
}

#[test]
fn short_tracks_are_left_out_as_seed_002_does() {
    let mut all = urban();
    all.estimator.min_track_distance_m = 0.0;
    let paper = urban();
    assert_eq!(paper.estimator.min_track_distance_m, 35.0);
    let track = &paper.tracks[0];
    let step = track.speed_mps / paper.snapshot_rate_hz;
    for seed in [1, 2] {
        let full = simulate(&all, &track.name, opts(seed)).unwrap();
        let kept = simulate(&paper, &track.name, opts(seed)).unwrap();
        let (full_span, kept_span) = (track_spans(&full), track_spans(&kept));
        // the kept tracks are exactly the long ones of the unfiltered run, with the same
        // detections (the selection happens after the random draws)
        let long: Vec<u64> = full_span
            .iter()
            .filter(|(_, (a, b))| (b - a) as f64 * step >= 35.0)
            .map(|(t, _)| *t)
            .collect();
        assert!(
            !long.is_empty() && long.len() < full_span.len(),
            "seed {seed}"
        );
        let mut kept_ids: Vec<u64> = kept_span.keys().copied().collect();
        let mut long_ids = long.clone();
        kept_ids.sort_unstable();
        long_ids.sort_unstable();
        assert_eq!(kept_ids, long_ids, "seed {seed}");
        for (a, b) in full.log.snapshots.iter().zip(&kept.log.snapshots) {
            let expect: Vec<_> = a
                .components
                .iter()
                .filter(|m| long.contains(&m.track))
                .collect();
            assert_eq!(expect, b.components.iter().collect::<Vec<_>>());
        }
        // the truth lists the transmitters of the kept tracks only
        let mut truth_ids: Vec<u64> = kept.truth.transmitters.iter().map(|t| t.track).collect();
        truth_ids.sort_unstable();
        assert_eq!(truth_ids, long_ids, "seed {seed}");
        assert_eq!(full.truth.poses, kept.truth.poses);
    }
}

#[test]
fn unresolvable_paths_are_reported_once() {
    // Single antenna (delay resolution only). A wall just behind the track line (y = −0.5):
    // the reflection is < 1 m longer than LoS, below c/B = 3 m: one component is reported.
    let wall = super::scenario::Wall {
        from: [-50.0, -0.5],
        to: [50.0, -0.5],
        reflection_loss_db: 3.0,
    };
    let mut scn = simple(vec![wall.clone()], vec![[-10.0, 0.0], [-9.0, 0.0]]);
    scn.receiver.aoa = false;
    let out = simulate(&scn, "t", opts(1)).unwrap();
    assert!(out.log.snapshots.iter().all(|s| s.components.len() == 1));
    // Move the wall far away (y = −20): both paths resolve.
    let far = super::scenario::Wall {
        from: [-50.0, -20.0],
        to: [50.0, -20.0],
        ..wall
    };
    let mut scn = simple(vec![far], vec![[-10.0, 0.0], [-9.0, 0.0]]);
    scn.receiver.aoa = false;
    let out = simulate(&scn, "t", opts(1)).unwrap();
    assert!(out.log.snapshots.iter().all(|s| s.components.len() == 2));
    // With the array, the near wall's reflection (≈ 93° away in angle) is resolved too.
    let scn = simple(vec![wall], vec![[-10.0, 0.0], [-9.0, 0.0]]);
    let out = simulate(&scn, "t", opts(1)).unwrap();
    assert!(out.log.snapshots.iter().all(|s| s.components.len() == 2));
}

#[test]
fn gyro_integrates_to_the_true_heading() {
    let mut scn = indoor();
    scn.gyro.noise_std_rad_s = 0.0;
    let out = simulate(&scn, "reference", opts(1)).unwrap();
    let dt = 1.0 / scn.snapshot_rate_hz;
    let mut heading = 0.0;
    for (s, p) in out.log.snapshots.iter().zip(&out.truth.poses) {
        heading = wrap_angle(heading + s.gyro * dt);
        assert!(wrap_angle(heading - p.heading_rad).abs() < 1e-9);
    }
    // starts at the local origin, heading +x
    let p0 = &out.truth.poses[0];
    assert!(p0.x.abs() < 1e-12 && p0.y.abs() < 1e-12 && p0.heading_rad.abs() < 1e-12);
}

#[test]
fn toa_only_drops_angles() {
    let out = simulate(
        &indoor(),
        "user03",
        SimOptions {
            seed: 1,
            toa_only: true,
        },
    )
    .unwrap();
    assert!(!out.log.header.aoa);
    assert!(
        out.log
            .snapshots
            .iter()
            .flat_map(|s| &s.components)
            .all(|c| c.aoa.is_none())
    );
    // and it parses back through the log reader
    echomap_shared::log::MeasurementLog::parse(&out.log.to_jsonl()).unwrap();
}

#[test]
fn bad_scenarios_name_the_field() {
    let base = serde_json::to_value(indoor()).unwrap();
    type Edit = Box<dyn Fn(&mut serde_json::Value)>;
    let cases: Vec<(&str, Edit)> = vec![
        (
            "carrier_hz",
            Box::new(|v| v["carrier_hz"] = serde_json::json!(null)),
        ),
        (
            "bandwidth_hz",
            Box::new(|v| v["bandwidth_hz"] = serde_json::json!(-1.0)),
        ),
        (
            "snapshot_rate_hz",
            Box::new(|v| v["snapshot_rate_hz"] = serde_json::json!(0.0)),
        ),
        (
            "walls[3]",
            Box::new(|v| v["walls"][3]["to"] = v["walls"][3]["from"].clone()),
        ),
        (
            "walls[0].reflection_loss_db",
            Box::new(|v| v["walls"][0]["reflection_loss_db"] = serde_json::json!(-3.0)),
        ),
        (
            "scatterers[1].scattering_loss_db",
            Box::new(|v| v["scatterers"][1]["scattering_loss_db"] = serde_json::json!("a lot")),
        ),
        (
            "tracks[2].waypoints",
            Box::new(|v| v["tracks"][2]["waypoints"] = serde_json::json!([[1.0, 2.0]])),
        ),
        (
            "tracks[0].speed_mps",
            Box::new(|v| v["tracks"][0]["speed_mps"] = serde_json::json!(0.0)),
        ),
        (
            "tracks[1].name",
            Box::new(|v| v["tracks"][1]["name"] = serde_json::json!("reference")),
        ),
        (
            "receiver.array_elements",
            Box::new(|v| v["receiver"]["array_elements"] = serde_json::json!(8)),
        ),
        (
            "receiver.array_elements",
            Box::new(|v| {
                v["receiver"]["array_geometry"] = serde_json::json!("circular");
                v["receiver"]["array_elements"] = serde_json::json!(2);
            }),
        ),
        (
            "estimator.max_order",
            Box::new(|v| v["estimator"]["max_order"] = serde_json::json!(3)),
        ),
        (
            "estimator.min_track_distance_m",
            Box::new(|v| v["estimator"]["min_track_distance_m"] = serde_json::json!(-35.0)),
        ),
        ("tracks", Box::new(|v| v["tracks"] = serde_json::json!([]))),
        (
            "receiver",
            Box::new(|v| v["receiver"]["colour"] = serde_json::json!("red")),
        ),
        (
            "unknown_top_level",
            Box::new(|v| v["unknown_top_level"] = serde_json::json!(1)),
        ),
    ];
    for (field, edit) in cases {
        let mut v = base.clone();
        edit(&mut v);
        let err = Scenario::from_json(&v.to_string()).unwrap_err();
        let text = err.to_string();
        match (&err, field) {
            (ScenarioError::Invalid { field: f, .. }, _) => {
                assert!(f.starts_with(field), "expected {field}, got {text}")
            }
            _ => panic!("unexpected error for {field}: {text}"),
        }
    }
    // NaN and overflow cannot even be written as JSON numbers: they are syntax errors.
    let text = base.to_string().replacen("1900000000.0", "1e400", 1);
    assert!(Scenario::from_json(&text).is_err());
    assert!(Scenario::from_json("{").is_err());
    // Programmatic NaN is caught by validation.
    let mut s = indoor();
    s.transmitter.position[0] = f64::NAN;
    assert!(
        matches!(s.validate(), Err(ScenarioError::Invalid { field, .. }) if field == "transmitter.position")
    );
}

#[test]
fn unknown_track_is_an_error() {
    let err = simulate(&indoor(), "nope", opts(1)).unwrap_err();
    assert!(err.to_string().contains("user21"));
}

#[test]
fn the_simulators_sensor_profile_states_its_noise_as_bounds() {
    use crate::filter::NoiseModel;
    // the built-in receiver (100 MHz, 64 samples, 3×3 array): Cramér–Rao terms at 0 dB of
    // 0.146 m and 0.0115 rad, stated rounded up; floors 1.5× as drawn — which is the filter's
    // default noise model, so a simulated log with its profile runs as it did without one
    let s = super::builtin::indoor();
    let p = s.sensor_profile(true);
    let (d, a) = (p.distance_m.unwrap(), p.aoa_rad.unwrap());
    let n = NoiseModel::default();
    assert_eq!(d.floor, n.distance_floor_m);
    assert_eq!(d.at_0db, n.distance_at_0db_m);
    assert_eq!(a.floor, n.aoa_floor_rad);
    assert_eq!(a.at_0db, n.aoa_at_0db_rad);
    // stated bounds never fall below the drawn noise
    for snr in [-10.0, 0.0, 10.0, 30.0] {
        let (sd, sa) = s.noise_std(snr);
        assert!(d.std(snr) >= sd && a.std(snr) >= sa, "{snr} dB");
    }
    // a single antenna states no angle; another bandwidth another distance law
    assert!(s.sensor_profile(false).aoa_rad.is_none());
    let mut narrow = s.clone();
    narrow.bandwidth_hz = 20e6;
    let nd = narrow.sensor_profile(true).distance_m.unwrap();
    assert!(nd.at_0db > 4.0 * d.at_0db && nd.at_0db <= 0.75, "{nd:?}");
}

#[test]
fn the_simulators_angle_noise_is_the_cramer_rao_bound_of_its_array() {
    use super::scenario::ArrayGeometry;
    use crate::radio::array::ArrayModel;
    // the deterministic angle CRB of one path in white noise of unit variance per element
    // and sample: 1 / (2·γ·‖∂a/∂θ − (aᴴ∂a/∂θ / M)·a‖²), γ the post-integration SNR — what the
    // simulator draws must be this for any layout, at any angle
    for (geometry, elements) in [
        (ArrayGeometry::Square, 9),
        (ArrayGeometry::Square, 16),
        (ArrayGeometry::Circular, 8),
        (ArrayGeometry::Circular, 5),
    ] {
        let mut s = super::builtin::urban();
        s.receiver.array_geometry = geometry;
        s.receiver.array_elements = elements;
        s.estimator.aoa_floor_rad = 0.0;
        s.validate().unwrap();
        let model = ArrayModel {
            elements_m: s.array_elements_m(true),
            wavelength_m: s.wavelength_m(),
            rho: 1.0,
        };
        assert_eq!(model.elements(), elements as usize);
        let gamma = 10f64.powf(0.1 * 10.0) * s.estimator.integration_samples;
        for theta in [0.0, 0.4, 1.3, -2.5] {
            let a = model.steering(theta);
            let da = model.steering_derivative(theta);
            let m = a.len() as f64;
            let proj = a
                .iter()
                .zip(&da)
                .map(|(x, y)| x.conj() * y)
                .sum::<nalgebra::Complex<f64>>()
                / m;
            let info: f64 = a
                .iter()
                .zip(&da)
                .map(|(x, y)| (y - proj * x).norm_sqr())
                .sum();
            let crb = (1.0 / (2.0 * gamma * info)).sqrt();
            let (_, drawn) = s.noise_std(10.0);
            assert!(
                (drawn / crb - 1.0).abs() < 1e-9,
                "{geometry:?} {elements}: drawn {drawn}, CRB {crb} at θ = {theta}"
            );
        }
    }
    // neighbours of the circle are half a wavelength apart
    let mut s = super::builtin::urban();
    s.receiver.array_geometry = ArrayGeometry::Circular;
    s.receiver.array_elements = 8;
    let e = s.array_elements_m(true);
    let gap = (e[1][0] - e[0][0]).hypot(e[1][1] - e[0][1]);
    assert!((gap - s.wavelength_m() / 2.0).abs() < 1e-12, "{gap}");
}

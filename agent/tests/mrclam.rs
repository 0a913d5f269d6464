//! Real data: UTIAS MRCLAM dataset 6 from ../shared/data/mrclam6 (beside the repository).
//! Channel-SLAM on the landmark range/bearing data must beat integrating the odometry alone.

use echomap_agent::filter::{BPrior, FilterConfig, NoiseModel};
use echomap_agent::mrclam::{ImportOptions, dead_reckoning, import};
use echomap_agent::run::run_filter;
use std::path::PathBuf;

fn dataset() -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/mrclam6");
    if dir.join("Barcodes.dat").exists() {
        Some(dir)
    } else {
        eprintln!(
            "SKIPPED: {} is absent; the MRCLAM real-data test needs it",
            dir.display()
        );
        None
    }
}

#[test]
fn slam_beats_dead_reckoning_on_real_robots() {
    let Some(dir) = dataset() else { return };
    // Robots 1 and 3, two seeds each: the mean MAE (seed 001 eq. 27) over the run must be at
    // most 60 % of the dead-reckoning error of the same odometry.
    for robot in [1, 3] {
        let (log, truth) = import(
            &dir,
            ImportOptions {
                robot,
                track_gap_s: 5.0,
                rate_hz: 10.0,
                snr_db: 20.0,
            },
        )
        .unwrap();
        assert!(
            truth.transmitters.len() > 15,
            "track gaps split landmarks into several tracks"
        );
        let dr = dead_reckoning(&log);
        let dr_err = dr
            .iter()
            .zip(&truth.poses)
            .map(|(p, t)| (p.0 - t.x).hypot(p.1 - t.y))
            .sum::<f64>()
            / dr.len() as f64;
        let mut mae = 0.0;
        for seed in [1, 2] {
            let cfg = FilterConfig {
                particles: 400,
                seed,
                initial_speed_mps: truth.poses[0].speed_mps,
                b_prior: BPrior::Zero { std_m: 0.05 },
                noise: NoiseModel {
                    distance_floor_m: 0.15,
                    aoa_floor_rad: 0.05,
                    ..NoiseModel::default()
                },
                association_p0: 1e-4,
                association_gate: 30.0,
                ..FilterConfig::default()
            };
            let out = run_filter(&log, Some(&truth), cfg, false).unwrap();
            let errs: Vec<f64> = out
                .rows
                .iter()
                .filter_map(|r| r.truth.map(|t| t.mae_m))
                .collect();
            mae += errs.iter().sum::<f64>() / errs.len() as f64 / 2.0;
        }
        eprintln!("robot {robot}: filter mean MAE {mae:.2} m, dead reckoning {dr_err:.2} m");
        assert!(
            mae < 0.6 * dr_err,
            "robot {robot}: filter {mae:.2} m vs dead reckoning {dr_err:.2} m"
        );
    }
}

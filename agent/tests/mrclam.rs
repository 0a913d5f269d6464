//! Real data: UTIAS MRCLAM dataset 6 from ../shared/data/mrclam6 (beside the repository).
//! Channel-SLAM on the landmark range/bearing data must beat integrating the odometry alone.

use clap::Parser;
use echomap_agent::cli::{FilterArgs, MRCLAM_RUN_ARGS};
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

/// The filter flags as `echomap-agent run` takes them.
#[derive(Debug, Parser)]
struct Flags {
    #[command(flatten)]
    filter: FilterArgs,
}

#[test]
fn slam_beats_dead_reckoning_on_real_robots() {
    let Some(dir) = dataset() else { return };
    // Robots 1 and 3, two seeds each, with the MRCLAM settings every command uses (noise
    // floors and the odometry heading model measured from the data, line of sight only) at
    // 400 particles: the mean MAE (seed 001 eq. 27) over the run must be at most 60 % of the
    // dead-reckoning error of the same odometry.
    let flags = Flags::parse_from(
        ["mrclam", "--particles", "400"]
            .into_iter()
            .chain(MRCLAM_RUN_ARGS),
    );
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
            let cfg = flags.filter.config(seed, truth.poses[0].speed_mps).unwrap();
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

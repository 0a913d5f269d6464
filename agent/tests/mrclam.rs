//! Real data: UTIAS MRCLAM dataset 6 from ../shared/data/mrclam6 (beside the repository).
//! Channel-SLAM on the landmark range/bearing data must beat integrating the odometry alone.

use echomap_agent::config::{Layers, resolve};
use echomap_agent::mrclam::{
    ImportOptions, OdometryIntegral, dead_reckoning, estimate_robot_delay, import, parse_table,
};
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
    // Robots 1 and 3, two seeds each, configured by nothing but the sensor profile the
    // importer writes (noise floors and the odometry heading model measured from the data,
    // line of sight only) at 400 particles: the mean MAE (Ulmschneider et al. 2021 eq. 27)
    // over the run must be at most 60 % of the dead-reckoning error of the same odometry.
    for robot in [1, 3] {
        let (log, truth) = import(&dir, ImportOptions::robot(robot)).unwrap();
        assert!(
            truth.transmitters.len() > 15,
            "track gaps split landmarks into several tracks"
        );
        let mut config = resolve(&Layers {
            sensor: log.header.sensor.as_ref(),
            ..Default::default()
        })
        .unwrap()
        .config;
        assert!(
            config.measurement.line_of_sight_only,
            "the imported log carries its sensor profile"
        );
        config.particles = 400;
        let dr = dead_reckoning(&log);
        let dr_err = dr
            .iter()
            .zip(&truth.poses)
            .map(|(p, t)| (p.0 - t.x).hypot(p.1 - t.y))
            .sum::<f64>()
            / dr.len() as f64;
        let mut mae = 0.0;
        for seed in [1, 2] {
            let cfg = config.filter_config(seed, truth.poses[0].speed_mps);
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

/// Heading error of the odometry, delayed by `delay` s, against the ground truth: the RMS over
/// consecutive 5 s windows of (integrated angular rate − true heading change), rad.
fn heading_window_rms(odo: &[Vec<f64>], gt: &[Vec<f64>], delay: f64) -> f64 {
    // consecutive 5 s windows over the time both cover
    let t0 = (odo[0][0] + delay).max(gt[0][0]);
    let t1 = (odo[odo.len() - 1][0] + delay).min(gt[gt.len() - 1][0]);
    let marks: Vec<f64> = (0..)
        .map(|k| t0 + 5.0 * k as f64)
        .take_while(|&t| t <= t1)
        .collect();
    let turn = OdometryIntegral::new(odo, 2);
    let heading = |t: f64| -> f64 {
        // unwrapped true heading by linear interpolation
        let i = gt.partition_point(|r| r[0] <= t).clamp(1, gt.len() - 1);
        let (a, b) = (&gt[i - 1], &gt[i]);
        let f = ((t - a[0]) / (b[0] - a[0])).clamp(0.0, 1.0);
        a[3] + echomap_shared::wrap_angle(b[3] - a[3]) * f
    };
    let errs: Vec<f64> = marks
        .windows(2)
        .map(|w| {
            let turned = echomap_shared::wrap_angle(heading(w[1]) - heading(w[0]));
            turn.over(w[0], w[1], delay) - turned
        })
        .collect();
    (errs.iter().map(|e| e * e).sum::<f64>() / errs.len() as f64).sqrt()
}

#[test]
fn the_odometry_delay_read_off_the_bearings_is_the_one_the_ground_truth_shows() {
    let Some(dir) = dataset() else { return };
    // MRCLAM's odometry is the commanded velocity; `--odometry-delay auto` estimates how late
    // the robot follows it from the landmark bearings alone. The ground truth, read here and
    // not by the estimate, must agree: for every robot the delay that best explains the true
    // heading changes over 5 s windows (grid of 0.05 s) lies within 0.1 s of the estimate,
    // and the estimate lowers the windows' heading error against no delay.
    for robot in 1..=5u32 {
        let est = estimate_robot_delay(&dir, robot)
            .unwrap()
            .expect("thousands of bearing pairs");
        let read = |name: &str, cols| {
            let text =
                std::fs::read_to_string(dir.join(format!("Robot{robot}_{name}.dat"))).unwrap();
            parse_table(&text, cols, name).unwrap()
        };
        let (odo, gt) = (read("Odometry", 3), read("Groundtruth", 4));
        let grid: Vec<(f64, f64)> = (0..=10)
            .map(|k| {
                let d = 0.05 * k as f64;
                (d, heading_window_rms(&odo, &gt, d))
            })
            .collect();
        let (best, _) = grid
            .iter()
            .copied()
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        let (at_est, at_zero) = (
            heading_window_rms(&odo, &gt, est.delay_s),
            heading_window_rms(&odo, &gt, 0.0),
        );
        eprintln!(
            "robot {robot}: delay {:.3} s from {} bearing pairs; ground truth's best {best:.2} s; \
             heading RMS per 5 s {at_zero:.4} → {at_est:.4} rad",
            est.delay_s, est.pairs
        );
        assert!(
            (est.delay_s - best).abs() <= 0.1,
            "robot {robot}: estimated {:.3} s, the ground truth's best {best:.2} s",
            est.delay_s
        );
        assert!(
            at_est < at_zero,
            "robot {robot}: {at_est:.4} rad with the estimate, {at_zero:.4} without"
        );
    }
}

fn agent() -> std::process::Command {
    std::process::Command::new(env!("CARGO_BIN_EXE_echomap-agent"))
}

fn ok(c: &mut std::process::Command) -> String {
    let o = c.output().unwrap();
    assert!(
        o.status.success(),
        "{c:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

#[test]
fn evaluating_recorded_logs_agrees_with_single_runs_and_refuses_a_log_without_truth() {
    let Some(dir) = dataset() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let log = |r: u32| tmp.path().join(format!("robot{r}"));
    for r in [1, 2] {
        ok(agent()
            .args(["import", "mrclam"])
            .arg(&dir)
            .args(["--robot", &r.to_string(), "--out"])
            .arg(log(r)));
    }
    let ev = tmp.path().join("ev");
    let logs = format!("{},{}", log(1).display(), log(2).display());
    ok(agent()
        .args([
            "evaluate",
            "--logs",
            &logs,
            "--seeds",
            "2",
            "--first-seed",
            "3",
        ])
        .args(["--particles", "100", "--out"])
        .arg(&ev));
    // the same log and seed through `run`: the same error and the same dead reckoning
    let one = tmp.path().join("one");
    ok(agent()
        .args(["run", "--log"])
        .arg(log(2))
        .args(["--particles", "100", "--seed", "4", "--quiet", "--out"])
        .arg(&one));
    let single: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(one.join("summary.json")).unwrap()).unwrap();
    let csv = std::fs::read_to_string(ev.join("runs.csv")).unwrap();
    let rows: Vec<Vec<String>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(str::to_owned).collect())
        .collect();
    assert_eq!(rows.len(), 4, "{csv}");
    let row = rows
        .iter()
        .find(|r| r[0] == "robot2" && r[1] == "4")
        .unwrap_or_else(|| panic!("no row for robot2 seed 4: {csv}"));
    let num = |s: &str| s.parse::<f64>().unwrap();
    let mae = single["mae_mean_m"].as_f64().unwrap();
    let dr = single["dead_reckoning_mean_m"].as_f64().unwrap();
    assert!((num(&row[2]) - mae).abs() < 1e-9, "{row:?} against {mae}");
    assert!((num(&row[4]) - dr).abs() < 1e-9, "{row:?} against {dr}");
    assert!((num(&row[6]) - mae / dr).abs() < 1e-9);
    let err = single["error_mean_m"].as_f64().unwrap();
    assert!(
        err <= mae + 1e-9,
        "the mean's error {err} above the MAE {mae}"
    );
    assert!(
        (num(&row[8]) - err / dr).abs() < 1e-9,
        "{row:?} against {err}"
    );
    // the per-log means and their median
    let mean_of = |name: &str| {
        let v: Vec<f64> = rows
            .iter()
            .filter(|r| r[0] == name)
            .map(|r| num(&r[6]))
            .collect();
        v.iter().sum::<f64>() / v.len() as f64
    };
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(ev.join("summary.json")).unwrap()).unwrap();
    let median = 0.5 * (mean_of("robot1") + mean_of("robot2"));
    assert!((summary["median_ratio"].as_f64().unwrap() - median).abs() < 1e-9);
    for f in ["ratio.png", "ratio.svg"] {
        assert!(std::fs::metadata(ev.join(f)).unwrap().len() > 1000, "{f}");
    }
    let md = std::fs::read_to_string(ev.join("results.md")).unwrap();
    assert!(
        md.contains("| robot1 |") && md.contains("| robot2 |"),
        "{md}"
    );
    // a log without its truth: a clear error, nothing written
    let bare = tmp.path().join("bare");
    std::fs::create_dir(&bare).unwrap();
    std::fs::copy(log(1).join("log.jsonl"), bare.join("log.jsonl")).unwrap();
    let ev2 = tmp.path().join("ev2");
    let o = agent()
        .args(["evaluate", "--logs"])
        .arg(format!("{},{}", log(1).display(), bare.display()))
        .args(["--seeds", "1", "--particles", "50", "--out"])
        .arg(&ev2)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("bare") && err.contains("truth.json"), "{err}");
    assert!(!ev2.exists());
}

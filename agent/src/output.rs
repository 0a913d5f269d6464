//! Writing run results: map.json, track.csv, summary.json, plots, and the console summary.

use crate::eval::{map_ospa, track_csv};
use crate::run::RunOutput;
use anyhow::{Context, Result};
use echomap_shared::log::{GroundTruth, MeasurementLog};
use echomap_shared::matching::fit_rigid;
use nalgebra::Point2;
use serde::Serialize;
use std::path::Path;

/// Error statistics of a run against ground truth (`summary.json`).
#[derive(Debug, Clone, Serialize)]
pub struct RunSummary {
    pub snapshots: usize,
    pub traveled_m: f64,
    pub transmitters: usize,
    pub mae_final_m: f64,
    pub mae_mean_m: f64,
    pub mae_max_m: f64,
    /// mean and final error of the reported position (the weighted mean, `err_m`); equal to
    /// the MAE for a collapsed cloud, below it when the cloud (or the islands) spread
    pub error_mean_m: f64,
    pub error_final_m: f64,
    pub rmse_max_m: f64,
    /// OSPA (Li et al. 2019 eq. 43), cut-off 5 m, order 1, in [x, y, b]
    pub map_ospa_m: f64,
    pub converged_transmitters: usize,
    pub true_transmitters: usize,
    /// mean error of integrating gyro + speed alone, for logs that carry speed
    pub dead_reckoning_mean_m: Option<f64>,
    pub dead_reckoning_final_m: Option<f64>,
    /// absolute trajectory error: RMS distance between the estimated (weighted-mean) track and
    /// the true one after the least-squares rigid alignment of the whole track (Sturm et al.,
    /// IROS 2012) — the error without the frame's unobservable rotation and offset
    pub ate_m: f64,
    /// the same for dead reckoning, for logs that carry speed
    pub dead_reckoning_ate_m: Option<f64>,
    /// share of snapshots whose true position lies inside the 95 % ellipse of the particle
    /// cloud (NEES ≤ 5.991): near 0.95 when the filter's reported uncertainty is honest
    pub coverage95: f64,
    /// detections of bound tracks decided to be gross errors (`measurement.outlier_probability`)
    pub outlier_detections: usize,
    /// detections of bound tracks decided to be jumps within an unresolved cluster
    /// (`measurement.jump_probability`)
    pub jump_detections: usize,
    /// tracks found to follow another path than their transmitter after a run of gross
    /// errors, and started again as new tracks
    pub track_switches: usize,
    /// the true track run through the filter's model (`filter::truth`): Σ_t ln p(z_t | true
    /// track) − ln p(z_t | particles). Positive: the data favour the truth and the filter lost
    /// it (an estimator failure); negative: the data favour the filter's wrong track (the
    /// radio model misfits the data)
    pub truth_log_bayes_factor: Option<f64>,
    /// normalized innovation squared per measurement dimension of the true track's
    /// detections of transmitters it had mapped: about 1 when the model fits the data
    pub truth_nis_per_dim: Option<f64>,
    /// with a prior map: log time (s) of the first accepted match, if any
    pub prior_matched_at_s: Option<f64>,
    /// with a prior map: particle-weighted number of transmitters taken over from it
    pub prior_transmitters_used: Option<f64>,
}

pub fn summarize(out: &RunOutput, truth: &GroundTruth, log: &MeasurementLog) -> RunSummary {
    let mae: Vec<f64> = out
        .rows
        .iter()
        .filter_map(|r| r.truth.map(|t| t.mae_m))
        .collect();
    let err: Vec<f64> = out
        .rows
        .iter()
        .filter_map(|r| r.truth.map(|t| t.err_m))
        .collect();
    let rmse_max = out
        .rows
        .iter()
        .filter_map(|r| r.truth.map(|t| t.rmse_m))
        .fold(0.0, f64::max);
    let (ospa, n_est, n_true) = map_ospa(&out.map, truth);
    let true_track = truth_points(truth);
    let (dr_mean, dr_final, dr_ate) = if log.header.speed {
        let dr = crate::mrclam::dead_reckoning(log);
        let e: Vec<f64> = dr
            .iter()
            .zip(&truth.poses)
            .map(|(p, t)| (p.0 - t.x).hypot(p.1 - t.y))
            .collect();
        let dr: Vec<Point2<f64>> = dr.iter().map(|p| Point2::new(p.0, p.1)).collect();
        (
            Some(e.iter().sum::<f64>() / e.len().max(1) as f64),
            e.last().copied(),
            Some(absolute_trajectory_error(&dr, &true_track)),
        )
    } else {
        (None, None, None)
    };
    RunSummary {
        snapshots: out.rows.len(),
        traveled_m: out.rows.last().map(|r| r.traveled_m).unwrap_or(0.0),
        transmitters: out.map.len(),
        mae_final_m: mae.last().copied().unwrap_or(f64::NAN),
        mae_mean_m: mae.iter().sum::<f64>() / mae.len().max(1) as f64,
        mae_max_m: mae.iter().cloned().fold(0.0, f64::max),
        error_mean_m: err.iter().sum::<f64>() / err.len().max(1) as f64,
        error_final_m: err.last().copied().unwrap_or(f64::NAN),
        rmse_max_m: rmse_max,
        map_ospa_m: ospa,
        converged_transmitters: n_est,
        true_transmitters: n_true,
        dead_reckoning_mean_m: dr_mean,
        dead_reckoning_final_m: dr_final,
        ate_m: track_ate(&out.rows, truth),
        dead_reckoning_ate_m: dr_ate,
        coverage95: coverage95(&out.rows),
        outlier_detections: out.filter.outlier_detections(),
        jump_detections: out.filter.jump_detections(),
        track_switches: out.filter.track_switches(),
        truth_log_bayes_factor: out.filter.truth_summary().map(|t| t.log_bayes_factor),
        truth_nis_per_dim: out.filter.truth_summary().and_then(|t| t.nis_per_dim),
        prior_matched_at_s: out.matches.iter().find(|m| m.accepted).map(|m| m.t),
        prior_transmitters_used: out.had_prior.then(|| out.filter.prior_transmitters_used()),
    }
}

/// Share of rows with truth whose NEES is within the χ²₂ 95 % quantile (NaN without truth).
pub fn coverage95(rows: &[crate::eval::TrackRow]) -> f64 {
    let nees: Vec<f64> = rows
        .iter()
        .filter_map(|r| r.truth.map(|t| t.nees))
        .collect();
    if nees.is_empty() {
        return f64::NAN;
    }
    nees.iter().filter(|&&e| e <= CHI2_2_95).count() as f64 / nees.len() as f64
}

/// The 95 % quantile of χ² with 2 degrees of freedom, `−2 ln 0.05`.
pub const CHI2_2_95: f64 = 5.991_464_547_107_979;

fn truth_points(truth: &GroundTruth) -> Vec<Point2<f64>> {
    truth.poses.iter().map(|p| Point2::new(p.x, p.y)).collect()
}

/// Absolute trajectory error of a run's weighted-mean track (one row per ground-truth pose).
pub fn track_ate(rows: &[crate::eval::TrackRow], truth: &GroundTruth) -> f64 {
    let est: Vec<Point2<f64>> = rows.iter().map(|r| Point2::new(r.x, r.y)).collect();
    absolute_trajectory_error(&est, &truth_points(truth))
}

/// RMS distance between `est` and `truth` (paired by index, the shorter length) after the
/// least-squares rigid transform of `est` onto `truth`; NaN when no transform can be fitted.
pub fn absolute_trajectory_error(est: &[Point2<f64>], truth: &[Point2<f64>]) -> f64 {
    let n = est.len().min(truth.len());
    let Some(t) = fit_rigid(&est[..n], &truth[..n]) else {
        return f64::NAN;
    };
    let sq: f64 = est[..n]
        .iter()
        .zip(&truth[..n])
        .map(|(e, g)| (t * e - g).norm_squared())
        .sum();
    (sq / n as f64).sqrt()
}

pub fn write_run(
    out: &RunOutput,
    truth: Option<&GroundTruth>,
    log: &MeasurementLog,
    dir: &Path,
) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    if let Some(truth) = truth {
        std::fs::write(
            dir.join("summary.json"),
            serde_json::to_string_pretty(&summarize(out, truth, log))?,
        )?;
    }
    std::fs::write(dir.join("track.csv"), track_csv(&out.rows))?;
    if out.map_error.is_none() {
        std::fs::write(dir.join("map.json"), out.map.to_json_pretty())?;
    }
    if out.had_prior {
        let mut s = String::from(
            "t,accepted,inliers,angle_rad,tx,ty,action,anchors,match_angle_rad,fused,reason\n",
        );
        for m in &out.matches {
            s.push_str(&format!(
                "{},{},{},{},{},{},{},{},{},{:.2},\"{}\"\n",
                m.t,
                m.accepted,
                m.inliers,
                m.angle_rad,
                m.tx,
                m.ty,
                m.action,
                m.anchors,
                m.match_angle_rad,
                m.fused,
                m.reason.replace('"', "'")
            ));
        }
        std::fs::write(dir.join("prior_matches.csv"), s)?;
    }
    for ext in ["png", "svg"] {
        crate::plot::draw_track_and_map(
            &out.rows,
            &out.map,
            truth,
            &dir.join(format!("track.{ext}")),
        )?;
        if truth.is_some() {
            crate::plot::draw_error(&out.rows, &dir.join(format!("error.{ext}")))?;
        }
    }
    if let Some(e) = &out.map_error {
        anyhow::bail!(
            "the map could not be exported ({e}); the track and summary are in {}",
            dir.display()
        );
    }
    Ok(())
}

pub fn print_summary(out: &RunOutput, truth: Option<&GroundTruth>, log: &MeasurementLog) {
    println!(
        "{} snapshots, {:.1} m travelled, {} transmitters in the map",
        out.rows.len(),
        out.rows.last().map(|r| r.traveled_m).unwrap_or(0.0),
        out.map.len()
    );
    if let Some(truth) = truth {
        let s = summarize(out, truth, log);
        println!(
            "MAE: final {:.2} m, mean {:.2} m, max {:.2} m; RMSE max {:.2} m; map OSPA {:.2} m ({} converged vs {} true transmitters)",
            s.mae_final_m,
            s.mae_mean_m,
            s.mae_max_m,
            s.rmse_max_m,
            s.map_ospa_m,
            s.converged_transmitters,
            s.true_transmitters
        );
        if out.had_prior {
            match s.prior_matched_at_s {
                Some(t) => println!(
                    "prior map: matched at t = {t:.1} s, {:.1} transmitters taken over (particle mean)",
                    s.prior_transmitters_used.unwrap_or(0.0)
                ),
                None => println!("prior map: never matched"),
            }
        }
        println!(
            "absolute trajectory error (after rigid alignment): {:.2} m; truth inside the 95 % ellipse in {:.1} % of snapshots",
            s.ate_m,
            100.0 * s.coverage95
        );
        if let Some(bf) = s.truth_log_bayes_factor {
            println!(
                "the true track under the filter's model: ln Bayes factor {bf:+.1} against the filter's ({}), NIS per dimension {:.2}",
                if bf >= 0.0 {
                    "the data favour the truth: the filter lost it"
                } else {
                    "the data favour the filter's track: the model misfits them"
                },
                s.truth_nis_per_dim.unwrap_or(f64::NAN)
            );
        }
        if let (Some(m), Some(f)) = (s.dead_reckoning_mean_m, s.dead_reckoning_final_m) {
            println!(
                "dead reckoning (gyro + speed only): mean error {m:.2} m, final {f:.2} m, ATE {:.2} m",
                s.dead_reckoning_ate_m.unwrap_or(f64::NAN)
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn track() -> Vec<Point2<f64>> {
        (0..200)
            .map(|k| {
                let a = k as f64 * 0.05;
                Point2::new(3.0 * a.cos() + 0.1 * k as f64, 2.0 * a.sin())
            })
            .collect()
    }

    #[test]
    fn the_trajectory_error_ignores_a_rigid_motion_of_the_frame() {
        let truth = track();
        let moved = nalgebra::Isometry2::new(nalgebra::Vector2::new(4.0, -1.5), 0.7);
        let est: Vec<_> = truth.iter().map(|p| moved * p).collect();
        // the plain error is metres, the aligned one nothing
        assert!((est[100] - truth[100]).norm() > 1.0);
        assert!(absolute_trajectory_error(&est, &truth) < 1e-9);
    }

    #[test]
    fn the_trajectory_error_is_the_rms_of_what_no_rigid_motion_explains() {
        let truth = track();
        // alternating ±0.3 m offsets along x: no rigid motion removes them, RMS 0.3 m
        let est: Vec<_> = truth
            .iter()
            .enumerate()
            .map(|(k, p)| p + nalgebra::Vector2::new(if k % 2 == 0 { 0.3 } else { -0.3 }, 0.0))
            .collect();
        let ate = absolute_trajectory_error(&est, &truth);
        assert!((ate - 0.3).abs() < 0.01, "{ate}");
        assert!(absolute_trajectory_error(&truth[..1], &truth[..1]).is_nan());
    }
}

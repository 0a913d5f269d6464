//! Writing run results: map.json, track.csv, summary.json, plots, and the console summary.

use crate::eval::{map_ospa, track_csv};
use crate::run::RunOutput;
use anyhow::{Context, Result};
use echomap_shared::log::{GroundTruth, MeasurementLog};
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
    pub rmse_max_m: f64,
    /// OSPA (seed 003 eq. 43), cut-off 5 m, order 1, in [x, y, b]
    pub map_ospa_m: f64,
    pub converged_transmitters: usize,
    pub true_transmitters: usize,
    /// mean error of integrating gyro + speed alone, for logs that carry speed
    pub dead_reckoning_mean_m: Option<f64>,
    pub dead_reckoning_final_m: Option<f64>,
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
    let rmse_max = out
        .rows
        .iter()
        .filter_map(|r| r.truth.map(|t| t.rmse_m))
        .fold(0.0, f64::max);
    let (ospa, n_est, n_true) = map_ospa(&out.map, truth);
    let (dr_mean, dr_final) = if log.header.speed {
        let dr = crate::mrclam::dead_reckoning(log);
        let e: Vec<f64> = dr
            .iter()
            .zip(&truth.poses)
            .map(|(p, t)| (p.0 - t.x).hypot(p.1 - t.y))
            .collect();
        (
            Some(e.iter().sum::<f64>() / e.len().max(1) as f64),
            e.last().copied(),
        )
    } else {
        (None, None)
    };
    RunSummary {
        snapshots: out.rows.len(),
        traveled_m: out.rows.last().map(|r| r.traveled_m).unwrap_or(0.0),
        transmitters: out.map.len(),
        mae_final_m: mae.last().copied().unwrap_or(f64::NAN),
        mae_mean_m: mae.iter().sum::<f64>() / mae.len().max(1) as f64,
        mae_max_m: mae.iter().cloned().fold(0.0, f64::max),
        rmse_max_m: rmse_max,
        map_ospa_m: ospa,
        converged_transmitters: n_est,
        true_transmitters: n_true,
        dead_reckoning_mean_m: dr_mean,
        dead_reckoning_final_m: dr_final,
        prior_matched_at_s: out.matches.iter().find(|m| m.accepted).map(|m| m.t),
        prior_transmitters_used: out.had_prior.then(|| out.filter.prior_transmitters_used()),
    }
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
    std::fs::write(dir.join("map.json"), out.map.to_json_pretty())?;
    std::fs::write(dir.join("track.csv"), track_csv(&out.rows))?;
    if out.had_prior {
        let mut s = String::from("t,accepted,inliers,angle_rad,tx,ty,action,reason\n");
        for m in &out.matches {
            s.push_str(&format!(
                "{},{},{},{},{},{},{},\"{}\"\n",
                m.t,
                m.accepted,
                m.inliers,
                m.angle_rad,
                m.tx,
                m.ty,
                m.action,
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
        if let (Some(m), Some(f)) = (s.dead_reckoning_mean_m, s.dead_reckoning_final_m) {
            println!("dead reckoning (gyro + speed only): mean error {m:.2} m, final {f:.2} m");
        }
    }
}

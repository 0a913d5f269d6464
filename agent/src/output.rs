//! Writing run results: map.json, track.csv, plots, and the console summary.

use crate::eval::{map_ospa, track_csv};
use crate::run::RunOutput;
use anyhow::{Context, Result};
use echomap_shared::log::GroundTruth;
use std::path::Path;

pub fn write_run(out: &RunOutput, truth: Option<&GroundTruth>, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    if let Some(truth) = truth {
        let mae: Vec<f64> = out
            .rows
            .iter()
            .filter_map(|r| r.truth.map(|t| t.mae_m))
            .collect();
        let rmse: Vec<f64> = out
            .rows
            .iter()
            .filter_map(|r| r.truth.map(|t| t.rmse_m))
            .collect();
        let (ospa, n_est, n_true) = map_ospa(&out.map, truth);
        let summary = serde_json::json!({
            "snapshots": out.rows.len(),
            "traveled_m": out.rows.last().map(|r| r.traveled_m),
            "transmitters": out.map.len(),
            "mae_final_m": mae.last(),
            "mae_mean_m": mae.iter().sum::<f64>() / mae.len().max(1) as f64,
            "mae_max_m": mae.iter().cloned().fold(0.0, f64::max),
            "rmse_max_m": rmse.iter().cloned().fold(0.0, f64::max),
            "map_ospa_m": ospa,
            "map_ospa_cutoff_m": 5.0,
            "map_ospa_order": 1,
            "converged_transmitters": n_est,
            "true_transmitters": n_true,
        });
        std::fs::write(
            dir.join("summary.json"),
            serde_json::to_string_pretty(&summary)?,
        )?;
    }
    std::fs::write(dir.join("map.json"), out.map.to_json_pretty())?;
    std::fs::write(dir.join("track.csv"), track_csv(&out.rows))?;
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

pub fn print_summary(
    out: &RunOutput,
    truth: Option<&GroundTruth>,
    log: &echomap_shared::log::MeasurementLog,
) {
    let last = out.rows.last();
    println!(
        "{} snapshots, {:.1} m travelled, {} transmitters in the map",
        out.rows.len(),
        last.map(|r| r.traveled_m).unwrap_or(0.0),
        out.map.len()
    );
    if let Some(truth) = truth {
        let errs: Vec<f64> = out
            .rows
            .iter()
            .filter_map(|r| r.truth.map(|t| t.mae_m))
            .collect();
        let mean = errs.iter().sum::<f64>() / errs.len().max(1) as f64;
        let rmse: Vec<f64> = out
            .rows
            .iter()
            .filter_map(|r| r.truth.map(|t| t.rmse_m))
            .collect();
        let (ospa, n_est, n_true) = map_ospa(&out.map, truth);
        println!(
            "MAE: final {:.2} m, mean {:.2} m, max {:.2} m; RMSE max {:.2} m; map OSPA {:.2} m ({} converged vs {} true transmitters)",
            errs.last().copied().unwrap_or(f64::NAN),
            mean,
            errs.iter().cloned().fold(0.0, f64::max),
            rmse.iter().cloned().fold(0.0, f64::max),
            ospa,
            n_est,
            n_true
        );
        if log.header.speed {
            let dr = crate::mrclam::dead_reckoning(log);
            let e: Vec<f64> = dr
                .iter()
                .zip(&truth.poses)
                .map(|(p, t)| (p.0 - t.x).hypot(p.1 - t.y))
                .collect();
            println!(
                "dead reckoning (gyro + speed only): mean error {:.2} m, final {:.2} m",
                e.iter().sum::<f64>() / e.len().max(1) as f64,
                e.last().copied().unwrap_or(f64::NAN)
            );
        }
    }
}

//! Running the filter over a measurement log, with ground truth when it is known.

use crate::eval::{TrackRow, TruthCols};
use crate::filter::export::export_map;
use crate::filter::model::Pose;
use crate::filter::prior::MatchEvent;
use crate::filter::{Filter, FilterConfig, PriorTracker};
use anyhow::Result;
use echomap_shared::TransmitterMap;
use echomap_shared::log::{GroundTruth, MeasurementLog};
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Debug)]
pub struct RunOutput {
    pub rows: Vec<TrackRow>,
    /// the user map (empty when it could not be exported: `map_error` says why)
    pub map: TransmitterMap,
    /// why the map could not be exported; the track and summary are written all the same
    pub map_error: Option<String>,
    pub filter: Filter,
    /// matching attempts against the prior map (empty without one)
    pub matches: Vec<MatchEvent>,
    /// whether a prior map was given
    pub had_prior: bool,
}

/// Runs the filter over every snapshot. With `truth`, rows carry the errors; the travelled
/// distance is then the true one (so that curves of several runs line up).
pub fn run_filter(
    log: &MeasurementLog,
    truth: Option<&GroundTruth>,
    cfg: FilterConfig,
    progress: bool,
) -> Result<RunOutput> {
    run_filter_with_prior(log, truth, cfg, progress, None)
}

/// [`run_filter`] with a prior map: `tracker` matches the agent's map against it every few
/// seconds of log time and hands it to the filter once a match is accepted.
pub fn run_filter_with_prior(
    log: &MeasurementLog,
    truth: Option<&GroundTruth>,
    cfg: FilterConfig,
    progress: bool,
    mut tracker: Option<PriorTracker>,
) -> Result<RunOutput> {
    if let Some(t) = truth {
        anyhow::ensure!(
            t.poses.len() == log.snapshots.len(),
            "ground truth has {} poses but the log {} snapshots",
            t.poses.len(),
            log.snapshots.len()
        );
    }
    let mut cfg = cfg;
    cfg.track_hold_s = log.header.track_hold_s.unwrap_or(0.0);
    let mut filter = Filter::new(cfg, log.header.aoa);
    let bar = if progress {
        let b = ProgressBar::new(log.snapshots.len() as u64);
        b.set_style(
            ProgressStyle::with_template(
                "{prefix} [{elapsed_precise}] {wide_bar} {pos}/{len} snapshots ({eta})",
            )
            .expect("static template"),
        );
        b.set_prefix("filter");
        b
    } else {
        ProgressBar::hidden()
    };
    let mut rows = Vec::with_capacity(log.snapshots.len());
    let mut true_traveled = 0.0;
    for (k, snap) in log.snapshots.iter().enumerate() {
        if let Some(t) = truth {
            let p = &t.poses[k];
            filter.set_true_pose(Pose {
                x: p.x,
                y: p.y,
                heading: p.heading_rad,
                speed: p.speed_mps,
            });
        }
        let stats = filter.step(snap);
        if let Some(tr) = tracker.as_mut() {
            let update = tr.after_step(&filter, snap)?;
            let fuses = !update.fuse.is_empty();
            let fused = filter.apply_prior_update(update);
            if fuses {
                tr.record_fused(fused);
            }
        }
        let truth_cols = truth.map(|t| {
            let p = &t.poses[k];
            if k > 0 {
                let q = &t.poses[k - 1];
                true_traveled += (p.x - q.x).hypot(p.y - q.y);
            }
            let (mae_m, rmse_m) = filter.errors(p.x, p.y);
            TruthCols {
                true_x: p.x,
                true_y: p.y,
                mae_m,
                rmse_m,
                err_m: (stats.x - p.x).hypot(stats.y - p.y),
                nees: filter.position_nees(p.x, p.y),
                truth_ll_ratio: stats.truth_ll_ratio.unwrap_or(f64::NAN),
            }
        });
        rows.push(TrackRow {
            t: stats.t,
            x: stats.x,
            y: stats.y,
            traveled_m: if truth.is_some() {
                true_traveled
            } else {
                stats.traveled_m
            },
            truth: truth_cols,
            ess: stats.ess,
            transmitters: stats.transmitters,
            components: stats.components,
            log_evidence: stats.log_evidence,
            with_prior: None,
        });
        bar.inc(1);
    }
    bar.finish_and_clear();
    filter.finish();
    let (map, map_error) = match export_map(&filter) {
        Ok(map) => (map, None),
        Err(e) => (
            TransmitterMap::new(filter.config().hex_size_m, Vec::new())?,
            Some(e.to_string()),
        ),
    };
    let had_prior = tracker.is_some();
    Ok(RunOutput {
        rows,
        map,
        map_error,
        filter,
        matches: tracker.map(|t| t.events).unwrap_or_default(),
        had_prior,
    })
}

/// [`run_filter_with_prior`] and [`run_filter`] side by side on the same log and seed: at
/// every snapshot the row of the filter under which the detections so far are the more likely
/// (the larger cumulative log evidence ln p(z₁..z_t), i.e. the Bayes factor of "the prior map
/// is right" against "no prior"; ties go to the prior). Causal: each row uses only the
/// snapshots up to it. The map, the filter and the verdict for the upload are those of the
/// filter ahead at the end; the match events are the prior filter's.
pub fn run_filter_with_fallback(
    log: &MeasurementLog,
    truth: Option<&GroundTruth>,
    cfg: FilterConfig,
    progress: bool,
    tracker: PriorTracker,
) -> Result<RunOutput> {
    let (with, alone) = rayon::join(
        || run_filter_with_prior(log, truth, cfg.clone(), progress, Some(tracker)),
        || run_filter(log, truth, cfg.clone(), false),
    );
    Ok(select_by_evidence(with?, alone?))
}

/// Row by row the more likely of two runs of one log (see [`run_filter_with_fallback`]).
fn select_by_evidence(with: RunOutput, alone: RunOutput) -> RunOutput {
    let rows = with
        .rows
        .into_iter()
        .zip(alone.rows)
        .map(|(w, a)| {
            let prior = w.log_evidence >= a.log_evidence;
            TrackRow {
                with_prior: Some(prior),
                ..if prior { w } else { a }
            }
        })
        .collect::<Vec<_>>();
    let prior_ahead = rows.last().is_none_or(|r| r.with_prior == Some(true));
    let (map, map_error, filter) = if prior_ahead {
        (with.map, with.map_error, with.filter)
    } else {
        (alone.map, alone.map_error, alone.filter)
    };
    RunOutput {
        rows,
        map,
        map_error,
        filter,
        matches: with.matches,
        had_prior: true,
    }
}

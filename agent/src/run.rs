//! Running the filter over a measurement log, with ground truth when it is known.

use crate::eval::{TrackRow, TruthCols};
use crate::filter::export::export_map;
use crate::filter::model::Pose;
use crate::filter::prior::MatchEvent;
use crate::filter::rbpf::nees;
use crate::filter::update::log_sum_exp;
use crate::filter::{Filter, FilterConfig, PriorTracker, StepStats};
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
///
/// With `cfg.islands` = K > 1 the particles are split into K independent filters ("islands",
/// Vergé et al. 2015), each with its own seed and its own copy of the prior tracker, and every
/// row reports their equally weighted mixture: the mean of the islands' means, and the
/// spread of the islands about it added to their own (the position covariance, `nees`). A
/// particle filter over a long track keeps few lineages, so one population's spread says
/// little of its error; the scatter between independent populations does. The map, the
/// filter and the match events are those of the island with the largest evidence at the end.
pub fn run_filter_with_prior(
    log: &MeasurementLog,
    truth: Option<&GroundTruth>,
    cfg: FilterConfig,
    progress: bool,
    tracker: Option<PriorTracker>,
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
    let islands = cfg.islands.clamp(1, cfg.particles.max(1));
    let mut filters: Vec<Filter> = (0..islands)
        .map(|i| Filter::new(island_config(&cfg, islands, i), log.header.aoa))
        .collect();
    let mut trackers: Vec<Option<PriorTracker>> = vec![tracker; islands];
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
    let mut traveled = 0.0;
    // from the origin, where every particle starts (as `StepStats::traveled_m`)
    let mut last_mean = [0.0f64; 2];
    for (k, snap) in log.snapshots.iter().enumerate() {
        let mut stats = Vec::with_capacity(islands);
        for (filter, tracker) in filters.iter_mut().zip(trackers.iter_mut()) {
            if let Some(t) = truth {
                let p = &t.poses[k];
                filter.set_true_pose(Pose {
                    x: p.x,
                    y: p.y,
                    heading: p.heading_rad,
                    speed: p.speed_mps,
                });
            }
            stats.push(filter.step(snap));
            if let Some(tr) = tracker.as_mut() {
                let update = tr.after_step(filter, snap)?;
                let fuses = !update.fuse.is_empty();
                let fused = filter.apply_prior_update(update);
                if fuses {
                    tr.record_fused(fused);
                }
            }
        }
        if let Some(t) = truth
            && k > 0
        {
            let (p, q) = (&t.poses[k], &t.poses[k - 1]);
            true_traveled += (p.x - q.x).hypot(p.y - q.y);
        }
        let row = if islands == 1 {
            let (filter, stats) = (&filters[0], &stats[0]);
            let truth_cols = truth.map(|t| {
                let p = &t.poses[k];
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
            TrackRow {
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
            }
        } else {
            let mix = IslandMixture::of(&filters, &stats);
            traveled += (mix.mean[0] - last_mean[0]).hypot(mix.mean[1] - last_mean[1]);
            last_mean = mix.mean;
            let truth_cols = truth.map(|t| {
                let p = &t.poses[k];
                let (mut mae, mut mse) = (0.0, 0.0);
                for f in &filters {
                    let (a, r) = f.errors(p.x, p.y);
                    mae += a / islands as f64;
                    mse += r * r / islands as f64;
                }
                TruthCols {
                    true_x: p.x,
                    true_y: p.y,
                    mae_m: mae,
                    rmse_m: mse.sqrt(),
                    err_m: (mix.mean[0] - p.x).hypot(mix.mean[1] - p.y),
                    nees: nees(mix.mean, mix.cov, p.x, p.y),
                    truth_ll_ratio: stats[0].truth_ll_ratio.unwrap_or(f64::NAN),
                }
            });
            TrackRow {
                t: stats[0].t,
                x: mix.mean[0],
                y: mix.mean[1],
                traveled_m: if truth.is_some() {
                    true_traveled
                } else {
                    traveled
                },
                truth: truth_cols,
                ess: stats.iter().map(|s| s.ess).sum(),
                transmitters: mix.transmitters,
                components: mix.components,
                log_evidence: mix.log_evidence,
                with_prior: None,
            }
        };
        rows.push(row);
        bar.inc(1);
    }
    bar.finish_and_clear();
    for f in &mut filters {
        f.finish();
    }
    // the island the detections favour most carries the map
    let best = (0..islands)
        .max_by(|&a, &b| {
            filters[a]
                .log_evidence()
                .total_cmp(&filters[b].log_evidence())
                .then(b.cmp(&a))
        })
        .unwrap_or(0);
    let filter = filters.swap_remove(best);
    let tracker = trackers.swap_remove(best);
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

/// Island `i` of `islands`: its share of the particles (the first ones take the remainder)
/// and its own seed (island 0 keeps the run's, so one island is the plain filter).
fn island_config(cfg: &FilterConfig, islands: usize, i: usize) -> FilterConfig {
    let n = cfg.particles.max(1);
    FilterConfig {
        particles: n / islands + usize::from(i < n % islands),
        islands: 1,
        seed: cfg
            .seed
            .wrapping_add((i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)),
        ..cfg.clone()
    }
}

/// The equally weighted mixture of the islands after one snapshot.
struct IslandMixture {
    mean: [f64; 2],
    /// `[xx, xy, yy]`: the islands' own covariances and their scatter about `mean`
    cov: [f64; 3],
    transmitters: f64,
    components: f64,
    /// ln of the mean of the islands' evidences
    log_evidence: f64,
}

impl IslandMixture {
    fn of(filters: &[Filter], stats: &[StepStats]) -> Self {
        let k = filters.len() as f64;
        let moments: Vec<([f64; 2], [f64; 3])> =
            filters.iter().map(Filter::position_moments).collect();
        let mut mean = [0.0; 2];
        for (m, _) in &moments {
            mean[0] += m[0] / k;
            mean[1] += m[1] / k;
        }
        let mut cov = [0.0; 3];
        for (m, c) in &moments {
            let (dx, dy) = (m[0] - mean[0], m[1] - mean[1]);
            cov[0] += (c[0] + dx * dx) / k;
            cov[1] += (c[1] + dx * dy) / k;
            cov[2] += (c[2] + dy * dy) / k;
        }
        IslandMixture {
            mean,
            cov,
            transmitters: stats.iter().map(|s| s.transmitters).sum::<f64>() / k,
            components: stats.iter().map(|s| s.components).sum::<f64>() / k,
            log_evidence: log_sum_exp(stats.iter().map(|s| s.log_evidence)) - k.ln(),
        }
    }
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

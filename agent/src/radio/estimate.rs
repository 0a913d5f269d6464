//! The front end end to end: a CIR (`cir`) → per snapshot SAGE estimation seeded by the
//! tracked paths (`sage`, `kest`) → an `echomap.log.v1` whose sensor profile states the
//! estimator's noise laws: the Cramér–Rao terms of its array and pulse at 0 dB, and floors
//! measured from its own tracks (the scatter of high-SNR detections about their tracks beyond
//! what the bound explains).

use super::cir::Cir;
use super::kest::{Tracker, TrackerConfig};
use super::sage::{SageConfig, Seed, SnapshotData, estimate};
use echomap_shared::log::{LOG_FORMAT, LogHeader, Measurement, MeasurementLog, Snapshot};
use echomap_shared::sensor::{NoiseLaw, SensorProfile};
use nalgebra::{Complex, Matrix2, Vector2};
use std::collections::HashMap;

/// Settings of the front end.
#[derive(Debug, Clone, PartialEq)]
pub struct FrontEndConfig {
    pub sage: SageConfig,
    pub tracker: TrackerConfig,
    /// tracks followed for less time than this (s, first to last detection) are left out
    /// of the log: a confirmation, as a tracker's M-of-N rule. A path seen for a moment is
    /// as likely noise or a neighbour's echo, and too short to place a transmitter
    pub min_track_s: f64,
}

impl Default for FrontEndConfig {
    fn default() -> Self {
        FrontEndConfig {
            sage: SageConfig::default(),
            tracker: TrackerConfig::default(),
            min_track_s: DEFAULT_MIN_TRACK_S,
        }
    }
}

/// What the front end found, beside the log.
#[derive(Debug, Clone, PartialEq)]
pub struct FrontEndStats {
    pub snapshots: usize,
    pub paths_per_snapshot: f64,
    pub tracks: usize,
    /// mean noise variance per sample (estimated where the CIR does not state it)
    pub noise_variance: f64,
}

/// The default confirmation time of a track (s).
pub const DEFAULT_MIN_TRACK_S: f64 = 0.5;

/// The fastest a path's distance changes (m/s) that a new track allows at its start.
const MAX_RANGE_RATE_MPS: f64 = 30.0;

/// Detections at least this strong (per-sample SNR, dB) measure the floors: there the
/// Cramér–Rao terms are small against them.
const FLOOR_SNR_DB: f64 = 10.0;

/// Estimates the paths of every snapshot of `cir` and writes them as a measurement log.
pub fn front_end(cir: &Cir, cfg: &FrontEndConfig) -> (MeasurementLog, FrontEndStats) {
    let meta = &cir.meta;
    let model = meta.model();
    let m = model.elements();
    let aoa = m > 1;
    let n = meta.samples;
    let mps = meta.metres_per_sample();
    let gain = meta.processing_gain;
    let mut tracker = Tracker::new(cfg.tracker.clone());
    let mut snapshots = Vec::with_capacity(meta.snapshots.len());
    let mut noise_sum = 0.0;
    // per track: (snapshot, d, θ, per-sample SNR dB), for the measured floors
    let mut history: HashMap<u64, Vec<(usize, f64, f64, f64)>> = HashMap::new();
    let mut prev_t: Option<f64> = None;
    for (k, s) in meta.snapshots.iter().enumerate() {
        let y: Vec<Complex<f64>> = cir
            .snapshot(k)
            .iter()
            .map(|c| Complex::new(f64::from(c.re), f64::from(c.im)))
            .collect();
        let noise_var = meta
            .noise_variance
            .unwrap_or_else(|| noise_from_samples(&y));
        noise_sum += noise_var;
        if let Some(pt) = prev_t {
            let dt = s.t - pt;
            tracker.predict(dt, s.gyro * dt);
        }
        prev_t = Some(s.t);
        // seeds leave a quarter of the paths to new ones: a channel whose tracks fill every
        // slot would never take up a path that appears
        let order = tracker.seed_order(cfg.sage.max_paths * 3 / 4);
        let seeds: Vec<Seed> = order
            .iter()
            .map(|&i| {
                let t = &tracker.tracks[i];
                Seed {
                    delay: (t.x[0] - meta.delay_origin_m) / mps,
                    aoa_rad: t.x[2],
                }
            })
            .collect();
        let found = estimate(
            &model,
            SnapshotData {
                data: &y,
                samples: n,
            },
            noise_var,
            &seeds,
            &cfg.sage,
        );
        let mut updated = vec![false; tracker.tracks.len()];
        let mut components = Vec::with_capacity(found.len());
        for p in &found {
            let d = meta.delay_origin_m + p.delay * mps;
            if d <= 0.0 {
                // no path is shorter than nothing: an edge effect of the delay window
                continue;
            }
            let snr_cir = p.amplitude.norm_sqr() / noise_var;
            let (sd, sa) = model.crb(n, p.delay, p.aoa_rad, snr_cir);
            let r = Matrix2::new(
                (sd * mps).powi(2),
                0.0,
                0.0,
                if aoa { sa * sa } else { 1.0 },
            );
            let z = Vector2::new(d, if aoa { p.aoa_rad } else { 0.0 });
            let id = match p.seed.map(|s| order[s]) {
                Some(i) if !updated[i] && tracker.distance2(i, z, &r) <= cfg.tracker.gate_chi2 => {
                    updated[i] = true;
                    tracker.update(i, z, &r);
                    tracker.tracks[i].id
                }
                _ => tracker.start(z, &r, MAX_RANGE_RATE_MPS),
            };
            let snr_db = 10.0 * (snr_cir / gain).log10();
            history
                .entry(id)
                .or_default()
                .push((k, d, p.aoa_rad, snr_db));
            components.push(Measurement {
                track: id,
                d,
                aoa: aoa.then_some(p.aoa_rad),
                snr_db,
            });
        }
        for (t, u) in tracker.tracks.iter_mut().zip(&updated) {
            if !u {
                t.missed += 1;
            }
        }
        // tracks started this snapshot are past `updated`'s end and were detected
        tracker.prune();
        components.sort_by_key(|c| c.track);
        snapshots.push(Snapshot {
            t: s.t,
            gyro: s.gyro,
            speed: s.speed,
            components,
            estimate: true,
        });
    }
    let k_total = meta.snapshots.len();
    let times: Vec<f64> = meta.snapshots.iter().map(|s| s.t).collect();
    history.retain(|_, h| {
        let (first, last) = (h[0].0, h[h.len() - 1].0);
        h.len() >= 2 && times[last] - times[first] >= cfg.min_track_s - 1e-9
    });
    for s in &mut snapshots {
        s.components.retain(|c| history.contains_key(&c.track));
    }
    let detections: usize = snapshots.iter().map(|s| s.components.len()).sum();
    let (crb_d, crb_a) = model.crb(n, n as f64 / 2.0, 0.0, gain);
    let (floor_d, floor_a, dof) = measured_floors(&history, &model, n, mps, gain, aoa);
    let sensor = SensorProfile {
        name: Some(format!(
            "echomap-agent estimate: SAGE + KEST-style tracking, {} MHz, {} element{}",
            meta.bandwidth_hz / 1e6,
            m,
            if m == 1 { "" } else { "s" }
        )),
        distance_m: Some(NoiseLaw {
            floor: floor_d,
            at_0db: crb_d * mps,
        }),
        aoa_rad: aoa.then_some(NoiseLaw {
            floor: floor_a,
            at_0db: crb_a,
        }),
        noise_dof: Some(dof),
        odometry: meta.odometry,
        ..Default::default()
    };
    let header = LogHeader {
        format: LOG_FORMAT.to_string(),
        snapshot_rate_hz: meta.snapshot_rate_hz,
        aoa,
        speed: meta.speed,
        track_hold_s: None,
        source: Some(format!(
            "echomap-agent estimate of {}",
            meta.source.as_deref().unwrap_or("a CIR")
        )),
        sensor: Some(sensor),
    };
    let stats = FrontEndStats {
        snapshots: k_total,
        paths_per_snapshot: detections as f64 / k_total.max(1) as f64,
        tracks: history.len(),
        noise_variance: noise_sum / k_total.max(1) as f64,
    };
    (MeasurementLog { header, snapshots }, stats)
}

/// σ² from the samples: the median of |y|² over ln 2 (the median of an exponential law),
/// which the few samples paths occupy barely move.
fn noise_from_samples(y: &[Complex<f64>]) -> f64 {
    let mut p: Vec<f64> = y.iter().map(|c| c.norm_sqr()).collect();
    let mid = p.len() / 2;
    let (_, median, _) = p.select_nth_unstable_by(mid, f64::total_cmp);
    (*median / std::f64::consts::LN_2).max(f64::MIN_POSITIVE)
}

/// The noise floors (distance m, angle rad) the tracks show, and the degrees of freedom of
/// their tails: over three consecutive detections of a track at ≥ `FLOOR_SNR_DB`, the second
/// difference has variance 6σ² for white errors (a path's own motion adds little at the
/// snapshot rate); σ² beyond the Cramér–Rao term at that SNR is the floor. Medians, so a
/// switch of paths does not count. The tails: the second differences over their stated σ,
/// distance and angle pooled, fitted by a Student-t law
/// ([`echomap_shared::calibration::student_t_dof`]; 0 when a Gaussian fits as well).
fn measured_floors(
    history: &HashMap<u64, Vec<(usize, f64, f64, f64)>>,
    model: &super::array::ArrayModel,
    samples: usize,
    mps: f64,
    gain: f64,
    aoa: bool,
) -> (f64, f64, f64) {
    let (mut excess_d, mut excess_a) = (Vec::new(), Vec::new());
    // (second difference of distance, its Cramér–Rao σ; the same of the angle)
    let mut raw = Vec::new();
    for h in history.values() {
        for w in h.windows(3) {
            let (a, b, c) = (w[0], w[1], w[2]);
            if b.0 != a.0 + 1 || c.0 != b.0 + 1 || w.iter().any(|x| x.3 < FLOOR_SNR_DB) {
                continue;
            }
            let snr = 10f64.powf(b.3 / 10.0) * gain;
            let (sd, sa) = model.crb(samples, samples as f64 / 2.0, b.2, snr);
            let dd = a.1 - 2.0 * b.1 + c.1;
            let da = echomap_shared::wrap_angle(
                echomap_shared::wrap_angle(a.2 - b.2) - echomap_shared::wrap_angle(b.2 - c.2),
            );
            excess_d.push(dd * dd / 6.0 - (sd * mps).powi(2));
            excess_a.push(da * da / 6.0 - sa * sa);
            raw.push((dd, sd * mps, da, sa));
        }
    }
    // the median of a χ²₁-distributed square is 0.455 of its mean
    let floor = |mut v: Vec<f64>| -> f64 {
        if v.is_empty() {
            return 0.0;
        }
        let mid = v.len() / 2;
        let (_, med, _) = v.select_nth_unstable_by(mid, f64::total_cmp);
        (*med / 0.455).max(0.0).sqrt()
    };
    let (floor_d, floor_a) = (floor(excess_d), floor(excess_a));
    let mut u = Vec::with_capacity(2 * raw.len());
    for (dd, sd, da, sa) in raw {
        let (vd, va) = (
            6.0 * (floor_d * floor_d + sd * sd),
            6.0 * (floor_a * floor_a + sa * sa),
        );
        if vd > 0.0 {
            u.push(dd / vd.sqrt());
        }
        if aoa && va > 0.0 && va.is_finite() {
            u.push(da / va.sqrt());
        }
    }
    let dof = echomap_shared::calibration::student_t_dof(&u);
    (floor_d, floor_a, dof)
}

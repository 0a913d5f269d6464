//! Import of the UTIAS MRCLAM dataset (Leung et al. 2011) into an `echomap.log.v1`
//! measurement log plus ground truth, in the robot's local frame.
//!
//! Mapping: landmark range → distance d (b = 0), bearing → AoA (counter-clockwise from the
//! heading, towards the landmark — echomap's convention), odometry angular rate → gyro,
//! forward velocity → speed. Measurements of other robots (subjects 1–5) are dropped. A
//! landmark keeps its track id while it is re-observed within `track_gap_s`; after a longer
//! gap it gets a new id, so the filter has to associate it with the transmitter it knows.
//! Snapshots are formed at a fixed rate; gyro and speed are the time averages of the
//! odometry (zero-order hold) over each snapshot interval. The camera delivers a few frames
//! per second and MRCLAM lists only its detections: a snapshot whose interval holds no
//! measurement row at all is written motion-only (`"estimate": false`), so that the filter
//! does not count it as "nothing visible".

use anyhow::{Context, Result, bail, ensure};
use echomap_shared::Transform2;
use echomap_shared::log::{
    GroundTruth, LOG_FORMAT, LogHeader, Measurement, MeasurementLog, Snapshot, TRUTH_FORMAT,
    TruePose, TrueTransmitter,
};
use echomap_shared::sensor::{NoiseLaw, OdometryNoise, SensorProfile};
use echomap_shared::wrap_angle;
use nalgebra::{Isometry2, Point2, Vector2};
use std::collections::HashMap;
use std::path::Path;

/// Import settings.
#[derive(Debug, Clone, Copy)]
pub struct ImportOptions {
    pub robot: u32,
    /// a landmark unseen for longer than this starts a new track id (s)
    pub track_gap_s: f64,
    /// snapshot rate (Hz)
    pub rate_hz: f64,
    /// SNR written for a measurement at 1 m range (dB). MRCLAM has none; a camera's barcode
    /// image shrinks as 1/range, so the importer writes `snr_db − 20·log10(range / 1 m)`, and
    /// the filter's SNR noise model (`σ = floor ⊕ at_0db·10^(−SNR/20)`) then gives a range
    /// noise that grows in proportion to the range, as the data's residuals do (docs/results/single-user.md)
    pub snr_db: f64,
    /// how late the robot moves after its odometry's time stamps (`--odometry-delay`)
    pub odometry_delay: OdometryDelay,
}

impl ImportOptions {
    /// The importer's defaults for `robot`: a track gap of 5 s, 10 Hz snapshots, 20 dB at 1 m,
    /// the odometry's time stamps as they are.
    pub fn robot(robot: u32) -> Self {
        ImportOptions {
            robot,
            track_gap_s: 5.0,
            rate_hz: 10.0,
            snr_db: 20.0,
            odometry_delay: OdometryDelay::Fixed(0.0),
        }
    }
}

/// The delay between MRCLAM's odometry time stamps and the motion they describe. MRCLAM's
/// odometry is the commanded velocity, and the robot follows its commands a fraction of a
/// second late; the landmark bearings, stamped by the camera, show it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum OdometryDelay {
    /// estimated from the data (`estimate_odometry_delay`): no ground truth used
    Auto,
    /// this many seconds (0 = the time stamps as they are)
    Fixed(f64),
}

impl std::str::FromStr for OdometryDelay {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "auto" {
            return Ok(Self::Auto);
        }
        match s.parse::<f64>() {
            Ok(v) if v.is_finite() && v.abs() <= MAX_DELAY_S => Ok(Self::Fixed(v)),
            _ => Err(format!(
                "expected `auto` or seconds within ±{MAX_DELAY_S}, got {s:?}"
            )),
        }
    }
}

/// One landmark detection: (t s, landmark subject, range m, bearing rad).
pub type Detection = (f64, i64, f64, f64);

/// The largest odometry delay the importer considers or accepts (s).
pub const MAX_DELAY_S: f64 = 2.0;

/// What `estimate_odometry_delay` found.
#[derive(Debug, Clone, Copy)]
pub struct DelayEstimate {
    /// the delay (s) to add to the odometry's time stamps
    pub delay_s: f64,
    /// pairs of detections of one landmark that went into it
    pub pairs: usize,
    /// RMS of the clipped bearing residuals (rad) with this delay
    pub rms_rad: f64,
    /// the same with no delay
    pub rms_at_zero_rad: f64,
}

/// The SNR (dB) written for a detection at `range_m`, given the SNR at 1 m: 20 dB less per
/// decade of range (a target whose image shrinks as 1/range).
pub fn snr_at_range(snr_at_1m_db: f64, range_m: f64) -> f64 {
    snr_at_1m_db - 20.0 * range_m.log10()
}

/// Rows of a whitespace-separated MRCLAM file; `#` lines are comments. Errors name the line.
pub fn parse_table(text: &str, columns: usize, name: &str) -> Result<Vec<Vec<f64>>> {
    let mut rows = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let vals: Vec<f64> = line
            .split_whitespace()
            .map(|v| v.parse::<f64>())
            .collect::<Result<_, _>>()
            .with_context(|| format!("{name} line {}: not a number in {line:?}", i + 1))?;
        ensure!(
            vals.len() == columns,
            "{name} line {}: expected {columns} columns, got {}",
            i + 1,
            vals.len()
        );
        ensure!(
            vals.iter().all(|v| v.is_finite()),
            "{name} line {}: non-finite value",
            i + 1
        );
        rows.push(vals);
    }
    Ok(rows)
}

fn read(dir: &Path, file: &str, columns: usize) -> Result<Vec<Vec<f64>>> {
    let path = dir.join(file);
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    parse_table(&text, columns, file)
}

/// Linear interpolation of the ground truth (t, x, y, θ) at time t (θ interpolated on the circle).
fn interp_pose(gt: &[Vec<f64>], t: f64) -> (f64, f64, f64) {
    let i = gt.partition_point(|r| r[0] <= t).clamp(1, gt.len() - 1);
    let (a, b) = (&gt[i - 1], &gt[i]);
    let f = if b[0] > a[0] {
        ((t - a[0]) / (b[0] - a[0])).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (
        a[1] + (b[1] - a[1]) * f,
        a[2] + (b[2] - a[2]) * f,
        wrap_angle(a[3] + wrap_angle(b[3] - a[3]) * f),
    )
}

/// Time average of a zero-order-hold signal (column `col` of `odo`) over (t0, t1].
fn average(odo: &[Vec<f64>], col: usize, t0: f64, t1: f64) -> f64 {
    if t1 <= t0 {
        return 0.0;
    }
    let mut i = odo.partition_point(|r| r[0] <= t0).saturating_sub(1);
    let mut acc = 0.0;
    let mut t = t0;
    while t < t1 {
        let next = odo
            .get(i + 1)
            .map(|r| r[0])
            .unwrap_or(f64::INFINITY)
            .min(t1);
        let v = if odo[i][0] <= t { odo[i][col] } else { 0.0 };
        acc += v * (next - t);
        t = next;
        i += 1;
        if i >= odo.len() {
            break;
        }
    }
    acc / (t1 - t0)
}

/// Integral of a zero-order-hold signal (column `col` of MRCLAM odometry rows (t, v, ω), 0
/// before its first sample) from the first time stamp to each time stamp; `integral_to`
/// interpolates it.
#[derive(Debug)]
pub struct OdometryIntegral<'a> {
    odo: &'a [Vec<f64>],
    col: usize,
    cum: Vec<f64>,
}

impl<'a> OdometryIntegral<'a> {
    pub fn new(odo: &'a [Vec<f64>], col: usize) -> Self {
        let mut cum = Vec::with_capacity(odo.len());
        let mut acc = 0.0;
        for (i, r) in odo.iter().enumerate() {
            if i > 0 {
                acc += odo[i - 1][col] * (r[0] - odo[i - 1][0]);
            }
            cum.push(acc);
        }
        Self { odo, col, cum }
    }

    fn integral_to(&self, t: f64) -> f64 {
        let i = self.odo.partition_point(|r| r[0] <= t);
        if i == 0 {
            return 0.0;
        }
        self.cum[i - 1] + self.odo[i - 1][self.col] * (t - self.odo[i - 1][0])
    }

    /// ∫ over (a, b] of the signal delayed by `delay` s.
    pub fn over(&self, a: f64, b: f64, delay: f64) -> f64 {
        self.integral_to(b - delay) - self.integral_to(a - delay)
    }
}

/// Consecutive detections of one landmark at most this far apart (s) form a pair.
const PAIR_MAX_S: f64 = 1.0;
/// Bearing residuals are clipped at this (rad): a misread barcode costs no more than this.
const RESIDUAL_CLIP_RAD: f64 = 0.3;
/// Fewer pairs than this and `auto` keeps the time stamps as they are.
const MIN_PAIRS: usize = 30;
/// Grid step of the delay search (s).
const DELAY_STEP_S: f64 = 0.01;

/// Estimates how late the robot moves after its odometry's time stamps from the landmark
/// bearings alone (no ground truth): for each pair of detections of one landmark less than
/// `PAIR_MAX_S` apart, the odometry delayed by τ moves and turns the robot from the first
/// detection to the second, which predicts the second bearing from the first range and
/// bearing. τ minimizes the sum of the squared bearing residuals, each clipped at
/// `RESIDUAL_CLIP_RAD`, over a grid of `DELAY_STEP_S` within ±`MAX_DELAY_S`, refined by a
/// parabola through the best grid point and its neighbours. `detections` are (t, landmark,
/// range, bearing) in time order. `None` with fewer than `MIN_PAIRS` pairs or when the best
/// delay lies on the grid's edge.
pub fn estimate_odometry_delay(
    odo: &[Vec<f64>],
    detections: &[Detection],
) -> Option<DelayEstimate> {
    let mut last: HashMap<i64, (f64, f64, f64)> = HashMap::new();
    let mut pairs = Vec::new();
    for &(t, subject, range, bearing) in detections {
        if let Some(&(t1, r1, b1)) = last.get(&subject)
            && t > t1
            && t - t1 <= PAIR_MAX_S
        {
            pairs.push((t1, t, r1, b1, bearing));
        }
        last.insert(subject, (t, range, bearing));
    }
    if pairs.len() < MIN_PAIRS {
        return None;
    }
    let (speed, turn) = (OdometryIntegral::new(odo, 1), OdometryIntegral::new(odo, 2));
    let cost = |delay: f64| -> f64 {
        pairs
            .iter()
            .map(|&(t1, t2, r1, b1, b2)| {
                let (ds, dth) = (speed.over(t1, t2, delay), turn.over(t1, t2, delay));
                let lx = r1 * b1.cos() - ds * (0.5 * dth).cos();
                let ly = r1 * b1.sin() - ds * (0.5 * dth).sin();
                let e = wrap_angle(b2 - (ly.atan2(lx) - dth));
                e.powi(2).min(RESIDUAL_CLIP_RAD.powi(2))
            })
            .sum()
    };
    let steps = (MAX_DELAY_S / DELAY_STEP_S).round() as i64;
    let grid: Vec<(f64, f64)> = (-steps..=steps)
        .map(|k| {
            let d = k as f64 * DELAY_STEP_S;
            (d, cost(d))
        })
        .collect();
    let best = (0..grid.len())
        .min_by(|&a, &b| grid[a].1.total_cmp(&grid[b].1))
        .expect("the grid is not empty");
    if best == 0 || best == grid.len() - 1 {
        return None;
    }
    let (c0, c1, c2) = (grid[best - 1].1, grid[best].1, grid[best + 1].1);
    let curvature = c0 - 2.0 * c1 + c2;
    let shift = if curvature > 0.0 {
        (0.5 * (c0 - c2) / curvature).clamp(-0.5, 0.5)
    } else {
        0.0
    };
    let delay_s = grid[best].0 + shift * DELAY_STEP_S;
    let rms = |c: f64| (c / pairs.len() as f64).sqrt();
    Some(DelayEstimate {
        delay_s,
        pairs: pairs.len(),
        rms_rad: rms(cost(delay_s)),
        rms_at_zero_rad: rms(cost(0.0)),
    })
}

/// A dataset's barcode → subject table and its landmarks' true positions (world frame).
struct Landmarks {
    subject_of: HashMap<i64, i64>,
    position: HashMap<i64, (f64, f64)>,
}

impl Landmarks {
    fn read(dir: &Path) -> Result<Self> {
        Ok(Self {
            subject_of: read(dir, "Barcodes.dat", 2)?
                .iter()
                .map(|r| (r[1] as i64, r[0] as i64))
                .collect(),
            position: read(dir, "Landmark_Groundtruth.dat", 5)?
                .iter()
                .map(|r| (r[0] as i64, (r[1], r[2])))
                .collect(),
        })
    }

    /// The landmark a measurement row (t, barcode, range, bearing) detected: `None` for
    /// another robot (subjects 1–5), an unknown barcode or no range.
    fn detected(&self, row: &[f64]) -> Option<i64> {
        let &subject = self.subject_of.get(&(row[1] as i64))?;
        (subject > 5 && self.position.contains_key(&subject) && row[2] > 0.0).then_some(subject)
    }

    /// The detections of landmarks among measurement rows, in their order.
    fn detections(&self, meas: &[Vec<f64>]) -> Vec<Detection> {
        meas.iter()
            .filter_map(|r| Some((r[0], self.detected(r)?, r[2], r[3])))
            .collect()
    }
}

/// `estimate_odometry_delay` for one robot of an MRCLAM dataset directory, as `import
/// --odometry-delay auto` computes it (ground truth unread).
pub fn estimate_robot_delay(dir: &Path, robot: u32) -> Result<Option<DelayEstimate>> {
    ensure!((1..=5).contains(&robot), "--robot must be 1–5, got {robot}");
    let landmarks = Landmarks::read(dir)?;
    let odo = read(dir, &format!("Robot{robot}_Odometry.dat"), 3)?;
    let meas = read(dir, &format!("Robot{robot}_Measurement.dat"), 4)?;
    Ok(estimate_odometry_delay(&odo, &landmarks.detections(&meas)))
}

/// Converts one robot of an MRCLAM dataset directory.
pub fn import(dir: &Path, opts: ImportOptions) -> Result<(MeasurementLog, GroundTruth)> {
    ensure!(
        (1..=5).contains(&opts.robot),
        "--robot must be 1–5, got {}",
        opts.robot
    );
    ensure!(
        opts.rate_hz > 0.0 && opts.rate_hz.is_finite(),
        "--rate must be positive"
    );
    ensure!(
        opts.track_gap_s > 0.0 && opts.track_gap_s.is_finite(),
        "--track-gap must be positive"
    );
    let landmarks = Landmarks::read(dir)?;
    let gt = read(dir, &format!("Robot{}_Groundtruth.dat", opts.robot), 4)?;
    let mut odo = read(dir, &format!("Robot{}_Odometry.dat", opts.robot), 3)?;
    let meas = read(dir, &format!("Robot{}_Measurement.dat", opts.robot), 4)?;
    ensure!(
        gt.len() >= 2 && !odo.is_empty(),
        "ground truth or odometry is empty"
    );
    let (delay, delay_note) = match opts.odometry_delay {
        OdometryDelay::Fixed(d) => (d, format!("odometry delay {d} s")),
        OdometryDelay::Auto => match estimate_odometry_delay(&odo, &landmarks.detections(&meas)) {
            Some(e) => (
                e.delay_s,
                format!(
                    "odometry delay {:.3} s estimated from {} bearing pairs, RMS {:.4} rad (undelayed {:.4})",
                    e.delay_s, e.pairs, e.rms_rad, e.rms_at_zero_rad
                ),
            ),
            None => (
                0.0,
                format!(
                    "odometry delay 0 s: not estimated (fewer than {MIN_PAIRS} bearing pairs, or the best delay on the ±{MAX_DELAY_S} s edge)"
                ),
            ),
        },
    };
    for r in &mut odo {
        r[0] += delay;
    }
    let t0 = odo[0][0].max(gt[0][0]);
    let t_end = odo[odo.len() - 1][0].min(gt[gt.len() - 1][0]);
    if t_end <= t0 {
        bail!("odometry and ground truth do not overlap in time");
    }
    let (x0, y0, h0) = interp_pose(&gt, t0);
    let world_from_local = Isometry2::new(Vector2::new(x0, y0), h0);
    let local_from_world = world_from_local.inverse();
    let dt = 1.0 / opts.rate_hz;
    let n = ((t_end - t0) / dt).floor() as usize + 1;

    let mut snapshots = Vec::with_capacity(n);
    let mut poses = Vec::with_capacity(n);
    let mut transmitters = Vec::new();
    let mut last_seen: HashMap<i64, (f64, u64)> = HashMap::new();
    let mut next_track = 1u64;
    let mut mi = meas.partition_point(|r| r[0] <= t0);
    for k in 0..n {
        let t = t0 + k as f64 * dt;
        let (gyro, speed) = if k == 0 {
            (0.0, average(&odo, 1, t0, t0 + dt).max(0.0))
        } else {
            (
                average(&odo, 2, t - dt, t),
                average(&odo, 1, t - dt, t).max(0.0),
            )
        };
        // measurements in (t − dt, t], the last one per landmark
        let mut latest: std::collections::BTreeMap<i64, (f64, f64, f64)> =
            std::collections::BTreeMap::new();
        // the camera looked in this interval iff it reported anything (a robot, an unknown
        // barcode): MRCLAM lists detections only, at a few frames per second
        let mut looked = false;
        while mi < meas.len() && meas[mi][0] <= t {
            let r = &meas[mi];
            mi += 1;
            looked = true;
            let Some(subject) = landmarks.detected(r) else {
                continue; // another robot, an unknown barcode, or no range
            };
            latest.insert(subject, (r[0], r[2], r[3]));
        }
        let mut components = Vec::new();
        for (subject, (tm, range, bearing)) in latest {
            let track = match last_seen.get(&subject) {
                Some(&(ts, id)) if tm - ts <= opts.track_gap_s => id,
                _ => {
                    let id = next_track;
                    next_track += 1;
                    let (lx, ly) = landmarks.position[&subject];
                    let p = local_from_world * Point2::new(lx, ly);
                    transmitters.push(TrueTransmitter {
                        track: id,
                        state: [p.x, p.y, 0.0],
                        kind: "landmark".into(),
                        path: format!("subject {subject}"),
                    });
                    id
                }
            };
            last_seen.insert(subject, (tm, track));
            components.push(Measurement {
                track,
                d: range,
                aoa: Some(wrap_angle(bearing)),
                snr_db: snr_at_range(opts.snr_db, range),
            });
        }
        components.sort_by_key(|c| c.track);
        snapshots.push(Snapshot {
            t: t - t0,
            gyro,
            speed: Some(speed),
            components,
            estimate: looked,
        });
        let (x, y, h) = interp_pose(&gt, t);
        let p = local_from_world * Point2::new(x, y);
        let (xn, yn, _) = interp_pose(&gt, (t + dt).min(t_end));
        poses.push(TruePose {
            t: t - t0,
            x: p.x,
            y: p.y,
            heading_rad: wrap_angle(h - h0),
            speed_mps: (xn - x).hypot(yn - y) / dt,
        });
    }
    let header = LogHeader {
        format: LOG_FORMAT.into(),
        snapshot_rate_hz: opts.rate_hz,
        aoa: true,
        speed: true,
        track_hold_s: Some(opts.track_gap_s),
        source: Some(format!(
            "UTIAS MRCLAM robot {} (track gap {} s, {delay_note})",
            opts.robot, opts.track_gap_s
        )),
        sensor: Some(sensor_profile()),
    };
    let truth = GroundTruth {
        format: TRUTH_FORMAT.into(),
        world_from_local: Transform2::from_isometry(&world_from_local),
        poses,
        transmitters,
    };
    Ok((MeasurementLog { header, snapshots }, truth))
}

/// What the MRCLAM robots' camera and wheel odometry are like, measured from Dataset 6 (see
/// docs/results/single-user.md): written into every imported log, so that `run --log` needs
/// no flag for this sensor.
pub fn sensor_profile() -> SensorProfile {
    SensorProfile {
        name: Some("UTIAS MRCLAM: monocular camera on barcoded landmarks, wheel odometry".into()),
        // with the importer's SNR (20 dB at 1 m, −20 dB per decade of range): σ_d = 0.05 ⊕
        // 0.06·range, 1.5× the range residual the data shows (≈ 0.04·range)
        distance_m: Some(NoiseLaw {
            floor: 0.05,
            at_0db: 0.6,
        }),
        aoa_rad: Some(NoiseLaw {
            floor: 0.05,
            at_0db: 0.012,
        }),
        // the landmarks are seen directly: no clock offset
        line_of_sight_only: true,
        // the camera sees a landmark only when it faces it: a place's visibility counts
        // would hold every landmark behind it as "not seen" there
        heading_dependent_detection: true,
        // the commanded-velocity odometry loses heading mostly while turning
        odometry: Some(OdometryNoise {
            heading_rad_per_sqrt_s: Some(0.006),
            heading_rad_per_sqrt_rad: Some(0.11),
            speed_std_mps: None,
            // the heading noise per turned angle stands for the wheels' calibration errors
            gyro_bias_rad_per_s: Some(0.0),
            speed_scale: Some(0.0),
        }),
        // 15 landmarks seen again and again: a new track id is almost always one seen before
        new_transmitter_density: Some(1e-4),
        // bearing and range errors with heavier tails than a Gaussian (occlusion, barcode
        // misreads at the edge of the image)
        gate_chi2: Some(30.0),
        // those tails lie within the wide gate; the documented MRCLAM figures take every
        // detection as drawn from the noise laws
        outlier_probability: Some(0.0),
        // and as Gaussian laws with that gate
        noise_dof: Some(0.0),
        // one barcode per landmark: no clusters
        jump_probability: Some(0.0),
        jump_std_m: None,
    }
}

/// Dead reckoning: integrates the log's gyro and speed alone from the origin.
pub fn dead_reckoning(log: &MeasurementLog) -> Vec<(f64, f64)> {
    let mut out = Vec::with_capacity(log.snapshots.len());
    let (mut x, mut y, mut h) = (0.0, 0.0, 0.0);
    let mut prev_t = None;
    for s in &log.snapshots {
        if let Some(pt) = prev_t {
            let dt: f64 = s.t - pt;
            let h_new = h + s.gyro * dt;
            let v = s.speed.unwrap_or(0.0);
            let hm = 0.5 * (h + h_new);
            x += v * dt * hm.cos();
            y += v * dt * hm.sin();
            h = h_new;
        }
        prev_t = Some(s.t);
        out.push((x, y));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tiny dataset in MRCLAM format: robot 1 drives along +x at 0.5 m/s for 10 s starting
    /// at (1, 2) heading +x; landmark 6 (barcode 40) at (4, 3); robot 2 (barcode 9) is seen too.
    fn write_dataset(dir: &Path) {
        let header = "# UTIAS\n# produced\n# format\n# columns\n";
        std::fs::write(
            dir.join("Barcodes.dat"),
            format!("{header}1 5\r\n2 9\r\n6 40\r\n"),
        )
        .unwrap();
        std::fs::write(
            dir.join("Landmark_Groundtruth.dat"),
            format!("{header}6 4.0 3.0 0.001 0.001\r\n"),
        )
        .unwrap();
        let mut gt = String::from(header);
        let mut odo = String::from(header);
        for k in 0..=100 {
            let t = 1000.0 + k as f64 * 0.1;
            gt.push_str(&format!("{t:.3} {:.4} 2.0 0.0\r\n", 1.0 + 0.05 * k as f64));
            odo.push_str(&format!("{t:.3} 0.5 0.0\r\n"));
        }
        std::fs::write(dir.join("Robot1_Groundtruth.dat"), gt).unwrap();
        std::fs::write(dir.join("Robot1_Odometry.dat"), odo).unwrap();
        // landmark seen at t = 1001.05 and 1001.55 (same track), then 1008.05 (gap > 2 s: new track)
        let m = |t: f64| {
            let x = 1.0 + 0.5 * (t - 1000.0);
            let (dx, dy) = (4.0 - x, 1.0f64);
            format!("{t:.3} 40 {:.4} {:.4}\r\n", dx.hypot(dy), dy.atan2(dx))
        };
        let meas = format!(
            "{header}{}{}1003.000 9 1.0 0.1\r\n{}",
            m(1001.05),
            m(1001.55),
            m(1008.05)
        );
        std::fs::write(dir.join("Robot1_Measurement.dat"), meas).unwrap();
    }

    #[test]
    fn imports_a_small_dataset() {
        let dir = tempfile::tempdir().unwrap();
        write_dataset(dir.path());
        let opts = ImportOptions {
            robot: 1,
            track_gap_s: 2.0,
            rate_hz: 10.0,
            snr_db: 20.0,
            odometry_delay: OdometryDelay::Fixed(0.0),
        };
        let (log, truth) = import(dir.path(), opts).unwrap();
        assert_eq!(log.snapshots.len(), 101);
        assert!(log.header.speed && log.header.aoa);
        let comps: Vec<&Measurement> = log.snapshots.iter().flat_map(|s| &s.components).collect();
        assert_eq!(comps.len(), 3, "the robot sighting is dropped");
        assert_eq!(comps[0].track, comps[1].track);
        assert_ne!(
            comps[1].track, comps[2].track,
            "a gap over --track-gap starts a new track"
        );
        assert_eq!(truth.transmitters.len(), 2);
        // the camera looked in 4 intervals (3 landmark sightings, 1 of the other robot); every
        // other snapshot is motion-only, and the robot's interval has an estimate but no component
        let looked: Vec<usize> = (0..log.snapshots.len())
            .filter(|&k| log.snapshots[k].estimate)
            .collect();
        assert_eq!(looked, [11, 16, 30, 81], "snapshots with a camera frame");
        assert!(log.snapshots[30].components.is_empty());
        // landmark (4,3) in the local frame of a robot starting at (1,2) heading +x: (3, 1)
        let s = truth.transmitters[0].state;
        assert!((s[0] - 3.0).abs() < 1e-9 && (s[1] - 1.0).abs() < 1e-9 && s[2] == 0.0);
        // range and bearing agree with the local geometry at the measurement
        for (snap, pose) in log.snapshots.iter().zip(&truth.poses) {
            for c in &snap.components {
                let d = (3.0 - pose.x).hypot(1.0 - pose.y);
                assert!((c.d - d).abs() < 0.06, "{} vs {d}", c.d);
            }
        }
        // the SNR falls 20 dB per decade of range: 20 dB at 1 m, 20 − 20·log10(d) here
        for c in &comps {
            let want = 20.0 - 20.0 * c.d.log10();
            assert!((c.snr_db - want).abs() < 1e-9, "{} vs {want}", c.snr_db);
        }
        assert!(
            comps[0].d > comps[1].d && comps[0].snr_db < comps[1].snr_db,
            "a farther detection has the lower SNR"
        );
        // gyro 0 and speed 0.5 → dead reckoning follows the truth
        let dr = dead_reckoning(&log);
        let last = truth.poses.last().unwrap();
        assert!((dr.last().unwrap().0 - last.x).abs() < 1e-6);
        // the log round-trips through the reader
        MeasurementLog::parse(&log.to_jsonl()).unwrap();
    }

    /// A robot that weaves (ω = 0.6·sin(2πt/8) rad/s at 0.3 m/s) among six landmarks and
    /// follows its odometry `delay` s late; the camera sees the landmarks within ±0.6 rad
    /// every 0.2 s, exactly. Returns the odometry rows and the detections.
    fn weaving_robot(delay: f64) -> (Vec<Vec<f64>>, Vec<Detection>) {
        let omega = |t: f64| 0.6 * (2.0 * std::f64::consts::PI * t / 8.0).sin();
        let odo: Vec<Vec<f64>> = (0..=3000)
            .map(|k| {
                let t = k as f64 * 0.02;
                vec![t, 0.3, omega(t)]
            })
            .collect();
        let landmarks: Vec<(f64, f64)> = (0..6)
            .map(|i| {
                let a = i as f64 * std::f64::consts::PI / 3.0;
                (3.0 + 4.0 * a.cos(), 4.0 * a.sin())
            })
            .collect();
        let (mut x, mut y, mut h) = (0.0, 0.0, 0.0);
        let mut detections = Vec::new();
        let step = 0.001;
        for k in 0..60_000 {
            let t = k as f64 * step;
            if k % 200 == 0 {
                for (i, &(lx, ly)) in landmarks.iter().enumerate() {
                    let (dx, dy) = (lx - x, ly - y);
                    let bearing = wrap_angle(dy.atan2(dx) - h);
                    if bearing.abs() < 0.6 && dx.hypot(dy) < 6.0 {
                        detections.push((t, i as i64 + 6, dx.hypot(dy), bearing));
                    }
                }
            }
            // the odometry's command at t − delay moves the robot at t (nothing before it)
            let (v, w) = if t >= delay {
                (0.3, omega(t - delay))
            } else {
                (0.0, 0.0)
            };
            x += v * step * h.cos();
            y += v * step * h.sin();
            h += w * step;
        }
        (odo, detections)
    }

    #[test]
    fn the_odometry_delay_is_read_off_the_bearings() {
        for delay in [0.0, 0.25, 0.4] {
            let (odo, detections) = weaving_robot(delay);
            let e = estimate_odometry_delay(&odo, &detections).expect("enough pairs");
            assert!(e.pairs > 50, "{} pairs", e.pairs);
            assert!(
                (e.delay_s - delay).abs() < 0.01,
                "delay {delay}: estimated {}",
                e.delay_s
            );
            assert!(e.rms_rad <= e.rms_at_zero_rad + 1e-12);
            if delay > 0.0 {
                assert!(
                    e.rms_rad < 0.5 * e.rms_at_zero_rad,
                    "the delayed odometry explains the bearings: {} vs {}",
                    e.rms_rad,
                    e.rms_at_zero_rad
                );
            }
        }
        // too few pairs: no estimate (and `auto` keeps the time stamps)
        let (odo, detections) = weaving_robot(0.25);
        assert!(estimate_odometry_delay(&odo, &detections[..20]).is_none());
    }

    #[test]
    fn odometry_delay_flag_values() {
        assert_eq!("auto".parse::<OdometryDelay>(), Ok(OdometryDelay::Auto));
        assert_eq!(
            "0.25".parse::<OdometryDelay>(),
            Ok(OdometryDelay::Fixed(0.25))
        );
        for bad in ["", "soon", "NaN", "inf", "2.5", "-3"] {
            let err = bad.parse::<OdometryDelay>().unwrap_err();
            assert!(err.contains("auto"), "{bad:?}: {err}");
        }
    }

    #[test]
    fn a_fixed_delay_shifts_the_odometry() {
        // the small dataset's odometry, delayed 0.5 s: the robot starts 0.5 s later, so the
        // log is 5 snapshots shorter and every speed is still the commanded 0.5 m/s
        let dir = tempfile::tempdir().unwrap();
        write_dataset(dir.path());
        let opts = |odometry_delay| ImportOptions {
            robot: 1,
            track_gap_s: 2.0,
            rate_hz: 10.0,
            snr_db: 20.0,
            odometry_delay,
        };
        let (log0, _) = import(dir.path(), opts(OdometryDelay::Fixed(0.0))).unwrap();
        let (log5, truth5) = import(dir.path(), opts(OdometryDelay::Fixed(0.5))).unwrap();
        assert_eq!(log0.snapshots.len(), 101);
        assert_eq!(log5.snapshots.len(), 96);
        assert!(log5.snapshots[1..].iter().all(|s| s.speed == Some(0.5)));
        // the truth starts at 1000.5 s (x = 1.25 m) too, and still ends at 6 m
        let last = truth5.poses.last().unwrap();
        assert!((last.x - 4.75).abs() < 1e-9, "{}", last.x);
        assert!(
            log5.header
                .source
                .as_deref()
                .unwrap()
                .contains("odometry delay 0.5 s")
        );
        // three detections cannot estimate it: `auto` keeps the time stamps and says so
        let (auto, _) = import(dir.path(), opts(OdometryDelay::Auto)).unwrap();
        assert_eq!(auto.snapshots.len(), 101);
        assert!(
            auto.header
                .source
                .as_deref()
                .unwrap()
                .contains("not estimated")
        );
    }

    #[test]
    fn malformed_files_name_the_line() {
        let dir = tempfile::tempdir().unwrap();
        write_dataset(dir.path());
        std::fs::write(
            dir.path().join("Robot1_Odometry.dat"),
            "# h\n1000.0 0.5 0.0\n1000.1 zero 0.0\n",
        )
        .unwrap();
        let err = import(
            dir.path(),
            ImportOptions {
                robot: 1,
                track_gap_s: 2.0,
                rate_hz: 10.0,
                snr_db: 20.0,
                odometry_delay: OdometryDelay::Fixed(0.0),
            },
        )
        .unwrap_err();
        assert!(
            format!("{err:#}").contains("Robot1_Odometry.dat line 3"),
            "{err:#}"
        );
    }
}

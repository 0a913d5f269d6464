//! Simulation of one user track: geometry → channel-estimator output → measurement log.
//!
//! Per snapshot and per traced path:
//! - received power `P = P_tx − FSPL(L, f_c) − Σ interaction losses + F` with free-space loss
//!   `FSPL = 20·log10(4πL/λ)` over the whole path length `L` and slow fading `F`, an AR(1)
//!   process in travelled distance (std `fading_std_db`, correlation `fading_correlation_m`);
//! - per-sample SNR against thermal noise `−174 dBm/Hz + 10·log10(B) + NF`;
//! - resolution: two paths closer than `c/B` in distance *and* (with AoA) closer than the
//!   array's angular resolution are one component; only the stronger is reported;
//! - detection: SNR ≥ `detection_threshold_db`;
//! - noise: Gaussian, with CRLB-shaped standard deviations for an estimator integrating
//!   `N` samples at SNR γ (Kay, Fundamentals of Statistical Signal Processing I, §3):
//!   `σ_d = √(σ_d,floor² + (c / (2π·β·√(2Nγ)))²)`, `β = B/√12` the rms bandwidth of a flat
//!   spectrum; `σ_θ = √(σ_θ,floor² + 1/(2Nγ·Σₘ(k·aₘ)²))` with `aₘ` element m's offset from the
//!   array's centre across the direction of arrival (isotropic for a square grid and for a
//!   circle, neighbours half a wavelength apart). The floors stand
//!   for model mismatch and calibration, which dominate at high SNR in practice.
//! - tracks: a component keeps its track id while it is reported in consecutive snapshots;
//!   once it is missing (blocked, faded, unresolved, or dropped at random with rate
//!   `track_loss_rate_hz`) and comes back it gets a new id — as KEST does (Gentner et al. 2016 §5).
//!
//! The gyroscope reports the true mean heading rate over each interval plus bias and white
//! noise. Everything is reported in the user's local frame (origin at the start, +x along the
//! initial heading). Randomness: one seed, independent ChaCha streams for fading, track
//! losses, measurement noise and gyro, so changing one noise source leaves the others alone.

use super::SPEED_OF_LIGHT;
use super::raytrace::{Geometry, Interaction, Path, sequences, trace_all};
use super::scenario::{
    ArrayGeometry, Scenario, ScenarioError, Track, circle_radius_in_half_wavelengths,
};
use super::trajectory::Trajectory;
use echomap_shared::Transform2;
use echomap_shared::log::{
    GroundTruth, LOG_FORMAT, LogHeader, Measurement, MeasurementLog, Snapshot, TRUTH_FORMAT,
    TruePose, TrueTransmitter,
};
use echomap_shared::sensor::{NoiseLaw, OdometryNoise, SensorProfile};
use echomap_shared::wrap_angle;
use nalgebra::{Isometry2, Point2};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use std::collections::BTreeMap;

/// The simulator's output: the log an agent consumes and the ground truth beside it.
#[derive(Debug, Clone)]
pub struct SimOutput {
    pub log: MeasurementLog,
    pub truth: GroundTruth,
}

/// Options that are not part of the scenario.
#[derive(Debug, Clone, Copy)]
pub struct SimOptions {
    pub seed: u64,
    /// force ToA-only output even if the scenario's receiver has an array
    pub toa_only: bool,
}

/// Stream ids of the independent random sources.
const STREAM_FADING: u64 = 1;
const STREAM_LOSS: u64 = 2;
const STREAM_NOISE: u64 = 3;
const STREAM_GYRO: u64 = 4;
/// The sampled channel's noise (`channel::synthesize`).
pub(super) const STREAM_CIR_NOISE: u64 = 5;

/// The independent random stream `stream` of `seed`.
pub(super) fn rng(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    r.set_stream(stream);
    r
}

fn normal(r: &mut ChaCha8Rng) -> f64 {
    r.sample(StandardNormal)
}

impl Scenario {
    pub fn geometry(&self) -> Geometry {
        let p = |a: [f64; 2]| Point2::new(a[0], a[1]);
        Geometry {
            tx: p(self.transmitter.position),
            clock_offset_m: self.transmitter.clock_offset_m,
            walls: self.walls.iter().map(|w| [p(w.from), p(w.to)]).collect(),
            scatterers: self.scatterers.iter().map(|s| p(s.position)).collect(),
        }
    }

    /// Noise power over the bandwidth (dBm).
    pub fn noise_power_dbm(&self) -> f64 {
        -174.0 + 10.0 * self.bandwidth_hz.log10() + self.receiver.noise_figure_db
    }

    /// Received power (dBm) of a path, before fading.
    pub fn path_power_dbm(&self, path: &Path) -> f64 {
        let lambda = self.wavelength_m();
        let fspl = 20.0 * (4.0 * std::f64::consts::PI * path.length_m.max(lambda) / lambda).log10();
        let losses: f64 = path
            .interactions
            .iter()
            .map(|i| match *i {
                Interaction::Reflect(w) => self.walls[w].reflection_loss_db,
                Interaction::Scatter(s) => self.scatterers[s].scattering_loss_db,
            })
            .sum();
        self.transmitter.power_dbm - fspl - losses
    }

    /// The sensor profile the simulator writes into its logs: the estimator's noise laws,
    /// stated as a data sheet states error bounds. The floors are [`PROFILE_FLOOR_MARGIN`]
    /// times as large as drawn, since they stand for model mismatch and calibration, which a
    /// filter should not take as exactly known; the Cramér–Rao terms at 0 dB are rounded up
    /// to two significant digits (a bound is never understated). The gyroscope is left out:
    /// its noise is far below the motion-model noise a walking user needs, which the filter's
    /// default covers.
    pub fn sensor_profile(&self, aoa: bool) -> SensorProfile {
        let e = &self.estimator;
        let (crlb_d, crlb_a) = self.crlb(0.0);
        SensorProfile {
            name: Some(format!(
                "echomap simulator: {} MHz, {} integrated samples, {}",
                self.bandwidth_hz / 1e6,
                e.integration_samples,
                if aoa {
                    let layout = match self.receiver.array_geometry {
                        ArrayGeometry::Square => "",
                        ArrayGeometry::Circular => "circular ",
                    };
                    format!("{}-element {layout}array", self.receiver.array_elements)
                } else {
                    "single antenna".to_string()
                }
            )),
            distance_m: Some(NoiseLaw {
                floor: PROFILE_FLOOR_MARGIN * e.distance_floor_m,
                at_0db: round_up_2_digits(crlb_d),
            }),
            aoa_rad: (aoa && crlb_a.is_finite()).then_some(NoiseLaw {
                floor: PROFILE_FLOOR_MARGIN * e.aoa_floor_rad,
                at_0db: round_up_2_digits(crlb_a),
            }),
            // the simulated estimator's errors are the noise laws alone, Gaussian, and each
            // track follows one virtual transmitter
            outlier_probability: Some(0.0),
            noise_dof: Some(0.0),
            jump_probability: Some(0.0),
            // the gyroscope's bias as configured (a data sheet's bound); no measured speed
            odometry: Some(OdometryNoise {
                gyro_bias_rad_per_s: Some(self.gyro.bias_rad_s.abs()),
                speed_scale: Some(0.0),
                ..Default::default()
            }),
            ..Default::default()
        }
    }

    /// The Cramér–Rao terms (distance m, AoA rad) at per-sample SNR `snr_db`, without floors.
    fn crlb(&self, snr_db: f64) -> (f64, f64) {
        let e = &self.estimator;
        let gamma = 10f64.powf(snr_db / 10.0) * e.integration_samples;
        let beta = self.bandwidth_hz / 12f64.sqrt();
        let crlb_d = SPEED_OF_LIGHT / (2.0 * std::f64::consts::PI * beta * (2.0 * gamma).sqrt());
        // Fisher information of the angle per unit 2Nγ: Σₘ (k·(rₘ − r̄)·u⊥(θ))², the same in
        // every direction for a square grid and for a circle; offsets in half-wavelengths, so
        // that k·offset = π·offset
        let m = f64::from(self.receiver.array_elements);
        let aperture = match self.receiver.array_geometry {
            ArrayGeometry::Square => {
                // Σ over a side×side grid of (π·offset)² per axis
                let side = m.sqrt();
                let axis: f64 = (0..side as usize)
                    .map(|i| (i as f64 - (side - 1.0) / 2.0).powi(2))
                    .sum();
                std::f64::consts::PI.powi(2) * side * axis
            }
            ArrayGeometry::Circular => {
                // M elements on a circle of radius 1/(2·sin(π/M)) half-wavelengths: M·(π·R)²/2
                let radius = circle_radius_in_half_wavelengths(self.receiver.array_elements);
                0.5 * m * (std::f64::consts::PI * radius).powi(2)
            }
        };
        let crlb_a = if aperture > 0.0 {
            (1.0 / (2.0 * gamma * aperture)).sqrt()
        } else {
            f64::INFINITY
        };
        (crlb_d, crlb_a)
    }

    /// Standard deviations (distance m, AoA rad) of the estimates at per-sample SNR `snr_db`.
    pub fn noise_std(&self, snr_db: f64) -> (f64, f64) {
        let (crlb_d, crlb_a) = self.crlb(snr_db);
        let e = &self.estimator;
        (
            e.distance_floor_m.hypot(crlb_d),
            e.aoa_floor_rad.hypot(crlb_a),
        )
    }
}

/// How much larger than drawn the simulator states its noise floors in a log's sensor
/// profile (see [`Scenario::sensor_profile`]).
pub const PROFILE_FLOOR_MARGIN: f64 = 1.5;

/// `x > 0` rounded up to two significant digits (0.1461 → 0.15, 0.01149 → 0.012).
fn round_up_2_digits(x: f64) -> f64 {
    if !(x.is_finite() && x > 0.0) {
        return x;
    }
    let scale = 10f64.powi(1 - x.log10().floor() as i32);
    // the tolerance keeps a value already on the grid (0.15·100 = 15.000000000000002) there
    (x * scale - 1e-9).ceil() / scale
}

/// Geometry, interaction sequences and trajectory for tracing `track` of `scenario`.
fn tracing_setup(
    scenario: &Scenario,
    track: &Track,
) -> (Geometry, Vec<Vec<Interaction>>, Trajectory) {
    let geo = scenario.geometry();
    let seqs = sequences(
        geo.walls.len(),
        geo.scatterers.len(),
        scenario.estimator.max_order,
    );
    (
        geo,
        seqs,
        Trajectory::new(&track.waypoints, track.turn_radius_m),
    )
}

/// One resolved, detected component before noise.
struct Candidate {
    seq: usize,
    path: Path,
    distance_m: f64,
    aoa_rad: f64,
    snr_db: f64,
}

/// Simulates `track_name` of `scenario`.
pub fn simulate(
    scenario: &Scenario,
    track_name: &str,
    opts: SimOptions,
) -> Result<SimOutput, ScenarioError> {
    Ok(simulate_paths(scenario, track_name, opts, false)?.0)
}

/// One traced path at one snapshot, as the channel carries it (before resolution and
/// detection): what a CIR is made of.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChannelPath {
    /// path length plus clock offset (m)
    pub distance_m: f64,
    /// angle of arrival relative to the heading (rad)
    pub aoa_rad: f64,
    /// per-sample SNR (dB), with fading
    pub snr_db: f64,
}

/// `simulate`, and with `channel` every traced path of every snapshot.
#[allow(clippy::type_complexity)]
pub fn simulate_paths(
    scenario: &Scenario,
    track_name: &str,
    opts: SimOptions,
    channel: bool,
) -> Result<(SimOutput, Option<Vec<Vec<ChannelPath>>>), ScenarioError> {
    scenario.validate()?;
    let mut channel_paths: Option<Vec<Vec<ChannelPath>>> = channel.then(Vec::new);
    let track: &Track = scenario.track(track_name)?;
    let (geo, seqs, traj) = tracing_setup(scenario, track);
    let dt = 1.0 / scenario.snapshot_rate_hz;
    let step = track.speed_mps * dt;
    let n_snap = (traj.length_m() / step).floor() as usize + 1;
    let aoa = scenario.receiver.aoa && !opts.toa_only;
    let resolution_d = SPEED_OF_LIGHT / scenario.bandwidth_hz;
    let resolution_a = scenario.angular_resolution_rad();
    let noise_dbm = scenario.noise_power_dbm();
    let est = &scenario.estimator;
    let loss_prob = (est.track_loss_rate_hz * dt).min(1.0);

    let (p0, h0) = traj.pose_at(0.0);
    let world_from_local = Isometry2::new(p0.coords, h0);
    let local_from_world = world_from_local.inverse();

    let mut fading_rng = rng(opts.seed, STREAM_FADING);
    let mut loss_rng = rng(opts.seed, STREAM_LOSS);
    let mut noise_rng = rng(opts.seed, STREAM_NOISE);
    let mut gyro_rng = rng(opts.seed, STREAM_GYRO);

    let mut fading: Vec<Option<f64>> = vec![None; seqs.len()];
    let mut current_track: Vec<Option<u64>> = vec![None; seqs.len()];
    let mut next_track: u64 = 1;
    let mut true_tx = Vec::new();
    let mut snapshots = Vec::with_capacity(n_snap);
    let mut poses = Vec::with_capacity(n_snap);
    let mut prev_heading = h0;
    let rho = (-step / est.fading_correlation_m).exp();

    for k in 0..n_snap {
        let s = k as f64 * step;
        let (pos, heading) = traj.pose_at(s);
        let t = k as f64 * dt;
        let true_rate = if k == 0 {
            0.0
        } else {
            wrap_angle(heading - prev_heading) / dt
        };
        prev_heading = heading;
        let gyro = true_rate
            + scenario.gyro.bias_rad_s
            + scenario.gyro.noise_std_rad_s * normal(&mut gyro_rng);

        // Trace, fade, and collect candidates in sequence order (deterministic).
        let paths = trace_all(&geo, &seqs, &pos);
        let mut valid = vec![false; seqs.len()];
        let mut cands = Vec::with_capacity(paths.len());
        for (seq, path) in paths {
            valid[seq] = true;
            let f = match fading[seq] {
                Some(prev) => {
                    rho * prev
                        + (1.0 - rho * rho).sqrt() * est.fading_std_db * normal(&mut fading_rng)
                }
                None => est.fading_std_db * normal(&mut fading_rng),
            };
            fading[seq] = Some(f);
            let snr_db = scenario.path_power_dbm(&path) + f - noise_dbm;
            let dir = path.points[path.points.len() - 2] - pos;
            let aoa_rad = wrap_angle(dir.y.atan2(dir.x) - heading);
            let distance_m = path.distance_m(geo.clock_offset_m);
            cands.push(Candidate {
                seq,
                path,
                distance_m,
                aoa_rad,
                snr_db,
            });
        }
        for (seq, v) in valid.iter().enumerate() {
            if !v {
                fading[seq] = None;
            }
        }
        if let Some(ch) = channel_paths.as_mut() {
            ch.push(
                cands
                    .iter()
                    .map(|c| ChannelPath {
                        distance_m: c.distance_m,
                        aoa_rad: c.aoa_rad,
                        snr_db: c.snr_db,
                    })
                    .collect(),
            );
        }
        // Resolution: components already tracked first (the estimator's tracking loop holds
        // them), then the strongest; a path too close to a kept one is absorbed by it.
        let tracked = |c: &Candidate| current_track[c.seq].is_some();
        cands.sort_by(|a, b| {
            tracked(b)
                .cmp(&tracked(a))
                .then(b.snr_db.total_cmp(&a.snr_db))
                .then(a.seq.cmp(&b.seq))
        });
        let mut kept: Vec<Candidate> = Vec::new();
        for c in cands {
            let threshold = est.detection_threshold_db
                - if tracked(&c) {
                    est.tracking_hysteresis_db
                } else {
                    0.0
                };
            if c.snr_db < threshold {
                continue;
            }
            let merged = kept.iter().any(|k| {
                (k.distance_m - c.distance_m).abs() < resolution_d
                    && (!aoa || wrap_angle(k.aoa_rad - c.aoa_rad).abs() < resolution_a)
            });
            if !merged {
                kept.push(c);
            }
        }
        kept.sort_by_key(|c| c.seq);
        // Spurious track losses, then track-id bookkeeping.
        let mut reported = vec![false; seqs.len()];
        let mut components = Vec::with_capacity(kept.len());
        for c in kept {
            let lost = current_track[c.seq].is_some() && loss_rng.random::<f64>() < loss_prob;
            if lost {
                continue;
            }
            reported[c.seq] = true;
            let id = *current_track[c.seq].get_or_insert_with(|| {
                let id = next_track;
                next_track += 1;
                let v = local_from_world * c.path.vtx;
                true_tx.push(TrueTransmitter {
                    track: id,
                    state: [v.x, v.y, c.path.b_m],
                    kind: c.path.kind().to_string(),
                    path: c.path.label(),
                });
                id
            });
            let (sd, sa) = scenario.noise_std(c.snr_db);
            let d = (c.distance_m + sd * normal(&mut noise_rng)).max(1e-3);
            let a = wrap_angle(c.aoa_rad + sa * normal(&mut noise_rng));
            components.push(Measurement {
                track: id,
                d,
                aoa: aoa.then_some(a),
                snr_db: c.snr_db,
            });
        }
        for (seq, r) in reported.iter().enumerate() {
            if !r {
                current_track[seq] = None;
            }
        }
        components.sort_by_key(|m| m.track);
        snapshots.push(Snapshot {
            t,
            gyro,
            speed: None,
            components,
            estimate: true,
        });
        let local = local_from_world * pos;
        poses.push(TruePose {
            t,
            x: local.x,
            y: local.y,
            heading_rad: wrap_angle(heading - h0),
            speed_mps: track.speed_mps,
        });
    }

    if est.min_track_distance_m > 0.0 {
        drop_short_tracks(&mut snapshots, &mut true_tx, step, est.min_track_distance_m);
    }

    let header = LogHeader {
        format: LOG_FORMAT.to_string(),
        snapshot_rate_hz: scenario.snapshot_rate_hz,
        aoa,
        speed: false,
        track_hold_s: None,
        source: Some(format!(
            "echomap-agent simulate: scenario {} track {} seed {}",
            scenario.name, track.name, opts.seed
        )),
        sensor: Some(scenario.sensor_profile(aoa)),
    };
    let truth = GroundTruth {
        format: TRUTH_FORMAT.to_string(),
        world_from_local: Transform2::from_isometry(&world_from_local),
        poses,
        transmitters: true_tx,
    };
    Ok((
        SimOutput {
            log: MeasurementLog { header, snapshots },
            truth,
        },
        channel_paths,
    ))
}

/// Removes the components of every track whose first and last detections lie less than
/// `min_m` of travel apart (`step` metres per snapshot), and their true transmitters.
fn drop_short_tracks(
    snapshots: &mut [Snapshot],
    true_tx: &mut Vec<TrueTransmitter>,
    step: f64,
    min_m: f64,
) {
    let mut span: BTreeMap<u64, (usize, usize)> = BTreeMap::new();
    for (k, s) in snapshots.iter().enumerate() {
        for m in &s.components {
            span.entry(m.track)
                .and_modify(|e| e.1 = k)
                .or_insert((k, k));
        }
    }
    let keep = |track: u64| {
        span.get(&track)
            .is_some_and(|&(a, b)| (b - a) as f64 * step >= min_m)
    };
    for s in snapshots.iter_mut() {
        s.components.retain(|m| keep(m.track));
    }
    true_tx.retain(|t| keep(t.track));
}

/// Noise-free virtual transmitters (world frame) that are detectable somewhere along a track,
/// sampled every `step_m` metres — for drawing scenarios.
pub fn visible_virtual_transmitters(
    scenario: &Scenario,
    track: &Track,
    step_m: f64,
) -> Vec<(Point2<f64>, f64, String)> {
    let (geo, seqs, traj) = tracing_setup(scenario, track);
    let noise = scenario.noise_power_dbm();
    let mut seen: Vec<Option<(Point2<f64>, f64, String)>> = vec![None; seqs.len()];
    let mut s = 0.0;
    while s <= traj.length_m() {
        let (pos, _) = traj.pose_at(s);
        for (seq, path) in trace_all(&geo, &seqs, &pos) {
            if seen[seq].is_none()
                && scenario.path_power_dbm(&path) - noise
                    >= scenario.estimator.detection_threshold_db
            {
                seen[seq] = Some((path.vtx, path.b_m, path.kind().to_string()));
            }
        }
        s += step_m;
    }
    seen.into_iter().flatten().collect()
}

impl SimOutput {
    /// The true map of the distinct (virtual) transmitters the track saw, in the frame
    /// `map_from_local` puts the track's local frame into, each one Gaussian of std `std_m` in
    /// x, y and b, existence 1, reliability 50 m, no visibility counts: a perfect prior map,
    /// for tests and for measuring how far a perfect map gets.
    pub fn truth_map(
        &self,
        map_from_local: &nalgebra::Isometry2<f64>,
        std_m: f64,
    ) -> echomap_shared::TransmitterMap {
        use echomap_shared::map::Transmitter;
        use echomap_shared::mixture::Component;
        use nalgebra::{Matrix3, Point2, Vector3};
        let mut seen: Vec<[f64; 3]> = Vec::new();
        let mut txs = Vec::new();
        for t in &self.truth.transmitters {
            let s = t.state;
            if seen
                .iter()
                .any(|q| (0..3).all(|k| (q[k] - s[k]).abs() < 1e-6))
            {
                continue;
            }
            seen.push(s);
            let p = map_from_local * Point2::new(s[0], s[1]);
            txs.push(Transmitter {
                id: format!("p{}", t.track),
                components: vec![Component::new(
                    1.0,
                    Vector3::new(p.x, p.y, s[2]),
                    Matrix3::identity() * std_m * std_m,
                )],
                existence: 1.0,
                reliability_m: 50.0,
                visibility: Default::default(),
            });
        }
        echomap_shared::TransmitterMap::new(2.0, txs).expect("true transmitters make a valid map")
    }
}

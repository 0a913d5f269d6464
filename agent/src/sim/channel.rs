//! The sampled channel of a simulated track: every traced path of every snapshot as a
//! band-limited pulse at each antenna element, in complex Gaussian noise — the CIR a
//! correlating receiver would deliver (format `radio::cir`).
//!
//! Per path: amplitude `|α|² = γ·G` (γ its per-sample SNR with fading, G the estimator's
//! `integration_samples`: the correlator's gain, so that the CIR's noise has variance 1),
//! carrier phase `−2π·d/λ` from the path's length, the array response of the scenario's
//! receiver (a square grid or a circle, neighbours half a wavelength apart, as its Cramér–Rao
//! terms assume; one element for ToA only) and the sinc pulse of the bandwidth sampled at the bandwidth. The
//! delay window starts at 0 m and ends 16 samples after the longest path.

use super::SPEED_OF_LIGHT;
use super::scenario::Scenario;
use super::simulate::{ChannelPath, STREAM_CIR_NOISE, rng};
use crate::radio::cir::{CIR_FORMAT, Cir, CirMeta, CirSnapshot};
use echomap_shared::log::MeasurementLog;
use nalgebra::Complex;
use rand_distr::{Distribution, StandardNormal};

/// Paths weaker than this below the detection threshold are left out of the CIR (dB): their
/// energy is far below the noise of one sample.
const WEAKEST_PATH_BELOW_THRESHOLD_DB: f64 = 30.0;

/// The CIR of `log`'s snapshots with `paths` (from `simulate_paths`).
pub fn synthesize(
    scenario: &Scenario,
    log: &MeasurementLog,
    paths: &[Vec<ChannelPath>],
    aoa: bool,
    seed: u64,
) -> Cir {
    let wavelength_m = scenario.wavelength_m();
    let elements_m = scenario.array_elements_m(aoa);
    let fs = scenario.bandwidth_hz;
    let metres_per_sample = SPEED_OF_LIGHT / fs;
    let longest = paths
        .iter()
        .flatten()
        .map(|p| p.distance_m)
        .fold(0.0, f64::max);
    let samples = (longest / metres_per_sample).ceil() as usize + 16;
    let gain = scenario.estimator.integration_samples.max(1.0);
    let meta = CirMeta {
        format: CIR_FORMAT.to_string(),
        carrier_hz: scenario.carrier_hz,
        bandwidth_hz: scenario.bandwidth_hz,
        sample_rate_hz: fs,
        pulse: "sinc".to_string(),
        delay_origin_m: 0.0,
        samples,
        elements_m,
        processing_gain: gain,
        noise_variance: Some(1.0),
        snapshot_rate_hz: log.header.snapshot_rate_hz,
        speed: log.header.speed,
        source: log.header.source.clone(),
        odometry: log.header.sensor.as_ref().and_then(|s| s.odometry),
        snapshots: log
            .snapshots
            .iter()
            .map(|s| CirSnapshot {
                t: s.t,
                gyro: s.gyro,
                speed: s.speed,
            })
            .collect(),
    };
    let model = meta.model();
    let m = model.elements();
    let mut rng = rng(seed, STREAM_CIR_NOISE);
    let sigma = std::f64::consts::FRAC_1_SQRT_2;
    let weakest = scenario.estimator.detection_threshold_db - WEAKEST_PATH_BELOW_THRESHOLD_DB;
    let mut data = Vec::with_capacity(paths.len() * m * samples);
    for snapshot_paths in paths {
        let mut y = vec![Complex::<f64>::new(0.0, 0.0); m * samples];
        for p in snapshot_paths.iter().filter(|p| p.snr_db >= weakest) {
            let amplitude = (10f64.powf(p.snr_db / 10.0) * gain).sqrt();
            let phase = -std::f64::consts::TAU * p.distance_m / wavelength_m;
            let alpha = Complex::from_polar(amplitude, phase);
            let tau = p.distance_m / metres_per_sample;
            let a = model.steering(p.aoa_rad);
            let pulse: Vec<f64> = (0..samples).map(|n| model.pulse(n as f64 - tau)).collect();
            for (e, ae) in a.iter().enumerate() {
                let g = alpha * ae;
                for (x, pk) in y[e * samples..(e + 1) * samples].iter_mut().zip(&pulse) {
                    *x += g * *pk;
                }
            }
        }
        for x in y {
            let re: f64 = StandardNormal.sample(&mut rng);
            let im: f64 = StandardNormal.sample(&mut rng);
            data.push(Complex::new(
                (x.re + sigma * re) as f32,
                (x.im + sigma * im) as f32,
            ));
        }
    }
    Cir { meta, data }
}

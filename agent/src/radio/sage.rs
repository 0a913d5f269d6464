//! Multipath parameter estimation in one snapshot: successive interference cancellation
//! finds new paths, SAGE refines all of them jointly (Fleury et al. 1999, "Channel parameter
//! estimation in mobile radio environments using the SAGE algorithm").
//!
//! Model (see `array`): `y_m[n] = Σ_l α_l·a_m(θ_l)·p(n − τ_l) + w_m[n]`, `w` white complex
//! Gaussian of variance σ² per sample and element. SAGE takes each path in turn as the hidden
//! "complete data" `x_l = y − Σ_{l'≠l} s_{l'}` and maximizes its likelihood coordinate-wise:
//! - delay: `τ_l = argmax |Σ_n p(n−τ)·w[n]|² / Σ_n p(n−τ)²`, `w = a(θ_l)^H x_l` (beamformed);
//! - angle: `θ_l = argmax |a(θ)^H v|²`, `v_m = Σ_n p(n−τ_l)·x_{l,m}[n]` (delay-matched);
//! - amplitude: `α_l = a(θ_l)^H v / (M·E_p)`, `E_p = Σ_n p(n−τ_l)²`.
//!
//! Each 1-D search is a golden-section search in a bracket of one sample or one angle-grid
//! step around the current value. New paths come from the largest cell of the residual
//! beamformed on an angle grid (`4·M` directions, at least 16), and are kept when the
//! generalized likelihood ratio `T = |a^H v|²/(σ²·M·E_p)` (exponential with mean 1 on noise
//! alone) exceeds `ln(cells/P_fa)`, `cells` = 2 × delays × grid angles: a false-alarm
//! probability of at most `P_fa` per snapshot over the search. A path handed in from the tracker is kept down to
//! `ln(1/P_fa)`: its place was known before the snapshot. Cost per snapshot: `O(L·M·N)` per
//! SAGE sweep and `O(G·M·N)` per new path (L paths, G grid angles, N samples).

use super::array::{ArrayModel, PulseTable};
use nalgebra::Complex;

/// Settings of the estimator.
#[derive(Debug, Clone, PartialEq)]
pub struct SageConfig {
    /// most paths per snapshot
    pub max_paths: usize,
    /// probability of one false path per snapshot over the whole search
    pub false_alarm_probability: f64,
    /// most SAGE sweeps after each new path (fewer when the delays have settled)
    pub sweeps: usize,
}

impl Default for SageConfig {
    fn default() -> Self {
        SageConfig {
            max_paths: 40,
            false_alarm_probability: 1e-3,
            sweeps: 20,
        }
    }
}

/// One estimated path.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PathEstimate {
    /// delay in samples after the first sample of the window
    pub delay: f64,
    /// angle of arrival (rad, body frame); 0 for a single antenna
    pub aoa_rad: f64,
    pub amplitude: Complex<f64>,
    /// the generalized likelihood ratio `T` of the path against noise
    pub statistic: f64,
    /// the index of the seed it was refined from; None for a new path
    pub seed: Option<usize>,
}

/// A path to start from: the tracker's prediction of a known path.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Seed {
    pub delay: f64,
    pub aoa_rad: f64,
}

/// One snapshot's samples, element-major: `data[m·samples + n]`.
#[derive(Debug, Clone, Copy)]
pub struct SnapshotData<'a> {
    pub data: &'a [Complex<f64>],
    pub samples: usize,
}

/// Estimates the paths of one snapshot. `noise_var` is σ² per sample and element; `seeds`
/// are the tracker's predictions (kept to a lower threshold, in this order).
pub fn estimate(
    model: &ArrayModel,
    snap: SnapshotData<'_>,
    noise_var: f64,
    seeds: &[Seed],
    cfg: &SageConfig,
) -> Vec<PathEstimate> {
    let mut s = Solver::new(model, snap, noise_var);
    let eta_new = (s.cells() / cfg.false_alarm_probability).ln();
    let eta_keep = (1.0 / cfg.false_alarm_probability).ln();
    let mut paths: Vec<(PathEstimate, f64)> = Vec::new();
    for (i, seed) in seeds.iter().enumerate().take(cfg.max_paths) {
        let mut p = s.refine(seed.delay, seed.aoa_rad, s.angle_step());
        p.seed = Some(i);
        s.subtract(&p, 1.0);
        paths.push((p, eta_keep));
    }
    while paths.len() < cfg.max_paths {
        let (delay, aoa) = s.strongest_cell();
        let p = s.refine(delay, aoa, s.angle_step());
        let duplicate = paths.iter().any(|(q, _)| s.same_cell(q, &p));
        if p.statistic < eta_new || duplicate {
            break;
        }
        s.subtract(&p, 1.0);
        paths.push((p, eta_new));
        // one sweep after each new path: a new path near an earlier one takes back what the
        // earlier one had absorbed of it (SIC alone leaves both biased)
        s.converge(&mut paths, cfg.sweeps);
    }
    s.converge(&mut paths, cfg.sweeps);
    paths
        .into_iter()
        .filter(|(p, eta)| p.statistic >= *eta)
        .map(|(p, _)| p)
        .collect()
}

/// The residual of one snapshot and what the searches need.
struct Solver<'a> {
    model: &'a ArrayModel,
    samples: usize,
    noise_var: f64,
    residual: Vec<Complex<f64>>,
    grid: Vec<(f64, Vec<Complex<f64>>)>,
    table: PulseTable,
}

const GOLDEN: f64 = 0.618_033_988_749_895;

/// The maximum of `f` over `[lo, hi]` by golden-section search (`iters` steps).
fn golden_max(mut lo: f64, mut hi: f64, iters: usize, mut f: impl FnMut(f64) -> f64) -> f64 {
    let mut a = hi - GOLDEN * (hi - lo);
    let mut b = lo + GOLDEN * (hi - lo);
    let (mut fa, mut fb) = (f(a), f(b));
    for _ in 0..iters {
        if fa < fb {
            lo = a;
            a = b;
            fa = fb;
            b = lo + GOLDEN * (hi - lo);
            fb = f(b);
        } else {
            hi = b;
            b = a;
            fb = fa;
            a = hi - GOLDEN * (hi - lo);
            fa = f(a);
        }
    }
    if fa > fb { a } else { b }
}

impl<'a> Solver<'a> {
    fn new(model: &'a ArrayModel, snap: SnapshotData<'_>, noise_var: f64) -> Self {
        let m = model.elements();
        let g = if m > 1 { (4 * m).max(16) } else { 1 };
        let grid = (0..g)
            .map(|i| {
                let th = std::f64::consts::TAU * i as f64 / g as f64;
                let th = echomap_shared::wrap_angle(th);
                (th, model.steering(th))
            })
            .collect();
        Solver {
            model,
            samples: snap.samples,
            noise_var: noise_var.max(f64::MIN_POSITIVE),
            residual: snap.data.to_vec(),
            grid,
            table: model.pulse_table(snap.samples),
        }
    }

    fn elements(&self) -> usize {
        self.model.elements()
    }

    /// The number of independent tries the search for a new path makes on noise: every
    /// sample delay and grid angle, twice over for the continuous refinement between them
    /// (an upper count; `noise_alone_rarely_makes_a_path` measures the rate it gives).
    fn cells(&self) -> f64 {
        (2 * self.samples * self.grid.len()) as f64
    }

    fn angle_step(&self) -> f64 {
        if self.elements() > 1 {
            std::f64::consts::TAU / self.grid.len() as f64
        } else {
            0.0
        }
    }

    fn pulse(&self, delay: f64) -> Vec<f64> {
        let mut out = vec![0.0; self.samples];
        self.table.fill(delay, &mut out);
        out
    }

    /// The residual's largest beamformed sample over the angle grid: (delay, angle).
    fn strongest_cell(&self) -> (f64, f64) {
        let n = self.samples;
        let mut best = (0.0, 0.0, f64::NEG_INFINITY);
        for (th, a) in &self.grid {
            for k in 0..n {
                let z: Complex<f64> = a
                    .iter()
                    .enumerate()
                    .map(|(m, am)| am.conj() * self.residual[m * n + k])
                    .sum();
                let v = z.norm_sqr();
                if v > best.2 {
                    best = (k as f64, *th, v);
                }
            }
        }
        (best.0, best.1)
    }

    /// `v_m = Σ_n p(n−τ)·x_m[n]` of `residual + s` (the path's complete data) and `E_p`.
    fn delay_matched(&self, pulse: &[f64]) -> (Vec<Complex<f64>>, f64) {
        let n = self.samples;
        let v = (0..self.elements())
            .map(|m| {
                self.residual[m * n..(m + 1) * n]
                    .iter()
                    .zip(pulse)
                    .map(|(x, p)| x * *p)
                    .sum()
            })
            .collect();
        (v, pulse.iter().map(|p| p * p).sum())
    }

    /// SAGE's coordinate-wise maximization for one path whose signal is not in the residual,
    /// starting at (`delay`, `aoa`): delay within ±1 sample, angle within ±`angle_bracket`.
    fn refine(&self, delay: f64, aoa: f64, angle_bracket: f64) -> PathEstimate {
        let n = self.samples;
        let m = self.elements();
        let mut aoa = aoa;
        let mut delay = delay;
        for _ in 0..2 {
            let a = self.model.steering(aoa);
            let w: Vec<Complex<f64>> = (0..n)
                .map(|k| {
                    a.iter()
                        .enumerate()
                        .map(|(e, ae)| ae.conj() * self.residual[e * n + k])
                        .sum()
                })
                .collect();
            let lo = (delay - 1.0).max(-0.5);
            let hi = (delay + 1.0).min(n as f64 - 0.5);
            delay = golden_max(lo, hi, 24, |tau| {
                let (z, e) = self.table.correlate(tau, &w);
                z.norm_sqr() / e.max(f64::MIN_POSITIVE)
            });
            if m > 1 && angle_bracket > 0.0 {
                let (v, _) = self.delay_matched(&self.pulse(delay));
                let mut a = vec![Complex::new(0.0, 0.0); m];
                aoa = golden_max(aoa - angle_bracket, aoa + angle_bracket, 24, |th| {
                    self.model.steering_into(th, &mut a);
                    let z: Complex<f64> = a.iter().zip(&v).map(|(x, y)| x.conj() * y).sum();
                    z.norm_sqr()
                });
                aoa = echomap_shared::wrap_angle(aoa);
            }
        }
        let (v, e) = self.delay_matched(&self.pulse(delay));
        let a = self.model.steering(aoa);
        let z: Complex<f64> = a.iter().zip(&v).map(|(x, y)| x.conj() * y).sum();
        let e = e.max(f64::MIN_POSITIVE);
        PathEstimate {
            delay,
            aoa_rad: if m > 1 { aoa } else { 0.0 },
            amplitude: z / (m as f64 * e),
            statistic: z.norm_sqr() / (self.noise_var * m as f64 * e),
            seed: None,
        }
    }

    /// SAGE sweeps (each path in turn re-estimated from its complete data) until no delay
    /// moves by more than a hundredth of a sample, at most `max_sweeps`.
    fn converge(&mut self, paths: &mut [(PathEstimate, f64)], max_sweeps: usize) {
        for _ in 0..max_sweeps {
            let mut moved: f64 = 0.0;
            for (p, _) in paths.iter_mut() {
                self.subtract(p, -1.0);
                let mut q = self.refine(p.delay, p.aoa_rad, 0.5 * self.angle_step());
                q.seed = p.seed;
                moved = moved.max((q.delay - p.delay).abs());
                *p = q;
                self.subtract(p, 1.0);
            }
            if moved < 0.01 {
                break;
            }
        }
    }

    /// `residual −= sign · s(path)`.
    fn subtract(&mut self, p: &PathEstimate, sign: f64) {
        let n = self.samples;
        let pulse = self.pulse(p.delay);
        let a = self.model.steering(p.aoa_rad);
        for (m, am) in a.iter().enumerate() {
            let g = p.amplitude * am * sign;
            for (x, pk) in self.residual[m * n..(m + 1) * n].iter_mut().zip(&pulse) {
                *x -= g * *pk;
            }
        }
    }

    /// Whether two estimates are one path: within half a sample and half a grid step.
    fn same_cell(&self, a: &PathEstimate, b: &PathEstimate) -> bool {
        (a.delay - b.delay).abs() < 0.5
            && echomap_shared::wrap_angle(a.aoa_rad - b.aoa_rad).abs() <= 0.5 * self.angle_step()
    }
}

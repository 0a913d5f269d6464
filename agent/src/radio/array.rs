//! The signal model of one propagation path in a sampled CIR (Fleury et al. 1999, SAGE):
//! `s_m[n] = α · a_m(θ) · p(n − τ)`, with
//! - `a_m(θ) = exp(j·2π/λ · r_m·u(θ))` the plane-wave response of element `m` at position
//!   `r_m` (metres, body frame: +x forward, +y left) to a wave arriving from the direction
//!   `u(θ) = (cos θ, sin θ)` — θ is the angle of arrival relative to the heading;
//! - `p(t) = sinc(ρ·t)` the band-limited pulse of bandwidth B sampled at `f_s` (`ρ = B/f_s ≤
//!   1`, t in samples): a flat spectrum over the band, rms bandwidth `B/√12`;
//! - `τ` the delay in samples after the first sample of the delay window.

use nalgebra::Complex;

/// The receiver's antenna array and sampling: what a CIR's samples mean.
#[derive(Debug, Clone, PartialEq)]
pub struct ArrayModel {
    /// element positions in the body frame (m)
    pub elements_m: Vec<[f64; 2]>,
    /// carrier wavelength (m)
    pub wavelength_m: f64,
    /// `B / f_s` (0 < ρ ≤ 1)
    pub rho: f64,
}

impl ArrayModel {
    pub fn elements(&self) -> usize {
        self.elements_m.len()
    }

    /// `a(θ)`, one complex gain per element.
    pub fn steering(&self, aoa_rad: f64) -> Vec<Complex<f64>> {
        let mut out = vec![Complex::new(0.0, 0.0); self.elements()];
        self.steering_into(aoa_rad, &mut out);
        out
    }

    /// `a(θ)` written into `out` (one entry per element).
    pub fn steering_into(&self, aoa_rad: f64, out: &mut [Complex<f64>]) {
        let k = std::f64::consts::TAU / self.wavelength_m;
        let (s, c) = aoa_rad.sin_cos();
        for (o, r) in out.iter_mut().zip(&self.elements_m) {
            *o = Complex::from_polar(1.0, k * (r[0] * c + r[1] * s));
        }
    }

    /// `∂a/∂θ`.
    pub fn steering_derivative(&self, aoa_rad: f64) -> Vec<Complex<f64>> {
        let k = std::f64::consts::TAU / self.wavelength_m;
        let (s, c) = aoa_rad.sin_cos();
        self.elements_m
            .iter()
            .map(|r| {
                let phase = k * (r[0] * c + r[1] * s);
                Complex::from_polar(1.0, phase) * Complex::new(0.0, k * (-r[0] * s + r[1] * c))
            })
            .collect()
    }

    /// The pulse at `t` samples from its peak.
    pub fn pulse(&self, t: f64) -> f64 {
        sinc(self.rho * t)
    }

    /// The pulse at the samples `0..samples` for any delay, at one `sin_cos` per delay
    /// instead of one `sin` per sample.
    pub fn pulse_table(&self, samples: usize) -> PulseTable {
        let w = std::f64::consts::PI * self.rho;
        PulseTable {
            w,
            sin_cos: (0..samples).map(|k| (w * k as f64).sin_cos()).collect(),
        }
    }

    /// The pulse's time derivative (per sample).
    pub fn pulse_derivative(&self, t: f64) -> f64 {
        let x = std::f64::consts::PI * self.rho * t;
        if x.abs() < 1e-6 {
            return 0.0;
        }
        self.rho * std::f64::consts::PI * (x.cos() / x - x.sin() / (x * x))
    }

    /// The Cramér–Rao bounds (delay in samples, angle in rad) of one path alone in a window
    /// of `samples` samples, at `snr` = |α|²/σ² per sample and element (linear), for an
    /// unknown complex amplitude (Kay 1993, §3.9; the Fisher information of each parameter
    /// with the amplitude's projected out, delay and angle decoupled for a real pulse).
    pub fn crb(&self, samples: usize, delay: f64, aoa_rad: f64, snr: f64) -> (f64, f64) {
        let m = self.elements() as f64;
        let (mut e, mut e1, mut ep) = (0.0, 0.0, 0.0);
        for n in 0..samples {
            let t = n as f64 - delay;
            let p = self.pulse(t);
            let d = self.pulse_derivative(t);
            e += p * p;
            e1 += d * d;
            ep += p * d;
        }
        let info_tau = 2.0 * snr * m * (e1 - ep * ep / e);
        let a = self.steering(aoa_rad);
        let da = self.steering_derivative(aoa_rad);
        let d2: f64 = da.iter().map(|x| x.norm_sqr()).sum();
        let cross: Complex<f64> = a.iter().zip(&da).map(|(x, y)| x.conj() * y).sum();
        let info_theta = 2.0 * snr * e * (d2 - cross.norm_sqr() / m);
        (1.0 / info_tau.sqrt(), 1.0 / info_theta.sqrt())
    }
}

/// `sin(πx)/(πx)`.
/// `p(k − τ)` at the samples `k = 0..n` of a window: with `w = π·ρ`,
/// `sin(w·(k − τ)) = sin(w·k)·cos(w·τ) − cos(w·k)·sin(w·τ)`, the first factors tabulated.
#[derive(Debug, Clone)]
pub struct PulseTable {
    w: f64,
    sin_cos: Vec<(f64, f64)>,
}

impl PulseTable {
    pub fn samples(&self) -> usize {
        self.sin_cos.len()
    }

    /// `out[k] = p(k − delay)` for every sample of the window.
    pub fn fill(&self, delay: f64, out: &mut [f64]) {
        let (st, ct) = (self.w * delay).sin_cos();
        for (k, (o, (sk, ck))) in out.iter_mut().zip(&self.sin_cos).enumerate() {
            let x = self.w * (k as f64 - delay);
            *o = if x.abs() < 1e-9 {
                1.0
            } else {
                (sk * ct - ck * st) / x
            };
        }
    }

    /// `Σ_k p(k − delay)·w_k` and `Σ_k p(k − delay)²`.
    pub fn correlate(&self, delay: f64, w: &[Complex<f64>]) -> (Complex<f64>, f64) {
        let (st, ct) = (self.w * delay).sin_cos();
        let (mut z, mut e) = (Complex::new(0.0, 0.0), 0.0);
        for (k, (wk, (sk, ck))) in w.iter().zip(&self.sin_cos).enumerate() {
            let x = self.w * (k as f64 - delay);
            let p = if x.abs() < 1e-9 {
                1.0
            } else {
                (sk * ct - ck * st) / x
            };
            z += wk * p;
            e += p * p;
        }
        (z, e)
    }
}

pub fn sinc(x: f64) -> f64 {
    let px = std::f64::consts::PI * x;
    if px.abs() < 1e-9 { 1.0 } else { px.sin() / px }
}

/// `count` elements on a circle of radius `radius_m` (first on +x, counter-clockwise).
pub fn uniform_circular(count: usize, radius_m: f64) -> Vec<[f64; 2]> {
    (0..count)
        .map(|i| {
            let phi = std::f64::consts::TAU * i as f64 / count as f64;
            [radius_m * phi.cos(), radius_m * phi.sin()]
        })
        .collect()
}

/// `side × side` elements at `spacing_m` in a square centred on the origin.
pub fn uniform_square(side: usize, spacing_m: f64) -> Vec<[f64; 2]> {
    let c = (side as f64 - 1.0) / 2.0;
    (0..side)
        .flat_map(|i| {
            (0..side).map(move |j| [(i as f64 - c) * spacing_m, (j as f64 - c) * spacing_m])
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pulse_table_is_the_pulse() {
        for rho in [1.0, 0.8, 0.37] {
            let m = ArrayModel {
                elements_m: vec![[0.0, 0.0]],
                wavelength_m: 0.2,
                rho,
            };
            let table = m.pulse_table(200);
            let mut out = vec![0.0; 200];
            for delay in [-0.5, 0.0, 3.0, 17.25, 101.999, 199.4] {
                table.fill(delay, &mut out);
                for (k, p) in out.iter().enumerate() {
                    let want = m.pulse(k as f64 - delay);
                    assert!(
                        (p - want).abs() < 1e-11,
                        "rho {rho} delay {delay} k {k}: {p} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn the_pulse_derivative_is_the_slope_of_the_pulse() {
        let m = ArrayModel {
            elements_m: vec![[0.0, 0.0]],
            wavelength_m: 0.2,
            rho: 0.8,
        };
        for t in [-3.3, -0.7, 0.2, 1.0, 2.5] {
            let h = 1e-6;
            let numeric = (m.pulse(t + h) - m.pulse(t - h)) / (2.0 * h);
            assert!((numeric - m.pulse_derivative(t)).abs() < 1e-6, "{t}");
        }
    }

    #[test]
    fn the_steering_derivative_is_the_slope_of_the_steering_vector() {
        let m = ArrayModel {
            elements_m: uniform_circular(8, 0.1),
            wavelength_m: 0.2,
            rho: 1.0,
        };
        let h = 1e-6;
        let (a, b) = (m.steering(0.4 + h), m.steering(0.4 - h));
        for (i, d) in m.steering_derivative(0.4).iter().enumerate() {
            assert!(((a[i] - b[i]) / (2.0 * h) - d).norm() < 1e-6);
        }
    }
}

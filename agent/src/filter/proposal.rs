//! The measurement-informed proposal of the user particles (the "optimal" proposal of
//! FastSLAM 2.0, Montemerlo et al. 2003, in the form of Doucet et al. 2000 §II.D): each particle
//! draws its motion noise from the Gaussian that linearizes `p(n | z, pose, map)` instead of
//! from the motion model `p(n)`, and carries the importance ratio `p(n) / q(n)` in its weight.
//!
//! Why: sampling from the motion model alone and weighting by sharp range and angle
//! likelihoods keeps only the few particles that happened to move right. After a few such
//! snapshots one ancestor's track — and the transmitters it mapped — is all that is left, and
//! every later error of that map turns into a track error nobody can correct (the degeneracy
//! that makes FastSLAM 1.0 inconsistent, Bailey et al. 2006). Drawing the noise where the
//! detections of the particle's own transmitters put it keeps the weights even.
//!
//! The noise is `n = (n_h, n_v)`: the heading noise of the step and the speed's deviation from
//! the measured (or previous) speed. Every detection of a transmitter the particle has
//! mapped is linearized at `n = 0` around the component of the transmitter's mixture that
//! explains it best, with that component's covariance added to the sensor's: `z ≈ ẑ + J·n`,
//! `S = H_tx·P·H_txᵀ + R`. Detections
//! outside the 99.9 % gate of that prediction (gross errors, wrong associations) do not
//! steer the draw. The weights stay exact whatever the linearization's quality: the
//! particle's weight gains `ln p(n) − ln q(n)` and then, as always, the likelihood of its
//! detections at the pose it moved to.

use super::config::FilterConfig;
use super::model::{Comp, Pose};
use super::srckf;
use super::update::Meas;
use echomap_shared::wrap_angle;
use nalgebra::{Matrix2, Matrix3, RowVector3, Vector2, Vector3};
use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// χ² quantiles 0.999 for one and two degrees of freedom: the gate of a detection that steers
/// the proposal.
const GATE_1: f64 = 10.83;
const GATE_2: f64 = 13.82;

/// The motion of one step as a function of its noise: `pose(n)` and `∂pose/∂n` at n = 0.
pub(super) struct Step {
    pub(super) from: Pose,
    /// heading change the gyro reports (rad)
    pub(super) turn: f64,
    /// speed before the noise (m/s): the measured speed or the particle's last
    pub(super) speed: f64,
    /// the speed is not measured: it is a random walk and cannot go negative
    pub(super) clamp: bool,
    pub(super) dt: f64,
    /// standard deviations of n_h (rad) and n_v (m/s)
    pub(super) sigma: (f64, f64),
}

impl Step {
    pub(super) fn new(
        cfg: &FilterConfig,
        from: &Pose,
        gyro: f64,
        speed: Option<f64>,
        dt: f64,
    ) -> Self {
        let var_h = cfg.heading_step_variance(gyro, dt);
        let (speed, clamp, sigma_v) = match speed {
            Some(v) => (v, false, cfg.speed_measurement_std_mps),
            None => (from.speed, true, cfg.speed_noise_mps_per_sqrt_s * dt.sqrt()),
        };
        Step {
            from: *from,
            turn: gyro * dt,
            speed,
            clamp,
            dt,
            sigma: (var_h.sqrt(), sigma_v),
        }
    }

    /// The pose after the step with noise `n` (the motion model of `Particle::predict`).
    pub(super) fn pose(&self, n: &Vector2<f64>) -> Pose {
        let speed = self.speed + n.y;
        let speed = if self.clamp { speed.max(0.0) } else { speed };
        let dh = wrap_angle(self.turn + n.x);
        let h_mid = self.from.heading + 0.5 * dh;
        Pose {
            x: self.from.x + speed * self.dt * h_mid.cos(),
            y: self.from.y + speed * self.dt * h_mid.sin(),
            heading: wrap_angle(self.from.heading + dh),
            speed,
        }
    }

    /// ∂(x, y, heading)/∂(n_h, n_v) at n = 0.
    fn jacobian(&self) -> nalgebra::Matrix3x2<f64> {
        let h_mid = self.from.heading + 0.5 * wrap_angle(self.turn);
        let (s, c) = h_mid.sin_cos();
        let v = self.speed.max(0.0) * self.dt;
        nalgebra::Matrix3x2::new(
            -0.5 * v * s,
            self.dt * c,
            0.5 * v * c,
            self.dt * s,
            1.0,
            0.0,
        )
    }

    /// ln of the motion model's density of `n` (Gaussian; the von Mises heading noise is
    /// normal to within 1/κ at the steps' concentrations).
    fn ln_prior(&self, n: &Vector2<f64>) -> f64 {
        let (sh, sv) = self.sigma;
        -0.5 * ((n.x / sh).powi(2) + (n.y / sv).powi(2))
            - (sh * sv).ln()
            - (2.0 * std::f64::consts::PI).ln()
    }
}

/// A linearized detection: the innovation `z − ẑ`, `J = ∂z/∂n` (rows: distance, angle), the
/// innovation's covariance `S` without the motion noise, and the measurement's dimension
/// (1 without an angle: its row is zero, with unit variance).
struct Linearized {
    nu: Vector2<f64>,
    j: Matrix2<f64>,
    s: Matrix2<f64>,
    dim: usize,
}

/// The linearized detection `z ≈ ẑ + J·n` of a transmitter with mean `m` and covariance `p`
/// seen from `pose`: its innovation `z − ẑ`, `J` (rows: distance, angle) and `S`.
fn linearize(
    m: &Meas,
    pose: &Pose,
    jac_pose: &nalgebra::Matrix3x2<f64>,
    mean: &Vector3<f64>,
    p: &Matrix3<f64>,
) -> Option<Linearized> {
    let (dx, dy) = (mean.x - pose.x, mean.y - pose.y);
    let r2 = dx * dx + dy * dy;
    if r2 < 1e-6 {
        return None;
    }
    let r = r2.sqrt();
    // rows over the pose (x, y, heading) and over the transmitter (x, y, b)
    let hd_pose = RowVector3::new(-dx / r, -dy / r, 0.0);
    let hd_tx = RowVector3::new(dx / r, dy / r, 1.0);
    let (sd, sa) = m.sigmas();
    match m.aoa() {
        Some(aoa) => {
            let ha_pose = RowVector3::new(dy / r2, -dx / r2, -1.0);
            let ha_tx = RowVector3::new(-dy / r2, dx / r2, 0.0);
            let nu = Vector2::new(
                m.d() - (r + mean.z),
                wrap_angle(aoa - (dy.atan2(dx) - pose.heading)),
            );
            let j_d = hd_pose * jac_pose;
            let j_a = ha_pose * jac_pose;
            let j = Matrix2::new(j_d[0], j_d[1], j_a[0], j_a[1]);
            let h_tx = nalgebra::Matrix2x3::from_rows(&[hd_tx, ha_tx]);
            let s = h_tx * p * h_tx.transpose() + Matrix2::new(sd * sd, 0.0, 0.0, sa * sa);
            Some(Linearized { nu, j, s, dim: 2 })
        }
        None => {
            let nu = Vector2::new(m.d() - (r + mean.z), 0.0);
            let j_d = hd_pose * jac_pose;
            let j = Matrix2::new(j_d[0], j_d[1], 0.0, 0.0);
            let s_d = (hd_tx * p * hd_tx.transpose())[0] + sd * sd;
            // the unused angle row carries unit variance and a zero innovation
            Some(Linearized {
                nu,
                j,
                s: Matrix2::new(s_d, 0.0, 0.0, 1.0),
                dim: 1,
            })
        }
    }
}

/// The detection linearized at the component of the transmitter's mixture that explains it
/// best — the largest `w_c·N(ν_c; 0, S_c + J·Q·Jᵀ)` — with its squared Mahalanobis distance
/// `νᵀ(S_c + J·Q·Jᵀ)⁻¹ν`, which the caller gates on. A young transmitter's components lie
/// along the ray it was first seen on, from the receiver out to the measured distance; their
/// moment-matched collapse sits halfway, where the angle's sensitivity to the receiver's
/// motion is not any component's, and a draw steered by it puts the particles where no
/// component would: the importance ratios then spread, and with them the weights.
fn best_component(
    m: &Meas,
    nominal: &Pose,
    jac_pose: &nalgebra::Matrix3x2<f64>,
    q: &Matrix2<f64>,
    comps: &[Comp],
) -> Option<(Linearized, f64)> {
    let mut best: Option<(f64, Linearized, f64)> = None;
    for c in comps.iter().filter(|c| c.weight > 0.0) {
        let Some(l) = linearize(m, nominal, jac_pose, &c.g.mean, &c.g.cov()) else {
            continue;
        };
        let s_full = l.s + l.j * q * l.j.transpose();
        let Some(chol) = srckf::SmallCholesky::new(&s_full) else {
            continue;
        };
        let l_diag = chol.l();
        let d2 = l.nu.dot(&chol.solve(&l.nu));
        let score = c.weight.ln() - 0.5 * d2 - (l_diag[(0, 0)] * l_diag[(1, 1)]).ln();
        if best.as_ref().is_none_or(|(b, _, _)| score > *b) {
            best = Some((score, l, d2));
        }
    }
    best.map(|(_, l, d2)| (l, d2))
}

/// Draws the step's noise from the proposal informed by `detections` (the measurement and the
/// mixture of a transmitter the particle has mapped, per detection). Returns the pose and
/// `ln p(n) − ln q(n)`, or None when no detection informs the step (the caller then draws from
/// the motion model).
pub(super) fn propose<'a>(
    step: &Step,
    detections: impl Iterator<Item = (&'a Meas, &'a [Comp])>,
    rng: &mut ChaCha8Rng,
) -> Option<(Pose, f64)> {
    let (sh, sv) = step.sigma;
    if !(sh > 0.0 && sv > 0.0 && sh.is_finite() && sv.is_finite()) {
        return None;
    }
    let q = Matrix2::new(sh * sh, 0.0, 0.0, sv * sv);
    let nominal = step.pose(&Vector2::zeros());
    let jac_pose = step.jacobian();
    let mut info = Matrix2::new(1.0 / (sh * sh), 0.0, 0.0, 1.0 / (sv * sv));
    let mut eta = Vector2::zeros();
    let mut used = 0;
    for (m, comps) in detections {
        let lin = best_component(m, &nominal, &jac_pose, &q, comps);
        let Some((Linearized { nu, j, s, dim }, d2)) = lin else {
            continue;
        };
        // the gate on the prediction's full spread, motion noise included
        let gate = if dim == 2 { GATE_2 } else { GATE_1 };
        if d2 > gate {
            continue;
        }
        let Some(s_inv) = s.try_inverse() else {
            continue;
        };
        // a Student-t detection in its tails steers the draw with the weight its law gives it
        let (dof, m_dim) = m.dof_and_dim();
        let s_inv = s_inv / srckf::student_t_noise_scale(d2, m_dim, dof);
        info += j.transpose() * s_inv * j;
        eta += j.transpose() * s_inv * nu;
        used += 1;
    }
    if used == 0 {
        return None;
    }
    let chol = info.cholesky()?;
    let mu = chol.solve(&eta);
    // n = μ + L⁻ᵀ·e with info = L·Lᵀ has covariance info⁻¹
    let e = Vector2::new(rng.sample(StandardNormal), rng.sample(StandardNormal));
    let l = chol.l();
    let dev = l.transpose().solve_upper_triangular(&e)?;
    let n = mu + dev;
    // ln q(n) = ln N(n; μ, info⁻¹) = −½‖e‖² + ln|L| − ln 2π
    let ln_q = -0.5 * e.norm_squared() + l[(0, 0)].ln() + l[(1, 1)].ln()
        - (2.0 * std::f64::consts::PI).ln();
    Some((step.pose(&n), step.ln_prior(&n) - ln_q))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::config::NoiseModel;
    use crate::filter::srckf::SqrtGaussian;
    use echomap_shared::log::Measurement;
    use rand::SeedableRng;

    /// One step from a known pose towards a mapped transmitter, and a detection made from a
    /// pose off the nominal step by `off`.
    struct Case {
        step: Step,
        comps: [Comp; 1],
        meas: Meas,
    }

    fn case(heading_noise: f64, speed_std: f64, off: Vector2<f64>) -> Case {
        let cfg = FilterConfig {
            heading_noise_rad_per_sqrt_s: heading_noise,
            speed_measurement_std_mps: speed_std,
            noise: NoiseModel {
                distance_floor_m: 0.05,
                aoa_floor_rad: 0.01,
                ..Default::default()
            },
            ..FilterConfig::default()
        };
        let from = Pose {
            x: 0.0,
            y: 0.0,
            heading: 0.3,
            speed: 1.0,
        };
        let step = Step::new(&cfg, &from, 0.2, Some(1.2), 0.5);
        let tx = SqrtGaussian::from_cov(
            Vector3::new(8.0, 5.0, 0.0),
            &Matrix3::from_diagonal(&Vector3::new(0.04, 0.04, 0.0004)),
        )
        .unwrap();
        let comps = [Comp { weight: 1.0, g: tx }];
        let truth = step.pose(&off);
        let z = crate::filter::model::h_toa_aoa(&truth, &comps[0].g.mean);
        let m = Measurement {
            track: 1,
            d: z.x,
            aoa: Some(z.y),
            snr_db: 20.0,
        };
        let meas = Meas::new(&m, &cfg, true);
        Case { step, comps, meas }
    }

    impl Case {
        fn ll(&self, p: &Pose) -> f64 {
            self.meas.log_likelihood(p, &self.comps[0].g).unwrap().0
        }

        /// Weighted mean position and ESS of `n` draws from the proposal (or, with `motion`,
        /// from the motion model), each weighted by its importance ratio times the likelihood.
        fn draw(&self, n: usize, motion: bool, seed: u64) -> (f64, f64, f64) {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let (sh, sv) = self.step.sigma;
            let (mut lw, mut poses) = (Vec::new(), Vec::new());
            for _ in 0..n {
                let (p, ratio) = if motion {
                    let e = Vector2::new(
                        sh * rng.sample::<f64, _>(StandardNormal),
                        sv * rng.sample::<f64, _>(StandardNormal),
                    );
                    (self.step.pose(&e), 0.0)
                } else {
                    let d = [(&self.meas, &self.comps[..])];
                    propose(&self.step, d.into_iter(), &mut rng).unwrap()
                };
                lw.push(ratio + self.ll(&p));
                poses.push(p);
            }
            let max = lw.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            let w: Vec<f64> = lw.iter().map(|l| (l - max).exp()).collect();
            let tot: f64 = w.iter().sum();
            let ess = tot * tot / w.iter().map(|x| x * x).sum::<f64>();
            let mx = poses.iter().zip(&w).map(|(p, w)| p.x * w).sum::<f64>() / tot;
            let my = poses.iter().zip(&w).map(|(p, w)| p.y * w).sum::<f64>() / tot;
            (mx, my, ess)
        }
    }

    /// Importance sampling with the proposal reproduces the exact posterior of the step: the
    /// weighted mean of the drawn poses equals the mean a dense grid over the noise gives,
    /// with nearly even weights. With no detection nothing is proposed.
    #[test]
    fn weighted_draws_match_the_posterior_of_the_step() {
        let c = case(0.05, 0.2, Vector2::new(0.03, 0.1));
        let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
        let (sh, sv) = c.step.sigma;
        for i in -120..=120 {
            for k in -120..=120 {
                let n = Vector2::new(i as f64 * sh / 20.0, k as f64 * sv / 20.0);
                let p = c.step.pose(&n);
                let w = (c.step.ln_prior(&n) + c.ll(&p)).exp();
                sw += w;
                sx += w * p.x;
                sy += w * p.y;
            }
        }
        let (gx, gy) = (sx / sw, sy / sw);
        let (mx, my, ess) = c.draw(4000, false, 3);
        assert!(
            (mx - gx).abs() < 2e-3 && (my - gy).abs() < 2e-3,
            "proposal {mx} {my} grid {gx} {gy}"
        );
        assert!(ess > 3000.0, "ess {ess}");
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        assert!(propose(&c.step, std::iter::empty(), &mut rng).is_none());
    }

    /// Where the detection is much sharper than the motion noise, drawing from the motion
    /// model leaves few particles with weight; the proposal keeps most of them, and both
    /// estimate the same position.
    #[test]
    fn the_proposal_keeps_the_weights_even_where_the_motion_model_cannot() {
        let c = case(0.3, 0.6, Vector2::new(0.2, 0.4));
        let (mx, my, ess) = c.draw(4000, false, 5);
        let (ox, oy, ess0) = c.draw(200_000, true, 6);
        let (share, share0) = (ess / 4000.0, ess0 / 200_000.0);
        assert!(
            share > 0.5 && share > 5.0 * share0,
            "effective share of the particles: proposal {share}, motion model {share0}"
        );
        assert!(
            (mx - ox).abs() < 0.01 && (my - oy).abs() < 0.01,
            "proposal ({mx}, {my}) against the motion model's ({ox}, {oy})"
        );
    }
}

//! The measurement update of one transmitter's Gaussian mixture: every component by the
//! square-root cubature Kalman filter (Gentner et al. 2016 eq. 45–46), pruning and merging
//! of components (§4.3), and the product of two mixtures that fuses a prior-map transmitter
//! into an own one.

use super::config::FilterConfig;
use super::model::{Comp, Pose, residual_toa, residual_toa_aoa, toa_aoa_images, toa_images};
use super::srckf::{self, SqrtGaussian};
use echomap_shared::log::Measurement;
use echomap_shared::mixture::{self, Component};
use nalgebra::{Matrix1, Matrix2, Matrix3, Vector1, Vector2, Vector3};

/// Per-measurement noise factor and the measurement as a vector.
pub(super) enum Meas {
    ToaAoa {
        z: Vector2<f64>,
        r_sqrt: Matrix2<f64>,
        /// degrees of freedom of the Student-t error law (0: Gaussian)
        dof: f64,
    },
    Toa {
        z: Vector1<f64>,
        r_sqrt: Matrix1<f64>,
        dof: f64,
    },
}

impl Meas {
    pub(super) fn new(m: &Measurement, cfg: &FilterConfig, aoa: bool) -> Self {
        let (sd, sa) = cfg.noise.std(m.snr_db);
        let dof = cfg.noise_dof;
        match (aoa, m.aoa) {
            (true, Some(a)) => Meas::ToaAoa {
                z: Vector2::new(m.d, a),
                r_sqrt: Matrix2::new(sd, 0.0, 0.0, sa),
                dof,
            },
            _ => Meas::Toa {
                z: Vector1::new(m.d),
                r_sqrt: Matrix1::new(sd),
                dof,
            },
        }
    }

    /// Degrees of freedom of the error law (0: Gaussian) and the measurement's dimension.
    pub(super) fn dof_and_dim(&self) -> (f64, usize) {
        match self {
            Meas::ToaAoa { dof, .. } => (*dof, 2),
            Meas::Toa { dof, .. } => (*dof, 1),
        }
    }

    pub(super) fn sigmas(&self) -> (f64, f64) {
        match self {
            Meas::ToaAoa { r_sqrt, .. } => (r_sqrt[(0, 0)], r_sqrt[(1, 1)]),
            Meas::Toa { r_sqrt, .. } => (r_sqrt[(0, 0)], std::f64::consts::PI),
        }
    }

    /// Updates one component; returns the posterior and the log-likelihood of the detection
    /// under the error law: ln N(z; ẑ, P_zz), or with Student-t errors the t density of the
    /// same scale. A Student-t detection far out in its tails updates the component with its
    /// noise widened by [`srckf::student_t_noise_scale`] (the t law's own weight for it), so
    /// that one wild detection pulls the transmitter as little as it weighs.
    pub(super) fn update(&self, pose: &Pose, g: &SqrtGaussian) -> Option<srckf::Updated> {
        match self {
            Meas::ToaAoa { z, r_sqrt, dof } => {
                let p = srckf::predict_images(
                    g,
                    |pts| toa_aoa_images(pose, pts),
                    residual_toa_aoa,
                    &(r_sqrt * r_sqrt.transpose()),
                );
                robust_update(g, z, r_sqrt, *dof, &p, residual_toa_aoa)
            }
            Meas::Toa { z, r_sqrt, dof } => {
                let p = srckf::predict_images(
                    g,
                    |pts| toa_images(pose, pts),
                    residual_toa,
                    &(r_sqrt * r_sqrt.transpose()),
                );
                robust_update(g, z, r_sqrt, *dof, &p, residual_toa)
            }
        }
    }

    /// `(log-likelihood under the error law, squared Mahalanobis distance of the innovation
    /// under P_zz)` without updating (for association likelihoods and gating).
    pub(super) fn log_likelihood(&self, pose: &Pose, g: &SqrtGaussian) -> Option<(f64, f64)> {
        let (ll, d2) = self.gaussian_log_likelihood(pose, g)?;
        let (dof, dim) = self.dof_and_dim();
        Some((srckf::student_t_log_density(ll, d2, dim, dof), d2))
    }

    fn gaussian_log_likelihood(&self, pose: &Pose, g: &SqrtGaussian) -> Option<(f64, f64)> {
        match self {
            Meas::ToaAoa { z, r_sqrt, .. } => {
                let p = srckf::predict_images(
                    g,
                    |pts| toa_aoa_images(pose, pts),
                    residual_toa_aoa,
                    &(r_sqrt * r_sqrt.transpose()),
                );
                srckf::log_normal_and_mahalanobis(&residual_toa_aoa(z, &p.z_hat), &p.pzz)
            }
            Meas::Toa { z, r_sqrt, .. } => {
                let p = srckf::predict_images(
                    g,
                    |pts| toa_images(pose, pts),
                    residual_toa,
                    &(r_sqrt * r_sqrt.transpose()),
                );
                srckf::log_normal_and_mahalanobis(&residual_toa(z, &p.z_hat), &p.pzz)
            }
        }
    }

    pub(super) fn d(&self) -> f64 {
        match self {
            Meas::ToaAoa { z, .. } => z.x,
            Meas::Toa { z, .. } => z.x,
        }
    }

    pub(super) fn aoa(&self) -> Option<f64> {
        match self {
            Meas::ToaAoa { z, .. } => Some(z.y),
            Meas::Toa { .. } => None,
        }
    }
}

/// The update of a component from its prediction `p` under the noise `r_sqrt`, with a
/// Student-t law of `dof` degrees of freedom (0: Gaussian): the t density of the innovation,
/// and for a detection in the tails the update repeated from the same cubature points with
/// the noise widened by [`srckf::student_t_noise_scale`].
fn robust_update<const M: usize>(
    g: &SqrtGaussian,
    z: &nalgebra::SVector<f64, M>,
    r_sqrt: &nalgebra::SMatrix<f64, M, M>,
    dof: f64,
    p: &srckf::Predicted<M>,
    residual: impl Fn(
        &nalgebra::SVector<f64, M>,
        &nalgebra::SVector<f64, M>,
    ) -> nalgebra::SVector<f64, M>
    + Copy,
) -> Option<srckf::Updated> {
    let u = srckf::update_predicted(g, z, r_sqrt, p, residual)?;
    if dof <= 0.0 {
        return Some(u);
    }
    let d2 = u.d2;
    let log_likelihood = srckf::student_t_log_density(u.log_likelihood, d2, M, dof);
    let scale = srckf::student_t_noise_scale(d2, M, dof);
    let mut out = if scale > 1.0 {
        let wide = r_sqrt * scale.sqrt();
        srckf::update_predicted(g, z, &wide, &p.with_noise(&wide), residual)?
    } else {
        u
    };
    out.log_likelihood = log_likelihood;
    out.d2 = d2;
    Some(out)
}

pub fn log_sum_exp(v: impl Iterator<Item = f64> + Clone) -> f64 {
    let max = v.clone().fold(f64::NEG_INFINITY, f64::max);
    if max == f64::NEG_INFINITY {
        return max;
    }
    max + v.map(|x| (x - max).exp()).sum::<f64>().ln()
}

/// Updates every component of a mixture with one measurement (eq. 46) and returns the
/// log marginal likelihood ln Σ_c w_c N(z; ẑ_c, P_zz,c) (the factor of eq. 45). Gross errors
/// are decided once per detection over the particle population (`Filter::weigh_detections`).
pub(super) fn update_mixture(
    comps: &mut Vec<Comp>,
    meas: &Meas,
    pose: &Pose,
    cfg: &FilterConfig,
    merge_now: bool,
) -> f64 {
    // In place: each component's posterior replaces its prior; its log-likelihood goes to
    // `lls` (on the stack for up to 32 components; NaN marks a numerically degenerate
    // update, dropped below).
    let mut max_ll = f64::NEG_INFINITY;
    let mut lls = [0.0f64; 32];
    let small = comps.len() <= lls.len();
    let mut big: Vec<f64> = Vec::new();
    for (k, c) in comps.iter_mut().enumerate() {
        let ll = match meas.update(pose, &c.g) {
            Some(u) => {
                c.g = u.posterior;
                u.log_likelihood
            }
            None => f64::NAN,
        };
        if ll > max_ll {
            max_ll = ll;
        }
        if small {
            lls[k] = ll;
        } else {
            big.push(ll);
        }
    }
    if !max_ll.is_finite() {
        // Numerically degenerate (every update failed): the particle gets no support.
        return -1e3;
    }
    let lls = if small { &lls[..comps.len()] } else { &big[..] };
    // w_c ∝ w_c·N(z; ẑ_c, P_zz,c) (eq. 46) with one exp per component and one ln per
    // mixture: Σ_c w_c·exp(ll_c − max) is the marginal likelihood scaled by exp(−max)
    let mut sum = 0.0;
    for (c, ll) in comps.iter_mut().zip(lls) {
        c.weight = if ll.is_nan() {
            0.0
        } else {
            c.weight * (ll - max_ll).exp()
        };
        sum += c.weight;
    }
    // the best component has weight w·exp(0) > 0, so something is kept and sum > 0
    comps.retain(|c| c.weight > 0.0);
    for c in comps.iter_mut() {
        c.weight /= sum;
    }
    tidy(comps, cfg, merge_now);
    max_ll + sum.ln()
}

/// Pruning (ρ), merging of close components and the per-transmitter cap (Gentner et al. 2016 §4.3).
pub(super) fn tidy(comps: &mut Vec<Comp>, cfg: &FilterConfig, merge_now: bool) {
    if comps.len() > 1 {
        let max_w = comps.iter().map(|c| c.weight).fold(0.0, f64::max);
        comps.retain(|c| c.weight >= cfg.prune_weight || c.weight == max_w);
        let total: f64 = comps.iter().map(|c| c.weight).sum();
        for c in comps.iter_mut() {
            c.weight /= total;
        }
    }
    let cap = if merge_now {
        1.max(close_cluster_count(comps))
    } else {
        usize::MAX
    };
    let cap = cap.min(cfg.max_components);
    if comps.len() > cap {
        let as_components: Vec<Component> = comps
            .iter()
            .map(|c| Component::new(c.weight, c.g.mean, c.g.cov()))
            .collect();
        let reduced = mixture::reduce(&as_components, cap);
        *comps = reduced
            .into_iter()
            .filter_map(|c| {
                SqrtGaussian::from_cov(c.mean, &c.cov).map(|g| Comp {
                    weight: c.weight,
                    g,
                })
            })
            .collect();
    }
}

/// Number of groups of components whose means lie within Mahalanobis distance 1 of each
/// other — merging down to this count removes duplicates that converged together.
pub(super) fn close_cluster_count(comps: &[Comp]) -> usize {
    if comps.len() < 2 {
        return comps.len();
    }
    let mut leaders: Vec<usize> = Vec::new();
    for (i, c) in comps.iter().enumerate() {
        let close = leaders.iter().any(|&l| {
            let p = c.g.cov() + comps[l].g.cov();
            let d = c.g.mean - comps[l].g.mean;
            p.cholesky()
                .map(|ch| d.dot(&ch.solve(&d)) < 1.0)
                .unwrap_or(false)
        });
        if !close {
            leaders.push(i);
        }
    }
    leaders.len()
}

/// The normalised product of two Gaussian mixtures over the same state, its log evidence
/// `ln Σ_ij w_i·w_j·N(m_j; m_i, P_i + P_j)`, and the floor of that evidence: the largest
/// `ln w_i·w_j − ½·ln|2π(P_i + P_j)|` less `gate_chi2 / 2`. None when no pair of components
/// gives a usable product.
pub(super) fn product_mixture(
    a: &[Comp],
    b: &[Comp],
    gate_chi2: f64,
) -> Option<(Vec<Comp>, f64, f64)> {
    let ln_2pi = (2.0 * std::f64::consts::PI).ln();
    let mut out: Vec<(f64, Vector3<f64>, Matrix3<f64>)> = Vec::new();
    let mut floor = f64::NEG_INFINITY;
    for ca in a {
        let pa = ca.g.cov();
        for cb in b {
            let s = pa + cb.g.cov();
            let Some(ch) = s.cholesky() else {
                continue;
            };
            let d = cb.g.mean - ca.g.mean;
            let ln_det = 2.0 * ch.l().diagonal().iter().map(|x| x.ln()).sum::<f64>();
            let ln_norm = ca.weight.ln() + cb.weight.ln() - 0.5 * (3.0 * ln_2pi + ln_det);
            floor = floor.max(ln_norm - 0.5 * gate_chi2);
            // K = P_a S⁻¹: mean m_a + K d, covariance P_a − K P_a
            let k = ch.solve(&pa).transpose();
            let mean = ca.g.mean + k * d;
            let cov = pa - k * pa;
            let cov = (cov + cov.transpose()) * 0.5;
            out.push((ln_norm - 0.5 * d.dot(&ch.solve(&d)), mean, cov));
        }
    }
    let total = log_sum_exp(out.iter().map(|o| o.0));
    if !total.is_finite() {
        return None;
    }
    let comps: Vec<Comp> = out
        .into_iter()
        .filter_map(|(l, mean, cov)| {
            SqrtGaussian::from_cov(mean, &cov).map(|g| Comp {
                weight: (l - total).exp(),
                g,
            })
        })
        .filter(|c| c.weight > 0.0)
        .collect();
    let sum: f64 = comps.iter().map(|c| c.weight).sum();
    if comps.is_empty() || sum <= 0.0 {
        return None;
    }
    let comps = comps
        .into_iter()
        .map(|c| Comp {
            weight: c.weight / sum,
            g: c.g,
        })
        .collect();
    Some((comps, total, floor))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::config::NoiseModel;

    fn setup(dof: f64) -> (FilterConfig, Pose, SqrtGaussian) {
        let cfg = FilterConfig {
            noise: NoiseModel {
                distance_floor_m: 0.1,
                aoa_floor_rad: 0.02,
                ..Default::default()
            },
            noise_dof: dof,
            ..FilterConfig::default()
        };
        let pose = Pose {
            x: 0.0,
            y: 0.0,
            heading: 0.0,
            speed: 1.0,
        };
        let g = SqrtGaussian::from_cov(
            Vector3::new(10.0, 0.0, 0.0),
            &Matrix3::from_diagonal(&Vector3::new(0.01, 0.01, 0.0025)),
        )
        .unwrap();
        (cfg, pose, g)
    }

    fn detection(d: f64, aoa: f64) -> Measurement {
        Measurement {
            track: 1,
            d,
            aoa: Some(aoa),
            snr_db: 30.0,
        }
    }

    #[test]
    fn a_student_t_law_lets_a_wild_detection_pull_less_and_cost_less() {
        let (gauss, pose, g) = setup(0.0);
        let (heavy, ..) = setup(4.0);
        // an established transmitter (0.1 m), a detection 1 m long and 0.1 rad off (about 7
        // and 4 σ of the prediction)
        let z = detection(11.0, 0.1);
        let a = Meas::new(&z, &gauss, true).update(&pose, &g).unwrap();
        let b = Meas::new(&z, &heavy, true).update(&pose, &g).unwrap();
        assert_eq!(
            a.d2, b.d2,
            "the distance is the prediction's, whatever the law"
        );
        let (moved_a, moved_b) = (
            (a.posterior.mean - g.mean).norm(),
            (b.posterior.mean - g.mean).norm(),
        );
        assert!(
            moved_b < 0.3 * moved_a,
            "moved {moved_b} with t, {moved_a} Gaussian"
        );
        assert!(b.log_likelihood > a.log_likelihood + 20.0);
        // the widened update still shrinks the component less than the Gaussian one does
        assert!(b.posterior.cov().determinant() > a.posterior.cov().determinant());
        // a detection where it is predicted is weighed and used almost alike
        let z = detection(10.05, 0.01);
        let a = Meas::new(&z, &gauss, true).update(&pose, &g).unwrap();
        let b = Meas::new(&z, &heavy, true).update(&pose, &g).unwrap();
        assert_eq!(a.posterior.mean, b.posterior.mean);
        assert!((a.log_likelihood - b.log_likelihood).abs() < 0.5);
        // log_likelihood without an update agrees with the update's
        let (ll, d2) = Meas::new(&z, &heavy, true)
            .log_likelihood(&pose, &g)
            .unwrap();
        assert!((ll - b.log_likelihood).abs() < 1e-9 && (d2 - b.d2).abs() < 1e-9);
    }
}

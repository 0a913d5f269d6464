//! Square-root cubature Kalman filter update for one Gaussian component of a transmitter
//! state `x = [x, y, b]` (Gentner et al. 2016 §3, §6 and Appendix A; Arasaratnam & Haykin 2009).
//!
//! Third-degree spherical-radial cubature with κ = 0: 2n = 6 points `m ± √n·S·eⱼ`, weights
//! 1/(2n). The covariance is carried as a lower-triangular factor `S` (P = S·Sᵀ) and updated
//! by an LQ ("tria") step on `[X − K·Z, K·S_R]`, which equals the Joseph form
//! `P − K·P_zz·Kᵀ` and stays positive definite in floating point.
//!
//! The component's marginal likelihood is `N(z; ẑ, P_zz)` with `P_zz` formed from the
//! cubature points plus R (DESIGN.md "Component likelihood"): unlike averaging the likelihood
//! over the points (Gentner et al. 2016 eq. 43), it stays informative for wide, freshly initialized
//! components. Cost: 6 measurement evaluations and O(n²·(2n+m)) flops per update.

use nalgebra::{Matrix3, SMatrix, SVector, Vector3};

/// Number of cubature points for the 3-dimensional transmitter state.
pub const POINTS: usize = 6;

/// A Gaussian in square-root form.
#[derive(Debug, Clone, PartialEq)]
pub struct SqrtGaussian {
    pub mean: Vector3<f64>,
    /// lower-triangular factor, P = S·Sᵀ
    pub sqrt: Matrix3<f64>,
}

impl SqrtGaussian {
    pub fn from_cov(mean: Vector3<f64>, cov: &Matrix3<f64>) -> Option<Self> {
        cov.cholesky().map(|c| SqrtGaussian { mean, sqrt: c.l() })
    }

    /// `P = S·Sᵀ` from the lower-triangular factor: the products with its zero upper part
    /// are left out, the rest summed in the order of the full product (same bits).
    #[inline]
    pub fn cov(&self) -> Matrix3<f64> {
        let s = &self.sqrt;
        let p00 = s[(0, 0)] * s[(0, 0)];
        let p10 = s[(1, 0)] * s[(0, 0)];
        let p20 = s[(2, 0)] * s[(0, 0)];
        let p11 = s[(1, 0)] * s[(1, 0)] + s[(1, 1)] * s[(1, 1)];
        let p21 = s[(2, 0)] * s[(1, 0)] + s[(2, 1)] * s[(1, 1)];
        let p22 = s[(2, 0)] * s[(2, 0)] + s[(2, 1)] * s[(2, 1)] + s[(2, 2)] * s[(2, 2)];
        Matrix3::new(p00, p10, p20, p10, p11, p21, p20, p21, p22)
    }

    /// The 6 cubature points.
    pub fn cubature_points(&self) -> [Vector3<f64>; POINTS] {
        let r = 3f64.sqrt();
        std::array::from_fn(|j| {
            let col = self.sqrt.column(j % 3) * r;
            if j < 3 {
                self.mean + col
            } else {
                self.mean - col
            }
        })
    }
}

/// Lower-triangular L (3×3) with L·Lᵀ = A·Aᵀ for a 3×C matrix A (LQ by Givens rotations).
pub fn tria<const C: usize>(a: &SMatrix<f64, 3, C>) -> Matrix3<f64> {
    let mut m = *a;
    for i in 0..3 {
        for j in (i + 1)..C {
            let (x, y) = (m[(i, i)], m[(i, j)]);
            if y == 0.0 {
                continue;
            }
            let r = (x * x + y * y).sqrt();
            let (c, s) = (x / r, y / r);
            for row in i..3 {
                let (u, v) = (m[(row, i)], m[(row, j)]);
                m[(row, i)] = c * u + s * v;
                m[(row, j)] = -s * u + c * v;
            }
        }
        if m[(i, i)] < 0.0 {
            for row in i..3 {
                m[(row, i)] = -m[(row, i)];
            }
        }
    }
    Matrix3::from_fn(|r, c| if c <= r { m[(r, c)] } else { 0.0 })
}

/// Predicted measurement statistics of a component: ẑ, the centred measurement points and
/// the centred state points (both scaled by 1/√(2n)), and P_zz (including R).
#[derive(Debug)]
pub struct Predicted<const M: usize> {
    pub z_hat: SVector<f64, M>,
    pub z_dev: SMatrix<f64, M, POINTS>,
    pub x_dev: SMatrix<f64, 3, POINTS>,
    pub pzz: SMatrix<f64, M, M>,
}

impl<const M: usize> Predicted<M> {
    /// The same prediction with the noise factor `r_sqrt` in `P_zz` instead: the cubature
    /// points and their images do not depend on the noise, so a second update of one
    /// component with wider noise (the Student-t law's) costs no measurement evaluation.
    pub fn with_noise(&self, r_sqrt: &SMatrix<f64, M, M>) -> Self {
        Predicted {
            z_hat: self.z_hat,
            z_dev: self.z_dev,
            x_dev: self.x_dev,
            pzz: self.z_dev * self.z_dev.transpose() + r_sqrt * r_sqrt.transpose(),
        }
    }
}

/// Propagates the cubature points through `h`. `residual(a, b)` is `a − b` with angles
/// wrapped; it is used for every difference in measurement space.
pub fn predict<const M: usize>(
    g: &SqrtGaussian,
    h: impl Fn(&Vector3<f64>) -> SVector<f64, M>,
    residual: impl Fn(&SVector<f64, M>, &SVector<f64, M>) -> SVector<f64, M>,
    r: &SMatrix<f64, M, M>,
) -> Predicted<M> {
    predict_images(g, |pts| pts.map(|p| h(&p)), residual, r)
}

/// [`predict`] with the images of all cubature points from one call of `images`, for a
/// measurement function that can share work between the points (`model::toa_aoa_images`).
#[inline]
pub fn predict_images<const M: usize>(
    g: &SqrtGaussian,
    images: impl Fn(&[Vector3<f64>; POINTS]) -> [SVector<f64, M>; POINTS],
    residual: impl Fn(&SVector<f64, M>, &SVector<f64, M>) -> SVector<f64, M>,
    r: &SMatrix<f64, M, M>,
) -> Predicted<M> {
    let pts = g.cubature_points();
    let zs = images(&pts);
    // Mean of angles: average the residuals against the first point, then add back.
    let z0 = zs[0];
    let mean_res = zs
        .iter()
        .fold(SVector::<f64, M>::zeros(), |acc, z| acc + residual(z, &z0))
        / POINTS as f64;
    let z_hat = z0 + mean_res;
    let scale = 1.0 / (POINTS as f64).sqrt();
    let devs: [SVector<f64, M>; POINTS] = std::array::from_fn(|j| residual(&zs[j], &z_hat) * scale);
    let z_dev = SMatrix::<f64, M, POINTS>::from_fn(|i, j| devs[j][i]);
    let x_dev = SMatrix::<f64, 3, POINTS>::from_fn(|i, j| (pts[j][i] - g.mean[i]) * scale);
    let pzz = z_dev * z_dev.transpose() + r;
    Predicted {
        z_hat,
        z_dev,
        x_dev,
        pzz,
    }
}

/// Cholesky factor of a small symmetric positive definite matrix (the 1×1 and 2×2
/// innovation covariances of the hot loop), with the operations of nalgebra's `Cholesky` in
/// its order, so that every result is the same to the bit, without its general-size loops
/// over dynamic views (they cost more than the arithmetic at these sizes).
#[derive(Debug, Clone, Copy)]
pub struct SmallCholesky<const M: usize> {
    l: SMatrix<f64, M, M>,
}

impl<const M: usize> SmallCholesky<M> {
    /// None when `p` is not positive definite (a zero, negative or NaN pivot).
    #[inline]
    pub fn new(p: &SMatrix<f64, M, M>) -> Option<Self> {
        let mut m = *p;
        for j in 0..M {
            for k in 0..j {
                let factor = -m[(j, k)];
                for i in j..M {
                    m[(i, j)] += factor * m[(i, k)];
                }
            }
            let diag = m[(j, j)];
            // nalgebra refuses a zero pivot and takes `try_sqrt`, which refuses < 0 and NaN
            if diag <= 0.0 || diag.is_nan() {
                return None;
            }
            let denom = diag.sqrt();
            m[(j, j)] = denom;
            for i in (j + 1)..M {
                m[(i, j)] /= denom;
            }
        }
        for j in 1..M {
            for i in 0..j {
                m[(i, j)] = 0.0;
            }
        }
        Some(SmallCholesky { l: m })
    }

    /// The lower-triangular factor L (P = L·Lᵀ).
    #[inline]
    pub fn l(&self) -> SMatrix<f64, M, M> {
        self.l
    }

    /// `P⁻¹·b`: forward substitution with L, then back substitution with Lᵀ.
    #[inline]
    pub fn solve(&self, b: &SVector<f64, M>) -> SVector<f64, M> {
        let x = self.solve_sides::<1>(&std::array::from_fn(|i| [b[i]]));
        SVector::<f64, M>::from_fn(|i, _| x[i][0])
    }

    /// [`Self::solve`] for N right-hand sides at once, `b[i][c]` row i of side c: the same
    /// operations on each side (the same bits), laid out so that the divisions of the sides
    /// can go to the vector unit together.
    #[inline]
    pub fn solve_sides<const N: usize>(&self, b: &[[f64; N]; M]) -> [[f64; N]; M] {
        let l = &self.l;
        let mut x = *b;
        for i in 0..M {
            let d = l[(i, i)];
            let coeff: [f64; N] = std::array::from_fn(|c| x[i][c] / d);
            x[i] = coeff;
            for r in (i + 1)..M {
                let lr = l[(r, i)];
                for c in 0..N {
                    x[r][c] -= coeff[c] * lr;
                }
            }
        }
        for i in (0..M).rev() {
            // nalgebra's dot over the rows below starts from +0
            let mut dot = [0.0; N];
            for r in (i + 1)..M {
                let lr = l[(r, i)];
                for c in 0..N {
                    dot[c] += lr * x[r][c];
                }
            }
            let d = l[(i, i)];
            for c in 0..N {
                x[i][c] = (x[i][c] - dot[c]) / d;
            }
        }
        x
    }
}

/// Log of `N(res; 0, P)`; None when P is not positive definite.
pub fn log_normal<const M: usize>(res: &SVector<f64, M>, p: &SMatrix<f64, M, M>) -> Option<f64> {
    log_normal_and_mahalanobis(res, p).map(|x| x.0)
}

/// `(ln N(res; 0, P), resᵀP⁻¹res)`; None when P is not positive definite.
pub fn log_normal_and_mahalanobis<const M: usize>(
    res: &SVector<f64, M>,
    p: &SMatrix<f64, M, M>,
) -> Option<(f64, f64)> {
    let chol = SmallCholesky::new(p)?;
    let l = chol.l();
    let log_det: f64 = 2.0 * (0..M).map(|i| l[(i, i)].ln()).sum::<f64>();
    let d2 = res.dot(&chol.solve(res));
    Some((
        -0.5 * (d2 + log_det + M as f64 * (2.0 * std::f64::consts::PI).ln()),
        d2,
    ))
}

/// ln of the Student-t density with `dof` degrees of freedom and scale matrix P, in `m`
/// dimensions, of a residual whose Gaussian density under P is `ln_normal` and whose squared
/// Mahalanobis distance is `d2`; `dof` = 0 is the Gaussian itself (returns `ln_normal`).
///
/// `ln t = ln Γ((ν+m)/2) − ln Γ(ν/2) − (m/2)·ln(νπ) − ½·ln|P| − ((ν+m)/2)·ln(1 + d²/ν)`,
/// with `−½·ln|P|` recovered from the Gaussian's `ln N = −½·(d² + ln|P| + m·ln 2π)`.
pub fn student_t_log_density(ln_normal: f64, d2: f64, m: usize, dof: f64) -> f64 {
    if dof <= 0.0 {
        return ln_normal;
    }
    let mf = m as f64;
    let neg_half_log_det = ln_normal + 0.5 * d2 + 0.5 * mf * (2.0 * std::f64::consts::PI).ln();
    libm::lgamma(0.5 * (dof + mf))
        - libm::lgamma(0.5 * dof)
        - 0.5 * mf * (dof * std::f64::consts::PI).ln()
        + neg_half_log_det
        - 0.5 * (dof + mf) * (d2 / dof).ln_1p()
}

/// The factor by which a Student-t measurement with `dof` degrees of freedom widens its
/// noise for a detection at squared Mahalanobis distance `d2` in `m` dimensions: the inverse
/// of the expected precision weight `(ν + m)/(ν + d²)` of the t law as a Gaussian scale
/// mixture (one step of its EM), never below 1; 1 for a Gaussian (`dof` = 0).
pub fn student_t_noise_scale(d2: f64, m: usize, dof: f64) -> f64 {
    if dof <= 0.0 {
        return 1.0;
    }
    ((dof + d2) / (dof + m as f64)).max(1.0)
}

/// Result of a measurement update of one component.
#[derive(Debug, Clone)]
pub struct Updated {
    pub posterior: SqrtGaussian,
    /// ln N(z; ẑ, P_zz): the component's marginal likelihood
    pub log_likelihood: f64,
    /// the innovation's squared Mahalanobis distance `νᵀ·P_zz⁻¹·ν`
    pub d2: f64,
}

/// Square-root cubature measurement update with measurement `z` and noise factor `r_sqrt`
/// (R = r_sqrt·r_sqrtᵀ). None when P_zz is not positive definite (degenerate input).
pub fn update<const M: usize>(
    g: &SqrtGaussian,
    z: &SVector<f64, M>,
    r_sqrt: &SMatrix<f64, M, M>,
    h: impl Fn(&Vector3<f64>) -> SVector<f64, M>,
    residual: impl Fn(&SVector<f64, M>, &SVector<f64, M>) -> SVector<f64, M> + Copy,
) -> Option<Updated> {
    let r = r_sqrt * r_sqrt.transpose();
    let p = predict(g, h, residual, &r);
    update_predicted(g, z, r_sqrt, &p, residual)
}

/// [`update`] from the component's cubature prediction `p`, made with the noise `r_sqrt`
/// (see [`Predicted::with_noise`] for another noise on the same points).
pub fn update_predicted<const M: usize>(
    g: &SqrtGaussian,
    z: &SVector<f64, M>,
    r_sqrt: &SMatrix<f64, M, M>,
    p: &Predicted<M>,
    residual: impl Fn(&SVector<f64, M>, &SVector<f64, M>) -> SVector<f64, M>,
) -> Option<Updated> {
    let chol = SmallCholesky::new(&p.pzz)?;
    let innovation = residual(z, &p.z_hat);
    let pxz = p.x_dev * p.z_dev.transpose();
    // K = Pxz·Pzz⁻¹  ⇔  Kᵀ = Pzz⁻¹·Pxzᵀ, one row of K per side, and P_zz⁻¹·ν for the
    // likelihood as the fourth
    let sides: [[f64; 4]; M] =
        std::array::from_fn(|i| [pxz[(0, i)], pxz[(1, i)], pxz[(2, i)], innovation[i]]);
    let solved = chol.solve_sides(&sides);
    let k = SMatrix::<f64, 3, M>::from_fn(|row, c| solved[c][row]);
    let pzz_inv_nu = SVector::<f64, M>::from_fn(|i, _| solved[i][3]);
    let mean = g.mean + k * innovation;
    // P⁺ = P − K·P_zz·Kᵀ = S·Sᵀ − U·Uᵀ with U = K·L_zz: M rank-1 downdates of the factor S
    // (O(n²) each). Where a downdate would cancel badly (a direction the measurement
    // determines almost completely) the factor comes from tria([X − K·Z, K·S_R]) instead,
    // the Joseph form, which stays positive definite in floating point.
    let u = k * chol.l();
    let sqrt = match downdate(&g.sqrt, &u) {
        Some(s) => s,
        None => {
            let a = p.x_dev - k * p.z_dev;
            let b = k * r_sqrt;
            match M {
                1 => tria(&SMatrix::<f64, 3, 7>::from_fn(|i, j| {
                    if j < POINTS {
                        a[(i, j)]
                    } else {
                        b[(i, j - POINTS)]
                    }
                })),
                2 => tria(&SMatrix::<f64, 3, 8>::from_fn(|i, j| {
                    if j < POINTS {
                        a[(i, j)]
                    } else {
                        b[(i, j - POINTS)]
                    }
                })),
                _ => {
                    let p_new = a * a.transpose() + b * b.transpose();
                    p_new.cholesky()?.l()
                }
            }
        }
    };
    // ln N(ν; 0, P_zz) from the factor already computed
    let l = chol.l();
    let log_det: f64 = 2.0 * (0..M).map(|i| l[(i, i)]).product::<f64>().ln();
    let d2 = innovation.dot(&pzz_inv_nu);
    let log_likelihood = -0.5 * (d2 + log_det + M as f64 * (2.0 * std::f64::consts::PI).ln());
    Some(Updated {
        posterior: SqrtGaussian { mean, sqrt },
        log_likelihood,
        d2,
    })
}

/// Smallest ratio of a downdated diagonal element to the original (squared) that the
/// downdate accepts; below it the Joseph-form tria is used (cancellation would cost more
/// than 6 of the 16 digits).
const DOWNDATE_MIN_RATIO: f64 = 1e-6;

/// Lower-triangular L' with L'·L'ᵀ = L·Lᵀ − U·Uᵀ by successive rank-1 Cholesky downdates;
/// None where the result would not be safely positive definite.
fn downdate<const M: usize>(l: &Matrix3<f64>, u: &SMatrix<f64, 3, M>) -> Option<Matrix3<f64>> {
    let mut l = *l;
    for c in 0..M {
        let mut x = u.column(c).into_owned();
        for k in 0..3 {
            let lkk = l[(k, k)];
            let r2 = lkk * lkk - x[k] * x[k];
            if r2.is_nan() || r2 <= DOWNDATE_MIN_RATIO * lkk * lkk {
                return None;
            }
            let r = r2.sqrt();
            let (cos, sin) = (r / lkk, x[k] / lkk);
            let inv_cos = lkk / r;
            l[(k, k)] = r;
            for i in (k + 1)..3 {
                let lik = (l[(i, k)] - sin * x[i]) * inv_cos;
                x[i] = cos * x[i] - sin * lik;
                l[(i, k)] = lik;
            }
        }
    }
    Some(l)
}

/// The plain sigma-point average of the measurement likelihood (Gentner et al. 2016 eq. 43), kept to
/// show why it is not used: ln( (1/2n)·Σⱼ N(z; h(Xⱼ), R) ).
pub fn sigma_point_average_log_likelihood<const M: usize>(
    g: &SqrtGaussian,
    z: &SVector<f64, M>,
    r: &SMatrix<f64, M, M>,
    h: impl Fn(&Vector3<f64>) -> SVector<f64, M>,
    residual: impl Fn(&SVector<f64, M>, &SVector<f64, M>) -> SVector<f64, M>,
) -> f64 {
    let logs: Vec<f64> = g
        .cubature_points()
        .iter()
        .map(|x| log_normal(&residual(z, &h(x)), r).unwrap_or(f64::NEG_INFINITY))
        .collect();
    let max = logs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    if max == f64::NEG_INFINITY {
        return max;
    }
    max + (logs.iter().map(|l| (l - max).exp()).sum::<f64>() / POINTS as f64).ln()
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;
    use nalgebra::{Matrix2, Vector1, Vector2};

    fn plain(a: &SVector<f64, 1>, b: &SVector<f64, 1>) -> SVector<f64, 1> {
        a - b
    }

    #[test]
    fn tria_reproduces_the_product() {
        let a = SMatrix::<f64, 3, 8>::from_fn(|i, j| {
            ((i * 7 + j * 3) % 5) as f64 - 1.7 + 0.1 * j as f64
        });
        let l = tria(&a);
        assert_relative_eq!(l * l.transpose(), a * a.transpose(), epsilon = 1e-10);
        assert!(l[(0, 1)] == 0.0 && l[(0, 2)] == 0.0 && l[(1, 2)] == 0.0);
        assert!((0..3).all(|i| l[(i, i)] >= 0.0));
    }

    #[test]
    fn the_small_factorizations_give_nalgebras_bits() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut u = || rng.random::<f64>() * 4.0 - 2.0;
        for _ in 0..2000 {
            let a = nalgebra::Matrix2::new(u(), u(), u(), u());
            let p = a * a.transpose() + nalgebra::Matrix2::identity() * 1e-3;
            let b = Vector2::new(u(), u());
            let ours = SmallCholesky::new(&p).unwrap();
            let theirs = p.cholesky().unwrap();
            assert_eq!(ours.l(), theirs.l());
            assert_eq!(ours.solve(&b), theirs.solve(&b));
            let sides = nalgebra::Matrix2x3::new(u(), u(), u(), u(), u(), u());
            let at_once = ours.solve_sides(&std::array::from_fn(|i| {
                [sides[(i, 0)], sides[(i, 1)], sides[(i, 2)]]
            }));
            let one_by_one = theirs.solve(&sides);
            for i in 0..2 {
                for c in 0..3 {
                    assert_eq!(at_once[i][c], one_by_one[(i, c)]);
                }
            }
            let p1 = nalgebra::Matrix1::new(u().abs() + 1e-3);
            let b1 = Vector1::new(u());
            assert_eq!(
                SmallCholesky::new(&p1).unwrap().solve(&b1),
                p1.cholesky().unwrap().solve(&b1)
            );
            let s = Matrix3::new(
                u().abs(),
                0.0,
                0.0,
                u(),
                u().abs(),
                0.0,
                u(),
                u(),
                u().abs(),
            );
            let g = SqrtGaussian {
                mean: Vector3::zeros(),
                sqrt: s,
            };
            assert_eq!(g.cov(), s * s.transpose());
        }
        // refused exactly where nalgebra refuses
        for p in [
            Matrix2::new(0.0, 0.0, 0.0, 1.0),
            Matrix2::new(1.0, 2.0, 2.0, 1.0),
            Matrix2::new(f64::NAN, 0.0, 0.0, 1.0),
            Matrix2::new(-1.0, 0.0, 0.0, 1.0),
        ] {
            assert!(SmallCholesky::new(&p).is_none() && p.cholesky().is_none());
        }
    }

    #[test]
    fn downdate_reproduces_the_difference_or_declines() {
        let l = Matrix3::new(2.0, 0.0, 0.0, 0.5, 1.5, 0.0, -0.3, 0.2, 1.1);
        let u = SMatrix::<f64, 3, 2>::new(0.9, 0.1, 0.3, 0.7, -0.2, 0.4);
        let d = downdate(&l, &u).expect("positive definite difference");
        assert_relative_eq!(
            d * d.transpose(),
            l * l.transpose() - u * u.transpose(),
            epsilon = 1e-12
        );
        assert!(d[(0, 1)] == 0.0 && d[(0, 2)] == 0.0 && d[(1, 2)] == 0.0);
        // a downdate that removes (almost) all of a direction is declined, not returned
        // with a cancelled diagonal
        let all = SMatrix::<f64, 3, 1>::new(2.0, 0.5, -0.3);
        assert!(downdate(&l, &all).is_none());
    }

    #[test]
    fn linear_measurement_matches_the_kalman_filter() {
        // h(x) = x + y + b is linear: the cubature update must equal the Kalman update.
        let cov = Matrix3::new(2.0, 0.3, 0.1, 0.3, 1.0, -0.2, 0.1, -0.2, 0.5);
        let g = SqrtGaussian::from_cov(Vector3::new(1.0, 2.0, 0.5), &cov).unwrap();
        let hmat = nalgebra::RowVector3::new(1.0, 1.0, 1.0);
        let r: f64 = 0.25;
        let z = Vector1::new(4.2);
        let up = update(
            &g,
            &z,
            &SMatrix::<f64, 1, 1>::new(r.sqrt()),
            |x| Vector1::new(x.x + x.y + x.z),
            plain,
        )
        .unwrap();
        let s = (hmat * cov * hmat.transpose())[(0, 0)] + r;
        let k = cov * hmat.transpose() / s;
        let innov = z[0] - (hmat * g.mean)[(0, 0)];
        assert_relative_eq!(up.posterior.mean, g.mean + k * innov, epsilon = 1e-10);
        assert_relative_eq!(
            up.posterior.cov(),
            cov - k * s * k.transpose(),
            epsilon = 1e-10
        );
        let ll = -0.5 * (innov * innov / s + s.ln() + (2.0 * std::f64::consts::PI).ln());
        assert_relative_eq!(up.log_likelihood, ll, epsilon = 1e-10);
    }

    /// Range-bearing from a user at the origin with heading 0.
    fn h_range_bearing(x: &Vector3<f64>) -> Vector2<f64> {
        Vector2::new(x.x.hypot(x.y) + x.z, x.y.atan2(x.x))
    }

    fn res_angle(a: &Vector2<f64>, b: &Vector2<f64>) -> Vector2<f64> {
        Vector2::new(a.x - b.x, echomap_shared::wrap_angle(a.y - b.y))
    }

    #[test]
    fn wide_component_likelihood_is_informative_where_the_sigma_point_average_is_not() {
        // A freshly initialized, wide component (5 m std) and a measurement 3 m off its mean.
        // The marginal N(z; ẑ, P_zz) is a smooth, moderate likelihood; the average of
        // N(z; h(Xⱼ), R) over the six points is essentially zero (every point is many σ_R
        // away), so it would wipe out particles that are in fact consistent.
        let g = SqrtGaussian::from_cov(
            Vector3::new(20.0, 0.0, 0.0),
            &Matrix3::from_diagonal(&Vector3::new(25.0, 25.0, 1.0)),
        )
        .unwrap();
        let r = Matrix2::from_diagonal(&Vector2::new(0.1f64.powi(2), 0.02f64.powi(2)));
        let z = Vector2::new(23.0, 0.05);
        let up = update(
            &g,
            &z,
            &Matrix2::from_diagonal(&Vector2::new(0.1, 0.02)),
            h_range_bearing,
            res_angle,
        )
        .unwrap();
        let avg = sigma_point_average_log_likelihood(&g, &z, &r, h_range_bearing, res_angle);
        assert!(up.log_likelihood > -6.0, "marginal {}", up.log_likelihood);
        assert!(
            avg < up.log_likelihood - 50.0,
            "average {avg} vs marginal {}",
            up.log_likelihood
        );
        // And the marginal ranks hypotheses sensibly: a measurement far outside the component
        // is less likely than one inside it.
        let far = update(
            &g,
            &Vector2::new(60.0, 0.05),
            &Matrix2::from_diagonal(&Vector2::new(0.1, 0.02)),
            h_range_bearing,
            res_angle,
        )
        .unwrap();
        assert!(far.log_likelihood < up.log_likelihood - 10.0);
    }

    #[test]
    fn angles_near_pi_are_wrapped() {
        // Transmitter straight behind the user: bearing ±π. Measurement on the other side of
        // the cut must not produce a 2π innovation.
        let g = SqrtGaussian::from_cov(
            Vector3::new(-10.0, 0.0, 0.0),
            &Matrix3::from_diagonal(&Vector3::new(0.5, 0.5, 0.01)),
        )
        .unwrap();
        let z = Vector2::new(10.0, -std::f64::consts::PI + 0.01);
        let up = update(
            &g,
            &z,
            &Matrix2::from_diagonal(&Vector2::new(0.1, 0.02)),
            h_range_bearing,
            res_angle,
        )
        .unwrap();
        assert!(up.log_likelihood > -5.0, "{}", up.log_likelihood);
        assert!((up.posterior.mean - g.mean).norm() < 1.0);
        assert!(up.posterior.mean.y < 0.0, "moved towards the measured side");
    }

    #[test]
    fn the_student_t_density_is_the_textbook_one() {
        // one dimension, scale s: t_ν(x) = Γ((ν+1)/2) / (Γ(ν/2)·√(νπ)·s) · (1 + x²/(ν s²))^(−(ν+1)/2)
        let s = 0.3f64;
        for (dof, x) in [(1.0, 0.2), (4.0, 1.5), (10.0, -0.7)] {
            let d2 = x * x / (s * s);
            let ln_n = -0.5 * (d2 + (s * s).ln() + (2.0 * std::f64::consts::PI).ln());
            let want = libm::lgamma((dof + 1.0) / 2.0)
                - libm::lgamma(dof / 2.0)
                - 0.5 * (dof * std::f64::consts::PI).ln()
                - s.ln()
                - (dof + 1.0) / 2.0 * (1.0 + d2 / dof).ln();
            assert_relative_eq!(
                student_t_log_density(ln_n, d2, 1, dof),
                want,
                epsilon = 1e-12
            );
        }
        // Cauchy (ν = 1) at x = s: 1/(2π·s)
        let ln_n = -0.5 * (1.0 + (s * s).ln() + (2.0 * std::f64::consts::PI).ln());
        assert_relative_eq!(
            student_t_log_density(ln_n, 1.0, 1, 1.0),
            (1.0 / (2.0 * std::f64::consts::PI * s)).ln(),
            epsilon = 1e-12
        );
        // two dimensions, unit scale, ν = 4: (1/2π)·(1 + d²/4)^(−3)
        assert_relative_eq!(
            student_t_log_density(
                -0.5 * (9.0 + 2.0 * (2.0 * std::f64::consts::PI).ln()),
                9.0,
                2,
                4.0
            ),
            -(2.0 * std::f64::consts::PI).ln() - 3.0 * (1.0 + 9.0 / 4.0f64).ln(),
            epsilon = 1e-12
        );
        // ν = 0 is the Gaussian, and a large ν approaches it
        assert_eq!(student_t_log_density(-3.2, 2.0, 2, 0.0), -3.2);
        let ln_n = -0.5 * (2.0 + 2.0 * (2.0 * std::f64::consts::PI).ln());
        assert_relative_eq!(
            student_t_log_density(ln_n, 2.0, 2, 1e7),
            ln_n,
            epsilon = 1e-5
        );
        // far out, the t law is far more forgiving than the Gaussian
        let far = 100.0;
        let ln_far = -0.5 * (far + 2.0 * (2.0 * std::f64::consts::PI).ln());
        assert!(student_t_log_density(ln_far, far, 2, 4.0) > ln_far + 35.0);
    }

    #[test]
    fn the_student_t_widens_only_detections_in_its_tails() {
        assert_eq!(student_t_noise_scale(50.0, 2, 0.0), 1.0);
        assert_eq!(student_t_noise_scale(1.0, 2, 4.0), 1.0);
        assert_relative_eq!(student_t_noise_scale(26.0, 2, 4.0), 5.0);
        assert_relative_eq!(student_t_noise_scale(4.0, 1, 3.0), 7.0 / 4.0);
    }
}

//! Registration: least-squares rigid transforms between point sets (2D Kabsch/Umeyama and
//! its covariance-weighted and correlated forms, refined by Gauss–Newton).

use super::*;

/// Least-squares rigid transform (rotation + translation, no scale, det = +1) taking
/// `from` onto `to` (2D Kabsch/Umeyama). None for fewer than two distinct points.
pub fn fit_rigid(from: &[Point2<f64>], to: &[Point2<f64>]) -> Option<Isometry2<f64>> {
    let n = from.len();
    if n < 2 || n != to.len() {
        return None;
    }
    let cf = from.iter().fold(Vector2::zeros(), |a, p| a + p.coords) / n as f64;
    let ct = to.iter().fold(Vector2::zeros(), |a, p| a + p.coords) / n as f64;
    let (mut dot, mut cross) = (0.0, 0.0);
    for (f, t) in from.iter().zip(to) {
        let (a, b) = (f.coords - cf, t.coords - ct);
        dot += a.dot(&b);
        cross += a.x * b.y - a.y * b.x;
    }
    if dot.abs() + cross.abs() < 1e-12 {
        return None;
    }
    let angle = cross.atan2(dot);
    let rot = nalgebra::Rotation2::new(angle);
    let t = ct - rot * cf;
    Some(Isometry2::new(t, angle))
}

/// Maximum-likelihood rigid transform taking the points `from` onto `to` when pair i's
/// residual `toᵢ − (R·fromᵢ + t)` is Gaussian with covariance `R·Cᶠᵢ·Rᵀ + Cᵗᵢ` (the two
/// maps' position covariances): Gauss–Newton on (θ, t) from `init`, the pair covariances
/// re-rotated every iteration. Unlike [`fit_rigid`] a transmitter known to 0.1 m pulls the
/// fit harder than one known to 2 m, and only across its long axis. None when the normal
/// equations are singular (fewer than two pairs, or every covariance degenerate).
pub fn fit_rigid_weighted(
    from: &[(Point2<f64>, Matrix2<f64>)],
    to: &[(Point2<f64>, Matrix2<f64>)],
    init: Isometry2<f64>,
) -> Option<Isometry2<f64>> {
    weighted_gauss_newton(from, to, init).map(|(iso, _)| iso)
}

/// [`fit_rigid_weighted`] with the covariance of its estimate: the inverse of the
/// Gauss–Newton information `Σ Jᵢᵀ Wᵢ Jᵢ` at the solution, over (θ, t_x, t_y) — what the
/// pair covariances allow the fit to know if the pairs' errors are independent.
pub fn fit_rigid_weighted_cov(
    from: &[(Point2<f64>, Matrix2<f64>)],
    to: &[(Point2<f64>, Matrix2<f64>)],
    init: Isometry2<f64>,
) -> Option<(Isometry2<f64>, Matrix3<f64>)> {
    let (iso, normal) = weighted_gauss_newton(from, to, init)?;
    let (angle, t) = (iso.rotation.angle(), iso.translation.vector);
    let cov = normal(angle, t)?.0.cholesky()?.inverse();
    Some((iso, cov))
}

/// [`fit_rigid_weighted_cov`] when the errors of the `from` points are correlated: the
/// maximum-likelihood rigid transform for a joint Gaussian error of the stacked `from` points
/// with covariance `cov_from` (2n × 2n, x and y of point i at rows 2i and 2i + 1) and
/// independent errors `cov_to[i]` of the `to` points. Generalized least squares by
/// Gauss–Newton on (θ, t) from `init`, `cov_from` re-rotated every iteration; returns the
/// transform and the inverse of its information. With a block-diagonal `cov_from` it is
/// [`fit_rigid_weighted_cov`]. What the correlation is for: points placed from one robot's
/// dead-reckoned poses share that dead reckoning's drift, which does not average out over
/// them and cannot be told from the transform's own rotation — the generalized fit gives the
/// shared part its due weight once instead of once per point. None when the joint covariance
/// or the normal equations are singular or the sizes disagree.
pub fn fit_rigid_correlated(
    from: &[Point2<f64>],
    cov_from: &nalgebra::DMatrix<f64>,
    to: &[(Point2<f64>, Matrix2<f64>)],
    init: Isometry2<f64>,
) -> Option<(Isometry2<f64>, Matrix3<f64>)> {
    let n = from.len();
    if n < 2 || to.len() != n || cov_from.shape() != (2 * n, 2 * n) {
        return None;
    }
    let normal = |angle: f64, t: Vector2<f64>| -> Option<(Matrix3<f64>, Vector3<f64>)> {
        let rot = nalgebra::Rotation2::new(angle).into_inner();
        let mut sigma = cov_from.clone();
        let mut jac = nalgebra::DMatrix::<f64>::zeros(2 * n, 3);
        let mut r = nalgebra::DVector::<f64>::zeros(2 * n);
        for i in 0..n {
            for j in 0..n {
                let block = rot * sigma.fixed_view::<2, 2>(2 * i, 2 * j) * rot.transpose();
                sigma.fixed_view_mut::<2, 2>(2 * i, 2 * j).copy_from(&block);
            }
            let c = sigma.fixed_view::<2, 2>(2 * i, 2 * i) + to[i].1;
            sigma.fixed_view_mut::<2, 2>(2 * i, 2 * i).copy_from(&c);
            let q = rot * from[i].coords;
            let ri = to[i].0.coords - q - t;
            r.fixed_rows_mut::<2>(2 * i).copy_from(&ri);
            // ∂r/∂θ = −(d/dθ R)·from = −(−q_y, q_x); ∂r/∂t = −I
            jac.fixed_view_mut::<2, 3>(2 * i, 0)
                .copy_from(&nalgebra::Matrix2x3::new(q.y, -1.0, 0.0, -q.x, 0.0, -1.0));
        }
        let ch = sigma.cholesky()?;
        let wj = ch.solve(&jac);
        let h = jac.transpose() * &wj;
        let g = wj.transpose() * r;
        Some((
            Matrix3::from_iterator(h.iter().copied()),
            Vector3::new(g[0], g[1], g[2]),
        ))
    };
    let iso = gauss_newton(init, normal)?;
    let cov = normal(iso.rotation.angle(), iso.translation.vector)?
        .0
        .cholesky()?
        .inverse();
    Some((iso, cov))
}

/// Gauss–Newton on (θ, t) from `init` with the normal equations `normal(θ, t)` = (information,
/// gradient): at most 20 steps, until a step is below 1e-12. None when the information is not
/// positive definite or the result not finite.
pub(super) fn gauss_newton(
    init: Isometry2<f64>,
    normal: impl Fn(f64, Vector2<f64>) -> Option<(Matrix3<f64>, Vector3<f64>)>,
) -> Option<Isometry2<f64>> {
    let (mut angle, mut t) = (init.rotation.angle(), init.translation.vector);
    for _ in 0..20 {
        let (h, g) = normal(angle, t)?;
        let step = h.cholesky()?.solve(&(-g));
        angle += step[0];
        t += Vector2::new(step[1], step[2]);
        if step.norm() < 1e-12 {
            break;
        }
    }
    (angle.is_finite() && t.iter().all(|v| v.is_finite())).then(|| Isometry2::new(t, angle))
}

/// The Gauss–Newton iteration of [`fit_rigid_weighted`]; also returns its normal equations
/// (information matrix and gradient at a given θ, t).
#[allow(clippy::type_complexity)]
pub(super) fn weighted_gauss_newton<'a>(
    from: &'a [(Point2<f64>, Matrix2<f64>)],
    to: &'a [(Point2<f64>, Matrix2<f64>)],
    init: Isometry2<f64>,
) -> Option<(
    Isometry2<f64>,
    impl Fn(f64, Vector2<f64>) -> Option<(Matrix3<f64>, Vector3<f64>)> + 'a,
)> {
    if from.len() < 2 || from.len() != to.len() {
        return None;
    }
    let normal = move |angle: f64, t: Vector2<f64>| -> Option<(Matrix3<f64>, Vector3<f64>)> {
        let rot = nalgebra::Rotation2::new(angle).into_inner();
        let (mut h, mut g) = (Matrix3::<f64>::zeros(), Vector3::<f64>::zeros());
        for ((pf, cf), (pt, ct)) in from.iter().zip(to) {
            let q = rot * pf.coords;
            let r = pt.coords - q - t;
            let w = (rot * cf * rot.transpose() + ct).try_inverse()?;
            // ∂r/∂θ = −(d/dθ R)·from = −(−q_y, q_x); ∂r/∂t = −I
            let j = nalgebra::Matrix2x3::new(q.y, -1.0, 0.0, -q.x, 0.0, -1.0);
            h += j.transpose() * w * j;
            g += j.transpose() * w * r;
        }
        Some((h, g))
    };
    gauss_newton(init, normal).map(|iso| (iso, normal))
}

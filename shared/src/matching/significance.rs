//! The acceptance test of a hypothesis: the expected number of false alarms (a-contrario, in
//! the manner of ORSA, Moisan & Stival 2004) and the mirror-image check.

use super::*;

/// Summed squared Mahalanobis distance of the inlier pairs under `iso`, each pair with the
/// covariance `R·C_u·Rᵀ + C_p` (`reflect`: the user points and covariances mirrored at the
/// x axis first).
pub(super) fn pair_chi2(
    iso: &Isometry2<f64>,
    pairs: &[(usize, usize)],
    u: &[Cand],
    p: &[Cand],
    reflect: bool,
) -> f64 {
    let m = nalgebra::Matrix2::new(1.0, 0.0, 0.0, if reflect { -1.0 } else { 1.0 });
    let rot = iso.rotation.to_rotation_matrix().into_inner();
    pairs
        .iter()
        .map(|&(i, j)| {
            let q = iso * Point2::from(m * u[i].p.coords);
            let cov = rot * m * u[i].cov * m.transpose() * rot.transpose() + p[j].cov;
            let r = p[j].p - q;
            cov.cholesky()
                .map(|c| r.dot(&c.solve(&r)))
                .unwrap_or(f64::INFINITY)
        })
        .sum()
}

/// How much worse the best mirror image of the inlier pairs fits than the hypothesis itself
/// (χ² difference): the user points reflected at the x axis, then the least-squares proper
/// rigid fit onto their prior partners — together the best improper rigid motion.
pub(super) fn mirror_excess_chi2(h: &Hypothesis, u: &[Cand], p: &[Cand]) -> f64 {
    let from: Vec<Point2<f64>> = h
        .pairs
        .iter()
        .map(|&(i, _)| Point2::new(u[i].p.x, -u[i].p.y))
        .collect();
    let to: Vec<Point2<f64>> = h.pairs.iter().map(|&(_, j)| p[j].p).collect();
    // None: every rotation fits equally well (e.g. a reflected square onto itself), so the
    // centroids aligned without rotation is as good as any
    let mirror = fit_rigid(&from, &to).unwrap_or_else(|| {
        let n = from.len().max(1) as f64;
        let cf = from.iter().fold(Vector2::zeros(), |a, q| a + q.coords) / n;
        let ct = to.iter().fold(Vector2::zeros(), |a, q| a + q.coords) / n;
        Isometry2::new(ct - cf, 0.0)
    });
    pair_chi2(&mirror, &h.pairs, u, p, true) - pair_chi2(&h.iso, &h.pairs, u, p, false)
}

/// Expected number of false alarms of a hypothesis (a-contrario test in the manner of ORSA,
/// Moisan & Stival 2004): how many of the `tests` hypotheses tried would, in maps without a
/// common part, fit at least as well by chance.
///
/// Null model: the prior candidates are spread uniformly over their bounding box (density ρ)
/// and independent of the user's. A user transmitter meets a chance partner at least as close
/// as inlier i (inside the ellipse of area e_i through its residual) and b-compatible with it
/// (fraction f_i of the prior candidates) with probability q_i = 1 − exp(−ρ·e_i·f_i). Sorting
/// the inliers by q, the three best are taken as the minimal sample: two pairs fix a rigid
/// transform and carry no evidence; the third was chosen among the prior transmitters whose
/// distances to the first two agree within `distance_tolerance_m`, so it counts with
/// q₃ = e₃ / (2·tol)². For j of the remaining inliers with q ≤ q_(3+j), the chance is the
/// Binomial tail P(X ≥ j), X ~ Bin(n − 3, q_(3+j)), n the user candidates the hypothesis
/// puts inside the prior's box. The false-alarm count is tests · (n − 3) · q₃ · min_j of
/// that tail (the factor n − 3 pays for choosing j).
pub(super) fn false_alarms(
    h: &Hypothesis,
    u: &[Cand],
    p: &[Cand],
    cfg: &MatchConfig,
    tests: usize,
) -> f64 {
    let (x0, y0, x1, y1) = bounds(p);
    let margin = cfg.inlier_threshold_m;
    let (x0, x1, y0, y1) = (x0 - margin, x1 + margin, y0 - margin, y1 + margin);
    let density = p.len() as f64 / ((x1 - x0) * (y1 - y0));
    let inside = u
        .iter()
        .map(|c| h.iso * c.p)
        .filter(|q| q.x >= x0 && q.x <= x1 && q.y >= y0 && q.y <= y1)
        .count();
    let k = h.pairs.len();
    if k <= 3 {
        return f64::INFINITY;
    }
    let n = inside.max(k) - 3;
    let mut q: Vec<(f64, f64)> = h
        .pairs
        .iter()
        .zip(&h.ellipse_m2)
        .map(|(&(i, _), &e)| {
            let f =
                p.iter().filter(|c| b_compatible(&u[i], c, cfg)).count() as f64 / p.len() as f64;
            ((1.0 - (-density * e * f).exp()).clamp(1e-300, 1.0), e)
        })
        .collect();
    q.sort_by(|a, b| a.0.total_cmp(&b.0));
    // The third sample member was chosen among the prior transmitters whose distances to the
    // first two agree within the tolerance — a region of at least (2·tol)² — so only its fine
    // residual within that region is evidence.
    let ln_third = (q[2].1 / (4.0 * cfg.distance_tolerance_m.powi(2)))
        .clamp(1e-300, 1.0)
        .ln();
    let best_tail = (1..=k - 3)
        .map(|j| ln_binomial_tail(n, j, q[2 + j].0))
        .fold(0.0, f64::min);
    if std::env::var_os("ECHOMAP_NFA_DEBUG").is_some() {
        eprintln!(
            "nfa: tests {tests} n {n} k {k} density {density:.4} q {q:?} best {best_tail:.2}"
        );
    }
    tests as f64 * n as f64 * (ln_third + best_tail).exp()
}

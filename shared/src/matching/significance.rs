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
/// Moisan & Stival 2004): how many hypotheses, among all that RANSAC could have formed from
/// these two maps, would fit at least as well by chance if the maps had no common part.
///
/// Null model: the prior candidates are spread uniformly over their bounding box (density ρ)
/// and independent of the user's. Under a transform, a user transmitter meets a chance partner
/// at least as close as inlier i (inside the ellipse of area e_i through its residual, in the
/// pair's covariance) and b-compatible with it (fraction f_i of the prior candidates) with
/// probability q_i = 1 − exp(−ρ·e_i·f_i).
///
/// Every hypothesis is counted whether RANSAC tried it or not. A transform is fixed by a first
/// pair (U·P choices for U user and P prior candidates: the translation, no evidence) and the
/// user transmitter that fixes the rotation (U − 1 choices): its partner is chance when some
/// prior transmitter lies on the circle its distance d to the first allows, in an annulus as
/// wide as its ellipse — probability q′ = 1 − exp(−ρ·f·2π·d·2r), r = √(e/π). The first pair is
/// the inlier of least q, the second the one of least q′. For j of the other inliers with
/// q ≤ q_(j) (sorted), the chance is the Binomial tail P(X ≥ j), X ~ Bin(n − 2, q_(j)), where n
/// counts every user candidate the transform puts inside the prior's box: a user transmitter
/// there without a counterpart is a trial that failed — evidence against the hypothesis. The
/// false-alarm count is `U·(U − 1)·P · (n − 2) · q′ · min_j P(X ≥ j)` (the factor n − 2 pays for
/// choosing j).
pub(super) fn false_alarms(h: &Hypothesis, u: &[Cand], p: &[Cand], cfg: &MatchConfig) -> f64 {
    let k = h.pairs.len();
    if k <= 2 {
        return f64::INFINITY;
    }
    let (x0, y0, x1, y1) = bounds(p);
    let margin = cfg.inlier_threshold_m;
    let (x0, x1, y0, y1) = (x0 - margin, x1 + margin, y0 - margin, y1 + margin);
    let density = p.len() as f64 / ((x1 - x0) * (y1 - y0));
    let inside = u
        .iter()
        .map(|c| h.iso * c.p)
        .filter(|q| q.x >= x0 && q.x <= x1 && q.y >= y0 && q.y <= y1)
        .count();
    let n = inside.max(k) - 2;
    // per inlier: ρ·f (chance partners per m²) and the ellipse area e
    let rate_area: Vec<(f64, f64)> = h
        .pairs
        .iter()
        .zip(&h.ellipse_m2)
        .map(|(&(i, _), &e)| {
            let f =
                p.iter().filter(|c| b_compatible(&u[i], c, cfg)).count() as f64 / p.len() as f64;
            (density * f, e)
        })
        .collect();
    let chance = |x: f64| (1.0 - (-x).exp()).clamp(1e-300, 1.0);
    let first = (0..k)
        .min_by(|&a, &b| {
            (rate_area[a].0 * rate_area[a].1).total_cmp(&(rate_area[b].0 * rate_area[b].1))
        })
        .expect("k > 2 inliers");
    let anchor = p[h.pairs[first].1].p;
    let (second, q_rot) = (0..k)
        .filter(|&i| i != first)
        .map(|i| {
            let (rate, e) = rate_area[i];
            let d = (p[h.pairs[i].1].p - anchor).norm();
            let r = (e / std::f64::consts::PI).sqrt();
            (i, chance(rate * 2.0 * std::f64::consts::PI * d * 2.0 * r))
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .expect("k > 2 inliers");
    let mut q: Vec<f64> = (0..k)
        .filter(|&i| i != first && i != second)
        .map(|i| chance(rate_area[i].0 * rate_area[i].1))
        .collect();
    q.sort_by(|a, b| a.total_cmp(b));
    let (nu, np) = (u.len() as f64, p.len() as f64);
    let ln_tests = nu.ln() + (nu - 1.0).ln() + np.ln() + (n as f64).ln();
    let best_tail = (1..=k - 2)
        .map(|j| ln_binomial_tail(n, j, q[j - 1]))
        .fold(0.0, f64::min);
    (ln_tests + q_rot.ln() + best_tail).exp()
}

//! Scoring a hypothesis: one-to-one inlier pairs under the χ² gate and the score of
//! Ulmschneider et al. 2021 eq. 18 (location term and visibility term).

use super::*;

/// Visibility term of eq. 18 for one correspondence: Σ over the user's (transformed) cells
/// of ln BetaBinomial(k; n, α_p + 1, β_p + 1) − ln BetaBinomial(k; n, 1, 1), where k, n are
/// the user's seen / total counts and α_p, β_p the prior's counts in the same cell.
pub(super) fn visibility_llr(
    user: &Transmitter,
    prior: &Transmitter,
    map_from_agent: &Isometry2<f64>,
    grid: &HexGrid,
    max_count: f64,
) -> f64 {
    if user.visibility.is_empty() || prior.visibility.is_empty() {
        return 0.0;
    }
    let moved = transform_visibility(&user.visibility, map_from_agent, grid);
    let mut llr = 0.0;
    for (cell, u) in &moved {
        if let Some(p) = prior.visibility.get(cell) {
            // at most `max_count` effective observations per cell (see MatchConfig)
            let n = u.alpha + u.beta;
            let scale = if n > max_count { max_count / n } else { 1.0 };
            let (k, m) = (u.alpha * scale, u.beta * scale);
            let (a, b) = (p.alpha + 1.0, p.beta + 1.0);
            llr += ln_beta(k + a, m + b)
                - ln_beta(a, b)
                - (ln_beta(k + 1.0, m + 1.0) - ln_beta(1.0, 1.0));
        }
    }
    llr
}

pub(super) struct Hypothesis {
    pub(super) iso: Isometry2<f64>,
    pub(super) pairs: Vec<(usize, usize)>, // candidate indices (user, prior)
    pub(super) residuals: Vec<f64>,
    /// per pair: the area of its uncertainty ellipse through the residual, π·d²·√det S (m²)
    pub(super) ellipse_m2: Vec<f64>,
    pub(super) loc_score: f64,
}

/// The squared Mahalanobis distance between user candidate `uc` (moved to `q`, covariance
/// `cov_u` rotated into the map frame) and prior candidate `pc`, when they are b-compatible
/// and inside the χ² gate.
pub(super) fn gated(
    uc: &Cand,
    q: &Point2<f64>,
    cov_u: &nalgebra::Matrix2<f64>,
    pc: &Cand,
    cfg: &MatchConfig,
) -> Option<f64> {
    if !b_compatible(uc, pc, cfg) {
        return None;
    }
    let r = pc.p - q;
    let d2 = (cov_u + pc.cov).cholesky()?.solve(&r).dot(&r);
    (d2 <= cfg.inlier_gate_chi2).then_some(d2)
}

/// One-to-one inlier pairs `(user, prior)` under `iso`, greedy by Mahalanobis distance, sorted.
pub(super) fn inlier_pairs(
    iso: &Isometry2<f64>,
    u: &[Cand],
    p: &[Cand],
    grid: &Grid,
    cfg: &MatchConfig,
) -> Vec<(usize, usize)> {
    let mut near = Vec::new();
    let mut cand_pairs: Vec<(f64, usize, usize)> = Vec::new();
    let rot = iso.rotation.to_rotation_matrix().into_inner();
    for (i, uc) in u.iter().enumerate() {
        let q = iso * uc.p;
        let cov_u = rot * uc.cov * rot.transpose();
        grid.near(&q, cfg.inlier_threshold_m, p, &mut near);
        for &j in &near {
            if let Some(d2) = gated(uc, &q, &cov_u, &p[j], cfg) {
                cand_pairs.push((d2, i, j));
            }
        }
    }
    cand_pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let (mut used_u, mut used_p) = (vec![false; u.len()], vec![false; p.len()]);
    let mut pairs = Vec::new();
    for (_, i, j) in cand_pairs {
        if !used_u[i] && !used_p[j] {
            used_u[i] = true;
            used_p[j] = true;
            pairs.push((i, j));
        }
    }
    pairs.sort_unstable();
    pairs
}

/// Pre-screen of a hypothesis: how many user candidates have some gated, b-compatible prior
/// candidate under `iso` (an upper bound of the one-to-one inlier count), or None as soon as
/// fewer than `need` remain possible.
pub(super) fn quick_count(
    iso: &Isometry2<f64>,
    u: &[Cand],
    p: &[Cand],
    grid: &Grid,
    cfg: &MatchConfig,
    need: usize,
) -> Option<usize> {
    let mut near = Vec::new();
    let rot = iso.rotation.to_rotation_matrix().into_inner();
    let mut count = 0;
    for (i, uc) in u.iter().enumerate() {
        if count + (u.len() - i) < need {
            return None;
        }
        let q = iso * uc.p;
        grid.near(&q, cfg.inlier_threshold_m, p, &mut near);
        let cov_u = rot * uc.cov * rot.transpose();
        let hit = near
            .iter()
            .any(|&j| gated(uc, &q, &cov_u, &p[j], cfg).is_some());
        count += usize::from(hit);
    }
    (count >= need).then_some(count)
}

/// The visibility term of eq. 18 for the pairs of a hypothesis, times its weight (0 when
/// the term is off).
#[allow(clippy::too_many_arguments)]
pub(super) fn visibility_score(
    iso: &Isometry2<f64>,
    pairs: &[(usize, usize)],
    user: &TransmitterMap,
    prior: &TransmitterMap,
    u: &[Cand],
    p: &[Cand],
    hex: &HexGrid,
    cfg: &MatchConfig,
) -> f64 {
    if !cfg.use_visibility {
        return 0.0;
    }
    pairs
        .iter()
        .map(|&(i, j)| {
            visibility_llr(
                &user.transmitters()[u[i].index],
                &prior.transmitters()[p[j].index],
                iso,
                hex,
                cfg.visibility_max_count,
            )
        })
        .sum::<f64>()
        * cfg.visibility_weight
}

/// How a given transform explains `user` against `prior`, scored as `match_maps` scores a
/// hypothesis (one-to-one inliers under the same gates, location + visibility term) but
/// without refitting it — to check whether an earlier match still holds and to compare it
/// with a new one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TransformScore {
    /// one-to-one inlier pairs under the transform
    pub inliers: usize,
    /// comparable with [`MatchResult::score`] of a match between the same two maps
    pub score: f64,
}

/// Scores `map_from_agent` on `user` against `prior` (see [`TransformScore`]).
pub fn score_transform(
    user: &TransmitterMap,
    prior: &TransmitterMap,
    map_from_agent: &Isometry2<f64>,
    cfg: &MatchConfig,
) -> TransformScore {
    let u = candidates(user, cfg);
    let p = candidates(prior, cfg);
    if u.is_empty() || p.is_empty() {
        return TransformScore {
            inliers: 0,
            score: 0.0,
        };
    }
    let grid = Grid::new(&p, cfg.inlier_threshold_m.max(1e-3));
    let pairs = inlier_pairs(map_from_agent, &u, &p, &grid, cfg);
    let (d2, sqrt_det) = pair_distances(map_from_agent, &pairs, &u, &p);
    let loc = location_score(&d2, &sqrt_det, ln_clutter_area(&p, cfg), cfg);
    let vis = visibility_score(
        map_from_agent,
        &pairs,
        user,
        prior,
        &u,
        &p,
        &prior.grid(),
        cfg,
    );
    TransformScore {
        inliers: pairs.len(),
        score: loc + vis,
    }
}

/// Per pair `(user, prior)` under `iso`: the squared Mahalanobis distance and √det of the
/// pair covariance `R·C_u·Rᵀ + C_p`.
pub(super) fn pair_distances(
    iso: &Isometry2<f64>,
    pairs: &[(usize, usize)],
    u: &[Cand],
    p: &[Cand],
) -> (Vec<f64>, Vec<f64>) {
    let rot = iso.rotation.to_rotation_matrix().into_inner();
    pairs
        .iter()
        .map(|&(i, j)| {
            let r = p[j].p - iso * u[i].p;
            let s = rot * u[i].cov * rot.transpose() + p[j].cov;
            let d2 = s
                .cholesky()
                .map(|c| r.dot(&c.solve(&r)))
                .unwrap_or(f64::INFINITY);
            (d2, s.determinant().max(0.0).sqrt())
        })
        .unzip()
}

/// ln of the clutter area: the prior candidates' bounding box widened by the inlier
/// threshold on every side (as in `false_alarms`).
pub(super) fn ln_clutter_area(p: &[Cand], cfg: &MatchConfig) -> f64 {
    let (x0, y0, x1, y1) = bounds(p);
    let m = 2.0 * cfg.inlier_threshold_m.max(1e-3);
    ((x1 - x0 + m) * (y1 - y0 + m)).ln()
}

/// The location term of a hypothesis (see [`LocationScore`]) from its inliers' squared
/// Mahalanobis distances `d2` and the √det of their pair covariances.
pub(super) fn location_score(d2: &[f64], sqrt_det: &[f64], ln_area: f64, cfg: &MatchConfig) -> f64 {
    match cfg.location_score {
        LocationScore::Msac => d2
            .iter()
            .map(|d| 1.0 - (d / cfg.inlier_gate_chi2).min(1.0))
            .sum(),
        LocationScore::Likelihood { min_scale } => {
            let base: Vec<f64> = sqrt_det
                .iter()
                .map(|s| ln_area - (2.0 * std::f64::consts::PI * s.max(1e-300)).ln())
                .collect();
            let sum_at = |k2: f64| -> f64 {
                d2.iter()
                    .zip(&base)
                    .map(|(d, b)| (b - k2.ln() - d / (2.0 * k2)).max(0.0))
                    .sum()
            };
            // k on a log-spaced grid over [min_scale, 1], plus the untruncated optimum
            // k² = Σd²/(2n) when it lies inside
            const STEPS: usize = 32;
            let lo = min_scale.clamp(1e-3, 1.0).ln();
            let mut best = sum_at(1.0);
            for s in 0..STEPS {
                let k = (lo * s as f64 / STEPS as f64).exp();
                best = best.max(sum_at(k * k));
            }
            let n = d2.len().max(1) as f64;
            let k2 = d2.iter().sum::<f64>() / (2.0 * n);
            if k2.is_finite() && k2 >= (2.0 * lo).exp() && k2 <= 1.0 {
                best = best.max(sum_at(k2));
            }
            best
        }
    }
}

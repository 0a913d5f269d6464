//! The RANSAC search (LO-RANSAC over minimal samples of three transmitters) that ties the
//! pieces together: [`match_maps`].

use super::*;

/// A matching candidate: index in its map, mean position, b and its std.
#[derive(Debug, Clone, Copy)]
pub(super) struct Cand {
    pub(super) index: usize,
    pub(super) p: Point2<f64>,
    /// position covariance (x/y block)
    pub(super) cov: nalgebra::Matrix2<f64>,
    pub(super) b: f64,
    pub(super) b_std: f64,
}

pub(super) fn candidates(map: &TransmitterMap, cfg: &MatchConfig) -> Vec<Cand> {
    map.transmitters()
        .iter()
        .enumerate()
        .filter(|(_, t)| t.existence >= cfg.min_existence)
        .filter_map(|(index, t)| {
            let (m, p) = t.moments();
            ((p[(0, 0)] + p[(1, 1)]).sqrt() <= cfg.max_position_std_m).then(|| Cand {
                index,
                p: Point2::new(m.x, m.y),
                cov: p.fixed_view::<2, 2>(0, 0).into_owned()
                    + nalgebra::Matrix2::identity() * cfg.position_floor_m.powi(2),
                b: m.z,
                b_std: p[(2, 2)].max(0.0).sqrt(),
            })
        })
        .collect()
}

pub(super) fn b_compatible(u: &Cand, p: &Cand, cfg: &MatchConfig) -> bool {
    (u.b - p.b).abs() <= cfg.b_gate_sigma * u.b_std.hypot(p.b_std) + cfg.b_gate_floor_m
}

/// Collects one-to-one inlier pairs under `iso` (greedy by distance) and refits.
pub(super) fn local_optimize(
    iso: Isometry2<f64>,
    u: &[Cand],
    p: &[Cand],
    grid: &Grid,
    ln_area: f64,
    cfg: &MatchConfig,
) -> Option<Hypothesis> {
    let mut iso = iso;
    let mut last: Vec<(usize, usize)> = Vec::new();
    for _ in 0..10 {
        let pairs = inlier_pairs(&iso, u, p, grid, cfg);
        if pairs.len() < 3 {
            return None;
        }
        let from: Vec<Point2<f64>> = pairs.iter().map(|&(i, _)| u[i].p).collect();
        let to: Vec<Point2<f64>> = pairs.iter().map(|&(_, j)| p[j].p).collect();
        iso = fit_rigid(&from, &to)?;
        // the least-squares fit starts the covariance-weighted one (ML under both maps'
        // position covariances)
        let from_cov: Vec<_> = pairs.iter().map(|&(i, _)| (u[i].p, u[i].cov)).collect();
        let to_cov: Vec<_> = pairs.iter().map(|&(_, j)| (p[j].p, p[j].cov)).collect();
        iso = fit_rigid_weighted(&from_cov, &to_cov, iso).unwrap_or(iso);
        if pairs == last {
            break;
        }
        last = pairs;
    }
    let residuals: Vec<f64> = last
        .iter()
        .map(|&(i, j)| (iso * u[i].p - p[j].p).norm())
        .collect();
    let (d2, sqrt_det) = pair_distances(&iso, &last, u, p);
    let loc_score = location_score(&d2, &sqrt_det, ln_area, cfg);
    let ellipse_m2 = d2
        .iter()
        .zip(&sqrt_det)
        .map(|(d, s)| std::f64::consts::PI * d * s)
        .collect();
    Some(Hypothesis {
        iso,
        pairs: last,
        residuals,
        ellipse_m2,
        loc_score,
    })
}

/// Matches `user` (agent frame) against `prior` (map frame). Deterministic for a given RNG
/// state; the RNG is only used to draw user triples.
pub fn match_maps(
    user: &TransmitterMap,
    prior: &TransmitterMap,
    cfg: &MatchConfig,
    rng: &mut impl Rng,
) -> MatchResult {
    let u = candidates(user, cfg);
    let p = candidates(prior, cfg);
    if u.len() < 3 || p.len() < 3 {
        return MatchResult::refused(
            MatchDecision::Undecided,
            format!(
                "too few converged transmitters to decide: {} in the user map, {} in the prior map (3 needed)",
                u.len(),
                p.len()
            ),
            0,
        );
    }
    // Prior pairs binned by distance, for consistent-pair lookup.
    let tol = cfg.distance_tolerance_m;
    let pairs = PairBins::new(&p, tol);
    let mut window: Vec<(f64, u32, u32)> = Vec::new();
    let grid = Grid::new(&p, cfg.inlier_threshold_m.max(1e-3));
    let ln_area = ln_clutter_area(&p, cfg);
    let hex = prior.grid();
    let overlap = Overlap::new(&u, &p, cfg);
    // a consistent triple whose transform overlaps the maps too little to decide: when the
    // best hypothesis is not accepted, it may still be this explanation
    let mut undecidable: Option<BestCase> = None;

    let mut best: Option<(f64, f64, Hypothesis)> = None;
    let mut best_count = 0usize;
    let mut third = Vec::new();
    let mut needed = cfg.max_iterations;
    let mut it = 0;
    while it < needed.min(cfg.max_iterations) {
        it += 1;
        // draw a user triple with distinct members
        let a = rng.random_range(0..u.len());
        let mut b = rng.random_range(0..u.len() - 1);
        if b >= a {
            b += 1;
        }
        let mut c = rng.random_range(0..u.len() - 2);
        for x in [a.min(b), a.max(b)] {
            if c >= x {
                c += 1;
            }
        }
        let (ua, ub, uc) = (&u[a], &u[b], &u[c]);
        let dab = (ua.p - ub.p).norm();
        let dac = (ua.p - uc.p).norm();
        let dbc = (ub.p - uc.p).norm();
        if dab < tol || dac < tol || dbc < tol {
            continue; // degenerate triple
        }
        // prior pairs whose distance agrees with dab, nearest first
        pairs.window(dab, tol, &mut window);
        let mut tried = 0;
        for &(_, i, j) in &window {
            if tried >= cfg.max_hypotheses_per_sample {
                break;
            }
            let (i, j) = (i as usize, j as usize);
            for (pa, pb) in [(i, j), (j, i)] {
                if !b_compatible(ua, &p[pa], cfg) || !b_compatible(ub, &p[pb], cfg) {
                    continue;
                }
                // the third member must lie where the first two pairs put it
                let Some(two) = fit_rigid(&[ua.p, ub.p], &[p[pa].p, p[pb].p]) else {
                    continue;
                };
                grid.near(&(two * uc.p), tol, &p, &mut third);
                for &k in &third {
                    let pc = &p[k];
                    if k == pa || k == pb || !b_compatible(uc, pc, cfg) {
                        continue;
                    }
                    if ((p[pa].p - pc.p).norm() - dac).abs() > tol
                        || ((p[pb].p - pc.p).norm() - dbc).abs() > tol
                    {
                        continue;
                    }
                    tried += 1;
                    let Some(iso) = fit_rigid(&[ua.p, ub.p, uc.p], &[p[pa].p, p[pb].p, pc.p])
                    else {
                        continue;
                    };
                    // the minimal sample itself must fit (a mirror image does not)
                    if [(ua, pa), (ub, pb), (uc, k)]
                        .iter()
                        .any(|(x, y)| (iso * x.p - p[*y].p).norm() > cfg.inlier_threshold_m)
                    {
                        continue;
                    }
                    if undecidable.is_none() {
                        undecidable = overlap.too_small(&iso);
                    }
                    // LO-RANSAC: local optimization only for hypotheses that do at least as
                    // well as the best so far on a single pass
                    let Some(count) = quick_count(&iso, &u, &p, &grid, cfg, best_count.max(3))
                    else {
                        continue;
                    };
                    best_count = count;
                    let Some(h) = local_optimize(iso, &u, &p, &grid, ln_area, cfg) else {
                        continue;
                    };
                    let vis = visibility_score(&h.iso, &h.pairs, user, prior, &u, &p, &hex, cfg);
                    let score = h.loc_score + vis;
                    if best.as_ref().is_none_or(|b| score > b.0) {
                        // adaptive iteration count from the inlier ratio of the best hypothesis
                        let w = (h.pairs.len() as f64 / u.len() as f64).min(1.0);
                        let p_good = w.powi(3);
                        if p_good > 0.0 && p_good < 1.0 {
                            needed =
                                ((1.0 - cfg.confidence).ln() / (1.0 - p_good).ln()).ceil() as usize;
                        } else if p_good >= 1.0 {
                            needed = it;
                        }
                        best = Some((score, vis, h));
                    }
                }
            }
        }
    }
    let Some((score, vis, h)) = best else {
        // nothing consistent: a refusal only says something when the maps could have shown
        // a common part
        let best = overlap.best_case(None);
        return if best.false_alarms <= cfg.max_false_alarms {
            MatchResult::refused(
                MatchDecision::Rejected,
                "no consistent transmitter triple found: the maps share nothing".into(),
                it,
            )
        } else {
            MatchResult::refused(
                MatchDecision::Undecided,
                format!(
                    "no consistent transmitter triple found, and {} user and {} prior transmitters are too few to decide (expected false alarms even if all agreed {:.2e} > {:.0e})",
                    u.len(),
                    p.len(),
                    best.false_alarms,
                    cfg.max_false_alarms
                ),
                it,
            )
        };
    };
    let nfa = false_alarms(&h, &u, &p, &Walked::new(user, prior, &p), cfg);
    let mirror = mirror_excess_chi2(&h, &u, &p);
    let accepted = h.pairs.len() >= cfg.min_inliers
        && nfa <= cfg.max_false_alarms
        && mirror >= cfg.min_mirror_chi2;
    let mut result = MatchResult {
        accepted,
        decision: MatchDecision::Accepted,
        map_from_agent: h.iso,
        correspondences: h
            .pairs
            .iter()
            .map(|&(i, j)| (u[i].index, p[j].index))
            .collect(),
        residuals_m: h.residuals,
        inliers: h.pairs.len(),
        score,
        visibility_score: vis,
        reason: None,
        iterations: it,
    };
    if accepted {
        return result;
    }
    let best = overlap.best_case(Some(&h.iso));
    let (decision, reason) = if mirror < cfg.min_mirror_chi2 {
        (
            MatchDecision::Undecided,
            format!(
                "the {} inliers are nearly collinear: a mirror image fits them almost as well (χ² worse by {mirror:.1} < {})",
                result.inliers, cfg.min_mirror_chi2
            ),
        )
    } else if best.false_alarms > cfg.max_false_alarms {
        (
            MatchDecision::Undecided,
            format!(
                "the maps overlap too little to decide: under the best transform {} user transmitters fall inside the prior's area and {} prior transmitters inside the user's; {} agree, and even if all agreed the expected false alarms would be {:.2e} > {:.0e}",
                best.user_overlap,
                best.prior_overlap,
                result.inliers,
                best.false_alarms,
                cfg.max_false_alarms
            ),
        )
    } else if let Some(small) = undecidable {
        (
            MatchDecision::Undecided,
            format!(
                "the maps may overlap too little to decide: the best transform ({} inliers) is not significant, and another that fits three transmitters puts only {} user transmitters inside the prior's area and {} prior transmitters inside the user's ({} needed to decide)",
                result.inliers, small.user_overlap, small.prior_overlap, cfg.min_inliers
            ),
        )
    } else if h.pairs.len() < cfg.min_inliers {
        (
            MatchDecision::Rejected,
            format!(
                "only {} inliers, {} needed, among {} user transmitters inside the prior's area",
                result.inliers, cfg.min_inliers, best.user_overlap
            ),
        )
    } else {
        (
            MatchDecision::Rejected,
            format!(
                "{} inliers could be chance in maps this dense (expected false alarms {nfa:.2e} > {:.0e}; {} user transmitters inside the prior's area, {} prior transmitters inside the user's)",
                result.inliers, cfg.max_false_alarms, best.user_overlap, best.prior_overlap
            ),
        )
    };
    result.decision = decision;
    result.reason = Some(reason);
    result
}

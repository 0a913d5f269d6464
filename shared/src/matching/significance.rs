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

/// Where the user's track went and where the prior saw each of its candidates, for the prior
/// side of [`false_alarms`].
pub(super) struct Walked {
    /// centres of the cells the user's map has visibility counts in (agent frame)
    cells: Vec<Point2<f64>>,
    /// the prior's grid
    prior_grid: HexGrid,
    /// per prior candidate: the cells from which the prior saw it more often than not
    seen: Vec<Vec<HexCell>>,
}

impl Walked {
    pub(super) fn new(user: &TransmitterMap, prior: &TransmitterMap, p: &[Cand]) -> Walked {
        let user_grid = user.grid();
        let cells: std::collections::BTreeSet<HexCell> = user
            .transmitters()
            .iter()
            .flat_map(|t| {
                t.visibility
                    .iter()
                    .filter(|(_, b)| b.alpha + b.beta > 0.0)
                    .map(|(c, _)| *c)
            })
            .collect();
        Walked {
            cells: cells.into_iter().map(|c| user_grid.centre(c)).collect(),
            prior_grid: prior.grid(),
            seen: p
                .iter()
                .map(|c| {
                    prior.transmitters()[c.index]
                        .visibility
                        .iter()
                        .filter(|(_, b)| b.alpha > b.beta)
                        .map(|(cell, _)| *cell)
                        .collect()
                })
                .collect(),
        }
    }
}

/// One agreeing pair as evidence for the false-alarm count: chance partners per m² (ρ·f), the
/// area of its uncertainty ellipse (m²) and where it sits (for the rotation annulus).
struct Agreement {
    rate: f64,
    area: f64,
    at: Point2<f64>,
}

/// The box a map's candidates cover, widened by `margin` on every side, and their density in it.
#[derive(Debug, Clone, Copy)]
struct Region {
    x0: f64,
    y0: f64,
    x1: f64,
    y1: f64,
    density: f64,
}

impl Region {
    fn of(c: &[Cand], margin: f64) -> Region {
        let (x0, y0, x1, y1) = bounds(c);
        let (x0, y0, x1, y1) = (x0 - margin, y0 - margin, x1 + margin, y1 + margin);
        Region {
            x0,
            y0,
            x1,
            y1,
            density: c.len() as f64 / ((x1 - x0) * (y1 - y0)),
        }
    }

    fn contains(&self, q: &Point2<f64>) -> bool {
        q.x >= self.x0 && q.x <= self.x1 && q.y >= self.y0 && q.y <= self.y1
    }
}

/// The fraction of `others` that `c` is b-compatible with.
fn compatible_fraction(c: &Cand, others: &[Cand], cfg: &MatchConfig) -> f64 {
    others.iter().filter(|o| b_compatible(c, o, cfg)).count() as f64 / others.len() as f64
}

/// The false-alarm count of one side (see [`false_alarms`]): `agree` are the agreeing pairs,
/// `trials` how many candidates of the testing map fall inside the other map's region, `n_from`
/// and `n_to` the two maps' candidate counts.
fn side_false_alarms(agree: &[Agreement], trials: usize, n_from: usize, n_to: usize) -> f64 {
    let k = agree.len();
    if k <= 2 {
        return f64::INFINITY;
    }
    let n = trials.max(k) - 2;
    let chance = |x: f64| (1.0 - (-x).exp()).clamp(1e-300, 1.0);
    let first = (0..k)
        .min_by(|&a, &b| {
            (agree[a].rate * agree[a].area).total_cmp(&(agree[b].rate * agree[b].area))
        })
        .expect("k > 2 agreements");
    let anchor = agree[first].at;
    let (second, q_rot) = (0..k)
        .filter(|&i| i != first)
        .map(|i| {
            let d = (agree[i].at - anchor).norm();
            let r = (agree[i].area / std::f64::consts::PI).sqrt();
            (
                i,
                chance(agree[i].rate * 2.0 * std::f64::consts::PI * d * 2.0 * r),
            )
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .expect("k > 2 agreements");
    let mut q: Vec<f64> = (0..k)
        .filter(|&i| i != first && i != second)
        .map(|i| chance(agree[i].rate * agree[i].area))
        .collect();
    q.sort_by(|a, b| a.total_cmp(b));
    let (nu, np) = (n_from as f64, n_to as f64);
    let ln_tests = nu.ln() + (nu - 1.0).ln() + np.ln() + (n as f64).ln();
    let best_tail = (1..=k - 2)
        .map(|j| ln_binomial_tail(n, j, q[j - 1]))
        .fold(0.0, f64::min);
    (ln_tests + q_rot.ln() + best_tail).exp()
}

/// Expected number of false alarms of a hypothesis (a-contrario test in the manner of ORSA,
/// Moisan & Stival 2004): how many hypotheses, among all that RANSAC could have formed from
/// these two maps, would fit at least as well by chance if the maps had no common part.
///
/// Null model, seen from the user map: the prior candidates are spread uniformly over their
/// bounding box (density ρ) and independent of the user's. Under a transform, a user
/// transmitter meets a chance partner at least as close as inlier i (inside the ellipse of
/// area e_i through its residual, in the pair's covariance) and b-compatible with it (fraction
/// f_i of the prior candidates) with probability q_i = 1 − exp(−ρ·e_i·f_i).
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
///
/// The same count seen from the prior map (the user candidates uniform over the user's box)
/// makes the prior transmitters the user should have met, but did not map, count against the
/// hypothesis too: where both maps say where they were seen (visibility cells), the prior
/// transmitters the prior saw from a cell the user's track passed through (under the
/// transform). Without visibility the maps do not say where the user went — a partial map early
/// in a walk covers less than its transmitters' extent — and nothing is counted there.
/// The hypothesis must be significant under both null models: the larger of the two counts is
/// returned.
pub(super) fn false_alarms(
    h: &Hypothesis,
    u: &[Cand],
    p: &[Cand],
    walked: &Walked,
    cfg: &MatchConfig,
) -> f64 {
    if h.pairs.len() <= 2 {
        return f64::INFINITY;
    }
    let margin = cfg.inlier_threshold_m;
    let (prior_region, user_region) = (Region::of(p, margin), Region::of(u, margin));
    let user_trials = u
        .iter()
        .filter(|c| prior_region.contains(&(h.iso * c.p)))
        .count();
    let moved: std::collections::HashSet<HexCell> = walked
        .cells
        .iter()
        .map(|c| walked.prior_grid.cell_of(&(h.iso * c)))
        .collect();
    let prior_trials = p
        .iter()
        .zip(&walked.seen)
        .filter(|(_, seen)| seen.iter().any(|cell| moved.contains(cell)))
        .count();
    let agree = |from_user: bool| -> Vec<Agreement> {
        h.pairs
            .iter()
            .zip(&h.ellipse_m2)
            .map(|(&(i, j), &area)| {
                let (rate, at) = if from_user {
                    (
                        prior_region.density * compatible_fraction(&u[i], p, cfg),
                        p[j].p,
                    )
                } else {
                    (
                        user_region.density * compatible_fraction(&p[j], u, cfg),
                        u[i].p,
                    )
                };
                Agreement { rate, area, at }
            })
            .collect()
    };
    let user_side = side_false_alarms(&agree(true), user_trials, u.len(), p.len());
    let prior_side = side_false_alarms(&agree(false), prior_trials, p.len(), u.len());
    user_side.max(prior_side)
}

/// What two maps could show at best under a transform: the overlap (each map's candidates
/// inside the other's region; without a transform, every candidate) and the false-alarm count
/// if every candidate of the smaller overlap agreed with a partner at the expected distance
/// (squared Mahalanobis distance 2, the mean of χ² with two degrees of freedom).
#[derive(Debug, Clone, Copy)]
pub(super) struct BestCase {
    /// user candidates inside the prior's region
    pub(super) user_overlap: usize,
    /// prior candidates inside the user's region
    pub(super) prior_overlap: usize,
    /// the false-alarm count of the best agreement the overlap allows
    pub(super) false_alarms: f64,
}

/// Whether a transform leaves enough overlap to decide, for one pair of maps: the regions,
/// b-compatible fractions and mean covariances computed once.
pub(super) struct Overlap<'a> {
    u: &'a [Cand],
    p: &'a [Cand],
    user_region: Region,
    prior_region: Region,
    /// per candidate: (ρ·f of its chance partners, its ellipse area at the expected distance)
    u_evidence: Vec<(f64, f64)>,
    p_evidence: Vec<(f64, f64)>,
    min_inliers: usize,
}

impl<'a> Overlap<'a> {
    pub(super) fn new(u: &'a [Cand], p: &'a [Cand], cfg: &MatchConfig) -> Self {
        let margin = cfg.inlier_threshold_m;
        let (user_region, prior_region) = (Region::of(u, margin), Region::of(p, margin));
        let mean_cov =
            |c: &[Cand]| c.iter().fold(Matrix2::zeros(), |a, x| a + x.cov) / c.len().max(1) as f64;
        let evidence = |own: &[Cand], other: &[Cand], region: &Region| -> Vec<(f64, f64)> {
            let partner = mean_cov(other);
            own.iter()
                .map(|c| {
                    (
                        region.density * compatible_fraction(c, other, cfg),
                        std::f64::consts::PI
                            * 2.0
                            * (c.cov + partner).determinant().max(0.0).sqrt(),
                    )
                })
                .collect()
        };
        Overlap {
            u,
            p,
            u_evidence: evidence(u, p, &prior_region),
            p_evidence: evidence(p, u, &user_region),
            user_region,
            prior_region,
            min_inliers: cfg.min_inliers.max(3),
        }
    }

    /// The candidates of each map that `iso` puts inside the other's region (all without one).
    fn sets(&self, iso: Option<&Isometry2<f64>>) -> (Vec<usize>, Vec<usize>) {
        match iso {
            Some(iso) => {
                let inverse = iso.inverse();
                (
                    (0..self.u.len())
                        .filter(|&i| self.prior_region.contains(&(iso * self.u[i].p)))
                        .collect(),
                    (0..self.p.len())
                        .filter(|&j| self.user_region.contains(&(inverse * self.p[j].p)))
                        .collect(),
                )
            }
            None => ((0..self.u.len()).collect(), (0..self.p.len()).collect()),
        }
    }

    /// The best case under `iso` (see [`BestCase`]).
    pub(super) fn best_case(&self, iso: Option<&Isometry2<f64>>) -> BestCase {
        let (ou, op) = self.sets(iso);
        let k = ou.len().min(op.len());
        // one side's best agreement: its k most telling overlap candidates
        let side = |own: &[usize], cands: &[Cand], evidence: &[(f64, f64)], n_to: usize| {
            let mut agree: Vec<Agreement> = own
                .iter()
                .map(|&i| Agreement {
                    rate: evidence[i].0,
                    area: evidence[i].1,
                    at: cands[i].p,
                })
                .collect();
            agree.sort_by(|a, b| (a.rate * a.area).total_cmp(&(b.rate * b.area)));
            agree.truncate(k);
            side_false_alarms(&agree, own.len(), cands.len(), n_to)
        };
        let false_alarms = if k < self.min_inliers {
            f64::INFINITY
        } else {
            side(&ou, self.u, &self.u_evidence, self.p.len()).max(side(
                &op,
                self.p,
                &self.p_evidence,
                self.u.len(),
            ))
        };
        BestCase {
            user_overlap: ou.len(),
            prior_overlap: op.len(),
            false_alarms,
        }
    }

    /// The overlap under `iso` when fewer candidates than the test's minimum number of inliers
    /// overlap on either side (counts only: cheap enough for every consistent triple).
    pub(super) fn too_small(&self, iso: &Isometry2<f64>) -> Option<BestCase> {
        let inverse = iso.inverse();
        let user_overlap = self
            .u
            .iter()
            .filter(|c| self.prior_region.contains(&(iso * c.p)))
            .count();
        let prior_overlap = self
            .p
            .iter()
            .filter(|c| self.user_region.contains(&(inverse * c.p)))
            .count();
        (user_overlap.min(prior_overlap) < self.min_inliers).then_some(BestCase {
            user_overlap,
            prior_overlap,
            false_alarms: f64::INFINITY,
        })
    }
}

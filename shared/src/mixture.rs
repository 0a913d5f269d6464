//! Gaussian mixtures over a transmitter state `[x, y, b]` and their reduction.
//!
//! A transmitter is represented by a weighted sum of Gaussians (Gentner et al. 2016 §4.3). The mixture
//! grows with initialization and merging of maps, so it is reduced by moment-preserving
//! pairwise merges chosen by Runnalls' KL-type upper bound
//! `B(i,j) = ½[(wᵢ+wⱼ)·ln|Pᵢⱼ| − wᵢ·ln|Pᵢ| − wⱼ·ln|Pⱼ|]`
//! (A. R. Runnalls, "Kullback-Leibler approach to Gaussian mixture reduction", IEEE TAES 2007),
//! where `Pᵢⱼ` is the covariance of the merged pair. Each merge preserves the total weight,
//! the mixture mean and the mixture covariance exactly.
//!
//! Complexity: `reduce` on n components with target K costs O(n²) cost evaluations up front
//! and O(n) per merge (n − K merges), i.e. O(n²) overall for the 3×3 states used here.

use nalgebra::{Matrix3, Vector3};
use thiserror::Error;

/// One weighted Gaussian component.
#[derive(Debug, Clone, PartialEq)]
pub struct Component {
    /// weight, > 0
    pub weight: f64,
    /// mean `[x, y, b]` (m)
    pub mean: Vector3<f64>,
    /// covariance (m²)
    pub cov: Matrix3<f64>,
}

/// Why a mixture was refused.
#[derive(Debug, Error, PartialEq)]
pub enum MixtureError {
    /// no component
    #[error("mixture is empty")]
    Empty,
    /// the weights do not sum to a positive finite number
    #[error("mixture weights sum to {0}, cannot normalize")]
    BadWeights(f64),
}

impl Component {
    /// A component of weight `weight`.
    pub fn new(weight: f64, mean: Vector3<f64>, cov: Matrix3<f64>) -> Self {
        Component { weight, mean, cov }
    }
}

/// Moment-preserving merge of two components: weight `wᵢ+wⱼ`, the weighted mean, and the
/// covariance including the spread of the means.
pub fn merge_pair(a: &Component, b: &Component) -> Component {
    let w = a.weight + b.weight;
    let (fa, fb) = (a.weight / w, b.weight / w);
    let mean = a.mean * fa + b.mean * fb;
    let diff = a.mean - b.mean;
    let cov = a.cov * fa + b.cov * fb + diff * diff.transpose() * (fa * fb);
    Component {
        weight: w,
        mean,
        cov: symmetrize(&cov),
    }
}

/// Squared Mahalanobis distance between two estimates' x, y (means `ma`, `mb`, covariances
/// `ca`, `cb` over `[x, y, b]`) under the sum of their covariances — independent estimates of
/// one place differ by that; `None` when the sum is singular.
pub fn xy_distance2(
    (ma, ca): (&Vector3<f64>, &Matrix3<f64>),
    (mb, cb): (&Vector3<f64>, &Matrix3<f64>),
) -> Option<f64> {
    let d = (ma - mb).xy();
    let s = (ca + cb).fixed_view::<2, 2>(0, 0).into_owned();
    Some(s.cholesky()?.solve(&d).dot(&d))
}

/// Overall mean and covariance of a (not necessarily normalized) mixture.
pub fn moments(components: &[Component]) -> Option<(Vector3<f64>, Matrix3<f64>)> {
    let total: f64 = components.iter().map(|c| c.weight).sum();
    if components.is_empty() || total.is_nan() || total <= 0.0 {
        return None;
    }
    let mean = components
        .iter()
        .fold(Vector3::zeros(), |acc, c| acc + c.mean * (c.weight / total));
    let cov = components.iter().fold(Matrix3::zeros(), |acc, c| {
        let d = c.mean - mean;
        acc + (c.cov + d * d.transpose()) * (c.weight / total)
    });
    Some((mean, symmetrize(&cov)))
}

/// Normalizes weights to sum to one.
pub fn normalize(components: &mut [Component]) -> Result<(), MixtureError> {
    if components.is_empty() {
        return Err(MixtureError::Empty);
    }
    let total: f64 = components.iter().map(|c| c.weight).sum();
    if !(total.is_finite() && total > 0.0) {
        return Err(MixtureError::BadWeights(total));
    }
    for c in components.iter_mut() {
        c.weight /= total;
    }
    Ok(())
}

/// Makes a matrix exactly symmetric (averages it with its transpose).
pub fn symmetrize(m: &Matrix3<f64>) -> Matrix3<f64> {
    (m + m.transpose()) * 0.5
}

fn ln_det(m: &Matrix3<f64>) -> f64 {
    // Covariances here are SPD; a determinant that underflows is clamped so the cost stays finite.
    m.determinant().max(f64::MIN_POSITIVE).ln()
}

/// Runnalls' merge cost of a pair (see the module doc).
pub fn runnalls_cost(a: &Component, b: &Component) -> f64 {
    let merged = merge_pair(a, b);
    0.5 * (merged.weight * ln_det(&merged.cov)
        - a.weight * ln_det(&a.cov)
        - b.weight * ln_det(&b.cov))
}

/// Reduces the mixture to at most `max_components` by repeatedly merging the pair of least
/// Runnalls cost. A mixture that already has at most `max_components` is returned unchanged.
/// Deterministic: ties are broken by component order.
pub fn reduce(components: &[Component], max_components: usize) -> Vec<Component> {
    let max_components = max_components.max(1);
    if components.len() <= max_components {
        return components.to_vec();
    }
    let mut slots: Vec<Option<Component>> = components.iter().cloned().map(Some).collect();
    let n = slots.len();
    // cost[i][j] for i < j; recomputed only for the row/column of a merged component.
    let mut cost = vec![f64::INFINITY; n * n];
    for i in 0..n {
        for j in (i + 1)..n {
            cost[i * n + j] = runnalls_cost(slots[i].as_ref().unwrap(), slots[j].as_ref().unwrap());
        }
    }
    let mut alive = n;
    while alive > max_components {
        let mut best = (f64::INFINITY, 0, 0);
        for i in 0..n {
            if slots[i].is_none() {
                continue;
            }
            for j in (i + 1)..n {
                if slots[j].is_some() && cost[i * n + j] < best.0 {
                    best = (cost[i * n + j], i, j);
                }
            }
        }
        let (_, i, j) = best;
        if i == j {
            // All remaining costs are NaN/inf (degenerate input): merge the first two alive.
            let mut it = (0..n).filter(|&k| slots[k].is_some());
            let (a, b) = (it.next().unwrap(), it.next().unwrap());
            best = (0.0, a, b);
        }
        let (_, i, j) = best;
        let merged = merge_pair(slots[i].as_ref().unwrap(), slots[j].as_ref().unwrap());
        slots[i] = Some(merged);
        slots[j] = None;
        alive -= 1;
        for k in 0..n {
            if k == i || slots[k].is_none() {
                continue;
            }
            let (lo, hi) = if k < i { (k, i) } else { (i, k) };
            cost[lo * n + hi] =
                runnalls_cost(slots[lo].as_ref().unwrap(), slots[hi].as_ref().unwrap());
        }
    }
    slots.into_iter().flatten().collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn spd(a: [f64; 6]) -> Matrix3<f64> {
        let l = Matrix3::new(
            a[0].abs() + 0.05,
            0.0,
            0.0,
            a[1],
            a[2].abs() + 0.05,
            0.0,
            a[3],
            a[4],
            a[5].abs() + 0.05,
        );
        l * l.transpose()
    }

    fn comp_strategy() -> impl Strategy<Value = Component> {
        (
            0.01f64..1.0,
            prop::array::uniform3(-50.0f64..50.0),
            prop::array::uniform6(-2.0f64..2.0),
        )
            .prop_map(|(w, m, c)| Component::new(w, Vector3::from(m), spd(c)))
    }

    fn close(a: &Matrix3<f64>, b: &Matrix3<f64>, tol: f64) -> bool {
        (a - b).abs().max() <= tol * (1.0 + b.abs().max())
    }

    proptest! {
        #[test]
        fn merge_pair_preserves_moments(a in comp_strategy(), b in comp_strategy()) {
            let before = moments(&[a.clone(), b.clone()]).unwrap();
            let m = merge_pair(&a, &b);
            prop_assert!((m.weight - (a.weight + b.weight)).abs() < 1e-12);
            let after = moments(std::slice::from_ref(&m)).unwrap();
            prop_assert!((before.0 - after.0).norm() < 1e-9 * (1.0 + before.0.norm()));
            prop_assert!(close(&before.1, &after.1, 1e-9));
        }

        #[test]
        fn reduce_preserves_weight_mean_cov(comps in prop::collection::vec(comp_strategy(), 1..40), k in 1usize..10) {
            let reduced = reduce(&comps, k);
            prop_assert!(reduced.len() <= k.max(1));
            let w0: f64 = comps.iter().map(|c| c.weight).sum();
            let w1: f64 = reduced.iter().map(|c| c.weight).sum();
            prop_assert!((w0 - w1).abs() < 1e-9 * w0);
            let (m0, p0) = moments(&comps).unwrap();
            let (m1, p1) = moments(&reduced).unwrap();
            prop_assert!((m0 - m1).norm() < 1e-8 * (1.0 + m0.norm()));
            prop_assert!(close(&p0, &p1, 1e-8));
            for c in &reduced {
                prop_assert!(c.cov.cholesky().is_some());
            }
        }

        #[test]
        fn reduce_keeps_small_mixtures(comps in prop::collection::vec(comp_strategy(), 1..8)) {
            let reduced = reduce(&comps, 8);
            prop_assert_eq!(reduced, comps);
        }
    }

    #[test]
    fn reduce_merges_the_close_pair_first() {
        let i = Matrix3::identity();
        let comps = vec![
            Component::new(0.3, Vector3::new(0.0, 0.0, 0.0), i),
            Component::new(0.3, Vector3::new(0.1, 0.0, 0.0), i),
            Component::new(0.4, Vector3::new(30.0, 0.0, 0.0), i),
        ];
        let r = reduce(&comps, 2);
        assert_eq!(r.len(), 2);
        assert!((r[0].weight - 0.6).abs() < 1e-12);
        assert!((r[1].mean.x - 30.0).abs() < 1e-12);
    }
}

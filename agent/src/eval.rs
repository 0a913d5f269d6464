//! Evaluation: per-snapshot errors of a filter run against ground truth (MAE of Ulmschneider et al. 2021
//! eq. 27, RMSE, error of the weighted-mean estimate) and the map error as OSPA (Li et al. 2019
//! eq. 43) between estimated and true transmitter states.

use echomap_shared::TransmitterMap;
use echomap_shared::log::GroundTruth;
use nalgebra::Vector3;
use pathfinding::prelude::{Matrix, kuhn_munkres_min};

/// One row of `track.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackRow {
    pub t: f64,
    pub x: f64,
    pub y: f64,
    pub traveled_m: f64,
    pub truth: Option<TruthCols>,
    pub ess: f64,
    pub transmitters: f64,
    pub components: f64,
    /// ln p(z₁..z_t) of the filter the row comes from ([`crate::filter::StepStats`])
    pub log_evidence: f64,
    /// with `--prior-fallback`: whether the row is the filter with the prior's (true) or the
    /// one without (false); None otherwise
    pub with_prior: Option<bool>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthCols {
    pub true_x: f64,
    pub true_y: f64,
    /// Σ wᵢ‖p − pᵢ‖ (Ulmschneider et al. 2021 eq. 27)
    pub mae_m: f64,
    /// √(Σ wᵢ‖p − pᵢ‖²)
    pub rmse_m: f64,
    /// ‖p − p̂‖ of the weighted-mean estimate p̂
    pub err_m: f64,
    /// normalized estimation error squared of the truth under the particle cloud
    /// ([`crate::filter::Filter::position_nees`]); ≤ 5.991 inside the 95 % ellipse
    pub nees: f64,
    /// ln p(z_t | true track) − ln p(z_t | particles): the snapshot's evidence for the true
    /// track, mapped by itself, over the filter's ([`crate::filter::truth`])
    pub truth_ll_ratio: f64,
}

pub fn track_csv(rows: &[TrackRow]) -> String {
    let mut s = String::from(
        "t,x,y,traveled_m,true_x,true_y,mae_m,rmse_m,err_m,nees,ess,transmitters,components,log_evidence,model,truth_ll_ratio\n",
    );
    for r in rows {
        let truth = match r.truth {
            Some(c) => format!(
                "{},{},{},{},{},{}",
                c.true_x, c.true_y, c.mae_m, c.rmse_m, c.err_m, c.nees
            ),
            None => ",,,,,".to_string(),
        };
        let model = match r.with_prior {
            Some(true) => "prior",
            Some(false) => "alone",
            None => "",
        };
        let ratio = r
            .truth
            .map(|c| c.truth_ll_ratio.to_string())
            .unwrap_or_default();
        s.push_str(&format!(
            "{},{},{},{},{},{},{},{},{},{},{}\n",
            r.t,
            r.x,
            r.y,
            r.traveled_m,
            truth,
            r.ess,
            r.transmitters,
            r.components,
            r.log_evidence,
            model,
            ratio
        ));
    }
    s
}

/// OSPA distance of order `p` with cut-off `c` between two point sets (Li et al. 2019 eq. 43):
/// `( (1/n)·(min_π Σᵢ d_c(xᵢ, y_π(i))^p + c^p·(n − m)) )^(1/p)` for m ≤ n, with
/// `d_c = min(c, ‖x − y‖)`; 0 for two empty sets.
pub fn ospa(a: &[Vector3<f64>], b: &[Vector3<f64>], c: f64, p: f64) -> f64 {
    let (x, y) = if a.len() <= b.len() { (a, b) } else { (b, a) };
    let (m, n) = (x.len(), y.len());
    if n == 0 {
        return 0.0;
    }
    let assignment = if m == 0 {
        0.0
    } else {
        // integer costs in micro-units for the Hungarian algorithm
        let scale = 1e6;
        let cost = Matrix::from_fn(m, n, |(i, j)| {
            ((x[i] - y[j]).norm().min(c).powf(p) * scale).round() as i64
        });
        let (total, _) = kuhn_munkres_min(&cost);
        total as f64 / scale
    };
    ((assignment + c.powf(p) * (n - m) as f64) / n as f64).powf(1.0 / p)
}

/// The map error of a user map against the true virtual transmitters: OSPA (c = 5 m,
/// p = 1) in `[x, y, b]` between the means of the well-converged transmitters (existence ≥ 0.5,
/// position std ≤ 2 m) and the distinct true states of every track id of the run.
pub fn map_ospa(map: &TransmitterMap, truth: &GroundTruth) -> (f64, usize, usize) {
    let est: Vec<Vector3<f64>> = map
        .transmitters()
        .iter()
        .filter(|t| t.existence >= 0.5)
        .filter_map(|t| {
            let (m, p) = t.moments();
            ((p[(0, 0)] + p[(1, 1)]).sqrt() <= 2.0).then_some(m)
        })
        .collect();
    let mut truths: Vec<Vector3<f64>> = Vec::new();
    for t in &truth.transmitters {
        let v = Vector3::from(t.state);
        if !truths.iter().any(|u| (u - v).norm() < 1e-6) {
            truths.push(v);
        }
    }
    (ospa(&est, &truths, 5.0, 1.0), est.len(), truths.len())
}

/// Percentile (linear interpolation) of unsorted values, q in [0, 1].
pub fn percentile(values: &[f64], q: f64) -> f64 {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let pos = q.clamp(0.0, 1.0) * (v.len() - 1) as f64;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    v[lo] + (v[hi] - v[lo]) * (pos - lo as f64)
}

/// Exact two-sided p-value of the Wilcoxon signed-rank test that paired differences `d` are
/// symmetric about 0: zeros (and non-finite values) are dropped, tied |d| get their mid-rank,
/// and the null distribution of the positive rank sum is counted over all 2ⁿ sign patterns
/// (in doubled ranks, so mid-ranks stay integers). None without a non-zero difference.
pub fn signed_rank_p(d: &[f64]) -> Option<f64> {
    let mut a: Vec<f64> = d
        .iter()
        .copied()
        .filter(|x| x.is_finite() && *x != 0.0)
        .collect();
    if a.is_empty() {
        return None;
    }
    a.sort_by(|x, y| x.abs().total_cmp(&y.abs()));
    // doubled mid-ranks: a run of ties at 1-based positions i..=j gets i + j
    let mut ranks = vec![0usize; a.len()];
    let mut i = 0;
    while i < a.len() {
        let mut j = i;
        while j + 1 < a.len() && a[j + 1].abs() == a[i].abs() {
            j += 1;
        }
        ranks[i..=j].fill(i + j + 2);
        i = j + 1;
    }
    let total: usize = ranks.iter().sum();
    let observed: usize = a
        .iter()
        .zip(&ranks)
        .filter(|(x, _)| **x > 0.0)
        .map(|(_, r)| r)
        .sum();
    // ways[s]: sign patterns whose positive doubled-rank sum is s
    let mut ways = vec![0.0f64; total + 1];
    ways[0] = 1.0;
    for &r in &ranks {
        for s in (r..=total).rev() {
            ways[s] += ways[s - r];
        }
    }
    let dev = |s: usize| (2 * s).abs_diff(total);
    let extreme: f64 = (0..=total)
        .filter(|&s| dev(s) >= dev(observed))
        .map(|s| ways[s])
        .sum();
    Some((extreme / 2f64.powi(a.len() as i32)).min(1.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ospa_basics() {
        let a = vec![Vector3::new(0.0, 0.0, 0.0), Vector3::new(10.0, 0.0, 0.0)];
        assert_eq!(ospa(&a, &a, 5.0, 1.0), 0.0);
        // one point shifted by 1 m: mean error 0.5
        let b = vec![Vector3::new(0.0, 1.0, 0.0), Vector3::new(10.0, 0.0, 0.0)];
        assert!((ospa(&a, &b, 5.0, 1.0) - 0.5).abs() < 1e-6);
        // a missing point costs c: (0 + 5)/2
        assert!((ospa(&a[..1], &a, 5.0, 1.0) - 2.5).abs() < 1e-6);
        // assignment is optimal, not greedy (swapped order)
        let c = vec![Vector3::new(10.0, 0.0, 0.0), Vector3::new(0.0, 0.0, 0.0)];
        assert!(ospa(&a, &c, 5.0, 1.0) < 1e-9);
        assert_eq!(ospa(&[], &[], 5.0, 1.0), 0.0);
    }

    #[test]
    fn signed_rank_p_counts_the_sign_patterns_exactly() {
        // five positive differences: only all-positive and all-negative are as extreme
        assert!((signed_rank_p(&[0.1, 0.2, 0.3, 0.4, 0.5]).unwrap() - 2.0 / 32.0).abs() < 1e-12);
        assert!((signed_rank_p(&[-0.1, -0.2, -0.3]).unwrap() - 2.0 / 8.0).abs() < 1e-12);
        // ranks 1..4, positive sum 1 + 4 = 5 = the mean: every pattern is as extreme
        assert_eq!(signed_rank_p(&[0.1, -0.2, -0.3, 0.4]).unwrap(), 1.0);
        // positive sum 4 (ranks 1..4, mean 5): all but the 2 patterns summing to 5 exactly
        // ({1, 4} and {2, 3}) are at least as far from the mean
        assert!((signed_rank_p(&[-0.1, -0.2, -0.3, 0.4]).unwrap() - 14.0 / 16.0).abs() < 1e-12);
        // ties share the mid-rank: |d| = 1, 1, 2 → ranks 1.5, 1.5, 3; positive sum 1.5 of 6
        // (patterns with sums 0, 1.5, 1.5, 4.5, 4.5, 6 of 8 are as far from 3)
        assert!((signed_rank_p(&[1.0, -1.0, -2.0]).unwrap() - 6.0 / 8.0).abs() < 1e-12);
        // zeros are dropped; nothing left is no test
        assert!((signed_rank_p(&[0.0, 0.1, 0.2]).unwrap() - 0.5).abs() < 1e-12);
        assert_eq!(signed_rank_p(&[0.0, f64::NAN]), None);
        // twenty runs all one way: 2 / 2^20
        let d: Vec<f64> = (1..=20).map(|k| -(k as f64)).collect();
        assert!((signed_rank_p(&d).unwrap() - 2.0 / 1048576.0).abs() < 1e-15);
    }

    #[test]
    fn percentiles() {
        let v = [5.0, 1.0, 3.0, 2.0, 4.0];
        assert_eq!(percentile(&v, 0.5), 3.0);
        assert_eq!(percentile(&v, 0.0), 1.0);
        assert_eq!(percentile(&v, 1.0), 5.0);
        assert!((percentile(&v, 0.95) - 4.8).abs() < 1e-12);
    }
}

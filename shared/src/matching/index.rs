//! Spatial indexes of the prior's candidates: a uniform grid for radius queries and the
//! pairwise distances binned for the distance-consistency search (Ulmschneider et al. 2021
//! eq. 17).

use super::*;

/// Uniform grid over the prior candidates' bounding box for radius queries, stored as
/// compressed rows (cell offsets into one index array). The cell is at least the query
/// radius and grows when the box would need more than a few cells per candidate.
pub(super) struct Grid {
    pub(super) cell: f64,
    pub(super) x0: f64,
    pub(super) y0: f64,
    pub(super) nx: usize,
    pub(super) ny: usize,
    /// `items[start[c]..start[c + 1]]` are the candidates in cell c, in index order
    pub(super) start: Vec<u32>,
    pub(super) items: Vec<u32>,
}

/// Bounding box (x0, y0, x1, y1) of candidate means; all zero for none.
pub(super) fn bounds(cands: &[Cand]) -> (f64, f64, f64, f64) {
    if cands.is_empty() {
        return (0.0, 0.0, 0.0, 0.0);
    }
    cands.iter().fold(
        (
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ),
        |(x0, y0, x1, y1), c| (x0.min(c.p.x), y0.min(c.p.y), x1.max(c.p.x), y1.max(c.p.y)),
    )
}

impl Grid {
    pub(super) fn new(cands: &[Cand], cell: f64) -> Self {
        let (x0, y0, x1, y1) = bounds(cands);
        let max_cells = 4 * cands.len() + 1024;
        let mut cell = cell;
        let dims = |cell: f64| {
            (
                ((x1 - x0) / cell).floor() as usize + 1,
                ((y1 - y0) / cell).floor() as usize + 1,
            )
        };
        while {
            let (nx, ny) = dims(cell);
            nx.saturating_mul(ny) > max_cells
        } {
            cell *= 2.0;
        }
        let (nx, ny) = dims(cell);
        let key = |p: &Point2<f64>| {
            let kx = (((p.x - x0) / cell).floor() as usize).min(nx - 1);
            let ky = (((p.y - y0) / cell).floor() as usize).min(ny - 1);
            ky * nx + kx
        };
        let mut start = vec![0u32; nx * ny + 1];
        for c in cands {
            start[key(&c.p) + 1] += 1;
        }
        for k in 1..start.len() {
            start[k] += start[k - 1];
        }
        let mut fill = start.clone();
        let mut items = vec![0u32; cands.len()];
        for (i, c) in cands.iter().enumerate() {
            let k = key(&c.p);
            items[fill[k] as usize] = i as u32;
            fill[k] += 1;
        }
        Grid {
            cell,
            x0,
            y0,
            nx,
            ny,
            start,
            items,
        }
    }

    /// Indices of the candidates within `r` (≤ the cell size) of `p`, in a fixed order.
    pub(super) fn near(&self, p: &Point2<f64>, r: f64, cands: &[Cand], out: &mut Vec<usize>) {
        out.clear();
        let fx = ((p.x - self.x0) / self.cell).floor();
        let fy = ((p.y - self.y0) / self.cell).floor();
        if !(fx >= -1.0 && fy >= -1.0 && fx <= self.nx as f64 && fy <= self.ny as f64) {
            return; // farther than one cell from the box (or not finite)
        }
        let (kx, ky) = (fx as i64, fy as i64);
        let r2 = r * r;
        for y in (ky - 1).max(0)..=(ky + 1).min(self.ny as i64 - 1) {
            for x in (kx - 1).max(0)..=(kx + 1).min(self.nx as i64 - 1) {
                let c = y as usize * self.nx + x as usize;
                for &i in &self.items[self.start[c] as usize..self.start[c + 1] as usize] {
                    if (cands[i as usize].p - p).norm_squared() <= r2 {
                        out.push(i as usize);
                    }
                }
            }
        }
    }
}

/// All pairs of prior candidates, counting-sorted into distance bins of width ≥ the distance
/// tolerance: building is O(P²) without a sort, and a lookup sorts only its window.
pub(super) struct PairBins {
    pub(super) width: f64,
    /// `pairs[start[b]..start[b + 1]]` are the pairs of bin b: (distance, i, j), i < j
    pub(super) start: Vec<u32>,
    pub(super) pairs: Vec<(f64, u32, u32)>,
}

impl PairBins {
    /// At most this many bins (a far outlier widens them instead of allocating more).
    pub(super) const MAX_BINS: usize = 1 << 16;

    pub(super) fn new(p: &[Cand], tol: f64) -> Self {
        let mut all = Vec::with_capacity(p.len() * p.len().saturating_sub(1) / 2);
        let mut max_d: f64 = 0.0;
        for i in 0..p.len() {
            for j in (i + 1)..p.len() {
                let d = (p[i].p - p[j].p).norm();
                max_d = max_d.max(d);
                all.push((d, i as u32, j as u32));
            }
        }
        let width = tol.max(1e-3).max(max_d / (Self::MAX_BINS - 1) as f64);
        let bins = (max_d / width) as usize + 1;
        let bin = |d: f64| ((d / width) as usize).min(bins - 1);
        let mut start = vec![0u32; bins + 1];
        for &(d, _, _) in &all {
            start[bin(d) + 1] += 1;
        }
        for b in 1..start.len() {
            start[b] += start[b - 1];
        }
        let mut fill = start.clone();
        let mut pairs = vec![(0.0, 0, 0); all.len()];
        for x in all {
            let b = bin(x.0);
            pairs[fill[b] as usize] = x;
            fill[b] += 1;
        }
        PairBins {
            width,
            start,
            pairs,
        }
    }

    /// The pairs whose distance is within `tol` of `d`, nearest first (ties by index).
    pub(super) fn window(&self, d: f64, tol: f64, out: &mut Vec<(f64, u32, u32)>) {
        out.clear();
        let bins = self.start.len() - 1;
        let bin = |x: f64| ((x.max(0.0) / self.width) as usize).min(bins - 1);
        let (lo, hi) = (bin(d - tol), bin(d + tol));
        let range = self.start[lo] as usize..self.start[hi + 1] as usize;
        out.extend(
            self.pairs[range]
                .iter()
                .filter(|x| (x.0 - d).abs() <= tol)
                .map(|&(x, i, j)| ((x - d).abs(), i, j)),
        );
        out.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    }
}

//! Transmitter visibility on a hex grid (Ulmschneider et al. 2021 eq. 11–12): per transmitter identity and
//! hexagon, counters of how often it was seen (C) and not seen (C̄) from there; with the
//! prior pseudo-counts (ν, ν̄) they form Beta(C + ν, C̄ + ν̄).
//!
//! Departure from the paper, for memory: the counters are kept once for the filter, along
//! the particle-weighted mean track, not per particle (4000 particles × 100 transmitters ×
//! visited hexagons would not fit); a transmitter counts as seen when the track the
//! majority of the particle weight binds to it is detected.

use echomap_shared::{Beta, HexCell, HexGrid};
use nalgebra::Point2;
use std::collections::BTreeMap;

#[derive(Debug, Clone)]
pub struct Visibility {
    grid: HexGrid,
    prior: (f64, f64),
    /// per identity: cell → (seen, not seen)
    counts: Vec<BTreeMap<HexCell, (f64, f64)>>,
}

impl Visibility {
    pub fn new(hex_size_m: f64, prior: (f64, f64)) -> Self {
        Visibility {
            grid: HexGrid::new(hex_size_m),
            prior,
            counts: Vec::new(),
        }
    }

    pub fn grid(&self) -> &HexGrid {
        &self.grid
    }

    fn slot(&mut self, identity: usize) -> &mut BTreeMap<HexCell, (f64, f64)> {
        if self.counts.len() <= identity {
            self.counts.resize_with(identity + 1, BTreeMap::new);
        }
        &mut self.counts[identity]
    }

    pub fn observe(&mut self, identity: usize, at: &Point2<f64>, seen: bool) {
        let cell = self.grid.cell_of(at);
        let e = self.slot(identity).entry(cell).or_insert((0.0, 0.0));
        if seen {
            e.0 += 1.0;
        } else {
            e.1 += 1.0;
        }
    }

    /// Posterior mean visibility E\[M\] = (C + ν)/(C + C̄ + ν + ν̄) of `identity` from `cell`.
    pub fn probability(&self, identity: usize, cell: HexCell) -> f64 {
        let (c, cbar) = self
            .counts
            .get(identity)
            .and_then(|m| m.get(&cell))
            .copied()
            .unwrap_or((0.0, 0.0));
        (c + self.prior.0) / (c + cbar + self.prior.0 + self.prior.1)
    }

    /// Evidence counts of one identity, for the exported map.
    pub fn cells(&self, identity: usize) -> BTreeMap<HexCell, Beta> {
        self.counts
            .get(identity)
            .map(|m| {
                m.iter()
                    .map(|(k, v)| {
                        (
                            *k,
                            Beta {
                                alpha: v.0,
                                beta: v.1,
                            },
                        )
                    })
                    .collect()
            })
            .unwrap_or_default()
    }
}

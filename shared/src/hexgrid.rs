//! Hexagonal visibility grid (Ulmschneider et al. 2021 §II, eq. 11–12): the plane is tiled by pointy-top
//! hexagons of circumradius `hex_size_m`, addressed by axial coordinates `(q, r)`.
//! Point ↔ cell conversion is delegated to the `hexx` crate (f32 internally: at 10 km from
//! the origin its resolution is still about a millimetre, far below any cell size used here).

use hexx::{Hex, HexLayout, Vec2};
use nalgebra::Point2;
use serde::{Deserialize, Serialize};

/// Axial coordinates of one hexagon.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct HexCell {
    /// axial column
    pub q: i32,
    /// axial row
    pub r: i32,
}

/// A pointy-top hex grid with its origin at the frame's origin.
#[derive(Debug, Clone)]
pub struct HexGrid {
    size_m: f64,
    layout: HexLayout,
}

impl HexGrid {
    /// `size_m` is the circumradius (centre to corner) of every hexagon; must be > 0.
    pub fn new(size_m: f64) -> Self {
        assert!(
            size_m.is_finite() && size_m > 0.0,
            "hex size must be positive"
        );
        HexGrid {
            size_m,
            layout: HexLayout::pointy().with_hex_size(size_m as f32),
        }
    }

    /// circumradius of a hexagon (m)
    pub fn size_m(&self) -> f64 {
        self.size_m
    }

    /// The cell containing `p`.
    pub fn cell_of(&self, p: &Point2<f64>) -> HexCell {
        let h = self
            .layout
            .world_pos_to_hex(Vec2::new(p.x as f32, p.y as f32));
        HexCell { q: h.x, r: h.y }
    }

    /// Centre of `cell`, computed in f64 (pointy-top axial → Cartesian).
    pub fn centre(&self, cell: HexCell) -> Point2<f64> {
        let sqrt3 = 3f64.sqrt();
        let (q, r) = (f64::from(cell.q), f64::from(cell.r));
        Point2::new(self.size_m * sqrt3 * (q + r / 2.0), self.size_m * 1.5 * r)
    }

    /// Hex distance (number of steps) between two cells.
    pub fn distance(a: HexCell, b: HexCell) -> u32 {
        Hex::new(a.q, a.r).unsigned_distance_to(Hex::new(b.q, b.r))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn centre_agrees_with_hexx() {
        let g = HexGrid::new(2.0);
        for q in -5..5 {
            for r in -5..5 {
                let c = g.centre(HexCell { q, r });
                let w = g.layout.hex_to_world_pos(Hex::new(q, r));
                assert!((c.x - f64::from(w.x)).abs() < 1e-4 && (c.y - f64::from(w.y)).abs() < 1e-4);
                assert_eq!(g.cell_of(&c), HexCell { q, r });
            }
        }
    }

    proptest! {
        /// A point is never farther from its cell's centre than the circumradius, and no
        /// neighbouring centre is closer (that is what "containing cell" means).
        #[test]
        fn point_lies_in_its_cell(x in -500.0f64..500.0, y in -500.0f64..500.0, size in 0.5f64..10.0) {
            let g = HexGrid::new(size);
            let p = Point2::new(x, y);
            let cell = g.cell_of(&p);
            let d = (g.centre(cell) - p).norm();
            prop_assert!(d <= size * (1.0 + 1e-4));
            for n in Hex::new(cell.q, cell.r).all_neighbors() {
                let dn = (g.centre(HexCell { q: n.x, r: n.y }) - p).norm();
                prop_assert!(dn >= d - 1e-3 * size);
            }
        }
    }
}

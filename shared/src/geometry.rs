//! Planar geometry helpers: angle wrapping and the JSON form of a proper 2D rigid motion.
//!
//! echomap frames are related by rotations and translations only (det R = +1, no scale);
//! `nalgebra::Isometry2` is the in-memory type, [`Transform2`] its wire form
//! `{"angle_rad": θ, "translation": [x, y]}` with `p_to = R(θ)·p_from + t`.

use nalgebra::{Isometry2, Matrix2, Vector2};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Wraps an angle to (−π, π].
#[inline]
pub fn wrap_angle(angle_rad: f64) -> f64 {
    // Fast path, inlined into the filter's hot loop: the hot callers pass angles within one
    // turn of the range.
    if angle_rad > -PI && angle_rad <= PI {
        return angle_rad;
    }
    wrap_angle_slow(angle_rad)
}

#[cold]
fn wrap_angle_slow(angle_rad: f64) -> f64 {
    if angle_rad > -3.0 * PI && angle_rad <= 3.0 * PI {
        let a = if angle_rad > PI {
            angle_rad - 2.0 * PI
        } else {
            angle_rad + 2.0 * PI
        };
        if a > -PI && a <= PI {
            return a;
        }
    }
    let mut a = angle_rad.rem_euclid(2.0 * PI);
    if a > PI {
        a -= 2.0 * PI;
    }
    // rem_euclid maps −π to π already; guard the tiny negative zero case.
    if a <= -PI { a + 2.0 * PI } else { a }
}

/// 2×2 rotation matrix for `angle_rad`.
pub fn rotation(angle_rad: f64) -> Matrix2<f64> {
    let (s, c) = angle_rad.sin_cos();
    Matrix2::new(c, -s, s, c)
}

/// Wire form of a 2D rigid transform: `p_to = R(angle_rad)·p_from + translation`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(deny_unknown_fields)]
pub struct Transform2 {
    /// rotation angle θ (rad, counter-clockwise)
    pub angle_rad: f64,
    /// translation t (m): p_to = R(θ)·p_from + t
    pub translation: [f64; 2],
}

impl Transform2 {
    /// the identity transform
    pub const IDENTITY: Transform2 = Transform2 {
        angle_rad: 0.0,
        translation: [0.0, 0.0],
    };

    /// as a nalgebra isometry
    pub fn to_isometry(self) -> Isometry2<f64> {
        Isometry2::new(
            Vector2::new(self.translation[0], self.translation[1]),
            self.angle_rad,
        )
    }

    /// from a nalgebra isometry
    pub fn from_isometry(iso: &Isometry2<f64>) -> Self {
        Transform2 {
            angle_rad: wrap_angle(iso.rotation.angle()),
            translation: [iso.translation.vector.x, iso.translation.vector.y],
        }
    }

    /// whether angle and translation are finite
    pub fn is_finite(&self) -> bool {
        self.angle_rad.is_finite() && self.translation.iter().all(|v| v.is_finite())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn wrap_angle_edges() {
        assert_eq!(wrap_angle(PI), PI);
        assert!((wrap_angle(-PI) - PI).abs() < 1e-15);
        assert!((wrap_angle(3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap_angle(-0.5) + 0.5).abs() < 1e-15);
        assert!((wrap_angle(2.0 * PI + 0.25) - 0.25).abs() < 1e-12);
    }

    proptest! {
        #[test]
        fn wrap_angle_range(a in -100.0f64..100.0) {
            let w = wrap_angle(a);
            prop_assert!(w > -PI && w <= PI);
            let k = ((a - w) / (2.0 * PI)).round();
            prop_assert!((a - w - k * 2.0 * PI).abs() < 1e-9);
        }

        #[test]
        fn transform_roundtrip(angle in -PI..PI, x in -1e3f64..1e3, y in -1e3f64..1e3) {
            let t = Transform2 { angle_rad: angle, translation: [x, y] };
            let back = Transform2::from_isometry(&t.to_isometry());
            prop_assert!((wrap_angle(back.angle_rad - angle)).abs() < 1e-12);
            prop_assert!((back.translation[0] - x).abs() < 1e-9);
            prop_assert!((back.translation[1] - y).abs() < 1e-9);
        }
    }
}

//! User trajectories: a waypoint polyline walked at constant speed, its corners rounded by
//! circular arcs so that the heading — and so the gyroscope — changes continuously.

use echomap_shared::wrap_angle;
use nalgebra::{Point2, Vector2};

#[derive(Debug, Clone)]
enum Piece {
    Line {
        start: Point2<f64>,
        heading: f64,
        len: f64,
    },
    Arc {
        center: Point2<f64>,
        radius: f64,
        start_heading: f64,
        turn: f64,
        len: f64,
    },
}

impl Piece {
    fn len(&self) -> f64 {
        match self {
            Piece::Line { len, .. } | Piece::Arc { len, .. } => *len,
        }
    }

    fn pose(&self, s: f64) -> (Point2<f64>, f64) {
        match *self {
            Piece::Line { start, heading, .. } => (
                start + Vector2::new(heading.cos(), heading.sin()) * s,
                heading,
            ),
            Piece::Arc {
                center,
                radius,
                start_heading,
                turn,
                len,
            } => {
                let frac = if len > 0.0 { s / len } else { 1.0 };
                let heading = start_heading + turn * frac;
                // The centre lies to the left (turn > 0) or right of the direction of travel.
                let side = turn.signum();
                let radial = heading - side * std::f64::consts::FRAC_PI_2;
                (
                    center + Vector2::new(radial.cos(), radial.sin()) * radius,
                    wrap_angle(heading),
                )
            }
        }
    }
}

/// A smooth trajectory parameterized by arc length.
#[derive(Debug, Clone)]
pub struct Trajectory {
    pieces: Vec<Piece>,
    length: f64,
}

impl Trajectory {
    /// Builds the trajectory; corners get arcs of `turn_radius_m`, shrunk where the adjacent
    /// segments are too short to hold them. Waypoints must be distinct consecutive points.
    pub fn new(waypoints: &[[f64; 2]], turn_radius_m: f64) -> Self {
        let pts: Vec<Point2<f64>> = waypoints.iter().map(|w| Point2::new(w[0], w[1])).collect();
        let n = pts.len();
        assert!(n >= 2, "validated scenarios have at least two waypoints");
        let dirs: Vec<Vector2<f64>> = (1..n).map(|i| (pts[i] - pts[i - 1]).normalize()).collect();
        let seg_len: Vec<f64> = (1..n).map(|i| (pts[i] - pts[i - 1]).norm()).collect();
        // Tangent length cut from each end of every segment.
        let mut cut = vec![0.0; n];
        let mut turns = vec![0.0; n];
        for i in 1..n - 1 {
            let turn = wrap_angle(dirs[i].y.atan2(dirs[i].x) - dirs[i - 1].y.atan2(dirs[i - 1].x));
            turns[i] = turn;
            let half = turn.abs() / 2.0;
            if turn.abs() < 1e-9 {
                continue;
            }
            let want = turn_radius_m * half.tan();
            cut[i] = want.min(0.5 * seg_len[i - 1]).min(0.5 * seg_len[i]);
        }
        let mut pieces = Vec::new();
        for i in 0..n - 1 {
            let heading = dirs[i].y.atan2(dirs[i].x);
            let start = pts[i] + dirs[i] * cut[i];
            let len = seg_len[i] - cut[i] - cut[i + 1];
            if len > 1e-12 {
                pieces.push(Piece::Line {
                    start,
                    heading,
                    len,
                });
            }
            let j = i + 1;
            if j < n - 1 && cut[j] > 0.0 {
                let turn = turns[j];
                let radius = cut[j] / (turn.abs() / 2.0).tan();
                let arc_start = pts[j] - dirs[i] * cut[j];
                let left = Vector2::new(-dirs[i].y, dirs[i].x) * turn.signum();
                pieces.push(Piece::Arc {
                    center: arc_start + left * radius,
                    radius,
                    start_heading: heading,
                    turn,
                    len: radius * turn.abs(),
                });
            }
        }
        let length = pieces.iter().map(Piece::len).sum();
        Trajectory { pieces, length }
    }

    pub fn length_m(&self) -> f64 {
        self.length
    }

    /// Position and heading (rad, wrapped) after `s` metres (clamped to the ends).
    pub fn pose_at(&self, s: f64) -> (Point2<f64>, f64) {
        let mut s = s.clamp(0.0, self.length);
        for p in &self.pieces {
            if s <= p.len() {
                return p.pose(s);
            }
            s -= p.len();
        }
        let last = self.pieces.last().expect("a trajectory has pieces");
        last.pose(last.len())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;
    use std::f64::consts::FRAC_PI_2;

    #[test]
    fn rounded_corner_is_continuous_and_shorter() {
        let t = Trajectory::new(&[[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]], 2.0);
        // 20 m polyline minus 2·r plus a quarter circle of r = 2.
        assert_relative_eq!(t.length_m(), 20.0 - 4.0 + FRAC_PI_2 * 2.0, epsilon = 1e-9);
        let (p0, h0) = t.pose_at(0.0);
        assert_relative_eq!(p0, Point2::new(0.0, 0.0));
        assert_relative_eq!(h0, 0.0);
        let (pe, he) = t.pose_at(t.length_m());
        assert_relative_eq!(pe, Point2::new(10.0, 10.0), epsilon = 1e-9);
        assert_relative_eq!(he, FRAC_PI_2, epsilon = 1e-9);
        // Continuity: small steps move by at most the step length.
        let mut prev = t.pose_at(0.0);
        let ds = 0.01;
        let mut s = ds;
        while s <= t.length_m() {
            let cur = t.pose_at(s);
            assert!((cur.0 - prev.0).norm() <= ds * (1.0 + 1e-6));
            assert!(wrap_angle(cur.1 - prev.1).abs() <= ds / 2.0 * (1.0 + 1e-6));
            prev = cur;
            s += ds;
        }
    }

    #[test]
    fn zero_radius_gives_the_polyline() {
        let t = Trajectory::new(&[[0.0, 0.0], [3.0, 0.0], [3.0, -4.0]], 0.0);
        assert_relative_eq!(t.length_m(), 7.0, epsilon = 1e-12);
        assert_relative_eq!(t.pose_at(5.0).0, Point2::new(3.0, -2.0), epsilon = 1e-12);
    }
}

//! Ray tracing by the image method, up to second order (Gentner et al. 2016 §2.1/§6.1, Ulmschneider et al. 2021 Fig. 1).
//!
//! A path is a sequence of interactions — specular reflections at wall segments and
//! scattering at point scatterers — between the transmitter and the receiver. Reflection
//! points follow from mirror images of the source; a reflection point must lie on its
//! segment, and every leg of the path is tested for occlusion by every wall.
//!
//! Each path is the line-of-sight signal of a *virtual transmitter* `[x, y, b]`: the source
//! after the last scatterer (the transmitter itself when there is none), mirrored at every
//! later wall, with `b` the distance travelled up to that last scatterer (plus the
//! transmitter's clock offset). Then `length = ‖p_rx − p_vtx‖ + b` holds exactly.
//!
//! Cost per receiver position: O(S·W) sequences for S interaction sequences and W walls.

use nalgebra::{Point2, Vector2};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Interaction {
    Reflect(usize),
    Scatter(usize),
}

/// Geometry for tracing: walls as segments, scatterers as points.
#[derive(Debug, Clone)]
pub struct Geometry {
    pub tx: Point2<f64>,
    pub clock_offset_m: f64,
    pub walls: Vec<[Point2<f64>; 2]>,
    pub scatterers: Vec<Point2<f64>>,
}

/// A traced propagation path.
#[derive(Debug, Clone, PartialEq)]
pub struct Path {
    pub interactions: Vec<Interaction>,
    /// transmitter, interaction points…, receiver
    pub points: Vec<Point2<f64>>,
    /// geometric length (m), without the clock offset
    pub length_m: f64,
    pub vtx: Point2<f64>,
    /// clock offset of the virtual transmitter (m), including the transmitter's own
    pub b_m: f64,
}

impl Path {
    /// Propagation distance the receiver measures: length + transmitter clock offset.
    pub fn distance_m(&self, clock_offset_m: f64) -> f64 {
        self.length_m + clock_offset_m
    }

    pub fn kind(&self) -> &'static str {
        if self.interactions.is_empty() {
            "physical"
        } else if self
            .interactions
            .iter()
            .any(|i| matches!(i, Interaction::Scatter(_)))
        {
            "scattering"
        } else {
            "reflection"
        }
    }

    /// `Tx>W3>S1` style label.
    pub fn label(&self) -> String {
        let mut s = String::from("Tx");
        for i in &self.interactions {
            match i {
                Interaction::Reflect(w) => s.push_str(&format!(">W{w}")),
                Interaction::Scatter(k) => s.push_str(&format!(">S{k}")),
            }
        }
        s
    }
}

/// All interaction sequences up to `max_order`, in a fixed order.
pub fn sequences(n_walls: usize, n_scatterers: usize, max_order: u8) -> Vec<Vec<Interaction>> {
    let singles: Vec<Interaction> = (0..n_walls)
        .map(Interaction::Reflect)
        .chain((0..n_scatterers).map(Interaction::Scatter))
        .collect();
    let mut out = vec![Vec::new()];
    if max_order >= 1 {
        out.extend(singles.iter().map(|&i| vec![i]));
    }
    if max_order >= 2 {
        for &a in &singles {
            for &b in &singles {
                if a != b {
                    out.push(vec![a, b]);
                }
            }
        }
    }
    out
}

fn mirror(p: &Point2<f64>, wall: &[Point2<f64>; 2]) -> Point2<f64> {
    let d = (wall[1] - wall[0]).normalize();
    let v = p - wall[0];
    let along = d * v.dot(&d);
    wall[0] + along * 2.0 - v
}

/// Intersection of segment p→q with a wall: (t along p→q, u along the wall).
fn intersect(p: &Point2<f64>, q: &Point2<f64>, wall: &[Point2<f64>; 2]) -> Option<(f64, f64)> {
    let r = q - p;
    let s = wall[1] - wall[0];
    let denom = cross(&r, &s);
    if denom.abs() < 1e-12 {
        return None;
    }
    let w = wall[0] - p;
    Some((cross(&w, &s) / denom, cross(&w, &r) / denom))
}

fn cross(a: &Vector2<f64>, b: &Vector2<f64>) -> f64 {
    a.x * b.y - a.y * b.x
}

const EPS: f64 = 1e-9;

/// True when the open segment p→q crosses any wall.
pub fn blocked(p: &Point2<f64>, q: &Point2<f64>, walls: &[[Point2<f64>; 2]]) -> bool {
    let len = (q - p).norm();
    if len < EPS {
        return false;
    }
    let tol = 1e-7 / len.max(1.0);
    let (minx, maxx) = (p.x.min(q.x), p.x.max(q.x));
    let (miny, maxy) = (p.y.min(q.y), p.y.max(q.y));
    walls.iter().any(|w| {
        if w[0].x.max(w[1].x) < minx || w[0].x.min(w[1].x) > maxx || w[0].y.max(w[1].y) < miny || w[0].y.min(w[1].y) > maxy {
            return false;
        }
        matches!(intersect(p, q, w), Some((t, u)) if t > tol && t < 1.0 - tol && (-EPS..=1.0 + EPS).contains(&u))
    })
}

/// Reflection points of a leg from `start` to `end` via `walls` (in order), or None when a
/// reflection point falls off its segment or behind the mirror.
fn leg_points(
    start: &Point2<f64>,
    end: &Point2<f64>,
    walls: &[&[Point2<f64>; 2]],
) -> Option<Vec<Point2<f64>>> {
    let mut images = vec![*start];
    for w in walls {
        let last = *images.last().unwrap();
        images.push(mirror(&last, w));
    }
    let mut pts = vec![Point2::origin(); walls.len()];
    let mut target = *end;
    for k in (0..walls.len()).rev() {
        let (t, u) = intersect(&target, &images[k + 1], walls[k])?;
        if !(t > EPS && t < 1.0 - EPS && (0.0..=1.0).contains(&u)) {
            return None;
        }
        let p = target + (images[k + 1] - target) * t;
        pts[k] = p;
        target = p;
    }
    Some(pts)
}

/// Traces one interaction sequence to the receiver at `rx`; None when the path is invalid.
pub fn trace_sequence(geo: &Geometry, seq: &[Interaction], rx: &Point2<f64>) -> Option<Path> {
    // Anchors: Tx, scatterers, Rx; between consecutive anchors a run of reflections.
    let mut points = vec![geo.tx];
    let mut anchor = geo.tx;
    let mut pending: Vec<&[Point2<f64>; 2]> = Vec::new();
    for inter in seq
        .iter()
        .chain(std::iter::once(&Interaction::Scatter(usize::MAX)))
    {
        match *inter {
            Interaction::Reflect(w) => pending.push(&geo.walls[w]),
            Interaction::Scatter(k) => {
                let next = if k == usize::MAX {
                    *rx
                } else {
                    geo.scatterers[k]
                };
                points.extend(leg_points(&anchor, &next, &pending)?);
                points.push(next);
                pending.clear();
                anchor = next;
            }
        }
    }
    for pair in points.windows(2) {
        if blocked(&pair[0], &pair[1], &geo.walls) {
            return None;
        }
    }
    // Virtual transmitter: follow the interactions from the source.
    let mut vtx = geo.tx;
    let mut b = geo.clock_offset_m;
    let mut travelled = 0.0;
    for (i, inter) in seq.iter().enumerate() {
        travelled += (points[i + 1] - points[i]).norm();
        match *inter {
            Interaction::Reflect(w) => vtx = mirror(&vtx, &geo.walls[w]),
            Interaction::Scatter(k) => {
                vtx = geo.scatterers[k];
                b = geo.clock_offset_m + travelled;
            }
        }
    }
    let length_m = points.windows(2).map(|p| (p[1] - p[0]).norm()).sum();
    Some(Path {
        interactions: seq.to_vec(),
        points,
        length_m,
        vtx,
        b_m: b,
    })
}

/// All valid paths to `rx` for the given sequences.
pub fn trace_all(
    geo: &Geometry,
    seqs: &[Vec<Interaction>],
    rx: &Point2<f64>,
) -> Vec<(usize, Path)> {
    seqs.iter()
        .enumerate()
        .filter_map(|(i, s)| trace_sequence(geo, s, rx).map(|p| (i, p)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    fn p(x: f64, y: f64) -> Point2<f64> {
        Point2::new(x, y)
    }

    fn geo(walls: Vec<[Point2<f64>; 2]>, scatterers: Vec<Point2<f64>>) -> Geometry {
        Geometry {
            tx: p(0.0, 0.0),
            clock_offset_m: 0.0,
            walls,
            scatterers,
        }
    }

    #[test]
    fn one_wall_reflection() {
        // Wall y = 5 from x = −10 to 10; Tx (0,0), Rx (4,0): reflection point (2,5).
        let g = geo(vec![[p(-10.0, 5.0), p(10.0, 5.0)]], vec![]);
        let path = trace_sequence(&g, &[Interaction::Reflect(0)], &p(4.0, 0.0)).unwrap();
        assert_relative_eq!(path.points[1], p(2.0, 5.0), epsilon = 1e-12);
        assert_relative_eq!(path.length_m, 2.0 * (4.0f64 + 25.0).sqrt(), epsilon = 1e-12);
        assert_relative_eq!(path.vtx, p(0.0, 10.0), epsilon = 1e-12);
        assert_eq!(path.b_m, 0.0);
        assert_eq!(path.kind(), "reflection");
    }

    #[test]
    fn reflection_point_off_the_segment_is_rejected() {
        // Same geometry but the wall only spans x ∈ [3, 10]: the point (2,5) is off it.
        let g = geo(vec![[p(3.0, 5.0), p(10.0, 5.0)]], vec![]);
        assert!(trace_sequence(&g, &[Interaction::Reflect(0)], &p(4.0, 0.0)).is_none());
        // Receiver on the other side of the wall: no specular reflection either.
        let g = geo(vec![[p(-10.0, 5.0), p(10.0, 5.0)]], vec![]);
        assert!(trace_sequence(&g, &[Interaction::Reflect(0)], &p(4.0, 8.0)).is_none());
    }

    #[test]
    fn corner_double_reflection() {
        // Walls x = 10 (wall 0) and y = 10 (wall 1) meet in a corner at (10,10); Tx (0,0), Rx (4,2).
        let g = geo(
            vec![
                [p(10.0, -20.0), p(10.0, 10.0)],
                [p(-20.0, 10.0), p(10.0, 10.0)],
            ],
            vec![],
        );
        let rx = p(4.0, 2.0);
        // Via y = 10 first: image (0,20), then x = 10: image (20,20).
        let path =
            trace_sequence(&g, &[Interaction::Reflect(1), Interaction::Reflect(0)], &rx).unwrap();
        assert_relative_eq!(path.vtx, p(20.0, 20.0), epsilon = 1e-12);
        assert_relative_eq!(path.length_m, (p(20.0, 20.0) - rx).norm(), epsilon = 1e-9);
        // By hand: Rx→(20,20) meets x = 10 at y = 2 + 18·6/16 = 8.75; from there towards
        // (0,20) the line meets y = 10 at x = 10 − 10/9.
        assert_relative_eq!(path.points[2], p(10.0, 8.75), epsilon = 1e-9);
        assert_relative_eq!(path.points[1], p(10.0 - 10.0 / 9.0, 10.0), epsilon = 1e-9);
        // The other order would need a point on y = 10 at x ≈ 11.1, off wall 1's extent.
        assert!(
            trace_sequence(&g, &[Interaction::Reflect(0), Interaction::Reflect(1)], &rx).is_none()
        );
    }

    #[test]
    fn scatterer_gives_clock_offset() {
        let g = Geometry {
            tx: p(0.0, 0.0),
            clock_offset_m: 1.5,
            walls: vec![],
            scatterers: vec![p(3.0, 4.0)],
        };
        let rx = p(3.0, 10.0);
        let path = trace_sequence(&g, &[Interaction::Scatter(0)], &rx).unwrap();
        assert_relative_eq!(path.vtx, p(3.0, 4.0));
        assert_relative_eq!(path.b_m, 1.5 + 5.0, epsilon = 1e-12);
        assert_relative_eq!(path.length_m, 11.0, epsilon = 1e-12);
        assert_relative_eq!(
            path.distance_m(g.clock_offset_m),
            (rx - path.vtx).norm() + path.b_m,
            epsilon = 1e-12
        );
    }

    #[test]
    fn scatter_then_reflect_vtx_is_mirrored_scatterer() {
        let g = geo(vec![[p(-50.0, 10.0), p(50.0, 10.0)]], vec![p(5.0, 2.0)]);
        let rx = p(-3.0, 1.0);
        let path =
            trace_sequence(&g, &[Interaction::Scatter(0), Interaction::Reflect(0)], &rx).unwrap();
        assert_relative_eq!(path.vtx, p(5.0, 18.0), epsilon = 1e-12);
        assert_relative_eq!(path.b_m, (5.0f64 * 5.0 + 4.0).sqrt(), epsilon = 1e-12);
        assert_relative_eq!(
            path.length_m,
            (rx - path.vtx).norm() + path.b_m,
            epsilon = 1e-9
        );
    }

    #[test]
    fn blocked_path() {
        // A wall between Tx and Rx blocks line of sight.
        let g = geo(vec![[p(2.0, -5.0), p(2.0, 5.0)]], vec![]);
        assert!(trace_sequence(&g, &[], &p(4.0, 0.0)).is_none());
        assert!(trace_sequence(&g, &[], &p(1.0, 3.0)).is_some());
        // A reflection leg that passes through a second wall is blocked.
        // (the leg Tx → (2,5) crosses y = 1 at x = 0.4)
        let g = geo(
            vec![[p(-10.0, 5.0), p(10.0, 5.0)], [p(0.2, 1.0), p(0.6, 1.0)]],
            vec![],
        );
        assert!(trace_sequence(&g, &[Interaction::Reflect(0)], &p(4.0, 0.0)).is_none());
    }

    #[test]
    fn sequence_counts() {
        // 3 walls + 2 scatterers: 1 + 5 + 5·4 = 26
        assert_eq!(sequences(3, 2, 2).len(), 26);
        assert_eq!(sequences(3, 2, 1).len(), 6);
        assert_eq!(sequences(3, 2, 0).len(), 1);
    }
}

//! Random transmitter fields for calibrating the acceptance test: dense maps without
//! visibility, the hardest case for telling a common part from a coincidence. Transmitters lie
//! in squares of 50–100 m, two thirds with b = 0 and the rest with b uniform in 0–30 m; every
//! map is one Gaussian of std 0.2–0.5 m per transmitter, its mean displaced by that noise.

use super::MatchResult;
use crate::map::{Transmitter, TransmitterMap};
use crate::mixture::Component;
use nalgebra::{Isometry2, Matrix3, Point2, Vector2, Vector3};
use rand::{Rng, RngExt};
use std::collections::BTreeMap;

/// Two maps drawn for calibration, with what is true of them.
#[derive(Debug, Clone)]
pub struct FieldPair {
    /// the user map, in its own random frame
    pub user: TransmitterMap,
    /// the prior map, in the world frame
    pub prior: TransmitterMap,
    /// the true `map_from_agent` (meaningless for an unrelated pair)
    pub truth: Isometry2<f64>,
    /// the first `shared` user transmitters are in the prior map too (0: unrelated)
    pub shared: usize,
    /// the per-coordinate noise std of both maps (m)
    pub std: f64,
}

fn point(side: f64, rng: &mut impl Rng) -> [f64; 3] {
    let b = if rng.random::<f64>() < 1.0 / 3.0 {
        rng.random::<f64>() * 30.0
    } else {
        0.0
    };
    [rng.random::<f64>() * side, rng.random::<f64>() * side, b]
}

/// A standard normal draw (Box–Muller).
fn normal(rng: &mut impl Rng) -> f64 {
    let u1: f64 = rng.random_range(1e-300..1.0);
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

fn map_of(
    points: &[[f64; 3]],
    std: f64,
    agent_from_world: &Isometry2<f64>,
    tag: &str,
    rng: &mut impl Rng,
) -> TransmitterMap {
    let txs = points
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let (nx, ny, nb) = (normal(rng), normal(rng), normal(rng));
            let q = agent_from_world * Point2::new(s[0] + std * nx, s[1] + std * ny);
            Transmitter {
                id: format!("{tag}{i}"),
                components: vec![Component::new(
                    1.0,
                    Vector3::new(q.x, q.y, (s[2] + std * nb).max(0.0)),
                    Matrix3::from_diagonal_element(std * std),
                )],
                existence: 1.0,
                reliability_m: 20.0,
                visibility: BTreeMap::new(),
            }
        })
        .collect();
    TransmitterMap::new(2.0, txs).expect("finite means and positive covariances")
}

fn random_frame(rng: &mut impl Rng) -> Isometry2<f64> {
    Isometry2::new(
        Vector2::new(
            rng.random_range(-300.0..300.0),
            rng.random_range(-300.0..300.0),
        ),
        rng.random_range(-std::f64::consts::PI..std::f64::consts::PI),
    )
}

/// Two independent fields of 8–40 transmitters each over the same square.
pub fn unrelated(rng: &mut impl Rng) -> FieldPair {
    let side = rng.random_range(50.0..=100.0);
    let std = rng.random_range(0.2..=0.5);
    let (n_u, n_p) = (rng.random_range(8..=40), rng.random_range(8..=40));
    let fu: Vec<[f64; 3]> = (0..n_u).map(|_| point(side, rng)).collect();
    let fp: Vec<[f64; 3]> = (0..n_p).map(|_| point(side, rng)).collect();
    let frame = random_frame(rng);
    FieldPair {
        user: map_of(&fu, std, &frame, "u", rng),
        prior: map_of(&fp, std, &Isometry2::identity(), "p", rng),
        truth: frame.inverse(),
        shared: 0,
        std,
    }
}

/// Two maps of one field: 8–40 user transmitters, at least 6 and at least half of them shared,
/// and up to as many prior-only transmitters as shared ones (≤ 50 % unshared on either side,
/// at most 40 per map).
pub fn related(rng: &mut impl Rng) -> FieldPair {
    let side = rng.random_range(50.0..=100.0);
    let std = rng.random_range(0.2..=0.5);
    let n_u = rng.random_range(8..=40usize);
    let own_fraction = rng.random_range(0.0..=0.5);
    let shared = ((n_u as f64 * (1.0 - own_fraction)).ceil() as usize).clamp(6, n_u);
    let own_u = n_u - shared;
    let own_p = rng.random_range(0..=shared.min(40 - shared));
    let field: Vec<[f64; 3]> = (0..shared + own_u + own_p)
        .map(|_| point(side, rng))
        .collect();
    let frame = random_frame(rng);
    let mut prior_pts: Vec<[f64; 3]> = field[..shared].to_vec();
    prior_pts.extend_from_slice(&field[shared + own_u..]);
    FieldPair {
        user: map_of(&field[..shared + own_u], std, &frame, "u", rng),
        prior: map_of(&prior_pts, std, &Isometry2::identity(), "p", rng),
        truth: frame.inverse(),
        shared,
        std,
    }
}

/// A dense prior (20–40 transmitters) and a user map that shares too little with it to decide:
/// either 3–4 user transmitters, all of them in the prior, or a user field of 8–40 beside the
/// prior's square that reaches into it with only 3–4 transmitters, all of them shared.
pub fn small_overlap(rng: &mut impl Rng) -> FieldPair {
    let side = rng.random_range(50.0..=100.0);
    let std = rng.random_range(0.2..=0.5);
    let n_p = rng.random_range(20..=40usize);
    let prior_pts: Vec<[f64; 3]> = (0..n_p).map(|_| point(side, rng)).collect();
    let shared = rng.random_range(3..=4usize);
    let mut user_pts: Vec<[f64; 3]> = prior_pts[..shared].to_vec();
    if rng.random::<bool>() {
        // a user field beside the prior's square (to its right, a gap of 10 m)
        let n_u = rng.random_range(8..=40usize);
        user_pts.extend((shared..n_u).map(|_| {
            let [x, y, b] = point(side, rng);
            [x + side + 10.0, y, b]
        }));
    }
    let shared = user_pts.iter().filter(|p| p[0] <= side).count();
    let frame = random_frame(rng);
    FieldPair {
        user: map_of(&user_pts, std, &frame, "u", rng),
        prior: map_of(&prior_pts, std, &Isometry2::identity(), "p", rng),
        truth: frame.inverse(),
        shared,
        std,
    }
}

impl FieldPair {
    /// Whether `r` recovered a related pair: accepted, and its transform puts every shared
    /// transmitter within 3σ of where the truth puts it.
    pub fn recovered(&self, r: &MatchResult) -> bool {
        self.shared > 0
            && r.accepted
            && self.user.transmitters()[..self.shared].iter().all(|t| {
                let m = t.moments().0;
                let q = Point2::new(m.x, m.y);
                (r.map_from_agent * q - self.truth * q).norm() <= 3.0 * self.std
            })
    }
}

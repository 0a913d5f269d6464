//! Tracking paths over snapshots, as KEST does (Jost et al. 2012, "Detection and tracking of
//! mobile propagation channel paths"; used by Gentner et al. 2016 §5): each path has a Kalman filter over
//! `[d, ḋ, θ, θ̇]` (distance m, its rate m/s, angle of arrival rad, its rate rad/s, body
//! frame); the prediction turns the angle by the gyro's heading change; the predicted paths
//! seed the snapshot's SAGE estimation, so a path keeps its id as long as its re-estimate lies
//! within the gate of its prediction. A path missed for more than `coast` snapshots ends;
//! a path found again later is a new id, as with KEST. New paths (found by SAGE beyond the
//! seeds) start new tracks.

use nalgebra::{Matrix2, Matrix2x4, Matrix4, Vector2, Vector4};

/// Settings of the tracker.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackerConfig {
    /// white acceleration of the distance (m/s² · √s)
    pub distance_acceleration: f64,
    /// white acceleration of the angle (rad/s² · √s)
    pub angle_acceleration: f64,
    /// snapshots a path may be missed before its track ends
    pub coast: usize,
    /// χ² gate (2 degrees of freedom) of a re-estimate around its prediction
    pub gate_chi2: f64,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        TrackerConfig {
            // a walking or driving receiver: a path's range rate changes by a few m/s within a
            // second in turns
            distance_acceleration: 5.0,
            angle_acceleration: 2.0,
            coast: 2,
            // 1 − 10⁻⁴
            gate_chi2: 18.4,
        }
    }
}

/// One tracked path.
#[derive(Debug, Clone, PartialEq)]
pub struct Track {
    pub id: u64,
    pub x: Vector4<f64>,
    pub p: Matrix4<f64>,
    /// snapshots since its last detection
    pub missed: usize,
    /// detections so far
    pub detections: usize,
}

/// The tracker's state between snapshots.
#[derive(Debug, Clone)]
pub struct Tracker {
    pub cfg: TrackerConfig,
    pub tracks: Vec<Track>,
    next_id: u64,
}

const H: Matrix2x4<f64> = Matrix2x4::new(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0);

impl Tracker {
    pub fn new(cfg: TrackerConfig) -> Self {
        Tracker {
            cfg,
            tracks: Vec::new(),
            next_id: 1,
        }
    }

    /// Moves every track `dt` seconds ahead; the heading turned by `heading_change` (rad).
    pub fn predict(&mut self, dt: f64, heading_change: f64) {
        let f = Matrix4::new(
            1.0, dt, 0.0, 0.0, //
            0.0, 1.0, 0.0, 0.0, //
            0.0, 0.0, 1.0, dt, //
            0.0, 0.0, 0.0, 1.0,
        );
        let q1 = |s: f64| {
            let s2 = s * s;
            Matrix2::new(
                s2 * dt.powi(3) / 3.0,
                s2 * dt * dt / 2.0,
                s2 * dt * dt / 2.0,
                s2 * dt,
            )
        };
        let mut q = Matrix4::zeros();
        q.fixed_view_mut::<2, 2>(0, 0)
            .copy_from(&q1(self.cfg.distance_acceleration));
        let qa = q1(self.cfg.angle_acceleration);
        q[(2, 2)] = qa[(0, 0)];
        q[(2, 3)] = qa[(0, 1)];
        q[(3, 2)] = qa[(1, 0)];
        q[(3, 3)] = qa[(1, 1)];
        for t in &mut self.tracks {
            t.x = f * t.x;
            t.x[2] = echomap_shared::wrap_angle(t.x[2] - heading_change);
            t.p = f * t.p * f.transpose() + q;
        }
    }

    /// The squared Mahalanobis distance of a measurement `z` (d, θ) with noise `r` from
    /// track `i`'s prediction.
    pub fn distance2(&self, i: usize, z: Vector2<f64>, r: &Matrix2<f64>) -> f64 {
        let t = &self.tracks[i];
        let mut nu = z - H * t.x;
        nu[1] = echomap_shared::wrap_angle(nu[1]);
        let s = H * t.p * H.transpose() + r;
        s.try_inverse()
            .map(|si| (nu.transpose() * si * nu)[(0, 0)])
            .unwrap_or(f64::INFINITY)
    }

    /// Updates track `i` with `z` (d, θ), noise covariance `r`.
    pub fn update(&mut self, i: usize, z: Vector2<f64>, r: &Matrix2<f64>) {
        let t = &mut self.tracks[i];
        let mut nu = z - H * t.x;
        nu[1] = echomap_shared::wrap_angle(nu[1]);
        let s = H * t.p * H.transpose() + r;
        if let Some(si) = s.try_inverse() {
            let k = t.p * H.transpose() * si;
            t.x += k * nu;
            t.x[2] = echomap_shared::wrap_angle(t.x[2]);
            t.p = (Matrix4::identity() - k * H) * t.p;
        }
        t.missed = 0;
        t.detections += 1;
    }

    /// Starts a track at `z` (d, θ) with noise `r`; returns its id.
    pub fn start(&mut self, z: Vector2<f64>, r: &Matrix2<f64>, max_range_rate: f64) -> u64 {
        let id = self.next_id;
        self.next_id += 1;
        let p = Matrix4::from_diagonal(&Vector4::new(
            r[(0, 0)],
            max_range_rate * max_range_rate,
            r[(1, 1)],
            1.0,
        ));
        self.tracks.push(Track {
            id,
            x: Vector4::new(z[0], 0.0, z[1], 0.0),
            p,
            missed: 0,
            detections: 1,
        });
        id
    }

    /// The indices of the tracks to seed the next estimation with, most trusted first: those
    /// detected last snapshot before those coasting, then the longer-lived; at most `max`.
    pub fn seed_order(&self, max: usize) -> Vec<usize> {
        let mut order: Vec<usize> = (0..self.tracks.len()).collect();
        order.sort_by_key(|&i| {
            let t = &self.tracks[i];
            (t.missed, std::cmp::Reverse(t.detections), t.id)
        });
        order.truncate(max);
        order
    }

    /// Ends the tracks missed more than `coast` snapshots in a row.
    pub fn prune(&mut self) {
        let coast = self.cfg.coast;
        self.tracks.retain(|t| t.missed <= coast);
    }
}

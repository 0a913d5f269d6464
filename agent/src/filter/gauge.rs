//! The gauge of a map segment: where a stretch of newly mapped transmitters sits in the agent
//! frame, which the radio cannot observe.
//!
//! After a silent stretch (no transmitter alive) the first detections are all of new tracks.
//! Every particle starts their transmitters from its own pose, so ranges and angles of arrival
//! say nothing about where that pose is: a rigid motion of a particle's pose together with
//! every transmitter it started since is invisible to all later detections. The segment's
//! gauge — the pose the particles had when it opened — keeps the distribution dead reckoning
//! gave it then, until a detection ties the segment to a transmitter mapped before (a loop
//! closure) or a prior map anchors the frame.
//!
//! A particle filter cannot keep that by itself: the weights select particles on how well
//! their *relative* track fits their maps, and with a sharp relative posterior a few
//! lineages win within seconds; every survivor then carries the same ancestor's gauge, a
//! single random draw from the spread dead reckoning had (measured on a ray-traced city
//! walk: a 7 m cloud collapsed to 0.1 m in 3 s, 16 m from the truth against dead reckoning's
//! 13 m). So the segment's gauge is fixed, as SLAM fixes the frame of its first pose: after
//! each resampling, while the segment is open, every particle is moved rigidly — its pose
//! together with the segment's transmitters (`FrameDelta`) — so that its pose at the
//! segment's start is the particles' weighted mean pose then. No particle's likelihood
//! changes, and the track keeps dead reckoning's best estimate of where the segment began
//! instead of a random particle's.
//!
//! Keeping the gauge's *spread* instead (each particle's gauge redrawn from the opening
//! distribution) was tried and is not done: on the MRCLAM robots it rotated the whole map
//! by 0.45 rad about the segment's start within minutes (mean error 3.1 m against 0.78 m).

use super::model::Pose;
use super::particle::{FrameDelta, Particle};
use super::rbpf::Filter;
use echomap_shared::wrap_angle;
use nalgebra::{Matrix3, Point2, Vector2, Vector3};
use rayon::prelude::*;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

/// An open segment: its id and the particles' weighted mean pose `[x, y, heading]` when it
/// opened.
#[derive(Debug, Clone)]
pub(super) struct Gauge {
    pub(super) segment: u32,
    mean: Vector3<f64>,
}

impl FrameDelta {
    /// `D` applied to a pose: position moved, heading turned by `d_theta`.
    pub(crate) fn forward_pose(&self, pose: &Pose) -> Pose {
        let (s, c) = self.d_theta.sin_cos();
        let (x, y) = (pose.x - self.centroid.x, pose.y - self.centroid.y);
        Pose {
            x: self.centroid.x + c * x - s * y + self.d_t.x,
            y: self.centroid.y + s * x + c * y + self.d_t.y,
            heading: wrap_angle(pose.heading + self.d_theta),
            speed: pose.speed,
        }
    }
}

/// Weighted mean and covariance of poses `[x, y, heading]` (heading: circular mean, wrapped
/// deviations).
fn pose_moments(poses: &[Pose], w: &[f64]) -> (Vector3<f64>, Matrix3<f64>) {
    let total: f64 = w.iter().sum();
    let (mut mx, mut my, mut ms, mut mc) = (0.0, 0.0, 0.0, 0.0);
    for (p, w) in poses.iter().zip(w) {
        mx += w * p.x;
        my += w * p.y;
        ms += w * p.heading.sin();
        mc += w * p.heading.cos();
    }
    let mean = Vector3::new(mx / total, my / total, ms.atan2(mc));
    let mut cov = Matrix3::zeros();
    for (p, w) in poses.iter().zip(w) {
        let e = Vector3::new(p.x - mean.x, p.y - mean.y, wrap_angle(p.heading - mean.z));
        cov += (w / total) * e * e.transpose();
    }
    (mean, cov)
}

impl Filter {
    /// Opens a segment when a snapshot's detections are all of new tracks after a silent
    /// stretch (`quiet`: no track alive before it) and the particles' poses then spread more
    /// than one detection resolves (the distance and angle floors of the noise law; a finer
    /// spread cannot matter to any later detection, and the new transmitters simply join the
    /// current segment). The particles' poses now are the new segment's gauge.
    pub(super) fn open_segment(&mut self, quiet: bool) {
        if !quiet || self.prior.is_some() || !self.cfg.keep_gauge {
            return;
        }
        let w = self.weights();
        let poses: Vec<Pose> = self.particles.iter().map(|p| p.pose).collect();
        let (mean, cov) = pose_moments(&poses, &w);
        let (sx, sh) = ((cov[(0, 0)] + cov[(1, 1)]).sqrt(), cov[(2, 2)].sqrt());
        if sx < self.cfg.noise.distance_floor_m && sh < self.cfg.noise.aoa_floor_rad {
            return;
        }
        self.segments += 1;
        self.segment = self.segments;
        for p in &mut self.particles {
            p.anchors.push((self.segment, p.pose));
        }
        self.open.push(Gauge {
            segment: self.segment,
            mean,
        });
    }

    /// Ties the open current segment to an earlier one once the majority of the weight binds
    /// a track alive now to a transmitter mapped in it: to an anchored segment (the start's,
    /// or one tied to it) the segment is anchored too; to an open one the two become one
    /// segment with the earlier one's gauge.
    pub(super) fn tie_segment(&mut self, w: &[f64], current: &BTreeSet<u64>) {
        if self.open.is_empty() {
            return;
        }
        if self.prior.is_some() {
            self.open.clear();
            for p in &mut self.particles {
                p.anchors.clear();
            }
            return;
        }
        let k = self.segment;
        if !self.open.iter().any(|g| g.segment == k) {
            return;
        }
        let mut tied: BTreeMap<u32, f64> = BTreeMap::new();
        for (p, w) in self.particles.iter().zip(w) {
            let segs: BTreeSet<u32> = p
                .bound
                .iter()
                .filter(|(t, _)| current.contains(t))
                .map(|(_, i)| self.identities[p.txs[*i as usize].identity as usize].segment)
                .filter(|s| *s != k)
                .collect();
            for s in segs {
                *tied.entry(s).or_insert(0.0) += w;
            }
        }
        let Some((&j, _)) = tied
            .iter()
            .filter(|(_, v)| **v > 0.5)
            .max_by(|a, b| a.1.total_cmp(b.1).then(b.0.cmp(a.0)))
        else {
            return;
        };
        for id in &mut self.identities {
            if id.segment == k {
                id.segment = j;
            }
        }
        self.open.retain(|g| g.segment != k);
        for p in &mut self.particles {
            p.anchors.retain(|(s, _)| *s != k);
        }
        self.segment = j;
    }

    /// After a resampling, while the current segment is open: every particle's gauge set to
    /// the segment's opening mean, as a rigid motion of the particle's pose, its anchor and
    /// the segment's transmitters.
    pub(super) fn restore_gauge(&mut self) {
        let segment = self.segment;
        let Some(g) = self.open.iter().find(|g| g.segment == segment).cloned() else {
            return;
        };
        let identities = &self.identities;
        self.particles.par_iter_mut().for_each(|p| {
            let Some(a) = p.anchors.iter().find(|(s, _)| *s == segment).map(|a| a.1) else {
                return;
            };
            let delta = FrameDelta {
                centroid: Point2::new(a.x, a.y),
                d_theta: wrap_angle(g.mean.z - a.heading),
                d_t: Vector2::new(g.mean.x - a.x, g.mean.y - a.y),
            };
            if delta.d_theta.abs() < 1e-12 && delta.d_t.norm() < 1e-12 {
                return;
            }
            move_segment(p, &delta, segment, |id| {
                identities[id as usize].segment == segment
            });
        });
    }
}

/// Moves a particle's pose, its anchor of `segment` and the transmitters `in_segment` by
/// `delta`.
fn move_segment(
    p: &mut Particle,
    delta: &FrameDelta,
    segment: u32,
    in_segment: impl Fn(u32) -> bool,
) {
    p.pose = delta.forward_pose(&p.pose);
    for (s, a) in &mut p.anchors {
        if *s == segment {
            *a = delta.forward_pose(a);
        }
    }
    let mut moved = vec![false; p.txs.len()];
    for (i, tx) in p.txs.iter_mut().enumerate() {
        if in_segment(tx.identity) {
            let t = Arc::make_mut(tx);
            t.comps = delta.apply(&t.comps);
            if let Some(b) = t.birth.as_mut() {
                b.pose = delta.forward_pose(&b.pose);
            }
            moved[i] = true;
        }
    }
    for pd in &mut p.pending {
        for c in &mut pd.cands {
            if let super::association::CandSource::Old(i) = c.source
                && moved.get(i as usize).copied().unwrap_or(false)
            {
                c.comps = delta.apply(&c.comps);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_delta_moves_a_pose_rigidly_and_its_inverse_undoes_it() {
        let d = FrameDelta {
            centroid: Point2::new(1.0, -2.0),
            d_theta: 0.3,
            d_t: Vector2::new(0.5, 0.25),
        };
        let p = Pose {
            x: 4.0,
            y: 1.0,
            heading: 3.0,
            speed: 1.2,
        };
        let q = d.forward_pose(&p);
        // the distance to the centroid is kept, the centroid moves by d_t
        let r0 = (p.x - 1.0).hypot(p.y + 2.0);
        let r1 = (q.x - 1.5).hypot(q.y + 1.75);
        assert!((r0 - r1).abs() < 1e-12);
        let back = d.inverse_pose(&q);
        assert!((back.x - p.x).abs() < 1e-12 && (back.y - p.y).abs() < 1e-12);
        assert!(wrap_angle(back.heading - p.heading).abs() < 1e-12);
    }

    #[test]
    fn pose_moments_wrap_the_heading() {
        let poses = [
            Pose {
                x: 0.0,
                y: 0.0,
                heading: 3.1,
                speed: 0.0,
            },
            Pose {
                x: 2.0,
                y: 1.0,
                heading: -3.1,
                speed: 0.0,
            },
        ];
        let (m, cov) = pose_moments(&poses, &[0.5, 0.5]);
        assert!((m.x - 1.0).abs() < 1e-12 && (m.y - 0.5).abs() < 1e-12);
        assert!(wrap_angle(m.z - std::f64::consts::PI).abs() < 1e-9);
        assert!(cov[(2, 2)] < 0.01, "heading spread across ±π is small");
        assert!((cov[(0, 0)] - 1.0).abs() < 1e-12 && (cov[(1, 1)] - 0.25).abs() < 1e-12);
    }
}

#[cfg(test)]
mod invariance {
    use super::*;
    use crate::sim::builtin::indoor;
    use crate::sim::simulate::{SimOptions, simulate};

    #[test]
    fn a_rigid_motion_of_a_particle_and_its_map_changes_none_of_its_weights() {
        // The indoor scene for 6 s, then every particle and its whole map moved rigidly: the
        // next 2 s weigh the particles as before (no resampling, no visibility term, which is
        // kept along the mean track in the agent frame) and the poses follow the motion.
        let out = simulate(
            &indoor(),
            "reference",
            SimOptions {
                seed: 3,
                toa_only: false,
            },
        )
        .unwrap();
        let cfg = super::super::FilterConfig {
            particles: 20,
            seed: 5,
            initial_speed_mps: 1.0,
            gyro_bias_std_rad_per_s: 0.0,
            speed_scale_std: 0.0,
            association_visibility_weight: 0.0,
            keep_gauge: false,
            resample_ess_ratio: 0.0,
            ..Default::default()
        };
        let mut a = Filter::new(cfg, true);
        for s in &out.log.snapshots[..60] {
            a.step(s);
        }
        let mut b = a.clone();
        let delta = FrameDelta {
            centroid: Point2::new(1.0, 2.0),
            d_theta: 0.4,
            d_t: Vector2::new(3.0, -1.5),
        };
        for p in &mut b.particles {
            move_segment(p, &delta, 0, |_| true);
        }
        for s in &out.log.snapshots[60..80] {
            a.step(s);
            b.step(s);
        }
        // equal up to the cubature rule, whose points follow the covariance's square root
        // (a rotated covariance's Cholesky factor is not the rotated factor): a few per cent
        // after 20 snapshots
        let (wa, wb) = (a.weights(), b.weights());
        for (x, y) in wa.iter().zip(&wb).filter(|(x, _)| **x > 1e-12) {
            assert!((x.ln() - y.ln()).abs() < 0.1, "{wa:?}\n{wb:?}");
        }
        let worst = a
            .particles
            .iter()
            .zip(&b.particles)
            .map(|(p, q)| {
                let moved = delta.forward_pose(&p.pose);
                (moved.x - q.pose.x).hypot(moved.y - q.pose.y)
            })
            .fold(0.0, f64::max);
        assert!(worst < 0.01, "poses apart by up to {worst} m");
    }
}

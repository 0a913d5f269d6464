//! One user particle of the RBGSPF: its pose, its transmitters (shared copy-on-write through
//! `Arc`) and the tracks bound to them, and its motion model (Gentner et al. 2016 eq. 16–18).

use super::association::{CandSource, Pending};
use super::config::{FilterConfig, Proposal};
use super::model::{Comp, Pose, initialize};
use super::prior_map::Prior;
use super::proposal;
use super::srckf::SqrtGaussian;
use super::update::{Meas, update_mixture};
use super::vonmises;
use echomap_shared::wrap_angle;
use nalgebra::{Point2, Vector2};
use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use std::sync::Arc;

/// One transmitter of one particle.
#[derive(Debug, Clone)]
pub struct TxState {
    /// dense index of the identity (the track that created it)
    pub identity: u32,
    pub comps: Vec<Comp>,
    /// distance this particle walked while the transmitter was visible (Ulmschneider et al. 2021 eq. 21)
    pub reliability_m: f64,
    /// started from a prior-map transmitter under the transform in use
    pub from_prior: bool,
    /// the detection it was started from (None for a prior copy): `Filter::fuse_prior`
    /// measures how much better the crowd's estimate is predicted now than by the wide
    /// mixture started then (the Occam factor of the fusion)
    pub birth: Option<Birth>,
}

/// The first detection of a transmitter and the particle's pose then: enough to rebuild the
/// mixture it started from (`initialize` is deterministic), at a few words per transmitter.
#[derive(Debug, Clone, Copy)]
pub struct Birth {
    pub(super) pose: Pose,
    pub(super) d: f64,
    pub(super) aoa: Option<f64>,
    pub(super) sd: f64,
    pub(super) sa: f64,
}

impl Birth {
    pub(super) fn of(pose: &Pose, m: &Meas) -> Self {
        let (sd, sa) = m.sigmas();
        Birth {
            pose: *pose,
            d: m.d(),
            aoa: m.aoa(),
            sd,
            sa,
        }
    }

    /// The wide mixture the transmitter started from.
    pub(super) fn mixture(&self, cfg: &FilterConfig) -> Vec<Comp> {
        initialize(cfg, &self.pose, self.d, self.aoa, self.sd, self.sa)
    }
}

#[derive(Debug, Clone)]
pub struct Particle {
    pub pose: Pose,
    pub log_w: f64,
    pub txs: Vec<Arc<TxState>>,
    /// active track id → index into `txs`
    pub bound: Vec<(u64, u32)>,
    /// prior-map transmitters (indices into the prior) this particle has taken over
    pub prior_used: Vec<u32>,
    /// this particle's own draw of the prior's transform (a static parameter of the
    /// particle, drawn when the prior is set; None = the transform as matched)
    pub prior_frame: Option<FrameDelta>,
    /// new tracks whose association is still open (`association_window` > 1)
    pub pending: Vec<Pending>,
    /// per open map segment, the pose this particle had when it began (`super::gauge`),
    /// moved with the particle by every gauge draw since
    pub anchors: Vec<(u32, Pose)>,
    /// this particle's draw of the odometry's calibration: the gyroscope's constant bias
    /// (rad/s) and the measured speed's scale (`motion.gyro_bias_std_rad_per_s`,
    /// `motion.speed_scale_std`); the detections select the draws that fit
    pub odometry: Calibration,
}

/// A constant error of the odometry, one draw per particle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Calibration {
    pub gyro_bias: f64,
    pub speed_scale: f64,
}

impl Calibration {
    /// The gyroscope's rate and the measured speed corrected by this calibration.
    pub fn correct(&self, gyro: f64, speed: Option<f64>) -> (f64, Option<f64>) {
        (gyro - self.gyro_bias, speed.map(|v| v * self.speed_scale))
    }
}

/// A small rigid motion of the agent frame, `D(p) = c + R(δθ)·(p − c) + δt`: one particle's
/// correction of the matched transform `agent_from_map`, so that the prior transmitters sit at
/// `D(agent_from_map(p_map))` for that particle. Evaluating a prior transmitter from the
/// particle's pose equals evaluating the untransformed one from `D⁻¹(pose)` (ranges and
/// angles of arrival are invariant under a rigid motion of both), which costs nothing per
/// candidate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameDelta {
    pub centroid: Point2<f64>,
    pub d_theta: f64,
    pub d_t: Vector2<f64>,
}

impl FrameDelta {
    /// `D⁻¹` applied to a pose (position and heading).
    pub(crate) fn inverse_pose(&self, pose: &Pose) -> Pose {
        let (s, c) = (-self.d_theta).sin_cos();
        let (x, y) = (
            pose.x - self.centroid.x - self.d_t.x,
            pose.y - self.centroid.y - self.d_t.y,
        );
        Pose {
            x: self.centroid.x + c * x - s * y,
            y: self.centroid.y + s * x + c * y,
            heading: wrap_angle(pose.heading - self.d_theta),
            speed: pose.speed,
        }
    }

    /// `D` applied to a mixture: means moved, x/y covariance blocks rotated (b is invariant).
    pub(crate) fn apply(&self, comps: &[Comp]) -> Vec<Comp> {
        let (s, c) = self.d_theta.sin_cos();
        let r = nalgebra::Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0);
        comps
            .iter()
            .filter_map(|k| {
                let m = k.g.mean;
                let (x, y) = (m.x - self.centroid.x, m.y - self.centroid.y);
                let mean = nalgebra::Vector3::new(
                    self.centroid.x + c * x - s * y + self.d_t.x,
                    self.centroid.y + s * x + c * y + self.d_t.y,
                    m.z,
                );
                let cov = r * k.g.cov() * r.transpose();
                SqrtGaussian::from_cov(mean, &cov).map(|g| Comp {
                    weight: k.weight,
                    g,
                })
            })
            .collect()
    }
}

/// Identity of a transmitter: the track id that created it.
#[derive(Debug, Clone)]
pub struct Identity {
    pub track: u64,
    /// the map segment it was born in (`super::gauge`)
    pub segment: u32,
}

impl Particle {
    /// Motion model (Gentner et al. 2016 eq. 16–18 in position/heading/speed form): the heading turns by
    /// the gyro rate plus von Mises noise, the speed follows a random walk (or the measured
    /// speed), and the position moves along the mean heading of the interval.
    pub(super) fn predict(
        &mut self,
        cfg: &FilterConfig,
        gyro: f64,
        speed: Option<f64>,
        dt: f64,
        rng: &mut ChaCha8Rng,
    ) {
        if dt <= 0.0 {
            return;
        }
        let var_h = cfg.heading_step_variance(gyro, dt);
        let sigma_h = var_h.sqrt();
        let kappa = if sigma_h > 0.0 {
            1.0 / (sigma_h * sigma_h)
        } else {
            f64::INFINITY
        };
        let mu = self.pose.heading + gyro * dt;
        let h_new = if kappa.is_finite() {
            vonmises::sample(mu, kappa, rng)
        } else {
            wrap_angle(mu)
        };
        let n: f64 = rng.sample(StandardNormal);
        self.pose.speed = match speed {
            // Unclamped: clipping the noise at zero would bias a standing user forward by
            // σ·0.4 m/s (0.02 m/s at the default σ — metres over a long stop on real data).
            Some(v) => v + cfg.speed_measurement_std_mps * n,
            None => (self.pose.speed + cfg.speed_noise_mps_per_sqrt_s * dt.sqrt() * n).max(0.0),
        };
        let h_mid = self.pose.heading + 0.5 * wrap_angle(h_new - self.pose.heading);
        self.pose.x += self.pose.speed * dt * h_mid.cos();
        self.pose.y += self.pose.speed * dt * h_mid.sin();
        self.pose.heading = h_new;
    }

    /// The motion step: from the proposal informed by this snapshot's detections of the
    /// particle's own transmitters when configured and any inform it (its importance ratio
    /// joins the weight), else from the motion model.
    pub(super) fn move_by(
        &mut self,
        cfg: &FilterConfig,
        gyro: f64,
        speed: Option<f64>,
        dt: f64,
        meas: &[(u64, Meas, u32)],
        rng: &mut ChaCha8Rng,
    ) {
        let (gyro, speed) = self.odometry.correct(gyro, speed);
        if cfg.proposal == Proposal::Informed && dt > 0.0 {
            let step = proposal::Step::new(cfg, &self.pose, gyro, speed, dt);
            let txs = &self.txs;
            let bound = &self.bound;
            touch_mixtures(txs, bound);
            let detections = meas.iter().filter_map(|(track, m, _)| {
                bound
                    .iter()
                    .find(|(t, _)| t == track)
                    .map(|&(_, idx)| (m, &txs[idx as usize].comps[..]))
            });
            if let Some((pose, ln_ratio)) = proposal::propose(&step, detections, rng) {
                self.pose = pose;
                self.log_w += ln_ratio;
                return;
            }
        }
        self.predict(cfg, gyro, speed, dt, rng);
    }

    /// Removes transmitter `slot`, renumbering what points behind it.
    pub(super) fn remove_slot(&mut self, slot: usize) {
        self.txs.remove(slot);
        let fix = |i: &mut u32| {
            if *i as usize > slot {
                *i -= 1;
            }
        };
        for (_, b) in &mut self.bound {
            fix(b);
        }
        for pd in &mut self.pending {
            fix(&mut pd.slot);
            for c in &mut pd.cands {
                if let CandSource::Old(old) = &mut c.source {
                    fix(old);
                }
            }
        }
    }

    /// Prior transmitter `idx` updated with the detection `m` and placed in this particle's
    /// frame: the mixture a track starts from when it is taken over.
    pub(super) fn prior_copy(
        &self,
        prior: Option<&Prior>,
        idx: usize,
        m: &Meas,
        cfg: &FilterConfig,
        merge_now: bool,
    ) -> Vec<Comp> {
        let prior = prior.expect("a prior candidate needs a prior");
        let mut comps = prior.txs[idx].comps.clone();
        let _ = update_mixture(&mut comps, m, &self.prior_pose(), cfg, merge_now);
        match &self.prior_frame {
            Some(d) => d.apply(&comps),
            None => comps,
        }
    }

    /// The pose from which this particle sees the prior's transmitters as the prior holds
    /// them: `D⁻¹(pose)` for its own transform draw.
    pub(super) fn prior_pose(&self) -> Pose {
        match &self.prior_frame {
            Some(d) => d.inverse_pose(&self.pose),
            None => self.pose,
        }
    }

    /// A new transmitter of this particle, bound to `track`: from the detection `birth`, or
    /// (None) a prior copy.
    pub(super) fn start_transmitter(
        &mut self,
        identity: u32,
        comps: Vec<Comp>,
        track: u64,
        updated: &mut Vec<bool>,
        birth: Option<Birth>,
    ) {
        self.txs.push(Arc::new(TxState {
            identity,
            comps,
            reliability_m: 0.0,
            from_prior: birth.is_none(),
            birth,
        }));
        self.bound.push((track, (self.txs.len() - 1) as u32));
        updated.push(true);
    }
}

/// Loads the first component of every bound transmitter's mixture before the proposal works
/// on them. The chain particle → transmitter → mixture is two dependent cache misses per
/// transmitter (the mixtures of 4000 particles do not fit in the cache); the proposal does
/// enough arithmetic per detection that the processor cannot reach the next detection's loads
/// while waiting for one. A loop of nothing but the loads lets it wait for all of them at
/// once. Changes no value.
fn touch_mixtures(txs: &[Arc<TxState>], bound: &[(u64, u32)]) {
    for &(_, idx) in bound {
        if let Some(c) = txs.get(idx as usize).and_then(|tx| tx.comps.first()) {
            std::hint::black_box(c.weight);
        }
    }
}

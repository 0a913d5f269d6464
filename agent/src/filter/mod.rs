//! Single-user Channel-SLAM: a Rao-Blackwellized Gaussian-sum particle filter (RBGSPF,
//! Gentner et al. 2016 §4, Algorithm 1). User particles carry the track; per particle every (virtual)
//! transmitter is a Gaussian mixture over `[x, y, b]` whose components are updated by
//! square-root cubature Kalman filters. New tracks are associated with old transmitters
//! (Gentner et al. 2016 §5) or, once the agent's map matches a prior map, with prior-map transmitters
//! (Ulmschneider et al. 2021 eq. 19, modules `prior` and `prior_map`), visibility is mapped on
//! a hex grid (Ulmschneider et al. 2021 eq. 11–12), and at the end the particle ensemble is exported as an `echomap.map.v1` user map.

pub mod association;
pub mod config;
pub mod export;
mod fusion;
mod gauge;
pub mod model;
mod observe;
pub mod particle;
pub mod prior;
pub mod prior_map;
mod proposal;
pub mod rbpf;
pub mod srckf;
pub mod truth;
pub mod update;
pub mod visibility;
pub mod vonmises;

pub use config::{Association, BPrior, FilterConfig, NoiseModel, Proposal};
pub use prior::{AnchorPose, Prior, PriorSettings, PriorTracker};
pub use rbpf::{Filter, StepStats};

#[cfg(test)]
mod tests;

//! Multipath scenario simulator: ray tracing by the image method (up to second order), a
//! KEST-like channel-estimator model (detection, resolution, SNR-dependent noise, track ids
//! that change when a component is lost), and a gyroscope.

pub mod builtin;
pub mod raytrace;
pub mod scenario;
pub mod simulate;
pub mod trajectory;

pub use scenario::{Scenario, ScenarioError};
pub use simulate::{SimOutput, simulate};

/// Speed of light in vacuum (m/s).
pub const SPEED_OF_LIGHT: f64 = 299_792_458.0;

#[cfg(test)]
mod tests;

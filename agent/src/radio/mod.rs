//! The radio front end: from sampled channel impulse responses (CIRs) to the per-snapshot
//! list of propagation paths the filter consumes.
//!
//! - `cir`: the CIR file format (`echomap.cir.v1`: JSON metadata + a NumPy `.npy` array);
//! - `array`: the receiver's array and pulse model (steering vectors, band-limited pulse);
//! - `sage`: the multipath parameter estimator of one snapshot (successive interference
//!   cancellation for new paths, SAGE for the joint maximum-likelihood refinement);
//! - `kest`: the tracker of paths over snapshots (a Kalman filter per path, as in KEST);
//! - `estimate`: CIR directory → `echomap.log.v1` with the estimator's sensor profile.

pub mod array;
pub mod cir;
pub mod estimate;
pub mod kest;
pub mod sage;

#![warn(missing_docs)]
//! Shared core of echomap: the transmitter-map contract (`echomap.map.v1`), 2D rigid
//! geometry, Gaussian mixtures and their reduction, the hexagonal visibility grid and the
//! measurement-log format, the sensor profile and the HTTP API's wire types. Pure and
//! synchronous: no I/O beyond serde, no global state.
//! Both the agent and the map server build on it, so anything exchanged between them is
//! defined (and validated) here.

pub mod api;
pub mod calibration;
pub mod fastmath;
pub mod geometry;
pub mod hexgrid;
pub mod log;
pub mod map;
pub mod matching;
pub mod merging;
pub mod mixture;
pub mod sensor;

pub use geometry::{Transform2, wrap_angle};
pub use hexgrid::{HexCell, HexGrid};
pub use map::{Beta, MapError, Transmitter, TransmitterMap};
pub use mixture::{Component, MixtureError};
pub use sensor::SensorProfile;

//! Scenario files (JSON): the environment, the radio and estimator settings, and user tracks.
//! Every field is documented in docs/formats.md; unknown fields and invalid values are rejected
//! with a message naming the field.

use crate::radio::array::{uniform_circular, uniform_square};
use serde::{Deserialize, Serialize};
use thiserror::Error;

#[derive(Debug, Error)]
pub enum ScenarioError {
    #[error("scenario is not valid JSON for this format: {0}")]
    Syntax(String),
    #[error("scenario field `{field}`: {message}")]
    Invalid { field: String, message: String },
    #[error("unknown track {name:?}; the scenario has: {available}")]
    UnknownTrack { name: String, available: String },
}

fn invalid(field: impl Into<String>, message: impl Into<String>) -> ScenarioError {
    ScenarioError::Invalid {
        field: field.into(),
        message: message.into(),
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    pub name: String,
    /// carrier frequency (Hz)
    pub carrier_hz: f64,
    /// signal bandwidth (Hz); the delay resolution is c / bandwidth
    pub bandwidth_hz: f64,
    /// channel snapshots per second
    pub snapshot_rate_hz: f64,
    pub transmitter: TransmitterSpec,
    #[serde(default)]
    pub walls: Vec<Wall>,
    #[serde(default)]
    pub scatterers: Vec<Scatterer>,
    #[serde(default)]
    pub receiver: Receiver,
    #[serde(default)]
    pub estimator: Estimator,
    #[serde(default)]
    pub gyro: Gyro,
    pub tracks: Vec<Track>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransmitterSpec {
    /// position [x, y] (m)
    pub position: [f64; 2],
    /// transmit power (dBm)
    pub power_dbm: f64,
    /// clock offset of the transmitter against the receiver, as a distance c·τ₀ ≥ 0 (m)
    #[serde(default)]
    pub clock_offset_m: f64,
}

fn default_reflection_loss() -> f64 {
    3.0
}
fn default_scattering_loss() -> f64 {
    6.0
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Wall {
    pub from: [f64; 2],
    pub to: [f64; 2],
    /// power lost at a specular reflection (dB), default 3
    #[serde(default = "default_reflection_loss")]
    pub reflection_loss_db: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scatterer {
    pub position: [f64; 2],
    /// power lost at the scatterer (dB), default 6
    #[serde(default = "default_scattering_loss")]
    pub scattering_loss_db: f64,
}

/// The radius, in half-wavelengths, of a circle of `m` elements whose neighbours are half a
/// wavelength apart: `1/(2·sin(π/m))`.
pub fn circle_radius_in_half_wavelengths(m: u32) -> f64 {
    1.0 / (2.0 * (std::f64::consts::PI / f64::from(m)).sin())
}

/// The layout of the receiver's antenna elements (neighbours λ/2 apart).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ArrayGeometry {
    /// a uniform square grid (uniform rectangular array, URA)
    Square,
    /// a uniform circular array (UCA)
    Circular,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Receiver {
    /// whether the array estimates angles of arrival (false: single antenna, ToA only)
    pub aoa: bool,
    /// antenna elements: a square number for a square grid, at least 3 for a circle
    pub array_elements: u32,
    /// how the elements are laid out, neighbours half a wavelength apart
    pub array_geometry: ArrayGeometry,
    /// receiver noise figure (dB); noise power = −174 dBm/Hz + 10·log10(B) + NF
    pub noise_figure_db: f64,
    /// angular resolution (rad); default the beamwidth λ/D of the array's aperture D
    /// ([`Scenario::angular_resolution_rad`])
    pub angular_resolution_rad: Option<f64>,
}

impl Default for Receiver {
    fn default() -> Self {
        Receiver {
            aoa: true,
            array_elements: 9,
            array_geometry: ArrayGeometry::Square,
            noise_figure_db: 7.0,
            angular_resolution_rad: None,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Estimator {
    /// a component is detected when its SNR (per sample, dB) is at least this
    pub detection_threshold_db: f64,
    /// a component already tracked stays detected down to `detection_threshold_db` minus this
    /// (dB): the estimator's tracking loop holds a track through shallow fades
    pub tracking_hysteresis_db: f64,
    /// independent samples the estimator integrates per snapshot (processing gain)
    pub integration_samples: f64,
    /// distance error floor (m): model mismatch, dense multipath, calibration
    pub distance_floor_m: f64,
    /// angle-of-arrival error floor (rad): array calibration
    pub aoa_floor_rad: f64,
    /// standard deviation of slow fading of each path's power (dB)
    pub fading_std_db: f64,
    /// distance over which a path's fading decorrelates (m)
    pub fading_correlation_m: f64,
    /// rate of spurious track losses per tracked component (1/s); a lost track is
    /// re-detected under a new id
    pub track_loss_rate_hz: f64,
    /// highest interaction order traced (0, 1 or 2)
    pub max_order: u8,
    /// components whose track spans less than this travelled distance (m, first to last
    /// detection) are left out of the log, as Gentner et al. 2016 §6.1 does with KEST's output ("only
    /// signal components that are observable for a user traveled distance of at least 35 m
    /// are … used"); 0 keeps every component. An offline selection: it needs the whole track
    pub min_track_distance_m: f64,
}

impl Default for Estimator {
    fn default() -> Self {
        Estimator {
            detection_threshold_db: 0.0,
            tracking_hysteresis_db: 3.0,
            integration_samples: 64.0,
            distance_floor_m: 0.25,
            aoa_floor_rad: 4f64.to_radians(),
            fading_std_db: 2.0,
            fading_correlation_m: 2.0,
            track_loss_rate_hz: 0.01,
            max_order: 2,
            min_track_distance_m: 0.0,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Gyro {
    /// white noise on the heading rate (rad/s, per snapshot)
    pub noise_std_rad_s: f64,
    /// constant bias of the heading rate (rad/s)
    pub bias_rad_s: f64,
}

impl Default for Gyro {
    fn default() -> Self {
        Gyro {
            noise_std_rad_s: 0.01,
            bias_rad_s: 0.0,
        }
    }
}

fn default_turn_radius() -> f64 {
    1.0
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Track {
    pub name: String,
    /// walking/driving speed (m/s)
    pub speed_mps: f64,
    /// polyline [[x, y], …]; corners are rounded with `turn_radius_m`
    pub waypoints: Vec<[f64; 2]>,
    #[serde(default = "default_turn_radius")]
    pub turn_radius_m: f64,
}

impl Scenario {
    /// Parses and validates a JSON scenario.
    pub fn from_json(text: &str) -> Result<Self, ScenarioError> {
        let de = &mut serde_json::Deserializer::from_str(text);
        let s: Scenario = serde_path_to_error::deserialize(de).map_err(|e| {
            let path = e.path().to_string();
            let inner = e.into_inner();
            if path == "." {
                ScenarioError::Syntax(inner.to_string())
            } else {
                invalid(path, inner.to_string())
            }
        })?;
        s.validate()?;
        Ok(s)
    }

    pub fn track(&self, name: &str) -> Result<&Track, ScenarioError> {
        self.tracks
            .iter()
            .find(|t| t.name == name)
            .ok_or_else(|| ScenarioError::UnknownTrack {
                name: name.to_string(),
                available: self
                    .tracks
                    .iter()
                    .map(|t| t.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
            })
    }

    /// Angular resolution in use (rad); default the beamwidth `λ/D` of the array's aperture
    /// `D` (a square grid: √M·λ/2; a circle: its diameter).
    pub fn angular_resolution_rad(&self) -> f64 {
        self.receiver.angular_resolution_rad.unwrap_or_else(|| {
            let m = f64::from(self.receiver.array_elements);
            match self.receiver.array_geometry {
                ArrayGeometry::Square => 2.0 / m.sqrt(),
                // λ over the circle's diameter 2·R·λ/2
                ArrayGeometry::Circular => {
                    1.0 / circle_radius_in_half_wavelengths(self.receiver.array_elements)
                }
            }
        })
    }

    /// Element positions of the receiver's array in the body frame (m), neighbours λ/2 apart
    /// (one element at the origin for ToA only).
    pub fn array_elements_m(&self, aoa: bool) -> Vec<[f64; 2]> {
        let spacing = self.wavelength_m() / 2.0;
        let m = self.receiver.array_elements;
        if !aoa {
            return vec![[0.0, 0.0]];
        }
        match self.receiver.array_geometry {
            ArrayGeometry::Square => {
                let side = f64::from(m).sqrt().round() as usize;
                uniform_square(side.max(1), spacing)
            }
            ArrayGeometry::Circular => {
                uniform_circular(m as usize, spacing * circle_radius_in_half_wavelengths(m))
            }
        }
    }

    pub fn wavelength_m(&self) -> f64 {
        super::SPEED_OF_LIGHT / self.carrier_hz
    }

    /// Checks every value; the error names the offending field.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        fn positive(field: &str, v: f64) -> Result<(), ScenarioError> {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(invalid(
                    field,
                    format!("must be a finite number > 0, got {v}"),
                ))
            }
        }
        fn non_negative(field: &str, v: f64) -> Result<(), ScenarioError> {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err(invalid(
                    field,
                    format!("must be a finite number ≥ 0, got {v}"),
                ))
            }
        }
        fn finite(field: &str, v: &[f64]) -> Result<(), ScenarioError> {
            if v.iter().all(|x| x.is_finite()) {
                Ok(())
            } else {
                Err(invalid(field, "must be finite numbers"))
            }
        }
        if self.name.is_empty() {
            return Err(invalid("name", "must not be empty"));
        }
        positive("carrier_hz", self.carrier_hz)?;
        positive("bandwidth_hz", self.bandwidth_hz)?;
        positive("snapshot_rate_hz", self.snapshot_rate_hz)?;
        finite("transmitter.position", &self.transmitter.position)?;
        finite("transmitter.power_dbm", &[self.transmitter.power_dbm])?;
        non_negative(
            "transmitter.clock_offset_m",
            self.transmitter.clock_offset_m,
        )?;
        for (i, w) in self.walls.iter().enumerate() {
            finite(&format!("walls[{i}].from"), &w.from)?;
            finite(&format!("walls[{i}].to"), &w.to)?;
            let len = ((w.to[0] - w.from[0]).powi(2) + (w.to[1] - w.from[1]).powi(2)).sqrt();
            if len < 1e-6 {
                return Err(invalid(format!("walls[{i}]"), "zero-length wall"));
            }
            non_negative(
                &format!("walls[{i}].reflection_loss_db"),
                w.reflection_loss_db,
            )?;
        }
        for (i, s) in self.scatterers.iter().enumerate() {
            finite(&format!("scatterers[{i}].position"), &s.position)?;
            non_negative(
                &format!("scatterers[{i}].scattering_loss_db"),
                s.scattering_loss_db,
            )?;
        }
        let m = self.receiver.array_elements;
        let side = f64::from(m).sqrt().round() as u32;
        match self.receiver.array_geometry {
            ArrayGeometry::Square if m == 0 || side * side != m => {
                return Err(invalid(
                    "receiver.array_elements",
                    format!("a square array needs a square number ≥ 1 of elements, got {m}"),
                ));
            }
            ArrayGeometry::Circular if m < 3 => {
                return Err(invalid(
                    "receiver.array_elements",
                    format!("a circular array needs at least 3 elements, got {m}"),
                ));
            }
            _ => {}
        }
        if self.receiver.aoa && m < 4 {
            return Err(invalid(
                "receiver.array_elements",
                "angle estimation needs at least 4 elements",
            ));
        }
        finite("receiver.noise_figure_db", &[self.receiver.noise_figure_db])?;
        if let Some(r) = self.receiver.angular_resolution_rad {
            positive("receiver.angular_resolution_rad", r)?;
        }
        let e = &self.estimator;
        finite(
            "estimator.detection_threshold_db",
            &[e.detection_threshold_db],
        )?;
        non_negative("estimator.tracking_hysteresis_db", e.tracking_hysteresis_db)?;
        if !(e.integration_samples.is_finite() && e.integration_samples >= 1.0) {
            return Err(invalid("estimator.integration_samples", "must be ≥ 1"));
        }
        non_negative("estimator.distance_floor_m", e.distance_floor_m)?;
        non_negative("estimator.aoa_floor_rad", e.aoa_floor_rad)?;
        non_negative("estimator.fading_std_db", e.fading_std_db)?;
        positive("estimator.fading_correlation_m", e.fading_correlation_m)?;
        non_negative("estimator.track_loss_rate_hz", e.track_loss_rate_hz)?;
        non_negative("estimator.min_track_distance_m", e.min_track_distance_m)?;
        if e.max_order > 2 {
            return Err(invalid(
                "estimator.max_order",
                "at most 2 (second-order paths)",
            ));
        }
        non_negative("gyro.noise_std_rad_s", self.gyro.noise_std_rad_s)?;
        finite("gyro.bias_rad_s", &[self.gyro.bias_rad_s])?;
        if self.tracks.is_empty() {
            return Err(invalid("tracks", "at least one track is needed"));
        }
        let mut names = std::collections::HashSet::new();
        for (i, t) in self.tracks.iter().enumerate() {
            if t.name.is_empty() || !names.insert(t.name.as_str()) {
                return Err(invalid(
                    format!("tracks[{i}].name"),
                    "must be non-empty and unique",
                ));
            }
            positive(&format!("tracks[{i}].speed_mps"), t.speed_mps)?;
            non_negative(&format!("tracks[{i}].turn_radius_m"), t.turn_radius_m)?;
            if t.waypoints.len() < 2 {
                return Err(invalid(
                    format!("tracks[{i}].waypoints"),
                    "a track needs at least two waypoints",
                ));
            }
            for (k, w) in t.waypoints.iter().enumerate() {
                finite(&format!("tracks[{i}].waypoints[{k}]"), w)?;
            }
            for k in 1..t.waypoints.len() {
                let (a, b) = (t.waypoints[k - 1], t.waypoints[k]);
                if ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt() < 1e-6 {
                    return Err(invalid(
                        format!("tracks[{i}].waypoints[{k}]"),
                        "repeats the previous waypoint",
                    ));
                }
            }
        }
        Ok(())
    }
}

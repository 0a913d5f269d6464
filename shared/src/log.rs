//! Measurement log `echomap.log.v1` and ground truth `echomap.truth.v1`.
//!
//! The log is what a channel estimator (KEST-like, Gentner et al. 2016 §2.3) plus a gyroscope deliver,
//! one JSON object per line:
//!
//! - line 1, the header: `{"format":"echomap.log.v1","snapshot_rate_hz":10.0,"aoa":true,
//!   "speed":false,"source":"…","sensor":{…}}` — `aoa` says whether components carry an angle
//!   of arrival, `speed` whether snapshots carry a speed measurement (step counter / wheel
//!   odometry), the optional `sensor` block what the sensor is like ([`SensorProfile`]);
//! - every further line, one snapshot: `{"t":0.1,"gyro":0.02,"speed":1.0,"components":[
//!   {"track":3,"d":12.5,"aoa":-0.4,"snr_db":14.2}]}`; a snapshot without a channel estimate
//!   (motion only: the sensor delivers estimates slower than the snapshot rate) says
//!   `"estimate":false` and has no components.
//!
//! `gyro` is the mean heading rate (rad/s, counter-clockwise positive) over the interval that
//! ends at `t`, i.e. the heading turned since the previous snapshot divided by its duration;
//! it is 0 on the first snapshot. `d` is the propagation distance c·τ in metres; `aoa` the
//! direction towards the (virtual) transmitter, counter-clockwise from the heading, in
//! (−π, π]. A `track` id stays the same while the estimator tracks the component
//! continuously; a lost and regained component gets a new id.
//!
//! Ground truth is one JSON document in the agent's local frame (origin at the start
//! position, +x along the initial heading), with the transform to the world frame.

use crate::geometry::Transform2;
pub use crate::sensor::SensorProfile;
use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::io::Write;
use thiserror::Error;

/// the `format` of a measurement log's header
pub const LOG_FORMAT: &str = "echomap.log.v1";
/// the `format` of a ground-truth document
pub const TRUTH_FORMAT: &str = "echomap.truth.v1";

/// The first line of a measurement log.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LogHeader {
    /// `echomap.log.v1`
    pub format: String,
    /// snapshots per second (Hz)
    pub snapshot_rate_hz: f64,
    /// whether components carry an angle of arrival
    pub aoa: bool,
    /// whether snapshots carry a measured speed
    #[serde(default)]
    pub speed: bool,
    /// How long a track stays alive without being detected (s): logs whose detections are
    /// sparse (camera landmarks) keep a track id across short gaps. Absent: a track is alive
    /// only in the snapshots that report it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub track_hold_s: Option<f64>,
    /// Free text: where the log came from (simulator scenario/track/seed, dataset, device).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
    /// What the sensor is like (noise laws, line of sight only, odometry noise): a filter
    /// takes its defaults from it. Absent: the filter's own defaults.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor: Option<SensorProfile>,
}

/// One detected propagation path of a snapshot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Measurement {
    /// track id: the same while the estimator tracks the path continuously
    pub track: u64,
    /// propagation distance c·τ (m)
    pub d: f64,
    /// angle of arrival relative to the heading (rad), present iff the header says `aoa`
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub aoa: Option<f64>,
    /// per-sample signal-to-noise ratio (dB)
    pub snr_db: f64,
}

/// One snapshot: odometry and the paths detected in it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Snapshot {
    /// time (s), strictly increasing
    pub t: f64,
    /// mean heading rate over the interval ending at `t` (rad/s)
    pub gyro: f64,
    /// measured speed (m/s), when the header says `speed`
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub speed: Option<f64>,
    /// the detected paths
    pub components: Vec<Measurement>,
    /// Whether the snapshot carries a channel estimate. `false`: motion only — the sensor
    /// delivered no estimate in this interval (a camera or estimator slower than the snapshot
    /// rate), so the empty `components` are no evidence that any transmitter was out of sight.
    /// Absent: `true`.
    #[serde(default = "yes", skip_serializing_if = "is_true")]
    pub estimate: bool,
}

fn yes() -> bool {
    true
}

fn is_true(b: &bool) -> bool {
    *b
}

/// A parsed and checked measurement log.
#[derive(Debug, Clone, PartialEq)]
pub struct MeasurementLog {
    /// the header line
    pub header: LogHeader,
    /// every snapshot, in time order
    pub snapshots: Vec<Snapshot>,
}

/// A malformed log, with the 1-based line at fault.
#[derive(Debug, Error, PartialEq)]
#[error("line {line}: {message}")]
pub struct LogError {
    /// 1-based line number
    pub line: usize,
    /// what is wrong
    pub message: String,
}

fn bad(line: usize, message: impl Into<String>) -> LogError {
    LogError {
        line,
        message: message.into(),
    }
}

impl MeasurementLog {
    /// Parses and checks a JSON-Lines log. Blank lines are skipped.
    pub fn parse(text: &str) -> Result<Self, LogError> {
        let mut lines = text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty());
        let (hl, htext) = lines
            .next()
            .ok_or_else(|| bad(1, "empty log: expected a header line"))?;
        let header: LogHeader =
            serde_json::from_str(htext).map_err(|e| bad(hl + 1, format!("bad header: {e}")))?;
        if header.format != LOG_FORMAT {
            return Err(bad(
                hl + 1,
                format!("format {:?}, expected {LOG_FORMAT:?}", header.format),
            ));
        }
        if !(header.snapshot_rate_hz.is_finite() && header.snapshot_rate_hz > 0.0) {
            return Err(bad(hl + 1, "snapshot_rate_hz must be a positive number"));
        }
        if let Some(h) = header.track_hold_s
            && !(h.is_finite() && h >= 0.0)
        {
            return Err(bad(hl + 1, "track_hold_s must be a finite number ≥ 0"));
        }
        if let Some(p) = &header.sensor {
            p.validate().map_err(|m| bad(hl + 1, m))?;
        }
        let mut snapshots = Vec::new();
        let mut last_t = f64::NEG_INFINITY;
        for (i, text) in lines {
            let line = i + 1;
            let s: Snapshot =
                serde_json::from_str(text).map_err(|e| bad(line, format!("bad snapshot: {e}")))?;
            check_snapshot(&header, &s, last_t).map_err(|m| bad(line, m))?;
            last_t = s.t;
            snapshots.push(s);
        }
        Ok(MeasurementLog { header, snapshots })
    }

    /// Writes the log as JSON Lines.
    pub fn write_to(&self, mut w: impl Write) -> std::io::Result<()> {
        serde_json::to_writer(&mut w, &self.header)?;
        w.write_all(b"\n")?;
        for s in &self.snapshots {
            serde_json::to_writer(&mut w, s)?;
            w.write_all(b"\n")?;
        }
        Ok(())
    }

    /// The log as JSON Lines text.
    pub fn to_jsonl(&self) -> String {
        let mut buf = Vec::new();
        self.write_to(&mut buf).expect("writing to memory");
        String::from_utf8(buf).expect("serde_json writes UTF-8")
    }
}

fn check_snapshot(h: &LogHeader, s: &Snapshot, last_t: f64) -> Result<(), String> {
    if !s.t.is_finite() {
        return Err("t is not finite".into());
    }
    if s.t <= last_t {
        return Err(format!("t = {} does not increase (previous {last_t})", s.t));
    }
    if !s.gyro.is_finite() {
        return Err("gyro is not finite".into());
    }
    match (h.speed, s.speed) {
        (true, None) => return Err("speed missing (the header declares speed)".into()),
        (false, Some(_)) => return Err("speed present but the header does not declare it".into()),
        (_, Some(v)) if !(v.is_finite() && v >= 0.0) => {
            return Err("speed must be finite and ≥ 0".into());
        }
        _ => {}
    }
    if !s.estimate && !s.components.is_empty() {
        return Err("components present but estimate is false (a motion-only snapshot)".into());
    }
    let mut tracks = HashSet::new();
    for (k, c) in s.components.iter().enumerate() {
        if !tracks.insert(c.track) {
            return Err(format!("components[{k}]: track {} appears twice", c.track));
        }
        if !(c.d.is_finite() && c.d > 0.0) {
            return Err(format!("components[{k}].d must be finite and > 0"));
        }
        if !c.snr_db.is_finite() {
            return Err(format!("components[{k}].snr_db is not finite"));
        }
        match (h.aoa, c.aoa) {
            (true, None) => {
                return Err(format!(
                    "components[{k}].aoa missing (the header declares aoa)"
                ));
            }
            (false, Some(_)) => {
                return Err(format!(
                    "components[{k}].aoa present but the header has aoa=false"
                ));
            }
            (_, Some(a)) if !(a.is_finite() && a.abs() <= std::f64::consts::PI + 1e-9) => {
                return Err(format!("components[{k}].aoa must lie in (−π, π]"));
            }
            _ => {}
        }
    }
    Ok(())
}

/// The user's true pose at one snapshot (local frame).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TruePose {
    /// time (s)
    pub t: f64,
    /// position x (m, local frame)
    pub x: f64,
    /// position y (m, local frame)
    pub y: f64,
    /// heading (rad, counter-clockwise from the initial heading)
    pub heading_rad: f64,
    /// speed (m/s)
    pub speed_mps: f64,
}

/// The true state of the (virtual) transmitter behind one track id (local frame).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrueTransmitter {
    /// the track id of the log
    pub track: u64,
    /// `[x, y, b]`
    pub state: [f64; 3],
    /// `physical`, `reflection`, `scattering`, … (free text)
    pub kind: String,
    /// the propagation path, e.g. `Tx>W3>S1`
    pub path: String,
}

/// The truth behind a simulated or recorded log (`echomap.truth.v1`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GroundTruth {
    /// `echomap.truth.v1`
    pub format: String,
    /// maps local coordinates into the world (scenario) frame
    pub world_from_local: Transform2,
    /// the true pose at every snapshot
    pub poses: Vec<TruePose>,
    /// the true (virtual) transmitter behind every track id
    pub transmitters: Vec<TrueTransmitter>,
}

impl GroundTruth {
    /// Parses and checks a ground-truth document.
    pub fn parse(text: &str) -> Result<Self, String> {
        let g: GroundTruth =
            serde_json::from_str(text).map_err(|e| format!("bad ground truth: {e}"))?;
        if g.format != TRUTH_FORMAT {
            return Err(format!(
                "ground truth format {:?}, expected {TRUTH_FORMAT:?}",
                g.format
            ));
        }
        Ok(g)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = r#"{"format":"echomap.log.v1","snapshot_rate_hz":10.0,"aoa":true}
{"t":0.0,"gyro":0.0,"components":[{"track":1,"d":10.5,"aoa":0.25,"snr_db":12.0}]}

{"t":0.1,"gyro":0.02,"components":[{"track":1,"d":10.4,"aoa":0.26,"snr_db":11.5},{"track":2,"d":20.0,"aoa":-3.1,"snr_db":3.0}]}
"#;

    #[test]
    fn parses_and_roundtrips() {
        let log = MeasurementLog::parse(GOOD).unwrap();
        assert_eq!(log.snapshots.len(), 2);
        assert_eq!(log.snapshots[1].components[1].aoa, Some(-3.1));
        let again = MeasurementLog::parse(&log.to_jsonl()).unwrap();
        assert_eq!(again, log);
    }

    #[test]
    fn motion_only_snapshots_say_so_and_others_stay_unchanged() {
        let text = r#"{"format":"echomap.log.v1","snapshot_rate_hz":10.0,"aoa":true}
{"t":0.0,"gyro":0.0,"components":[]}
{"t":0.1,"gyro":0.0,"components":[],"estimate":false}
"#;
        let log = MeasurementLog::parse(text).unwrap();
        assert!(log.snapshots[0].estimate, "absent means an estimate");
        assert!(!log.snapshots[1].estimate);
        let out = log.to_jsonl();
        // a snapshot with an estimate is written as before (no new field)
        assert_eq!(out.matches("estimate").count(), 1, "{out}");
        assert_eq!(MeasurementLog::parse(&out).unwrap(), log);
    }

    #[test]
    fn a_sensor_profile_in_the_header_is_read_checked_and_optional() {
        let with = r#"{"format":"echomap.log.v1","snapshot_rate_hz":10.0,"aoa":true,"sensor":{"distance_m":{"floor":0.05,"at_0db":0.6},"line_of_sight_only":true}}
{"t":0.0,"gyro":0.0,"components":[]}
"#;
        let log = MeasurementLog::parse(with).unwrap();
        let p = log.header.sensor.as_ref().unwrap();
        assert!(p.line_of_sight_only);
        assert_eq!(p.distance_m.unwrap().at_0db, 0.6);
        assert_eq!(MeasurementLog::parse(&log.to_jsonl()).unwrap(), log);
        // without the block: as before, and nothing is written for it
        let without = MeasurementLog::parse(GOOD).unwrap();
        assert!(without.header.sensor.is_none());
        assert!(!without.to_jsonl().contains("sensor"));
        let bad = with.replace("0.05", "-0.05");
        let e = MeasurementLog::parse(&bad).unwrap_err();
        assert_eq!(e.line, 1);
        assert!(e.message.contains("sensor.distance_m.floor"), "{e}");
    }

    #[test]
    fn errors_name_the_line() {
        let header = r#"{"format":"echomap.log.v1","snapshot_rate_hz":10.0,"aoa":true}"#;
        let ok = r#"{"t":0.0,"gyro":0.0,"components":[]}"#;
        let cases = [
            (
                format!(
                    "{header}\n{ok}\n{{\"t\":0.1,\"gyro\":0.0,\"components\":[{{\"track\":1,\"d\":-1,\"aoa\":0.0,\"snr_db\":1}}]}}"
                ),
                3,
            ),
            (format!("{header}\n{ok}\nnot json"), 3),
            (format!("{header}\n{ok}\n{ok}"), 3),
            (
                format!(
                    "{header}\n{{\"t\":0.0,\"gyro\":0.0,\"components\":[{{\"track\":1,\"d\":1,\"snr_db\":1}}]}}"
                ),
                2,
            ),
            (
                format!("{header}\n{{\"t\":0.0,\"gyro\":0.0,\"components\":[],\"bogus\":1}}"),
                2,
            ),
            (
                "{\"format\":\"other\",\"snapshot_rate_hz\":10.0,\"aoa\":true}".to_string(),
                1,
            ),
            (
                "{\"format\":\"echomap.log.v1\",\"snapshot_rate_hz\":0,\"aoa\":true}".to_string(),
                1,
            ),
            (String::new(), 1),
            (
                format!(
                    "{header}\n{ok}\n{{\"t\":0.1,\"gyro\":0.0,\"estimate\":false,\"components\":[{{\"track\":1,\"d\":1,\"aoa\":0.0,\"snr_db\":1}}]}}"
                ),
                3,
            ),
        ];
        for (text, line) in cases {
            let e = MeasurementLog::parse(&text).unwrap_err();
            assert_eq!(e.line, line, "{text}: {e}");
        }
    }
}

//! The sensor profile of a measurement log: what the receiver and odometry that wrote the log
//! are like, stated once by whoever wrote it (a simulator, an importer, a device's driver).
//!
//! A filter that reads a log takes its measurement and motion noise from the profile, so a
//! user does not have to know the sensor. Every field is optional: what a profile leaves out
//! takes the filter's default, and a log without a profile keeps working as before.
//!
//! The noise of an estimate at per-sample SNR γ (dB) follows the shape of the Cramér–Rao
//! bound plus a floor: `σ(γ) = √(floor² + (at_0db · 10^(−γ/20))²)`. The values are the errors
//! a filter should assume, including whatever the writer allows for what its Gaussian model
//! does not capture (calibration, unresolved clusters).

use serde::{Deserialize, Serialize};

/// A noise law `σ(γ) = √(floor² + (at_0db · 10^(−γ/20))²)` (units of the measured quantity).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoiseLaw {
    /// the error that remains at high SNR
    pub floor: f64,
    /// the SNR-dependent error at an SNR of 0 dB, falling by 10^(−γ/20)
    pub at_0db: f64,
}

impl NoiseLaw {
    /// σ at an SNR of `snr_db`.
    pub fn std(&self, snr_db: f64) -> f64 {
        self.floor.hypot(self.at_0db * 10f64.powf(-snr_db / 20.0))
    }
}

/// The odometry's error model: heading from a gyroscope or wheels, speed from a step counter
/// or wheels.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OdometryNoise {
    /// heading random walk (rad/√s)
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub heading_rad_per_sqrt_s: Option<f64>,
    /// heading error that grows with the turned angle (rad/√rad): wheel odometry, whose
    /// heading error comes from turning rather than from time
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub heading_rad_per_sqrt_rad: Option<f64>,
    /// standard deviation of a measured speed (m/s), for logs that carry speed
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub speed_std_mps: Option<f64>,
    /// standard deviation of the gyroscope's constant bias over the log (rad/s): what a data
    /// sheet states as the bias stability after turn-on (0: calibrated, or no gyroscope)
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gyro_bias_rad_per_s: Option<f64>,
    /// standard deviation of the measured speed's constant relative scale error (0.02 = 2 %):
    /// a step length or wheel radius that is not quite the assumed one
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub speed_scale: Option<f64>,
}

/// What the sensor that wrote a log is like (the optional `sensor` block of the log header).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorProfile {
    /// a free-text name of the sensor (`UTIAS MRCLAM camera`, `simulated 3×3 array`)
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// the distance estimates' error law (m)
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distance_m: Option<NoiseLaw>,
    /// the angle-of-arrival estimates' error law (rad)
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub aoa_rad: Option<NoiseLaw>,
    /// every detected path is a line-of-sight path: clock offsets are zero (landmark
    /// sensors, ranging beacons), so a detection fixes its transmitter's range
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub line_of_sight_only: bool,
    /// whether a transmitter in range is detected depends on the receiver's heading (a
    /// camera's field of view, a directional antenna), not only on where the receiver is:
    /// per-place visibility statistics do not apply
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub heading_dependent_detection: bool,
    /// the odometry's error model
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub odometry: Option<OdometryNoise>,
    /// density of detections of transmitters not seen before, over the measurement space
    /// (1/(m·rad); ToA-only 1/m): low where almost every new track id is a transmitter seen
    /// before (a few landmarks seen again and again), high in rich multipath
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub new_transmitter_density: Option<f64>,
    /// squared Mahalanobis distance (χ²) within which the detections of a known transmitter
    /// fall, under the stated noise laws: wider where the errors have heavier tails than a
    /// Gaussian
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gate_chi2: Option<f64>,
    /// probability that a detection of a known transmitter is a gross error (a path swapped
    /// for another, a misread identity) rather than drawn from the stated noise laws; a
    /// sensor that states nothing is taken to have them
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outlier_probability: Option<f64>,
    /// degrees of freedom ν of a Student-t error law whose scale is the noise laws above: an
    /// estimator whose errors are mostly as stated but now and then many times larger (paths
    /// closer than the resolution, sidelobes of strong paths) states a small ν (3–5); 0 is a
    /// Gaussian
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_dof: Option<f64>,
    /// probability that a detection of a known transmitter comes from another member of
    /// its unresolved cluster (paths closer than the resolution, which the tracker keeps
    /// under one id): the same direction, the clock offset stepped
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub jump_probability: Option<f64>,
    /// root mean square of such a step of the clock offset (m)
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub jump_std_m: Option<f64>,
}

impl SensorProfile {
    /// Checks that every stated number is finite and in its range; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        let mut checks: Vec<(&str, Option<f64>, bool)> = Vec::new();
        let non_negative = false;
        let positive = true;
        if let Some(d) = &self.distance_m {
            checks.push(("sensor.distance_m.floor", Some(d.floor), non_negative));
            checks.push(("sensor.distance_m.at_0db", Some(d.at_0db), non_negative));
        }
        if let Some(a) = &self.aoa_rad {
            checks.push(("sensor.aoa_rad.floor", Some(a.floor), non_negative));
            checks.push(("sensor.aoa_rad.at_0db", Some(a.at_0db), non_negative));
        }
        if let Some(o) = &self.odometry {
            checks.push((
                "sensor.odometry.heading_rad_per_sqrt_s",
                o.heading_rad_per_sqrt_s,
                non_negative,
            ));
            checks.push((
                "sensor.odometry.heading_rad_per_sqrt_rad",
                o.heading_rad_per_sqrt_rad,
                non_negative,
            ));
            checks.push((
                "sensor.odometry.speed_std_mps",
                o.speed_std_mps,
                non_negative,
            ));
            checks.push((
                "sensor.odometry.gyro_bias_rad_per_s",
                o.gyro_bias_rad_per_s,
                non_negative,
            ));
            checks.push(("sensor.odometry.speed_scale", o.speed_scale, non_negative));
        }
        checks.push((
            "sensor.new_transmitter_density",
            self.new_transmitter_density,
            positive,
        ));
        checks.push(("sensor.gate_chi2", self.gate_chi2, positive));
        checks.push(("sensor.noise_dof", self.noise_dof, non_negative));
        checks.push(("sensor.jump_std_m", self.jump_std_m, positive));
        for (field, v) in [
            ("sensor.outlier_probability", self.outlier_probability),
            ("sensor.jump_probability", self.jump_probability),
        ] {
            if let Some(v) = v
                && !(0.0..1.0).contains(&v)
            {
                return Err(format!("{field} must be in [0, 1), got {v}"));
            }
        }
        for (field, v, strict) in checks {
            let Some(v) = v else { continue };
            let ok = v.is_finite() && if strict { v > 0.0 } else { v >= 0.0 };
            if !ok {
                let want = if strict { "> 0" } else { "≥ 0" };
                return Err(format!("{field} must be a finite number {want}, got {v}"));
            }
        }
        for (field, law) in [
            ("sensor.distance_m", self.distance_m),
            ("sensor.aoa_rad", self.aoa_rad),
        ] {
            if let Some(l) = law
                && l.floor == 0.0
                && l.at_0db == 0.0
            {
                return Err(format!("{field}: floor and at_0db are both 0 (no noise)"));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_noise_law_falls_with_snr_to_its_floor() {
        let l = NoiseLaw {
            floor: 0.3,
            at_0db: 0.4,
        };
        assert!((l.std(0.0) - 0.5).abs() < 1e-12);
        assert!((l.std(60.0) - 0.3).abs() < 1e-6);
        assert!(l.std(-10.0) > l.std(0.0));
    }

    #[test]
    fn a_profile_roundtrips_and_leaves_out_what_it_does_not_state() {
        let p = SensorProfile {
            distance_m: Some(NoiseLaw {
                floor: 0.05,
                at_0db: 0.6,
            }),
            line_of_sight_only: true,
            ..Default::default()
        };
        let text = serde_json::to_string(&p).unwrap();
        assert!(!text.contains("aoa_rad") && !text.contains("heading_dependent"));
        assert_eq!(serde_json::from_str::<SensorProfile>(&text).unwrap(), p);
        assert_eq!(
            serde_json::from_str::<SensorProfile>("{}").unwrap(),
            SensorProfile::default()
        );
    }

    #[test]
    fn bad_values_and_unknown_fields_are_named() {
        let bad = |json: &str| {
            let p: SensorProfile = serde_json::from_str(json).unwrap();
            p.validate().unwrap_err()
        };
        assert!(
            bad(r#"{"distance_m":{"floor":-1,"at_0db":0.1}}"#).contains("sensor.distance_m.floor")
        );
        assert!(bad(r#"{"gate_chi2":0}"#).contains("sensor.gate_chi2"));
        assert!(
            bad(r#"{"odometry":{"heading_rad_per_sqrt_s":-0.1}}"#)
                .contains("sensor.odometry.heading_rad_per_sqrt_s")
        );
        assert!(bad(r#"{"aoa_rad":{"floor":0,"at_0db":0}}"#).contains("no noise"));
        let e = serde_json::from_str::<SensorProfile>(r#"{"distance":{}}"#).unwrap_err();
        assert!(e.to_string().contains("unknown field `distance`"), "{e}");
    }
}

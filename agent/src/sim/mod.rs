//! Multipath scenario simulator: ray tracing by the image method (up to second order), a
//! KEST-like channel-estimator model (detection, resolution, SNR-dependent noise, track ids
//! that change when a component is lost), and a gyroscope.

pub mod builtin;
pub mod channel;
pub mod raytrace;
pub mod scenario;
pub mod simulate;
pub mod trajectory;

pub use scenario::{Scenario, ScenarioError};
pub use simulate::{SimOutput, simulate};

/// Speed of light in vacuum (m/s).
pub const SPEED_OF_LIGHT: f64 = 299_792_458.0;

/// A built-in scenario by name (`indoor`, `urban`) or a JSON scenario file; `toa_only` drops
/// the angles of arrival (a single-antenna receiver).
pub fn load_scenario(name_or_path: &str, toa_only: bool) -> anyhow::Result<Scenario> {
    use anyhow::Context;
    let mut s = match builtin::builtin(name_or_path) {
        Some(s) => s,
        None => {
            let path = std::path::Path::new(name_or_path);
            if !path.exists() {
                anyhow::bail!(
                    "unknown scenario {name_or_path:?}: not a built-in ({}) and no such file",
                    builtin::NAMES.join(", ")
                );
            }
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            Scenario::from_json(&text)
                .with_context(|| format!("in scenario file {}", path.display()))?
        }
    };
    if toa_only {
        s.receiver.aoa = false;
    }
    Ok(s)
}

/// The scenario's user tracks: every track but `reference`, in order.
pub fn user_tracks(name_or_path: &str) -> anyhow::Result<Vec<String>> {
    Ok(load_scenario(name_or_path, false)?
        .tracks
        .iter()
        .map(|t| t.name.clone())
        .filter(|n| n != "reference")
        .collect())
}

#[cfg(test)]
mod tests;

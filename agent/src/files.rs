//! Reading and writing the agent's files: measurement-log directories (`log.jsonl`,
//! `truth.json`), maps and prior maps, and the JSON form of a match.

use anyhow::{Context, Result};
use echomap_shared::TransmitterMap;
use echomap_shared::log::{GroundTruth, MeasurementLog};
use std::path::Path;

/// Reads `dir/log.jsonl` and, when present, `dir/truth.json`.
pub fn read_log_dir(dir: &Path) -> Result<(MeasurementLog, Option<GroundTruth>)> {
    let log_path = dir.join("log.jsonl");
    let text = std::fs::read_to_string(&log_path)
        .with_context(|| format!("reading {}", log_path.display()))?;
    let log = MeasurementLog::parse(&text).with_context(|| format!("in {}", log_path.display()))?;
    let truth_path = dir.join("truth.json");
    let truth = if truth_path.exists() {
        let text = std::fs::read_to_string(&truth_path)
            .with_context(|| format!("reading {}", truth_path.display()))?;
        Some(
            GroundTruth::parse(&text)
                .map_err(anyhow::Error::msg)
                .with_context(|| format!("in {}", truth_path.display()))?,
        )
    } else {
        None
    };
    Ok((log, truth))
}

/// Writes `dir/log.jsonl` (`dir` created if missing) through a temporary file renamed into
/// place, so a failed write leaves no half-written log.
pub fn write_log(log: &MeasurementLog, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let log_path = dir.join("log.jsonl");
    let mut tmp = tempfile::NamedTempFile::new_in(dir)
        .with_context(|| format!("creating {}", log_path.display()))?;
    {
        let mut w = std::io::BufWriter::new(tmp.as_file_mut());
        log.write_to(&mut w)
            .with_context(|| format!("writing {}", log_path.display()))?;
        std::io::Write::flush(&mut w)?;
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        tmp.as_file()
            .set_permissions(std::fs::Permissions::from_mode(0o644))?;
    }
    tmp.persist(&log_path)
        .with_context(|| format!("writing {}", log_path.display()))?;
    Ok(())
}

/// Writes `log.jsonl` and `truth.json` into `dir` (created if missing).
pub fn write_log_dir(log: &MeasurementLog, truth: &GroundTruth, dir: &Path) -> Result<()> {
    write_log(log, dir)?;
    let truth_path = dir.join("truth.json");
    std::fs::write(&truth_path, serde_json::to_string(truth)?)
        .with_context(|| format!("writing {}", truth_path.display()))?;
    Ok(())
}

/// An `echomap.map.v1` file.
pub fn read_map(path: &Path) -> Result<TransmitterMap> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    TransmitterMap::from_json(&text).with_context(|| format!("in {}", path.display()))
}

/// A prior map file: a bare `echomap.map.v1` map or a served map document.
pub fn read_prior(path: &Path) -> Result<TransmitterMap> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    match TransmitterMap::from_json(&text) {
        Ok(m) => Ok(m),
        Err(bare) => crate::client::parse_prior(&text)
            .map(|p| p.map)
            .map_err(|doc| {
                anyhow::anyhow!(
                    "{} is neither an echomap.map.v1 map ({bare}) nor a served map document ({doc})",
                    path.display()
                )
            }),
    }
}

/// JSON form of a match result (ids instead of indices).
pub fn match_json(
    r: &echomap_shared::matching::MatchResult,
    user: &TransmitterMap,
    prior: &TransmitterMap,
) -> serde_json::Value {
    let t = echomap_shared::Transform2::from_isometry(&r.map_from_agent);
    serde_json::json!({
        "accepted": r.accepted,
        "decision": r.decision.as_str(),
        "map_from_agent": t,
        "correspondences": r.correspondences.iter().map(|&(u, p)| [user.transmitters()[u].id.clone(), prior.transmitters()[p].id.clone()]).collect::<Vec<_>>(),
        "residuals_m": r.residuals_m,
        "inliers": r.inliers,
        "score": if r.score.is_finite() { r.score } else { 0.0 },
        "visibility_score": r.visibility_score,
        "iterations": r.iterations,
        "reason": r.reason,
    })
}

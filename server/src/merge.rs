//! What happens to an upload: the first one initializes a map (it defines the map frame), later
//! ones are matched against the current version (Ulmschneider et al. 2021 §III, RANSAC) and merged weighted by
//! reliability (Ulmschneider et al. 2021 §IV). Pure and synchronous: the server runs it on the blocking pool.
//!
//! The RANSAC draws are seeded from the SHA-256 of the request body, so an upload meets the same
//! draws whenever it is processed: a rollback's replay rebuilds exactly the map that merging the
//! remaining uploads afresh would give.

use crate::api::{ContributionRequest, Correspondence};
use echomap_shared::map::TransmitterMap;
use echomap_shared::matching::{MatchConfig, MatchResult, match_maps};
use echomap_shared::merging::{MergeConfig, MergeStats, merge_maps};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sha2::{Digest, Sha256};
use std::sync::Arc;

/// Hex SHA-256 of a request body.
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// RANSAC seed of an upload: the first 8 bytes of its body's SHA-256.
pub fn seed_of(sha256_hex: &str) -> u64 {
    let bytes = hex::decode(&sha256_hex[..16]).expect("hex digest");
    u64::from_le_bytes(bytes.try_into().expect("8 bytes"))
}

#[derive(Debug, Clone)]
pub enum Outcome {
    /// first contribution: the map is the upload, in its own frame
    Initialized { map: Arc<TransmitterMap> },
    Merged {
        map: Arc<TransmitterMap>,
        matched: MatchResult,
        stats: MergeStats,
    },
    Rejected {
        reason: String,
        matched: MatchResult,
    },
}

/// Matches `user` (agent frame) against `prior` (map frame, `None` before the first version)
/// and merges it.
pub fn integrate(
    prior: Option<&TransmitterMap>,
    user: &Arc<TransmitterMap>,
    seed: u64,
    match_cfg: &MatchConfig,
    merge_cfg: &MergeConfig,
) -> anyhow::Result<Outcome> {
    let Some(prior) = prior.filter(|p| !p.is_empty()) else {
        return Ok(Outcome::Initialized { map: user.clone() });
    };
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let matched = match_maps(user, prior, match_cfg, &mut rng);
    if !matched.accepted {
        let reason = matched
            .reason
            .clone()
            .unwrap_or_else(|| "no consistent transform".to_owned());
        return Ok(Outcome::Rejected { reason, matched });
    }
    let (map, stats) = merge_maps(
        prior,
        user,
        &matched.map_from_agent,
        &matched.correspondences,
        merge_cfg,
    )?;
    // merge_maps builds its result through TransmitterMap::new, which validates it (finite
    // numbers, SPD covariances, limits): nothing invalid can be stored or served.
    Ok(Outcome::Merged {
        map: Arc::new(map),
        matched,
        stats,
    })
}

/// The correspondences of a match by transmitter id.
pub fn correspondences(
    user: &TransmitterMap,
    prior: &TransmitterMap,
    m: &MatchResult,
) -> Vec<Correspondence> {
    m.correspondences
        .iter()
        .enumerate()
        .map(|(k, &(ui, pi))| Correspondence {
            agent: user.transmitters()[ui].id.clone(),
            map: prior.transmitters()[pi].id.clone(),
            residual_m: m.residuals_m.get(k).copied().unwrap_or(0.0),
        })
        .collect()
}

/// Rebuilds a map by integrating stored uploads (verbatim request bodies) in order. Uploads
/// that no longer match are left out and reported.
pub fn replay(
    uploads: &[(i64, String)],
    match_cfg: &MatchConfig,
    merge_cfg: &MergeConfig,
) -> anyhow::Result<(Option<Arc<TransmitterMap>>, Vec<i64>)> {
    let mut map: Option<Arc<TransmitterMap>> = None;
    let mut dropped = Vec::new();
    for (id, body) in uploads {
        let req: ContributionRequest = serde_json::from_str(body)?;
        let user = Arc::new(TransmitterMap::from_doc(req.map)?);
        let seed = seed_of(&sha256_hex(body.as_bytes()));
        match integrate(map.as_deref(), &user, seed, match_cfg, merge_cfg)? {
            Outcome::Initialized { map: m } | Outcome::Merged { map: m, .. } => map = Some(m),
            Outcome::Rejected { .. } => dropped.push(*id),
        }
    }
    Ok((map, dropped))
}

//! The wire contract of the map server's HTTP API v1: request and response bodies. Their JSON
//! shape is the API; the server generates its OpenAPI document from these types (feature
//! `openapi`), and clients use the same types, so neither side can drift from the other.

use crate::geometry::Transform2;
use crate::map::wire::MapDoc;
use serde::{Deserialize, Serialize};

/// A map in the list of maps.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct MapInfo {
    /// map name
    pub name: String,
    /// current version; 0 before the first accepted contribution
    pub version: i64,
    /// accepted contributions merged into the current version
    pub contributions: i64,
    /// reads need a token allowed for this map
    pub private: bool,
    /// RFC 3339
    pub created: String,
    /// when the current version was committed, RFC 3339 (absent before the first)
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub updated: Option<String>,
}

/// The list of maps.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct MapList {
    /// every map, by name
    pub maps: Vec<MapInfo>,
}

/// Body of `PUT /v1/maps/{map}` (optional).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(deny_unknown_fields)]
pub struct CreateMap {
    /// reads need a token allowed for this map
    #[serde(default)]
    pub private: bool,
}

/// A map version: the `echomap.map.v1` document in the map frame plus its identity.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct MapVersion {
    /// map name
    pub map: String,
    /// version number, 1 for the first accepted contribution
    pub version: i64,
    /// accepted contributions merged into this version
    pub contributions: i64,
    /// the `echomap.map.v1` document (map frame)
    #[serde(flatten)]
    pub doc: MapDoc,
}

/// Body of `POST /v1/maps/{map}/contributions`: a user map in the agent's frame and metadata.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(deny_unknown_fields)]
pub struct ContributionRequest {
    /// label of the device/agent (the authenticated contributor comes from the token)
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub contributor: Option<String>,
    /// run id chosen by the agent
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub run: Option<String>,
    /// distance the user walked, metres
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub traveled_m: Option<f64>,
    /// the user map, `echomap.map.v1`, in the agent's frame
    pub map: MapDoc,
}

/// Body of `POST /v1/maps/{map}/match`. Extra fields (e.g. a whole contribution) are ignored.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct MatchRequest {
    /// the (partial) user map to match, agent frame
    pub map: MapDoc,
}

/// One matched pair: a transmitter of the upload and one of the map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Correspondence {
    /// transmitter id in the upload
    pub agent: String,
    /// transmitter id in the map
    pub map: String,
    /// position residual after the transform, metres
    pub residual_m: f64,
}

/// 201 answer to an accepted contribution (replayed byte for byte on an idempotent retry).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct ContributionAccepted {
    /// id of the stored contribution
    pub contribution: i64,
    /// map name
    pub map: String,
    /// `accepted`
    pub status: String,
    /// the version this contribution produced
    pub version: i64,
    /// true when this was the first contribution: it defines the map frame
    pub initialized: bool,
    /// takes agent-frame coordinates into the map frame
    pub map_from_agent: Transform2,
    /// the matched pairs
    pub correspondences: Vec<Correspondence>,
    /// number of inlier pairs
    pub inliers: usize,
    /// score of the chosen hypothesis (location + visibility)
    pub score: f64,
    /// transmitters merged into existing ones
    pub merged: usize,
    /// transmitters added as new
    pub added: usize,
    /// transmitters in the new version
    pub transmitters: usize,
}

/// Answer of `POST /v1/maps/{map}/match` (nothing is written).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct MatchAnswer {
    /// whether the match passed the acceptance test
    pub accepted: bool,
    /// map version matched against
    pub version: i64,
    /// takes map coordinates into the agent frame (present when accepted)
    pub agent_from_map: Option<Transform2>,
    /// the inverse: agent frame into map frame
    pub map_from_agent: Option<Transform2>,
    /// the matched pairs
    pub correspondences: Vec<Correspondence>,
    /// number of inlier pairs
    pub inliers: usize,
    /// score of the chosen hypothesis
    pub score: f64,
    /// why the match was refused, when it was
    pub reason: Option<String>,
}

/// A stored contribution with its outcome.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct ContributionInfo {
    /// contribution id
    pub id: i64,
    /// the contributor its token names
    pub contributor: String,
    /// the agent/device label sent with it
    pub agent: Option<String>,
    /// run id chosen by the agent
    pub run: Option<String>,
    /// distance the user walked, metres
    pub traveled_m: Option<f64>,
    /// RFC 3339
    pub received: String,
    /// accepted, rejected or rolled_back
    pub status: String,
    /// why it was refused or dropped, if it was
    pub reason: Option<String>,
    /// transmitters in the uploaded map
    pub transmitters: i64,
    /// the map version it was matched against
    pub matched_version: Option<i64>,
    /// the version it produced, if accepted
    pub version: Option<i64>,
    /// takes agent-frame coordinates into the map frame, when matched
    pub map_from_agent: Option<Transform2>,
    /// number of inlier pairs, when matched
    pub inliers: Option<i64>,
    /// score of the match, when matched
    pub score: Option<f64>,
    /// transmitters merged into existing ones
    pub merged: Option<i64>,
    /// transmitters added as new
    pub added: Option<i64>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
/// A page of the contributions list.
pub struct ContributionPage {
    /// contributions in id order
    pub contributions: Vec<ContributionInfo>,
    /// pass as `after` for the next page; absent on the last page
    pub next: Option<i64>,
}

/// Answer of a rollback.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct RolledBack {
    /// id of the contribution rolled back
    pub rolled_back: i64,
    /// the new version (the map rebuilt without the contribution)
    pub version: i64,
    /// transmitters in the new version
    pub transmitters: usize,
    /// accepted contributions that no longer matched during the replay (left out)
    pub dropped: Vec<i64>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
/// Answer of the health checks.
pub struct Health {
    /// `ok` when the server is live (and, for `/readyz`, its database reachable)
    pub status: String,
}

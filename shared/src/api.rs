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
    pub name: String,
    /// current version; 0 before the first accepted contribution
    pub version: i64,
    /// accepted contributions merged into the current version
    pub contributions: i64,
    pub private: bool,
    /// RFC 3339
    pub created: String,
}

/// The list of maps.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct MapList {
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
    pub map: String,
    pub version: i64,
    pub contributions: i64,
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
    pub map: MapDoc,
}

/// Body of `POST /v1/maps/{map}/match`. Extra fields (e.g. a whole contribution) are ignored.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct MatchRequest {
    pub map: MapDoc,
}

/// One matched pair: a transmitter of the upload and one of the map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Correspondence {
    pub agent: String,
    pub map: String,
    /// position residual after the transform, metres
    pub residual_m: f64,
}

/// 201 answer to an accepted contribution (replayed byte for byte on an idempotent retry).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct ContributionAccepted {
    pub contribution: i64,
    pub map: String,
    pub status: String,
    /// the version this contribution produced
    pub version: i64,
    /// true when this was the first contribution: it defines the map frame
    pub initialized: bool,
    /// takes agent-frame coordinates into the map frame
    pub map_from_agent: Transform2,
    pub correspondences: Vec<Correspondence>,
    pub inliers: usize,
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
    pub accepted: bool,
    /// map version matched against
    pub version: i64,
    /// takes map coordinates into the agent frame (present when accepted)
    pub agent_from_map: Option<Transform2>,
    /// the inverse: agent frame into map frame
    pub map_from_agent: Option<Transform2>,
    pub correspondences: Vec<Correspondence>,
    pub inliers: usize,
    pub score: f64,
    pub reason: Option<String>,
}

/// A stored contribution with its outcome.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct ContributionInfo {
    pub id: i64,
    pub contributor: String,
    pub agent: Option<String>,
    pub run: Option<String>,
    pub traveled_m: Option<f64>,
    /// RFC 3339
    pub received: String,
    /// accepted, rejected or rolled_back
    pub status: String,
    pub reason: Option<String>,
    pub transmitters: i64,
    pub matched_version: Option<i64>,
    /// the version it produced, if accepted
    pub version: Option<i64>,
    pub map_from_agent: Option<Transform2>,
    pub inliers: Option<i64>,
    pub score: Option<f64>,
    pub merged: Option<i64>,
    pub added: Option<i64>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
/// A page of the contributions list.
pub struct ContributionPage {
    pub contributions: Vec<ContributionInfo>,
    /// pass as `after` for the next page; absent on the last page
    pub next: Option<i64>,
}

/// Answer of a rollback.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct RolledBack {
    pub rolled_back: i64,
    /// the new version (the map rebuilt without the contribution)
    pub version: i64,
    pub transmitters: usize,
    /// accepted contributions that no longer matched during the replay (left out)
    pub dropped: Vec<i64>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
/// Answer of the health checks.
pub struct Health {
    pub status: String,
}

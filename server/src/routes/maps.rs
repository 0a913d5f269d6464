//! Maps: list, create, current version (conditional GET), past versions, read-only matching.

use super::common::{authorize_read, authorize_write, json_response, rfc3339, validate_map};
use super::extract::{JsonBytes, parse_json};
use crate::api::{CreateMap, MapInfo, MapList, MatchAnswer, MatchRequest};
use crate::error::{ApiError, ApiResult, Problem};
use crate::merge::{correspondences, seed_of, sha256_hex};
use crate::model::MapName;
use crate::state::SharedState;
use crate::storage::MapRow;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use echomap_shared::geometry::Transform2;
use echomap_shared::map::TransmitterMap;
use echomap_shared::matching::match_maps;
use rand::SeedableRng;

fn info(row: &MapRow) -> MapInfo {
    MapInfo {
        name: row.name.clone(),
        version: row.current_version,
        contributions: row.contributions,
        private: row.private,
        created: rfc3339(row.created_ms),
        updated: row.updated_ms.map(rfc3339),
    }
}

fn to_json<T: serde::Serialize>(status: StatusCode, v: &T) -> ApiResult<Response> {
    Ok(json_response(
        status,
        serde_json::to_vec(v).map_err(anyhow::Error::from)?,
    ))
}

/// List the maps readable without a token (and the private ones the token may read).
#[utoipa::path(get, path = "/v1/maps", tag = "maps",
    responses((status = 200, body = MapList)))]
pub async fn list_maps(State(app): State<SharedState>, headers: HeaderMap) -> ApiResult<Response> {
    let who = app.tokens.from_headers(&headers).ok().flatten();
    let maps = app
        .storage
        .maps()
        .await?
        .iter()
        .filter(|m| !m.private || who.as_ref().is_some_and(|w| w.may_write(&m.name)))
        .map(info)
        .collect();
    to_json(StatusCode::OK, &MapList { maps })
}

/// Create a map (idempotent: an existing map with the same settings answers 200).
#[utoipa::path(put, path = "/v1/maps/{map}", tag = "maps",
    params(("map" = String, Path, description = "1–64 characters of [a-z0-9._-]")),
    request_body(content = Option<CreateMap>, description = "optional settings"),
    responses(
        (status = 201, body = MapInfo, description = "created"),
        (status = 200, body = MapInfo, description = "already existed"),
        (status = 400, body = Problem), (status = 401, body = Problem), (status = 403, body = Problem),
        (status = 409, body = Problem, description = "exists with other settings"),
        (status = 429, body = Problem)))]
pub async fn put_map(
    State(app): State<SharedState>,
    Path(name): Path<String>,
    headers: HeaderMap,
    JsonBytes(body): JsonBytes,
) -> ApiResult<Response> {
    let name = MapName::parse(&name)?;
    let who = authorize_write(&app, &name, &headers)?;
    app.check_rate(&who).await?;
    // no body, or `null`: the default settings
    let settings: CreateMap = if body.iter().all(u8::is_ascii_whitespace) {
        CreateMap::default()
    } else {
        // an object (or null): serde would also read a struct from a JSON array
        let start = body.trim_ascii_start();
        if !start.starts_with(b"{") && !start.starts_with(b"null") {
            return Err(ApiError::Invalid {
                field: String::new(),
                detail: "the body must be a JSON object (or null)".into(),
            });
        }
        parse_json::<Option<CreateMap>>(&body)?.unwrap_or_default()
    };
    let (row, created) = app
        .storage
        .create_map(name.as_str(), settings.private)
        .await?;
    if !created && row.private != settings.private {
        return Err(ApiError::Conflict(format!(
            "map {name:?} exists with private = {}",
            row.private
        )));
    }
    if created {
        tracing::info!(map = %name, contributor = %who.contributor, "map created");
    }
    let mut resp = to_json(
        if created {
            StatusCode::CREATED
        } else {
            StatusCode::OK
        },
        &info(&row),
    )?;
    if let Ok(loc) = HeaderValue::from_str(&format!("/v1/maps/{name}")) {
        resp.headers_mut().insert(header::LOCATION, loc);
    }
    Ok(resp)
}

fn etag_matches(headers: &HeaderMap, etag: &str) -> bool {
    headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .map(|t| t.trim().trim_start_matches("W/"))
        .any(|t| t == "*" || t == etag)
}

/// The current map in the map frame, with its version and contribution count. `ETag` is the
/// version; `If-None-Match` with it answers 304.
#[utoipa::path(get, path = "/v1/maps/{map}", tag = "maps",
    params(("map" = String, Path)),
    responses(
        (status = 200, body = crate::api::MapVersion, headers(("ETag" = String))),
        (status = 304, description = "not modified"),
        (status = 400, body = Problem), (status = 401, body = Problem), (status = 403, body = Problem),
        (status = 404, body = Problem)))]
pub async fn get_map(
    State(app): State<SharedState>,
    Path(name): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let name = MapName::parse(&name)?;
    let row = app.map_ref(name.as_str()).await?;
    authorize_read(&app, &row, &headers)?;
    let cur = app.current(&row).await?;
    let etag = format!("\"{}\"", cur.version);
    let etag_value = HeaderValue::from_str(&etag).expect("digits and quotes");
    let cache = HeaderValue::from_static("no-cache");
    if etag_matches(&headers, &etag) {
        return Ok((
            StatusCode::NOT_MODIFIED,
            [(header::ETAG, etag_value), (header::CACHE_CONTROL, cache)],
        )
            .into_response());
    }
    let mut resp = json_response(StatusCode::OK, cur.body.clone());
    resp.headers_mut().insert(header::ETAG, etag_value);
    resp.headers_mut().insert(header::CACHE_CONTROL, cache);
    Ok(resp)
}

/// A past version of a map.
#[utoipa::path(get, path = "/v1/maps/{map}/versions/{n}", tag = "maps",
    params(("map" = String, Path), ("n" = i64, Path, description = "version number ≥ 1")),
    responses((status = 200, body = crate::api::MapVersion), (status = 404, body = Problem)))]
pub async fn get_version(
    State(app): State<SharedState>,
    Path((name, n)): Path<(String, String)>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let name = MapName::parse(&name)?;
    let n: i64 = n.parse().map_err(|_| ApiError::BadRequest {
        detail: format!(
            "version must be an integer ≥ 1, got {:?}",
            crate::model::truncate(&n, 40)
        ),
    })?;
    let row = app.map_ref(name.as_str()).await?;
    authorize_read(&app, &row, &headers)?;
    let v = app
        .storage
        .version(row.id, n)
        .await?
        .ok_or_else(|| ApiError::NotFound(format!("map {name:?} has no version {n}")))?;
    let map =
        TransmitterMap::from_json(&v.body).map_err(|e| anyhow::anyhow!("stored version: {e}"))?;
    let accepted_then = app.storage.contributions_merged_up_to(row.id, n).await?;
    let doc = echomap_shared::map::wire::MapDoc::from(map);
    let mut resp = to_json(
        StatusCode::OK,
        &crate::api::MapVersion {
            map: row.name.clone(),
            version: v.number,
            contributions: accepted_then,
            doc,
        },
    )?;
    resp.headers_mut().insert(
        header::ETAG,
        HeaderValue::from_str(&format!("\"{}\"", v.number)).expect("digits"),
    );
    Ok(resp)
}

/// Match a (partial) user map against the current map; nothing is written. Returns the
/// transform taking map coordinates into the agent frame.
#[utoipa::path(post, path = "/v1/maps/{map}/match", tag = "maps",
    params(("map" = String, Path)),
    request_body = MatchRequest,
    responses((status = 200, body = MatchAnswer), (status = 404, body = Problem),
        (status = 422, body = Problem), (status = 429, body = Problem)))]
pub async fn match_map(
    State(app): State<SharedState>,
    Path(name): Path<String>,
    headers: HeaderMap,
    JsonBytes(body): JsonBytes,
) -> ApiResult<Response> {
    let name = MapName::parse(&name)?;
    let row = app.map_ref(name.as_str()).await?;
    authorize_read(&app, &row, &headers)?;
    if let Some(who) = app.tokens.from_headers(&headers)? {
        app.check_rate(&who).await?;
    }
    let req: MatchRequest = parse_json(&body)?;
    let user = validate_map(req.map, "map")?;
    let cur = app.current(&row).await?;
    let Some(prior) = cur.map.clone().filter(|m| !m.is_empty()) else {
        return to_json(
            StatusCode::OK,
            &MatchAnswer {
                accepted: false,
                version: cur.version,
                agent_from_map: None,
                map_from_agent: None,
                correspondences: vec![],
                inliers: 0,
                score: 0.0,
                reason: Some("the map has no transmitters yet".into()),
            },
        );
    };
    let seed = seed_of(&sha256_hex(&body));
    let cfg = app.match_cfg.clone();
    let started = std::time::Instant::now();
    let answer = tokio::task::spawn_blocking(move || {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let m = match_maps(&user, &prior, &cfg, &mut rng);
        let score = if m.score.is_finite() { m.score } else { 0.0 };
        MatchAnswer {
            accepted: m.accepted,
            version: cur.version,
            agent_from_map: m
                .accepted
                .then(|| Transform2::from_isometry(&m.map_from_agent.inverse())),
            map_from_agent: m
                .accepted
                .then(|| Transform2::from_isometry(&m.map_from_agent)),
            correspondences: correspondences(&user, &prior, &m),
            inliers: m.inliers,
            score,
            reason: m.reason.clone(),
        }
    })
    .await
    .map_err(anyhow::Error::from)?;
    metrics::histogram!("echomap_match_duration_seconds").record(started.elapsed().as_secs_f64());
    to_json(StatusCode::OK, &answer)
}

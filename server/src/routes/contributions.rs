//! Contributions: upload (idempotent, matched and merged into a new version), list, roll back.

use super::common::{authorize_read, authorize_write, json_response, rfc3339, validate_map};
use super::extract::{JsonBytes, parse_json};
use crate::api::{
    ContributionAccepted, ContributionInfo, ContributionPage, ContributionRequest, RolledBack,
};
use crate::error::{ApiError, ApiResult, PROBLEM_JSON, Problem};
use crate::merge::{replay, sha256_hex};
use crate::model::{IdempotencyKey, MapName};
use crate::state::{SharedState, render_json};
use crate::storage::{CommitError, NewContribution, NewVersion, StoredResponse};
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use echomap_shared::map::TransmitterMap;
use serde::Deserialize;
use std::sync::Arc;

fn check_text(field: &str, v: &Option<String>) -> ApiResult<()> {
    match v {
        Some(s) if s.is_empty() || s.chars().count() > 128 || s.chars().any(char::is_control) => {
            Err(ApiError::Invalid {
                field: field.to_owned(),
                detail: "must be 1–128 printable characters".into(),
            })
        }
        _ => Ok(()),
    }
}

/// The response stored with a contribution (201 JSON or a problem document).
fn stored_reply(status: u16, body: Vec<u8>) -> Response {
    let status = StatusCode::from_u16(status).unwrap_or(StatusCode::OK);
    let ct = if status.is_success() {
        "application/json"
    } else {
        PROBLEM_JSON
    };
    let mut resp = (status, body).into_response();
    resp.headers_mut()
        .insert(header::CONTENT_TYPE, HeaderValue::from_static(ct));
    resp
}

fn replay_stored(s: StoredResponse) -> Response {
    let mut resp = stored_reply(s.response_status as u16, s.response_body);
    resp.headers_mut()
        .insert("idempotent-replayed", HeaderValue::from_static("true"));
    resp
}

/// Upload a user map (agent frame) with metadata. Requires `Idempotency-Key`. The first
/// contribution defines the map frame; later ones are matched (RANSAC) and merged into a new
/// version committed with the contribution. Uploads that match no part of the map
/// (`unmatched`) or share too little with it to decide (`undecided`) are stored as rejected → 422.
#[utoipa::path(post, path = "/v1/maps/{map}/contributions", tag = "contributions",
    params(("map" = String, Path),
        ("Idempotency-Key" = String, Header, description = "unique per upload; retries reuse it")),
    request_body = ContributionRequest,
    responses(
        (status = 201, body = ContributionAccepted),
        (status = 400, body = Problem, description = "malformed JSON, bad name, missing Idempotency-Key"),
        (status = 401, body = Problem), (status = 403, body = Problem), (status = 404, body = Problem),
        (status = 409, body = Problem, description = "same key still in progress"),
        (status = 413, body = Problem), (status = 415, body = Problem),
        (status = 422, body = Problem, description = "invalid map (field named), key reused with another body, or refused by the matcher: `unmatched` or `undecided` (stored as rejected, map unchanged)"),
        (status = 429, body = Problem, description = "write rate limit, or the contributor's quota of rejected contributions, exceeded (Retry-After)")))]
pub async fn post_contribution(
    State(app): State<SharedState>,
    Path(name): Path<String>,
    headers: HeaderMap,
    JsonBytes(body): JsonBytes,
) -> ApiResult<Response> {
    let name = MapName::parse(&name)?;
    let who = authorize_write(&app, &name, &headers)?;
    let row = app.map_ref(name.as_str()).await?;
    let key = IdempotencyKey::from_headers(&headers)?;
    let sha = sha256_hex(&body);
    let lookup = |s: StoredResponse| {
        if s.request_sha256 == sha {
            Ok(replay_stored(s))
        } else {
            Err(ApiError::IdempotencyMismatch)
        }
    };
    if let Some(s) = app
        .storage
        .stored_response(row.id, &who.contributor, key.as_str())
        .await?
    {
        return lookup(s);
    }
    app.check_rate(&who).await?;
    app.check_quota(&who).await?;
    let _in_flight = app.begin(row.id, &who.contributor, key.as_str())?;
    // the first request with this key may have completed between the lookup and `begin`
    if let Some(s) = app
        .storage
        .stored_response(row.id, &who.contributor, key.as_str())
        .await?
    {
        return lookup(s);
    }
    let ContributionRequest {
        contributor: agent,
        run,
        traveled_m,
        map,
    } = parse_json(&body)?;
    check_text("contributor", &agent)?;
    check_text("run", &run)?;
    if let Some(d) = traveled_m
        && !(d.is_finite() && d >= 0.0)
    {
        return Err(ApiError::Invalid {
            field: "traveled_m".into(),
            detail: format!("must be a finite distance ≥ 0, got {d}"),
        });
    }
    let user = Arc::new(validate_map(map, "map")?);
    if user.is_empty() {
        return Err(ApiError::Invalid {
            field: "map.transmitters".into(),
            detail: "a contribution needs at least one transmitter".into(),
        });
    }
    let body_text = String::from_utf8(body.to_vec()).map_err(|_| ApiError::MalformedJson {
        detail: "body is not UTF-8".into(),
    })?;

    let contribution = NewContribution {
        contributor: who.contributor.clone(),
        agent,
        run,
        traveled_m,
        idempotency_key: key.as_str().to_owned(),
        request_sha256: sha.clone(),
        body: body_text,
        accepted: true,
        reason: None,
        transmitters: user.len() as i64,
        transform: None,
        inliers: None,
        score: None,
        merged: None,
        added: None,
    };
    let (reply, answer) = tokio::sync::oneshot::channel();
    crate::worker::submit(
        &app,
        &row,
        crate::worker::Job {
            user,
            sha256: sha.clone(),
            contribution,
            reply,
        },
    )?;
    let (status, bytes) = answer
        .await
        .map_err(|_| ApiError::Unavailable("the merge worker dropped the upload".into()))??;
    Ok(stored_reply(status, bytes))
}

#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct PageQuery {
    /// return contributions with id greater than this (default 0)
    #[serde(default)]
    after: i64,
    /// page size, 1–1000 (default 100)
    #[serde(default = "default_limit")]
    limit: i64,
}

fn default_limit() -> i64 {
    100
}

/// Contributions of a map, oldest first, with status and match statistics (keyset paging).
#[utoipa::path(get, path = "/v1/maps/{map}/contributions", tag = "contributions",
    params(("map" = String, Path), PageQuery),
    responses((status = 200, body = ContributionPage), (status = 404, body = Problem)))]
pub async fn list_contributions(
    State(app): State<SharedState>,
    Path(name): Path<String>,
    query: Result<Query<PageQuery>, axum::extract::rejection::QueryRejection>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let name = MapName::parse(&name)?;
    let Query(q) = query.map_err(|e| ApiError::BadRequest {
        detail: e.body_text(),
    })?;
    if !(1..=1000).contains(&q.limit) {
        return Err(ApiError::BadRequest {
            detail: format!("limit must lie in 1..=1000, got {}", q.limit),
        });
    }
    if q.after < 0 {
        return Err(ApiError::BadRequest {
            detail: format!("after must be ≥ 0, got {}", q.after),
        });
    }
    let row = app.map_ref(name.as_str()).await?;
    authorize_read(&app, &row, &headers)?;
    let rows = app
        .storage
        .contributions(row.id, q.after, q.limit + 1)
        .await?;
    let more = rows.len() as i64 > q.limit;
    let contributions: Vec<ContributionInfo> = rows
        .into_iter()
        .take(q.limit as usize)
        .map(|r| ContributionInfo {
            id: r.id,
            contributor: r.contributor,
            agent: r.agent,
            run: r.run,
            traveled_m: r.traveled_m,
            received: rfc3339(r.received_ms),
            status: r.status,
            reason: r.reason,
            transmitters: r.transmitters,
            matched_version: r.matched_version,
            version: r.version,
            map_from_agent: r.transform.and_then(|t| serde_json::from_str(&t).ok()),
            inliers: r.inliers,
            score: r.score,
            merged: r.merged,
            added: r.added,
        })
        .collect();
    let next = if more {
        contributions.last().map(|c| c.id)
    } else {
        None
    };
    let body = serde_json::to_vec(&ContributionPage {
        contributions,
        next,
    })
    .map_err(anyhow::Error::from)?;
    Ok(json_response(StatusCode::OK, body))
}

/// Roll a contribution back: the map is rebuilt by replaying the remaining accepted
/// contributions in their original order and committed as a new version; history is kept.
/// Allowed to the contribution's contributor and to operators (token scope `*`).
#[utoipa::path(delete, path = "/v1/maps/{map}/contributions/{id}", tag = "contributions",
    params(("map" = String, Path), ("id" = i64, Path)),
    responses((status = 200, body = RolledBack), (status = 401, body = Problem),
        (status = 403, body = Problem), (status = 404, body = Problem),
        (status = 409, body = Problem, description = "not an accepted contribution")))]
pub async fn delete_contribution(
    State(app): State<SharedState>,
    Path((name, id)): Path<(String, String)>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let name = MapName::parse(&name)?;
    let who = authorize_write(&app, &name, &headers)?;
    let id: i64 = id.parse().map_err(|_| ApiError::BadRequest {
        detail: "contribution id must be an integer".into(),
    })?;
    let row = app.map_ref(name.as_str()).await?;
    app.check_rate(&who).await?;
    let lock = app.map_lock(row.id);
    let _merging = lock.lock().await;
    loop {
        let (status, owner) = app
            .storage
            .contribution_status(row.id, id)
            .await?
            .ok_or_else(|| ApiError::NotFound(format!("map {name:?} has no contribution {id}")))?;
        if owner != who.contributor && !who.is_operator() {
            return Err(ApiError::Forbidden(
                "only its contributor or an operator may roll a contribution back".into(),
            ));
        }
        if status != "accepted" {
            return Err(ApiError::Conflict(format!(
                "contribution {id} is {status}, not accepted"
            )));
        }
        let cur = app.current(&row).await?;
        let uploads = app.storage.accepted_bodies(row.id, id).await?;
        let (mcfg, gcfg) = (app.match_cfg.clone(), app.merge_cfg.clone());
        let hex = cur
            .map
            .as_ref()
            .map_or(echomap_shared::map::DEFAULT_HEX_SIZE_M, |m| m.hex_size_m());
        let (rebuilt, dropped) =
            tokio::task::spawn_blocking(move || replay(&uploads, &mcfg, &gcfg))
                .await
                .map_err(anyhow::Error::from)??;
        let rebuilt = match rebuilt {
            Some(m) => m,
            None => Arc::new(TransmitterMap::empty(hex).map_err(|e| anyhow::anyhow!("{e}"))?),
        };
        let v = NewVersion {
            body: serde_json::to_string(&rebuilt).map_err(anyhow::Error::from)?,
            encoding: crate::delta::Encoding::Full,
            transmitters: rebuilt.len() as i64,
        };
        match app
            .storage
            .commit_rollback(row.id, cur.version, id, &v)
            .await
        {
            Ok(n) => {
                let contributions = (cur.contributions - 1).max(0);
                let n_tx = rebuilt.len();
                app.install(
                    row.id,
                    Arc::new(render_json(
                        name.as_str(),
                        n,
                        contributions,
                        Some(rebuilt),
                        &v.body,
                    )?),
                );
                tracing::info!(map = %name, contribution = id, version = n, ?dropped, "contribution rolled back");
                let body = serde_json::to_vec(&RolledBack {
                    rolled_back: id,
                    version: n,
                    transmitters: n_tx,
                    dropped,
                })
                .map_err(anyhow::Error::from)?;
                return Ok(json_response(StatusCode::OK, body));
            }
            Err(CommitError::VersionMoved { .. }) => {
                app.forget(row.id);
                continue;
            }
            Err(CommitError::NotAccepted) => {
                return Err(ApiError::Conflict(format!(
                    "contribution {id} is no longer accepted"
                )));
            }
            Err(CommitError::Db(e)) => return Err(e.into()),
            Err(e @ CommitError::DuplicateKey { .. }) => return Err(ApiError::Internal(e.into())),
        }
    }
}

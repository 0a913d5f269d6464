//! Contributions: upload (idempotent, matched and merged into a new version), list, roll back.

use super::extract::{JsonBytes, parse_json};
use super::maps::{authorize_read, json_response, rfc3339, transform_of};
use crate::api::{
    ContributionAccepted, ContributionInfo, ContributionPage, ContributionRequest, RolledBack,
};
use crate::error::{ApiError, ApiResult, PROBLEM_JSON, Problem, problem_body};
use crate::merge::{Outcome, correspondences, integrate, replay, seed_of, sha256_hex};
use crate::model::{IdempotencyKey, MapName};
use crate::state::{SharedState, render_json};
use crate::storage::{CommitError, NewContribution, NewVersion, StoredResponse};
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use echomap_shared::geometry::Transform2;
use echomap_shared::map::TransmitterMap;
use echomap_shared::map::wire::MapDoc;
use serde::Deserialize;
use std::sync::Arc;
use std::time::Instant;

/// Renders the stored response once the contribution id and new version are known.
type Respond = Box<dyn FnOnce(i64, Option<i64>) -> (u16, Vec<u8>) + Send>;

/// Validates a wire map; errors name the field under `prefix`.
pub fn validate_map(doc: MapDoc, prefix: &str) -> ApiResult<TransmitterMap> {
    TransmitterMap::from_doc(doc).map_err(|e| ApiError::Invalid {
        field: format!("{prefix}.{}", e.path),
        detail: e.kind.to_string(),
    })
}

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

fn replay_stored(s: StoredResponse) -> Response {
    let status = StatusCode::from_u16(s.response_status as u16).unwrap_or(StatusCode::OK);
    let ct = if status.is_success() {
        "application/json"
    } else {
        PROBLEM_JSON
    };
    let mut resp = (status, s.response_body).into_response();
    resp.headers_mut()
        .insert(header::CONTENT_TYPE, HeaderValue::from_static(ct));
    resp.headers_mut()
        .insert("idempotent-replayed", HeaderValue::from_static("true"));
    resp
}

/// Upload a user map (agent frame) with metadata. Requires `Idempotency-Key`. The first
/// contribution defines the map frame; later ones are matched (RANSAC) and merged into a new
/// version committed with the contribution. Unmatched uploads are stored as rejected → 422.
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
        (status = 422, body = Problem, description = "invalid map (field named), key reused with another body, or unmatched (stored as rejected)"),
        (status = 429, body = Problem)))]
pub async fn post_contribution(
    State(app): State<SharedState>,
    Path(name): Path<String>,
    headers: HeaderMap,
    JsonBytes(body): JsonBytes,
) -> ApiResult<Response> {
    let name = MapName::parse(&name)?;
    let who = app.tokens.require(&headers)?;
    let row = app.map_row(name.as_str()).await?;
    if !who.may_write(name.as_str()) {
        return Err(ApiError::Forbidden(format!(
            "token may not write map {name:?}"
        )));
    }
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
    app.limiter.check(&who)?;
    let _in_flight = app.begin(row.id, &who.contributor, key.as_str())?;
    // the first request with this key may have completed between the lookup and `begin`
    if let Some(s) = app
        .storage
        .stored_response(row.id, &who.contributor, key.as_str())
        .await?
    {
        return lookup(s);
    }
    let req: ContributionRequest = parse_json(&body)?;
    check_text("contributor", &req.contributor)?;
    check_text("run", &req.run)?;
    if let Some(d) = req.traveled_m
        && !(d.is_finite() && d >= 0.0)
    {
        return Err(ApiError::Invalid {
            field: "traveled_m".into(),
            detail: format!("must be a finite distance ≥ 0, got {d}"),
        });
    }
    let (agent, run, traveled_m) = (req.contributor.clone(), req.run.clone(), req.traveled_m);
    let user = Arc::new(validate_map(req.map, "map")?);
    if user.is_empty() {
        return Err(ApiError::Invalid {
            field: "map.transmitters".into(),
            detail: "a contribution needs at least one transmitter".into(),
        });
    }
    let body_text = String::from_utf8(body.to_vec()).map_err(|_| ApiError::MalformedJson {
        detail: "body is not UTF-8".into(),
    })?;

    let lock = app.map_lock(row.id);
    let _merging = lock.lock().await;
    loop {
        let cur = app.current(&row).await?;
        if let Some(prior) = &cur.map
            && !prior.is_empty()
            && prior.hex_size_m() != user.hex_size_m()
        {
            return Err(ApiError::Invalid {
                field: "map.hex_size_m".into(),
                detail: format!("must equal the map's {} m", prior.hex_size_m()),
            });
        }
        let (prior, u, mcfg, gcfg) = (
            cur.map.clone(),
            user.clone(),
            app.match_cfg.clone(),
            app.merge_cfg.clone(),
        );
        let seed = seed_of(&sha);
        let started = Instant::now();
        let outcome = tokio::task::spawn_blocking(move || {
            integrate(prior.as_deref(), &u, seed, &mcfg, &gcfg)
        })
        .await
        .map_err(anyhow::Error::from)??;
        metrics::histogram!("echomap_integrate_duration_seconds")
            .record(started.elapsed().as_secs_f64());
        let mut c = NewContribution {
            contributor: who.contributor.clone(),
            agent: agent.clone(),
            run: run.clone(),
            traveled_m,
            idempotency_key: key.as_str().to_owned(),
            request_sha256: sha.clone(),
            body: body_text.clone(),
            accepted: true,
            reason: None,
            transmitters: user.len() as i64,
            matched_version: cur.version,
            transform: None,
            inliers: None,
            score: None,
            merged: None,
            added: None,
        };
        let prior_map = cur.map.clone();
        let (new_map, response): (Option<TransmitterMap>, Respond) = match outcome {
            Outcome::Initialized { map } => {
                c.transform = Some(
                    serde_json::to_string(&Transform2::IDENTITY).map_err(anyhow::Error::from)?,
                );
                c.added = Some(map.len() as i64);
                c.merged = Some(0);
                let (n_tx, mapname) = (map.len(), name.to_string());
                (
                    Some(map),
                    Box::new(move |id, version| {
                        accepted_body(ContributionAccepted {
                            contribution: id,
                            map: mapname,
                            status: "accepted".into(),
                            version: version.unwrap_or(0),
                            initialized: true,
                            map_from_agent: Transform2::IDENTITY,
                            correspondences: vec![],
                            inliers: 0,
                            score: 0.0,
                            merged: 0,
                            added: n_tx,
                            transmitters: n_tx,
                        })
                    }),
                )
            }
            Outcome::Merged {
                map,
                matched,
                stats,
            } => {
                let t = transform_of(&matched.map_from_agent);
                let corr = correspondences(
                    &user,
                    prior_map.as_deref().expect("merged into a prior"),
                    &matched,
                );
                c.transform = Some(serde_json::to_string(&t).map_err(anyhow::Error::from)?);
                c.inliers = Some(matched.inliers as i64);
                c.score = Some(matched.score);
                c.merged = Some(stats.merged as i64);
                c.added = Some(stats.added as i64);
                let (n_tx, mapname) = (map.len(), name.to_string());
                (
                    Some(map),
                    Box::new(move |id, version| {
                        accepted_body(ContributionAccepted {
                            contribution: id,
                            map: mapname,
                            status: "accepted".into(),
                            version: version.unwrap_or(0),
                            initialized: false,
                            map_from_agent: t,
                            correspondences: corr,
                            inliers: matched.inliers,
                            score: matched.score,
                            merged: stats.merged,
                            added: stats.added,
                            transmitters: n_tx,
                        })
                    }),
                )
            }
            Outcome::Rejected { reason, matched } => {
                c.accepted = false;
                c.reason = Some(reason.clone());
                c.inliers = Some(matched.inliers as i64);
                c.score = matched.score.is_finite().then_some(matched.score);
                (
                    None,
                    Box::new(move |id, _| {
                        let p = ApiError::Unmatched {
                            reason,
                            contribution: id,
                        }
                        .problem();
                        (p.status, problem_body(&p))
                    }),
                )
            }
        };
        let version = match &new_map {
            Some(m) => Some(NewVersion {
                body: serde_json::to_string(m).map_err(anyhow::Error::from)?,
                transmitters: m.len() as i64,
            }),
            None => None,
        };
        match app
            .storage
            .commit_contribution(row.id, cur.version, &c, version.as_ref(), response)
            .await
        {
            Ok((status, bytes)) => {
                if let Some(m) = new_map {
                    let n = cur.version + 1;
                    let contributions = cur.contributions + 1;
                    let doc = version.as_ref().map_or("{}", |v| v.body.as_str());
                    app.install(
                        row.id,
                        Arc::new(render_json(
                            name.as_str(),
                            n,
                            contributions,
                            Some(Arc::new(m)),
                            doc,
                        )?),
                    );
                    metrics::counter!("echomap_merges_total").increment(1);
                    metrics::gauge!("echomap_map_transmitters", "map" => name.to_string())
                        .set(version.as_ref().map_or(0.0, |v| v.transmitters as f64));
                    tracing::info!(map = %name, version = n, contributor = %who.contributor, "contribution accepted");
                } else {
                    metrics::counter!("echomap_rejections_total").increment(1);
                    tracing::info!(map = %name, contributor = %who.contributor, reason = ?c.reason, "contribution rejected");
                }
                let status = StatusCode::from_u16(status).unwrap_or(StatusCode::OK);
                let ct = if status.is_success() {
                    "application/json"
                } else {
                    PROBLEM_JSON
                };
                let mut resp = (status, bytes).into_response();
                resp.headers_mut()
                    .insert(header::CONTENT_TYPE, HeaderValue::from_static(ct));
                return Ok(resp);
            }
            Err(CommitError::VersionMoved { expected, actual }) => {
                // another replica committed meanwhile: forget the cached version and re-match
                tracing::debug!(map = %name, expected, actual, "version moved; re-matching");
                app.forget(row.id);
                continue;
            }
            Err(CommitError::DuplicateKey) => {
                let s = app
                    .storage
                    .stored_response(row.id, &who.contributor, key.as_str())
                    .await?
                    .ok_or_else(|| anyhow::anyhow!("duplicate key without a stored response"))?;
                return lookup(s);
            }
            Err(CommitError::Db(e)) => return Err(e.into()),
        }
    }
}

fn accepted_body(a: ContributionAccepted) -> (u16, Vec<u8>) {
    (
        201,
        serde_json::to_vec(&a).expect("a response always serializes"),
    )
}

#[derive(Debug, Deserialize, utoipa::IntoParams)]
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
    let row = app.map_row(name.as_str()).await?;
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
    let who = app.tokens.require(&headers)?;
    let id: i64 = id.parse().map_err(|_| ApiError::BadRequest {
        detail: "contribution id must be an integer".into(),
    })?;
    let row = app.map_row(name.as_str()).await?;
    if !who.may_write(name.as_str()) {
        return Err(ApiError::Forbidden(format!(
            "token may not write map {name:?}"
        )));
    }
    app.limiter.check(&who)?;
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
            None => TransmitterMap::empty(hex).map_err(|e| anyhow::anyhow!("{e}"))?,
        };
        let v = NewVersion {
            body: serde_json::to_string(&rebuilt).map_err(anyhow::Error::from)?,
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
                        Some(Arc::new(rebuilt)),
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
            Err(CommitError::DuplicateKey) => {
                return Err(ApiError::Conflict(format!(
                    "contribution {id} is no longer accepted"
                )));
            }
            Err(CommitError::Db(e)) => return Err(e.into()),
        }
    }
}

//! Operations: liveness, readiness, Prometheus metrics, and the 404 fallback.

use crate::api::Health;
use crate::error::{ApiError, ApiResult, Problem};
use crate::state::SharedState;
use axum::extract::State;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

/// Liveness: the process serves requests.
#[utoipa::path(get, path = "/healthz", tag = "operations", responses((status = 200, body = Health)))]
pub async fn healthz() -> Response {
    super::common::json_response(StatusCode::OK, r#"{"status":"ok"}"#)
}

/// Readiness: the database answers and every migration is applied.
#[utoipa::path(get, path = "/readyz", tag = "operations",
    responses((status = 200, body = Health), (status = 503, body = Problem)))]
pub async fn readyz(State(app): State<SharedState>) -> ApiResult<Response> {
    match app.storage.ready().await {
        Ok(true) => Ok(super::common::json_response(
            StatusCode::OK,
            r#"{"status":"ready"}"#,
        )),
        Ok(false) => Err(ApiError::Unavailable("migrations not applied".into())),
        Err(e) => {
            tracing::warn!(error = %e, "readiness check failed");
            Err(ApiError::Unavailable("database unreachable".into()))
        }
    }
}

/// Prometheus text exposition: request counts and latency histograms by route and status,
/// merges, rejections, match/merge durations, map sizes.
#[utoipa::path(get, path = "/metrics", tag = "operations",
    responses((status = 200, content_type = "text/plain", body = String)))]
pub async fn metrics() -> Response {
    let handle = crate::metrics::handle();
    handle.run_upkeep();
    (
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("text/plain; version=0.0.4; charset=utf-8"),
        )],
        handle.render(),
    )
        .into_response()
}

pub async fn not_found() -> ApiError {
    ApiError::NotFound("no such route".into())
}

//! What the map and contribution routes share: authorization, JSON responses, time stamps
//! and the validation of an uploaded map.

use crate::error::{ApiError, ApiResult};
use crate::model::MapName;
use crate::state::{AppState, MapRef};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use echomap_shared::map::TransmitterMap;
use echomap_shared::map::wire::MapDoc;

/// Milliseconds since the epoch as RFC 3339.
pub fn rfc3339(ms: i64) -> String {
    let t = std::time::UNIX_EPOCH + std::time::Duration::from_millis(ms.max(0) as u64);
    humantime::format_rfc3339_millis(t).to_string()
}

/// Writes need a token allowed for the map (401 without one, 403 for another map).
pub fn authorize_write(
    app: &AppState,
    name: &MapName,
    headers: &HeaderMap,
) -> ApiResult<crate::auth::Principal> {
    let who = app.tokens.require(headers)?;
    if who.may_write(name.as_str()) {
        Ok(who)
    } else {
        Err(ApiError::Forbidden(format!(
            "token may not write map {name:?}"
        )))
    }
}

/// Reads of a private map need a token allowed for it.
pub fn authorize_read(app: &AppState, row: &MapRef, headers: &HeaderMap) -> ApiResult<()> {
    if !row.private {
        return Ok(());
    }
    let who = app.tokens.require(headers)?;
    if who.may_write(&row.name) {
        Ok(())
    } else {
        Err(ApiError::Forbidden(format!(
            "map {:?} is private",
            row.name
        )))
    }
}

pub fn json_response(status: StatusCode, body: impl Into<axum::body::Body>) -> Response {
    (
        status,
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/json"),
        )],
        body.into(),
    )
        .into_response()
}

/// Validates a wire map; errors name the field under `prefix`.
pub fn validate_map(doc: MapDoc, prefix: &str) -> ApiResult<TransmitterMap> {
    TransmitterMap::from_doc(doc).map_err(|e| ApiError::Invalid {
        field: format!("{prefix}.{}", e.path),
        detail: e.kind.to_string(),
    })
}

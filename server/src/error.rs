//! One error type for every handler, rendered as RFC 9457 `application/problem+json`.
//! Server-side failures (5xx) are logged with their cause and answered with a generic detail.

use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use utoipa::ToSchema;

/// Base of the `type` URIs of echomap problems (documented in docs/server.md).
pub const PROBLEM_BASE: &str = "https://echomap.invalid/problems/";
pub const PROBLEM_JSON: &str = "application/problem+json";

/// RFC 9457 problem details, with echomap's extension members.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct Problem {
    /// URI naming the problem type
    #[serde(rename = "type")]
    pub kind: String,
    pub title: String,
    pub status: u16,
    pub detail: String,
    /// the offending field (JSON path) when there is one
    #[serde(skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
    /// id of the stored (rejected) contribution, for unmatched uploads
    #[serde(skip_serializing_if = "Option::is_none")]
    pub contribution: Option<i64>,
}

#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    #[error("{detail}")]
    BadRequest { detail: String },
    #[error("malformed JSON: {detail}")]
    MalformedJson { detail: String },
    #[error("missing Idempotency-Key header")]
    MissingIdempotencyKey,
    #[error("{0}")]
    Unauthorized(String),
    #[error("{0}")]
    Forbidden(String),
    #[error("{0}")]
    NotFound(String),
    #[error("{0}")]
    Conflict(String),
    #[error("request body exceeds the limit of {limit} bytes")]
    PayloadTooLarge { limit: usize },
    #[error("{field}: {detail}")]
    Invalid { field: String, detail: String },
    #[error("Idempotency-Key reused with a different request body")]
    IdempotencyMismatch,
    #[error("the contribution could not be matched to the map: {reason}")]
    Unmatched { reason: String, contribution: i64 },
    #[error(
        "the contribution shares too little with the map to decide; keep it and try again when the map has grown: {reason}"
    )]
    Undecided { reason: String, contribution: i64 },
    #[error("unsupported media type: {0}")]
    UnsupportedMediaType(String),
    #[error("rate limit exceeded; retry after {retry_after_s} s")]
    RateLimited { retry_after_s: u64 },
    #[error("{detail}")]
    QuotaExceeded { detail: String, retry_after_s: u64 },
    #[error("service unavailable: {0}")]
    Unavailable(String),
    #[error(transparent)]
    Database(#[from] sqlx::Error),
    #[error(transparent)]
    Internal(#[from] anyhow::Error),
}

impl ApiError {
    pub fn status(&self) -> StatusCode {
        use ApiError::*;
        match self {
            BadRequest { .. } | MalformedJson { .. } | MissingIdempotencyKey => {
                StatusCode::BAD_REQUEST
            }
            Unauthorized(_) => StatusCode::UNAUTHORIZED,
            Forbidden(_) => StatusCode::FORBIDDEN,
            NotFound(_) => StatusCode::NOT_FOUND,
            Conflict(_) => StatusCode::CONFLICT,
            PayloadTooLarge { .. } => StatusCode::PAYLOAD_TOO_LARGE,
            UnsupportedMediaType(_) => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            Invalid { .. } | IdempotencyMismatch | Unmatched { .. } | Undecided { .. } => {
                StatusCode::UNPROCESSABLE_ENTITY
            }
            RateLimited { .. } | QuotaExceeded { .. } => StatusCode::TOO_MANY_REQUESTS,
            Unavailable(_) => StatusCode::SERVICE_UNAVAILABLE,
            Database(_) | Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    fn slug(&self) -> &'static str {
        use ApiError::*;
        match self {
            BadRequest { .. } => "bad-request",
            MalformedJson { .. } => "malformed-json",
            MissingIdempotencyKey => "missing-idempotency-key",
            Unauthorized(_) => "unauthorized",
            Forbidden(_) => "forbidden",
            NotFound(_) => "not-found",
            Conflict(_) => "conflict",
            PayloadTooLarge { .. } => "payload-too-large",
            UnsupportedMediaType(_) => "unsupported-media-type",
            Invalid { .. } => "invalid-field",
            IdempotencyMismatch => "idempotency-key-reused",
            Unmatched { .. } => "unmatched",
            Undecided { .. } => "undecided",
            RateLimited { .. } => "rate-limited",
            QuotaExceeded { .. } => "quota-exceeded",
            Unavailable(_) => "unavailable",
            Database(_) | Internal(_) => "internal",
        }
    }

    /// The problem document; 5xx causes are logged here and replaced by a generic detail.
    pub fn problem(&self) -> Problem {
        let status = self.status();
        let detail = if status.is_server_error() {
            tracing::error!(error = ?self, "request failed");
            "internal error; the cause was logged on the server".to_owned()
        } else {
            self.to_string()
        };
        let (field, contribution) = match self {
            ApiError::Invalid { field, .. } => (Some(field.clone()), None),
            ApiError::Unmatched { contribution, .. } | ApiError::Undecided { contribution, .. } => {
                (None, Some(*contribution))
            }
            _ => (None, None),
        };
        Problem {
            kind: format!("{PROBLEM_BASE}{}", self.slug()),
            title: status.canonical_reason().unwrap_or("error").to_owned(),
            status: status.as_u16(),
            detail,
            field,
            contribution,
        }
    }
}

/// The bytes of a problem+json response body.
pub fn problem_body(p: &Problem) -> Vec<u8> {
    serde_json::to_vec(p).expect("a problem always serializes")
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.status();
        let mut resp = (
            status,
            [(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON))],
            problem_body(&self.problem()),
        )
            .into_response();
        match &self {
            ApiError::Unauthorized(_) => {
                resp.headers_mut().insert(
                    header::WWW_AUTHENTICATE,
                    HeaderValue::from_static("Bearer realm=\"echomap\""),
                );
            }
            ApiError::RateLimited { retry_after_s }
            | ApiError::QuotaExceeded { retry_after_s, .. } => {
                resp.headers_mut()
                    .insert(header::RETRY_AFTER, HeaderValue::from(*retry_after_s));
            }
            _ => {}
        }
        resp
    }
}

pub type ApiResult<T> = Result<T, ApiError>;

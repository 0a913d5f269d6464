//! Request-body extraction whose failures come back as problem+json.

use crate::error::ApiError;
use axum::body::Bytes;
use axum::extract::{FromRequest, Request};
use axum::http::{StatusCode, header};
use serde::de::DeserializeOwned;

/// The raw body of a JSON request: content type checked, size limited (413).
#[derive(Debug)]
pub struct JsonBytes(pub Bytes);

impl<S: Send + Sync> FromRequest<S> for JsonBytes {
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, ApiError> {
        if let Some(ct) = req.headers().get(header::CONTENT_TYPE) {
            let ct = ct.to_str().unwrap_or("");
            let essence = ct
                .split(';')
                .next()
                .unwrap_or("")
                .trim()
                .to_ascii_lowercase();
            if essence != "application/json" && !essence.ends_with("+json") {
                return Err(ApiError::UnsupportedMediaType(format!(
                    "{ct:?}; send application/json"
                )));
            }
        }
        let limit = req
            .extensions()
            .get::<crate::routes::extract::Limit>()
            .map(|l| l.0);
        Bytes::from_request(req, state)
            .await
            .map(JsonBytes)
            .map_err(|r| {
                if r.status() == StatusCode::PAYLOAD_TOO_LARGE {
                    ApiError::PayloadTooLarge {
                        limit: limit.unwrap_or(0),
                    }
                } else {
                    ApiError::BadRequest {
                        detail: format!("cannot read the request body: {r}"),
                    }
                }
            })
    }
}

/// The configured body limit, for error messages.
#[derive(Debug, Clone, Copy)]
pub struct Limit(pub usize);

/// Parses JSON: syntax errors → 400, shape errors (missing/unknown field, wrong type) → 422
/// naming the field.
pub fn parse_json<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, ApiError> {
    let de = &mut serde_json::Deserializer::from_slice(bytes);
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        match inner.classify() {
            serde_json::error::Category::Data => {
                let msg = inner.to_string();
                let mut field = if path == "." { String::new() } else { path };
                // serde names a missing field in the message, at its parent's path
                if let Some(name) = msg
                    .strip_prefix("missing field `")
                    .and_then(|r| r.split('`').next())
                {
                    if !field.is_empty() {
                        field.push('.');
                    }
                    field.push_str(name);
                }
                let detail = msg.split(" at line ").next().unwrap_or(&msg).to_owned();
                ApiError::Invalid { field, detail }
            }
            _ => ApiError::MalformedJson {
                detail: inner.to_string(),
            },
        }
    })
}

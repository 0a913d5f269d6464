//! The map viewer: one page (HTML, CSS and JavaScript in one file, embedded in the binary, no
//! external assets) at `/viewer/` that lists the maps and draws one on a 2D canvas — every
//! transmitter's mixture components as 95 % covariance ellipses (colour by clock offset,
//! existence or reliability; opacity by weight), visibility cells as a hexagon layer, versions,
//! contributions with rollback for token holders, and a user's run overlaid through the match
//! endpoint. It reads and writes only through the public API, with the reader's own token.

use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Redirect, Response};

const PAGE: &str = include_str!("viewer/index.html");

/// `GET /viewer/`: the page.
pub async fn page() -> Response {
    (
        [
            (
                header::CONTENT_TYPE,
                HeaderValue::from_static("text/html; charset=utf-8"),
            ),
            (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
            (
                header::CONTENT_SECURITY_POLICY,
                HeaderValue::from_static(
                    "default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; connect-src 'self'",
                ),
            ),
        ],
        PAGE,
    )
        .into_response()
}

/// `GET /` and `GET /viewer`: to the page.
pub async fn to_page() -> Redirect {
    Redirect::temporary("/viewer/")
}

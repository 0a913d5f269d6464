//! Bearer tokens from a token file, kept hashed in memory and compared in constant time, and
//! the per-token write rate limit.
//!
//! File format, one token per line: `<token> <contributor> <maps>`, where `<maps>` is `*` (every
//! map, and the right to roll back anyone's contribution) or a comma-separated list of map names.
//! Blank lines and lines starting with `#` are ignored.

use crate::error::ApiError;
use axum::http::HeaderMap;
use governor::clock::{Clock, DefaultClock};
use governor::{DefaultKeyedRateLimiter, Quota, RateLimiter};
use sha2::{Digest, Sha256};
use std::num::NonZeroU32;
use std::path::Path;
use subtle::ConstantTimeEq;

/// Which maps a token may write.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MapScope {
    All,
    Only(Vec<String>),
}

#[derive(Debug, Clone)]
struct Entry {
    hash: [u8; 32],
    contributor: String,
    scope: MapScope,
}

/// Who a valid token belongs to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Principal {
    pub contributor: String,
    pub scope: MapScope,
}

impl Principal {
    pub fn may_write(&self, map: &str) -> bool {
        match &self.scope {
            MapScope::All => true,
            MapScope::Only(maps) => maps.iter().any(|m| m == map),
        }
    }

    /// Operators (scope `*`) may roll back any contribution.
    pub fn is_operator(&self) -> bool {
        self.scope == MapScope::All
    }
}

#[derive(Debug, thiserror::Error)]
pub enum TokenFileError {
    #[error("cannot read token file {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("token file line {line}: {detail}")]
    Line { line: usize, detail: String },
}

#[derive(Debug, Default)]
pub struct TokenStore {
    entries: Vec<Entry>,
}

fn sha256(bytes: &[u8]) -> [u8; 32] {
    Sha256::digest(bytes).into()
}

impl TokenStore {
    pub fn load(path: &Path) -> Result<Self, TokenFileError> {
        let text = std::fs::read_to_string(path).map_err(|source| TokenFileError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::parse(&text)
    }

    pub fn parse(text: &str) -> Result<Self, TokenFileError> {
        let mut entries = Vec::new();
        for (i, raw) in text.lines().enumerate() {
            let line = raw.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let bad = |detail: &str| TokenFileError::Line {
                line: i + 1,
                detail: detail.to_owned(),
            };
            let fields: Vec<&str> = line.split_whitespace().collect();
            let [token, contributor, maps] = fields[..] else {
                return Err(bad("expected `<token> <contributor> <maps>`"));
            };
            if token.len() < 16 {
                return Err(bad("token shorter than 16 characters"));
            }
            let scope = if maps == "*" {
                MapScope::All
            } else {
                let names: Vec<String> = maps.split(',').map(str::to_owned).collect();
                if let Some(n) = names
                    .iter()
                    .find(|n| crate::model::MapName::parse(n).is_err())
                {
                    return Err(bad(&format!("invalid map name {n:?}")));
                }
                MapScope::Only(names)
            };
            let hash = sha256(token.as_bytes());
            if entries.iter().any(|e: &Entry| e.hash == hash) {
                return Err(bad("duplicate token"));
            }
            entries.push(Entry {
                hash,
                contributor: contributor.to_owned(),
                scope,
            });
        }
        Ok(TokenStore { entries })
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The principal of a presented token. Every stored hash is compared (constant time each),
    /// so the time taken does not depend on which entry matched.
    pub fn verify(&self, token: &str) -> Option<Principal> {
        let hash = sha256(token.as_bytes());
        let mut found = None;
        for e in &self.entries {
            if bool::from(e.hash.ct_eq(&hash)) {
                found = Some(e);
            }
        }
        found.map(|e| Principal {
            contributor: e.contributor.clone(),
            scope: e.scope.clone(),
        })
    }

    /// The principal named by an `Authorization: Bearer` header: `Ok(None)` when there is no
    /// header, 401 when it is malformed or unknown.
    pub fn from_headers(&self, headers: &HeaderMap) -> Result<Option<Principal>, ApiError> {
        let Some(value) = headers.get(axum::http::header::AUTHORIZATION) else {
            return Ok(None);
        };
        let token = value
            .to_str()
            .ok()
            .and_then(|v| v.strip_prefix("Bearer "))
            .map(str::trim)
            .filter(|t| !t.is_empty())
            .ok_or_else(|| {
                ApiError::Unauthorized("Authorization must be `Bearer <token>`".into())
            })?;
        self.verify(token)
            .map(Some)
            .ok_or_else(|| ApiError::Unauthorized("unknown token".into()))
    }

    /// The principal of a write request: 401 without a valid token.
    pub fn require(&self, headers: &HeaderMap) -> Result<Principal, ApiError> {
        self.from_headers(headers)?.ok_or_else(|| {
            ApiError::Unauthorized("this request needs `Authorization: Bearer <token>`".into())
        })
    }
}

/// Per-contributor write rate limit (GCRA, `governor`).
#[derive(Debug)]
pub struct WriteLimiter {
    limiter: DefaultKeyedRateLimiter<String>,
    /// ms between two writes at the sustained rate
    pub emission_ms: f64,
    /// how far ahead of now a contributor's next allowed write may lie (burst − 1 emissions)
    pub tolerance_ms: f64,
}

impl WriteLimiter {
    pub fn new(per_second: u32, burst: u32) -> Self {
        let per_second = NonZeroU32::new(per_second.max(1)).expect("≥ 1");
        let burst = NonZeroU32::new(burst.max(1)).expect("≥ 1");
        let emission_ms = 1000.0 / f64::from(per_second.get());
        WriteLimiter {
            limiter: RateLimiter::keyed(Quota::per_second(per_second).allow_burst(burst)),
            emission_ms,
            tolerance_ms: emission_ms * f64::from(burst.get() - 1),
        }
    }

    /// 429 with the wait in whole seconds (at least 1) when the contributor is over its quota
    /// in this process.
    pub fn check(&self, who: &Principal) -> Result<(), ApiError> {
        self.limiter
            .check_key(&who.contributor)
            .map_err(|not_until| {
                let wait = not_until.wait_time_from(DefaultClock::default().now());
                ApiError::RateLimited {
                    retry_after_s: wait.as_secs_f64().ceil().max(1.0) as u64,
                }
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn token_file_parses_and_verifies() {
        let store = TokenStore::parse(
            "# operators\nop-0123456789abcdef alice *\n\nuser-0123456789abcdef bob lab,hall-2\n",
        )
        .unwrap();
        assert_eq!(store.len(), 2);
        let op = store.verify("op-0123456789abcdef").unwrap();
        assert!(op.is_operator() && op.may_write("anything"));
        let bob = store.verify("user-0123456789abcdef").unwrap();
        assert_eq!(bob.contributor, "bob");
        assert!(bob.may_write("lab") && bob.may_write("hall-2") && !bob.may_write("labx"));
        assert!(store.verify("user-0123456789abcdeX").is_none());
    }

    #[test]
    fn bad_token_files_name_the_line() {
        for (text, line) in [
            ("a-very-long-token-1 bob\n", 1),
            ("# c\nshort bob *\n", 2),
            ("a-very-long-token-1 bob ../etc\n", 1),
            ("a-very-long-token-1 bob *\na-very-long-token-1 eve *\n", 2),
        ] {
            match TokenStore::parse(text) {
                Err(TokenFileError::Line { line: l, .. }) => assert_eq!(l, line, "{text}"),
                other => panic!("{text}: {other:?}"),
            }
        }
    }
}

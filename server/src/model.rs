//! Domain newtypes checked at the boundary: past `parse`, a value cannot be invalid.

use crate::error::ApiError;

/// A map name: 1–64 characters of `[a-z0-9._-]`, not `.` or `..`. It is only ever a bound
/// SQL parameter and a JSON string, never part of a file path.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct MapName(String);

impl MapName {
    pub const MAX_LEN: usize = 64;

    pub fn parse(s: &str) -> Result<Self, ApiError> {
        let ok = !s.is_empty()
            && s.len() <= Self::MAX_LEN
            && s != "."
            && s != ".."
            && s.bytes()
                .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b"._-".contains(&b));
        if ok {
            Ok(MapName(s.to_owned()))
        } else {
            Err(ApiError::BadRequest {
                detail: format!(
                    "invalid map name {:?}: 1–{} characters of [a-z0-9._-]",
                    truncate(s, 80),
                    Self::MAX_LEN
                ),
            })
        }
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl std::fmt::Display for MapName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// An `Idempotency-Key` header value: 1–255 visible ASCII characters.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct IdempotencyKey(String);

impl IdempotencyKey {
    pub const HEADER: &'static str = "idempotency-key";

    pub fn from_headers(headers: &axum::http::HeaderMap) -> Result<Self, ApiError> {
        let v = headers
            .get(Self::HEADER)
            .ok_or(ApiError::MissingIdempotencyKey)?;
        let s = v.to_str().map_err(|_| ApiError::BadRequest {
            detail: "Idempotency-Key must be visible ASCII".into(),
        })?;
        // draft-ietf-httpapi-idempotency-key-header: a (quoted) string; accept both forms
        let s = s.trim();
        // a quoted key is unwrapped only when something is left inside the quotes: `"` and
        // `""` are keys of their own
        let s = match s.strip_prefix('"').and_then(|s| s.strip_suffix('"')) {
            Some(inner) if !inner.is_empty() => inner,
            _ => s,
        };
        if s.is_empty() || s.len() > 255 || !s.bytes().all(|b| b.is_ascii_graphic()) {
            return Err(ApiError::BadRequest {
                detail: "Idempotency-Key must be 1–255 visible ASCII characters".into(),
            });
        }
        Ok(IdempotencyKey(s.to_owned()))
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }
}

pub fn truncate(s: &str, max: usize) -> String {
    s.chars().take(max).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn map_names() {
        for good in ["a", "lab-2", "hall_3.v1", &"x".repeat(64)] {
            assert!(MapName::parse(good).is_ok(), "{good}");
        }
        for bad in [
            "",
            ".",
            "..",
            "../etc",
            "a/b",
            "A",
            "x'; DROP TABLE maps;--",
            "a b",
            "ä",
            &"x".repeat(65),
            "a\0",
        ] {
            assert!(MapName::parse(bad).is_err(), "{bad}");
        }
    }

    fn key(v: &str) -> Result<IdempotencyKey, ApiError> {
        let mut h = axum::http::HeaderMap::new();
        h.insert(IdempotencyKey::HEADER, v.parse().unwrap());
        IdempotencyKey::from_headers(&h)
    }

    #[test]
    fn idempotency_keys_of_every_visible_ascii_form() {
        // every value the published pattern `^[!-~]{1,255}$` allows is a key
        for (raw, stored) in [
            ("k1", "k1"),
            ("\"k1\"", "k1"),
            ("\"", "\""),
            ("\"\"", "\"\""),
            ("\"\"\"", "\""),
            ("~", "~"),
        ] {
            assert_eq!(key(raw).unwrap().as_str(), stored, "{raw}");
        }
        assert!(key(&"k".repeat(255)).is_ok());
        for bad in ["", " ", "a b", &"k".repeat(256)] {
            assert!(key(bad).is_err(), "{bad:?}");
        }
    }
}

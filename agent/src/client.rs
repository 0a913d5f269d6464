//! HTTP client of the map server (`echomap-server`, API v1): fetch the current prior map with a
//! conditional GET, upload a user map as a contribution with an `Idempotency-Key`, match a map
//! remotely. Network errors, 5xx and 429 are retried with capped exponential backoff (429
//! honours `Retry-After`); other 4xx never are — they are answers, reported with their
//! problem+json detail.

use echomap_shared::map::TransmitterMap;
use rand::{RngExt, SeedableRng};
use serde_json::Value;
use sha2::{Digest, Sha256};
use std::time::Duration;

/// A `reqwest` client builder with *ring* installed as the process's rustls crypto provider.
///
/// reqwest is built without a provider (`rustls-no-provider`: its default, aws-lc-rs, doubles
/// the release build's time on two cores) and panics in `build` when none is installed.
/// Installing it again, or after another one was installed, changes nothing.
pub fn http_client_builder() -> reqwest::ClientBuilder {
    let _ = rustls::crypto::ring::default_provider().install_default();
    reqwest::Client::builder()
}

/// Client settings.
#[derive(Debug, Clone)]
pub struct ClientConfig {
    /// server base URL, e.g. `http://127.0.0.1:8080`
    pub base_url: String,
    /// bearer token for writes (and private maps)
    pub token: Option<String>,
    /// retries after the first attempt; default 6
    pub max_retries: u32,
    /// first backoff; doubles per retry up to `max_backoff`; default 200 ms
    pub initial_backoff: Duration,
    /// default 10 s
    pub max_backoff: Duration,
    /// per-request timeout; default 60 s
    pub timeout: Duration,
}

impl ClientConfig {
    pub fn new(base_url: impl Into<String>) -> Self {
        ClientConfig {
            base_url: base_url.into().trim_end_matches('/').to_owned(),
            token: None,
            max_retries: 6,
            initial_backoff: Duration::from_millis(200),
            max_backoff: Duration::from_secs(10),
            timeout: Duration::from_secs(60),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// the server answered with an error status that retrying cannot fix
    #[error("server answered {status}: {detail}")]
    Status {
        status: u16,
        detail: String,
        problem: Option<Value>,
    },
    #[error("server unreachable after {attempts} attempts: {last}")]
    Unreachable { attempts: u32, last: String },
    #[error("unexpected response: {0}")]
    Protocol(String),
}

/// The prior map as served: identity and the validated map (map frame).
#[derive(Debug, Clone)]
pub struct PriorMap {
    pub name: String,
    pub version: i64,
    pub contributions: i64,
    pub map: TransmitterMap,
    /// the response body as received (cache it to send `If-None-Match` next time)
    pub body: String,
}

#[derive(Debug, Clone)]
pub enum Fetched {
    Fresh(PriorMap),
    /// the server's version is the one the caller has
    NotModified,
}

/// Body of `POST /v1/maps/{map}/contributions` (the API's wire type).
pub use echomap_shared::api::ContributionRequest as Contribution;

/// What the server did with an upload.
#[derive(Debug, Clone)]
pub enum UploadOutcome {
    /// 201: merged into a new version (the response body)
    Accepted(Value),
    /// 422 `unmatched`: stored as rejected, the map is unchanged (the problem document)
    Rejected(Value),
    /// 422 `undecided`: the upload shares too little with the map to decide; stored as
    /// rejected, the map is unchanged — worth another try once the map has grown
    Undecided(Value),
}

#[derive(Debug, Clone)]
pub struct MapClient {
    http: reqwest::Client,
    cfg: ClientConfig,
}

/// The Idempotency-Key of an upload: derived from its bytes, so re-sending the same upload
/// (even from a restarted process) can never merge it twice.
pub fn idempotency_key(body: &[u8]) -> String {
    format!("sha256-{}", &hex::encode(Sha256::digest(body))[..32])
}

enum Attempt {
    Done(reqwest::Response),
    Retry { wait: Option<Duration>, why: String },
}

impl MapClient {
    pub fn new(cfg: ClientConfig) -> Result<Self, ClientError> {
        let http = http_client_builder()
            .timeout(cfg.timeout)
            .user_agent(concat!("echomap-agent/", env!("CARGO_PKG_VERSION")))
            .build()
            .map_err(|e| ClientError::Protocol(e.to_string()))?;
        Ok(MapClient { http, cfg })
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.cfg.base_url)
    }

    /// Sends the request made by `make` until it gets an answer that is not a network error,
    /// 5xx or 429, or the retries are spent. Backoff: full jitter on a capped exponential,
    /// drawn from a generator seeded by `seed` (reproducible).
    async fn send(
        &self,
        seed: u64,
        make: impl Fn() -> reqwest::RequestBuilder,
    ) -> Result<reqwest::Response, ClientError> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut backoff = self.cfg.initial_backoff;
        let mut last = String::new();
        for attempt in 0..=self.cfg.max_retries {
            let outcome = match make().send().await {
                Ok(r) if r.status().is_server_error() => Attempt::Retry {
                    wait: None,
                    why: format!("HTTP {}", r.status()),
                },
                Ok(r) if r.status() == reqwest::StatusCode::TOO_MANY_REQUESTS => {
                    let wait = r
                        .headers()
                        .get(reqwest::header::RETRY_AFTER)
                        .and_then(|v| v.to_str().ok())
                        .and_then(|v| v.trim().parse::<u64>().ok())
                        .map(Duration::from_secs);
                    Attempt::Retry {
                        wait,
                        why: "HTTP 429".into(),
                    }
                }
                Ok(r) => Attempt::Done(r),
                Err(e) => Attempt::Retry {
                    wait: None,
                    why: e.to_string(),
                },
            };
            match outcome {
                Attempt::Done(r) => return Ok(r),
                Attempt::Retry { wait, why } => {
                    last = why;
                    if attempt == self.cfg.max_retries {
                        break;
                    }
                    let jittered = backoff.mul_f64(rng.random_range(0.5..1.0));
                    let wait = wait.unwrap_or(jittered).min(self.cfg.max_backoff);
                    tracing::warn!(attempt = attempt + 1, error = %last, wait_ms = wait.as_millis() as u64, "retrying");
                    tokio::time::sleep(wait).await;
                    backoff = (backoff * 2).min(self.cfg.max_backoff);
                }
            }
        }
        Err(ClientError::Unreachable {
            attempts: self.cfg.max_retries + 1,
            last,
        })
    }

    fn auth(&self, rb: reqwest::RequestBuilder) -> reqwest::RequestBuilder {
        match &self.cfg.token {
            Some(t) => rb.bearer_auth(t),
            None => rb,
        }
    }

    async fn fail(r: reqwest::Response) -> ClientError {
        let status = r.status().as_u16();
        let text = r.text().await.unwrap_or_default();
        let problem: Option<Value> = serde_json::from_str(&text).ok();
        let detail = problem
            .as_ref()
            .and_then(|p| p.get("detail"))
            .and_then(Value::as_str)
            .map_or_else(|| text.chars().take(200).collect(), str::to_owned);
        ClientError::Status {
            status,
            detail,
            problem,
        }
    }

    /// `GET /v1/maps/{map}`; with `have_version`, a conditional GET (`If-None-Match`).
    pub async fn fetch(
        &self,
        map: &str,
        have_version: Option<i64>,
    ) -> Result<Fetched, ClientError> {
        let url = self.url(&format!("/v1/maps/{map}"));
        let r = self
            .send(0, || {
                let rb = self.auth(self.http.get(&url));
                match have_version {
                    Some(v) => rb.header(reqwest::header::IF_NONE_MATCH, format!("\"{v}\"")),
                    None => rb,
                }
            })
            .await?;
        if r.status() == reqwest::StatusCode::NOT_MODIFIED {
            return Ok(Fetched::NotModified);
        }
        Self::map_document(r).await.map(Fetched::Fresh)
    }

    /// A successful map or version response parsed, any other status as its problem.
    async fn map_document(r: reqwest::Response) -> Result<PriorMap, ClientError> {
        if !r.status().is_success() {
            return Err(Self::fail(r).await);
        }
        let body = r
            .text()
            .await
            .map_err(|e| ClientError::Protocol(e.to_string()))?;
        parse_prior(&body)
    }

    /// `PUT /v1/maps/{map}`: creates the map (idempotent; an existing map is fine).
    pub async fn create_map(&self, map: &str) -> Result<(), ClientError> {
        let url = self.url(&format!("/v1/maps/{map}"));
        let r = self
            .send(2, || {
                self.auth(self.http.put(&url))
                    .header(reqwest::header::CONTENT_TYPE, "application/json")
                    .body("{}")
            })
            .await?;
        if r.status().is_success() {
            Ok(())
        } else {
            Err(Self::fail(r).await)
        }
    }

    /// `GET /v1/maps/{map}/versions/{n}`: one stored version (same document as the map).
    pub async fn fetch_version(&self, map: &str, n: i64) -> Result<PriorMap, ClientError> {
        let url = self.url(&format!("/v1/maps/{map}/versions/{n}"));
        let r = self.send(3, || self.auth(self.http.get(&url))).await?;
        Self::map_document(r).await
    }

    /// `POST /v1/maps/{map}/contributions` with an Idempotency-Key derived from the body.
    pub async fn upload(&self, map: &str, c: &Contribution) -> Result<UploadOutcome, ClientError> {
        self.upload_attempt(map, c, None).await
    }

    /// Uploads `c` again after the server refused it as contribution `refused` (e.g. undecided,
    /// when the map has grown since). The Idempotency-Key is derived from the body and the
    /// refused contribution's id: a new key for a deliberate new attempt — the refusal merged
    /// nothing, so nothing can merge twice — and the same key when this attempt is re-sent.
    pub async fn upload_again(
        &self,
        map: &str,
        c: &Contribution,
        refused: i64,
    ) -> Result<UploadOutcome, ClientError> {
        self.upload_attempt(map, c, Some(refused)).await
    }

    async fn upload_attempt(
        &self,
        map: &str,
        c: &Contribution,
        refused: Option<i64>,
    ) -> Result<UploadOutcome, ClientError> {
        let body = serde_json::to_vec(c).map_err(|e| ClientError::Protocol(e.to_string()))?;
        let key = match refused {
            None => idempotency_key(&body),
            Some(id) => {
                let mut tagged = body.clone();
                tagged.extend_from_slice(format!("\nafter refused contribution {id}").as_bytes());
                idempotency_key(&tagged)
            }
        };
        let seed = u64::from_le_bytes(Sha256::digest(&body)[..8].try_into().expect("8 bytes"));
        let url = self.url(&format!("/v1/maps/{map}/contributions"));
        let r = self
            .send(seed, || {
                self.auth(self.http.post(&url))
                    .header("Idempotency-Key", &key)
                    .header(reqwest::header::CONTENT_TYPE, "application/json")
                    .body(body.clone())
            })
            .await?;
        let status = r.status();
        if status == reqwest::StatusCode::CREATED {
            let v: Value = r
                .json()
                .await
                .map_err(|e| ClientError::Protocol(e.to_string()))?;
            return Ok(UploadOutcome::Accepted(v));
        }
        let err = Self::fail(r).await;
        if let ClientError::Status {
            status: 422,
            problem: Some(p),
            ..
        } = &err
        {
            match p.get("type").and_then(Value::as_str) {
                Some(t) if t.ends_with("/unmatched") => {
                    return Ok(UploadOutcome::Rejected(p.clone()));
                }
                Some(t) if t.ends_with("/undecided") => {
                    return Ok(UploadOutcome::Undecided(p.clone()));
                }
                _ => {}
            }
        }
        Err(err)
    }

    /// `POST /v1/maps/{map}/match`: matches `user` remotely; nothing is written.
    pub async fn match_map(&self, map: &str, user: &TransmitterMap) -> Result<Value, ClientError> {
        let body = serde_json::to_vec(&serde_json::json!({ "map": user }))
            .map_err(|e| ClientError::Protocol(e.to_string()))?;
        let url = self.url(&format!("/v1/maps/{map}/match"));
        let r = self
            .send(1, || {
                self.auth(self.http.post(&url))
                    .header(reqwest::header::CONTENT_TYPE, "application/json")
                    .body(body.clone())
            })
            .await?;
        if !r.status().is_success() {
            return Err(Self::fail(r).await);
        }
        r.json()
            .await
            .map_err(|e| ClientError::Protocol(e.to_string()))
    }
}

/// Parses a served map (`{"map","version","contributions", …echomap.map.v1…}`).
pub fn parse_prior(body: &str) -> Result<PriorMap, ClientError> {
    let mut v: Value =
        serde_json::from_str(body).map_err(|e| ClientError::Protocol(e.to_string()))?;
    let obj = v
        .as_object_mut()
        .ok_or_else(|| ClientError::Protocol("map response is not an object".into()))?;
    let name = obj
        .remove("map")
        .and_then(|x| x.as_str().map(str::to_owned));
    let version = obj.remove("version").and_then(|x| x.as_i64());
    let contributions = obj.remove("contributions").and_then(|x| x.as_i64());
    let (Some(name), Some(version), Some(contributions)) = (name, version, contributions) else {
        return Err(ClientError::Protocol(
            "map response lacks map/version/contributions".into(),
        ));
    };
    // what is left is the echomap.map.v1 document; deserializing validates it
    let map: TransmitterMap = serde_json::from_value(v)
        .map_err(|e| ClientError::Protocol(format!("invalid map: {e}")))?;
    Ok(PriorMap {
        name,
        version,
        contributions,
        map,
        body: body.to_owned(),
    })
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_client_for_https_builds() {
        // without a crypto provider reqwest panics ("No rustls crypto provider is configured")
        let client = super::http_client_builder().https_only(true).build();
        assert!(client.is_ok(), "{client:?}");
    }
}

//! Shared server state: storage, tokens, limits, the per-map merge locks, the in-flight
//! idempotency keys and the cache of current map versions.

use crate::auth::{TokenStore, WriteLimiter};
use crate::config::Config;
use crate::error::ApiError;
use crate::heads::{Heads, ReplicaCache};
use crate::storage::{Kind, Storage};
use bytes::Bytes;
use echomap_shared::map::TransmitterMap;
use echomap_shared::matching::MatchConfig;
use echomap_shared::merging::MergeConfig;
use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex, RwLock};

/// What never changes about a map: its identity and read setting. (Version and counts do
/// change; they come from [`CachedVersion`] or the database.)
#[derive(Debug, Clone)]
pub struct MapRef {
    pub id: i64,
    pub name: String,
    pub private: bool,
}

/// A map version held in memory: parsed for matching, and the rendered `GET` body.
#[derive(Debug)]
pub struct CachedVersion {
    pub version: i64,
    pub contributions: i64,
    /// `None` for version 0 (no contribution yet)
    pub map: Option<Arc<TransmitterMap>>,
    pub body: Bytes,
}

#[derive(Debug)]
pub struct AppState {
    pub storage: Storage,
    pub tokens: TokenStore,
    pub limiter: WriteLimiter,
    pub config: Config,
    pub match_cfg: MatchConfig,
    pub merge_cfg: MergeConfig,
    map_locks: Mutex<HashMap<i64, Arc<tokio::sync::Mutex<()>>>>,
    merge_queues: Mutex<HashMap<i64, tokio::sync::mpsc::UnboundedSender<crate::job::Job>>>,
    in_flight: Mutex<HashSet<(i64, String, String)>>,
    /// current version per map id; only ever replaced by a newer version
    current: RwLock<HashMap<i64, Arc<CachedVersion>>>,
    /// map name → row, for maps known to exist (names are never deleted or reused)
    known: RwLock<HashMap<String, MapRef>>,
    /// heads announced by PostgreSQL (`--replica-cache listen`)
    pub heads: Arc<Heads>,
}

pub type SharedState = Arc<AppState>;

/// Removes its key from the in-flight set when the request finishes (or is cancelled).
#[derive(Debug)]
pub struct InFlight<'a> {
    state: &'a AppState,
    key: (i64, String, String),
}

impl Drop for InFlight<'_> {
    fn drop(&mut self) {
        self.state
            .in_flight
            .lock()
            .expect("in-flight set poisoned")
            .remove(&self.key);
    }
}

impl AppState {
    pub fn new(storage: Storage, tokens: TokenStore, config: Config) -> Self {
        let limiter = WriteLimiter::new(config.rate_limit_per_s, config.rate_limit_burst);
        let match_cfg = MatchConfig::default()
            .with_visibility_weight(config.match_visibility_weight)
            .with_location_score(config.match_score.location_score());
        let merge_cfg = MergeConfig::default().with_absorb_chi2(config.merge_absorb_chi2);
        AppState {
            storage,
            tokens,
            limiter,
            config,
            match_cfg,
            merge_cfg,
            map_locks: Mutex::default(),
            merge_queues: Mutex::default(),
            in_flight: Mutex::default(),
            current: RwLock::default(),
            known: RwLock::default(),
            heads: Arc::default(),
        }
    }

    /// The write rate limit: per process on SQLite (the only process), shared by every
    /// replica on PostgreSQL (one upsert per write, [`Storage::take_write_cell`]); 429 with the
    /// wait in whole seconds (at least 1).
    pub async fn check_rate(&self, who: &crate::auth::Principal) -> Result<(), ApiError> {
        match self.storage.kind() {
            Kind::Sqlite => self.limiter.check(who),
            Kind::Postgres => match self
                .storage
                .take_write_cell(
                    &who.contributor,
                    self.limiter.emission_ms,
                    self.limiter.tolerance_ms,
                )
                .await?
            {
                None => Ok(()),
                Some(wait_ms) => Err(ApiError::RateLimited {
                    retry_after_s: (wait_ms / 1000.0).ceil().max(1.0) as u64,
                }),
            },
        }
    }

    /// The per-contributor quota of rejected contributions: at most
    /// `rejected_quota_per_day` stored rejections in any 24 hours, counted in the database (so
    /// shared by every replica). Over it → 429 until the oldest rejection in the window ages out.
    pub async fn check_quota(&self, who: &crate::auth::Principal) -> Result<(), ApiError> {
        const DAY_MS: i64 = 24 * 3600 * 1000;
        let quota = i64::from(self.config.rejected_quota_per_day);
        let now = crate::storage::now_ms();
        let (count, oldest) = self
            .storage
            .rejected_since(&who.contributor, now - DAY_MS)
            .await?;
        if count < quota {
            return Ok(());
        }
        let wait_ms = oldest.map_or(DAY_MS, |t| (t + DAY_MS - now).max(0));
        Err(ApiError::QuotaExceeded {
            detail: format!(
                "contributor {:?} has {count} rejected contributions in the last 24 h, the quota is {quota}: \
                 uploads that match no map are refused until the oldest ages out",
                who.contributor
            ),
            retry_after_s: ((wait_ms as f64) / 1000.0).ceil().max(1.0) as u64,
        })
    }

    /// The lock serializing merges of one map in this process.
    pub fn map_lock(&self, map_id: i64) -> Arc<tokio::sync::Mutex<()>> {
        self.map_locks
            .lock()
            .expect("lock table poisoned")
            .entry(map_id)
            .or_default()
            .clone()
    }

    /// The queue of a map's merge worker, started by `start` on first use.
    pub fn merge_queue(
        &self,
        map_id: i64,
        start: impl FnOnce() -> tokio::sync::mpsc::UnboundedSender<crate::job::Job>,
    ) -> tokio::sync::mpsc::UnboundedSender<crate::job::Job> {
        self.merge_queues
            .lock()
            .expect("queue table poisoned")
            .entry(map_id)
            .or_insert_with(start)
            .clone()
    }

    /// Registers a request with an idempotency key; 409 while the same key is being processed.
    pub fn begin(
        &self,
        map_id: i64,
        contributor: &str,
        key: &str,
    ) -> Result<InFlight<'_>, ApiError> {
        let key = (map_id, contributor.to_owned(), key.to_owned());
        let fresh = self
            .in_flight
            .lock()
            .expect("in-flight set poisoned")
            .insert(key.clone());
        if !fresh {
            return Err(ApiError::Conflict(
                "a request with this Idempotency-Key is still being processed; retry later".into(),
            ));
        }
        Ok(InFlight { state: self, key })
    }

    /// The identity of an existing map (cached: maps are never deleted or changed).
    pub async fn map_ref(&self, name: &str) -> Result<MapRef, ApiError> {
        if let Some(row) = self.known.read().expect("poisoned").get(name) {
            return Ok(row.clone());
        }
        let row = self
            .storage
            .map(name)
            .await?
            .map(|r| MapRef {
                id: r.id,
                name: r.name,
                private: r.private,
            })
            .ok_or_else(|| ApiError::NotFound(format!("no map named {name:?}")))?;
        self.known
            .write()
            .expect("poisoned")
            .insert(name.to_owned(), row.clone());
        Ok(row)
    }

    /// The current version of a map, from the cache or the database. On PostgreSQL other
    /// replicas commit to the same database, so the cached version is served only while the
    /// stored `current_version` still equals it: read on every request (`--replica-cache
    /// check`, one indexed read), or only when no listening session vouches for it
    /// (`listen`, see [`Heads`]). On SQLite this process is the only writer and the cache is
    /// authoritative.
    pub async fn current(&self, row: &MapRef) -> Result<Arc<CachedVersion>, ApiError> {
        let cached = self.current.read().expect("poisoned").get(&row.id).cloned();
        let listen = self.config.replica_cache == ReplicaCache::Listen;
        if let Some(c) = cached {
            let fresh = match self.storage.kind() {
                Kind::Sqlite => true,
                Kind::Postgres if listen && self.heads.vouches(row.id, c.version) => true,
                Kind::Postgres => {
                    let session = self.heads.session();
                    metrics::counter!("echomap_head_reads_total").increment(1);
                    let head = self.storage.current_version(row.id).await?;
                    if head == Some(c.version) && listen {
                        self.heads.verified(row.id, c.version, session);
                    }
                    head == Some(c.version)
                }
            };
            if fresh {
                return Ok(c);
            }
            metrics::counter!("echomap_cache_reloads_total").increment(1);
        }
        let session = self.heads.session();
        let fresh = self
            .storage
            .map(&row.name)
            .await?
            .ok_or_else(|| ApiError::NotFound(format!("no map named {:?}", row.name)))?;
        let cached = if fresh.current_version == 0 {
            Arc::new(render(&fresh.name, 0, 0, None)?)
        } else {
            let v = self
                .storage
                .version(fresh.id, fresh.current_version)
                .await?
                .ok_or_else(|| anyhow::anyhow!("map {} lacks its current version", fresh.name))?;
            let map = TransmitterMap::from_json(&v.body)
                .map_err(|e| anyhow::anyhow!("stored version does not parse: {e}"))?;
            Arc::new(render_json(
                &fresh.name,
                v.number,
                fresh.contributions,
                Some(Arc::new(map)),
                &v.body,
            )?)
        };
        let installed = self.install(row.id, cached);
        if listen && self.storage.kind() == Kind::Postgres {
            self.heads.verified(row.id, fresh.current_version, session);
        }
        Ok(installed)
    }

    /// Drops the cached version of a map (another writer moved it).
    pub fn forget(&self, map_id: i64) {
        self.current.write().expect("poisoned").remove(&map_id);
    }

    /// Makes `c` the cached current version unless a newer one is already there; returns the
    /// one that is current afterwards.
    pub fn install(&self, map_id: i64, c: Arc<CachedVersion>) -> Arc<CachedVersion> {
        let mut cur = self.current.write().expect("poisoned");
        match cur.get(&map_id) {
            Some(have) if have.version >= c.version => have.clone(),
            _ => {
                cur.insert(map_id, c.clone());
                c
            }
        }
    }
}

/// Renders the `GET /v1/maps/{map}` body of a version from the map's serialized
/// `echomap.map.v1` document (`doc_json`, as stored): the identity members are spliced in
/// front, so the map is serialized once per version.
pub fn render_json(
    name: &str,
    version: i64,
    contributions: i64,
    map: Option<Arc<TransmitterMap>>,
    doc_json: &str,
) -> Result<CachedVersion, ApiError> {
    let head = serde_json::to_string(&serde_json::json!({
        "map": name, "version": version, "contributions": contributions
    }))
    .map_err(anyhow::Error::from)?;
    let rest = doc_json
        .strip_prefix('{')
        .ok_or_else(|| anyhow::anyhow!("a map document is a JSON object"))?;
    let mut body = String::with_capacity(head.len() + doc_json.len() + 1);
    body.push_str(&head[..head.len() - 1]);
    if rest.trim_start() != "}" {
        body.push(',');
    }
    body.push_str(rest);
    Ok(CachedVersion {
        version,
        contributions,
        map,
        body: Bytes::from(body),
    })
}

/// Renders the `GET /v1/maps/{map}` body of a version.
pub fn render(
    name: &str,
    version: i64,
    contributions: i64,
    map: Option<Arc<TransmitterMap>>,
) -> Result<CachedVersion, ApiError> {
    let doc_json = match &map {
        Some(m) => serde_json::to_string(&**m),
        None => serde_json::to_string(
            &TransmitterMap::empty(echomap_shared::map::DEFAULT_HEX_SIZE_M)
                .map_err(|e| anyhow::anyhow!("{e}"))?,
        ),
    }
    .map_err(anyhow::Error::from)?;
    render_json(name, version, contributions, map, &doc_json)
}

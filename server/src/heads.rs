//! What a replica on PostgreSQL knows about the maps' heads without asking the database
//! (`--replica-cache listen`). Every commit that moves a map's `current_version` notifies the
//! channel [`CHANNEL`] (a trigger, `migrations/postgres/20261206000001_notify_heads.sql`); a
//! task listens and records, per map, the newest version announced. A cached version is served
//! without reading the head when it was found current while the same listening session was up
//! and no newer version has been announced since. Whenever the listening connection is down,
//! notifications may be lost, so the session's generation ends and every request reads the head
//! again (`check`) until a new session is listening.

use std::collections::HashMap;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

/// The channel the trigger notifies.
pub const CHANNEL: &str = "echomap_heads";

/// How a replica on PostgreSQL knows that its cached current version of a map is still the
/// current one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReplicaCache {
    /// read the stored head on every request (one indexed read): a version another replica
    /// committed is served at once
    Check,
    /// trust the cache until a notification says the head moved: no read per request, but a
    /// version another replica committed is served only once its notification has arrived
    Listen,
}

impl ReplicaCache {
    /// Every mode, by its name.
    pub const ALL: [(&'static str, ReplicaCache); 2] = [
        ("check", ReplicaCache::Check),
        ("listen", ReplicaCache::Listen),
    ];
}

impl std::str::FromStr for ReplicaCache {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        crate::config::by_name(&Self::ALL, s, "replica cache")
    }
}

impl std::fmt::Display for ReplicaCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(crate::config::name_of(&Self::ALL, self))
    }
}

#[derive(Debug, Default)]
struct Known {
    /// newest version announced for the map in the current session
    announced: i64,
    /// (version, session) in which the cached version was last found current
    verified: Option<(i64, u64)>,
}

/// The heads announced to this process, per map id.
#[derive(Debug, Default)]
pub struct Heads {
    /// the listening session now up (0: none; notifications may be missed)
    session: AtomicU64,
    sessions: AtomicU64,
    known: Mutex<HashMap<i64, Known>>,
}

impl Heads {
    /// The listening session now up, 0 if none. Read it *before* reading a head from the
    /// database, and pass it to [`Heads::verified`].
    pub fn session(&self) -> u64 {
        self.session.load(Ordering::SeqCst)
    }

    /// A new listening session is up (call after `LISTEN` succeeded): what earlier sessions
    /// verified no longer counts.
    pub fn listening(&self) -> u64 {
        let s = self.sessions.fetch_add(1, Ordering::SeqCst) + 1;
        self.known.lock().expect("heads poisoned").clear();
        self.session.store(s, Ordering::SeqCst);
        s
    }

    /// The listening connection is down: notifications may be lost from now on.
    pub fn deaf(&self) {
        self.session.store(0, Ordering::SeqCst);
    }

    /// A notification: `map_id` is at `version` (or later).
    pub fn announced(&self, map_id: i64, version: i64) {
        let mut known = self.known.lock().expect("heads poisoned");
        let k = known.entry(map_id).or_default();
        k.announced = k.announced.max(version);
    }

    /// The database said `version` is `map_id`'s head, read after [`Heads::session`] returned
    /// `session`.
    pub fn verified(&self, map_id: i64, version: i64, session: u64) {
        if session == 0 {
            return;
        }
        let mut known = self.known.lock().expect("heads poisoned");
        if self.session.load(Ordering::SeqCst) == session {
            known.entry(map_id).or_default().verified = Some((version, session));
        }
    }

    /// Whether `version` may be served as `map_id`'s head without reading the database: it
    /// was verified in the listening session still up, and nothing newer was announced since.
    pub fn vouches(&self, map_id: i64, version: i64) -> bool {
        let session = self.session();
        if session == 0 {
            return false;
        }
        let known = self.known.lock().expect("heads poisoned");
        known
            .get(&map_id)
            .is_some_and(|k| k.verified == Some((version, session)) && k.announced <= version)
    }
}

/// Parses a notification's payload `<map id>:<version>`.
pub fn parse_payload(payload: &str) -> Option<(i64, i64)> {
    let (id, version) = payload.split_once(':')?;
    Some((id.parse().ok()?, version.parse().ok()?))
}

/// Listens on [`CHANNEL`] for as long as the process runs, reconnecting after a lost
/// connection (every `retry`), and records every announcement in `heads`.
pub async fn listen(pool: sqlx::PgPool, heads: std::sync::Arc<Heads>, retry: Duration) {
    use sqlx::postgres::PgListener;
    loop {
        heads.deaf();
        let mut listener = match PgListener::connect_with(&pool).await {
            Ok(l) => l,
            Err(e) => {
                if pool.is_closed() {
                    return;
                }
                tracing::warn!(error = %e, "cannot open the listening connection; retrying");
                tokio::time::sleep(retry).await;
                continue;
            }
        };
        if let Err(e) = listener.listen(CHANNEL).await {
            tracing::warn!(error = %e, "LISTEN failed; retrying");
            tokio::time::sleep(retry).await;
            continue;
        }
        let session = heads.listening();
        tracing::info!(session, "listening for map heads");
        metrics::counter!("echomap_head_listen_sessions_total").increment(1);
        loop {
            match listener.try_recv().await {
                Ok(Some(n)) => match parse_payload(n.payload()) {
                    Some((map_id, version)) => heads.announced(map_id, version),
                    None => tracing::warn!(payload = n.payload(), "unexpected head notification"),
                },
                // the connection was lost: notifications until the next session may be missed
                Ok(None) => {
                    tracing::warn!("the listening connection was lost; reconnecting");
                    break;
                }
                Err(e) => {
                    if pool.is_closed() {
                        heads.deaf();
                        return;
                    }
                    tracing::warn!(error = %e, "listening failed; reconnecting");
                    tokio::time::sleep(retry).await;
                    break;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_version_is_vouched_for_only_within_the_session_that_verified_it() {
        let h = Heads::default();
        // not listening: nothing is vouched for, and nothing is recorded
        h.verified(1, 3, h.session());
        assert!(!h.vouches(1, 3));
        let s = h.listening();
        assert_eq!(h.session(), s);
        h.verified(1, 3, s);
        assert!(h.vouches(1, 3));
        assert!(!h.vouches(1, 2), "another version than the one verified");
        assert!(!h.vouches(2, 3), "another map");
        // an older or equal announcement changes nothing, a newer one ends it
        h.announced(1, 3);
        assert!(h.vouches(1, 3));
        h.announced(1, 4);
        assert!(!h.vouches(1, 3));
        h.verified(1, 4, s);
        assert!(h.vouches(1, 4));
        // the connection drops: nothing is vouched for, and a head read in the old session
        // does not count in the next one
        h.deaf();
        assert!(!h.vouches(1, 4));
        let t = h.listening();
        assert_ne!(s, t);
        assert!(!h.vouches(1, 4));
        h.verified(1, 4, s);
        assert!(!h.vouches(1, 4), "read before the new session was up");
        h.verified(1, 4, t);
        assert!(h.vouches(1, 4));
    }

    #[test]
    fn payloads_are_map_id_colon_version() {
        assert_eq!(parse_payload("12:7"), Some((12, 7)));
        assert_eq!(parse_payload("12"), None);
        assert_eq!(parse_payload("a:7"), None);
        assert_eq!(parse_payload("12:x"), None);
    }
}

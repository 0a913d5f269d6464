//! All SQL of the server. SQLite in WAL mode with `synchronous=FULL` (an acknowledged
//! contribution survives a power cut), one writer connection taking `BEGIN IMMEDIATE`
//! transactions, and a separate read pool that merges never block.
//!
//! Every query is a static string with bound parameters (`$1`, valid on SQLite and PostgreSQL).
//! Writers check that the map's `current_version` is still the one they matched against before
//! committing (optimistic concurrency), so several server replicas on one database cannot lose
//! updates; inside one process merges of a map are additionally serialized by a lock.

use crate::delta::Encoding;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::{Row, SqlitePool};
use std::str::FromStr;
use std::time::Duration;

pub static MIGRATOR: sqlx::migrate::Migrator = sqlx::migrate!("../migrations");

/// SQLite waits this long for a lock before failing with "database is locked".
pub const BUSY_TIMEOUT: Duration = Duration::from_secs(10);

#[derive(Debug, Clone)]
pub struct Storage {
    writer: SqlitePool,
    reader: SqlitePool,
}

#[derive(Debug, Clone, sqlx::FromRow)]
pub struct MapRow {
    pub id: i64,
    pub name: String,
    pub private: bool,
    pub created_ms: i64,
    pub current_version: i64,
    /// accepted (not rolled back) contributions
    pub contributions: i64,
}

#[derive(Debug, Clone, sqlx::FromRow)]
pub struct VersionRow {
    pub number: i64,
    pub parent: Option<i64>,
    pub kind: String,
    pub contribution_id: i64,
    /// the full `echomap.map.v1` document (deltas are resolved when read)
    pub body: String,
    /// how the body is stored: `full` or `delta`
    pub encoding: String,
    pub transmitters: i64,
    pub created_ms: i64,
}

#[derive(Debug, Clone, sqlx::FromRow)]
pub struct StoredResponse {
    pub request_sha256: String,
    pub response_status: i64,
    pub response_body: Vec<u8>,
}

#[derive(Debug, Clone, sqlx::FromRow)]
pub struct ContributionRow {
    pub id: i64,
    pub contributor: String,
    pub agent: Option<String>,
    pub run: Option<String>,
    pub traveled_m: Option<f64>,
    pub received_ms: i64,
    pub status: String,
    pub reason: Option<String>,
    pub transmitters: i64,
    pub matched_version: Option<i64>,
    pub transform: Option<String>,
    pub inliers: Option<i64>,
    pub score: Option<f64>,
    pub merged: Option<i64>,
    pub added: Option<i64>,
    /// the version this contribution produced, if accepted
    pub version: Option<i64>,
}

/// A contribution to insert (its response is filled in once its id is known).
#[derive(Debug, Clone)]
pub struct NewContribution {
    pub contributor: String,
    pub agent: Option<String>,
    pub run: Option<String>,
    pub traveled_m: Option<f64>,
    pub idempotency_key: String,
    pub request_sha256: String,
    pub body: String,
    pub accepted: bool,
    pub reason: Option<String>,
    pub transmitters: i64,
    pub transform: Option<String>,
    pub inliers: Option<i64>,
    pub score: Option<f64>,
    pub merged: Option<i64>,
    pub added: Option<i64>,
}

/// The stored response of a contribution, rendered once its id and version are known.
pub type Respond = Box<dyn FnOnce(i64, Option<i64>) -> (u16, Vec<u8>) + Send>;

/// One contribution of a batch commit.
pub struct PendingCommit {
    pub contribution: NewContribution,
    /// the merged map it produced (accepted contributions)
    pub version: Option<NewVersion>,
    pub respond: Respond,
}

impl std::fmt::Debug for PendingCommit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PendingCommit")
            .field("contribution", &self.contribution)
            .field("version", &self.version.as_ref().map(|v| v.transmitters))
            .finish()
    }
}

/// A merged map to commit as the next version.
#[derive(Debug, Clone)]
pub struct NewVersion {
    /// the `echomap.map.v1` document, or a delta against the previous version
    pub body: String,
    pub encoding: Encoding,
    pub transmitters: i64,
}

#[derive(Debug, thiserror::Error)]
pub enum CommitError {
    /// another writer committed a version since this one was matched: re-match and retry
    #[error("map version moved from {expected} to {actual}")]
    VersionMoved { expected: i64, actual: i64 },
    /// entry `index`'s (contributor, Idempotency-Key) was committed meanwhile (another replica)
    #[error("idempotency key of batch entry {index} already used")]
    DuplicateKey { index: usize },
    /// the contribution to roll back is no longer accepted
    #[error("contribution no longer accepted")]
    NotAccepted,
    #[error(transparent)]
    Db(#[from] sqlx::Error),
}

/// The effective connection settings, read back from the database.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Pragmas {
    pub journal_mode: String,
    pub synchronous: i64,
    pub busy_timeout_ms: i64,
    pub foreign_keys: i64,
}

/// Optimistic concurrency: the map must still be at the version the caller matched against.
async fn expect_version(
    tx: &mut sqlx::Transaction<'static, sqlx::Sqlite>,
    map_id: i64,
    expected: i64,
) -> Result<(), CommitError> {
    let actual: i64 = sqlx::query_scalar("SELECT current_version FROM maps WHERE id = $1")
        .bind(map_id)
        .fetch_one(&mut **tx)
        .await?;
    if actual == expected {
        Ok(())
    } else {
        Err(CommitError::VersionMoved { expected, actual })
    }
}

/// Appends version `number` (its parent is `number − 1`, none for the first).
fn corrupt(map_id: i64, number: i64, why: &str) -> sqlx::Error {
    sqlx::Error::Protocol(format!("version {number} of map {map_id}: {why}"))
}

async fn insert_version(
    tx: &mut sqlx::Transaction<'static, sqlx::Sqlite>,
    map_id: i64,
    number: i64,
    kind: &str,
    contribution_id: i64,
    v: &NewVersion,
    created_ms: i64,
) -> Result<(), sqlx::Error> {
    sqlx::query(
        "INSERT INTO versions (map_id, number, parent, kind, contribution_id, body, encoding, transmitters, created_ms)
         VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9)",
    )
    .bind(map_id)
    .bind(number)
    .bind((number > 1).then_some(number - 1))
    .bind(kind)
    .bind(contribution_id)
    .bind(&v.body)
    .bind(v.encoding.as_str())
    .bind(v.transmitters)
    .bind(created_ms)
    .execute(&mut **tx)
    .await?;
    Ok(())
}

async fn set_current_version(
    tx: &mut sqlx::Transaction<'static, sqlx::Sqlite>,
    map_id: i64,
    number: i64,
) -> Result<(), sqlx::Error> {
    sqlx::query("UPDATE maps SET current_version = $1 WHERE id = $2")
        .bind(number)
        .bind(map_id)
        .execute(&mut **tx)
        .await?;
    Ok(())
}

pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as i64)
        .unwrap_or(0)
}

fn connect_options(url: &str) -> Result<SqliteConnectOptions, sqlx::Error> {
    let base = if url.starts_with("sqlite:") {
        SqliteConnectOptions::from_str(url)?
    } else {
        SqliteConnectOptions::new().filename(url)
    };
    Ok(base
        .create_if_missing(true)
        .journal_mode(SqliteJournalMode::Wal)
        .synchronous(SqliteSynchronous::Full)
        .busy_timeout(BUSY_TIMEOUT)
        .foreign_keys(true))
}

impl Storage {
    /// Opens (creating if missing) the database and applies the migrations.
    pub async fn open(url: &str, read_connections: u32) -> anyhow::Result<Self> {
        use anyhow::Context;
        let opts = connect_options(url).with_context(|| format!("bad database URL {url:?}"))?;
        let writer = SqlitePoolOptions::new()
            .max_connections(1)
            .acquire_timeout(Duration::from_secs(60))
            .connect_with(opts.clone())
            .await
            .with_context(|| format!("cannot open database {url:?}"))?;
        MIGRATOR.run(&writer).await.context("applying migrations")?;
        let reader = SqlitePoolOptions::new()
            .max_connections(read_connections.max(1))
            .acquire_timeout(Duration::from_secs(30))
            .connect_with(opts)
            .await
            .context("opening the read pool")?;
        Ok(Storage { writer, reader })
    }

    pub async fn close(&self) {
        self.reader.close().await;
        self.writer.close().await;
    }

    /// The settings of one connection of each pool (they must agree).
    pub async fn pragmas(&self) -> Result<[Pragmas; 2], sqlx::Error> {
        async fn read(pool: &SqlitePool) -> Result<Pragmas, sqlx::Error> {
            let mut c = pool.acquire().await?;
            Ok(Pragmas {
                journal_mode: sqlx::query_scalar("PRAGMA journal_mode")
                    .fetch_one(&mut *c)
                    .await?,
                synchronous: sqlx::query_scalar("PRAGMA synchronous")
                    .fetch_one(&mut *c)
                    .await?,
                busy_timeout_ms: sqlx::query_scalar("PRAGMA busy_timeout")
                    .fetch_one(&mut *c)
                    .await?,
                foreign_keys: sqlx::query_scalar("PRAGMA foreign_keys")
                    .fetch_one(&mut *c)
                    .await?,
            })
        }
        Ok([read(&self.writer).await?, read(&self.reader).await?])
    }

    /// Database reachable and every migration of this binary applied.
    pub async fn ready(&self) -> Result<bool, sqlx::Error> {
        let applied: i64 =
            sqlx::query_scalar("SELECT COUNT(*) FROM _sqlx_migrations WHERE success = 1")
                .fetch_one(&self.reader)
                .await?;
        Ok(applied as usize >= MIGRATOR.migrations.len())
    }

    /// Creates the map if it does not exist; returns it and whether it was created.
    pub async fn create_map(
        &self,
        name: &str,
        private: bool,
    ) -> Result<(MapRow, bool), sqlx::Error> {
        let mut tx = self.writer.begin_with("BEGIN IMMEDIATE").await?;
        let inserted = sqlx::query(
            "INSERT INTO maps (name, private, created_ms) VALUES ($1, $2, $3) ON CONFLICT (name) DO NOTHING",
        )
        .bind(name)
        .bind(private)
        .bind(now_ms())
        .execute(&mut *tx)
        .await?
        .rows_affected()
            == 1;
        tx.commit().await?;
        let row = self.map(name).await?.ok_or(sqlx::Error::RowNotFound)?;
        Ok((row, inserted))
    }

    pub async fn map(&self, name: &str) -> Result<Option<MapRow>, sqlx::Error> {
        sqlx::query_as(
            "SELECT m.id, m.name, m.private, m.created_ms, m.current_version,
                    (SELECT COUNT(*) FROM contributions c WHERE c.map_id = m.id AND c.status = 'accepted') AS contributions
             FROM maps m WHERE m.name = $1",
        )
        .bind(name)
        .fetch_optional(&self.reader)
        .await
    }

    pub async fn maps(&self) -> Result<Vec<MapRow>, sqlx::Error> {
        sqlx::query_as(
            "SELECT m.id, m.name, m.private, m.created_ms, m.current_version,
                    (SELECT COUNT(*) FROM contributions c WHERE c.map_id = m.id AND c.status = 'accepted') AS contributions
             FROM maps m ORDER BY m.name",
        )
        .fetch_all(&self.reader)
        .await
    }

    /// Version `number` with its full document (a stored delta is resolved from the nearest
    /// earlier full body, in one read transaction).
    pub async fn version(
        &self,
        map_id: i64,
        number: i64,
    ) -> Result<Option<VersionRow>, sqlx::Error> {
        let mut tx = self.reader.begin().await?;
        let row: Option<VersionRow> = sqlx::query_as(
            "SELECT number, parent, kind, contribution_id, body, encoding, transmitters, created_ms
             FROM versions WHERE map_id = $1 AND number = $2",
        )
        .bind(map_id)
        .bind(number)
        .fetch_optional(&mut *tx)
        .await?;
        let Some(mut row) = row else {
            return Ok(None);
        };
        if row.encoding == Encoding::Delta.as_str() {
            let chain: Vec<(String, String)> = sqlx::query_as(
                "SELECT encoding, body FROM versions
                 WHERE map_id = $1 AND number <= $2 AND number >= (
                     SELECT MAX(number) FROM versions
                     WHERE map_id = $1 AND number < $2 AND encoding = 'full')
                 ORDER BY number",
            )
            .bind(map_id)
            .bind(number)
            .fetch_all(&mut *tx)
            .await?;
            let mut steps = chain.into_iter();
            let mut doc = match steps.next() {
                Some((e, body)) if e == Encoding::Full.as_str() => body,
                _ => return Err(corrupt(map_id, number, "no full body before the delta")),
            };
            for (_, delta) in steps {
                doc = crate::delta::apply(&doc, &delta).map_err(|e| corrupt(map_id, number, &e))?;
            }
            row.body = doc;
            row.encoding = Encoding::Full.as_str().into();
        }
        tx.commit().await?;
        Ok(Some(row))
    }

    /// Contributions merged into version `n`: merges up to it minus rollbacks up to it.
    pub async fn contributions_merged_up_to(
        &self,
        map_id: i64,
        n: i64,
    ) -> Result<i64, sqlx::Error> {
        sqlx::query_scalar(
            "SELECT COALESCE(SUM(CASE kind WHEN 'merge' THEN 1 ELSE -1 END), 0)
             FROM versions WHERE map_id = $1 AND number <= $2",
        )
        .bind(map_id)
        .bind(n)
        .fetch_one(&self.reader)
        .await
    }

    pub async fn stored_response(
        &self,
        map_id: i64,
        contributor: &str,
        key: &str,
    ) -> Result<Option<StoredResponse>, sqlx::Error> {
        sqlx::query_as(
            "SELECT request_sha256, response_status, response_body FROM contributions
             WHERE map_id = $1 AND contributor = $2 AND idempotency_key = $3",
        )
        .bind(map_id)
        .bind(contributor)
        .bind(key)
        .fetch_optional(&self.reader)
        .await
    }

    /// Commits a batch of contributions (each accepted one with the version it produced, in
    /// order) in one `BEGIN IMMEDIATE` transaction — one fsync for the batch — provided the
    /// map is still at `expected_version`. Each entry's `respond(contribution id, new version)`
    /// renders the response stored with it (replayed on retries).
    pub async fn commit_batch(
        &self,
        map_id: i64,
        expected_version: i64,
        entries: Vec<PendingCommit>,
    ) -> Result<Vec<(u16, Vec<u8>)>, CommitError> {
        let mut tx = self.writer.begin_with("BEGIN IMMEDIATE").await?;
        expect_version(&mut tx, map_id, expected_version).await?;
        let now = now_ms();
        let mut current = expected_version;
        let mut responses = Vec::with_capacity(entries.len());
        for (index, e) in entries.into_iter().enumerate() {
            let c = &e.contribution;
            let inserted = sqlx::query(
                "INSERT INTO contributions (map_id, contributor, agent, run, traveled_m, idempotency_key,
                    request_sha256, body, received_ms, status, reason, transmitters, matched_version,
                    transform, inliers, score, merged, added, response_status, response_body)
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, $14, $15, $16, $17, $18, 0, x'')
                 ON CONFLICT (map_id, contributor, idempotency_key) DO NOTHING",
            )
            .bind(map_id)
            .bind(&c.contributor)
            .bind(&c.agent)
            .bind(&c.run)
            .bind(c.traveled_m)
            .bind(&c.idempotency_key)
            .bind(&c.request_sha256)
            .bind(&c.body)
            .bind(now)
            .bind(if c.accepted { "accepted" } else { "rejected" })
            .bind(&c.reason)
            .bind(c.transmitters)
            .bind(current)
            .bind(&c.transform)
            .bind(c.inliers)
            .bind(c.score)
            .bind(c.merged)
            .bind(c.added)
            .execute(&mut *tx)
            .await?;
            if inserted.rows_affected() == 0 {
                return Err(CommitError::DuplicateKey { index });
            }
            let id = inserted.last_insert_rowid();
            let new_version = match &e.version {
                Some(v) => {
                    let number = current + 1;
                    insert_version(&mut tx, map_id, number, "merge", id, v, now).await?;
                    current = number;
                    Some(number)
                }
                None => None,
            };
            let (status, body) = (e.respond)(id, new_version);
            sqlx::query(
                "UPDATE contributions SET response_status = $1, response_body = $2 WHERE id = $3",
            )
            .bind(i64::from(status))
            .bind(&body)
            .bind(id)
            .execute(&mut *tx)
            .await?;
            responses.push((status, body));
        }
        if current != expected_version {
            set_current_version(&mut tx, map_id, current).await?;
        }
        tx.commit().await?;
        Ok(responses)
    }

    pub async fn contributions(
        &self,
        map_id: i64,
        after: i64,
        limit: i64,
    ) -> Result<Vec<ContributionRow>, sqlx::Error> {
        sqlx::query_as(
            "SELECT c.id, c.contributor, c.agent, c.run, c.traveled_m, c.received_ms, c.status, c.reason,
                    c.transmitters, c.matched_version, c.transform, c.inliers, c.score, c.merged, c.added,
                    (SELECT v.number FROM versions v WHERE v.contribution_id = c.id AND v.kind = 'merge') AS version
             FROM contributions c WHERE c.map_id = $1 AND c.id > $2 ORDER BY c.id LIMIT $3",
        )
        .bind(map_id)
        .bind(after)
        .bind(limit)
        .fetch_all(&self.reader)
        .await
    }

    /// Status of one contribution of a map, with its contributor.
    pub async fn contribution_status(
        &self,
        map_id: i64,
        id: i64,
    ) -> Result<Option<(String, String)>, sqlx::Error> {
        let row = sqlx::query(
            "SELECT status, contributor FROM contributions WHERE map_id = $1 AND id = $2",
        )
        .bind(map_id)
        .bind(id)
        .fetch_optional(&self.reader)
        .await?;
        Ok(row.map(|r| (r.get(0), r.get(1))))
    }

    /// Verbatim bodies of the accepted contributions of a map, oldest first, without `except`.
    pub async fn accepted_bodies(
        &self,
        map_id: i64,
        except: i64,
    ) -> Result<Vec<(i64, String)>, sqlx::Error> {
        let rows = sqlx::query(
            "SELECT id, body FROM contributions WHERE map_id = $1 AND status = 'accepted' AND id <> $2 ORDER BY id",
        )
        .bind(map_id)
        .bind(except)
        .fetch_all(&self.reader)
        .await?;
        Ok(rows.into_iter().map(|r| (r.get(0), r.get(1))).collect())
    }

    /// Marks `contribution_id` rolled back and commits the rebuilt map as the next version,
    /// if the map is still at `expected_version` and the contribution still accepted.
    pub async fn commit_rollback(
        &self,
        map_id: i64,
        expected_version: i64,
        contribution_id: i64,
        rebuilt: &NewVersion,
    ) -> Result<i64, CommitError> {
        let mut tx = self.writer.begin_with("BEGIN IMMEDIATE").await?;
        expect_version(&mut tx, map_id, expected_version).await?;
        let changed = sqlx::query(
            "UPDATE contributions SET status = 'rolled_back' WHERE id = $1 AND map_id = $2 AND status = 'accepted'",
        )
        .bind(contribution_id)
        .bind(map_id)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        if changed != 1 {
            return Err(CommitError::NotAccepted);
        }
        let number = expected_version + 1;
        insert_version(
            &mut tx,
            map_id,
            number,
            "rollback",
            contribution_id,
            rebuilt,
            now_ms(),
        )
        .await?;
        set_current_version(&mut tx, map_id, number).await?;
        tx.commit().await?;
        Ok(number)
    }
}

//! All SQL of the server, on SQLite (the embedded default) or PostgreSQL (the scale path: several
//! server replicas on one database).
//!
//! SQLite runs in WAL mode with `synchronous=FULL` (an acknowledged contribution survives a power
//! cut), one writer connection taking `BEGIN IMMEDIATE` transactions, and a separate read pool
//! that merges never block. PostgreSQL uses one pool; a commit locks its map's row
//! (`SELECT … FOR UPDATE`), which serializes the merges of one map across replicas while other
//! maps commit in parallel.
//!
//! Every query is one static string with bound parameters (`$1`, valid on both databases),
//! written once and compiled for each backend by the `on_reader!` and `in_write_tx!`
//! macros. Writers check that the map's `current_version` is still the one they matched against
//! before committing (optimistic concurrency), so several server processes on one database
//! cannot lose updates; inside one process merges of a map are additionally serialized by a
//! lock.

use crate::delta::Encoding;
use sqlx::SqlitePool;
use sqlx::postgres::{PgConnectOptions, PgPool, PgPoolOptions};
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use std::str::FromStr;
use std::time::Duration;

/// The SQLite schema (`migrations/*.sql`).
pub static MIGRATOR: sqlx::migrate::Migrator = sqlx::migrate!("../migrations");
/// The same schema in PostgreSQL's types (`migrations/postgres/*.sql`).
pub static PG_MIGRATOR: sqlx::migrate::Migrator = sqlx::migrate!("../migrations/postgres");

/// SQLite waits this long for a lock before failing with "database is locked".
pub const BUSY_TIMEOUT: Duration = Duration::from_secs(10);

/// Which database a URL names: `postgres://` or `postgresql://` is PostgreSQL, anything else
/// (`sqlite://…` or a plain path) SQLite.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    Sqlite,
    Postgres,
}

impl Kind {
    pub fn of_url(url: &str) -> Kind {
        if url.starts_with("postgres://") || url.starts_with("postgresql://") {
            Kind::Postgres
        } else {
            Kind::Sqlite
        }
    }
}

#[derive(Debug, Clone)]
enum Backend {
    Sqlite {
        writer: SqlitePool,
        reader: SqlitePool,
    },
    Postgres(PgPool),
}

#[derive(Debug, Clone)]
pub struct Storage {
    backend: Backend,
}

/// Evaluates `$body` with `$pool` bound to the read pool of the backend (the body is compiled
/// once per database).
macro_rules! on_reader {
    ($self:expr, |$pool:ident| $body:expr) => {
        match &$self.backend {
            Backend::Sqlite { reader: $pool, .. } => $body,
            Backend::Postgres($pool) => $body,
        }
    };
}

/// Evaluates `$body` with `$tx` a write transaction and `$lock` the query that reads a map's
/// `current_version` and, on PostgreSQL, locks its row until the transaction ends. On SQLite
/// the transaction is `BEGIN IMMEDIATE` (it takes the database's write lock at once).
macro_rules! in_write_tx {
    ($self:expr, |$tx:ident, $lock:ident| $body:expr) => {
        match &$self.backend {
            Backend::Sqlite { writer, .. } => {
                #[allow(unused_mut)]
                let mut $tx = writer.begin_with("BEGIN IMMEDIATE").await?;
                let $lock = "SELECT current_version FROM maps WHERE id = $1";
                $body
            }
            Backend::Postgres(pool) => {
                #[allow(unused_mut)]
                let mut $tx = pool.begin().await?;
                let $lock = "SELECT current_version FROM maps WHERE id = $1 FOR UPDATE";
                $body
            }
        }
    };
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
    /// when the current version was committed (none before the first)
    pub updated_ms: Option<i64>,
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

/// Optimistic concurrency, inside [`in_write_tx!`]: returns `VersionMoved` unless the map is
/// still at the version the caller matched against.
macro_rules! expect_version {
    ($tx:ident, $lock:ident, $map_id:expr, $expected:expr) => {{
        let (map_id, expected): (i64, i64) = ($map_id, $expected);
        let actual: i64 = sqlx::query_scalar($lock)
            .bind(map_id)
            .fetch_one(&mut *$tx)
            .await?;
        if actual != expected {
            return Err(CommitError::VersionMoved { expected, actual });
        }
    }};
}

/// Appends version `$number` (its parent is `number − 1`, none for the first), inside
/// [`in_write_tx!`].
macro_rules! insert_version {
    ($tx:ident, $map_id:expr, $number:expr, $kind:expr, $contribution_id:expr, $v:expr, $created_ms:expr) => {{
        let (number, v): (i64, &NewVersion) = ($number, $v);
        sqlx::query(
            "INSERT INTO versions (map_id, number, parent, kind, contribution_id, body, encoding, transmitters, created_ms)
             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9)",
        )
        .bind($map_id)
        .bind(number)
        .bind((number > 1).then_some(number - 1))
        .bind($kind)
        .bind($contribution_id)
        .bind(&v.body)
        .bind(v.encoding.as_str())
        .bind(v.transmitters)
        .bind($created_ms)
        .execute(&mut *$tx)
        .await?;
    }};
}

/// Moves the map's `current_version`, inside [`in_write_tx!`].
macro_rules! set_current_version {
    ($tx:ident, $map_id:expr, $number:expr) => {{
        sqlx::query("UPDATE maps SET current_version = $1 WHERE id = $2")
            .bind($number)
            .bind($map_id)
            .execute(&mut *$tx)
            .await?;
    }};
}

fn corrupt(map_id: i64, number: i64, why: &str) -> sqlx::Error {
    sqlx::Error::Protocol(format!("version {number} of map {map_id}: {why}"))
}

pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as i64)
        .unwrap_or(0)
}

fn sqlite_options(url: &str) -> Result<SqliteConnectOptions, sqlx::Error> {
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

/// How long [`Storage::open`] waits for a PostgreSQL connection (the server's
/// `--database-timeout-s` default).
pub const PG_CONNECT_TIMEOUT: Duration = Duration::from_secs(60);

/// The file a SQLite URL or path names (`None` for PostgreSQL or an unparsable URL).
pub fn sqlite_file(url: &str) -> Option<std::path::PathBuf> {
    if Kind::of_url(url) != Kind::Sqlite {
        return None;
    }
    Some(sqlite_options(url).ok()?.get_filename().to_path_buf())
}

/// Connections a PostgreSQL pool keeps for commits, besides `read_connections` for reads.
pub const PG_WRITE_CONNECTIONS: u32 = 4;

impl Storage {
    /// Opens the database and applies the migrations. SQLite: the file is created if missing.
    /// PostgreSQL: the database must exist; the migrator takes an advisory lock, so replicas
    /// starting together apply each migration once.
    pub async fn open(url: &str, read_connections: u32) -> anyhow::Result<Self> {
        Self::open_with(url, read_connections, PG_CONNECT_TIMEOUT).await
    }

    /// [`Storage::open`], waiting at most `pg_timeout` for a PostgreSQL connection (at
    /// start-up and per request).
    pub async fn open_with(
        url: &str,
        read_connections: u32,
        pg_timeout: Duration,
    ) -> anyhow::Result<Self> {
        use anyhow::Context;
        let read_connections = read_connections.max(1);
        let backend = match Kind::of_url(url) {
            Kind::Sqlite => {
                let opts =
                    sqlite_options(url).with_context(|| format!("bad database URL {url:?}"))?;
                let writer = SqlitePoolOptions::new()
                    .max_connections(1)
                    .acquire_timeout(Duration::from_secs(60))
                    .connect_with(opts.clone())
                    .await
                    .with_context(|| format!("cannot open database {url:?}"))?;
                MIGRATOR.run(&writer).await.context("applying migrations")?;
                let reader = SqlitePoolOptions::new()
                    .max_connections(read_connections)
                    .acquire_timeout(Duration::from_secs(30))
                    .connect_with(opts)
                    .await
                    .context("opening the read pool")?;
                Backend::Sqlite { writer, reader }
            }
            Kind::Postgres => {
                let opts = PgConnectOptions::from_str(url)
                    .with_context(|| format!("bad database URL {}", redact(url)))?;
                let pool = PgPoolOptions::new()
                    .max_connections(read_connections + PG_WRITE_CONNECTIONS)
                    .acquire_timeout(pg_timeout)
                    .connect_with(opts)
                    .await
                    .with_context(|| format!("cannot connect to {}", redact(url)))?;
                PG_MIGRATOR
                    .run(&pool)
                    .await
                    .context("applying migrations")?;
                Backend::Postgres(pool)
            }
        };
        Ok(Storage { backend })
    }

    /// A pool of one connection to the same PostgreSQL database, connecting on first use
    /// (for a connection held by a listener, apart from the request pools); `None` on SQLite.
    pub fn pg_side_pool(&self) -> Option<PgPool> {
        match &self.backend {
            Backend::Postgres(pool) => Some(
                PgPoolOptions::new()
                    .max_connections(1)
                    .acquire_timeout(pool.options().get_acquire_timeout())
                    .connect_lazy_with((*pool.connect_options()).clone()),
            ),
            Backend::Sqlite { .. } => None,
        }
    }

    pub fn kind(&self) -> Kind {
        match self.backend {
            Backend::Sqlite { .. } => Kind::Sqlite,
            Backend::Postgres(_) => Kind::Postgres,
        }
    }

    fn migrator(&self) -> &'static sqlx::migrate::Migrator {
        match self.kind() {
            Kind::Sqlite => &MIGRATOR,
            Kind::Postgres => &PG_MIGRATOR,
        }
    }

    pub async fn close(&self) {
        match &self.backend {
            Backend::Sqlite { writer, reader } => {
                reader.close().await;
                writer.close().await;
            }
            Backend::Postgres(pool) => pool.close().await,
        }
    }

    /// The settings of one connection of each SQLite pool (they must agree); an error on
    /// PostgreSQL, which has no PRAGMAs.
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
        match &self.backend {
            Backend::Sqlite { writer, reader } => Ok([read(writer).await?, read(reader).await?]),
            Backend::Postgres(_) => Err(sqlx::Error::Configuration(
                "PRAGMAs are SQLite settings; this server runs on PostgreSQL".into(),
            )),
        }
    }

    /// Database reachable and every migration of this binary applied.
    pub async fn ready(&self) -> Result<bool, sqlx::Error> {
        let applied: i64 = on_reader!(self, |pool| {
            sqlx::query_scalar("SELECT COUNT(*) FROM _sqlx_migrations WHERE success")
                .fetch_one(pool)
                .await?
        });
        Ok(applied as usize >= self.migrator().migrations.len())
    }

    /// Creates the map if it does not exist; returns it and whether it was created.
    pub async fn create_map(
        &self,
        name: &str,
        private: bool,
    ) -> Result<(MapRow, bool), sqlx::Error> {
        let inserted = in_write_tx!(self, |tx, _lock| {
            let n = sqlx::query(
                "INSERT INTO maps (name, private, created_ms) VALUES ($1, $2, $3) ON CONFLICT (name) DO NOTHING",
            )
            .bind(name)
            .bind(private)
            .bind(now_ms())
            .execute(&mut *tx)
            .await?
            .rows_affected();
            tx.commit().await?;
            n == 1
        });
        let row = self.map(name).await?.ok_or(sqlx::Error::RowNotFound)?;
        Ok((row, inserted))
    }

    pub async fn map(&self, name: &str) -> Result<Option<MapRow>, sqlx::Error> {
        on_reader!(self, |pool| {
            sqlx::query_as(
                "SELECT m.id, m.name, m.private, m.created_ms, m.current_version,
                        (SELECT COUNT(*) FROM contributions c WHERE c.map_id = m.id AND c.status = 'accepted') AS contributions,
                        (SELECT v.created_ms FROM versions v WHERE v.map_id = m.id AND v.number = m.current_version) AS updated_ms
                 FROM maps m WHERE m.name = $1",
            )
            .bind(name)
            .fetch_optional(pool)
            .await
        })
    }

    /// PostgreSQL: takes one write from `contributor`'s allowance shared by every replica
    /// (GCRA on the database's clock: an emission interval of `emission_ms`, a burst tolerance
    /// of `tolerance_ms`). `None` when the write is allowed, else how many ms until it would
    /// be. On SQLite (one process) the caller's own limiter decides: always `None`.
    pub async fn take_write_cell(
        &self,
        contributor: &str,
        emission_ms: f64,
        tolerance_ms: f64,
    ) -> Result<Option<f64>, sqlx::Error> {
        // one instant per statement (the replicas' own clocks play no part)
        const NOW: &str = "(EXTRACT(EPOCH FROM statement_timestamp()) * 1000)::DOUBLE PRECISION";
        let Backend::Postgres(pool) = &self.backend else {
            return Ok(None);
        };
        let taken: Option<f64> = sqlx::query_scalar(sqlx::AssertSqlSafe(format!(
            "INSERT INTO write_limits AS w (contributor, tat_ms) VALUES ($1, {NOW} + $2)
             ON CONFLICT (contributor) DO UPDATE SET tat_ms = GREATEST(w.tat_ms, {NOW}) + $2
                 WHERE w.tat_ms - {NOW} <= $3
             RETURNING tat_ms"
        )))
        .bind(contributor)
        .bind(emission_ms)
        .bind(tolerance_ms)
        .fetch_optional(pool)
        .await?;
        if taken.is_some() {
            return Ok(None);
        }
        let wait: f64 = sqlx::query_scalar(sqlx::AssertSqlSafe(format!(
            "SELECT tat_ms - {NOW} - $2 FROM write_limits WHERE contributor = $1"
        )))
        .bind(contributor)
        .bind(tolerance_ms)
        .fetch_one(pool)
        .await?;
        Ok(Some(wait.max(0.0)))
    }

    /// The version number a map is at, as stored (for replicas: another process may have
    /// committed since this one cached it).
    pub async fn current_version(&self, map_id: i64) -> Result<Option<i64>, sqlx::Error> {
        on_reader!(self, |pool| {
            sqlx::query_scalar("SELECT current_version FROM maps WHERE id = $1")
                .bind(map_id)
                .fetch_optional(pool)
                .await
        })
    }

    pub async fn maps(&self) -> Result<Vec<MapRow>, sqlx::Error> {
        on_reader!(self, |pool| {
            sqlx::query_as(
                "SELECT m.id, m.name, m.private, m.created_ms, m.current_version,
                        (SELECT COUNT(*) FROM contributions c WHERE c.map_id = m.id AND c.status = 'accepted') AS contributions,
                        (SELECT v.created_ms FROM versions v WHERE v.map_id = m.id AND v.number = m.current_version) AS updated_ms
                 FROM maps m ORDER BY m.name",
            )
            .fetch_all(pool)
            .await
        })
    }

    /// Version `number` with its full document (a stored delta is resolved from the nearest
    /// earlier full body, in one read transaction).
    pub async fn version(
        &self,
        map_id: i64,
        number: i64,
    ) -> Result<Option<VersionRow>, sqlx::Error> {
        let (mut row, chain) = on_reader!(self, |pool| {
            let mut tx = pool.begin().await?;
            let row: Option<VersionRow> = sqlx::query_as(
                "SELECT number, parent, kind, contribution_id, body, encoding, transmitters, created_ms
                 FROM versions WHERE map_id = $1 AND number = $2",
            )
            .bind(map_id)
            .bind(number)
            .fetch_optional(&mut *tx)
            .await?;
            let Some(row) = row else {
                return Ok(None);
            };
            let chain: Vec<(String, String)> = if row.encoding == Encoding::Delta.as_str() {
                sqlx::query_as(
                    "SELECT encoding, body FROM versions
                     WHERE map_id = $1 AND number <= $2 AND number >= (
                         SELECT MAX(number) FROM versions
                         WHERE map_id = $1 AND number < $2 AND encoding = 'full')
                     ORDER BY number",
                )
                .bind(map_id)
                .bind(number)
                .fetch_all(&mut *tx)
                .await?
            } else {
                Vec::new()
            };
            tx.commit().await?;
            (row, chain)
        });
        if row.encoding == Encoding::Delta.as_str() {
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
        Ok(Some(row))
    }

    /// Contributions merged into version `n`: merges up to it minus rollbacks up to it.
    pub async fn contributions_merged_up_to(
        &self,
        map_id: i64,
        n: i64,
    ) -> Result<i64, sqlx::Error> {
        on_reader!(self, |pool| {
            sqlx::query_scalar(
                "SELECT COALESCE(SUM(CASE kind WHEN 'merge' THEN 1 ELSE -1 END), 0)
                 FROM versions WHERE map_id = $1 AND number <= $2",
            )
            .bind(map_id)
            .bind(n)
            .fetch_one(pool)
            .await
        })
    }

    pub async fn stored_response(
        &self,
        map_id: i64,
        contributor: &str,
        key: &str,
    ) -> Result<Option<StoredResponse>, sqlx::Error> {
        on_reader!(self, |pool| {
            sqlx::query_as(
                "SELECT request_sha256, response_status, response_body FROM contributions
                 WHERE map_id = $1 AND contributor = $2 AND idempotency_key = $3",
            )
            .bind(map_id)
            .bind(contributor)
            .bind(key)
            .fetch_optional(pool)
            .await
        })
    }

    /// How many of `contributor`'s contributions (to any map) were rejected since `since_ms`, and
    /// when the oldest of them was received.
    pub async fn rejected_since(
        &self,
        contributor: &str,
        since_ms: i64,
    ) -> Result<(i64, Option<i64>), sqlx::Error> {
        on_reader!(self, |pool| {
            sqlx::query_as(
                "SELECT COUNT(*), MIN(received_ms) FROM contributions
                 WHERE contributor = $1 AND received_ms >= $2 AND status = 'rejected'",
            )
            .bind(contributor)
            .bind(since_ms)
            .fetch_one(pool)
            .await
        })
    }

    /// Commits a batch of contributions (each accepted one with the version it produced, in
    /// order) in one write transaction — one fsync for the batch — provided the map is still
    /// at `expected_version`. Each entry's `respond(contribution id, new version)` renders the
    /// response stored with it (replayed on retries).
    pub async fn commit_batch(
        &self,
        map_id: i64,
        expected_version: i64,
        entries: Vec<PendingCommit>,
    ) -> Result<Vec<(u16, Vec<u8>)>, CommitError> {
        in_write_tx!(self, |tx, lock| {
            expect_version!(tx, lock, map_id, expected_version);
            let now = now_ms();
            let mut current = expected_version;
            let mut responses = Vec::with_capacity(entries.len());
            for (index, e) in entries.into_iter().enumerate() {
                let c = &e.contribution;
                let id: Option<i64> = sqlx::query_scalar(
                    "INSERT INTO contributions (map_id, contributor, agent, run, traveled_m, idempotency_key,
                        request_sha256, body, received_ms, status, reason, transmitters, matched_version,
                        transform, inliers, score, merged, added, response_status, response_body)
                     VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, $14, $15, $16, $17, $18, 0, $19)
                     ON CONFLICT (map_id, contributor, idempotency_key) DO NOTHING
                     RETURNING id",
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
                .bind(Vec::<u8>::new())
                .fetch_optional(&mut *tx)
                .await?;
                let Some(id) = id else {
                    return Err(CommitError::DuplicateKey { index });
                };
                let new_version = match &e.version {
                    Some(v) => {
                        let number = current + 1;
                        insert_version!(tx, map_id, number, "merge", id, v, now);
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
                set_current_version!(tx, map_id, current);
            }
            tx.commit().await?;
            Ok(responses)
        })
    }

    pub async fn contributions(
        &self,
        map_id: i64,
        after: i64,
        limit: i64,
    ) -> Result<Vec<ContributionRow>, sqlx::Error> {
        on_reader!(self, |pool| {
            sqlx::query_as(
                "SELECT c.id, c.contributor, c.agent, c.run, c.traveled_m, c.received_ms, c.status, c.reason,
                        c.transmitters, c.matched_version, c.transform, c.inliers, c.score, c.merged, c.added,
                        (SELECT v.number FROM versions v WHERE v.contribution_id = c.id AND v.kind = 'merge') AS version
                 FROM contributions c WHERE c.map_id = $1 AND c.id > $2 ORDER BY c.id LIMIT $3",
            )
            .bind(map_id)
            .bind(after)
            .bind(limit)
            .fetch_all(pool)
            .await
        })
    }

    /// Status of one contribution of a map, with its contributor.
    pub async fn contribution_status(
        &self,
        map_id: i64,
        id: i64,
    ) -> Result<Option<(String, String)>, sqlx::Error> {
        on_reader!(self, |pool| {
            sqlx::query_as(
                "SELECT status, contributor FROM contributions WHERE map_id = $1 AND id = $2",
            )
            .bind(map_id)
            .bind(id)
            .fetch_optional(pool)
            .await
        })
    }

    /// Verbatim bodies of the accepted contributions of a map, oldest first, without `except`.
    pub async fn accepted_bodies(
        &self,
        map_id: i64,
        except: i64,
    ) -> Result<Vec<(i64, String)>, sqlx::Error> {
        on_reader!(self, |pool| {
            sqlx::query_as(
                "SELECT id, body FROM contributions WHERE map_id = $1 AND status = 'accepted' AND id <> $2 ORDER BY id",
            )
            .bind(map_id)
            .bind(except)
            .fetch_all(pool)
            .await
        })
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
        in_write_tx!(self, |tx, lock| {
            expect_version!(tx, lock, map_id, expected_version);
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
            insert_version!(
                tx,
                map_id,
                number,
                "rollback",
                contribution_id,
                rebuilt,
                now_ms()
            );
            set_current_version!(tx, map_id, number);
            tx.commit().await?;
            Ok(number)
        })
    }
}

/// Rows read from the source per step of [`Storage::copy_into`] (the `copy-to --page-rows`
/// default).
pub const COPY_PAGE: u32 = 500;

#[derive(Debug, sqlx::FromRow)]
struct MapCopy {
    id: i64,
    name: String,
    private: bool,
    created_ms: i64,
    current_version: i64,
}

#[derive(Debug, sqlx::FromRow)]
struct ContributionCopy {
    id: i64,
    map_id: i64,
    contributor: String,
    agent: Option<String>,
    run: Option<String>,
    traveled_m: Option<f64>,
    idempotency_key: String,
    request_sha256: String,
    body: String,
    received_ms: i64,
    status: String,
    reason: Option<String>,
    transmitters: i64,
    matched_version: Option<i64>,
    transform: Option<String>,
    inliers: Option<i64>,
    score: Option<f64>,
    merged: Option<i64>,
    added: Option<i64>,
    response_status: i64,
    response_body: Vec<u8>,
}

#[derive(Debug, sqlx::FromRow)]
struct VersionCopy {
    map_id: i64,
    number: i64,
    parent: Option<i64>,
    kind: String,
    contribution_id: i64,
    body: String,
    encoding: String,
    transmitters: i64,
    created_ms: i64,
}

/// What [`Storage::copy_into`] copied.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Copied {
    pub maps: usize,
    pub contributions: usize,
    pub versions: usize,
}

impl Storage {
    /// Whether the database holds no map.
    pub async fn is_empty(&self) -> Result<bool, sqlx::Error> {
        let n: i64 = on_reader!(self, |pool| {
            sqlx::query_scalar("SELECT COUNT(*) FROM maps")
                .fetch_one(pool)
                .await?
        });
        Ok(n == 0)
    }

    /// Copies every map, contribution and version, row for row with their ids (so stored
    /// responses, ETags and contribution ids stay valid), into `target`, which must hold no
    /// map — e.g. from SQLite to PostgreSQL when one machine is no longer enough. One write
    /// transaction on the target, filled page by page (`page_rows` rows in memory at a
    /// time): it gets everything or nothing. Version bodies are copied as stored (full or
    /// delta). Stop the servers writing to `self` first.
    pub async fn copy_into(&self, target: &Storage, page_rows: u32) -> anyhow::Result<Copied> {
        use anyhow::Context;
        let page_rows = i64::from(page_rows.max(1));
        anyhow::ensure!(
            target.is_empty().await?,
            "the target database already holds maps: copy only into an empty database"
        );
        // PostgreSQL's identity columns take given ids only when told to
        let (insert_map, insert_contribution) = match target.kind() {
            Kind::Sqlite => (
                "INSERT INTO maps (id, name, private, created_ms, current_version)
                 VALUES ($1, $2, $3, $4, $5)",
                "INSERT INTO contributions (id, map_id, contributor, agent, run, traveled_m,
                    idempotency_key, request_sha256, body, received_ms, status, reason, transmitters,
                    matched_version, transform, inliers, score, merged, added, response_status,
                    response_body)
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, $14, $15, $16,
                    $17, $18, $19, $20, $21)",
            ),
            Kind::Postgres => (
                "INSERT INTO maps (id, name, private, created_ms, current_version)
                 OVERRIDING SYSTEM VALUE VALUES ($1, $2, $3, $4, $5)",
                "INSERT INTO contributions (id, map_id, contributor, agent, run, traveled_m,
                    idempotency_key, request_sha256, body, received_ms, status, reason, transmitters,
                    matched_version, transform, inliers, score, merged, added, response_status,
                    response_body)
                 OVERRIDING SYSTEM VALUE
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, $14, $15, $16,
                    $17, $18, $19, $20, $21)",
            ),
        };
        let mut copied = Copied {
            maps: 0,
            contributions: 0,
            versions: 0,
        };
        let result: Result<(), CommitError> = async {
            in_write_tx!(target, |tx, _lock| {
                let maps: Vec<MapCopy> = on_reader!(self, |pool| {
                    sqlx::query_as(
                        "SELECT id, name, private, created_ms, current_version FROM maps ORDER BY id",
                    )
                    .fetch_all(pool)
                    .await?
                });
                for m in &maps {
                    sqlx::query(insert_map)
                        .bind(m.id)
                        .bind(&m.name)
                        .bind(m.private)
                        .bind(m.created_ms)
                        .bind(m.current_version)
                        .execute(&mut *tx)
                        .await?;
                }
                copied.maps = maps.len();
                let mut after = 0;
                loop {
                    let page: Vec<ContributionCopy> = on_reader!(self, |pool| {
                        sqlx::query_as(
                            "SELECT id, map_id, contributor, agent, run, traveled_m, idempotency_key,
                                    request_sha256, body, received_ms, status, reason, transmitters,
                                    matched_version, transform, inliers, score, merged, added,
                                    response_status, response_body
                             FROM contributions WHERE id > $1 ORDER BY id LIMIT $2",
                        )
                        .bind(after)
                        .bind(page_rows)
                        .fetch_all(pool)
                        .await?
                    });
                    let Some(last) = page.last() else { break };
                    after = last.id;
                    for c in &page {
                        sqlx::query(insert_contribution)
                            .bind(c.id)
                            .bind(c.map_id)
                            .bind(&c.contributor)
                            .bind(&c.agent)
                            .bind(&c.run)
                            .bind(c.traveled_m)
                            .bind(&c.idempotency_key)
                            .bind(&c.request_sha256)
                            .bind(&c.body)
                            .bind(c.received_ms)
                            .bind(&c.status)
                            .bind(&c.reason)
                            .bind(c.transmitters)
                            .bind(c.matched_version)
                            .bind(&c.transform)
                            .bind(c.inliers)
                            .bind(c.score)
                            .bind(c.merged)
                            .bind(c.added)
                            .bind(c.response_status)
                            .bind(&c.response_body)
                            .execute(&mut *tx)
                            .await?;
                    }
                    copied.contributions += page.len();
                }
                let mut after = (0, 0);
                loop {
                    let page: Vec<VersionCopy> = on_reader!(self, |pool| {
                        sqlx::query_as(
                            "SELECT map_id, number, parent, kind, contribution_id, body, encoding,
                                    transmitters, created_ms
                             FROM versions WHERE map_id > $1 OR (map_id = $1 AND number > $2)
                             ORDER BY map_id, number LIMIT $3",
                        )
                        .bind(after.0)
                        .bind(after.1)
                        .bind(page_rows)
                        .fetch_all(pool)
                        .await?
                    });
                    let Some(last) = page.last() else { break };
                    after = (last.map_id, last.number);
                    for v in &page {
                        sqlx::query(
                            "INSERT INTO versions (map_id, number, parent, kind, contribution_id,
                                body, encoding, transmitters, created_ms)
                             VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9)",
                        )
                        .bind(v.map_id)
                        .bind(v.number)
                        .bind(v.parent)
                        .bind(&v.kind)
                        .bind(v.contribution_id)
                        .bind(&v.body)
                        .bind(&v.encoding)
                        .bind(v.transmitters)
                        .bind(v.created_ms)
                        .execute(&mut *tx)
                        .await?;
                    }
                    copied.versions += page.len();
                }
                if target.kind() == Kind::Postgres {
                    // the next generated ids continue after the copied ones
                    for table in [
                        "SELECT setval(pg_get_serial_sequence('maps', 'id'), (SELECT COALESCE(MAX(id), 0) + 1 FROM maps), false)",
                        "SELECT setval(pg_get_serial_sequence('contributions', 'id'), (SELECT COALESCE(MAX(id), 0) + 1 FROM contributions), false)",
                    ] {
                        sqlx::query(table).execute(&mut *tx).await?;
                    }
                }
                tx.commit().await?;
                Ok(())
            })
        }
        .await;
        result.context("writing the copy (nothing was written)")?;
        Ok(copied)
    }
}

/// The URL without its password, for error messages and logs.
pub fn redact(url: &str) -> String {
    match (url.find("://"), url.rfind('@')) {
        (Some(scheme), Some(at)) if at > scheme => {
            let userinfo = &url[scheme + 3..at];
            match userinfo.find(':') {
                Some(colon) => format!(
                    "{}{}:***{}",
                    &url[..scheme + 3],
                    &userinfo[..colon],
                    &url[at..]
                ),
                None => url.to_owned(),
            }
        }
        _ => url.to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_url_names_the_backend() {
        assert_eq!(Kind::of_url("postgres://u@h/db"), Kind::Postgres);
        assert_eq!(Kind::of_url("postgresql://h/db"), Kind::Postgres);
        assert_eq!(Kind::of_url("sqlite://echomap.db"), Kind::Sqlite);
        assert_eq!(Kind::of_url("/var/lib/echomap/echomap.db"), Kind::Sqlite);
        assert_eq!(Kind::of_url("postgres.db"), Kind::Sqlite);
        let file = |u: &str| sqlite_file(u).map(|p| p.display().to_string());
        assert_eq!(
            file("sqlite://data/echomap.db").as_deref(),
            Some("data/echomap.db")
        );
        assert_eq!(
            file("/var/lib/echomap.db").as_deref(),
            Some("/var/lib/echomap.db")
        );
        assert_eq!(file("postgres://u@h/db"), None);
    }

    #[test]
    fn a_password_never_reaches_a_message() {
        assert_eq!(
            redact("postgres://echomap:s3cret@db:5432/echomap"),
            "postgres://echomap:***@db:5432/echomap"
        );
        assert_eq!(
            redact("postgres://echomap@db/echomap"),
            "postgres://echomap@db/echomap"
        );
        assert_eq!(redact("sqlite://echomap.db"), "sqlite://echomap.db");
    }
}

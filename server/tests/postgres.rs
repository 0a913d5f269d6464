//! The scale path: two `echomap-server` processes (replicas) on one real PostgreSQL server.
//!
//! Each test starts a private PostgreSQL cluster (initdb in a temporary directory, loopback
//! only, `trust` authentication) from the server binaries on this machine (Debian's
//! `postgresql` package), so nothing outside the test is touched. Without those binaries the
//! tests fail and say so; `ECHOMAP_SKIP_POSTGRES=1` skips them on purpose, with a line on
//! stderr.

mod common;

use common::*;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// A private PostgreSQL server for one test, stopped (and its files removed) on drop.
struct Postgres {
    /// the cluster's files, removed when the test ends
    _dir: tempfile::TempDir,
    child: Child,
    port: u16,
}

/// `name` from PATH, else from the newest `/usr/lib/postgresql/<major>/bin`.
fn pg_binary(name: &str) -> Option<PathBuf> {
    let on_path = std::env::var_os("PATH")
        .into_iter()
        .flat_map(|p| std::env::split_paths(&p).collect::<Vec<_>>())
        .map(|d| d.join(name))
        .find(|p| p.is_file());
    on_path.or_else(|| {
        let mut majors: Vec<PathBuf> = std::fs::read_dir("/usr/lib/postgresql")
            .ok()?
            .filter_map(|e| e.ok().map(|e| e.path().join("bin").join(name)))
            .filter(|p| p.is_file())
            .collect();
        majors.sort();
        majors.pop()
    })
}

fn running_as_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
        .unwrap_or(false)
}

/// PostgreSQL refuses to run as root: then the cluster is owned by and run as `postgres`.
fn as_cluster_owner(program: &Path) -> Command {
    if running_as_root() {
        let mut c = Command::new("runuser");
        c.args(["-u", "postgres", "--"]).arg(program);
        c
    } else {
        Command::new(program)
    }
}

impl Postgres {
    /// `None` only when `ECHOMAP_SKIP_POSTGRES=1` is set.
    fn start() -> Option<Postgres> {
        if std::env::var("ECHOMAP_SKIP_POSTGRES").as_deref() == Ok("1") {
            eprintln!("skipped: ECHOMAP_SKIP_POSTGRES=1");
            return None;
        }
        let (Some(initdb), Some(postgres)) = (pg_binary("initdb"), pg_binary("postgres")) else {
            panic!(
                "the PostgreSQL tests need the server binaries initdb and postgres \
                 (Debian: apt-get install postgresql); ECHOMAP_SKIP_POSTGRES=1 skips them"
            );
        };
        let dir = tempfile::tempdir().unwrap();
        if running_as_root() {
            let ok = Command::new("chown")
                .args(["postgres:postgres"])
                .arg(dir.path())
                .status()
                .unwrap()
                .success();
            assert!(ok, "chown of the cluster directory to postgres");
        }
        let data = dir.path().join("data");
        let out = as_cluster_owner(&initdb)
            .arg("-D")
            .arg(&data)
            .args([
                "-U",
                "echomap",
                "--auth=trust",
                "--encoding=UTF8",
                "--locale=C",
                "--no-sync",
            ])
            .output()
            .expect("run initdb");
        assert!(
            out.status.success(),
            "initdb failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let child = as_cluster_owner(&postgres)
            .arg("-D")
            .arg(&data)
            .args(["-p", &port.to_string(), "-c", "listen_addresses=127.0.0.1"])
            .arg("-c")
            .arg(format!("unix_socket_directories={}", dir.path().display()))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start postgres");
        Some(Postgres {
            _dir: dir,
            child,
            port,
        })
    }

    fn url(&self, database: &str) -> String {
        format!("postgres://echomap@127.0.0.1:{}/{database}", self.port)
    }

    /// Waits for the server, creates `database` and returns its URL.
    async fn create_database(&self, database: &str) -> String {
        let admin = self.url("postgres");
        let mut waited = Duration::ZERO;
        let pool = loop {
            match sqlx::PgPool::connect(&admin).await {
                Ok(p) => break p,
                Err(e) if waited < Duration::from_secs(60) => {
                    let _ = e;
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    waited += Duration::from_millis(100);
                }
                Err(e) => panic!("PostgreSQL did not come up in 60 s: {e}"),
            }
        };
        sqlx::query(sqlx::AssertSqlSafe(format!("CREATE DATABASE {database}")))
            .execute(&pool)
            .await
            .unwrap();
        pool.close().await;
        self.url(database)
    }
}

impl Drop for Postgres {
    fn drop(&mut self) {
        // `immediate` shutdown: the data is thrown away with the directory. (A signal to the
        // child would reach `runuser`, not the server, when running as root.)
        if let Some(pg_ctl) = pg_binary("pg_ctl") {
            let _ = as_cluster_owner(&pg_ctl)
                .arg("-D")
                .arg(self._dir.path().join("data"))
                .args(["stop", "-m", "immediate", "-w"])
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .status();
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Sends `request`; its status and JSON body.
async fn json_of(request: reqwest::RequestBuilder) -> (reqwest::StatusCode, Value) {
    let r = request.send().await.unwrap();
    let status = r.status();
    (status, r.json().await.unwrap())
}

async fn get_json(c: &reqwest::Client, url: String) -> (reqwest::StatusCode, Value) {
    json_of(c.get(url)).await
}

/// `GET url` with the operator's token (which may read private maps).
async fn get_json_as_operator(c: &reqwest::Client, url: String) -> Value {
    json_of(c.get(url).bearer_auth(OPERATOR)).await.1
}

/// Two `echomap-server` processes (replicas) on the new database `database` of `pg`, with the
/// test tokens and `env` settings, started at once (the migrator's advisory lock serializes
/// their migrations); the database URL, the processes with their base URLs, and the directory
/// holding the token file.
async fn two_replicas(
    pg: &Postgres,
    database: &str,
    env: &[(&str, &str)],
) -> (
    String,
    [(tokio::process::Child, String); 2],
    tempfile::TempDir,
) {
    let url = pg.create_database(database).await;
    let dir = tempfile::tempdir().unwrap();
    let tokens = token_file(dir.path(), &[]);
    let (a, b) = tokio::join!(
        spawn_server_process_with(&url, &tokens, env),
        spawn_server_process_with(&url, &tokens, env)
    );
    (url, [a, b], dir)
}

/// `PUT /v1/maps/{name}` on `base` with `token`; the answer.
async fn put_map(c: &reqwest::Client, base: &str, name: &str, token: &str) -> reqwest::Response {
    c.put(format!("{base}/v1/maps/{name}"))
        .bearer_auth(token)
        .send()
        .await
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_replicas_on_one_postgres_lose_no_update() {
    let Some(pg) = Postgres::start() else { return };
    // both replicas apply the migrations at once: the migrator's advisory lock serializes them
    let (url, [(_a, a), (_b, b)], _dir) = two_replicas(&pg, "replicas", &[]).await;
    let replicas = [a.clone(), b.clone()];
    let c = client();
    assert_eq!(put_map(&c, &a, "crowd", OPERATOR).await.status(), 201);
    // the other replica sees the map at once and does not create it again
    assert_eq!(put_map(&c, &b, "crowd", OPERATOR).await.status(), 200);

    // 16 uploaders × 6 uploads, each upload to the other replica than the one before
    let truth = world(3, 25);
    let (uploaders, uploads) = (16u64, 6u64);
    let mut tasks = Vec::new();
    for u in 0..uploaders {
        let (c, truth, replicas) = (c.clone(), truth.clone(), replicas.clone());
        let token = [ALICE, BOB, OPERATOR][(u % 3) as usize];
        tasks.push(tokio::spawn(async move {
            let mut out = Vec::new();
            for k in 0..uploads {
                let body = contribution(
                    user_map(&truth, 5000 + u * 10 + k, 0.8, 0.1),
                    &format!("{u}-{k}"),
                );
                let base = &replicas[((u + k) % 2) as usize];
                let r = c
                    .post(format!("{base}/v1/maps/crowd/contributions"))
                    .bearer_auth(token)
                    .header("Idempotency-Key", format!("u{u}-k{k}"))
                    .json(&body)
                    .send()
                    .await
                    .unwrap();
                let status = r.status().as_u16();
                out.push((status, r.json::<Value>().await.unwrap()));
            }
            out
        }));
    }
    let mut accepted = Vec::new();
    let mut rejected = 0;
    for t in tasks {
        for (status, v) in t.await.unwrap() {
            match status {
                201 => accepted.push((
                    v["contribution"].as_i64().unwrap(),
                    v["version"].as_i64().unwrap(),
                )),
                422 => rejected += 1,
                other => panic!("unexpected {other}: {v}"),
            }
        }
    }
    let total = (uploaders * uploads) as usize;
    assert_eq!(accepted.len() + rejected, total);
    assert!(
        accepted.len() * 10 >= total * 9,
        "only {} of {total} accepted",
        accepted.len()
    );
    // versions 1..n without gaps, each produced by exactly one 201, parents chained
    let mut versions: Vec<i64> = accepted.iter().map(|a| a.1).collect();
    versions.sort_unstable();
    assert_eq!(versions, (1..=accepted.len() as i64).collect::<Vec<_>>());
    let db = sqlx::PgPool::connect(&url).await.unwrap();
    let provenance: Vec<(i64, i64, Option<i64>)> =
        sqlx::query_as("SELECT contribution_id, number, parent FROM versions ORDER BY number")
            .fetch_all(&db)
            .await
            .unwrap();
    let mut expected = accepted.clone();
    expected.sort_by_key(|a| a.1);
    assert_eq!(
        provenance.iter().map(|p| (p.0, p.1)).collect::<Vec<_>>(),
        expected,
        "every 201 in exactly one version's provenance"
    );
    for (_, n, parent) in &provenance {
        assert_eq!(*parent, (*n > 1).then_some(n - 1));
    }
    let stored: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM contributions")
        .fetch_one(&db)
        .await
        .unwrap();
    assert_eq!(stored as usize, total);
    // every version, read from both replicas in turn, is the merge of its parent and upload
    let chain: Vec<(i64, String, String)> = sqlx::query_as(
        "SELECT v.number, c.body, c.request_sha256 FROM versions v
         JOIN contributions c ON c.id = v.contribution_id ORDER BY v.number",
    )
    .fetch_all(&db)
    .await
    .unwrap();
    assert_versions_are_merges(&c, &[&a, &b], "crowd", &chain).await;
    // both replicas serve the head, whichever committed it
    let n = accepted.len() as i64;
    for base in [&a, &b] {
        let (status, cur) = get_json(&c, format!("{base}/v1/maps/crowd")).await;
        assert_eq!(status, 200);
        assert_eq!(
            (cur["version"].as_i64(), cur["contributions"].as_i64()),
            (Some(n), Some(n))
        );
    }

    // the same upload and key sent to A, then to B: one contribution, the same bytes back
    let body = contribution(user_map(&truth, 9001, 0.8, 0.1), "again");
    let mut answers = Vec::new();
    for base in [&a, &b] {
        let r = c
            .post(format!("{base}/v1/maps/crowd/contributions"))
            .bearer_auth(ALICE)
            .header("Idempotency-Key", "same-key-both-replicas")
            .json(&body)
            .send()
            .await
            .unwrap();
        answers.push((r.status(), r.bytes().await.unwrap()));
    }
    assert_eq!(answers[0], answers[1]);
    assert_eq!(answers[0].0, 201, "{:?}", answers[0].1);
    let copies: i64 = sqlx::query_scalar(
        "SELECT COUNT(*) FROM contributions WHERE idempotency_key = 'same-key-both-replicas'",
    )
    .fetch_one(&db)
    .await
    .unwrap();
    assert_eq!(copies, 1);

    // A caches the head; B rolls a contribution back; A must serve B's new version at once
    let (_, head) = get_json(&c, format!("{a}/v1/maps/crowd")).await;
    let head = head["version"].as_i64().unwrap();
    assert_eq!(head, n + 1);
    let victim = accepted[0].0;
    let r = c
        .delete(format!("{b}/v1/maps/crowd/contributions/{victim}"))
        .bearer_auth(OPERATOR)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let rolled: Value = r.json().await.unwrap();
    assert_eq!(rolled["version"].as_i64(), Some(head + 1));
    let (_, cur) = get_json(&c, format!("{a}/v1/maps/crowd")).await;
    assert_eq!(
        cur["version"].as_i64(),
        Some(head + 1),
        "replica A serves a stale version"
    );
    assert_eq!(cur["contributions"].as_i64(), Some(n));
    let (_, via_b) = get_json(&c, format!("{b}/v1/maps/crowd")).await;
    assert_eq!(cur, via_b);
    // and a second rollback of the same contribution, now through A, is refused
    let r = c
        .delete(format!("{a}/v1/maps/crowd/contributions/{victim}"))
        .bearer_auth(OPERATOR)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 409);
    db.close().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn readiness_and_settings_on_postgres() {
    let Some(pg) = Postgres::start() else { return };
    let url = pg.create_database("ready").await;
    let storage = echomap_server::storage::Storage::open(&url, 2)
        .await
        .unwrap();
    assert_eq!(storage.kind(), echomap_server::storage::Kind::Postgres);
    assert!(storage.ready().await.unwrap(), "every migration applied");
    // SQLite's PRAGMAs do not exist here: a clear error, not made-up values
    let e = storage.pragmas().await.unwrap_err().to_string();
    assert!(e.contains("PostgreSQL"), "{e}");
    // opening again (a restart, or a second replica) applies nothing twice
    let again = echomap_server::storage::Storage::open(&url, 2)
        .await
        .unwrap();
    let applied: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM _sqlx_migrations")
        .fetch_one(&sqlx::PgPool::connect(&url).await.unwrap())
        .await
        .unwrap();
    assert_eq!(
        applied as usize,
        echomap_server::storage::PG_MIGRATOR.migrations.len()
    );
    let (created, fresh) = again.create_map("hall", true).await.unwrap();
    assert!(fresh && created.private && created.current_version == 0);
    let (seen, fresh) = storage.create_map("hall", false).await.unwrap();
    assert!(!fresh && seen.private && seen.id == created.id);
    again.close().await;
    storage.close().await;
}

#[tokio::test]
async fn an_unreachable_postgres_is_a_clear_error_without_the_password() {
    // a port nothing listens on: bound, then released
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let url = format!("postgres://echomap:hunter2@127.0.0.1:{port}/echomap");
    let e = echomap_server::storage::Storage::open_with(&url, 1, Duration::from_secs(2))
        .await
        .unwrap_err();
    let msg = format!("{e:#}");
    assert!(
        msg.contains("cannot connect to postgres://echomap:***@127.0.0.1"),
        "{msg}"
    );
    assert!(!msg.contains("hunter2"), "{msg}");
}

/// The read and write paths a client uses, on PostgreSQL (one in-process server): rejected
/// uploads stored with their reason and the map unchanged, listing and paging, ETag and 304,
/// private maps, past versions, and a rollback that equals merging the others afresh.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_api_on_postgres() {
    let Some(pg) = Postgres::start() else { return };
    let url = pg.create_database("api").await;
    let s = TestServer::start_with(|cfg| cfg.database_url = url.clone()).await;
    assert_eq!(
        s.state.storage.kind(),
        echomap_server::storage::Kind::Postgres
    );
    let c = client();
    let bodies = seeded_map(&c, &s, "r1").await;
    let r = c.get(s.url("/v1/maps/r1")).send().await.unwrap();
    let etag = r.headers()["etag"].to_str().unwrap().to_owned();
    assert_eq!(etag, "\"3\"");
    let before: Value = r.json().await.unwrap();
    let r = c
        .get(s.url("/v1/maps/r1"))
        .header("If-None-Match", &etag)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 304);
    // an unrelated map is rejected, stored with its reason, and changes nothing
    let poison = contribution(user_map(&world(901, 25), 901, 0.9, 0.1), "poison");
    let r = post_contribution(&c, &s, "r1", BOB, "poison", &poison).await;
    assert_eq!(r.status(), 422);
    let p: Value = r.json().await.unwrap();
    assert!(common::is_refusal(&p), "{p}");
    let (_, after) = get_json(&c, s.url("/v1/maps/r1")).await;
    assert_eq!(after, before);
    // keyset paging over the four contributions, two per page
    let (_, page1) = get_json(&c, s.url("/v1/maps/r1/contributions?limit=2")).await;
    let next = page1["next"].as_i64().expect("a second page");
    let (_, page2) = get_json(
        &c,
        s.url(&format!("/v1/maps/r1/contributions?after={next}&limit=2")),
    )
    .await;
    let rows: Vec<&Value> = page1["contributions"]
        .as_array()
        .unwrap()
        .iter()
        .chain(page2["contributions"].as_array().unwrap())
        .collect();
    let statuses: Vec<&str> = rows.iter().map(|x| x["status"].as_str().unwrap()).collect();
    assert_eq!(statuses, ["accepted", "accepted", "accepted", "rejected"]);
    let versions: Vec<Option<i64>> = rows.iter().map(|x| x["version"].as_i64()).collect();
    assert_eq!(versions, [Some(1), Some(2), Some(3), None]);
    assert_eq!(rows[3]["contributor"], "bob");
    // roll back the second: the new version equals merging the first and third afresh
    let second = rows[1]["id"].as_i64().unwrap();
    let r = c
        .delete(s.url(&format!("/v1/maps/r1/contributions/{second}")))
        .bearer_auth(ALICE)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let fresh = TestServer::start().await;
    create_map(&c, &fresh, "r1").await;
    for (k, b) in [&bodies[0], &bodies[2]].into_iter().enumerate() {
        let r = post_contribution(&c, &fresh, "r1", ALICE, &format!("k{k}"), b).await;
        assert_eq!(r.status(), 201);
    }
    let (_, rolled) = get_json(&c, s.url("/v1/maps/r1")).await;
    let (_, afresh) = get_json(&c, fresh.url("/v1/maps/r1")).await;
    assert_eq!(
        (rolled["version"].as_i64(), rolled["contributions"].as_i64()),
        (Some(4), Some(2))
    );
    assert_eq!(rolled["transmitters"], afresh["transmitters"]);
    // history is kept
    let (status, v2) = get_json(&c, s.url("/v1/maps/r1/versions/2")).await;
    assert_eq!((status.as_u16(), v2["version"].as_i64()), (200, Some(2)));
    // a private map: 401 without a token, listed only with one
    let r = c
        .put(s.url("/v1/maps/secret"))
        .bearer_auth(ALICE)
        .json(&serde_json::json!({"private": true}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let r = c.get(s.url("/v1/maps/secret")).send().await.unwrap();
    assert_eq!(r.status(), 401);
    let names = |v: &Value| -> Vec<String> {
        v["maps"]
            .as_array()
            .unwrap()
            .iter()
            .map(|m| m["name"].as_str().unwrap().to_owned())
            .collect()
    };
    let (_, public) = get_json(&c, s.url("/v1/maps")).await;
    assert_eq!(names(&public), ["r1"]);
    let all = get_json_as_operator(&c, s.url("/v1/maps")).await;
    assert_eq!(names(&all), ["r1", "secret"]);
    fresh.stop().await;
    s.stop().await;
}

/// Runs `echomap-server --database-url SOURCE copy-to TARGET --page-rows 5` (pages of 5 rows,
/// so the copy spans several pages and the versions' pages cross from one map to the next);
/// returns success and stdout+stderr.
fn copy_to(source: &str, target: &str) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_echomap-server"))
        .args([
            "--database-url",
            source,
            "copy-to",
            target,
            "--page-rows",
            "5",
        ])
        .env("RUST_LOG", "warn")
        .output()
        .expect("run echomap-server copy-to");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

/// Everything a client can read of the maps `names`, as served by `s`.
async fn everything(c: &reqwest::Client, s: &TestServer, names: &[&str]) -> Vec<Value> {
    let get = |path: String| get_json_as_operator(c, s.url(&path));
    let mut out = vec![get("/v1/maps".into()).await];
    for name in names {
        let cur = get(format!("/v1/maps/{name}")).await;
        for n in 1..=cur["version"].as_i64().unwrap() {
            out.push(get(format!("/v1/maps/{name}/versions/{n}")).await);
        }
        out.push(cur);
        out.push(get(format!("/v1/maps/{name}/contributions?limit=1000")).await);
    }
    out
}

/// When one machine is no longer enough: a SQLite database with history (accepted, rejected
/// and rolled-back contributions, delta-encoded versions, a private map) moves to PostgreSQL
/// with `copy-to`, and a server on the copy answers exactly as before — stored responses
/// replayed byte for byte — and goes on from the copied ids; and back to SQLite.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sqlite_database_moves_to_postgres_and_back() {
    let Some(pg) = Postgres::start() else { return };
    let target = pg.create_database("moved").await;
    let c = client();
    let old = TestServer::start().await;
    let bodies = seeded_map(&c, &old, "r1").await;
    let poison = contribution(user_map(&world(901, 25), 901, 0.9, 0.1), "poison");
    let r = post_contribution(&c, &old, "r1", BOB, "poison", &poison).await;
    assert_eq!(r.status(), 422);
    let (_, page) = get_json(&c, old.url("/v1/maps/r1/contributions")).await;
    let second = page["contributions"][1]["id"].as_i64().unwrap();
    let r = c
        .delete(old.url(&format!("/v1/maps/r1/contributions/{second}")))
        .bearer_auth(ALICE)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let r = c
        .put(old.url("/v1/maps/secret"))
        .bearer_auth(ALICE)
        .json(&serde_json::json!({"private": true}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    // 8 uploads queue behind the held merge lock and are committed in group commits, which
    // store all versions but their last as deltas
    let truth = world(2, 20);
    let secret = old.state.map_ref("secret").await.unwrap().id;
    let lock = old.state.map_lock(secret);
    let held = lock.lock().await;
    let mut tasks = Vec::new();
    for k in 0..8u64 {
        let (c, url) = (c.clone(), old.url("/v1/maps/secret/contributions"));
        let b = contribution(user_map(&truth, 40 + k, 0.85, 0.1), &format!("s{k}"));
        tasks.push(tokio::spawn(async move {
            let r = c
                .post(url)
                .bearer_auth(ALICE)
                .header("Idempotency-Key", format!("s{k}"))
                .json(&b)
                .send()
                .await
                .unwrap();
            r.status().as_u16()
        }));
    }
    tokio::time::sleep(Duration::from_secs(1)).await;
    drop(held);
    for t in tasks {
        assert_eq!(t.await.unwrap(), 201);
    }
    let source = sqlx::SqlitePool::connect_with(
        sqlx::sqlite::SqliteConnectOptions::new()
            .filename(&old.db)
            .read_only(true),
    )
    .await
    .unwrap();
    let deltas: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM versions WHERE encoding = 'delta'")
        .fetch_one(&source)
        .await
        .unwrap();
    source.close().await;
    assert!(deltas >= 1, "no delta-encoded version to copy");
    let before = everything(&c, &old, &["r1", "secret"]).await;
    let first_reply = post_contribution(&c, &old, "r1", ALICE, "r1-0", &bodies[0]).await;
    assert_eq!(first_reply.status(), 201);
    let first_reply = first_reply.bytes().await.unwrap();

    // a missing source is refused and creates nothing
    let missing = old.dir.path().join("missing.db").display().to_string();
    let (ok, text) = copy_to(&missing, &target);
    assert!(!ok && text.contains("does not exist"), "{text}");
    assert!(!std::path::Path::new(&missing).exists());
    let (ok, text) = copy_to(&old.db.display().to_string(), &target);
    assert!(ok, "{text}");
    assert!(
        text.contains("copied 2 maps, 12 contributions and 12 versions"),
        "{text}"
    );
    // into a database that already holds maps: refused, nothing written
    let (ok, text) = copy_to(&old.db.display().to_string(), &target);
    assert!(!ok && text.contains("already holds maps"), "{text}");

    let moved = TestServer::start_with(|cfg| cfg.database_url = target.clone()).await;
    assert_eq!(everything(&c, &moved, &["r1", "secret"]).await, before);
    // a retry reaching the new server gets the stored response byte for byte
    let replay = post_contribution(&c, &moved, "r1", ALICE, "r1-0", &bodies[0]).await;
    assert_eq!(replay.headers()["idempotent-replayed"], "true");
    assert_eq!(replay.bytes().await.unwrap(), first_reply);
    // new writes continue after the copied ids
    let b = contribution(user_map(&world(1, 25), 77, 0.85, 0.1), "after");
    let r = post_contribution(&c, &moved, "r1", ALICE, "after-move", &b).await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(
        (v["contribution"].as_i64(), v["version"].as_i64()),
        (Some(13), Some(5))
    );

    // and back: PostgreSQL → a new SQLite file
    let back = tempfile::tempdir().unwrap();
    let back_db = back.path().join("back.db").display().to_string();
    let after = everything(&c, &moved, &["r1", "secret"]).await;
    let (ok, text) = copy_to(&target, &back_db);
    assert!(ok, "{text}");
    let returned = TestServer::start_with(|cfg| cfg.database_url = back_db.clone()).await;
    assert_eq!(everything(&c, &returned, &["r1", "secret"]).await, after);
    returned.stop().await;
    moved.stop().await;
    old.stop().await;
}

/// The value of the unlabelled metric `name` on `base`'s `/metrics` (0 while it was never set).
async fn metric(c: &reqwest::Client, base: &str, name: &str) -> f64 {
    let text = c
        .get(format!("{base}/metrics"))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.trim().parse().ok())
        .unwrap_or(0.0)
}

/// Polls `base`'s map `name` until it serves `version` (at most 10 s); how long that took.
async fn await_version(c: &reqwest::Client, base: &str, name: &str, version: i64) -> Duration {
    let start = std::time::Instant::now();
    loop {
        let (status, cur) = get_json(c, format!("{base}/v1/maps/{name}")).await;
        assert_eq!(status, 200);
        if cur["version"].as_i64() == Some(version) {
            return start.elapsed();
        }
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "{base} still serves version {} of {name}, not {version}",
            cur["version"]
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// Polls `base` until it has opened `sessions` listening sessions (at most 10 s).
async fn await_listening(c: &reqwest::Client, base: &str, sessions: f64) {
    let start = std::time::Instant::now();
    while metric(c, base, "echomap_head_listen_sessions_total").await < sessions {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "{base} opened fewer than {sessions} listening sessions in 10 s"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn listening_replicas_serve_each_others_commits_without_reading_the_head() {
    let Some(pg) = Postgres::start() else { return };
    let listen = [("ECHOMAP_REPLICA_CACHE", "listen")];
    let (url, [(_a, a), (_b, b)], _dir) = two_replicas(&pg, "listening", &listen).await;
    let c = client();
    assert_eq!(put_map(&c, &a, "hall", OPERATOR).await.status(), 201);
    let truth = world(3, 25);
    let mut k = 0u64;
    let mut upload = |base: String| {
        k += 1;
        let body = contribution(user_map(&truth, 7000 + k, 0.8, 0.1), &format!("l{k}"));
        let c = c.clone();
        async move {
            let r = c
                .post(format!("{base}/v1/maps/hall/contributions"))
                .bearer_auth(ALICE)
                .header("Idempotency-Key", format!("listen-{k}"))
                .json(&body)
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 201);
            r.json::<Value>().await.unwrap()["version"]
                .as_i64()
                .unwrap()
        }
    };
    // both replicas listen (the task starts beside the server)
    for base in [&a, &b] {
        await_listening(&c, base, 1.0).await;
    }
    assert_eq!(upload(a.clone()).await, 1);
    await_version(&c, &b, "hall", 1).await;
    // B serves its cached version 1 on and on without reading the head once it has been
    // found current (in `check` mode every one of these GETs reads it)
    let reads = metric(&c, &b, "echomap_head_reads_total").await;
    for _ in 0..20 {
        let (_, cur) = get_json(&c, format!("{b}/v1/maps/hall")).await;
        assert_eq!(cur["version"].as_i64(), Some(1));
    }
    let more = metric(&c, &b, "echomap_head_reads_total").await - reads;
    assert!(
        more <= 1.0,
        "{more} head reads for 20 GETs of a vouched version"
    );
    // A commits version 2: the notification reaches B, which then serves it
    assert_eq!(upload(a.clone()).await, 2);
    let late = await_version(&c, &b, "hall", 2).await;
    eprintln!("B served A's version 2 after {late:?}");
    // and the other way round
    let (_, cur) = get_json(&c, format!("{a}/v1/maps/hall")).await;
    assert_eq!(cur["version"].as_i64(), Some(2));
    assert_eq!(upload(b.clone()).await, 3);
    await_version(&c, &a, "hall", 3).await;

    // the database ends both listening sessions: the replicas read the head again until they
    // listen anew, and a commit made meanwhile is not lost on the other replica
    let db = sqlx::PgPool::connect(&url).await.unwrap();
    let ended: Vec<bool> = sqlx::query_scalar(
        "SELECT pg_terminate_backend(pid) FROM pg_stat_activity
         WHERE datname = 'listening' AND query LIKE 'LISTEN%'",
    )
    .fetch_all(&db)
    .await
    .unwrap();
    assert_eq!(ended, [true, true], "one listening session per replica");
    assert_eq!(upload(a.clone()).await, 4);
    await_version(&c, &b, "hall", 4).await;
    for base in [&a, &b] {
        await_listening(&c, base, 2.0).await;
    }
    assert_eq!(upload(b.clone()).await, 5);
    await_version(&c, &a, "hall", 5).await;
    db.close().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_write_rate_limit_is_shared_by_the_replicas() {
    let Some(pg) = Postgres::start() else { return };
    // 1 write per second, bursts of 3: per contributor, whichever replica takes the write
    let limit = [("ECHOMAP_RATE_LIMIT", "1"), ("ECHOMAP_RATE_BURST", "3")];
    let (_url, [(_a, a), (_b, b)], _dir) = two_replicas(&pg, "limits", &limit).await;
    let c = client();
    let start = std::time::Instant::now();
    let mut answers = Vec::new();
    for k in 0..8 {
        let r = put_map(&c, [&a, &b][k % 2], "limited", ALICE).await;
        answers.push((r.status().as_u16(), r.headers().get("retry-after").cloned()));
    }
    let elapsed = start.elapsed().as_secs_f64();
    let allowed = answers.iter().filter(|(s, _)| *s != 429).count();
    // a limiter per replica would allow 3 on each, 6 in all
    assert!(
        allowed >= 3 && allowed as f64 <= 3.0 + elapsed.floor(),
        "{allowed} of 8 writes allowed in {elapsed:.2} s: {answers:?}"
    );
    assert!(answers[..3].iter().all(|(s, _)| *s == 201 || *s == 200));
    for (status, retry) in &answers {
        if *status == 429 {
            let secs: u64 = retry.as_ref().unwrap().to_str().unwrap().parse().unwrap();
            assert_eq!(
                secs, 1,
                "one write per second: the next one within a second"
            );
        }
    }
    // another contributor has its own allowance
    assert_eq!(put_map(&c, &b, "limited", BOB).await.status(), 200);
    // and the allowance comes back at the sustained rate
    tokio::time::sleep(Duration::from_millis(1100)).await;
    assert_eq!(put_map(&c, &a, "limited", ALICE).await.status(), 200);
}

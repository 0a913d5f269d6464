//! Test support: a real server on 127.0.0.1:0 with a fresh SQLite file, synthetic maps with a
//! known truth, and a database dump to prove that rejected requests change nothing.
#![allow(dead_code)]

use echomap_server::{Application, Config};
use serde_json::Value;
use sqlx::Row;
use sqlx::sqlite::SqliteConnectOptions;
use std::path::{Path, PathBuf};
use tokio::sync::oneshot;

pub const OPERATOR: &str = "operator-token-0123456789";
pub const ALICE: &str = "alice-token-0123456789ab";
pub const BOB: &str = "bob-token-0123456789abcd";
/// may only write the map "other"
pub const CAROL: &str = "carol-token-0123456789ab";
/// may write the map "hall" only (not an operator)
pub const DAVE: &str = "dave-token-0123456789abcd";

pub fn token_file(dir: &Path, extra: &[(String, String)]) -> PathBuf {
    let mut text = format!(
        "# test tokens\n{OPERATOR} operator *\n{ALICE} alice *\n{BOB} bob *\n{CAROL} carol other\n{DAVE} dave hall\n"
    );
    for (token, who) in extra {
        text.push_str(&format!("{token} {who} *\n"));
    }
    let path = dir.join("tokens.txt");
    std::fs::write(&path, text).unwrap();
    path
}

#[derive(Debug)]
pub struct TestServer {
    pub base: String,
    pub db: PathBuf,
    pub dir: tempfile::TempDir,
    pub state: echomap_server::state::SharedState,
    stop: Option<oneshot::Sender<()>>,
    task: Option<tokio::task::JoinHandle<anyhow::Result<()>>>,
}

impl TestServer {
    pub async fn start() -> Self {
        Self::start_with(|_| {}).await
    }

    pub async fn start_with(tweak: impl FnOnce(&mut Config)) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join("echomap.db");
        let mut cfg = Config::for_database(db.display().to_string());
        cfg.token_file = Some(token_file(dir.path(), &[]));
        cfg.rate_limit_per_s = 10_000;
        cfg.rate_limit_burst = 10_000;
        tweak(&mut cfg);
        let app = Application::build(cfg).await.unwrap();
        let base = format!("http://{}", app.local_addr());
        let state = app.state();
        let (stop, rx) = oneshot::channel::<()>();
        let task = tokio::spawn(app.run_until(async move {
            let _ = rx.await;
        }));
        TestServer {
            base,
            db,
            dir,
            state,
            stop: Some(stop),
            task: Some(task),
        }
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    pub async fn stop(mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.task.take() {
            t.await.unwrap().unwrap();
        }
    }
}

pub fn client() -> reqwest::Client {
    echomap_server::http::client_builder()
        .pool_max_idle_per_host(64)
        .build()
        .unwrap()
}

pub async fn create_map(c: &reqwest::Client, s: &TestServer, name: &str) {
    let r = c
        .put(s.url(&format!("/v1/maps/{name}")))
        .bearer_auth(OPERATOR)
        .send()
        .await
        .unwrap();
    assert!(r.status() == 201 || r.status() == 200, "{}", r.status());
}

#[allow(unused_imports)]
pub use echomap_server::synth::{contribution, world};

/// A user map of `world` (one component per transmitter); see [`echomap_server::synth`].
pub fn user_map(world: &[[f64; 3]], seed: u64, keep: f64, noise_m: f64) -> Value {
    echomap_server::synth::user_map(world, seed, keep, noise_m, 1)
}

pub async fn post_contribution(
    c: &reqwest::Client,
    s: &TestServer,
    map: &str,
    token: &str,
    key: &str,
    body: &Value,
) -> reqwest::Response {
    c.post(s.url(&format!("/v1/maps/{map}/contributions")))
        .bearer_auth(token)
        .header("Idempotency-Key", key)
        .json(body)
        .send()
        .await
        .unwrap()
}

/// Every row of every table, as text (a `.dump` without the sqlite3 tool).
pub async fn dump(db: &Path) -> String {
    let opts = SqliteConnectOptions::new().filename(db).read_only(true);
    let pool = sqlx::SqlitePool::connect_with(opts).await.unwrap();
    let tables: Vec<String> = sqlx::query_scalar(
        "SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%' ORDER BY name",
    )
    .fetch_all(&pool)
    .await
    .unwrap();
    let mut out = String::new();
    for t in tables {
        let cols: Vec<String> =
            sqlx::query(sqlx::AssertSqlSafe(format!("PRAGMA table_info(\"{t}\")")))
                .fetch_all(&pool)
                .await
                .unwrap()
                .iter()
                .map(|r| r.get::<String, _>(1))
                .collect();
        let expr = cols
            .iter()
            .map(|c| format!("quote(\"{c}\")"))
            .collect::<Vec<_>>()
            .join(" || ',' || ");
        let rows: Vec<String> = sqlx::query_scalar(sqlx::AssertSqlSafe(format!(
            "SELECT {expr} FROM \"{t}\" ORDER BY rowid"
        )))
        .fetch_all(&pool)
        .await
        .unwrap();
        out.push_str(&format!("-- {t}\n"));
        for r in rows {
            out.push_str(&r);
            out.push('\n');
        }
    }
    pool.close().await;
    out
}

/// Starts a real `echomap-server` process on 127.0.0.1:0 with `database` (a SQLite path or a
/// `postgres://` URL); returns it with its base URL, read from its first stdout line.
pub async fn spawn_server_process(
    database: impl AsRef<std::ffi::OsStr>,
    tokens: &Path,
) -> (tokio::process::Child, String) {
    spawn_server_process_with(database, tokens, &[]).await
}

/// [`spawn_server_process`] with more settings as `ECHOMAP_*` environment variables.
pub async fn spawn_server_process_with(
    database: impl AsRef<std::ffi::OsStr>,
    tokens: &Path,
    env: &[(&str, &str)],
) -> (tokio::process::Child, String) {
    use tokio::io::AsyncBufReadExt;
    let mut child = tokio::process::Command::new(env!("CARGO_BIN_EXE_echomap-server"))
        .args(["--listen", "127.0.0.1:0", "--database-url"])
        .arg(database)
        .arg("--token-file")
        .arg(tokens)
        .env("RUST_LOG", "warn")
        .env("ECHOMAP_RATE_LIMIT", "100000")
        .env("ECHOMAP_RATE_BURST", "100000")
        .envs(env.iter().copied())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .kill_on_drop(true)
        .spawn()
        .expect("start echomap-server");
    let stdout = child.stdout.take().unwrap();
    let mut line = String::new();
    tokio::io::BufReader::new(stdout)
        .read_line(&mut line)
        .await
        .unwrap();
    let base = line
        .trim()
        .strip_prefix("echomap-server listening on ")
        .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
        .to_owned();
    (child, base)
}

/// Checks that every stored version `(number, upload body, request SHA-256)`, oldest first,
/// is served by each of `bases` (in turn) as exactly the merge of its parent and its upload —
/// whether its body is stored whole or as a delta.
pub async fn assert_versions_are_merges(
    c: &reqwest::Client,
    bases: &[&str],
    map: &str,
    versions: &[(i64, String, String)],
) {
    use echomap_shared::map::TransmitterMap;
    use std::sync::Arc;
    let mut parent: Option<Arc<TransmitterMap>> = None;
    for (i, (n, body, sha)) in versions.iter().enumerate() {
        let upload: Value = serde_json::from_str(body).unwrap();
        let user = Arc::new(TransmitterMap::from_json(&upload["map"].to_string()).unwrap());
        let expected = match echomap_server::merge::integrate(
            parent.as_deref(),
            &user,
            echomap_server::merge::seed_of(sha),
            &Default::default(),
            &Default::default(),
        )
        .unwrap()
        {
            echomap_server::merge::Outcome::Initialized { map }
            | echomap_server::merge::Outcome::Merged { map, .. } => map,
            other => panic!("version {n} from a rejected upload: {other:?}"),
        };
        let base = bases[i % bases.len()];
        let served: Value = c
            .get(format!("{base}/v1/maps/{map}/versions/{n}"))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        assert_eq!(
            served["transmitters"],
            serde_json::to_value(expected.as_ref()).unwrap()["transmitters"],
            "version {n} from {base}"
        );
        parent = Some(expected);
    }
}

/// A map with three accepted contributions of world 1.
pub async fn seeded_map(c: &reqwest::Client, s: &TestServer, name: &str) -> Vec<Value> {
    create_map(c, s, name).await;
    let truth = world(1, 25);
    let mut bodies = Vec::new();
    for (k, seed) in [11u64, 12, 13].into_iter().enumerate() {
        let b = contribution(user_map(&truth, seed, 0.85, 0.1), &format!("run-{k}"));
        let r = post_contribution(c, s, name, ALICE, &format!("{name}-{k}"), &b).await;
        assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
        bodies.push(b);
    }
    bodies
}

/// Whether a problem document refuses a contribution for what it contains: it matched no part
/// of the map (`unmatched`) or shares too little with it to decide (`undecided`).
pub fn is_refusal(p: &Value) -> bool {
    p["type"]
        .as_str()
        .is_some_and(|t| t.ends_with("/unmatched") || t.ends_with("/undecided"))
}

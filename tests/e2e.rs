//! End to end, as a user runs it: a real `echomap-server` process on loopback and triples of
//! `echomap-agent run --server … --map …` processes, one after another, on the indoor scenario.
//! Each agent fetches the prior map, runs Channel-SLAM and uploads its map.
//!
//! Built as a test of the server package (`server/Cargo.toml`, `[[test]] e2e`); the agent
//! binary is taken from the same target directory, which `cargo test --workspace` fills.

#[path = "../server/tests/common/mod.rs"]
mod common;

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use tokio::process::Command;

fn agent_binary() -> PathBuf {
    let server = PathBuf::from(env!("CARGO_BIN_EXE_echomap-server"));
    let agent = server.with_file_name(format!("echomap-agent{}", std::env::consts::EXE_SUFFIX));
    assert!(
        agent.exists(),
        "{} is missing: run `cargo test --workspace` (it builds both binaries)",
        agent.display()
    );
    agent
}

/// One agent process: `run --scenario indoor --track user01 --seed SEED --server … --map MAP`.
async fn run_agent(base: &str, map: &str, seed: u64, token: &Path, out: &Path) -> Agent {
    let status = Command::new(agent_binary())
        .args([
            "run",
            "--scenario",
            "indoor",
            "--track",
            "user01",
            "--particles",
            "200",
            "--quiet",
        ])
        .args(["--seed", &seed.to_string(), "--server", base, "--map", map])
        .arg("--token-file")
        .arg(token)
        .arg("--out")
        .arg(out)
        .stdout(Stdio::null())
        .status()
        .await
        .unwrap();
    assert!(
        status.success(),
        "agent (seed {seed}, map {map}) failed: {status:?}"
    );
    let read = |f: &str| -> Value {
        serde_json::from_str(&std::fs::read_to_string(out.join(f)).unwrap()).unwrap()
    };
    assert!(out.join("map.json").exists());
    Agent {
        prior: read("prior.json"),
        upload: read("upload.json"),
        summary: read("summary.json"),
    }
}

async fn get_json(c: &reqwest::Client, url: String) -> Value {
    c.get(url).send().await.unwrap().json().await.unwrap()
}

#[derive(Debug)]
struct Agent {
    prior: Value,
    upload: Value,
    summary: Value,
}

impl Agent {
    fn metric(&self, key: &str) -> f64 {
        self.summary[key].as_f64().unwrap()
    }
}

/// Triples of agents on the same track `user01`, each triple on a map of its own: agent 1
/// (seed K) starts from an empty map, agent 2 (seed 100 + K: other measurements of the same
/// walk) from agent 1's map, agent 3 walks agent 1's measurements again (seed K) with the map
/// the two left. Every triple must reach map version 3 with agents 2 and 3 matching the prior
/// while they run; over the triples, agent 3's error must be lower than agent 1's — the same
/// measurements, once alone and once with the crowd's map.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_agents_share_a_map_through_a_real_server() {
    let dir = tempfile::tempdir().unwrap();
    let tokens = common::token_file(dir.path(), &[]);
    let agent_token = dir.path().join("agent-token");
    std::fs::write(&agent_token, format!("# agent token\n{}\n", common::ALICE)).unwrap();
    let (mut server, base) = common::spawn_server_process(dir.path().join("e2e.db"), &tokens).await;
    let c = common::client();

    let mut firsts = Vec::new();
    let mut lasts = Vec::new();
    for k in 1..=TRIPLES {
        let map = format!("indoor-k{k}");
        let r = c
            .put(format!("{base}/v1/maps/{map}"))
            .bearer_auth(common::OPERATOR)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 201);
        let mut agents = Vec::new();
        for (n, seed) in [(1, k), (2, 100 + k), (3, k)] {
            let out = dir.path().join(format!("k{k}-agent{n}"));
            agents.push(run_agent(&base, &map, seed, &agent_token, &out).await);
        }
        for (n, a) in agents.iter().enumerate() {
            let status = a.upload["status"].as_str().unwrap();
            assert_eq!(
                status,
                "accepted",
                "triple {k}, agent {}: {}",
                n + 1,
                a.upload
            );
        }
        assert_eq!(
            agents[0].upload["response"]["initialized"], true,
            "the first upload initializes the map"
        );
        // the first agent saw an empty map, the later ones the map the earlier ones left
        let versions: Vec<i64> = agents
            .iter()
            .map(|a| a.prior["version"].as_i64().unwrap())
            .collect();
        assert_eq!(versions, [0, 1, 2], "triple {k}");
        // the later agents matched the prior map while running and took transmitters over
        for (n, a) in agents.iter().enumerate().skip(1) {
            assert!(
                a.summary["prior_matched_at_s"].as_f64().is_some(),
                "triple {k}: agent {} never matched the prior: {}",
                n + 1,
                a.summary
            );
            assert!(
                a.metric("prior_transmitters_used") >= 3.0,
                "triple {k}: agent {}: {}",
                n + 1,
                a.summary
            );
        }
        let page = get_json(&c, format!("{base}/v1/maps/{map}/contributions")).await;
        let rows = page["contributions"].as_array().unwrap();
        assert_eq!(rows.len(), 3, "every agent's upload is recorded");
        assert!(
            rows.iter()
                .all(|r| r["contributor"] == "alice" && r["agent"] == "echomap-agent")
        );
        // the same track walked again: the later maps match the first one's and merge
        assert!(
            rows[1..]
                .iter()
                .all(|r| r["status"] == "accepted" && r["merged"].as_i64().unwrap_or(0) >= 5),
            "a later upload did not match the first map: {rows:?}"
        );
        let head = get_json(&c, format!("{base}/v1/maps/{map}")).await;
        assert_eq!(head["version"], 3, "every upload merged: {rows:?}");
        eprintln!(
            "triple {k}: mean MAE {:.2} / {:.2} / {:.2} m, final MAE {:.2} / {:.2} / {:.2} m, ATE {:.2} / {:.2} / {:.2} m",
            agents[0].metric("mae_mean_m"),
            agents[1].metric("mae_mean_m"),
            agents[2].metric("mae_mean_m"),
            agents[0].metric("mae_final_m"),
            agents[1].metric("mae_final_m"),
            agents[2].metric("mae_final_m"),
            agents[0].metric("ate_m"),
            agents[1].metric("ate_m"),
            agents[2].metric("ate_m"),
        );
        lasts.push(agents.pop().unwrap());
        firsts.push(agents.swap_remove(0));
    }
    // Over the triples (a single pair can go either way: a map built from two walks of the
    // same track carries their correlated errors, docs/results/current.md, "Three agents on one track"): the
    // final error of the walk and the error of its shape (ATE, after rigid alignment).
    for key in ["mae_final_m", "ate_m"] {
        let mean = |v: &[Agent]| v.iter().map(|a| a.metric(key)).sum::<f64>() / v.len() as f64;
        let (first, last) = (mean(&firsts), mean(&lasts));
        eprintln!("{key}: agent 1 {first:.3} m, agent 3 {last:.3} m (mean of {TRIPLES} triples)");
        assert!(
            last < first,
            "{key}: the agent with the crowd's map ({last:.3} m) is not better than the same walk alone ({first:.3} m)"
        );
    }
    server.start_kill().unwrap();
    server.wait().await.unwrap();
}

/// Triples of agents the end-to-end test runs (seeds K = 1…TRIPLES).
const TRIPLES: u64 = 4;

/// `echomap-agent upload DIR` with the server's answer: its console output and `upload.json`.
async fn upload_again(base: &str, map: &str, token: &Path, dir: &Path) -> (bool, String, Value) {
    let out = Command::new(agent_binary())
        .arg("upload")
        .arg(dir)
        .args(["--server", base, "--map", map])
        .arg("--token-file")
        .arg(token)
        .output()
        .await
        .unwrap();
    let text =
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    let saved = std::fs::read_to_string(dir.join("upload.json"))
        .map(|t| serde_json::from_str(&t).unwrap())
        .unwrap_or(Value::Null);
    (out.status.success(), text, saved)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_upload_that_overlaps_too_little_is_kept_and_merges_once_the_map_has_grown() {
    let dir = tempfile::tempdir().unwrap();
    let tokens = common::token_file(dir.path(), &[]);
    let agent_token = dir.path().join("agent-token");
    std::fs::write(&agent_token, format!("{}\n", common::ALICE)).unwrap();
    let (mut server, base) =
        common::spawn_server_process(dir.path().join("grow.db"), &tokens).await;
    let c = common::client();
    let r = c
        .put(format!("{base}/v1/maps/street"))
        .bearer_auth(common::OPERATOR)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    // one street of 60 transmitters, sorted west to east, with a gap of 8 m after the western
    // 20 (the first walk saw those)
    let mut world = common::world(9, 60);
    world.sort_by(|a, b| a[0].total_cmp(&b[0]));
    for w in &mut world[20..] {
        w[0] += 8.0;
    }
    let post = |body: Value, key: &'static str| {
        let c = c.clone();
        let url = format!("{base}/v1/maps/street/contributions");
        async move {
            let r = c
                .post(url)
                .bearer_auth(common::BOB)
                .header("Idempotency-Key", key)
                .json(&body)
                .send()
                .await
                .unwrap();
            (r.status().as_u16(), r.json::<Value>().await.unwrap())
        }
    };
    let west = common::contribution(common::user_map(&world[..20], 1, 1.0, 0.1), "west");
    assert_eq!(post(west, "west").await.0, 201);
    // our short walk east of it saw six transmitters and shares the three at the seam
    let ours = dir.path().join("ours");
    std::fs::create_dir_all(&ours).unwrap();
    let body = common::contribution(common::user_map(&world[17..23], 2, 1.0, 0.1), "ours");
    std::fs::write(ours.join("contribution.json"), body.to_string()).unwrap();
    let (ok, text, saved) = upload_again(&base, "street", &agent_token, &ours).await;
    assert!(ok, "{text}");
    assert_eq!(saved["status"], "undecided", "{text}");
    let problem = &saved["response"];
    assert!(
        problem["type"].as_str().unwrap().ends_with("/undecided"),
        "{problem}"
    );
    assert!(
        problem["detail"].as_str().unwrap().contains("decide"),
        "{problem}"
    );
    assert!(
        text.contains("echomap-agent upload"),
        "no hint to try again: {text}"
    );
    let head = get_json(&c, format!("{base}/v1/maps/street")).await;
    assert_eq!(head["version"], 1, "an undecided upload changed the map");
    // a second walk along the middle of the street overlaps the first one widely and merges
    let middle = common::contribution(common::user_map(&world[8..45], 3, 1.0, 0.1), "middle");
    assert_eq!(post(middle, "middle").await.0, 201);
    // now the map covers much of our walk: the kept upload, sent again, merges
    let (ok, text, saved) = upload_again(&base, "street", &agent_token, &ours).await;
    assert!(ok, "{text}");
    assert_eq!(saved["status"], "accepted", "{text}");
    assert_eq!(saved["response"]["inliers"], 6, "{saved}");
    let head = get_json(&c, format!("{base}/v1/maps/street")).await;
    assert_eq!(head["version"], 3);
    // a merged upload is not sent twice
    let (ok, text, _) = upload_again(&base, "street", &agent_token, &ours).await;
    assert!(!ok && text.contains("already merged"), "{text}");
    let page = get_json(&c, format!("{base}/v1/maps/street/contributions")).await;
    let statuses: Vec<&str> = page["contributions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["status"].as_str().unwrap())
        .collect();
    assert_eq!(statuses, ["accepted", "rejected", "accepted", "accepted"]);
    server.start_kill().unwrap();
    server.wait().await.unwrap();
}

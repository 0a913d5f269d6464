//! End to end, as a user runs it: a real `echomap-server` process on loopback and three
//! `echomap-agent run --server … --map …` processes, one after another, on the indoor scenario.
//! Each agent fetches the prior map, runs Channel-SLAM and uploads its map.
//!
//! Built as a test of the server package (`server/Cargo.toml`, `[[test]] e2e`); the agent
//! binary is taken from the same target directory, which `cargo test --workspace` fills.

#[path = "../server/tests/common/mod.rs"]
mod common;

use serde_json::Value;
use std::path::PathBuf;
use std::process::Stdio;
use tokio::io::{AsyncBufReadExt, BufReader};
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_agents_share_a_map_through_a_real_server() {
    let dir = tempfile::tempdir().unwrap();
    let tokens = common::token_file(dir.path(), &[]);
    let agent_token = dir.path().join("agent-token");
    std::fs::write(&agent_token, format!("# agent token\n{}\n", common::ALICE)).unwrap();
    let mut server = Command::new(env!("CARGO_BIN_EXE_echomap-server"))
        .args(["--listen", "127.0.0.1:0", "--database-url"])
        .arg(dir.path().join("e2e.db"))
        .arg("--token-file")
        .arg(&tokens)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .kill_on_drop(true)
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(server.stdout.take().unwrap())
        .read_line(&mut line)
        .await
        .unwrap();
    let base = line
        .trim()
        .strip_prefix("echomap-server listening on ")
        .unwrap()
        .to_owned();
    let c = common::client();
    let r = c
        .put(format!("{base}/v1/maps/indoor"))
        .bearer_auth(common::OPERATOR)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);

    let mut seen_versions = Vec::new();
    let mut summaries: Vec<Value> = Vec::new();
    for seed in 1..=3u64 {
        let out = dir.path().join(format!("agent{seed}"));
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
            .args([
                "--seed",
                &seed.to_string(),
                "--server",
                &base,
                "--map",
                "indoor",
                "--token-file",
            ])
            .arg(&agent_token)
            .arg("--out")
            .arg(&out)
            .stdout(Stdio::null())
            .status()
            .await
            .unwrap();
        assert!(status.success(), "agent {seed} failed: {status:?}");
        let prior: Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("prior.json")).unwrap())
                .unwrap();
        seen_versions.push(prior["version"].as_i64().unwrap());
        let upload: Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("upload.json")).unwrap())
                .unwrap();
        let status = upload["status"].as_str().unwrap();
        assert!(status == "accepted" || status == "rejected", "{upload}");
        if seed == 1 {
            assert_eq!(status, "accepted", "the first upload initializes the map");
            assert_eq!(upload["response"]["initialized"], true);
        }
        assert!(out.join("map.json").exists() && out.join("summary.json").exists());
        summaries.push(
            serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap())
                .unwrap(),
        );
    }
    // the later agents matched the prior map while running and took transmitters over
    for (k, s) in summaries.iter().enumerate().skip(1) {
        assert!(
            s["prior_matched_at_s"].as_f64().is_some(),
            "agent {} never matched the prior: {s}",
            k + 1
        );
        assert!(
            s["prior_transmitters_used"].as_f64().unwrap() >= 3.0,
            "agent {}: {s}",
            k + 1
        );
    }
    eprintln!(
        "final MAE per agent: {:?}",
        summaries
            .iter()
            .map(|s| s["mae_final_m"].as_f64().unwrap())
            .collect::<Vec<_>>()
    );
    // the first agent saw an empty map, the later ones the map the earlier ones left
    assert_eq!(seen_versions[0], 0);
    assert!(
        seen_versions[1] >= 1 && seen_versions[2] >= seen_versions[1],
        "{seen_versions:?}"
    );
    let page: Value = c
        .get(format!("{base}/v1/maps/indoor/contributions"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let rows = page["contributions"].as_array().unwrap();
    assert_eq!(rows.len(), 3, "every agent's upload is recorded");
    let map: Value = c
        .get(format!("{base}/v1/maps/indoor"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(map["version"], 3, "every upload merged: {rows:?}");
    // the same track walked again: a later agent's map must match the first one's and merge
    let merged = rows[1..]
        .iter()
        .filter(|r| r["status"] == "accepted" && r["merged"].as_i64().unwrap_or(0) >= 5)
        .count();
    assert!(
        merged >= 1,
        "no later upload matched the first map: {rows:?}"
    );
    assert!(
        rows.iter()
            .all(|r| r["contributor"] == "alice" && r["agent"] == "echomap-agent")
    );
    server.start_kill().unwrap();
    server.wait().await.unwrap();
}

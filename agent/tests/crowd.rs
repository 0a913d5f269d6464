//! `echomap-agent crowd` against a real map server on loopback (embedded, its own SQLite
//! file): one agent process fails for real — its output directory holds directories where
//! it must write `prior.json` and `map.json` — and the crowd reports it, goes on with the
//! next user, and exits with status 1. Nothing of the failed user reaches the server.

use echomap_agent::local_server::LocalServer;
use std::process::Command;

#[test]
fn a_failed_agent_process_is_reported_and_the_others_go_on() {
    let server = LocalServer::start().expect("loopback server");
    let out = tempfile::tempdir().unwrap();
    // user02 cannot write its files: the process starts, fails, and exits non-zero
    for f in ["prior.json", "map.json"] {
        std::fs::create_dir_all(out.path().join("user02").join(f).join("blocked")).unwrap();
    }
    let res = Command::new(env!("CARGO_BIN_EXE_echomap-agent"))
        .args([
            "crowd",
            "--server",
            &server.url,
            "--map",
            "crowd-test",
            "--token-file",
        ])
        .arg(&server.token_file)
        .args([
            "--scenario",
            "indoor",
            "--users",
            "3",
            "--particles",
            "40",
            "--seed",
            "1",
        ])
        .arg("--out")
        .arg(out.path())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert_eq!(res.status.code(), Some(1), "crowd must fail: {stderr}");
    assert!(
        stderr.contains("1 of 3 agent processes failed"),
        "stderr: {stderr}"
    );

    let results: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("crowd.json")).unwrap())
            .unwrap();
    let results = results.as_array().unwrap();
    let names: Vec<&str> = results
        .iter()
        .map(|r| r["user"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["user01", "user02", "user03"]);
    let ok: Vec<bool> = results.iter().map(|r| r["ok"].as_bool().unwrap()).collect();
    assert_eq!(ok, [true, false, true], "{results:#?}");
    let error = results[1]["error"].as_str().unwrap();
    assert!(error.contains("exit"), "error names the exit: {error}");
    assert!(results[1]["version"].is_null());
    // the users before and after the failure ran to the end and uploaded
    for r in [&results[0], &results[2]] {
        assert!(r["mae_final_m"].as_f64().is_some_and(f64::is_finite), "{r}");
        assert!(
            out.path()
                .join(r["user"].as_str().unwrap())
                .join("upload.json")
                .is_file()
        );
    }
    assert!(
        !out.path().join("user02").join("upload.json").exists(),
        "the failed user uploaded nothing"
    );
    let table = std::fs::read_to_string(out.path().join("crowd.md")).unwrap();
    assert!(table.contains("user02"), "{table}");

    // the server holds exactly the two uploads of user01 and user03
    let url = format!("{}/v1/maps/crowd-test/contributions", server.url);
    let list: serde_json::Value = tokio::runtime::Runtime::new()
        .unwrap()
        .block_on(async {
            let c = echomap_server::http::client_builder().build()?;
            c.get(url).send().await?.json().await
        })
        .unwrap();
    let agents: Vec<&str> = list["contributions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["agent"].as_str().unwrap_or(""))
        .collect();
    assert_eq!(agents, ["user01", "user03"], "{list}");
    server.stop().unwrap();
}

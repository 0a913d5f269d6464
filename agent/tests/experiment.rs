//! `echomap-agent experiment cooperative` as a user runs it: its own loopback server, a real
//! contributor process uploading a map, and the reference user run alone and with that map.
//! The tables and curves it writes must agree with what each reference process wrote.

use serde_json::Value;
use std::path::Path;
use std::process::Command;

fn json(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

#[test]
fn the_cooperative_experiment_reports_what_its_reference_runs_measured() {
    let out = tempfile::tempdir().unwrap();
    let res = Command::new(env!("CARGO_BIN_EXE_echomap-agent"))
        .args([
            "experiment",
            "cooperative",
            "--scenario",
            "indoor",
            "--contributors",
            "0,1",
            "--runs",
            "1",
            "--first-seed",
            "4",
            "--particles",
            "40",
            "--reference-particles",
            "60",
            "--out",
        ])
        .arg(out.path())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert!(res.status.success(), "experiment failed: {stderr}");

    let run = out.path().join("run-seed4");
    assert!(
        run.join("prior-c01.json").exists(),
        "the c = 1 prior was saved"
    );
    let curves = json(&out.path().join("summary.json"));
    let curves = curves.as_array().unwrap();
    let labels: Vec<&str> = curves
        .iter()
        .map(|c| c["label"].as_str().unwrap())
        .collect();
    assert_eq!(labels, ["single-user", "c01"]);
    let table = std::fs::read_to_string(out.path().join("results.md")).unwrap();
    for c in curves {
        let label = c["label"].as_str().unwrap();
        let own = json(&run.join(format!("reference-{label}")).join("summary.json"));
        // one run: the experiment's figures are that run's own
        let ate = c["ate_m"].as_array().unwrap();
        assert_eq!(ate.len(), 1, "{label}: {c}");
        let ate = ate[0].as_f64().unwrap();
        assert!(ate.is_finite() && ate > 0.0, "{label}: ATE {ate}");
        assert_eq!(ate, own["ate_m"].as_f64().unwrap(), "{label}");
        let final_mae = c["final_mae"][0].as_f64().unwrap();
        assert!(
            (final_mae - own["mae_final_m"].as_f64().unwrap()).abs() < 1e-9,
            "{label}: {final_mae} vs {own}"
        );
        let row = table
            .lines()
            .find(|l| l.starts_with(&format!("| {label} |")))
            .unwrap_or_else(|| panic!("no row for {label} in\n{table}"));
        assert!(row.ends_with(&format!("| {ate:.2} |")), "{row}");
    }
    // the c = 1 reference ran with the prior (whether it matched is up to the 40-particle map)
    let with = json(&run.join("reference-c01").join("summary.json"));
    assert!(with["prior_transmitters_used"].as_f64().is_some(), "{with}");
}

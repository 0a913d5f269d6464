//! The `echomap-agent` binary as a user runs it: real processes, real files.

use std::path::Path;
use std::process::Command;

fn agent() -> Command {
    Command::new(env!("CARGO_BIN_EXE_echomap-agent"))
}

fn files_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn simulate_writes_a_log_and_ground_truth_that_parse() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let st = agent()
        .args([
            "simulate",
            "--scenario",
            "indoor",
            "--track",
            "user05",
            "--seed",
            "9",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    assert_eq!(files_in(&out), ["log.jsonl", "truth.json"]);
    let log = echomap_shared::log::MeasurementLog::parse(
        &std::fs::read_to_string(out.join("log.jsonl")).unwrap(),
    )
    .unwrap();
    let truth = echomap_shared::log::GroundTruth::parse(
        &std::fs::read_to_string(out.join("truth.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(log.snapshots.len(), truth.poses.len());
    assert!(log.header.aoa);
    // every track id in the log has a true transmitter
    let ids: std::collections::HashSet<u64> = truth.transmitters.iter().map(|t| t.track).collect();
    assert!(
        log.snapshots
            .iter()
            .flat_map(|s| &s.components)
            .all(|c| ids.contains(&c.track))
    );
}

#[test]
fn scenario_draws_png_and_svg_and_dumps_json_that_loads_back() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["urban.png", "urban.svg", "urban.json"] {
        let st = agent()
            .args(["scenario", "--scenario", "urban", "--out"])
            .arg(dir.path().join(name))
            .output()
            .unwrap();
        assert!(
            st.status.success(),
            "{}",
            String::from_utf8_lossy(&st.stderr)
        );
    }
    let png = std::fs::read(dir.path().join("urban.png")).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    let svg = std::fs::read_to_string(dir.path().join("urban.svg")).unwrap();
    assert!(svg.contains("<svg") && svg.contains("Tx"));
    // the dumped scenario file simulates exactly like the built-in
    let a = dir.path().join("a");
    let b = dir.path().join("b");
    let file = dir.path().join("urban.json");
    for (scn, out) in [(file.to_str().unwrap(), &a), ("urban", &b)] {
        let st = agent()
            .args(["simulate", "--scenario", scn, "--seed", "3", "--out"])
            .arg(out)
            .output()
            .unwrap();
        assert!(st.status.success());
    }
    assert_eq!(
        std::fs::read(a.join("log.jsonl")).unwrap(),
        std::fs::read(b.join("log.jsonl")).unwrap()
    );
}

#[test]
fn a_bad_scenario_file_fails_naming_the_field_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let mut v = serde_json::to_value(echomap_agent::sim::builtin::indoor()).unwrap();
    v["tracks"][4]["waypoints"] = serde_json::json!([[0.0, 0.0]]);
    let file = dir.path().join("bad.json");
    std::fs::write(&file, v.to_string()).unwrap();
    let out = dir.path().join("out");
    let st = agent()
        .args(["simulate", "--scenario"])
        .arg(&file)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(!st.status.success());
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(err.contains("tracks[4].waypoints"), "{err}");
    assert!(!out.exists());
}

#[test]
fn the_readme_example_scenario_simulates() {
    let file = concat!(env!("CARGO_MANIFEST_DIR"), "/scenarios/example.json");
    let scn =
        echomap_agent::sim::Scenario::from_json(&std::fs::read_to_string(file).unwrap()).unwrap();
    assert_eq!(
        scn.walls[1].reflection_loss_db, 3.0,
        "default reflection loss"
    );
    assert_eq!(
        scn.scatterers[1].scattering_loss_db, 6.0,
        "default scattering loss"
    );
    let dir = tempfile::tempdir().unwrap();
    let st = agent()
        .args(["simulate", "--scenario", file, "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    let log = echomap_shared::log::MeasurementLog::parse(
        &std::fs::read_to_string(dir.path().join("log.jsonl")).unwrap(),
    )
    .unwrap();
    assert!(
        log.snapshots.iter().all(|s| !s.components.is_empty()),
        "LoS everywhere in the corridor"
    );
}

/// `simulate --scenario indoor --track TRACK --seed SEED --out DIR`, which must succeed.
fn simulate_indoor(track: &str, seed: u64, dir: &Path) {
    succeed(
        agent()
            .args([
                "simulate",
                "--scenario",
                "indoor",
                "--track",
                track,
                "--seed",
            ])
            .arg(seed.to_string())
            .arg("--out")
            .arg(dir),
    );
}

/// Runs `cmd`, which must succeed (else the assertion shows its stderr); returns its stdout.
fn succeed(cmd: &mut Command) -> String {
    let st = cmd.output().unwrap();
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    String::from_utf8_lossy(&st.stdout).into_owned()
}

#[test]
fn run_writes_map_track_and_plots() {
    let dir = tempfile::tempdir().unwrap();
    let sim_dir = dir.path().join("sim");
    simulate_indoor("user01", 2, &sim_dir);
    let out = dir.path().join("run");
    let stdout = run_ok(&sim_dir, &out, 2, &[]);
    assert!(stdout.contains("MAE"));
    let map = echomap_shared::TransmitterMap::from_json(
        &std::fs::read_to_string(out.join("map.json")).unwrap(),
    )
    .unwrap();
    assert!(!map.is_empty());
    let csv = std::fs::read_to_string(out.join("track.csv")).unwrap();
    let mut lines = csv.lines();
    assert!(
        lines
            .next()
            .unwrap()
            .starts_with("t,x,y,traveled_m,true_x,true_y,mae_m,rmse_m")
    );
    let log = std::fs::read_to_string(sim_dir.join("log.jsonl")).unwrap();
    assert_eq!(
        lines.count(),
        log.lines().count() - 1,
        "one row per snapshot"
    );
    for f in [
        "track.png",
        "track.svg",
        "error.png",
        "error.svg",
        "summary.json",
    ] {
        assert!(out.join(f).exists(), "{f}");
    }
}

#[test]
fn the_configuration_comes_from_the_sensor_profile_a_file_and_flags_and_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    simulate_indoor("user01", 1, &sim);
    let file = dir.path().join("mine.toml");
    std::fs::write(
        &file,
        "[motion]\nheading_noise_rad_per_sqrt_s = 0.02\n[association]\nwindow = 3\n",
    )
    .unwrap();
    let print = |extra: &[&str]| {
        let st = agent()
            .args(["config", "print", "--log"])
            .arg(&sim)
            .arg("--config")
            .arg(&file)
            .args(extra)
            .output()
            .unwrap();
        assert!(
            st.status.success(),
            "{}",
            String::from_utf8_lossy(&st.stderr)
        );
        String::from_utf8(st.stdout).unwrap()
    };
    let text = print(&["--set", "association.window=5", "--particles", "77"]);
    let line = |key: &str| {
        text.lines()
            .find(|l| l.starts_with(&format!("{key} = ")))
            .unwrap_or_else(|| panic!("no {key} in\n{text}"))
            .to_string()
    };
    // the simulator's profile states its noise floors 1.5× as drawn (0.25 m)
    assert!(line("distance_floor_m").contains("= 0.375"), "{text}");
    assert!(
        line("distance_floor_m").ends_with("# sensor profile"),
        "{text}"
    );
    assert!(line("heading_noise_rad_per_sqrt_s").contains("= 0.02"));
    assert!(line("heading_noise_rad_per_sqrt_s").contains("# file"));
    assert!(line("window").contains("= 5") && line("window").ends_with("# flag"));
    assert!(line("particles").contains("= 77") && line("particles").ends_with("# flag"));
    assert!(line("gate_chi2").ends_with("# default"));

    // a run with the file uses it, and writes the configuration it used
    let out = dir.path().join("run");
    let st = agent()
        .args(["run", "--quiet", "--particles", "50", "--log"])
        .arg(&sim)
        .arg("--config")
        .arg(&file)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    let used = std::fs::read_to_string(out.join("config.toml")).unwrap();
    assert!(
        used.lines()
            .any(|l| l.starts_with("window = 3") && l.contains("# file")),
        "{used}"
    );

    // an unknown key is refused, named, and nothing is written
    std::fs::write(&file, "[motion]\nheading_noise = 0.02\n").unwrap();
    let err = refused_run(&sim, &[std::ffi::OsStr::new("--config"), file.as_os_str()]);
    assert!(err.contains("motion.heading_noise"), "{err}");
}

#[test]
fn a_ray_traced_walk_without_noise_laws_gets_the_ones_it_was_made_with() {
    // The Sionna walks state no sensor profile; their README gives the noise they were made
    // with: σ_d = √(0.1² + (1.65/√(2·SNR))²) m and σ_θ = √(0.035² + (0.35/√(2·SNR))²) rad,
    // i.e. floors 0.1 m and 0.035 rad and 1.17 m and 0.247 rad at 0 dB.
    for walk in ["etoile-walk1", "florence-walk1"] {
        let log = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/data/sionna")
            .join(walk);
        if !log.join("log.jsonl").exists() {
            eprintln!(
                "SKIPPED: {} is absent; the ray-traced real-data check needs it",
                log.display()
            );
            return;
        }
        let st = agent()
            .args(["config", "print", "--log"])
            .arg(&log)
            .output()
            .unwrap();
        assert!(
            st.status.success(),
            "{}",
            String::from_utf8_lossy(&st.stderr)
        );
        let text = String::from_utf8(st.stdout).unwrap();
        let value = |key: &str| -> f64 {
            let l = text
                .lines()
                .find(|l| l.starts_with(&format!("{key} = ")))
                .unwrap_or_else(|| panic!("no {key} in\n{text}"));
            assert!(l.ends_with("# measured from the log"), "{l}");
            l.split('=')
                .nth(1)
                .unwrap()
                .split('#')
                .next()
                .unwrap()
                .trim()
                .parse()
                .unwrap()
        };
        for (key, want) in [
            ("distance_floor_m", 0.1),
            ("distance_at_0db_m", 1.167),
            ("aoa_floor_rad", 0.035),
            ("aoa_at_0db_rad", 0.247),
        ] {
            let got = value(key);
            assert!(
                (got / want - 1.0).abs() < 0.1,
                "{walk}: {key} {got} against {want}"
            );
        }
        // the noise was drawn Gaussian, and its tails measure so
        assert_eq!(value("noise_dof"), 0.0, "{walk}");
    }
}

/// Runs `run --quiet --log LOG EXTRA… --out DIR`, which must fail and write nothing; returns
/// what it printed on stderr.
fn refused_run(log: &Path, extra: &[&std::ffi::OsStr]) -> String {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let st = agent()
        .args(["run", "--quiet", "--log"])
        .arg(log)
        .args(extra)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(!st.status.success());
    assert!(!out.exists(), "a refused run wrote {}", out.display());
    String::from_utf8_lossy(&st.stderr).into_owned()
}

#[test]
fn run_on_a_malformed_log_names_the_line_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("in");
    std::fs::create_dir_all(&log).unwrap();
    std::fs::write(
        log.join("log.jsonl"),
        "{\"format\":\"echomap.log.v1\",\"snapshot_rate_hz\":10.0,\"aoa\":true}\n{\"t\":0.0,\"gyro\":0.0,\"components\":[]}\n{\"t\":0.1,\"gyro\":0.0,\"components\":[{\"track\":1,\"d\":\"far\",\"aoa\":0.0,\"snr_db\":3}]}\n",
    )
    .unwrap();
    let err = refused_run(&log, &[]);
    assert!(err.contains("line 3"), "{err}");
}

fn chiral_map(frame: nalgebra::Isometry2<f64>, prefix: &str) -> echomap_shared::TransmitterMap {
    use echomap_shared::map::Transmitter;
    use echomap_shared::mixture::Component;
    let pts = [
        [0.0, 0.0, 0.0],
        [10.0, 0.0, 0.0],
        [3.0, 7.0, 0.0],
        [15.0, 12.0, 4.0],
        [-4.0, 9.0, 0.0],
        [7.0, 18.0, 0.0],
        [21.0, 3.0, 9.0],
    ];
    let ts = pts
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let q = frame * nalgebra::Point2::new(p[0], p[1]);
            Transmitter {
                id: format!("{prefix}{i}"),
                components: vec![Component::new(
                    1.0,
                    nalgebra::Vector3::new(q.x, q.y, p[2]),
                    nalgebra::Matrix3::identity() * 0.02,
                )],
                existence: 1.0,
                reliability_m: 20.0,
                visibility: Default::default(),
            }
        })
        .collect();
    echomap_shared::TransmitterMap::new(2.0, ts).unwrap()
}

#[test]
fn match_and_merge_commands() {
    let dir = tempfile::tempdir().unwrap();
    let map_from_agent = nalgebra::Isometry2::new(nalgebra::Vector2::new(4.0, -7.0), 0.8);
    let prior = chiral_map(nalgebra::Isometry2::identity(), "p");
    let user = chiral_map(map_from_agent.inverse(), "u");
    let (pf, uf) = (dir.path().join("prior.json"), dir.path().join("user.json"));
    std::fs::write(&pf, prior.to_json_pretty()).unwrap();
    std::fs::write(&uf, user.to_json_pretty()).unwrap();
    let st = agent()
        .arg("match")
        .arg(&uf)
        .arg(&pf)
        .arg("--json")
        .output()
        .unwrap();
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&st.stdout).unwrap();
    assert_eq!(v["accepted"], true, "{v}");
    assert!((v["map_from_agent"]["angle_rad"].as_f64().unwrap() - 0.8).abs() < 1e-6);
    let pairs = v["correspondences"].as_array().unwrap();
    assert_eq!(pairs.len(), 7);
    assert!(
        pairs
            .iter()
            .all(|p| p[0].as_str().unwrap()[1..] == p[1].as_str().unwrap()[1..])
    );
    // merge: every user transmitter merges into its prior counterpart
    let out = dir.path().join("merged.json");
    let st = agent()
        .arg("merge")
        .arg(&pf)
        .arg(&uf)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    let merged =
        echomap_shared::TransmitterMap::from_json(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(merged.len(), 7);
    assert!(
        merged
            .transmitters()
            .iter()
            .all(|t| (t.reliability_m - 40.0).abs() < 1e-9)
    );
    // a user map holding a second copy of one transmitter: added as a new one by default,
    // merged into its prior counterpart with --absorb-chi2
    let mut twice = user.transmitters().to_vec();
    let mut copy = twice[2].clone();
    copy.id = "copy".into();
    copy.components[0].mean.x += 0.05;
    twice.push(copy);
    let tf = dir.path().join("twice.json");
    let twice = echomap_shared::TransmitterMap::new(2.0, twice).unwrap();
    std::fs::write(&tf, twice.to_json_pretty()).unwrap();
    for (absorb, count, p2_reliability) in [("0", 8, 40.0), ("9.21", 7, 60.0)] {
        let out = dir.path().join(format!("twice-{absorb}.json"));
        let st = agent()
            .args(["merge", "--absorb-chi2", absorb, "--out"])
            .arg(&out)
            .arg(&pf)
            .arg(&tf)
            .output()
            .unwrap();
        assert!(
            st.status.success(),
            "{}",
            String::from_utf8_lossy(&st.stderr)
        );
        let m = echomap_shared::TransmitterMap::from_json(&std::fs::read_to_string(&out).unwrap())
            .unwrap();
        assert_eq!(m.len(), count, "--absorb-chi2 {absorb}");
        let p2 = m.transmitters().iter().find(|t| t.id == "p2").unwrap();
        assert!((p2.reliability_m - p2_reliability).abs() < 1e-9, "{absorb}");
    }
    let st = agent()
        .args(["merge", "--absorb-chi2=-1", "--out"])
        .arg(dir.path().join("never.json"))
        .arg(&pf)
        .arg(&tf)
        .output()
        .unwrap();
    assert!(!st.status.success());
    assert!(String::from_utf8_lossy(&st.stderr).contains("non-negative"));
    assert!(!dir.path().join("never.json").exists());
    // an unrelated (mirrored) user map is rejected and nothing is written
    let mirrored = chiral_map(nalgebra::Isometry2::identity(), "m")
        .transformed(&nalgebra::Isometry2::identity());
    let mirrored = echomap_shared::TransmitterMap::new(
        2.0,
        mirrored
            .transmitters()
            .iter()
            .cloned()
            .map(|mut t| {
                t.components[0].mean.x = -t.components[0].mean.x;
                t
            })
            .collect(),
    )
    .unwrap();
    let mf = dir.path().join("mirrored.json");
    std::fs::write(&mf, mirrored.to_json_pretty()).unwrap();
    let out2 = dir.path().join("merged2.json");
    let st = agent()
        .arg("merge")
        .arg(&pf)
        .arg(&mf)
        .arg("--out")
        .arg(&out2)
        .output()
        .unwrap();
    assert!(!st.status.success());
    assert!(!out2.exists());
}

/// `run --log LOG --out OUT --particles 100 --quiet --seed SEED` plus `extra`; must succeed.
/// Returns what it printed.
fn run_ok(log: &Path, out: &Path, seed: u64, extra: &[&str]) -> String {
    succeed(
        agent()
            .args(["run", "--particles", "100", "--quiet", "--seed"])
            .arg(seed.to_string())
            .arg("--log")
            .arg(log)
            .arg("--out")
            .arg(out)
            .args(extra),
    )
}

#[test]
fn a_prior_the_configuration_says_not_to_use_leaves_the_run_as_if_alone() {
    let dir = tempfile::tempdir().unwrap();
    let (sim1, sim2) = (dir.path().join("sim1"), dir.path().join("sim2"));
    simulate_indoor("user01", 3, &sim1);
    simulate_indoor("user02", 3, &sim2);
    let first = dir.path().join("first");
    run_ok(&sim1, &first, 3, &[]);
    let prior = first.join("map.json");
    let prior = prior.to_str().unwrap();
    let (alone, with, ignored) = (
        dir.path().join("alone"),
        dir.path().join("with"),
        dir.path().join("ignored"),
    );
    run_ok(&sim2, &alone, 3, &[]);
    run_ok(&sim2, &with, 3, &["--prior", prior]);
    run_ok(
        &sim2,
        &ignored,
        3,
        &["--prior", prior, "--set", "prior.use_in_filter=false"],
    );
    assert!(with.join("prior_matches.csv").exists(), "the prior is used");
    assert!(!ignored.join("prior_matches.csv").exists());
    let track = |d: &Path| std::fs::read_to_string(d.join("track.csv")).unwrap();
    assert_eq!(track(&ignored), track(&alone), "as if alone");
}

/// `simulate --cir` then `estimate`: the log, the truth and the channel waterfall land in the
/// output; an invalid confirmation time is refused before anything is written.
#[test]
fn estimate_turns_a_simulated_channel_into_a_log_and_a_waterfall() {
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    let st = agent()
        .args(["simulate", "--scenario", "indoor", "--track", "user05"])
        .args(["--seed", "4", "--cir", "--out"])
        .arg(&sim)
        .output()
        .unwrap();
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    let est = dir.path().join("est");
    let bad = agent()
        .arg("estimate")
        .arg(&sim)
        .args(["--min-track-s=-1", "--out"])
        .arg(&est)
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(
        String::from_utf8_lossy(&bad.stderr).contains("--min-track-s"),
        "{}",
        String::from_utf8_lossy(&bad.stderr)
    );
    assert!(!est.exists(), "nothing is written for a refused run");
    let st = agent()
        .arg("estimate")
        .arg(&sim)
        .arg("--out")
        .arg(&est)
        .output()
        .unwrap();
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    assert_eq!(files_in(&est), ["log.jsonl", "truth.json", "waterfall.png"]);
    let log = echomap_shared::log::MeasurementLog::parse(
        &std::fs::read_to_string(est.join("log.jsonl")).unwrap(),
    )
    .unwrap();
    let ideal = echomap_shared::log::MeasurementLog::parse(
        &std::fs::read_to_string(sim.join("log.jsonl")).unwrap(),
    )
    .unwrap();
    assert_eq!(log.snapshots.len(), ideal.snapshots.len());
    assert!(log.header.sensor.is_some_and(|s| s.distance_m.is_some()));
    assert!(log.snapshots.iter().any(|s| !s.components.is_empty()));
    let png = std::fs::read(est.join("waterfall.png")).unwrap();
    assert!(
        png.starts_with(b"\x89PNG") && png.len() > 10_000,
        "{} bytes",
        png.len()
    );
}

/// `islands` splits the particles into independent filters, also with a prior map: the run
/// writes its configuration, one row per snapshot and a summary whose reported position errs
/// no more than the islands' mean MAE; more islands than particles is refused, naming the key.
#[test]
fn islands_run_with_and_without_a_prior_and_are_validated() {
    let dir = tempfile::tempdir().unwrap();
    let (sim1, sim2) = (dir.path().join("sim1"), dir.path().join("sim2"));
    simulate_indoor("user01", 4, &sim1);
    simulate_indoor("user02", 4, &sim2);
    let first = dir.path().join("first");
    run_ok(&sim1, &first, 4, &["--set", "islands=2"]);
    let prior = first.join("map.json");
    assert!(
        !echomap_shared::TransmitterMap::from_json(&std::fs::read_to_string(&prior).unwrap())
            .unwrap()
            .is_empty()
    );
    let (one, two) = (dir.path().join("one"), dir.path().join("two"));
    let prior = prior.to_str().unwrap();
    run_ok(&sim2, &one, 4, &["--prior", prior]);
    run_ok(&sim2, &two, 4, &["--prior", prior, "--set", "islands=2"]);
    let config = std::fs::read_to_string(two.join("config.toml")).unwrap();
    assert!(config.contains("islands = 2"), "{config}");
    let track = |d: &Path| std::fs::read_to_string(d.join("track.csv")).unwrap();
    let log = std::fs::read_to_string(sim2.join("log.jsonl")).unwrap();
    assert_eq!(track(&two).lines().count(), log.lines().count());
    assert_ne!(track(&one), track(&two), "two islands are not one filter");
    assert!(two.join("prior_matches.csv").exists());
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(two.join("summary.json")).unwrap()).unwrap();
    let (err, mae) = (
        summary["error_mean_m"].as_f64().unwrap(),
        summary["mae_mean_m"].as_f64().unwrap(),
    );
    assert!(
        err.is_finite() && err <= mae + 1e-9,
        "error {err}, MAE {mae}"
    );
    let e = refused_run(
        &sim2,
        &["--particles", "100", "--set", "islands=101"].map(std::ffi::OsStr::new),
    );
    assert!(e.contains("islands"), "{e}");
}

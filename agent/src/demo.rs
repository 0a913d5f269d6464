//! `echomap-agent demo`, the main job: a map server on loopback (SQLite in a temporary
//! directory), a crowd of agent processes building a map of the indoor scenario one after
//! another, then the reference user alone and with the crowd's map; results table, plots.

use crate::evaluate::Curves;
use crate::experiment::{ExperimentSpec, cooperative_scenario};
use crate::sim::user_tracks;
use anyhow::Result;
use std::path::PathBuf;

/// What the demo runs.
#[derive(Debug, Clone)]
pub struct DemoSpec {
    /// seed of the simulations and filters
    pub seed: u64,
    /// number of contributing users (indoor tracks user01, user02, …)
    pub users: usize,
    /// particles of every agent
    pub particles: usize,
    pub out: PathBuf,
}

pub fn demo(a: &DemoSpec) -> Result<()> {
    let tracks = user_tracks("indoor")?;
    anyhow::ensure!(
        a.users >= 1 && a.users <= tracks.len(),
        "--users must be 1..={}",
        tracks.len()
    );
    anyhow::ensure!(a.particles >= 1, "--particles must be at least 1");
    std::fs::create_dir_all(&a.out)?;
    // the scenario with every track, for orientation
    let scenario = crate::sim::builtin::indoor();
    let mut drawn = vec!["reference".to_string()];
    drawn.extend(tracks[..a.users].iter().cloned());
    crate::plot::draw_scenario(&scenario, &drawn, "reference", &a.out.join("scenario.png"))?;
    let particles = serde_json::json!({ "particles": a.particles });
    let spec = ExperimentSpec {
        exe: std::env::current_exe()?,
        server: None,
        token_file: None,
        runs: 1,
        first_seed: a.seed,
        parallel: 2,
        crowd_config: particles.clone(),
        reference_config: particles,
        out: a.out.clone(),
        progress: true,
        match_visibility_weight: 1.0,
        match_score: echomap_shared::matching::MatchScore::Msac,
        merge_absorb_chi2: 0.0,
    };
    println!(
        "echomap demo: {} users build a map of `indoor` on a fresh map server, then the reference user runs alone and with it ({} particles each)",
        a.users, a.particles
    );
    let curves: Vec<Curves> =
        cooperative_scenario(&spec, "indoor", &tracks, "reference", &[0, a.users])?;
    let (alone, with) = (&curves[0], &curves[1]);
    let f = |c: &Curves| c.final_mae.first().copied().unwrap_or(f64::NAN);
    let m = |c: &Curves| c.mean_mae.first().copied().unwrap_or(f64::NAN);
    println!(
        "reference user: final MAE {:.2} m alone, {:.2} m with the map of {} users; mean MAE {:.2} m → {:.2} m",
        f(alone),
        f(with),
        a.users,
        m(alone),
        m(with)
    );
    println!(
        "plots: {} (MAE vs travelled distance), {}; per-user outputs under {}",
        a.out.join("error.png").display(),
        a.out.join("scenario.png").display(),
        a.out.join(format!("run-seed{}", a.seed)).display()
    );
    Ok(())
}

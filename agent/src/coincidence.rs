//! Calibration of map matching on dense random fields (`echomap_shared::matching::fields`):
//! how often unrelated maps are accepted and related ones recovered, against the number of
//! transmitters per map and the acceptance threshold (expected false alarms ε).

use crate::plot::{self, Curve};
use anyhow::{Context, Result};
use echomap_shared::matching::fields::{FieldPair, related, unrelated};
use echomap_shared::matching::{MatchConfig, match_maps};
use plotters::style::RGBColor;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use std::fmt::Write as _;
use std::path::PathBuf;

/// What to measure.
#[derive(Debug, Clone)]
pub struct CoincidenceSpec {
    /// unrelated pairs drawn (related: a fifth as many)
    pub pairs: usize,
    /// seed of the first pair (pair k uses seed + k)
    pub seed: u64,
    /// acceptance thresholds ε to evaluate (the default matcher uses its own)
    pub thresholds: Vec<f64>,
    /// output folder: coincidence.csv, false_accepts.svg, summary.md
    pub out: PathBuf,
}

/// Bins of transmitters per map (mean of the two maps).
const BINS: [(usize, usize); 4] = [(8, 15), (16, 23), (24, 31), (32, 40)];

fn bin_of(f: &FieldPair) -> usize {
    let n = (f.user.len() + f.prior.len()) / 2;
    BINS.iter()
        .position(|&(_, hi)| n <= hi)
        .unwrap_or(BINS.len() - 1)
}

/// Runs the calibration; returns the summary table (markdown) it also writes.
pub fn coincidence(spec: &CoincidenceSpec) -> Result<String> {
    anyhow::ensure!(spec.pairs >= 1, "--pairs must be at least 1");
    anyhow::ensure!(
        spec.thresholds.iter().all(|e| e.is_finite() && *e > 0.0),
        "every threshold must be a positive number"
    );
    std::fs::create_dir_all(&spec.out)
        .with_context(|| format!("creating {}", spec.out.display()))?;
    let related_pairs = spec.pairs.div_ceil(5);
    let mut csv = String::from("kind,pair,bin,user,prior,shared,threshold,accepted,recovered\n");
    // per threshold: per bin (unrelated pairs, accepted), (related pairs, recovered)
    let mut table = Vec::new();
    for &eps in &spec.thresholds {
        let cfg = MatchConfig {
            max_false_alarms: eps,
            ..MatchConfig::default()
        };
        let run = |kind: &str, n: usize, draw: fn(&mut ChaCha8Rng) -> FieldPair| {
            (0..n)
                .into_par_iter()
                .map(|k| {
                    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed.wrapping_add(k as u64));
                    let f = draw(&mut rng);
                    let r = match_maps(&f.user, &f.prior, &cfg, &mut rng);
                    let (bin, recovered) = (bin_of(&f), f.recovered(&r));
                    let row = format!(
                        "{kind},{k},{bin},{},{},{},{eps:e},{},{recovered}\n",
                        f.user.len(),
                        f.prior.len(),
                        f.shared,
                        r.accepted,
                    );
                    (bin, r.accepted, recovered, row)
                })
                .collect::<Vec<_>>()
        };
        let un = run("unrelated", spec.pairs, unrelated);
        let re = run("related", related_pairs, related);
        let mut per_bin = vec![[0usize; 4]; BINS.len()];
        for (b, accepted, _, row) in &un {
            per_bin[*b][0] += 1;
            per_bin[*b][1] += *accepted as usize;
            csv.push_str(row);
        }
        for (b, _, recovered, row) in &re {
            per_bin[*b][2] += 1;
            per_bin[*b][3] += *recovered as usize;
            csv.push_str(row);
        }
        table.push((eps, per_bin));
    }
    std::fs::write(spec.out.join("coincidence.csv"), csv)?;
    let mut md = String::from(
        "| ε | transmitters per map | unrelated accepted | per 1000 | related recovered |\n| --- | --- | --- | --- | --- |\n",
    );
    let colours = [
        RGBColor(200, 30, 30),
        RGBColor(30, 90, 200),
        RGBColor(30, 150, 60),
        RGBColor(140, 60, 160),
    ];
    let mut curves: Vec<Curve> = Vec::new();
    for (i, (eps, per_bin)) in table.iter().enumerate() {
        let mut pts = Vec::new();
        let (mut tu, mut ta, mut tr, mut tok) = (0, 0, 0, 0);
        for (b, c) in per_bin.iter().enumerate() {
            let rate = 1000.0 * c[1] as f64 / c[0].max(1) as f64;
            let _ = writeln!(
                md,
                "| {eps:e} | {}–{} | {}/{} | {rate:.1} | {}/{} |",
                BINS[b].0, BINS[b].1, c[1], c[0], c[3], c[2]
            );
            pts.push(((BINS[b].0 + BINS[b].1) as f64 / 2.0, rate));
            (tu, ta, tr, tok) = (tu + c[0], ta + c[1], tr + c[2], tok + c[3]);
        }
        let _ = writeln!(
            md,
            "| {eps:e} | all | **{ta}/{tu}** | {:.2} | **{tok}/{tr}** ({:.1} %) |",
            1000.0 * ta as f64 / tu.max(1) as f64,
            100.0 * tok as f64 / tr.max(1) as f64
        );
        curves.push((format!("ε = {eps:e}"), colours[i % colours.len()], pts));
    }
    std::fs::write(spec.out.join("summary.md"), &md)?;
    plot::draw_xy(
        "Unrelated dense maps accepted, by size and threshold ε",
        "transmitters per map",
        "false accepts per 1000 pairs",
        &curves,
        &spec.out.join("false_accepts.svg"),
    )?;
    Ok(md)
}

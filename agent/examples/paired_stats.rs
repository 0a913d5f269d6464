//! Pairs each MRCLAM reference robot's runs with the others' map against the same runs alone,
//! over one or more `experiment cooperative --dataset mrclam` output directories (e.g. seeds
//! 1–10 and 11–20), and prints the table the experiment appends to `results.md`: the median of
//! the differences (mean MAE, final MAE, ATE), how many runs are lower with the map, and the
//! exact Wilcoxon signed-rank p-value. `cargo run --release --example paired_stats -- DIR [DIR...]`
use echomap_agent::evaluate::Curves;
use echomap_agent::experiment::paired_table;

fn main() -> anyhow::Result<()> {
    let dirs: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(!dirs.is_empty(), "usage: paired_stats DIR [DIR...]");
    let mut all: Vec<Curves> = Vec::new();
    for dir in &dirs {
        let path = std::path::Path::new(dir).join("summary.json");
        let text = std::fs::read_to_string(&path)
            .map_err(|e| anyhow::anyhow!("reading {}: {e}", path.display()))?;
        let curves: Vec<Curves> = serde_json::from_str(&text)?;
        for c in curves {
            match all.iter_mut().find(|a| a.label == c.label) {
                Some(a) => {
                    a.mean_mae.extend(c.mean_mae);
                    a.final_mae.extend(c.final_mae);
                    a.ate_m.extend(c.ate_m);
                }
                None => all.push(c),
            }
        }
    }
    print!("{}", paired_table(&all)?);
    Ok(())
}

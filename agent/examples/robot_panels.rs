//! Draws `robots.png/svg` (one panel per reference robot) from the `summary.json` of an
//! `experiment cooperative --dataset mrclam` output directory, as the experiment itself does
//! since 2026-12-03: `cargo run --release --example robot_panels -- DIR [TITLE]`.
use echomap_agent::evaluate::Curves;
use echomap_agent::experiment::write_robot_panels;
use std::path::Path;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (dir, title) = match args.as_slice() {
        [dir] => (dir, "MRCLAM: each robot alone and with the others' map"),
        [dir, title] => (dir, title.as_str()),
        _ => anyhow::bail!("usage: robot_panels DIR [TITLE]"),
    };
    let dir = Path::new(dir);
    let all: Vec<Curves> =
        serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json"))?)?;
    write_robot_panels(&all, title, dir)
}

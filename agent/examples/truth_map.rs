//! Writes the true virtual-transmitter map of a simulated indoor track (map frame = the
//! track's local frame), every transmitter one Gaussian of std STD (m):
//! `cargo run --release --example truth_map -- TRACK SEED STD OUT.json`.
use echomap_agent::sim::builtin::indoor;
use echomap_agent::sim::simulate::{SimOptions, simulate};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [track, seed, std_m, out] = args.as_slice() else {
        anyhow::bail!("usage: truth_map TRACK SEED STD OUT.json");
    };
    let sim = simulate(
        &indoor(),
        track,
        SimOptions {
            seed: seed.parse()?,
            toa_only: false,
        },
    )?;
    let map = sim.truth_map(&nalgebra::Isometry2::identity(), std_m.parse()?);
    std::fs::write(out, map.to_json_pretty())?;
    Ok(())
}

//! Writes the true virtual-transmitter map of a simulated track (map frame = its local frame),
//! every transmitter one Gaussian of std STD: `cargo run --example truth_map -- TRACK SEED STD OUT`.
use echomap_agent::sim::builtin::indoor;
use echomap_agent::sim::simulate::{SimOptions, simulate};
use echomap_shared::map::Transmitter;
use echomap_shared::mixture::Component;
use nalgebra::{Matrix3, Vector3};

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seed: u64 = a[2].parse().unwrap();
    let std_m: f64 = a[3].parse().unwrap();
    let out = simulate(
        &indoor(),
        &a[1],
        SimOptions {
            seed,
            toa_only: false,
        },
    )
    .unwrap();
    let mut seen: Vec<[f64; 3]> = Vec::new();
    let mut txs = Vec::new();
    for t in &out.truth.transmitters {
        let s = t.state;
        if seen
            .iter()
            .any(|q| (0..3).all(|k| (q[k] - s[k]).abs() < 1e-6))
        {
            continue;
        }
        seen.push(s);
        txs.push(Transmitter {
            id: format!("p{}", t.track),
            components: vec![Component::new(
                1.0,
                Vector3::new(s[0], s[1], s[2]),
                Matrix3::identity() * std_m * std_m,
            )],
            existence: 1.0,
            reliability_m: 50.0,
            visibility: Default::default(),
        });
    }
    let m = echomap_shared::TransmitterMap::new(2.0, txs).unwrap();
    std::fs::write(&a[4], serde_json::to_string(&m).unwrap()).unwrap();
}

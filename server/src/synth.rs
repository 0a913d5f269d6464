//! Synthetic maps with a known truth, for tests and the load benchmark: a world of
//! transmitters and user maps of it as agents would upload them (own frame, subset, noise).

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};

/// A world of `n` transmitters `[x, y, b]` spread over a 60 m × 40 m area; half are
/// physical/reflections (`b = 0`), half scatterers with a clock offset.
pub fn world(seed: u64, n: usize) -> Vec<[f64; 3]> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            let b = if rng.random_bool(0.5) {
                0.0
            } else {
                rng.random_range(0.5..8.0)
            };
            [
                rng.random_range(-30.0..30.0),
                rng.random_range(-20.0..20.0),
                b,
            ]
        })
        .collect()
}

fn normal(rng: &mut ChaCha8Rng) -> f64 {
    // Box–Muller
    let u1: f64 = rng.random_range(1e-12..1.0);
    let u2: f64 = rng.random::<f64>();
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// A user map (`echomap.map.v1` JSON) of `world` seen in a random agent frame: each transmitter
/// kept with probability `keep`, positions perturbed by `noise_m`, `components` Gaussian
/// components per transmitter (spread by 0.2 m). Ids are `u<seed>-<world index>`, so tests can
/// tell whether a match paired the right transmitters.
pub fn user_map(
    world: &[[f64; 3]],
    seed: u64,
    keep: f64,
    noise_m: f64,
    components: usize,
) -> Value {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let angle: f64 = rng.random_range(-3.1..3.1);
    let (tx, ty): (f64, f64) = (rng.random_range(-20.0..20.0), rng.random_range(-20.0..20.0));
    let (s, c) = angle.sin_cos();
    let k = components.max(1);
    let mut transmitters = Vec::new();
    for (i, w) in world.iter().enumerate() {
        if !rng.random_bool(keep) {
            continue;
        }
        let (x, y) = (
            w[0] + noise_m * normal(&mut rng),
            w[1] + noise_m * normal(&mut rng),
        );
        let var = 0.05 + noise_m * noise_m;
        let comps: Vec<Value> = (0..k)
            .map(|j| {
                let off = if k == 1 {
                    0.0
                } else {
                    0.2 * (j as f64 - (k - 1) as f64 / 2.0)
                };
                let (xj, yj) = (x + off, y - off);
                // agent_from_world: p_a = R(angle)·p_w + t
                let (xa, ya) = (c * xj - s * yj + tx, s * xj + c * yj + ty);
                json!({"weight": 1.0 / k as f64, "mean": [xa, ya, w[2]],
                       "cov": [[var, 0.0, 0.0], [0.0, var, 0.0], [0.0, 0.0, var]]})
            })
            .collect();
        transmitters.push(json!({
            "id": format!("u{seed}-{i}"),
            "components": comps,
            "existence": 0.95,
            "reliability_m": rng.random_range(5.0..50.0),
            "visibility": []
        }));
    }
    json!({"format": "echomap.map.v1", "hex_size_m": 2.0, "transmitters": transmitters})
}

/// A contribution body around a user map.
pub fn contribution(map: Value, run: &str) -> Value {
    json!({"contributor": "synthetic-agent", "run": run, "traveled_m": 100.0, "map": map})
}

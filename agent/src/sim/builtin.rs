//! Built-in scenarios modelled on the papers.
//!
//! - `indoor` (Ulmschneider et al. 2021 §V, Fig. 4/6): a 40 m × 24 m floor with a ring corridor around an
//!   inner block of two rooms (doorways south and north), eight pillars as point scatterers,
//!   one transmitter in the west corridor; 1.9 GHz, 100 MHz, 10 Hz, 9-element array.
//!   Track `reference` (150 m, one loop and a return along its first leg) and 21 further
//!   tracks `user01`…`user21` that start at different points of the ring, in both directions,
//!   at different lateral offsets.
//! - `urban` (Gentner et al. 2016 §6.1, Fig. 6): six buildings around a central block, eight poles,
//!   one transmitter in the south street; 1.5 GHz, 100 MHz, 20 Hz, 9-element array; the track
//!   `reference` is 500 m at 10 m/s with one loop around the central building.
//!
//! The layouts are our own reconstructions (the papers give figures, not coordinates).

use super::scenario::{
    Estimator, Gyro, Receiver, Scatterer, Scenario, Track, TransmitterSpec, Wall,
};

pub const NAMES: [&str; 2] = ["indoor", "urban"];

/// A built-in scenario by name.
pub fn builtin(name: &str) -> Option<Scenario> {
    match name {
        "indoor" => Some(indoor()),
        "urban" => Some(urban()),
        _ => None,
    }
}

fn wall(from: [f64; 2], to: [f64; 2]) -> Wall {
    Wall {
        from,
        to,
        reflection_loss_db: 3.0,
    }
}

fn building(x0: f64, y0: f64, x1: f64, y1: f64) -> Vec<Wall> {
    vec![
        wall([x0, y0], [x1, y0]),
        wall([x1, y0], [x1, y1]),
        wall([x1, y1], [x0, y1]),
        wall([x0, y1], [x0, y0]),
    ]
}

fn scatterers(points: &[[f64; 2]]) -> Vec<Scatterer> {
    points
        .iter()
        .map(|&position| Scatterer {
            position,
            scattering_loss_db: 6.0,
        })
        .collect()
}

/// Corners of the indoor ring corridor's centre line, inset by `delta` metres.
fn ring(delta: f64) -> [[f64; 2]; 4] {
    [
        [4.0 + delta, 4.0 + delta],
        [36.0 - delta, 4.0 + delta],
        [36.0 - delta, 20.0 - delta],
        [4.0 + delta, 20.0 - delta],
    ]
}

/// Waypoints of a walk of `length` metres along the ring inset by `delta`, starting at arc
/// position `start` (metres from the first corner, counter-clockwise), in direction `ccw`.
fn ring_walk(delta: f64, start: f64, length: f64, ccw: bool) -> Vec<[f64; 2]> {
    let mut corners = ring(delta).to_vec();
    if !ccw {
        corners.reverse();
    }
    let n = corners.len();
    let seg = |i: usize| {
        let (a, b) = (corners[i % n], corners[(i + 1) % n]);
        (a, b, ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt())
    };
    let perimeter: f64 = (0..n).map(|i| seg(i).2).sum();
    let lerp =
        |a: [f64; 2], b: [f64; 2], f: f64| [a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f];
    // locate the start
    let mut i = 0;
    let mut u = start.rem_euclid(perimeter);
    while u >= seg(i).2 {
        u -= seg(i).2;
        i += 1;
    }
    let (a, b, l) = seg(i);
    let mut pts = vec![lerp(a, b, u / l)];
    let mut remaining = length;
    let mut avail = l - u;
    loop {
        let (a, b, l) = seg(i);
        if remaining <= avail {
            pts.push(lerp(a, b, (l - avail + remaining) / l));
            break;
        }
        remaining -= avail;
        pts.push(b);
        i += 1;
        avail = seg(i).2;
    }
    pts
}

pub fn indoor() -> Scenario {
    let mut walls = building(0.0, 0.0, 40.0, 24.0);
    // inner block with doorways in its south (x 18–22) and north (x 22–26) walls
    walls.extend([
        wall([12.0, 8.0], [18.0, 8.0]),
        wall([22.0, 8.0], [28.0, 8.0]),
        wall([28.0, 8.0], [28.0, 16.0]),
        wall([28.0, 16.0], [26.0, 16.0]),
        wall([22.0, 16.0], [12.0, 16.0]),
        wall([12.0, 16.0], [12.0, 8.0]),
        wall([20.0, 8.0], [20.0, 16.0]),
    ]);
    let mut tracks = vec![Track {
        name: "reference".into(),
        speed_mps: 1.0,
        waypoints: vec![
            [4.0, 4.0],
            [36.0, 4.0],
            [36.0, 20.0],
            [4.0, 20.0],
            [4.0, 4.0],
            [36.0, 4.0],
            [36.0, 20.0],
            [30.0, 20.0],
        ],
        turn_radius_m: 1.0,
    }];
    for i in 1..=21u32 {
        let fi = f64::from(i);
        tracks.push(Track {
            name: format!("user{i:02}"),
            speed_mps: 1.0 + 0.05 * f64::from(i % 5),
            waypoints: ring_walk(
                f64::from((i * 7) % 9) * 0.5 - 2.0,
                (fi * 37.0) % 96.0 + 0.5,
                70.0 + f64::from((i * 13) % 50),
                i % 2 == 0,
            ),
            turn_radius_m: 1.0,
        });
    }
    Scenario {
        name: "indoor".into(),
        carrier_hz: 1.9e9,
        bandwidth_hz: 100e6,
        snapshot_rate_hz: 10.0,
        transmitter: TransmitterSpec {
            position: [7.0, 12.0],
            power_dbm: -10.0,
            clock_offset_m: 0.0,
        },
        walls,
        scatterers: scatterers(&[
            [9.0, 6.0],
            [31.0, 6.0],
            [31.0, 18.0],
            [9.0, 18.0],
            [20.0, 2.0],
            [20.0, 22.0],
            [2.5, 12.0],
            [38.0, 12.0],
        ]),
        receiver: Receiver::default(),
        estimator: Estimator::default(),
        gyro: Gyro {
            noise_std_rad_s: 0.01,
            bias_rad_s: 0.0,
        },
        tracks,
    }
}

pub fn urban() -> Scenario {
    let mut walls = Vec::new();
    for (x0, y0, x1, y1) in [
        (100.0, 60.0, 160.0, 100.0), // central building
        (20.0, 10.0, 80.0, 38.0),
        (100.0, 10.0, 160.0, 38.0),
        (182.0, 40.0, 230.0, 120.0),
        (100.0, 122.0, 160.0, 160.0),
        (20.0, 62.0, 78.0, 120.0),
    ] {
        walls.extend(building(x0, y0, x1, y1));
    }
    Scenario {
        name: "urban".into(),
        carrier_hz: 1.5e9,
        bandwidth_hz: 100e6,
        snapshot_rate_hz: 20.0,
        transmitter: TransmitterSpec {
            position: [130.0, 44.0],
            power_dbm: 0.0,
            clock_offset_m: 0.0,
        },
        walls,
        scatterers: scatterers(&[
            [50.0, 42.0],
            [120.0, 56.0],
            [176.0, 75.0],
            [125.0, 104.0],
            [84.0, 80.0],
            [176.0, 44.0],
            [95.0, 116.0],
            [10.0, 56.0],
        ]),
        receiver: Receiver::default(),
        estimator: Estimator {
            fading_correlation_m: 5.0,
            // Gentner et al. 2016 §6.1 uses only the components observable over at least 35 m of travel
            min_track_distance_m: 35.0,
            ..Estimator::default()
        },
        gyro: Gyro {
            noise_std_rad_s: 0.01,
            bias_rad_s: 0.0,
        },
        tracks: vec![Track {
            name: "reference".into(),
            speed_mps: 10.0,
            waypoints: vec![
                [-20.0, 50.0],
                [170.0, 50.0],
                [170.0, 110.0],
                [90.0, 110.0],
                [90.0, 50.0],
                [170.0, 50.0],
                [170.0, 80.0],
            ],
            turn_radius_m: 5.0,
        }],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtins_are_valid() {
        for name in NAMES {
            let s = builtin(name).unwrap();
            s.validate().unwrap();
            // and survive a JSON round trip through the file format
            let back = Scenario::from_json(&serde_json::to_string(&s).unwrap()).unwrap();
            assert_eq!(back, s);
        }
    }

    #[test]
    fn indoor_tracks() {
        let s = indoor();
        assert_eq!(s.tracks.len(), 22);
        let reference = super::super::trajectory::Trajectory::new(&s.tracks[0].waypoints, 0.0);
        assert!((reference.length_m() - 150.0).abs() < 1e-9);
        for t in &s.tracks[1..] {
            let len = super::super::trajectory::Trajectory::new(&t.waypoints, 0.0).length_m();
            assert!((70.0..=120.0).contains(&len), "{} is {len} m", t.name);
        }
    }

    #[test]
    fn urban_reference_is_500m() {
        let s = urban();
        let len = super::super::trajectory::Trajectory::new(&s.tracks[0].waypoints, 0.0).length_m();
        assert!((len - 500.0).abs() < 1e-9);
    }
}

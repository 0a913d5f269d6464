use super::*;
use crate::geometry::wrap_angle;
use proptest::prelude::*;
use std::f64::consts::PI;

fn comp(weight: f64, mean: [f64; 3]) -> Component {
    Component {
        weight,
        mean: Vector3::from(mean),
        cov: Matrix3::from_diagonal(&Vector3::new(0.5, 0.4, 0.2)),
    }
}

fn sample_map() -> TransmitterMap {
    let mut vis = BTreeMap::new();
    vis.insert(
        HexCell { q: 3, r: -1 },
        Beta {
            alpha: 12.0,
            beta: 2.0,
        },
    );
    vis.insert(
        HexCell { q: 0, r: 0 },
        Beta {
            alpha: 0.0,
            beta: 5.5,
        },
    );
    TransmitterMap::new(
        2.0,
        vec![
            Transmitter {
                id: "t17".into(),
                components: vec![comp(0.8, [12.1, -3.4, 0.0]), comp(0.2, [11.0, -2.0, 0.3])],
                existence: 0.93,
                reliability_m: 41.5,
                visibility: vis,
            },
            Transmitter {
                id: "t18".into(),
                components: vec![comp(1.0, [-5.0, 7.25, 3.5])],
                existence: 1.0,
                reliability_m: 0.0,
                visibility: BTreeMap::new(),
            },
        ],
    )
    .unwrap()
}

#[test]
fn json_roundtrip_is_exact() {
    let m = sample_map();
    let text = m.to_json_pretty();
    let back = TransmitterMap::from_json(&text).unwrap();
    assert_eq!(back, m);
    assert_eq!(back.to_json_pretty(), text);
}

#[test]
fn design_example_parses() {
    let text = r#"{
      "format": "echomap.map.v1",
      "hex_size_m": 2.0,
      "transmitters": [
        {
          "id": "t17",
          "components": [
            { "weight": 0.8, "mean": [12.1, -3.4, 0.0], "cov": [[0.5, 0.1, 0.0], [0.1, 0.4, 0.0], [0.0, 0.0, 0.2]] },
            { "weight": 0.2, "mean": [12.1, -3.4, 0.0], "cov": [[0.5, 0.1, 0.0], [0.1, 0.4, 0.0], [0.0, 0.0, 0.2]] }
          ],
          "existence": 0.93,
          "reliability_m": 41.5,
          "visibility": [ { "q": 3, "r": -1, "alpha": 12.0, "beta": 2.0 } ]
        }
      ]
    }"#;
    let m = TransmitterMap::from_json(text).unwrap();
    assert_eq!(m.len(), 1);
    assert_eq!(
        m.transmitters()[0].visibility[&HexCell { q: 3, r: -1 }].alpha,
        12.0
    );
}

/// Applies `edit` to the JSON of the sample map and returns the validation error's path.
fn reject(edit: impl FnOnce(&mut serde_json::Value)) -> ParseError {
    let mut v = serde_json::to_value(sample_map()).unwrap();
    edit(&mut v);
    TransmitterMap::from_json(&v.to_string()).unwrap_err()
}

fn invalid_path(e: ParseError) -> String {
    match e {
        ParseError::Invalid(me) => me.path,
        ParseError::Syntax(s) => panic!("expected a validation error, got syntax error {s}"),
    }
}

#[test]
fn validation_names_the_field_at_fault() {
    use serde_json::json;
    type Edit = Box<dyn FnOnce(&mut serde_json::Value)>;
    let cases: Vec<(&str, Edit)> = vec![
        (
            "format",
            Box::new(|v| v["format"] = json!("echomap.map.v0")),
        ),
        ("hex_size_m", Box::new(|v| v["hex_size_m"] = json!(0.0))),
        (
            "transmitters[0].components[1].weight",
            Box::new(|v| v["transmitters"][0]["components"][1]["weight"] = json!(-0.2)),
        ),
        (
            "transmitters[0].components",
            Box::new(|v| v["transmitters"][0]["components"][1]["weight"] = json!(0.3)),
        ),
        (
            "transmitters[1].components[0].cov",
            Box::new(|v| v["transmitters"][1]["components"][0]["cov"][0][1] = json!(0.3)),
        ),
        (
            "transmitters[1].components[0].cov",
            Box::new(|v| v["transmitters"][1]["components"][0]["cov"][0][0] = json!(-1.0)),
        ),
        (
            "transmitters[1].components[0].cov",
            Box::new(|v| {
                v["transmitters"][1]["components"][0]["cov"] =
                    json!([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
            }),
        ),
        (
            "transmitters[1].existence",
            Box::new(|v| v["transmitters"][1]["existence"] = json!(1.5)),
        ),
        (
            "transmitters[1].reliability_m",
            Box::new(|v| v["transmitters"][1]["reliability_m"] = json!(-3.0)),
        ),
        (
            "transmitters[1].id",
            Box::new(|v| v["transmitters"][1]["id"] = json!("t17")),
        ),
        (
            "transmitters[1].id",
            Box::new(|v| v["transmitters"][1]["id"] = json!("")),
        ),
        (
            "transmitters[1].components",
            Box::new(|v| v["transmitters"][1]["components"] = json!([])),
        ),
        (
            "transmitters[0].visibility[q=0,r=0].beta",
            Box::new(|v| v["transmitters"][0]["visibility"][0]["beta"] = json!(-1.0)),
        ),
        (
            "transmitters[0].visibility",
            Box::new(|v| {
                let c = v["transmitters"][0]["visibility"][0].clone();
                v["transmitters"][0]["visibility"]
                    .as_array_mut()
                    .unwrap()
                    .push(c);
            }),
        ),
    ];
    for (path, edit) in cases {
        assert_eq!(invalid_path(reject(edit)), path);
    }
}

#[test]
fn non_numbers_and_unknown_fields_are_syntax_errors() {
    for text in [
        r#"{"format":"echomap.map.v1","hex_size_m":2.0,"transmitters":[],"extra":1}"#,
        r#"{"format":"echomap.map.v1","hex_size_m":null,"transmitters":[]}"#,
        r#"{"format":"echomap.map.v1","hex_size_m":1e400,"transmitters":[]}"#,
        r#"{"format":"echomap.map.v1","hex_size_m":NaN,"transmitters":[]}"#,
        "not json",
    ] {
        assert!(
            matches!(TransmitterMap::from_json(text), Err(ParseError::Syntax(_))),
            "{text}"
        );
    }
}

#[test]
fn size_limits_are_enforced() {
    let t = |i: usize| Transmitter {
        id: format!("t{i}"),
        components: vec![comp(1.0, [0.0, 0.0, 0.0])],
        existence: 0.5,
        reliability_m: 1.0,
        visibility: BTreeMap::new(),
    };
    let too_many: Vec<_> = (0..=MAX_TRANSMITTERS).map(t).collect();
    let e = TransmitterMap::new(2.0, too_many).unwrap_err();
    assert!(matches!(e.kind, MapErrorKind::TooMany { .. }));
    let mut one = t(0);
    one.components = vec![comp(1.0 / 65.0, [0.0; 3]); 65];
    let e = TransmitterMap::new(2.0, vec![one]).unwrap_err();
    assert_eq!(e.path, "transmitters[0].components");
}

#[test]
fn maps_beyond_the_limits_keep_what_carries_the_most_evidence() {
    // 3 transmitters with 40,000 cells each: 120,000 > 100,000; the cells of transmitter i
    // at column q carry i + q/100,000 observations, so the weakest are transmitter 0's
    let t = |i: usize| Transmitter {
        id: format!("t{i}"),
        components: vec![comp(1.0, [i as f64, 0.0, 0.0])],
        existence: 0.5 + 0.1 * i as f64,
        reliability_m: 1.0,
        visibility: (0..40_000)
            .map(|q| {
                let n = i as f64 + 1.0 + q as f64 / 100_000.0;
                (
                    HexCell { q, r: 0 },
                    Beta {
                        alpha: n,
                        beta: 0.0,
                    },
                )
            })
            .collect(),
    };
    let mut txs: Vec<_> = (0..3).map(t).collect();
    let untouched = txs.clone();
    assert!(TransmitterMap::new(2.0, txs.clone()).is_err());
    let pruned = fit_to_limits(&mut txs);
    assert_eq!(
        pruned,
        Pruned {
            transmitters: 0,
            cells: 20_000
        }
    );
    let cells: Vec<usize> = txs.iter().map(|t| t.visibility.len()).collect();
    assert_eq!(cells, [20_000, 40_000, 40_000]);
    // transmitter 0 kept its 20,000 best cells, the columns 20,000 and up
    assert_eq!(
        txs[0].visibility.keys().next(),
        Some(&HexCell { q: 20_000, r: 0 })
    );
    assert_eq!(txs[1].visibility, untouched[1].visibility);
    assert!(TransmitterMap::new(2.0, txs.clone()).is_ok());
    // within the limits nothing changes
    let mut again = txs.clone();
    assert_eq!(fit_to_limits(&mut again), Pruned::default());
    assert_eq!(again, txs);
    // too many transmitters: the least existence × reliability go, order kept
    let mut many: Vec<Transmitter> = (0..MAX_TRANSMITTERS + 3)
        .map(|i| Transmitter {
            id: format!("m{i}"),
            components: vec![comp(1.0, [0.0; 3])],
            existence: if i % 1000 == 7 && i < 3000 { 0.01 } else { 0.9 },
            reliability_m: 5.0,
            visibility: BTreeMap::new(),
        })
        .collect();
    let pruned = fit_to_limits(&mut many);
    assert_eq!(pruned.transmitters, 3);
    assert_eq!(many.len(), MAX_TRANSMITTERS);
    assert!(
        many.iter()
            .all(|t| t.id != "m7" && t.id != "m1007" && t.id != "m2007")
    );
    assert!(many.windows(2).all(|w| {
        let n = |t: &Transmitter| t.id[1..].parse::<usize>().unwrap();
        n(&w[0]) < n(&w[1])
    }));
}

#[test]
fn non_finite_values_are_rejected_in_memory_too() {
    let mut t = sample_map().into_transmitters();
    t[0].components[0].mean.x = f64::NAN;
    let e = TransmitterMap::new(2.0, t).unwrap_err();
    assert_eq!(e.path, "transmitters[0].components[0].mean");
    assert_eq!(e.kind, MapErrorKind::NotFinite);
}

fn spd(a: [f64; 6]) -> Matrix3<f64> {
    let l = Matrix3::new(
        a[0].abs() + 0.05,
        0.0,
        0.0,
        a[1],
        a[2].abs() + 0.05,
        0.0,
        a[3],
        a[4],
        a[5].abs() + 0.05,
    );
    l * l.transpose()
}

prop_compose! {
    fn arb_transmitter(i: usize)(
        comps in prop::collection::vec((0.05f64..1.0, prop::array::uniform3(-80.0f64..80.0), prop::array::uniform6(-2.0f64..2.0)), 1..5),
        existence in 0.0f64..=1.0,
        reliability in 0.0f64..500.0,
        cells in prop::collection::btree_map((-30i32..30, -30i32..30), (0.0f64..50.0, 0.0f64..50.0), 0..30),
    ) -> Transmitter {
        let total: f64 = comps.iter().map(|c| c.0).sum();
        Transmitter {
            id: format!("t{i}"),
            components: comps.into_iter().map(|(w, m, c)| Component { weight: w / total, mean: Vector3::from(m), cov: spd(c) }).collect(),
            existence,
            reliability_m: reliability,
            visibility: cells.into_iter().map(|((q, r), (a, b))| (HexCell { q, r }, Beta { alpha: a, beta: b })).collect(),
        }
    }
}

fn arb_map() -> impl Strategy<Value = TransmitterMap> {
    (0.5f64..5.0, prop::collection::vec(0..1usize, 0..12)).prop_flat_map(|(size, v)| {
        let ts: Vec<_> = (0..v.len()).map(arb_transmitter).collect();
        ts.prop_map(move |ts| TransmitterMap::new(size, ts).unwrap())
    })
}

fn total_counts(m: &TransmitterMap) -> (f64, f64) {
    m.transmitters()
        .iter()
        .flat_map(|t| t.visibility.values())
        .fold((0.0, 0.0), |acc, b| (acc.0 + b.alpha, acc.1 + b.beta))
}

proptest! {
    #[test]
    fn json_roundtrip_random(m in arb_map()) {
        let back = TransmitterMap::from_json(&serde_json::to_string(&m).unwrap()).unwrap();
        prop_assert_eq!(back, m);
    }

    #[test]
    fn transform_then_inverse_restores(m in arb_map(), angle in -PI..PI, tx in -500.0f64..500.0, ty in -500.0f64..500.0) {
        let iso = Isometry2::new(nalgebra::Vector2::new(tx, ty), angle);
        let there = m.transformed(&iso);
        // still a valid map (re-validate through JSON)
        let there = TransmitterMap::from_json(&serde_json::to_string(&there).unwrap()).unwrap();
        let back = there.transformed(&iso.inverse());
        for (a, b) in m.transmitters().iter().zip(back.transmitters()) {
            prop_assert_eq!(&a.id, &b.id);
            for (ca, cb) in a.components.iter().zip(&b.components) {
                prop_assert!((ca.mean - cb.mean).norm() < 1e-9 * (1.0 + ca.mean.norm()));
                prop_assert!((ca.cov - cb.cov).abs().max() < 1e-9 * (1.0 + ca.cov.abs().max()));
                prop_assert_eq!(ca.weight, cb.weight);
            }
        }
        let (a0, b0) = total_counts(&m);
        let (a1, b1) = total_counts(&back);
        prop_assert!((a0 - a1).abs() < 1e-9 * (1.0 + a0) && (b0 - b1).abs() < 1e-9 * (1.0 + b0));
        let (a2, b2) = total_counts(&there);
        prop_assert!((a0 - a2).abs() < 1e-9 * (1.0 + a0) && (b0 - b2).abs() < 1e-9 * (1.0 + b0));
    }
}

#[test]
fn transform_moves_means_and_rotates_covariances() {
    let m = sample_map();
    let iso = Isometry2::new(nalgebra::Vector2::new(1.0, 2.0), PI / 2.0);
    let t = m.transformed(&iso);
    let c = &t.transmitters()[1].components[0];
    // (−5, 7.25) rotated by 90° → (−7.25, −5), then + (1, 2)
    assert!((c.mean.x - (-6.25)).abs() < 1e-12 && (c.mean.y - (-3.0)).abs() < 1e-12);
    assert_eq!(c.mean.z, 3.5);
    // diag(0.5, 0.4) rotated by 90° swaps the variances
    assert!((c.cov[(0, 0)] - 0.4).abs() < 1e-12 && (c.cov[(1, 1)] - 0.5).abs() < 1e-12);
    assert!(wrap_angle(iso.rotation.angle() - PI / 2.0).abs() < 1e-12);
}

//! Calibration of the matcher's acceptance test on dense random fields without visibility
//! (`matching::fields`): unrelated pairs must be refused (at most 1 in 1,000 accepted over
//! 5,000 pairs); related pairs (≥ 6 shared, up to 50 % of either map unshared, the same noise)
//! recovered with the right transform in ≥ 99 % of 1,000 cases. The false-accept rate against
//! the number of transmitters is plotted by `echomap-agent experiment coincidence`.

use echomap_shared::matching::fields::{FieldPair, related, small_overlap, unrelated};
use echomap_shared::matching::{MatchConfig, MatchDecision, match_maps};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use std::collections::BTreeMap;

#[test]
fn unrelated_dense_fields_are_refused() {
    let cases = 5000u64;
    let accepted: Vec<(u64, usize, usize, usize)> = (0..cases)
        .into_par_iter()
        .filter_map(|k| {
            let mut rng = ChaCha8Rng::seed_from_u64(0x0C01_C1DE ^ k);
            let f = unrelated(&mut rng);
            let r = match_maps(&f.user, &f.prior, &MatchConfig::default(), &mut rng);
            r.accepted
                .then_some((k, f.user.len(), f.prior.len(), r.inliers))
        })
        .collect();
    eprintln!(
        "unrelated dense fields: {}/{cases} accepted (case, user, prior, inliers): {accepted:?}",
        accepted.len()
    );
    assert!(
        accepted.len() as f64 <= cases as f64 / 1000.0,
        "{} of {cases} unrelated pairs accepted: {accepted:?}",
        accepted.len()
    );
}

#[test]
fn related_dense_fields_are_recovered() {
    let cases = 1000u64;
    let missed: Vec<(u64, usize, usize, f64, usize, bool)> = (0..cases)
        .into_par_iter()
        .filter_map(|k| {
            let mut rng = ChaCha8Rng::seed_from_u64(0x5A_3E ^ (k << 8));
            let f = related(&mut rng);
            let r = match_maps(&f.user, &f.prior, &MatchConfig::default(), &mut rng);
            (!f.recovered(&r)).then_some((k, f.user.len(), f.shared, f.std, r.inliers, r.accepted))
        })
        .collect();
    eprintln!(
        "related dense fields: {}/{cases} recovered; missed (case, user, shared, std, inliers, accepted): {missed:?}",
        cases as usize - missed.len()
    );
    assert!(
        missed.len() as f64 <= 0.01 * cases as f64,
        "{} of {cases} related pairs missed",
        missed.len()
    );
}

#[test]
fn maps_that_share_too_little_are_undecided_and_never_merged() {
    // (decision, whether the user map is small: 3–4 transmitters, all shared)
    let run = |cases: u64, seed: u64, draw: fn(&mut ChaCha8Rng) -> FieldPair| {
        (0..cases)
            .into_par_iter()
            .map(|k| {
                let mut rng = ChaCha8Rng::seed_from_u64(seed ^ (k << 12));
                let f = draw(&mut rng);
                let r = match_maps(&f.user, &f.prior, &MatchConfig::default(), &mut rng);
                (r.decision, f.user.len() <= 4)
            })
            .collect::<Vec<_>>()
    };
    let count = |all: &[(MatchDecision, bool)], small: bool| {
        let mut c: BTreeMap<&'static str, usize> = BTreeMap::new();
        for (d, _) in all.iter().filter(|(_, s)| *s == small) {
            *c.entry(d.as_str()).or_default() += 1;
        }
        c
    };
    let few = run(1000, 0x5A11, small_overlap);
    let unrelated = run(1000, 0xD1FF, unrelated);
    let (small_user, edge, unrelated) = (
        count(&few, true),
        count(&few, false),
        count(&unrelated, false),
    );
    eprintln!(
        "3–4 user transmitters, all shared: {small_user:?}; a user field reaching 3–4 shared transmitters into the prior: {edge:?}; unrelated: {unrelated:?}"
    );
    // too little overlap is never merged; a user map too small to decide is called undecided
    for c in [&small_user, &edge, &unrelated] {
        assert_eq!(c.get("accepted"), None, "{c:?}");
    }
    assert_eq!(small_user.len(), 1, "{small_user:?}");
    assert!(small_user.contains_key("undecided"), "{small_user:?}");
    // a refusal of a large map says why: most dense unrelated maps over one area are
    // contradicted under every transform found (rejected); the rest might overlap a little
    let n: usize = unrelated.values().sum();
    assert!(
        unrelated.get("rejected").copied().unwrap_or(0) as f64 >= 0.5 * n as f64,
        "{unrelated:?}"
    );
}

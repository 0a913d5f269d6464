//! Calibration of the matcher's acceptance test on dense random fields without visibility
//! (`matching::fields`): unrelated pairs must be refused (at most 1 in 1,000 accepted over
//! 5,000 pairs); related pairs (≥ 6 shared, up to 50 % of either map unshared, the same noise)
//! recovered with the right transform in ≥ 99 % of 1,000 cases. The false-accept rate against
//! the number of transmitters is plotted by `echomap-agent experiment coincidence`.

use echomap_shared::matching::fields::{related, unrelated};
use echomap_shared::matching::{MatchConfig, match_maps};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

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

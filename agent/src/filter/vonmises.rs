//! Von Mises sampling by the Best–Fisher (1979) rejection algorithm, for the heading noise
//! of the user motion model (Gentner et al. 2016 eq. 17). For very large κ the distribution is normal
//! with std 1/√κ to machine precision and that is sampled directly.

use echomap_shared::wrap_angle;
use rand::{Rng, RngExt};
use rand_distr::StandardNormal;
use std::f64::consts::PI;

/// Draws from VM(mu, kappa); kappa = 0 is uniform on the circle.
pub fn sample(mu: f64, kappa: f64, rng: &mut impl Rng) -> f64 {
    if kappa < 1e-8 {
        return wrap_angle(rng.random_range(-PI..PI));
    }
    if kappa > 1e6 {
        let n: f64 = rng.sample(StandardNormal);
        return wrap_angle(mu + n / kappa.sqrt());
    }
    let tau = 1.0 + (1.0 + 4.0 * kappa * kappa).sqrt();
    let rho = (tau - (2.0 * tau).sqrt()) / (2.0 * kappa);
    let r = (1.0 + rho * rho) / (2.0 * rho);
    loop {
        let u1: f64 = rng.random();
        let u2: f64 = rng.random();
        let u3: f64 = rng.random();
        let z = (PI * u1).cos();
        let f = (1.0 + r * z) / (r + z);
        let c = kappa * (r - f);
        if c * (2.0 - c) - u2 > 0.0 || (c / u2).ln() + 1.0 - c >= 0.0 {
            let theta = if u3 > 0.5 {
                f.clamp(-1.0, 1.0).acos()
            } else {
                -f.clamp(-1.0, 1.0).acos()
            };
            return wrap_angle(mu + theta);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn std_is_one_over_sqrt_kappa_for_concentrated_distributions() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for kappa in [100.0, 4000.0, 1e5, 1e7] {
            let n = 20_000;
            let xs: Vec<f64> = (0..n).map(|_| sample(0.3, kappa, &mut rng) - 0.3).collect();
            let mean = xs.iter().sum::<f64>() / n as f64;
            let std = (xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64).sqrt();
            let want = 1.0 / f64::sqrt(kappa);
            assert!(
                (std / want - 1.0).abs() < 0.05,
                "kappa {kappa}: std {std}, want {want}"
            );
            assert!(mean.abs() < 5.0 * want / (n as f64).sqrt() + 1e-12);
        }
    }

    #[test]
    fn wide_distribution_matches_the_mean_resultant_length() {
        // E[cos θ] = I1(κ)/I0(κ); for κ = 1 that is 0.44639.
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        let n = 50_000;
        let m: f64 = (0..n)
            .map(|_| sample(0.0, 1.0, &mut rng).cos())
            .sum::<f64>()
            / n as f64;
        assert!((m - 0.44639).abs() < 0.01, "{m}");
    }
}

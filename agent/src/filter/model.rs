//! Measurement model (Gentner et al. 2016 eq. 19–21, AoA convention of DESIGN.md) and the
//! initialization of a new transmitter from its first measurement (Gentner et al. 2016 §4.3).

use super::config::{BPrior, FilterConfig};
use super::srckf::SqrtGaussian;
use echomap_shared::fastmath::fast_atan2;
use echomap_shared::wrap_angle;
use nalgebra::{Matrix3, Vector1, Vector2, Vector3};

/// User pose of one particle: position, heading (rad) and speed (m/s).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub x: f64,
    pub y: f64,
    pub heading: f64,
    pub speed: f64,
}

/// Range + AoA of a transmitter state seen from `pose`: `d = ‖p_tx − p_u‖ + b`,
/// `θ = atan2(Δy, Δx) − heading` (wrapped).
#[inline(always)]
pub fn h_toa_aoa(pose: &Pose, x: &Vector3<f64>) -> Vector2<f64> {
    let (dx, dy) = (x.x - pose.x, x.y - pose.y);
    // sqrt of the sum of squares: libm's hypot guards overflow we cannot have here and is
    // several times slower (it dominated the profile).
    Vector2::new(
        (dx * dx + dy * dy).sqrt() + x.z,
        wrap_angle(fast_atan2(dy, dx) - pose.heading),
    )
}

/// [`h_toa_aoa`] at the six cubature points of `srckf::SqrtGaussian::cubature_points`.
/// The points `m ± √3·S·e₃` move b alone (the factor S is lower triangular, its third column
/// is `(0, 0, s₃₃)`), so they share one distance in the plane and one angle: five square
/// roots and arctangents instead of six, every image the same to the bit.
#[inline(always)]
pub fn toa_aoa_images(pose: &Pose, pts: &[Vector3<f64>; 6]) -> [Vector2<f64>; 6] {
    debug_assert!(pts[2].x == pts[5].x && pts[2].y == pts[5].y);
    let (dx, dy) = (pts[2].x - pose.x, pts[2].y - pose.y);
    let planar = (dx * dx + dy * dy).sqrt();
    let angle = wrap_angle(fast_atan2(dy, dx) - pose.heading);
    [
        h_toa_aoa(pose, &pts[0]),
        h_toa_aoa(pose, &pts[1]),
        Vector2::new(planar + pts[2].z, angle),
        h_toa_aoa(pose, &pts[3]),
        h_toa_aoa(pose, &pts[4]),
        Vector2::new(planar + pts[5].z, angle),
    ]
}

/// [`h_toa`] at the six cubature points, sharing the planar distance of the two points that
/// differ from the mean in b alone (see [`toa_aoa_images`]).
#[inline(always)]
pub fn toa_images(pose: &Pose, pts: &[Vector3<f64>; 6]) -> [Vector1<f64>; 6] {
    let (dx, dy) = (pts[2].x - pose.x, pts[2].y - pose.y);
    let planar = (dx * dx + dy * dy).sqrt();
    [
        h_toa(pose, &pts[0]),
        h_toa(pose, &pts[1]),
        Vector1::new(planar + pts[2].z),
        h_toa(pose, &pts[3]),
        h_toa(pose, &pts[4]),
        Vector1::new(planar + pts[5].z),
    ]
}

#[inline(always)]
pub fn h_toa(pose: &Pose, x: &Vector3<f64>) -> Vector1<f64> {
    let (dx, dy) = (x.x - pose.x, x.y - pose.y);
    Vector1::new((dx * dx + dy * dy).sqrt() + x.z)
}

#[inline(always)]
pub fn residual_toa_aoa(a: &Vector2<f64>, b: &Vector2<f64>) -> Vector2<f64> {
    Vector2::new(a.x - b.x, wrap_angle(a.y - b.y))
}

#[inline(always)]
pub fn residual_toa(a: &Vector1<f64>, b: &Vector1<f64>) -> Vector1<f64> {
    a - b
}

/// One weighted component of a transmitter mixture.
#[derive(Debug, Clone, PartialEq)]
pub struct Comp {
    pub weight: f64,
    pub g: SqrtGaussian,
}

/// Mean and covariance of a mixture's state `[x, y, b]` (`mixture::moments` of the shared
/// crate); None for an empty or weightless mixture.
pub fn mixture_moments(comps: &[Comp]) -> Option<(Vector3<f64>, Matrix3<f64>)> {
    echomap_shared::mixture::moments(
        &comps
            .iter()
            .map(|c| echomap_shared::mixture::Component::new(c.weight, c.g.mean, c.g.cov()))
            .collect::<Vec<_>>(),
    )
}

fn outer(v: &Vector3<f64>) -> Matrix3<f64> {
    v * v.transpose()
}

/// Components of a new transmitter from its first measurement `(d, θ)` at `pose`.
///
/// With AoA, the transmitter lies on the ray from the user along `heading + θ` at a range
/// `r ∈ (0, d]` with `b = d − r`: components are spread along that ray (their count grows
/// with d), each elongated along the ray direction in (x, y, b) space — moving along the ray
/// by δ changes b by −δ — and `r·σ_θ` wide across it. ToA-only: rings of components around
/// the user. With a zero-b prior, the range is d itself.
pub fn initialize(
    cfg: &FilterConfig,
    pose: &Pose,
    d: f64,
    aoa: Option<f64>,
    sigma_d: f64,
    sigma_a: f64,
) -> Vec<Comp> {
    let eps = 1e-6;
    let ranges: Vec<(f64, f64)> = match cfg.b_prior {
        BPrior::Zero { .. } => vec![(d, 0.0)],
        BPrior::Uniform => {
            let n = ((d / cfg.init_spacing_m).ceil() as usize).clamp(1, cfg.init_max_components);
            let dr = d / n as f64;
            (0..n).map(|k| ((k as f64 + 0.5) * dr, dr / 2.0)).collect()
        }
    };
    let angles: Vec<(f64, f64)> = match aoa {
        Some(a) => vec![(pose.heading + a, sigma_a)],
        None => {
            // A ring: enough directions to cover the circle at the mean range, within budget.
            let r_mid = ranges[ranges.len() / 2].0;
            let budget = (cfg.init_max_components * 2 / ranges.len().max(1)).max(4);
            let n = ((2.0 * std::f64::consts::PI * r_mid / cfg.init_spacing_m).ceil() as usize)
                .clamp(4, budget.max(4));
            let step = 2.0 * std::f64::consts::PI / n as f64;
            (0..n).map(|k| (k as f64 * step, step / 2.0)).collect()
        }
    };
    let b_std = match cfg.b_prior {
        BPrior::Zero { std_m } => std_m.max(eps),
        BPrior::Uniform => sigma_d,
    };
    let mut comps = Vec::with_capacity(ranges.len() * angles.len());
    for &(phi, s_phi) in &angles {
        let u = Vector2::new(phi.cos(), phi.sin());
        let along = Vector3::new(u.x, u.y, -1.0);
        let across = Vector3::new(-u.y, u.x, 0.0);
        let radial = Vector3::new(u.x, u.y, 0.0);
        for &(r, s_r) in &ranges {
            let mean = Vector3::new(pose.x + r * u.x, pose.y + r * u.y, (d - r).max(0.0));
            let s_across = (r * s_phi).max(0.05);
            let mut cov = outer(&across) * s_across.powi(2) + Matrix3::identity() * eps;
            match cfg.b_prior {
                // b fixed near 0: the range error is radial in x/y
                BPrior::Zero { .. } => {
                    cov += outer(&radial) * sigma_d.powi(2) + outer(&Vector3::z()) * b_std.powi(2);
                }
                BPrior::Uniform => {
                    cov += outer(&along) * s_r.powi(2) + outer(&Vector3::z()) * b_std.powi(2);
                }
            }
            if let Some(g) = SqrtGaussian::from_cov(mean, &cov) {
                comps.push(Comp { weight: 1.0, g });
            }
        }
    }
    let n = comps.len() as f64;
    for c in &mut comps {
        c.weight = 1.0 / n;
    }
    comps
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shared_images_are_the_measurement_function_at_every_point() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut u = || rng.random::<f64>() * 40.0 - 20.0;
        for _ in 0..1000 {
            let pose = Pose {
                x: u(),
                y: u(),
                heading: u() / 6.0,
                speed: 1.0,
            };
            let cov = Matrix3::new(u(), u(), u(), u(), u(), u(), u(), u(), u());
            let cov = cov * cov.transpose() * 0.01 + Matrix3::identity() * 1e-4;
            let g = SqrtGaussian::from_cov(Vector3::new(u(), u(), u().abs()), &cov).unwrap();
            let pts = g.cubature_points();
            let shared = toa_aoa_images(&pose, &pts);
            let shared_toa = toa_images(&pose, &pts);
            for j in 0..6 {
                assert_eq!(shared[j], h_toa_aoa(&pose, &pts[j]));
                assert_eq!(shared_toa[j], h_toa(&pose, &pts[j]));
            }
        }
    }

    #[test]
    fn initial_components_reproduce_the_measurement() {
        let cfg = FilterConfig::default();
        let pose = Pose {
            x: 1.0,
            y: 2.0,
            heading: 0.7,
            speed: 1.0,
        };
        let comps = initialize(&cfg, &pose, 20.0, Some(-0.4), 0.1, 0.03);
        assert_eq!(comps.len(), 10);
        let total: f64 = comps.iter().map(|c| c.weight).sum();
        assert!((total - 1.0).abs() < 1e-12);
        for c in &comps {
            let z = h_toa_aoa(&pose, &c.g.mean);
            assert!(
                // the fast atan2 is exact to 2e-8 rad
                (z.x - 20.0).abs() < 1e-9 && wrap_angle(z.y + 0.4).abs() < 1e-7,
                "{z:?}"
            );
            assert!(c.g.mean.z >= 0.0);
        }
        // ToA-only: rings, every mean at the right distance
        let comps = initialize(&cfg, &pose, 20.0, None, 0.1, 0.03);
        assert!(comps.len() >= 10);
        assert!(
            comps
                .iter()
                .all(|c| (h_toa(&pose, &c.g.mean).x - 20.0).abs() < 1e-9)
        );
        // zero-b prior: one component at range d, b ≈ 0
        let cfg = FilterConfig {
            b_prior: BPrior::Zero { std_m: 0.05 },
            ..FilterConfig::default()
        };
        let comps = initialize(&cfg, &pose, 20.0, Some(-0.4), 0.1, 0.03);
        assert_eq!(comps.len(), 1);
        assert!(comps[0].g.mean.z.abs() < 1e-12);
    }
}

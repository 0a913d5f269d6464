//! Map matching: the rigid transform `map_from_agent` and the transmitter correspondences
//! between a user map (agent frame) and a prior map (map frame), Ulmschneider et al. 2021 §III, Fig. 3.
//!
//! RANSAC over minimal samples of three transmitters. Beyond the paper's random draw from
//! both maps, the prior triple is found from the user triple by pairwise-distance
//! consistency (eq. 17 as a search): prior pairs whose distance agrees with the user pair's
//! within `distance_tolerance_m`, nearest first, both orderings; the third member is looked
//! up where the first two pairs put it. Pairs are gated by the frame-invariant clock offset
//! b. Each consistent triple gives a least-squares rigid transform (2D Kabsch without scale:
//! a proper rotation, so a mirror image never fits). LO-RANSAC: a hypothesis that does at
//! least as well as the best so far on a single pass is locally optimized — every pair
//! inside the χ² gate re-collected one-to-one and the transform re-estimated until the set is
//! stable. Hypotheses are scored by eq. 18: the location term p(H) — the inliers'
//! MSAC's truncated quadratic ([`LocationScore::Msac`], default) or the log-likelihood ratio
//! against clutter with a covariance scale fitted per hypothesis ([`LocationScore::Likelihood`]) —
//! plus the visibility term log p(M|H) — the user's transformed
//! visibility counts scored under the prior's Beta distributions (Beta-binomial), as a
//! log-likelihood ratio against an uninformative Beta(1, 1). The number of user triples drawn
//! adapts to the best inlier ratio and `confidence`. The chosen hypothesis is accepted by an
//! a-contrario test on its residuals (`false_alarms`, in the manner of ORSA).
//!
//! Complexity: O(P²) once for the prior pairs, binned by distance; per drawn triple O(k log k)
//! for the k prior pairs of consistent distance (at most `max_hypotheses_per_sample` tried), O(U) for each single-pass check with a uniform
//! grid of prior means, and O(U·iterations) for each local optimization.

use crate::hexgrid::{HexCell, HexGrid};
use crate::map::{Transmitter, TransmitterMap, transform_visibility};
use nalgebra::{Isometry2, Matrix2, Matrix3, Point2, Vector2, Vector3};
use rand::{Rng, RngExt};

mod config;
pub mod fields;
mod index;
mod ransac;
mod registration;
mod score;
mod significance;
mod special;

pub use config::*;
use index::*;
pub use ransac::*;
pub use registration::*;
pub use score::*;
use significance::*;
pub use special::*;

//! The transmitter map, `echomap.map.v1` — the contract between agents and the map server.
//!
//! A map holds (virtual) transmitters, each a Gaussian mixture over `[x, y, b]` (Gentner et al. 2016
//! §4.3), an existence probability (Ulmschneider et al. 2021 eq. 20/25), a reliability distance (eq. 21/24)
//! and hexagonal visibility counters (eq. 11–12). A [`TransmitterMap`] can only be built
//! through validation ([`TransmitterMap::new`] or deserialization), so every value past the
//! boundary is finite, every covariance symmetric positive-definite, every weight vector
//! normalized, and a rejected map names the field at fault.
//!
//! Visibility: `alpha`/`beta` are the *evidence counts* of eq. 12 — how often the transmitter
//! was seen / not seen from the cell (C and C̄) — without the prior pseudo-counts ν, ν̄.
//! Consumers add their own prior when they form the Beta distribution; merging adds counts
//! (eq. 26) without double-counting a prior.

use crate::geometry::rotation;
use crate::hexgrid::{HexCell, HexGrid};
use crate::mixture::{Component, symmetrize};
use nalgebra::{Isometry2, Matrix3, Point2, Vector3};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashSet};
use thiserror::Error;

/// the `format` of a transmitter map
pub const MAP_FORMAT: &str = "echomap.map.v1";
/// Hexagon circumradius of visibility grids unless a map says otherwise (metres).
pub const DEFAULT_HEX_SIZE_M: f64 = 2.0;
/// most transmitters a map may hold
pub const MAX_TRANSMITTERS: usize = 10_000;
/// most mixture components a transmitter may hold
pub const MAX_COMPONENTS: usize = 64;
/// most visibility cells a map may hold, over all transmitters
pub const MAX_VISIBILITY_CELLS: usize = 100_000;
/// longest transmitter id (characters)
pub const MAX_ID_LEN: usize = 128;
/// Tolerance on `|Σ weights − 1|`.
pub const WEIGHT_SUM_TOLERANCE: f64 = 1e-6;
/// Relative tolerance on covariance asymmetry `|Pᵢⱼ − Pⱼᵢ| ≤ tol·max|P|`.
pub const SYMMETRY_TOLERANCE: f64 = 1e-9;

/// What is wrong with a map, and where (`path` is a JSON-pointer-like location such as
/// `transmitters[3].components[1].cov`).
#[derive(Debug, Clone, PartialEq, Error)]
#[error("{path}: {kind}")]
pub struct MapError {
    /// the field at fault
    pub path: String,
    /// what is wrong with it
    pub kind: MapErrorKind,
}

/// What is wrong with a field of a map.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum MapErrorKind {
    /// the `format` is not `echomap.map.v1`
    #[error("unsupported format {0:?}, expected \"echomap.map.v1\"")]
    Format(String),
    /// a number is NaN or infinite
    #[error("value is not a finite number")]
    NotFinite,
    /// a number that must be positive is not
    #[error("must be > 0, got {0}")]
    NotPositive(f64),
    /// a number that must not be negative is
    #[error("must be ≥ 0, got {0}")]
    Negative(f64),
    /// a probability outside [0, 1]
    #[error("must lie in [0, 1], got {0}")]
    NotProbability(f64),
    /// mixture weights that do not sum to 1
    #[error("weights sum to {0}, expected 1 (±1e-6)")]
    WeightSum(f64),
    /// a covariance that is not symmetric
    #[error("covariance is not symmetric")]
    NotSymmetric,
    /// a covariance that is not positive definite
    #[error("covariance is not positive definite")]
    NotPositiveDefinite,
    /// two transmitters with the same id
    #[error("duplicate id {0:?}")]
    DuplicateId(String),
    /// a visibility cell given twice (axial q, r)
    #[error("duplicate visibility cell (q={q}, r={r})")]
    DuplicateCell {
        /// axial column
        q: i32,
        /// axial row
        r: i32,
    },
    /// an empty, overlong or unprintable id
    #[error("id must be 1–128 printable characters")]
    BadId,
    /// more entries than the format allows
    #[error("too many entries: {count} > limit {limit}")]
    TooMany {
        /// how many there are
        count: usize,
        /// how many the format allows
        limit: usize,
    },
    /// a list that must not be empty is
    #[error("must not be empty")]
    Empty,
}

fn err(path: impl Into<String>, kind: MapErrorKind) -> MapError {
    MapError {
        path: path.into(),
        kind,
    }
}

/// Beta-distribution evidence of one transmitter's visibility from one hexagon.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Beta {
    /// times seen from this cell (C of eq. 12)
    pub alpha: f64,
    /// times not seen from this cell (C̄ of eq. 12)
    pub beta: f64,
}

/// One (virtual) transmitter.
#[derive(Debug, Clone, PartialEq)]
pub struct Transmitter {
    /// unique id within the map
    pub id: String,
    /// Gaussian mixture over `[x, y, b]`
    pub components: Vec<Component>,
    /// belief that the transmitter exists, in [0, 1]
    pub existence: f64,
    /// distance walked while it was visible (m)
    pub reliability_m: f64,
    /// Beta evidence of being seen, per hexagon
    pub visibility: BTreeMap<HexCell, Beta>,
}

impl Transmitter {
    /// Mixture mean and covariance of the transmitter state.
    pub fn moments(&self) -> (Vector3<f64>, Matrix3<f64>) {
        crate::mixture::moments(&self.components).expect("validated mixture is non-empty")
    }
}

/// A validated transmitter map. Construct with [`TransmitterMap::new`] or by deserializing.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "wire::MapDoc", into = "wire::MapDoc")]
pub struct TransmitterMap {
    hex_size_m: f64,
    transmitters: Vec<Transmitter>,
}

impl TransmitterMap {
    /// Validates and builds a map.
    pub fn new(hex_size_m: f64, transmitters: Vec<Transmitter>) -> Result<Self, MapError> {
        validate(hex_size_m, &transmitters)?;
        Ok(TransmitterMap {
            hex_size_m,
            transmitters,
        })
    }

    /// An empty map with the given hex size.
    pub fn empty(hex_size_m: f64) -> Result<Self, MapError> {
        Self::new(hex_size_m, Vec::new())
    }

    /// circumradius of the visibility grid's hexagons (m)
    pub fn hex_size_m(&self) -> f64 {
        self.hex_size_m
    }

    /// the transmitters, in id order
    pub fn transmitters(&self) -> &[Transmitter] {
        &self.transmitters
    }

    /// the transmitters, by value
    pub fn into_transmitters(self) -> Vec<Transmitter> {
        self.transmitters
    }

    /// the visibility grid
    pub fn grid(&self) -> HexGrid {
        HexGrid::new(self.hex_size_m)
    }

    /// number of transmitters
    pub fn len(&self) -> usize {
        self.transmitters.len()
    }

    /// whether the map has no transmitter
    pub fn is_empty(&self) -> bool {
        self.transmitters.is_empty()
    }

    /// Parses and validates a JSON document.
    pub fn from_json(text: &str) -> Result<Self, ParseError> {
        let doc: wire::MapDoc =
            serde_json::from_str(text).map_err(|e| ParseError::Syntax(e.to_string()))?;
        Self::from_doc(doc).map_err(ParseError::Invalid)
    }

    /// Validates an already parsed wire document.
    pub fn from_doc(doc: wire::MapDoc) -> Result<Self, MapError> {
        wire::convert(doc)
    }

    /// The map as indented `echomap.map.v1` JSON.
    pub fn to_json_pretty(&self) -> String {
        serde_json::to_string_pretty(self).expect("a validated map always serializes")
    }

    /// The map expressed in another frame: `to_from` maps this map's coordinates into the
    /// target frame. Means get `R·p + t` on x/y, covariances `R·P·Rᵀ` on the x/y block (and
    /// `R·P_xb` on the cross terms); `b` is frame-invariant. Visibility cells are re-binned by
    /// their transformed centres; counts of cells landing together are added.
    pub fn transformed(&self, to_from: &Isometry2<f64>) -> TransmitterMap {
        let grid = self.grid();
        let transmitters = self
            .transmitters
            .iter()
            .map(|t| transform_transmitter(t, to_from, &grid))
            .collect();
        // Rigid motions keep SPD-ness and finiteness of finite inputs, so this stays valid.
        TransmitterMap {
            hex_size_m: self.hex_size_m,
            transmitters,
        }
    }
}

/// Applies a rigid transform to one Gaussian component over `[x, y, b]`.
pub fn transform_component(c: &Component, to_from: &Isometry2<f64>) -> Component {
    let angle = to_from.rotation.angle();
    let r2 = rotation(angle);
    let mut r3 = Matrix3::identity();
    r3.fixed_view_mut::<2, 2>(0, 0).copy_from(&r2);
    let p = to_from * Point2::new(c.mean.x, c.mean.y);
    Component {
        weight: c.weight,
        mean: Vector3::new(p.x, p.y, c.mean.z),
        cov: symmetrize(&(r3 * c.cov * r3.transpose())),
    }
}

/// Re-bins visibility counts into the same-size grid of the target frame.
pub fn transform_visibility(
    vis: &BTreeMap<HexCell, Beta>,
    to_from: &Isometry2<f64>,
    grid: &HexGrid,
) -> BTreeMap<HexCell, Beta> {
    let mut out: BTreeMap<HexCell, Beta> = BTreeMap::new();
    for (cell, b) in vis {
        let target = grid.cell_of(&(to_from * grid.centre(*cell)));
        let e = out.entry(target).or_insert(Beta {
            alpha: 0.0,
            beta: 0.0,
        });
        e.alpha += b.alpha;
        e.beta += b.beta;
    }
    out
}

fn transform_transmitter(t: &Transmitter, to_from: &Isometry2<f64>, grid: &HexGrid) -> Transmitter {
    Transmitter {
        id: t.id.clone(),
        components: t
            .components
            .iter()
            .map(|c| transform_component(c, to_from))
            .collect(),
        existence: t.existence,
        reliability_m: t.reliability_m,
        visibility: transform_visibility(&t.visibility, to_from, grid),
    }
}

fn check_finite(path: &str, v: f64) -> Result<(), MapError> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(err(path, MapErrorKind::NotFinite))
    }
}

/// Validates one covariance: finite, symmetric, positive definite.
pub fn validate_cov(path: &str, cov: &Matrix3<f64>) -> Result<(), MapError> {
    if cov.iter().any(|v| !v.is_finite()) {
        return Err(err(path, MapErrorKind::NotFinite));
    }
    let scale = cov.abs().max().max(f64::MIN_POSITIVE);
    for i in 0..3 {
        for j in (i + 1)..3 {
            if (cov[(i, j)] - cov[(j, i)]).abs() > SYMMETRY_TOLERANCE * scale {
                return Err(err(path, MapErrorKind::NotSymmetric));
            }
        }
    }
    if cov.cholesky().is_none() || (0..3).any(|i| cov[(i, i)] <= 0.0) {
        return Err(err(path, MapErrorKind::NotPositiveDefinite));
    }
    Ok(())
}

/// What [`fit_to_limits`] left out.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Pruned {
    /// transmitters dropped
    pub transmitters: usize,
    /// visibility cells dropped
    pub cells: usize,
}

/// Brings transmitters within the format's limits on their number ([`MAX_TRANSMITTERS`]) and
/// on the visibility cells over all of them ([`MAX_VISIBILITY_CELLS`]), keeping what carries
/// the most evidence: the transmitters of largest existence × reliability, then the cells with
/// the most observations (α + β), ties broken by position so the result is deterministic.
/// Transmitters within the limits are returned unchanged.
pub fn fit_to_limits(transmitters: &mut Vec<Transmitter>) -> Pruned {
    let mut pruned = Pruned::default();
    if transmitters.len() > MAX_TRANSMITTERS {
        let mut order: Vec<usize> = (0..transmitters.len()).collect();
        let worth = |t: &Transmitter| t.existence * t.reliability_m.max(1e-9);
        order.sort_by(|&a, &b| {
            worth(&transmitters[b])
                .total_cmp(&worth(&transmitters[a]))
                .then(a.cmp(&b))
        });
        let mut keep = vec![false; transmitters.len()];
        for &i in &order[..MAX_TRANSMITTERS] {
            keep[i] = true;
        }
        pruned.transmitters = transmitters.len() - MAX_TRANSMITTERS;
        let mut k = 0;
        transmitters.retain(|_| {
            k += 1;
            keep[k - 1]
        });
    }
    let total: usize = transmitters.iter().map(|t| t.visibility.len()).sum();
    if total > MAX_VISIBILITY_CELLS {
        let mut cells: Vec<(f64, usize, HexCell)> = transmitters
            .iter()
            .enumerate()
            .flat_map(|(i, t)| {
                t.visibility
                    .iter()
                    .map(move |(c, b)| (b.alpha + b.beta, i, *c))
            })
            .collect();
        cells.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
        for &(_, i, c) in &cells[MAX_VISIBILITY_CELLS..] {
            transmitters[i].visibility.remove(&c);
        }
        pruned.cells = total - MAX_VISIBILITY_CELLS;
    }
    pruned
}

fn validate(hex_size_m: f64, transmitters: &[Transmitter]) -> Result<(), MapError> {
    check_finite("hex_size_m", hex_size_m)?;
    if hex_size_m <= 0.0 {
        return Err(err("hex_size_m", MapErrorKind::NotPositive(hex_size_m)));
    }
    if transmitters.len() > MAX_TRANSMITTERS {
        return Err(err(
            "transmitters",
            MapErrorKind::TooMany {
                count: transmitters.len(),
                limit: MAX_TRANSMITTERS,
            },
        ));
    }
    let total_cells: usize = transmitters.iter().map(|t| t.visibility.len()).sum();
    if total_cells > MAX_VISIBILITY_CELLS {
        return Err(err(
            "transmitters[*].visibility",
            MapErrorKind::TooMany {
                count: total_cells,
                limit: MAX_VISIBILITY_CELLS,
            },
        ));
    }
    let mut ids = HashSet::with_capacity(transmitters.len());
    for (ti, t) in transmitters.iter().enumerate() {
        let at = |w: Where| format!("transmitters[{ti}]{w}");
        if t.id.is_empty() || t.id.len() > MAX_ID_LEN || t.id.chars().any(|c| c.is_control()) {
            return Err(err(at(Where::Id), MapErrorKind::BadId));
        }
        if !ids.insert(t.id.as_str()) {
            return Err(err(at(Where::Id), MapErrorKind::DuplicateId(t.id.clone())));
        }
        // the path is only formatted for an error: this runs on every merge of the server
        check_transmitter(t).map_err(|(w, kind)| err(at(w), kind))?;
    }
    Ok(())
}

/// Where in a transmitter a validation error lies (formatted as a path suffix).
#[derive(Debug, Clone, Copy)]
enum Where {
    Id,
    Components,
    Component(usize, &'static str),
    Existence,
    Reliability,
    Visibility(i32, i32, &'static str),
}

impl std::fmt::Display for Where {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Where::Id => write!(f, ".id"),
            Where::Components => write!(f, ".components"),
            Where::Component(ci, field) => write!(f, ".components[{ci}].{field}"),
            Where::Existence => write!(f, ".existence"),
            Where::Reliability => write!(f, ".reliability_m"),
            Where::Visibility(q, r, field) => write!(f, ".visibility[q={q},r={r}].{field}"),
        }
    }
}

fn check_transmitter(t: &Transmitter) -> Result<(), (Where, MapErrorKind)> {
    let finite = |w: Where, v: f64| {
        if v.is_finite() {
            Ok(())
        } else {
            Err((w, MapErrorKind::NotFinite))
        }
    };
    if t.components.is_empty() {
        return Err((Where::Components, MapErrorKind::Empty));
    }
    if t.components.len() > MAX_COMPONENTS {
        return Err((
            Where::Components,
            MapErrorKind::TooMany {
                count: t.components.len(),
                limit: MAX_COMPONENTS,
            },
        ));
    }
    let mut sum = 0.0;
    for (ci, c) in t.components.iter().enumerate() {
        finite(Where::Component(ci, "weight"), c.weight)?;
        if c.weight <= 0.0 {
            return Err((
                Where::Component(ci, "weight"),
                MapErrorKind::NotPositive(c.weight),
            ));
        }
        sum += c.weight;
        if c.mean.iter().any(|v| !v.is_finite()) {
            return Err((Where::Component(ci, "mean"), MapErrorKind::NotFinite));
        }
        validate_cov("", &c.cov).map_err(|e| (Where::Component(ci, "cov"), e.kind))?;
    }
    if (sum - 1.0).abs() > WEIGHT_SUM_TOLERANCE {
        return Err((Where::Components, MapErrorKind::WeightSum(sum)));
    }
    finite(Where::Existence, t.existence)?;
    if !(0.0..=1.0).contains(&t.existence) {
        return Err((Where::Existence, MapErrorKind::NotProbability(t.existence)));
    }
    finite(Where::Reliability, t.reliability_m)?;
    if t.reliability_m < 0.0 {
        return Err((Where::Reliability, MapErrorKind::Negative(t.reliability_m)));
    }
    for (cell, b) in &t.visibility {
        for (name, v) in [("alpha", b.alpha), ("beta", b.beta)] {
            finite(Where::Visibility(cell.q, cell.r, name), v)?;
            if v < 0.0 {
                return Err((
                    Where::Visibility(cell.q, cell.r, name),
                    MapErrorKind::Negative(v),
                ));
            }
        }
    }
    Ok(())
}

/// Why a JSON map document was rejected: not JSON / wrong shape, or invalid content.
#[derive(Debug, Error)]
pub enum ParseError {
    /// not JSON, or not the shape of a map
    #[error("malformed map JSON: {0}")]
    Syntax(String),
    /// the shape is right but a value is not
    #[error("invalid map: {0}")]
    Invalid(MapError),
}

/// Serde wire structs: the JSON shape of DESIGN.md, converted to and from the validated types.
/// Parse into [`wire::MapDoc`] first when the shape and the content errors must be told apart
/// (as the server does), then validate with [`TransmitterMap::from_doc`].
pub mod wire {
    use super::*;

    /// A map as JSON carries it.
    #[derive(Debug, Clone, Serialize, Deserialize)]
    #[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
    #[serde(deny_unknown_fields)]
    pub struct MapDoc {
        /// `echomap.map.v1`
        pub format: String,
        /// circumradius of the visibility hexagons (m)
        pub hex_size_m: f64,
        /// the transmitters
        pub transmitters: Vec<TransmitterDoc>,
    }

    /// A transmitter as JSON carries it.
    #[derive(Debug, Clone, Serialize, Deserialize)]
    #[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
    #[serde(deny_unknown_fields)]
    pub struct TransmitterDoc {
        /// unique id within the map
        pub id: String,
        /// Gaussian mixture over `[x, y, b]`
        pub components: Vec<ComponentDoc>,
        /// belief that it exists, in [0, 1]
        pub existence: f64,
        /// distance walked while it was visible (m)
        pub reliability_m: f64,
        /// Beta evidence per hexagon
        #[serde(default)]
        pub visibility: Vec<CellDoc>,
    }

    /// A mixture component as JSON carries it.
    #[derive(Debug, Clone, Serialize, Deserialize)]
    #[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
    #[serde(deny_unknown_fields)]
    pub struct ComponentDoc {
        /// weight, > 0; a mixture's weights sum to 1
        pub weight: f64,
        /// mean `[x, y, b]` (m)
        pub mean: [f64; 3],
        /// covariance (m², symmetric positive definite)
        pub cov: [[f64; 3]; 3],
    }

    /// An axial coordinate: a JSON integer in the i32 range, written as `3` or `3.0` (JSON
    /// does not tell the two apart).
    fn axial<'de, D: serde::Deserializer<'de>>(d: D) -> Result<i32, D::Error> {
        let v = f64::deserialize(d)?;
        if v.fract() == 0.0 && v >= f64::from(i32::MIN) && v <= f64::from(i32::MAX) {
            Ok(v as i32)
        } else {
            Err(serde::de::Error::custom(format!(
                "expected an integer in the i32 range, got {v}"
            )))
        }
    }

    /// A visibility cell as JSON carries it.
    #[derive(Debug, Clone, Serialize, Deserialize)]
    #[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
    #[serde(deny_unknown_fields)]
    pub struct CellDoc {
        /// axial column
        #[serde(deserialize_with = "axial")]
        pub q: i32,
        /// axial row
        #[serde(deserialize_with = "axial")]
        pub r: i32,
        /// evidence of being seen from the cell
        pub alpha: f64,
        /// evidence of not being seen from the cell
        pub beta: f64,
    }

    impl TryFrom<MapDoc> for TransmitterMap {
        type Error = MapError;
        fn try_from(doc: MapDoc) -> Result<Self, MapError> {
            convert(doc)
        }
    }

    pub(super) fn convert(doc: MapDoc) -> Result<TransmitterMap, MapError> {
        if doc.format != MAP_FORMAT {
            return Err(err("format", MapErrorKind::Format(doc.format)));
        }
        if doc.transmitters.len() > MAX_TRANSMITTERS {
            return Err(err(
                "transmitters",
                MapErrorKind::TooMany {
                    count: doc.transmitters.len(),
                    limit: MAX_TRANSMITTERS,
                },
            ));
        }
        let mut transmitters = Vec::with_capacity(doc.transmitters.len());
        for (ti, t) in doc.transmitters.into_iter().enumerate() {
            let mut visibility = BTreeMap::new();
            for c in t.visibility {
                let cell = HexCell { q: c.q, r: c.r };
                if visibility
                    .insert(
                        cell,
                        Beta {
                            alpha: c.alpha,
                            beta: c.beta,
                        },
                    )
                    .is_some()
                {
                    return Err(err(
                        format!("transmitters[{ti}].visibility"),
                        MapErrorKind::DuplicateCell { q: c.q, r: c.r },
                    ));
                }
            }
            let components = t
                .components
                .into_iter()
                .map(|c| Component {
                    weight: c.weight,
                    mean: Vector3::from(c.mean),
                    cov: Matrix3::from_fn(|i, j| c.cov[i][j]),
                })
                .collect();
            transmitters.push(Transmitter {
                id: t.id,
                components,
                existence: t.existence,
                reliability_m: t.reliability_m,
                visibility,
            });
        }
        TransmitterMap::new(doc.hex_size_m, transmitters)
    }

    impl From<TransmitterMap> for MapDoc {
        fn from(m: TransmitterMap) -> Self {
            MapDoc {
                format: MAP_FORMAT.to_string(),
                hex_size_m: m.hex_size_m,
                transmitters: m
                    .transmitters
                    .into_iter()
                    .map(|t| TransmitterDoc {
                        id: t.id,
                        components: t
                            .components
                            .into_iter()
                            .map(|c| ComponentDoc {
                                weight: c.weight,
                                mean: [c.mean.x, c.mean.y, c.mean.z],
                                cov: std::array::from_fn(|i| {
                                    std::array::from_fn(|j| c.cov[(i, j)])
                                }),
                            })
                            .collect(),
                        existence: t.existence,
                        reliability_m: t.reliability_m,
                        visibility: t
                            .visibility
                            .into_iter()
                            .map(|(cell, b)| CellDoc {
                                q: cell.q,
                                r: cell.r,
                                alpha: b.alpha,
                                beta: b.beta,
                            })
                            .collect(),
                    })
                    .collect(),
            }
        }
    }
}

#[cfg(test)]
mod tests;

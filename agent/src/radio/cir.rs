//! The CIR format `echomap.cir.v1`: a directory with
//! - `cir.json`: what the samples mean (carrier, bandwidth, sample rate, pulse, the distance of
//!   the first delay sample, element positions, the correlator's processing gain) and the
//!   odometry of each snapshot (`t`, `gyro`, optional `speed`, as in `echomap.log.v1`);
//! - `cir.npy`: the samples, NumPy `complex64` (or `complex128`), C order, shape
//!   `[snapshots, elements, samples]`: `np.save("cir.npy", h.astype(np.complex64))` writes
//!   it from Python, MATLAB through its `writeNPY`.
//!
//! Amplitudes are in units of the noise: the noise on each sample and element is expected to
//! be circular complex Gaussian of variance `noise_variance` (1 if left out), after the
//! correlator's `processing_gain`; a path of per-sample SNR γ before the correlator has
//! `|α|² = γ · processing_gain · noise_variance` at its peak. Reading checks every field,
//! the array's type and shape against them, and every sample for NaN or infinity; an error
//! names the file and the field or snapshot. Writing goes to temporary files renamed into
//! place, so a failed write leaves no half-written CIR.

use super::array::ArrayModel;
use nalgebra::Complex;
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};

pub const CIR_FORMAT: &str = "echomap.cir.v1";
pub const META_FILE: &str = "cir.json";
pub const SAMPLES_FILE: &str = "cir.npy";

/// Odometry of one snapshot (as in `echomap.log.v1`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CirSnapshot {
    /// time (s), strictly increasing
    pub t: f64,
    /// mean heading rate over the interval ending at `t` (rad/s)
    pub gyro: f64,
    /// measured speed (m/s)
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub speed: Option<f64>,
}

/// `cir.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CirMeta {
    pub format: String,
    pub carrier_hz: f64,
    pub bandwidth_hz: f64,
    pub sample_rate_hz: f64,
    /// the pulse shape: only `sinc` (a flat spectrum over the band)
    pub pulse: String,
    /// distance (m) that the first delay sample stands for: `d = delay_origin_m + c·n/f_s`
    pub delay_origin_m: f64,
    /// delay samples per element and snapshot
    pub samples: usize,
    /// element positions in the body frame (m; +x forward, +y left)
    pub elements_m: Vec<[f64; 2]>,
    /// the correlator's gain over the per-sample SNR (linear, ≥ 1)
    pub processing_gain: f64,
    /// noise variance per sample and element; left out: estimated from the samples
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_variance: Option<f64>,
    pub snapshot_rate_hz: f64,
    /// whether `speed` is given in the snapshots
    pub speed: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
    /// the odometry's error model, as a log's sensor profile states it: `estimate` passes it
    /// on to the log it writes
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub odometry: Option<echomap_shared::sensor::OdometryNoise>,
    pub snapshots: Vec<CirSnapshot>,
}

/// A CIR in memory: the metadata and the samples, `data[(k·M + m)·N + n]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Cir {
    pub meta: CirMeta,
    pub data: Vec<Complex<f32>>,
}

#[derive(Debug, thiserror::Error)]
pub enum CirError {
    #[error("{file}: {source}")]
    Io {
        file: PathBuf,
        source: std::io::Error,
    },
    #[error("{file}: {field}: {why}")]
    Invalid {
        file: PathBuf,
        field: String,
        why: String,
    },
}

fn io(file: &Path) -> impl FnOnce(std::io::Error) -> CirError + '_ {
    move |source| CirError::Io {
        file: file.to_path_buf(),
        source,
    }
}

fn invalid(file: &Path, field: impl Into<String>, why: impl Into<String>) -> CirError {
    CirError::Invalid {
        file: file.to_path_buf(),
        field: field.into(),
        why: why.into(),
    }
}

impl CirMeta {
    /// Checks every field; the error names it.
    pub fn validate(&self, file: &Path) -> Result<(), CirError> {
        if self.format != CIR_FORMAT {
            return Err(invalid(
                file,
                "format",
                format!("expected {CIR_FORMAT:?}, got {:?}", self.format),
            ));
        }
        for (field, v) in [
            ("carrier_hz", self.carrier_hz),
            ("bandwidth_hz", self.bandwidth_hz),
            ("sample_rate_hz", self.sample_rate_hz),
            ("snapshot_rate_hz", self.snapshot_rate_hz),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(invalid(
                    file,
                    field,
                    format!("must be finite and > 0, got {v}"),
                ));
            }
        }
        if self.bandwidth_hz > self.sample_rate_hz {
            return Err(invalid(
                file,
                "sample_rate_hz",
                format!(
                    "must be at least the bandwidth ({} Hz), got {}",
                    self.bandwidth_hz, self.sample_rate_hz
                ),
            ));
        }
        if self.pulse != "sinc" {
            return Err(invalid(
                file,
                "pulse",
                format!("only \"sinc\" is known, got {:?}", self.pulse),
            ));
        }
        if !self.delay_origin_m.is_finite() {
            return Err(invalid(file, "delay_origin_m", "must be finite"));
        }
        if self.samples == 0 {
            return Err(invalid(file, "samples", "must be at least 1"));
        }
        if self.elements_m.is_empty() {
            return Err(invalid(file, "elements_m", "needs at least one element"));
        }
        if let Some(i) = self
            .elements_m
            .iter()
            .position(|e| !(e[0].is_finite() && e[1].is_finite()))
        {
            return Err(invalid(file, format!("elements_m[{i}]"), "must be finite"));
        }
        if !(self.processing_gain.is_finite() && self.processing_gain >= 1.0) {
            return Err(invalid(
                file,
                "processing_gain",
                format!("must be finite and ≥ 1, got {}", self.processing_gain),
            ));
        }
        if let Some(v) = self.noise_variance
            && !(v.is_finite() && v > 0.0)
        {
            return Err(invalid(
                file,
                "noise_variance",
                format!("must be finite and > 0, got {v}"),
            ));
        }
        let mut prev = f64::NEG_INFINITY;
        for (k, s) in self.snapshots.iter().enumerate() {
            if !(s.t.is_finite() && s.t > prev) {
                return Err(invalid(
                    file,
                    format!("snapshots[{k}].t"),
                    "must be finite and increasing",
                ));
            }
            prev = s.t;
            if !s.gyro.is_finite() {
                return Err(invalid(
                    file,
                    format!("snapshots[{k}].gyro"),
                    "must be finite",
                ));
            }
            match (self.speed, s.speed) {
                (true, Some(v)) if v.is_finite() => {}
                (true, _) => {
                    return Err(invalid(
                        file,
                        format!("snapshots[{k}].speed"),
                        "must be a finite number (the header says speed)",
                    ));
                }
                (false, Some(_)) => {
                    return Err(invalid(
                        file,
                        format!("snapshots[{k}].speed"),
                        "given, but the header says no speed",
                    ));
                }
                (false, None) => {}
            }
        }
        Ok(())
    }

    /// The array and pulse model of these samples.
    pub fn model(&self) -> ArrayModel {
        ArrayModel {
            elements_m: self.elements_m.clone(),
            wavelength_m: crate::sim::SPEED_OF_LIGHT / self.carrier_hz,
            rho: self.bandwidth_hz / self.sample_rate_hz,
        }
    }

    /// Distance (m) per delay sample.
    pub fn metres_per_sample(&self) -> f64 {
        crate::sim::SPEED_OF_LIGHT / self.sample_rate_hz
    }
}

impl Cir {
    /// Samples of snapshot `k`, element-major (`[m·N + n]`).
    pub fn snapshot(&self, k: usize) -> &[Complex<f32>] {
        let len = self.meta.elements_m.len() * self.meta.samples;
        &self.data[k * len..(k + 1) * len]
    }

    /// Reads and checks a CIR directory.
    pub fn read(dir: &Path) -> Result<Cir, CirError> {
        let meta_path = dir.join(META_FILE);
        let text = std::fs::read_to_string(&meta_path).map_err(io(&meta_path))?;
        let de = &mut serde_json::Deserializer::from_str(&text);
        let meta: CirMeta = serde_path_to_error::deserialize(de)
            .map_err(|e| invalid(&meta_path, e.path().to_string(), e.inner().to_string()))?;
        meta.validate(&meta_path)?;
        let npy_path = dir.join(SAMPLES_FILE);
        let file = File::open(&npy_path).map_err(io(&npy_path))?;
        let npy = npyz::NpyFile::new(BufReader::new(file)).map_err(io(&npy_path))?;
        let want = [
            meta.snapshots.len() as u64,
            meta.elements_m.len() as u64,
            meta.samples as u64,
        ];
        if npy.shape() != want {
            return Err(invalid(
                &npy_path,
                "shape",
                format!(
                    "expected [snapshots, elements, samples] = {want:?} from {META_FILE}, got {:?}",
                    npy.shape()
                ),
            ));
        }
        if npy.order() != npyz::Order::C {
            return Err(invalid(&npy_path, "order", "must be C order (row-major)"));
        }
        let dtype = match npy.dtype() {
            npyz::DType::Plain(t) => t.to_string(),
            other => other.descr(),
        };
        let data: Vec<Complex<f32>> = match dtype.as_str() {
            "<c8" => npy.into_vec::<Complex<f32>>().map_err(io(&npy_path))?,
            "<c16" => npy
                .into_vec::<Complex<f64>>()
                .map_err(io(&npy_path))?
                .into_iter()
                .map(|c| Complex::new(c.re as f32, c.im as f32))
                .collect(),
            other => {
                return Err(invalid(
                    &npy_path,
                    "dtype",
                    format!("expected complex64 ('<c8') or complex128 ('<c16'), got {other:?}"),
                ));
            }
        };
        let per = meta.elements_m.len() * meta.samples;
        if let Some(i) = data
            .iter()
            .position(|c| !(c.re.is_finite() && c.im.is_finite()))
        {
            return Err(invalid(
                &npy_path,
                format!(
                    "snapshot {} element {} sample {}",
                    i / per,
                    (i % per) / meta.samples,
                    i % meta.samples
                ),
                "not a finite number",
            ));
        }
        Ok(Cir { meta, data })
    }

    /// Writes the CIR into `dir` (created if missing), each file through a temporary file
    /// renamed into place (readable by all, as a file written directly would be).
    pub fn write(&self, dir: &Path) -> Result<(), CirError> {
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let meta_path = dir.join(META_FILE);
        self.meta.validate(&meta_path)?;
        let npy_path = dir.join(SAMPLES_FILE);
        let per = self.meta.elements_m.len() * self.meta.samples;
        if self.data.len() != per * self.meta.snapshots.len() {
            return Err(invalid(
                &npy_path,
                "data",
                format!(
                    "{} samples for {} snapshots of {per}",
                    self.data.len(),
                    self.meta.snapshots.len()
                ),
            ));
        }
        let tmp = tempfile::NamedTempFile::new_in(dir).map_err(io(&npy_path))?;
        {
            use npyz::WriterBuilder;
            let mut out = BufWriter::new(tmp.as_file());
            let mut w = npyz::WriteOptions::new()
                .default_dtype()
                .shape(&[
                    self.meta.snapshots.len() as u64,
                    self.meta.elements_m.len() as u64,
                    self.meta.samples as u64,
                ])
                .writer(&mut out)
                .begin_nd()
                .map_err(io(&npy_path))?;
            w.extend(self.data.iter().copied()).map_err(io(&npy_path))?;
            w.finish().map_err(io(&npy_path))?;
            out.flush().map_err(io(&npy_path))?;
        }
        persist(tmp, &npy_path)?;
        let mut tmp = tempfile::NamedTempFile::new_in(dir).map_err(io(&meta_path))?;
        serde_json::to_writer_pretty(&mut tmp, &self.meta)
            .map_err(|e| invalid(&meta_path, "metadata", e.to_string()))?;
        persist(tmp, &meta_path)
    }
}

/// Renames a finished temporary file into place with the usual permissions.
fn persist(tmp: tempfile::NamedTempFile, path: &Path) -> Result<(), CirError> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        tmp.as_file()
            .set_permissions(std::fs::Permissions::from_mode(0o644))
            .map_err(io(path))?;
    }
    tmp.persist(path).map_err(|e| CirError::Io {
        file: path.to_path_buf(),
        source: e.error,
    })?;
    Ok(())
}

//! The pq stage as file-level jobs: train on a features file and encode it, or encode it
//! with an existing codebook. The `pq` tool and the pipeline both run these, so they write
//! the same bytes and print the same report; [`TrainParams`] is the pipeline's `[pq]`
//! section as it is.
//!
//! ```
//! use profuse_formats::{Features, FileKind, Floats};
//! use profuse_pq::{job, TrainParams};
//!
//! let dir = tempfile::tempdir()?;
//! let (n, d) = (300, 8);
//! // Unit rows (SPEC: descriptors are L2-normalised).
//! let mut data: Vec<f32> = (0..n * d).map(|i| ((i * 7919 % 101) as f32 - 50.0) / 50.0).collect();
//! for row in data.chunks_mut(d) {
//!     let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt();
//!     row.iter_mut().for_each(|v| *v /= norm);
//! }
//! let features = Features {
//!     features: Floats::F32(data.into()),
//!     dim: d,
//!     valid: vec![1u8; n].into(),
//!     weight_sum: None,
//!     extra: Default::default(),
//! };
//! let input = dir.path().join("features.safetensors");
//! features.write(&input)?;
//! let params = TrainParams { m: 4, iters: 3, ..TrainParams::default() };
//! let report = job::train_file(&input, &dir.path().join("pq.safetensors"), &params)?;
//! assert_eq!((report.vectors, report.valid, report.m), (n, n, 4));
//! assert!(report.reconstruction_cosine_mean.is_some_and(|c| c > 0.5));
//! # Ok::<(), Box<dyn std::error::Error + Send + Sync>>(())
//! ```

use std::path::{Path, PathBuf};
use std::time::Instant;

use profuse_formats::{FileKind, FormatError, Pq};
use serde::Serialize;

use crate::{reconstruction_cosine, train, Codebook, PqError, TrainParams};

/// What can go wrong in a job: a file, or the method on a named file's vectors.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum JobError {
    /// A file could not be read or written, or breaks a rule of its kind.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// Training or encoding failed on this file's vectors.
    #[error("{path}: {error}")]
    Pq {
        /// The file.
        path: String,
        /// Why.
        error: PqError,
    },
}

fn in_file(path: &Path) -> impl FnOnce(PqError) -> JobError + '_ {
    move |error| JobError::Pq {
        path: path.display().to_string(),
        error,
    }
}

/// What a training run did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrainReport {
    /// Descriptors encoded.
    pub vectors: usize,
    /// Valid descriptors.
    pub valid: usize,
    /// Dimension D.
    pub dim: usize,
    /// Sub-quantisers M.
    pub m: usize,
    /// Dimensions per sub-quantiser.
    pub dsub: usize,
    /// Training vectors sampled.
    pub train_samples: Option<u64>,
    /// Lloyd iterations.
    pub kmeans_iters: usize,
    /// Seed.
    pub seed: u64,
    /// Mean cosine between a valid descriptor and its decode.
    pub reconstruction_cosine_mean: Option<f64>,
    /// The pq file written (non-UTF-8 bytes shown as U+FFFD in JSON).
    #[serde(serialize_with = "profuse_formats::output::lossy_path::one")]
    pub out: PathBuf,
    /// Training seconds.
    pub train_s: f64,
    /// Encoding seconds.
    pub encode_s: f64,
}

/// What an encoding run did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EncodeReport {
    /// Descriptors encoded.
    pub vectors: usize,
    /// Valid descriptors.
    pub valid: usize,
    /// Dimension D.
    pub dim: usize,
    /// Sub-quantisers M.
    pub m: usize,
    /// Mean cosine between a valid descriptor and its decode.
    pub reconstruction_cosine_mean: Option<f64>,
    /// The pq file written (non-UTF-8 bytes shown as U+FFFD in JSON).
    #[serde(serialize_with = "profuse_formats::output::lossy_path::one")]
    pub out: PathBuf,
    /// Encoding seconds.
    pub encode_s: f64,
}

/// Trains M x 256 centroids on the valid descriptors of `features`, encodes every
/// descriptor and writes the pq file `out` (atomically).
pub fn train_file(
    features: &Path,
    out: &Path,
    params: &TrainParams,
) -> Result<TrainReport, JobError> {
    let f = profuse_formats::Features::read(features)?;
    let t0 = Instant::now();
    let codebook = train(&f, params).map_err(in_file(features))?;
    let train_s = t0.elapsed().as_secs_f64();
    let t0 = Instant::now();
    let pq = codebook.encode_features(&f).map_err(in_file(features))?;
    let encode_s = t0.elapsed().as_secs_f64();
    let reconstruction_cosine_mean = reconstruction_cosine(&f, &pq);
    pq.write(out)?;
    Ok(TrainReport {
        vectors: pq.len(),
        valid: valid_count(&pq),
        dim: pq.dim(),
        m: pq.m,
        dsub: pq.dsub,
        train_samples: pq.extra.get("train_samples").and_then(|s| s.parse().ok()),
        kmeans_iters: params.iters,
        seed: params.seed,
        reconstruction_cosine_mean,
        out: out.to_path_buf(),
        train_s,
        encode_s,
    })
}

/// Encodes the descriptors of `features` with the centroids of the pq file `codebook` and
/// writes a new pq file `out` (same codebook, new codes).
pub fn encode_file(codebook: &Path, features: &Path, out: &Path) -> Result<EncodeReport, JobError> {
    let existing = Pq::read(codebook)?;
    let f = profuse_formats::Features::read(features)?;
    let book = Codebook::from_pq(&existing).map_err(in_file(codebook))?;
    let t0 = Instant::now();
    let encoded = book.encode_features(&f).map_err(in_file(features))?;
    let encode_s = t0.elapsed().as_secs_f64();
    let reconstruction_cosine_mean = reconstruction_cosine(&f, &encoded);
    encoded.write(out)?;
    Ok(EncodeReport {
        vectors: encoded.len(),
        valid: valid_count(&encoded),
        dim: encoded.dim(),
        m: encoded.m,
        reconstruction_cosine_mean,
        out: out.to_path_buf(),
        encode_s,
    })
}

fn valid_count(pq: &Pq) -> usize {
    pq.valid.iter().filter(|&&v| v == 1).count()
}

//! The warp-graph stage as a file-level job: read masks, matches (and cameras and
//! Gaussians for the depth test and the consensus grouping), build the proposals, write
//! them (atomically) and report. The `warp-graph` tool and the pipeline both run this.
//!
//! ```
//! use warp_graph::job::{self, Job};
//!
//! let dir = tempfile::tempdir()?;
//! let mut config = synth::Config::preset(synth::Preset::Tiny, 2);
//! config.gaussians = 2000; // ground-truth Gaussians, which the tiny preset leaves out
//! synth::generate(&config, dir.path())?;
//! let file = |name: &str| dir.path().join(name);
//! let job = Job {
//!     masks: file("masks.safetensors"),
//!     matches: file("matches.safetensors"),
//!     cameras: Some(file("cameras.safetensors")),
//!     gaussians: Some(file("gt/gaussians.safetensors")),
//!     out: file("proposals.safetensors"),
//! };
//! let report = job::run(&job, &warp_graph::Params::default(), &|_, _| {})?;
//! assert_eq!(report.out, file("proposals.safetensors"));
//! assert!(report.outcome.masks > 0);
//! # Ok::<(), Box<dyn std::error::Error + Send + Sync>>(())
//! ```

use std::error::Error;
use std::fmt;
use std::path::{Path, PathBuf};
use std::time::Instant;

use profuse_formats::{
    Cameras, FileKind, FormatError, Gaussians, Masks, Matches, WarpPartial, WARP_INPUTS,
};
use serde::Serialize;

use crate::{Association, Inputs, Params, Report, WarpGraphError};

/// The files of one run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Job {
    /// Masks (profuse.masks).
    pub masks: PathBuf,
    /// Dense matches (profuse.matches).
    pub matches: PathBuf,
    /// Cameras (profuse.cameras), for the depth test and the consensus grouping.
    pub cameras: Option<PathBuf>,
    /// Gaussians (profuse.gaussians), for the depth test and the consensus grouping.
    pub gaussians: Option<PathBuf>,
    /// The proposals file to write.
    pub out: PathBuf,
}

impl Job {
    /// An error of the association, naming the input files.
    pub(crate) fn inputs_error(&self, error: WarpGraphError) -> JobError {
        JobError::Inputs {
            files: self.files(),
            error: Box::new(error),
        }
    }

    /// The input files as the tool's flags, for messages.
    fn files(&self) -> String {
        let mut files = format!(
            "--masks {} --matches {}",
            self.masks.display(),
            self.matches.display()
        );
        let flag = |name: &str, p: &Option<PathBuf>| {
            p.as_ref()
                .map(|p| format!(" --{name} {}", p.display()))
                .unwrap_or_default()
        };
        files.push_str(&flag("cameras", &self.cameras));
        files.push_str(&flag("gaussians", &self.gaussians));
        files
    }
}

/// What can go wrong in a job.
#[derive(Debug)]
#[non_exhaustive]
pub enum JobError {
    /// A file could not be read or written, or breaks a rule of its kind.
    Format(FormatError),
    /// Shards of `--warp-partials` that were made from other inputs or parameters, or
    /// that do not cover every view pair exactly once.
    Shards(crate::ShardMismatch),
    /// The inputs (named by their flags) do not fit together, or a parameter is invalid.
    Inputs {
        /// The input files.
        files: String,
        /// Why (boxed: the error is large and rarely built).
        error: Box<WarpGraphError>,
    },
}

impl fmt::Display for JobError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            JobError::Format(e) => e.fmt(f),
            JobError::Shards(e) => e.fmt(f),
            JobError::Inputs { files, error } => write!(f, "{files}: {error}"),
        }
    }
}

impl Error for JobError {
    fn source(&self) -> Option<&(dyn Error + 'static)> {
        match self {
            JobError::Format(e) => e.source(),
            JobError::Shards(_) => None,
            // The message already holds the error; its own cause comes next.
            JobError::Inputs { error, .. } => error.source(),
        }
    }
}

impl From<FormatError> for JobError {
    fn from(e: FormatError) -> JobError {
        JobError::Format(e)
    }
}

/// What a run did: the same object from the tool (stdout) and the pipeline.
#[derive(Debug, Clone, Serialize)]
pub struct JobReport {
    /// The association's counts.
    #[serde(flatten)]
    pub outcome: Report,
    /// The proposals file written (non-UTF-8 bytes shown as U+FFFD in JSON).
    #[serde(serialize_with = "profuse_formats::output::lossy_path::one")]
    pub out: PathBuf,
    /// Seconds, reading and writing included.
    pub seconds: f64,
}

fn read_optional<T: FileKind>(p: &Option<PathBuf>) -> Result<Option<T>, FormatError> {
    p.as_deref().map(|p: &Path| T::read(p)).transpose()
}

/// Runs a job; `progress` gets (view pairs done, view pairs).
pub fn run(
    job: &Job,
    params: &Params,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<JobReport, JobError> {
    let start = Instant::now();
    let outcome = with_association(job, params, |a, _| {
        a.run(progress).map_err(|e| job.inputs_error(e))
    })?;
    finish(job, outcome, start)
}

/// Writes the proposals and reports.
fn finish(job: &Job, outcome: crate::Outcome, start: Instant) -> Result<JobReport, JobError> {
    outcome.proposals.write(&job.out)?;
    Ok(JobReport {
        outcome: outcome.report,
        out: job.out.clone(),
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// Reads the job's inputs and runs `f` on the prepared association (and the masks).
fn with_association<T>(
    job: &Job,
    params: &Params,
    f: impl FnOnce(&Association<'_>, &Masks) -> Result<T, JobError>,
) -> Result<T, JobError> {
    let masks = Masks::read(&job.masks)?;
    let matches = Matches::read(&job.matches)?;
    let cameras: Option<Cameras> = read_optional(&job.cameras)?;
    let gaussians: Option<Gaussians> = read_optional(&job.gaussians)?;
    let mut inputs = Inputs::new(&masks, &matches);
    if let Some(c) = &cameras {
        inputs = inputs.with_cameras(c);
    }
    if let Some(g) = &gaussians {
        inputs = inputs.with_gaussians(g);
    }
    let association = Association::new(inputs, params).map_err(|e| job.inputs_error(e))?;
    f(&association, &masks)
}

/// The files of a `warps` run: dense warps from the Gaussians' rendered depth
/// ([`crate::depth_warps`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WarpsJob {
    /// Gaussians (profuse.gaussians), e.g. from gs-init.
    pub gaussians: PathBuf,
    /// Cameras (profuse.cameras).
    pub cameras: PathBuf,
    /// The matches file to write.
    pub out: PathBuf,
}

/// What a `warps` run did.
#[derive(Debug, Clone, Serialize)]
pub struct WarpsReport {
    /// The counts.
    #[serde(flatten)]
    pub warps: crate::DepthWarpReport,
    /// The matches file written.
    #[serde(serialize_with = "profuse_formats::output::lossy_path::one")]
    pub out: PathBuf,
    /// Seconds, reading and writing included.
    pub seconds: f64,
}

/// Runs a `warps` job; `progress` gets (depth maps and pairs done, total).
pub fn run_warps(
    job: &WarpsJob,
    params: &crate::DepthWarpParams,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<WarpsReport, JobError> {
    let start = Instant::now();
    let gaussians = Gaussians::read(&job.gaussians)?;
    let cameras = Cameras::read(&job.cameras)?;
    let (matches, report) =
        crate::depth_warps(&gaussians, &cameras, params, progress).map_err(|error| {
            JobError::Inputs {
                files: format!(
                    "--gaussians {} --cameras {}",
                    job.gaussians.display(),
                    job.cameras.display()
                ),
                error: Box::new(error),
            }
        })?;
    matches.write(&job.out)?;
    Ok(WarpsReport {
        warps: report,
        out: job.out.clone(),
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// What a `warp-shard` run did.
#[derive(Debug, Clone, Serialize)]
pub struct ShardReport {
    /// The view pairs computed, `[a, b)` of the run's list.
    pub pairs: [usize; 2],
    /// The view pairs of the whole run, T.
    pub view_pairs: usize,
    /// Links accepted in these pairs.
    pub edges: usize,
    /// The evidence file written.
    #[serde(serialize_with = "profuse_formats::output::lossy_path::one")]
    pub partial_out: PathBuf,
    /// Seconds, reading, hashing and writing included.
    pub seconds: f64,
}

/// One shard of a job: the evidence of view pairs `pairs` (of the run's list, ascending
/// (i, j)) written to `partial_out` (atomically) as a `profuse.warp_partial` file that
/// records the identity of the job's inputs and parameters, for [`run_merged`].
pub fn run_shard(
    job: &Job,
    params: &Params,
    pairs: std::ops::Range<usize>,
    partial_out: &Path,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<ShardReport, JobError> {
    let start = Instant::now();
    let ids = input_ids(job, params)?;
    let partial = with_association(job, params, |a, masks| {
        let evidence = a
            .pair_evidence(pairs.clone(), progress)
            .map_err(|e| job.inputs_error(e))?;
        Ok(evidence.to_partial(
            masks.num_views(),
            masks.num_masks(),
            a.num_view_pairs(),
            ids,
        ))
    })?;
    partial.write(partial_out)?;
    Ok(ShardReport {
        pairs: [pairs.start, pairs.end],
        view_pairs: partial.num_view_pairs,
        edges: partial.num_edges(),
        partial_out: partial_out.to_path_buf(),
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// The finishing step of a sharded job: merges the evidence that [`run_shard`] wrote for
/// disjoint ranges covering every view pair, groups the masks and writes `job.out`,
/// byte-identical to an unsharded [`run`]. A shard made from other inputs or parameters
/// (an `input_*` key that differs from this job's) or a set of shards that leaves a pair
/// out or covers one twice is refused ([`JobError::Shards`]) before anything is written.
pub fn run_merged(job: &Job, params: &Params, partials: &[PathBuf]) -> Result<JobReport, JobError> {
    let start = Instant::now();
    let ids = input_ids(job, params)?;
    let mut shards = Vec::with_capacity(partials.len());
    for path in partials {
        let partial = WarpPartial::read(path)?;
        let name = path.display().to_string();
        check_inputs(&name, &ids, &partial)?;
        shards.push((name, crate::Evidence::from_partial(&partial)));
    }
    let outcome = with_association(job, params, |a, _| {
        let evidence =
            crate::Evidence::merge(shards, a.num_view_pairs()).map_err(JobError::Shards)?;
        a.group(&evidence).map_err(|e| job.inputs_error(e))
    })?;
    finish(job, outcome, start)
}

/// A shard's `input_*` values equal this job's.
fn check_inputs(name: &str, ids: &[String; 5], partial: &WarpPartial) -> Result<(), JobError> {
    let differing = WARP_INPUTS
        .iter()
        .zip(ids.iter().zip(&partial.inputs))
        .find(|(_, (own, theirs))| own != theirs);
    match differing {
        Some((field, (own, theirs))) => Err(JobError::Shards(crate::ShardMismatch::Inputs {
            shard: name.to_string(),
            field,
            expected: own.clone(),
            found: theirs.clone(),
        })),
        None => Ok(()),
    }
}

/// The values of the `input_*` keys ([`WARP_INPUTS`] order) for this job: every input
/// file's size and content hash (`none` when absent), and the parameters as JSON.
fn input_ids(job: &Job, params: &Params) -> Result<[String; 5], JobError> {
    let optional = |p: &Option<PathBuf>| match p {
        Some(p) => content_id(p),
        None => Ok("none".to_string()),
    };
    let params = serde_json::to_string(params).map_err(|e| {
        job.inputs_error(WarpGraphError::InvalidParameter {
            name: "params",
            value: e.to_string(),
            expected: "parameters that serialise to JSON",
        })
    })?;
    Ok([
        content_id(&job.masks)?,
        content_id(&job.matches)?,
        optional(&job.cameras)?,
        optional(&job.gaussians)?,
        params,
    ])
}

/// `SIZE:HASH`: the file's size and a 64-bit hash of its bytes (8-byte little-endian
/// words, multiply-rotate; not cryptographic: it tells files apart, it does not resist
/// forgery), read in 1 MiB blocks so that memory stays flat for any size.
fn content_id(path: &Path) -> Result<String, FormatError> {
    use std::io::Read;
    let io = |source| FormatError::Io {
        path: path.display().to_string(),
        action: "cannot read",
        source,
    };
    let mut file = std::fs::File::open(path).map_err(io)?;
    let mut buf = vec![0u8; 1 << 20];
    let (mut hash, mut size) = (0xcbf2_9ce4_8422_2325u64, 0u64);
    loop {
        let mut n = 0;
        while n < buf.len() {
            match file.read(&mut buf[n..]).map_err(io)? {
                0 => break,
                k => n += k,
            }
        }
        for chunk in buf[..n].chunks(8) {
            let mut word = [0u8; 8];
            word[..chunk.len()].copy_from_slice(chunk);
            hash = (hash.rotate_left(23) ^ u64::from_le_bytes(word))
                .wrapping_mul(0x9e37_79b9_7f4a_7c15);
        }
        size += n as u64;
        if n < buf.len() {
            return Ok(format!("{size}:{hash:016x}"));
        }
    }
}

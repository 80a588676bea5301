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

use profuse_formats::{Cameras, FileKind, FormatError, Gaussians, Masks, Matches};
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
            JobError::Inputs { files, error } => write!(f, "{files}: {error}"),
        }
    }
}

impl Error for JobError {
    fn source(&self) -> Option<&(dyn Error + 'static)> {
        match self {
            JobError::Format(e) => e.source(),
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
    let masks = Masks::read(&job.masks)?;
    let matches = Matches::read(&job.matches)?;
    let cameras: Option<Cameras> = read_optional(&job.cameras)?;
    let gaussians: Option<Gaussians> = read_optional(&job.gaussians)?;
    let with_files = |error| JobError::Inputs {
        files: job.files(),
        error: Box::new(error),
    };
    let mut inputs = Inputs::new(&masks, &matches);
    if let Some(c) = &cameras {
        inputs = inputs.with_cameras(c);
    }
    if let Some(g) = &gaussians {
        inputs = inputs.with_gaussians(g);
    }
    let outcome = Association::new(inputs, params)
        .and_then(|a| a.run(progress))
        .map_err(with_files)?;
    outcome.proposals.write(&job.out)?;
    Ok(JobReport {
        outcome: outcome.report,
        out: job.out.clone(),
        seconds: start.elapsed().as_secs_f64(),
    })
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

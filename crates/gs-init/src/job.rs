//! The gs-init stage as a file-level job: read cameras, images and matches, triangulate
//! and initialise, write the Gaussians (atomically) and report. The `gs-init` tool and
//! the pipeline both run this, so they print the same report.
//!
//! ```
//! use gs_init::job::{self, Job};
//!
//! let dir = tempfile::tempdir()?;
//! synth::generate(&synth::Config::preset(synth::Preset::Tiny, 1), dir.path())?;
//! let job = Job {
//!     inputs: gs_init::Inputs::scene(dir.path())?,
//!     out: dir.path().join("gaussians.safetensors"),
//! };
//! let report = job::run(&job, &gs_init::Params::default(), &|_, _| {})?;
//! assert!(report.report.kept > 0);
//! assert!(job.out.is_file());
//! # Ok::<(), Box<dyn std::error::Error + Send + Sync>>(())
//! ```

use std::path::PathBuf;
use std::time::Instant;

use profuse_formats::FileKind;
use serde::Serialize;

use crate::{initialise_files, Inputs, Params, Report, Result};

/// The files of one run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Job {
    /// Cameras, images and matches.
    pub inputs: Inputs,
    /// The Gaussians file to write.
    pub out: PathBuf,
}

/// What a run did: the same object from the tool (stdout) and the pipeline.
#[derive(Debug, Clone, Serialize)]
pub struct JobReport {
    /// The initialisation's counts and per-reference-view figures.
    #[serde(flatten)]
    pub report: Report,
    /// The Gaussians file written (non-UTF-8 bytes shown as U+FFFD in JSON).
    #[serde(serialize_with = "profuse_formats::output::lossy_path::one")]
    pub out: PathBuf,
    /// Seconds, reading and writing included.
    pub seconds: f64,
}

/// Runs a job; `progress` gets (reference views done, reference views). The output's
/// folder is created when missing. An empty result (no point survived the gates) is
/// written too, and reported with `kept == 0`.
pub fn run(
    job: &Job,
    params: &Params,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<JobReport> {
    let start = Instant::now();
    let (gaussians, report) = initialise_files(&job.inputs, params, progress)?;
    // Only now: a failed run leaves nothing behind, not even a folder.
    if let Some(parent) = job.out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|source| crate::InitError::OutputFolder {
            path: parent.display().to_string(),
            source,
        })?;
    }
    gaussians.write(&job.out)?;
    Ok(JobReport {
        report,
        out: job.out.clone(),
        seconds: start.elapsed().as_secs_f64(),
    })
}

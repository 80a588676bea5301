//! `gs-init`: triangulate confident matches into initial 3D Gaussians (paper §3.1), and
//! benchmark it.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error (naming the file) goes to stderr, the exit code is 1, and nothing
//! is written.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use gs_init::job::{self, Job};
use gs_init::{FlatParams, Inputs, MatchFile, Params};
use profuse_bench::gs_init as bench;
use profuse_tools::{chatty, init_threads, progress_bar, run, warn, BoxError};
use serde_json::Value;

#[derive(Debug, Parser)]
#[command(
    name = "gs-init",
    version,
    about = "Triangulate confident matches into initial 3D Gaussians (ProFuse §3.1 / EDGS)",
    long_about = "Triangulate confident dense (profuse.matches) or sparse (profuse.sparse_matches) \
                  correspondences into initial 3D Gaussians (ProFuse §3.1, after EDGS). Dense: \
                  reference views by seeded k-means over camera poses, each triangulated against \
                  its nearest views by pose that it has match pairs with. Sparse: every listed pair, \
                  each match between its two views. Up to --budget confident matches are sampled per \
                  reference (seeded), triangulated by linear DLT, gated (non-finite, behind a \
                  camera, reprojection error, triangulation angle), and become Gaussians coloured \
                  from the reference image (SH degree 0, identity rotation, opacity 0.5). Output is \
                  byte-identical for any thread count (RAYON_NUM_THREADS). Prints one JSON report on \
                  stdout: counts that add up (sampled = kept + rejected.total) and the parameters."
)]
struct Cli {
    /// Do not print progress or warnings on stderr.
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Initialise Gaussians from cameras, images and matches; write a gaussians file.
    Run {
        /// Cameras file (profuse.cameras).
        #[arg(long)]
        cameras: PathBuf,
        /// Folder that cameras.image_names are relative to (the scene directory), or the
        /// folder holding the image files themselves. Only reference views' images are read.
        #[arg(long)]
        images: PathBuf,
        /// Dense matches file (profuse.matches).
        #[arg(
            long,
            required_unless_present = "sparse_matches",
            conflicts_with = "sparse_matches"
        )]
        matches: Option<PathBuf>,
        /// Sparse matches file (profuse.sparse_matches).
        #[arg(long)]
        sparse_matches: Option<PathBuf>,
        /// Gaussians file to write (profuse.gaussians, SH degree 0).
        #[arg(long)]
        out: PathBuf,
        /// Also write the JSON report to this file.
        #[arg(long)]
        report_json: Option<PathBuf>,
        #[command(flatten)]
        params: FlatParams,
    },
    /// Time an initialisation of a synthetic scene (generated into a temporary folder and
    /// removed afterwards) or of a scene directory; print points per second and peak
    /// memory as one JSON object.
    Bench {
        #[command(flatten)]
        params: bench::BenchParams,
        /// Worker threads (default: rayon's, i.e. RAYON_NUM_THREADS or the core count).
        #[arg(long)]
        threads: Option<usize>,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| execute(cli.command, quiet))
}

fn execute(command: Command, quiet: bool) -> Result<Value, BoxError> {
    match command {
        Command::Run {
            cameras,
            images,
            matches,
            sparse_matches,
            out,
            report_json,
            params,
        } => {
            let matches = match (matches, sparse_matches) {
                (Some(m), _) => MatchFile::Dense(m),
                (None, Some(s)) => MatchFile::Sparse(s),
                (None, None) => return Err("give --matches or --sparse-matches".into()),
            };
            let inputs = Inputs {
                cameras,
                images,
                matches,
            };
            let params = Params::from(params);
            profuse_tools::check_outputs([out.as_path()])?;
            let job = Job { inputs, out };
            let report = with_progress(chatty(quiet), |p| job::run(&job, &params, p))?;
            if report.report.kept == 0 {
                warn(quiet, "no point survived: the gaussians file is empty");
            }
            let value = serde_json::to_value(&report)?;
            if let Some(path) = report_json {
                write_json(&path, &value)?;
            }
            Ok(value)
        }
        Command::Bench { params, threads } => {
            init_threads(threads)?;
            with_progress(chatty(quiet), |p| bench::run(&params, p))
        }
    }
}

/// Runs `f` with a progress callback that drives a bar over the reference views.
fn with_progress<T>(show: bool, f: impl FnOnce(&(dyn Fn(usize, usize) + Sync)) -> T) -> T {
    if !show {
        return f(&|_, _| {});
    }
    let bar = progress_bar(show, 0, "gs-init", "reference views");
    let result = f(&|done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    });
    bar.finish_and_clear();
    result
}

/// Writes pretty JSON atomically.
fn write_json(path: &Path, value: &Value) -> Result<(), BoxError> {
    let text = serde_json::to_string_pretty(value)? + "\n";
    profuse_tools::write_file(path, text.as_bytes())
}

//! `warp-graph`: group the masks of all views into 3D Context Proposals by warping them
//! across view pairs (ProFuse Algorithm 1), and benchmark the association.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error (naming the file) goes to stderr, the exit code is 1, and nothing
//! is written.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use profuse_bench::warp_graph as bench;
use profuse_tools::{chatty, init_threads, progress_bar, run};
use warp_graph::job::{self, Job};
use warp_graph::{FlatParams, Params};

#[derive(Debug, Parser)]
#[command(
    name = "warp-graph",
    version,
    about = "3D Context Proposals: cross-view mask association over dense warps (ProFuse Algorithm 1)",
    long_about = "Links masks of different views that mutually overlap under the dense warps of \
                  the matches file (gated IoU >= tau_iou and box IoU >= tau_box in both \
                  directions, over cells with certainty >= tau_alpha that pass the visibility \
                  test), and writes the connected components over all views, filtered by \
                  s_min / v_min, as a proposals file. Prints one JSON report on stdout."
)]
struct Cli {
    /// Do not print progress on stderr.
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Build the proposals of a scene and write them (profuse.proposals, SPEC.md §4.6).
    Run {
        /// Masks file (profuse.masks): per-view label maps.
        #[arg(long)]
        masks: PathBuf,
        /// Matches file (profuse.matches): dense warps of ordered view pairs.
        #[arg(long)]
        matches: PathBuf,
        /// Cameras file (profuse.cameras); needed for `pixels` warps and depth visibility.
        #[arg(long)]
        cameras: Option<PathBuf>,
        /// Gaussians file (profuse.gaussians, e.g. from gs-init) whose rendered depth gives
        /// the depth visibility test; needs --cameras.
        #[arg(long, requires = "cameras")]
        gaussians: Option<PathBuf>,
        /// The proposals file to write.
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        params: FlatParams,
    },
    /// Dense warps from geometry (for scenes with only sparse matches): render each view's
    /// depth from the Gaussians, carry every grid cell of view i into view j, and keep it
    /// where the depths agree (certainty 1 − (e / depth_tol)², e the relative depth
    /// disagreement in view j; occluded cells get 0). Writes a matches file (SPEC.md §4.4,
    /// pixel coordinates) that `warp-graph run --matches` reads.
    Warps(profuse_tools::warps::WarpsArgs),
    /// Time the association on synthetic Voronoi label maps with exact shift warps and print
    /// ordered pairs per second and peak memory as one JSON object.
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
    let show = chatty(cli.quiet);
    run(|| match cli.command {
        Command::Run {
            masks,
            matches,
            cameras,
            gaussians,
            out,
            params,
        } => {
            profuse_tools::check_outputs([out.as_path()])?;
            let job = Job {
                masks,
                matches,
                cameras,
                gaussians,
                out,
            };
            let report = with_bar(show, |p| job::run(&job, &Params::from(params), p))?;
            Ok(serde_json::to_value(report)?)
        }
        Command::Warps(a) => profuse_tools::warps::run(a, show),
        Command::Bench { params, threads } => {
            init_threads(threads)?;
            with_bar(show, |p| bench::run(&params, p))
        }
    })
}

/// Runs `f` with a progress callback that drives a bar over the view pairs.
fn with_bar<T>(show: bool, f: impl FnOnce(&(dyn Fn(usize, usize) + Sync)) -> T) -> T {
    let bar = progress_bar(show, 0, "warp-graph", "view pairs");
    let result = f(&|done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    });
    bar.finish_and_clear();
    result
}

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
use warp_graph::job::{self, Job, WarpsJob};
use warp_graph::{DepthWarpParams, FlatParams, Pairs, Params};

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
    Warps {
        /// Gaussians file (profuse.gaussians, e.g. from gs-init).
        #[arg(long)]
        gaussians: PathBuf,
        /// Cameras file (profuse.cameras).
        #[arg(long)]
        cameras: PathBuf,
        /// The matches file to write.
        #[arg(long)]
        out: PathBuf,
        /// Ordered pairs I-J, comma-separated (default: each view with its --nearest views
        /// by camera centre, both directions).
        #[arg(long, value_delimiter = ',', value_parser = parse_pair, conflicts_with = "nearest")]
        pairs: Vec<[u32; 2]>,
        /// Views paired with each view, nearest camera centres first.
        #[arg(long, value_name = "K", default_value_t = 4)]
        nearest: usize,
        /// Image pixels per grid cell along each axis.
        #[arg(long, value_name = "S", default_value_t = 4)]
        stride: usize,
        /// Relative depth tolerance: certainty falls to 0 at this disagreement.
        #[arg(long, value_name = "T", default_value_t = 0.05)]
        depth_tol: f64,
        /// Accumulated alpha below which a rendered pixel has no depth.
        #[arg(long, value_name = "A", default_value_t = 0.5)]
        min_alpha: f32,
        /// Reject cells on a depth edge: a 4-neighbour's depth differs by more than E
        /// relative (default off: more precise warps, but fewer links in warp-graph).
        #[arg(long, value_name = "E")]
        edge_tol: Option<f64>,
    },
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
        Command::Warps {
            gaussians,
            cameras,
            out,
            pairs,
            nearest,
            stride,
            depth_tol,
            min_alpha,
            edge_tol,
        } => {
            profuse_tools::check_outputs([out.as_path()])?;
            let params = DepthWarpParams {
                stride,
                depth_tol,
                min_alpha,
                edge_tol: edge_tol.unwrap_or(warp_graph::DEFAULT_EDGE_TOL),
                pairs: if pairs.is_empty() {
                    Pairs::Nearest(nearest)
                } else {
                    Pairs::Explicit(pairs)
                },
            };
            let job = WarpsJob {
                gaussians,
                cameras,
                out,
            };
            let report = with_bar(show, |p| job::run_warps(&job, &params, p))?;
            Ok(serde_json::to_value(report)?)
        }
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

/// `I-J` → [I, J].
fn parse_pair(s: &str) -> Result<[u32; 2], String> {
    let (i, j) = s
        .split_once('-')
        .ok_or_else(|| format!("{s:?}: expected a pair I-J of view indices"))?;
    let view = |t: &str| {
        t.trim()
            .parse::<u32>()
            .map_err(|e| format!("{s:?}: {t:?} is not a view index ({e})"))
    };
    Ok([view(i)?, view(j)?])
}

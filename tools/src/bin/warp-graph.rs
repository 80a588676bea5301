//! `warp-graph`: group the masks of all views into 3D Context Proposals by warping them
//! across view pairs (ProFuse Algorithm 1), and benchmark the association.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error (naming the file) goes to stderr, the exit code is 1, and nothing
//! is written.

use std::error::Error;
use std::fmt;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{Args, Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use profuse_formats::{Cameras, FileKind, Gaussians, Masks, Matches};
use profuse_tools::{chatty, peak_rss_mb, run, BoxError};
use serde_json::{json, Value};
// rayon as re-exported by splat-raster (the tools package has no direct rayon dependency).
use splat_raster::rayon;
use warp_graph::{
    synthetic, Association, ConsensusParams, Grouping, Inputs, Params, Sampling, Visibility,
    WarpGraphError,
};

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
        params: ParamArgs,
    },
    /// Time the association on synthetic Voronoi label maps with exact shift warps and print
    /// ordered pairs per second and peak memory as one JSON object.
    Bench {
        /// Image and mask width.
        #[arg(long, default_value_t = 1000)]
        width: usize,
        /// Image and mask height.
        #[arg(long, default_value_t = 730)]
        height: usize,
        /// Views.
        #[arg(long, default_value_t = 8)]
        views: usize,
        /// Mean masks (Voronoi cells) per view.
        #[arg(long, default_value_t = 100)]
        masks_per_view: usize,
        /// Warp grid = image subsampled by this step (1 = one warp cell per pixel).
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
        grid_step: u64,
        /// Views paired with each view on either side (both directions).
        #[arg(long, default_value_t = 1)]
        neighbours: usize,
        /// Worker threads (default: rayon's, i.e. RAYON_NUM_THREADS or the core count).
        #[arg(long)]
        threads: Option<usize>,
        /// Run the association this many times and report the fastest.
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
        repeat: u64,
        #[command(flatten)]
        params: ParamArgs,
    },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum VisArg {
    /// Both tests with --gaussians, else fwd-bwd.
    Auto,
    /// No occlusion test.
    None,
    /// Rendered depth of the Gaussians in both views (needs --cameras and --gaussians).
    Depth,
    /// Round trip through the reverse warp.
    FwdBwd,
    /// Depth and fwd-bwd.
    Both,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum SamplingArg {
    /// Bilinear weights over the four surrounding mask pixels (fractional overlaps).
    Bilinear,
    /// The mask pixel containing the warped position.
    Nearest,
}

#[derive(Debug, Args)]
struct ParamArgs {
    /// Certainty threshold of the gate Γ = [certainty >= tau_alpha] ∧ vis_mask.
    #[arg(long, default_value_t = 0.5)]
    tau_alpha: f32,
    /// Gated mask IoU needed in both directions (authors' run script: 0.2).
    #[arg(long, default_value_t = 0.2)]
    tau_iou: f64,
    /// Gated bounding-box IoU needed in both directions (authors' run script: 0.08).
    #[arg(long, default_value_t = 0.08)]
    tau_box: f64,
    /// Minimal members of a proposal.
    #[arg(long, default_value_t = 2)]
    s_min: usize,
    /// Minimal distinct views of a proposal.
    #[arg(long, default_value_t = 2)]
    v_min: usize,
    /// Occlusion test forming vis_mask.
    #[arg(long, value_enum, default_value = "auto")]
    visibility: VisArg,
    /// How view j's labels are sampled at warped positions.
    #[arg(long, value_enum, default_value = "bilinear")]
    sampling: SamplingArg,
    /// Depth test: relative tolerance |z_j − D_j(q)| <= tol · D_j(q).
    #[arg(long, default_value_t = 0.1)]
    depth_tolerance: f32,
    /// Depth test: rendered depth counts only where the accumulated alpha reaches this.
    #[arg(long, default_value_t = 0.5)]
    depth_min_alpha: f32,
    /// Forward-backward test: largest round-trip error in warp-grid cells.
    #[arg(long, default_value_t = 2.0)]
    fwd_bwd_tolerance: f32,
    /// Skip view pairs that have only one of their two warps (default: judge them on the
    /// one available).
    #[arg(long)]
    require_both_warps: bool,
    /// Same-view guard: two masks of one view join a proposal only when at least this many
    /// masks of other views link to both; 0 = the paper's plain connected components.
    #[arg(long, default_value_t = 1)]
    same_view_support: usize,
    /// Rendered depth maps kept in memory at once (LRU over views).
    #[arg(long, default_value_t = 8)]
    depth_cache_views: usize,
    /// Extent rule 1 (needs --gaussians; only with the same-view guard): refuse a link
    /// that unites two components of two masks or more whose 3D extents agree less than
    /// this (the larger share of one's depth points inside the other's padded box);
    /// 0 = off.
    #[arg(long, default_value_t = 0.3)]
    extent_agreement: f64,
    /// Extent rule 2 (needs --gaussians; only with the same-view guard): after the links,
    /// merge components whose padded 3D boxes have at least this IoU (largest first, the
    /// same-view guard still applies); 0 = off. Both rules 0 = the guard alone.
    #[arg(long, default_value_t = 0.1)]
    extent_merge_iou: f64,
    /// Share of a component's depth points left out on each side of each axis when its 3D
    /// box is taken.
    #[arg(long, default_value_t = 0.05)]
    extent_trim: f64,
    /// Padding of the 3D boxes on each side, as a share of the scene diagonal.
    #[arg(long, default_value_t = 0.01)]
    extent_pad: f64,
    /// How masks become proposals: `links` (the warp links of Algorithm 1, with the guard
    /// and extent rules above), `consensus` (view consensus over the Gaussians; needs
    /// --cameras and --gaussians; see the crate README), or `auto` (consensus when
    /// --cameras and --gaussians are given, else links).
    #[arg(long, value_enum, default_value = "auto")]
    grouping: GroupingArg,
    /// Consensus: a view observes a mask when at least this share of the mask's points
    /// carry a label there.
    #[arg(long, default_value_t = 0.3)]
    consensus_visible_ratio: f64,
    /// Consensus: a mask is contained in a mask of another view when more than this share
    /// of its labelled points there carry that mask's label.
    #[arg(long, default_value_t = 0.8)]
    consensus_contained_ratio: f64,
    /// Consensus: a mask split in more than this share of the views observing it is
    /// under-segmented and joins no proposal.
    #[arg(long, default_value_t = 0.5)]
    consensus_undersegment_ratio: f64,
    /// Consensus: two clusters join when the views containing both in one mask are at
    /// least this share of the views containing both.
    #[arg(long, default_value_t = 0.9)]
    consensus_threshold: f64,
    /// Consensus: most Gaussians tracked as points (every k-th beyond; all are rendered).
    #[arg(long, default_value_t = 200_000)]
    consensus_max_points: usize,
    /// Consensus: do not unite clusters along the warp links after the iterations (step 7
    /// of the crate README's consensus rules).
    #[arg(long)]
    no_consensus_link_merge: bool,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum GroupingArg {
    Auto,
    Links,
    Consensus,
}

impl ParamArgs {
    fn params(&self) -> Params {
        Params {
            tau_alpha: self.tau_alpha,
            tau_iou: self.tau_iou,
            tau_box: self.tau_box,
            s_min: self.s_min,
            v_min: self.v_min,
            sampling: match self.sampling {
                SamplingArg::Bilinear => Sampling::Bilinear,
                SamplingArg::Nearest => Sampling::Nearest,
            },
            visibility: match self.visibility {
                VisArg::Auto => Visibility::Auto,
                VisArg::None => Visibility::None,
                VisArg::Depth => Visibility::Depth,
                VisArg::FwdBwd => Visibility::FwdBwd,
                VisArg::Both => Visibility::Both,
            },
            depth_tolerance: self.depth_tolerance,
            depth_min_alpha: self.depth_min_alpha,
            fwd_bwd_tolerance: self.fwd_bwd_tolerance,
            require_both_warps: self.require_both_warps,
            depth_cache_views: self.depth_cache_views,
            same_view_support: (self.same_view_support > 0).then_some(self.same_view_support),
            extent_agreement: (self.extent_agreement > 0.0).then_some(self.extent_agreement),
            extent_merge_iou: (self.extent_merge_iou > 0.0).then_some(self.extent_merge_iou),
            extent_trim: self.extent_trim,
            extent_pad: self.extent_pad,
            grouping: match self.grouping {
                GroupingArg::Auto => Grouping::Auto,
                GroupingArg::Links => Grouping::Links,
                GroupingArg::Consensus => Grouping::Consensus,
            },
            consensus: ConsensusParams {
                visible_ratio: self.consensus_visible_ratio,
                contained_ratio: self.consensus_contained_ratio,
                undersegment_ratio: self.consensus_undersegment_ratio,
                consensus: self.consensus_threshold,
                max_points: self.consensus_max_points,
                link_merge: !self.no_consensus_link_merge,
            },
        }
    }
}

/// A library error with the input files it concerns.
#[derive(Debug)]
struct InputsError {
    files: String,
    source: WarpGraphError,
}

impl fmt::Display for InputsError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.files, self.source)
    }
}

impl Error for InputsError {
    fn source(&self) -> Option<&(dyn Error + 'static)> {
        self.source.source()
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| match cli.command {
        Command::Run {
            masks,
            matches,
            cameras,
            gaussians,
            out,
            params,
        } => run_command(
            &masks,
            &matches,
            cameras.as_deref(),
            gaussians.as_deref(),
            &out,
            &params.params(),
            quiet,
        ),
        Command::Bench {
            width,
            height,
            views,
            masks_per_view,
            grid_step,
            neighbours,
            threads,
            repeat,
            params,
        } => {
            let cfg = synthetic::Config {
                views,
                width,
                height,
                grid_step: grid_step as usize,
                masks_per_view,
                neighbours,
                warp_noise: 0.5,
                ..synthetic::Config::default()
            };
            match threads {
                Some(t) => rayon_pool(t)?.install(|| bench(&cfg, &params.params(), repeat, quiet)),
                None => bench(&cfg, &params.params(), repeat, quiet),
            }
        }
    })
}

fn rayon_pool(threads: usize) -> Result<rayon::ThreadPool, BoxError> {
    Ok(rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?)
}

fn progress_bar(quiet: bool, what: &str) -> ProgressBar {
    if !chatty(quiet) {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(0);
    if let Ok(style) =
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} view pairs {elapsed}")
    {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_message(what.to_string());
    bar
}

fn run_command(
    masks_path: &Path,
    matches_path: &Path,
    cameras_path: Option<&Path>,
    gaussians_path: Option<&Path>,
    out: &Path,
    params: &Params,
    quiet: bool,
) -> Result<Value, BoxError> {
    let start = Instant::now();
    let masks = Masks::read(masks_path)?;
    let matches = Matches::read(matches_path)?;
    let cameras = cameras_path.map(Cameras::read).transpose()?;
    let gaussians = gaussians_path.map(Gaussians::read).transpose()?;
    let mut files = format!(
        "--masks {} --matches {}",
        masks_path.display(),
        matches_path.display()
    );
    if let Some(c) = cameras_path {
        files.push_str(&format!(" --cameras {}", c.display()));
    }
    if let Some(g) = gaussians_path {
        files.push_str(&format!(" --gaussians {}", g.display()));
    }
    let with_files = |source| InputsError {
        files: files.clone(),
        source,
    };
    let mut inputs = Inputs::new(&masks, &matches);
    if let Some(c) = &cameras {
        inputs = inputs.with_cameras(c);
    }
    if let Some(g) = &gaussians {
        inputs = inputs.with_gaussians(g);
    }
    let association = Association::new(inputs, params).map_err(with_files)?;
    let bar = progress_bar(quiet, "warp-graph");
    let outcome = association
        .run(&|done, total| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        })
        .map_err(with_files)?;
    bar.finish_and_clear();
    outcome.proposals.write(out)?;
    let mut report = serde_json::to_value(&outcome.report)?;
    if let Value::Object(map) = &mut report {
        map.insert("out".into(), json!(out.display().to_string()));
        map.insert("seconds".into(), json!(start.elapsed().as_secs_f64()));
    }
    Ok(report)
}

/// CPU seconds (user + system, all threads) of this process so far, from /proc/self/stat
/// (Linux clock ticks of 1/100 s); 0 where unavailable.
fn cpu_seconds() -> f64 {
    std::fs::read_to_string("/proc/self/stat")
        .ok()
        .and_then(|s| {
            // Fields after the parenthesised command name; utime and stime are 14 and 15.
            let rest = s.rsplit_once(')')?.1;
            let f: Vec<&str> = rest.split_whitespace().collect();
            let ticks = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
            Some(ticks / 100.0)
        })
        .unwrap_or(0.0)
}

fn bench(
    cfg: &synthetic::Config,
    params: &Params,
    repeat: u64,
    quiet: bool,
) -> Result<Value, BoxError> {
    let t = Instant::now();
    let scene = synthetic::scene(cfg);
    let generate_s = t.elapsed().as_secs_f64();
    let input_mb = (scene.masks.labels.len() * 2
        + (scene.matches.warp.len() + scene.matches.certainty.len()) * 4) as f64
        / (1024.0 * 1024.0);
    let association = Association::new(Inputs::new(&scene.masks, &scene.matches), params)?;
    let bar = progress_bar(quiet, "warp-graph bench");
    let (mut best, mut best_cpu) = (f64::INFINITY, 0.0);
    let mut outcome = None;
    for _ in 0..repeat {
        let (t, cpu) = (Instant::now(), cpu_seconds());
        let o = association.run(&|done, total| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        })?;
        let wall = t.elapsed().as_secs_f64();
        if wall < best {
            (best, best_cpu) = (wall, cpu_seconds() - cpu);
        }
        outcome = Some(o);
    }
    bar.finish_and_clear();
    let Some(o) = outcome else {
        return Err("no run".into());
    };
    let scores =
        profuse_metrics::cluster::cluster_scores(&o.proposals.mask_proposal, &scene.truth)?;
    let pairs = o.report.pairs;
    Ok(json!({
        "width": cfg.width,
        "height": cfg.height,
        "grid": o.report.grid,
        "views": cfg.views,
        "masks": o.report.masks,
        "masks_per_view": o.report.masks as f64 / cfg.views.max(1) as f64,
        "pairs": pairs,
        "threads": rayon::current_num_threads(),
        "visibility": o.report.visibility,
        "sampling": o.report.sampling,
        "seconds": best,
        "cpu_s": best_cpu,
        "pairs_per_s": pairs as f64 / best,
        "mcells_per_s": o.report.cells.total as f64 / best / 1e6,
        "edges_tested": o.report.edges_tested,
        "edges_accepted": o.report.edges_accepted,
        "proposals": o.report.components.proposals,
        "ari": scores.ari,
        "generate_s": generate_s,
        "input_mb": input_mb,
        "peak_rss_mb": peak_rss_mb(),
    }))
}

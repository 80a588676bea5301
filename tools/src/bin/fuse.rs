//! `fuse`: register proposal descriptors onto Gaussians (ProFuse paper §3.3) from the
//! rasterizer's top-K weights; shard the views and merge partial sums; benchmark.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error goes to stderr, the exit code is 1 and no output file is written.

use std::ops::Range;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand, ValueEnum};
use profuse_bench::fuse as bench;
use profuse_formats::{Cameras, FileKind};
use profuse_fuse::job::{self, Job, Params, Register};
use profuse_fuse::{MemberWeight, Orphans, Precision, DEFAULT_K};
use profuse_tools::{chatty, check_outputs, init_threads, progress_bar, run, BoxError};
use serde_json::{json, Value};

#[derive(Debug, Parser)]
#[command(
    name = "fuse",
    version,
    about = "Register proposal descriptors onto Gaussians from top-K ray weights (ProFuse §3.3)",
    long_about = "Register language descriptors onto 3D Gaussians without training (ProFuse §3.3). \
                  Every view is rendered at the mask grid with its per-pixel top-K contributors \
                  (Gaussian id, weight ω = T·α); in one pass the masks' masses μ = Σ ω and a \
                  sparse Gaussian x proposal weight matrix W = Σ ω are accumulated (exactly, in \
                  fixed point). Then each proposal's descriptor is the normalised μ-weighted sum \
                  of its member masks' features, and each Gaussian's the normalised W-weighted \
                  sum of the descriptors of the proposals it was rendered into. Views can be \
                  processed in shards (--views, --partial-out) and merged (`fuse merge`) with a \
                  result identical to one run. Prints one JSON report on stdout."
)]
struct Cli {
    /// Do not print progress on stderr.
    #[arg(long, global = true)]
    quiet: bool,
    /// Worker threads (default: rayon's, i.e. RAYON_NUM_THREADS or the core count). The
    /// results do not depend on it.
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Register descriptors (all views, or a shard of them) and write the features and/or
    /// the shard's partial sums.
    Run(RunArgs),
    /// Add up partial-sums files of disjoint view shards that together cover every view,
    /// and write the features: byte-identical to an unsharded `fuse run`.
    Merge {
        /// Partial-sums files written by `fuse run --partial-out`.
        #[arg(required = true)]
        partials: Vec<PathBuf>,
        /// The features file to write (profuse.features).
        #[arg(long)]
        out: PathBuf,
        /// Storage precision of the descriptors (auto = that of the mask features).
        #[arg(long, value_enum, default_value = "auto")]
        precision: PrecisionArg,
    },
    /// Benchmark registration on a synthetic scene (synth preset `scale`, generated in a
    /// child process into a temporary or given directory; generation is not timed and its
    /// memory is not counted). Prints seconds (render + accumulate + finish), the split,
    /// views per second, nonzero W entries and peak RSS.
    Bench(bench::Params),
    /// (Internal) generate the benchmark scene; run by `bench` in a child process.
    #[command(hide = true)]
    GenerateBenchScene {
        #[arg(long)]
        out: PathBuf,
        /// The synth configuration, as JSON.
        #[arg(long)]
        config: String,
    },
}

#[derive(Debug, clap::Args)]
struct RunArgs {
    /// Gaussians (profuse.gaussians) to register descriptors onto.
    #[arg(long)]
    gaussians: PathBuf,
    /// Cameras of the views (profuse.cameras).
    #[arg(long)]
    cameras: PathBuf,
    /// Masks with their features (profuse.masks), view v = view v of the cameras.
    #[arg(long)]
    masks: PathBuf,
    /// 3D Context Proposals (profuse.proposals) grouping the masks.
    #[arg(long, required_unless_present = "no_proposals")]
    proposals: Option<PathBuf>,
    /// No proposals: every mask registers its own feature (the Dr. Splat-style baseline).
    #[arg(long, conflicts_with_all = ["proposals", "orphans", "registration", "member_weight", "pixel_share_power"])]
    no_proposals: bool,
    /// What a mask's pixels register. `proposals` (paper): the proposal's descriptor
    /// f̄_P = normalise(Σ μ_k f_k over its masks). `blend`: per mask m,
    /// normalise(α f̄_P + (1 − α) f_m / |f_m|) with α = clamp(a_m / c_P, 0, 1),
    /// a_m = cos(f_m, f̄_P) and c_P the μ-weighted mean of a_k over the proposal: a mask as
    /// coherent as the proposal's average member keeps f̄_P, one orthogonal to it keeps
    /// its own feature, so the minority object of an impure proposal is not overwritten.
    /// W then has one column per mask (like --no-proposals), which costs memory and time.
    #[arg(long, value_enum, default_value = "proposals")]
    registration: Register,
    /// What a member mask k weighs in f̄_P. `share` (default): μ_k · s_k, with s_k the
    /// proposals file's `mask_share` (the share of the mask that the other views find on
    /// one object; the consensus grouping writes it), so that the part of a mask lying on
    /// a neighbouring object does not enter the proposal's descriptor; μ_k where the file
    /// has no shares. `mass`: μ_k (the paper's eq. proposal-desc).
    #[arg(long, value_enum, default_value = "share")]
    member_weight: MemberWeight,
    /// The exponent e of a member mask's pixel weights in W: every top-K hit of a pixel of
    /// member m weighs ω · s_m^e, s_m the proposals file's `mask_share`, so a mask the
    /// other views find partly on a neighbouring object (a chair mask running onto the
    /// floor) registers its proposal's descriptor with less weight everywhere, and where
    /// it overlaps the neighbour that object's own masks decide. Orphans weigh ω. 0: the
    /// paper (ω alone; also when the file has no shares). Finite, >= 0.
    #[arg(long, default_value_t = profuse_fuse::DEFAULT_PIXEL_SHARE_POWER)]
    pixel_share_power: f64,
    /// The features file to write (profuse.features: descriptors, valid, weight_sum).
    #[arg(long, required_unless_present = "partial_out")]
    out: Option<PathBuf>,
    /// Write this run's exact partial sums (profuse.fuse_partial) for `fuse merge`.
    #[arg(long)]
    partial_out: Option<PathBuf>,
    /// Top-K contributors per pixel (1..=256).
    #[arg(long, default_value_t = DEFAULT_K as u16, value_parser = clap::value_parser!(u16).range(1..=256))]
    k: u16,
    /// Masks without a proposal: make each its own proposal with its own feature (default:
    /// masks the grouping leaves out keep their evidence), or ignore their pixels (paper).
    #[arg(long, value_enum, default_value = "singleton")]
    orphans: Orphans,
    /// Process only views a..b (half-open): a shard; with --out the features come from
    /// these views alone.
    #[arg(long, value_name = "A..B", value_parser = parse_range)]
    views: Option<Range<usize>>,
    /// Storage precision of the descriptors (auto = that of the mask features).
    #[arg(long, value_enum, default_value = "auto")]
    precision: PrecisionArg,
    /// Also write the semantic index (profuse.semantic_index, needs --out): per Gaussian
    /// its dominant proposal (U16 index) and that proposal's share of its weight, plus the
    /// proposal descriptor table, for `query --semantic-index`.
    #[arg(long, requires = "out")]
    semantic_index: Option<PathBuf>,
    /// Smallest share of a Gaussian's weight its largest proposal must hold to be its
    /// dominant proposal (in [0, 1]); the others fall back to their PQ code in a query.
    /// 0 makes every Gaussian with a proposal dominant and omits the share from the file:
    /// the index alone, 2 bytes a Gaussian (what `--semantics index` reads).
    #[arg(long, default_value_t = profuse_fuse::DEFAULT_MIN_SHARE)]
    min_share: f64,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum PrecisionArg {
    /// The precision of the mask features.
    Auto,
    F16,
    F32,
}

impl PrecisionArg {
    fn precision(self) -> Option<Precision> {
        match self {
            PrecisionArg::Auto => None,
            PrecisionArg::F16 => Some(Precision::F16),
            PrecisionArg::F32 => Some(Precision::F32),
        }
    }
}

fn parse_range(s: &str) -> Result<Range<usize>, String> {
    let err = || format!("expected A..B with integers A < B, got {s:?}");
    let (a, b) = s.split_once("..").ok_or_else(err)?;
    let (a, b): (usize, usize) = (a.parse().map_err(|_| err())?, b.parse().map_err(|_| err())?);
    if a >= b {
        return Err(err());
    }
    Ok(a..b)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    run(|| {
        init_threads(cli.threads)?;
        execute(cli.command, cli.quiet)
    })
}

/// A progress bar over the views, with the (Gaussian, group) pairs of the last one.
fn view_bar(show: bool, views: u64) -> indicatif::ProgressBar {
    progress_bar(show, views, "fuse", "views")
}

fn execute(command: Command, quiet: bool) -> Result<Value, BoxError> {
    let show = chatty(quiet);
    match command {
        Command::Run(args) => run_command(args, show),
        Command::Merge {
            partials,
            out,
            precision,
        } => {
            check_outputs([out.as_path()])?;
            let report = job::merge_files(&partials, &out, precision.precision())?;
            if show {
                eprintln!("merged {} partial files", partials.len());
            }
            let mut value = serde_json::to_value(report)?;
            value["partials"] = json!(partials
                .iter()
                .map(|p| p.to_string_lossy())
                .collect::<Vec<_>>());
            Ok(value)
        }
        Command::Bench(args) => bench(args, show),
        Command::GenerateBenchScene { out, config } => {
            profuse_bench::common::generate(&out, &config)
        }
    }
}

fn run_command(a: RunArgs, show: bool) -> Result<Value, BoxError> {
    check_outputs(
        a.out
            .iter()
            .chain(&a.partial_out)
            .chain(&a.semantic_index)
            .map(|p| p.as_path()),
    )?;
    let views = match &a.views {
        Some(v) => v.len(),
        None => Cameras::read(&a.cameras)?.len(),
    };
    let job = Job {
        gaussians: a.gaussians,
        cameras: a.cameras,
        masks: a.masks,
        proposals: a.proposals,
        out: a.out,
        partial_out: a.partial_out,
        views: a.views,
        precision: a.precision.precision(),
        semantic_index: a.semantic_index,
    };
    let params = Params {
        k: usize::from(a.k),
        orphans: a.orphans,
        no_proposals: a.no_proposals,
        registration: a.registration,
        member_weight: a.member_weight,
        pixel_share_power: a.pixel_share_power,
        min_share: a.min_share,
    };
    let bar = view_bar(show, views as u64);
    let run = job::run(&job, &params, &mut |r| {
        bar.inc(1);
        bar.set_message(format!("{} pairs", r.nnz));
    })?;
    bar.finish_and_clear();
    Ok(serde_json::to_value(run.report)?)
}

fn bench(params: bench::Params, show: bool) -> Result<Value, BoxError> {
    let bar = view_bar(show, params.views as u64);
    let report = bench::run(&params, show, &mut |r| {
        bar.inc(1);
        bar.set_message(format!("{} pairs", r.nnz));
    })?;
    bar.finish_and_clear();
    Ok(report)
}

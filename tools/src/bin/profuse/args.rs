//! The command line of `profuse`: every subcommand and option with its help.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};
use profuse_pipeline::StageName;

#[derive(Parser, Debug)]
#[command(
    name = "profuse",
    version,
    about = "ProFuse: open-vocabulary 3D Gaussians without render-supervised training"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Make a scene directory from a capture: photos alone (COLMAP poses), a COLMAP
    /// project, or a transforms.json, optionally with a splat trained elsewhere. Stages
    /// (each skipped when up to date): sfm, poses (undistort and cut), correspondences
    /// (COLMAP's tracks or keypoint pairs), gs-init and gs-refine (or the given splat),
    /// masks (SAM), features (CLIP crops with --clip-image), prompts (with --clip-text),
    /// warps. Prints one JSON report (also SCENE/prepare.json); `profuse run SCENE` then
    /// fuses the scene and `profuse view SCENE/out` shows it.
    Prepare(crate::prepare::PrepareArgs),
    /// Validate a ProFuse file and print its kind, version, tensors, metadata and counts as
    /// JSON on stdout. Exit code 0 when valid, 1 when invalid (the error also goes to stderr).
    Inspect {
        /// The file to inspect (any kind of SPEC.md).
        file: PathBuf,
    },
    /// Run every stage on a scene directory (SPEC.md §6): gs-init, gs-refine (only with
    /// gs_refine.iterations > 0), warp-graph, fuse, pq,
    /// query (LERF layout over gt/label frames when present) and vertex-transfer (when
    /// gt/mesh.safetensors exists). A stage is skipped when its outputs are newer than its
    /// inputs and its parameters are unchanged. Prints the timing table (paper Table 4
    /// shape) on stderr and one JSON summary, with ground-truth scores when gt/ exists, on
    /// stdout.
    Run {
        /// The scene directory.
        scene: PathBuf,
        /// Use this proposals file (another grouping's, or ground truth) instead of running
        /// warp-graph; it must have one entry per mask of SCENE/masks.safetensors.
        #[arg(long, value_name = "FILE")]
        proposals: Option<PathBuf>,
        /// Use this Gaussians file (SPEC.md §4.2: a trained splat converted with
        /// `scene-io`, or the geometry of another run of the same photos) instead of
        /// running gs-init and gs-refine; it is checked and copied to out/.
        #[arg(long, value_name = "FILE")]
        gaussians: Option<PathBuf>,
        /// Stop after this stage (gs-init, gs-refine, warp-graph, fuse, pq, query,
        /// vertex-transfer);
        /// a run that stops early prints its stages but no scores. Used to split a run
        /// into parts, e.g. `--until warp-graph`, then `fuse-shard` per view range (on any
        /// machine that sees the files), then `--fuse-partials`.
        #[arg(long, value_name = "STAGE")]
        until: Option<StageName>,
        /// Finish the fuse stage from these partial-sums files (written by `profuse
        /// fuse-shard` over disjoint view ranges that together cover every view) instead of
        /// rendering: byte-identical features. Shards made from other Gaussians,
        /// proposals, masks or fuse parameters are refused.
        #[arg(long, value_name = "FILE", num_args = 1..)]
        fuse_partials: Vec<PathBuf>,
        /// Finish the warp-graph stage from these evidence files (written by `profuse
        /// warp-shard` over disjoint view-pair ranges that together cover every view pair)
        /// instead of computing every pair: byte-identical proposals. Shards made from
        /// other masks, matches, cameras, Gaussians or warp_graph parameters are refused.
        #[arg(long, value_name = "FILE", num_args = 1..)]
        warp_partials: Vec<PathBuf>,
        /// Per-Gaussian semantics the query and vertex-transfer stages read (config key
        /// query.semantics): `pq` (PQ codes of every Gaussian, default), `index` (fuse
        /// also writes out/semantic_index.safetensors: each Gaussian's dominant proposal,
        /// 2 bytes, plus the proposal descriptor table; a prompt scores the P proposals)
        /// or `both` (the index, with PQ codes for Gaussians without a dominant proposal).
        #[arg(long, value_enum)]
        semantics: Option<profuse_query::Semantics>,
        #[command(flatten)]
        common: Common,
    },
    /// One view-pair shard of a run's warp-graph stage: compute the mask-pair evidence of
    /// view pairs A..B (half-open; the run's unordered view pairs in ascending (i, j)
    /// order) from SCENE and the Gaussians under --out-dir (from `profuse run --until
    /// gs-refine`) with the run's configuration, and write it to --partial-out for
    /// `profuse run --warp-partials`. Takes no lock and writes only --partial-out
    /// (atomically). Prints a JSON report on stdout whose `view_pairs` is the run's number
    /// of view pairs T (`--pairs 0..0` writes an empty shard and tells T).
    WarpShard {
        /// The scene directory.
        scene: PathBuf,
        /// The view pairs to compute, `A..B` (half-open, B <= T).
        #[arg(long, value_name = "A..B", value_parser = pair_range)]
        pairs: std::ops::Range<usize>,
        /// The evidence file to write (profuse.warp_partial).
        #[arg(long, value_name = "FILE")]
        partial_out: PathBuf,
        #[command(flatten)]
        common: Common,
    },
    /// One view shard of a run's fuse stage: render views A..B (half-open) of SCENE into
    /// the Gaussians and proposals under --out-dir (from `profuse run --until warp-graph`)
    /// with the run's configuration (give --config OUT/config.toml), and write the exact
    /// partial sums to --partial-out for `profuse run --fuse-partials`. Takes no lock and
    /// writes only --partial-out (atomically), so shards run in parallel on many machines.
    /// Prints the fuse report as JSON on stdout.
    FuseShard {
        /// The scene directory.
        scene: PathBuf,
        /// The views to render, `A..B` (half-open).
        #[arg(long, value_name = "A..B", value_parser = view_range)]
        views: std::ops::Range<usize>,
        /// The partial-sums file to write (profuse.fuse_partial).
        #[arg(long, value_name = "FILE")]
        partial_out: PathBuf,
        #[command(flatten)]
        common: Common,
    },
    /// Generate the synthetic demo scene (24 views, 320x240, a furnished room; --preset and
    /// --faults pick another synth scene), run the pipeline and the --no-proposals
    /// baseline, and print LERF-style selection mIoU / Acc@0.25, ScanNet-style mIoU,
    /// proposal ARI / purity / completeness, the wrong-class pixel share of both methods
    /// and timings. Overlays of the selections on the rendered views are written under
    /// OUT/out/query/overlay/.
    Demo {
        /// Scene directory to generate into (default: <temp dir>/profuse-demo).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Seed of the synthetic scene.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[command(flatten)]
        scene: SceneArgs,
        /// Print one JSON object instead of the text report.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        common: Common,
    },
    /// The accuracy harness: for every fault set (outer) and seed (inner), generate the
    /// synthetic scene, run the pipeline with the demo's settings (plus --config / --set,
    /// the same for both methods) and the --no-proposals baseline, and score both. Rows
    /// run one after the other; each equals `profuse demo --seed S --faults F --json` with
    /// the same options. Prints a table (or, with --json, one object {rows, summary}) on
    /// stdout; progress (row i/n, seed, faults, elapsed) on stderr.
    Sweep {
        /// Seeds: comma-separated seeds and inclusive ranges, e.g. `0-15`, `0,3,7`, `0-3,9`.
        #[arg(long, value_name = "LIST")]
        seeds: String,
        /// Fault sets, comma-separated (default, noisy-features, harsh-segmentation,
        /// sparse-views; see `synth --help`).
        #[arg(long, value_name = "LIST", default_value = "default")]
        faults: String,
        /// The synth preset of every scene: `tiny` (4 views at 64x48, D = 64; set `pq.m` to
        /// a divisor of 64) or `demo` (the demo scene).
        #[arg(long, default_value = "demo", value_parser = preset)]
        preset: synth::Preset,
        /// Print one JSON object {rows, summary} instead of the table.
        #[arg(long)]
        json: bool,
        /// Directory for the scenes (one subdirectory `<faults>-seed<S>` per row; the
        /// report is also written to DIR/sweep.json). Default: a temporary directory,
        /// removed at the end unless --keep.
        #[arg(long, value_name = "DIR")]
        out: Option<PathBuf>,
        /// Keep every row's scene and pipeline outputs (default: removed after the row).
        #[arg(long)]
        keep: bool,
        /// Also run each row with the ground-truth proposals (the ceiling of any grouping).
        #[arg(long)]
        oracle: bool,
        /// TOML configuration whose keys apply on top of the demo's settings (to both
        /// methods).
        #[arg(long, value_name = "TOML")]
        config: Option<PathBuf>,
        /// Override one parameter (TOML value; repeatable; after --config), e.g.
        /// `--set fuse.k=40`.
        #[arg(long = "set", value_name = "SECTION.KEY=VALUE")]
        set: Vec<String>,
        /// No progress on stderr.
        #[arg(long)]
        quiet: bool,
    },
    /// Serve a local web page that shows the scene's Gaussians (gsplat.js, served from this
    /// binary: nothing is fetched from the internet), lists the prompts, tints the
    /// Gaussians a prompt selects (relevancy from the PQ codes, threshold slider), selects
    /// by click (query by click: the clicked mask's proposal) and jumps to the scene's
    /// camera views. Prints {"url": ...} on stdout once listening; runs until stopped.
    View {
        /// A pipeline output: the scene directory (with cameras.safetensors,
        /// prompts.safetensors and out/ holding gaussians.safetensors and pq.safetensors)
        /// or its out/ directory. masks.safetensors and out/proposals.safetensors enable
        /// query by click.
        dir: PathBuf,
        /// TCP port (0: any free port).
        #[arg(long, default_value_t = 8765)]
        port: u16,
        /// Address to listen on. The default serves this machine only.
        #[arg(long, default_value = "127.0.0.1")]
        host: std::net::IpAddr,
        /// Show Gaussians without prompts: DIR (or DIR/out) holds gaussians.safetensors and
        /// DIR, DIR/scene (the layout of examples/fox.sh) or DIR/.. cameras.safetensors.
        #[arg(long)]
        gaussians_only: bool,
        /// No messages on stderr.
        #[arg(long)]
        quiet: bool,
    },
}

/// `A..B` with A < B.
fn view_range(s: &str) -> Result<std::ops::Range<usize>, String> {
    let r = profuse_tools::half_open_range(s, "view")?;
    if r.is_empty() {
        return Err(format!("empty view range {s:?}: A must be below B"));
    }
    Ok(r)
}

/// A view-pair range; `A..A` (empty) is allowed: it asks for T alone.
fn pair_range(s: &str) -> Result<std::ops::Range<usize>, String> {
    profuse_tools::half_open_range(s, "view-pair")
}

/// The synth presets an experiment runs on (see the argument help).
fn preset(name: &str) -> Result<synth::Preset, String> {
    match name {
        "tiny" | "demo" => synth::Preset::parse(name).map_err(|e| e.to_string()),
        other => Err(format!("expected tiny or demo, got {other:?}")),
    }
}

/// The synthetic scene of `demo`.
#[derive(Args, Debug)]
pub struct SceneArgs {
    /// The synth preset: `tiny` (4 views at 64x48, D = 64; set `pq.m` to a divisor of 64)
    /// or `demo` (24 views at 320x240, 10 objects, D = 512).
    #[arg(long, default_value = "demo", value_parser = preset)]
    pub preset: synth::Preset,
    /// The synth fault set applied on top of the preset (see `synth --help`).
    #[arg(long, value_name = "NAME", default_value = "default",
          value_parser = clap::builder::PossibleValuesParser::new(synth::FaultSet::NAMES))]
    pub faults: String,
}

#[derive(Args, Debug)]
pub struct Common {
    /// TOML configuration (sections gs_init, gs_refine, warp_graph, fuse, pq, query,
    /// vertex_transfer;
    /// `out/config.toml` of a run is a complete one). For `run` missing keys take the
    /// paper's defaults; for `demo` they keep the demo's settings (gs_init.budget=3000,
    /// gs_refine.iterations=500, pq.sample=16384, pq.iters=10) and the file's keys apply
    /// on top.
    #[arg(long, value_name = "TOML")]
    pub config: Option<PathBuf>,
    /// Override one parameter, e.g. `--set fuse.k=40 --set query.threshold=0.6` (TOML
    /// values; repeatable; applied after --config).
    #[arg(long = "set", value_name = "SECTION.KEY=VALUE")]
    pub set: Vec<String>,
    /// Redo every stage even when its outputs are up to date.
    #[arg(long)]
    pub force: bool,
    /// Output directory (default: SCENE/out).
    #[arg(long, value_name = "DIR")]
    pub out_dir: Option<PathBuf>,
    /// Wait while another run holds the output directory's lock (default: fail at once).
    #[arg(long)]
    pub wait: bool,
    /// No progress bars or tables on stderr.
    #[arg(long)]
    pub quiet: bool,
}

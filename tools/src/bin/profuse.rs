//! `profuse`: the umbrella command of the ProFuse pipeline: `inspect` (SPEC.md §5 report of
//! any file), `run` (every stage with up-to-date checks), `demo` (the paper's experiment
//! against the `--no-proposals` baseline on a synth scene) and `sweep` (the demo over
//! seeds and fault sets). The work lives in `profuse_pipeline` (`cli`, `demo`, `sweep`);
//! this tool parses arguments, displays progress and prints.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};
use profuse_pipeline::cli;
use profuse_pipeline::demo::{self, DemoOptions};
use profuse_pipeline::sweep::{self, SweepEvent, SweepOptions};
use profuse_pipeline::RunOptions;
use profuse_tools::stages::StageBars;
use profuse_tools::{chatty, print_result, run, BoxError};
use serde_json::Value;

#[derive(Parser, Debug)]
#[command(
    name = "profuse",
    version,
    about = "ProFuse: open-vocabulary 3D Gaussians without render-supervised training"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Validate a ProFuse file and print its kind, version, tensors, metadata and counts as
    /// JSON on stdout. Exit code 0 when valid, 1 when invalid (the error also goes to stderr).
    Inspect {
        /// The file to inspect (any kind of SPEC.md).
        file: PathBuf,
    },
    /// Run every stage on a scene directory (SPEC.md §6): gs-init, warp-graph, fuse, pq,
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
struct SceneArgs {
    /// The synth preset: `tiny` (4 views at 64x48, D = 64; set `pq.m` to a divisor of 64)
    /// or `demo` (24 views at 320x240, 10 objects, D = 512).
    #[arg(long, default_value = "demo", value_parser = preset)]
    preset: synth::Preset,
    /// The synth fault set applied on top of the preset (see `synth --help`).
    #[arg(long, value_name = "NAME", default_value = "default",
          value_parser = clap::builder::PossibleValuesParser::new(synth::FaultSet::NAMES))]
    faults: String,
}

#[derive(Args, Debug)]
struct Common {
    /// TOML configuration (sections gs_init, warp_graph, fuse, pq, query, vertex_transfer;
    /// `out/config.toml` of a run is a complete one). For `run` missing keys take the
    /// paper's defaults; for `demo` they keep the demo's settings (gs_init.budget=3000,
    /// pq.sample=16384, pq.iters=10) and the file's keys apply on top.
    #[arg(long, value_name = "TOML")]
    config: Option<PathBuf>,
    /// Override one parameter, e.g. `--set fuse.k=40 --set query.threshold=0.6` (TOML
    /// values; repeatable; applied after --config).
    #[arg(long = "set", value_name = "SECTION.KEY=VALUE")]
    set: Vec<String>,
    /// Redo every stage even when its outputs are up to date.
    #[arg(long)]
    force: bool,
    /// Output directory (default: SCENE/out).
    #[arg(long, value_name = "DIR")]
    out_dir: Option<PathBuf>,
    /// Wait while another run holds the output directory's lock (default: fail at once).
    #[arg(long)]
    wait: bool,
    /// No progress bars or tables on stderr.
    #[arg(long)]
    quiet: bool,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::Inspect { file } => inspect(&file),
        Command::Run {
            scene,
            proposals,
            common,
        } => run(|| run_scene(&scene, proposals, &common)),
        Command::Demo {
            out,
            seed,
            scene,
            json,
            common,
        } => print_result(demo(out, seed, &scene, json, &common)),
        Command::Sweep {
            seeds,
            faults,
            preset,
            json,
            out,
            keep,
            oracle,
            config,
            set,
            quiet,
        } => print_result((|| {
            let opts = SweepOptions {
                seeds: sweep::parse_seeds(&seeds)?,
                faults: sweep::parse_fault_sets(&faults)?,
                preset,
                out,
                keep,
                config: cli::demo_config(config.as_deref(), &set)?,
                oracle,
            };
            run_sweep(&opts, json, quiet)
        })()),
    }
}

fn inspect(file: &Path) -> ExitCode {
    let report = profuse_formats::inspect(file);
    let text = serde_json::to_string_pretty(&report.json).unwrap_or_else(|_| "{}".to_string());
    if writeln!(std::io::stdout().lock(), "{text}").is_err() {
        return ExitCode::FAILURE;
    }
    match report.error {
        None => ExitCode::SUCCESS,
        Some(e) => {
            profuse_tools::report_error(&e);
            ExitCode::FAILURE
        }
    }
}

fn run_options(common: &Common, proposals: Option<PathBuf>) -> RunOptions {
    RunOptions {
        out: common.out_dir.clone(),
        force: common.force,
        proposals,
        wait: common.wait,
    }
}

fn run_scene(scene: &Path, proposals: Option<PathBuf>, common: &Common) -> Result<Value, BoxError> {
    let config = cli::run_config(common.config.as_deref(), &common.set)?;
    let bars = StageBars::new(chatty(common.quiet));
    let opts = run_options(common, proposals);
    let value = cli::run_and_record(scene, &config, &opts, &|e| bars.event(e))?;
    print_timing(common.quiet, &value);
    Ok(value)
}

/// The paper's Table 4 on stderr, from a summary's `timing_s`, unless quiet.
fn print_timing(quiet: bool, summary: &Value) {
    if chatty(quiet) {
        if let Ok(timing) = serde_json::from_value(summary["timing_s"].clone()) {
            eprintln!("{}", cli::timing_table(&timing));
        }
    }
}

fn demo(
    out: Option<PathBuf>,
    seed: u64,
    scene: &SceneArgs,
    as_json: bool,
    common: &Common,
) -> Result<String, BoxError> {
    let show = chatty(common.quiet);
    let opts = DemoOptions {
        scene: out,
        seed,
        preset: scene.preset,
        faults: synth::FaultSet::parse(&scene.faults)?,
        config: cli::demo_config(common.config.as_deref(), &common.set)?,
        run: run_options(common, None),
    };
    let bars = StageBars::new(show);
    let value = demo::run_demo(&opts, &|e| bars.event(e), &|msg| {
        if show {
            eprintln!("{msg}");
        }
    })?;
    print_timing(common.quiet, &value);
    Ok(if as_json {
        serde_json::to_string_pretty(&value)?
    } else {
        demo::demo_text(&value)
    })
}

fn run_sweep(opts: &SweepOptions, as_json: bool, quiet: bool) -> Result<String, BoxError> {
    let show = chatty(quiet);
    let events = |e: SweepEvent<'_>| {
        if show {
            eprintln!("{}", e.line());
        }
    };
    let report = sweep::sweep(opts, &events)?;
    if show && opts.keep {
        eprintln!("scenes kept under {}", sweep::parent_dir(opts).display());
    }
    Ok(if as_json {
        serde_json::to_string_pretty(&report)?
    } else {
        sweep::text_table(&report)
    })
}

//! `profuse`: the umbrella command of the ProFuse pipeline.
//!
//! * `profuse inspect FILE` prints a JSON report of any ProFuse file (SPEC.md §5) and exits
//!   1 when the file is invalid.
//! * `profuse run SCENE_DIR` runs every stage (gs-init, warp-graph, fuse, pq, query,
//!   vertex-transfer) with up-to-date checks, prints a timing table in the paper's Table 4
//!   shape on stderr and a JSON summary on stdout.
//! * `profuse demo` generates the synthetic demo scene, runs the pipeline and its
//!   `--no-proposals` baseline, and prints the selection and ScanNet-style scores.
//! * `profuse sweep` repeats the demo's experiment over seeds and synth fault sets and
//!   prints one row per (fault set, seed) and the means.
//!
//! The experiments live in `profuse_pipeline::{demo, sweep}`; this tool parses arguments
//! and displays progress.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Mutex;

use clap::{Args, Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use profuse_pipeline::config::Config;
use profuse_pipeline::demo::{self, DemoOptions};
use profuse_pipeline::sweep::{self, SweepEvent, SweepOptions};
use profuse_pipeline::{evaluate::evaluate_run, run as run_pipeline, Event, Paths, RunOptions};
use profuse_tools::{chatty, run, BoxError};
use serde_json::{json, Value};

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
        /// The synth preset of every scene.
        #[arg(long, value_enum, default_value = "demo")]
        preset: PresetArg,
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

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum PresetArg {
    /// 4 views at 64x48, D = 64 (seconds; set `pq.m` to a divisor of 64, e.g. 16).
    Tiny,
    /// 24 views at 320x240, 10 objects, D = 512 (the demo scene).
    Demo,
}

impl PresetArg {
    fn preset(self) -> synth::Preset {
        match self {
            PresetArg::Tiny => synth::Preset::Tiny,
            PresetArg::Demo => synth::Preset::Demo,
        }
    }
}

/// The synthetic scene of `demo`.
#[derive(Args, Debug)]
struct SceneArgs {
    /// The synth preset.
    #[arg(long, value_enum, default_value = "demo")]
    preset: PresetArg,
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
    /// No progress bars or tables on stderr.
    #[arg(long)]
    quiet: bool,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::Inspect { file } => inspect(&file),
        Command::Run { scene, common } => run(|| run_scene(&scene, &common)),
        Command::Demo {
            out,
            seed,
            scene,
            json,
            common,
        } => demo(out, seed, &scene, json, &common),
        Command::Sweep {
            seeds,
            faults,
            preset,
            json,
            out,
            keep,
            config,
            set,
            quiet,
        } => {
            let opts = (|| -> Result<SweepOptions, BoxError> {
                Ok(SweepOptions {
                    seeds: sweep::parse_seeds(&seeds)?,
                    faults: sweep::parse_fault_sets(&faults)?,
                    preset: preset.preset(),
                    out,
                    keep,
                    config: demo_config(config.as_deref(), &set)?,
                })
            })();
            match opts {
                Ok(opts) => run_sweep(&opts, json, quiet),
                Err(e) => {
                    profuse_tools::report_error(&*e);
                    ExitCode::FAILURE
                }
            }
        }
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

/// The configuration from --config and --set.
fn load_config(common: &Common) -> Result<Config, BoxError> {
    let base = match &common.config {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .map_err(|e| format!("{}: cannot read the configuration: {e}", path.display()))?;
            Config::from_toml(&text, &path.display().to_string())?
        }
        None => Config::default(),
    };
    Ok(base.with_overrides(&common.set)?)
}

/// Progress display: one bar per running stage on stderr.
struct Display {
    on: bool,
    bar: Mutex<Option<ProgressBar>>,
}

impl Display {
    fn new(on: bool) -> Self {
        Display {
            on,
            bar: Mutex::new(None),
        }
    }

    fn event(&self, e: Event<'_>) {
        if !self.on {
            return;
        }
        let Ok(mut bar) = self.bar.lock() else {
            return;
        };
        match e {
            Event::Start { stage, reason } => {
                let b = ProgressBar::new(0);
                b.set_style(
                    ProgressStyle::with_template("{prefix:>16} [{bar:30}] {pos}/{len} {msg}")
                        .unwrap_or_else(|_| ProgressStyle::default_bar())
                        .progress_chars("=> "),
                );
                b.set_prefix(stage.to_string());
                b.set_message(format!("({reason})"));
                *bar = Some(b);
            }
            Event::Progress { done, total } => {
                if let Some(b) = bar.as_ref() {
                    b.set_length(total);
                    b.set_position(done);
                }
            }
            Event::Done {
                stage,
                ran,
                seconds,
            } => {
                if let Some(b) = bar.take() {
                    b.finish_and_clear();
                }
                if ran {
                    eprintln!("{stage:>16} done in {seconds:.2} s");
                } else {
                    eprintln!("{stage:>16} up to date");
                }
            }
        }
    }
}

/// The timing table in the shape of the paper's Table 4.
fn print_timing(t: &std::collections::BTreeMap<String, f64>) {
    let get = |k: &str| t.get(k).copied().unwrap_or(0.0);
    eprintln!();
    eprintln!(
        "{:<12} {:>10} {:>10} {:>10} {:>10}",
        "", "Geometry", "Semantics", "Total", "Indexing"
    );
    eprintln!(
        "{:<12} {:>9.2}s {:>9.2}s {:>9.2}s {:>9.2}s   (PQ)",
        "ProFuse-rs",
        get("geometry"),
        get("semantics"),
        get("total"),
        get("indexing")
    );
    eprintln!(
        "{:<12} gs-init {:.2} s; warp-graph {:.2} s + fuse {:.2} s; evaluation outputs (query, vertex-transfer) {:.2} s",
        "",
        get("gs-init"),
        get("warp-graph"),
        get("fuse") + get("fuse_baseline"),
        get("evaluation")
    );
}

fn run_scene(scene: &Path, common: &Common) -> Result<Value, BoxError> {
    let config = load_config(common)?;
    let display = Display::new(chatty(common.quiet));
    let opts = RunOptions {
        out: common.out_dir.clone(),
        force: common.force,
    };
    let summary = run_pipeline(scene, &config, &opts, &|e| display.event(e))?;
    let paths = Paths::new(scene, &summary.out, config.fuse.no_proposals);
    let scores = evaluate_run(&paths, &config, &summary)?;
    if chatty(common.quiet) {
        print_timing(&summary.timing_s);
    }
    let mut value = serde_json::to_value(&summary)?;
    if let Value::Object(map) = &mut value {
        map.insert("metrics".into(), json!(scores));
        map.insert("config".into(), json!(summary.out.join("config.toml")));
    }
    write_json(
        &summary.out.join(format!("summary{}.json", paths.suffix)),
        &value,
    )?;
    Ok(value)
}

fn write_json(path: &Path, value: &Value) -> Result<(), BoxError> {
    profuse_tools::write_file(path, &serde_json::to_vec_pretty(value)?)
}

/// The demo's configuration: DEMO_SETTINGS, then the keys of --config, then --set.
fn demo_config(config: Option<&Path>, set: &[String]) -> Result<Config, BoxError> {
    let text = match config {
        Some(path) => Some(
            std::fs::read_to_string(path)
                .map_err(|e| format!("{}: cannot read the configuration: {e}", path.display()))?,
        ),
        None => None,
    };
    let label = config.map(|p| p.display().to_string()).unwrap_or_default();
    Ok(demo::demo_config(
        text.as_deref().map(|t| (t, label.as_str())),
        set,
    )?)
}

fn demo(
    out: Option<PathBuf>,
    seed: u64,
    scene: &SceneArgs,
    as_json: bool,
    common: &Common,
) -> ExitCode {
    let body = || -> Result<Value, BoxError> {
        let show = chatty(common.quiet);
        let opts = DemoOptions {
            scene: out,
            seed,
            preset: scene.preset.preset(),
            faults: synth::FaultSet::parse(&scene.faults)?,
            config: demo_config(common.config.as_deref(), &common.set)?,
            run: RunOptions {
                out: common.out_dir.clone(),
                force: common.force,
            },
        };
        let display = Display::new(show);
        let value = demo::run_demo(&opts, &|e| display.event(e), &|msg| {
            if show {
                eprintln!("{msg}");
            }
        })?;
        if show {
            if let Ok(timing) = serde_json::from_value(value["timing_s"].clone()) {
                print_timing(&timing);
            }
        }
        Ok(value)
    };
    match body() {
        Ok(value) => {
            let text = if as_json {
                serde_json::to_string_pretty(&value).unwrap_or_default()
            } else {
                demo::demo_text(&value)
            };
            if writeln!(std::io::stdout().lock(), "{text}").is_err() {
                return ExitCode::FAILURE;
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            profuse_tools::report_error(&*e);
            ExitCode::FAILURE
        }
    }
}

fn run_sweep(opts: &SweepOptions, as_json: bool, quiet: bool) -> ExitCode {
    let show = chatty(quiet);
    let events = |e: SweepEvent<'_>| {
        if !show {
            return;
        }
        match e {
            SweepEvent::RowStart {
                index,
                total,
                seed,
                faults,
                elapsed,
            } => eprintln!("row {index}/{total}: seed {seed}, faults {faults} ({elapsed:.0} s elapsed)"),
            SweepEvent::RowDone {
                index,
                total,
                row,
                elapsed,
            } => eprintln!(
                "row {index}/{total} done in {:.1} s: LERF mIoU {:.2} vs {:.2} ({elapsed:.0} s elapsed)",
                row.seconds, row.lerf_miou, row.baseline_lerf_miou
            ),
        }
    };
    match sweep::sweep(opts, &events) {
        Ok(report) => {
            if show && opts.keep {
                eprintln!("scenes kept under {}", sweep::parent_dir(opts).display());
            }
            let text = if as_json {
                serde_json::to_string_pretty(&report).unwrap_or_default()
            } else {
                sweep::text_table(&report)
            };
            if writeln!(std::io::stdout().lock(), "{text}").is_err() {
                return ExitCode::FAILURE;
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            profuse_tools::report_error(&e);
            ExitCode::FAILURE
        }
    }
}

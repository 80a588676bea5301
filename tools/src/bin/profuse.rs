//! `profuse`: the umbrella command of the ProFuse pipeline.
//!
//! * `profuse inspect FILE` prints a JSON report of any ProFuse file (SPEC.md §5) and exits
//!   1 when the file is invalid.
//! * `profuse run SCENE_DIR` runs every stage (gs-init, warp-graph, fuse, pq, query,
//!   vertex-transfer) with up-to-date checks, prints a timing table in the paper's Table 4
//!   shape on stderr and a JSON summary on stdout.
//! * `profuse demo` generates the synthetic demo scene, runs the pipeline and its
//!   `--no-proposals` baseline, and prints the selection and ScanNet-style scores.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Mutex;

use clap::{Args, Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use profuse_pipeline::config::Config;
use profuse_pipeline::{
    evaluate::evaluate, run as run_pipeline, Event, Paths, RunOptions, Summary,
};
use profuse_tools::{chatty, run, BoxError};
use serde_json::{json, Map, Value};

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
    /// Generate the synthetic demo scene (24 views, 320x240, a furnished room), run the
    /// pipeline and the --no-proposals baseline, and print LERF-style selection mIoU /
    /// Acc@0.25, ScanNet-style mIoU, proposal ARI and timings. Overlays of the selections on
    /// the rendered views are written under OUT/out/query/overlay/.
    Demo {
        /// Scene directory to generate into (default: <temp dir>/profuse-demo).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Seed of the synthetic scene.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Print one JSON object instead of the text report.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        common: Common,
    },
}

#[derive(Args, Debug)]
struct Common {
    /// TOML configuration (sections gs_init, warp_graph, fuse, pq, query, vertex_transfer;
    /// missing keys take the paper's defaults; `out/config.toml` of a run is a complete one).
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
            json,
            common,
        } => demo(out, seed, json, &common),
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
fn print_timing(summary: &Summary) {
    let t = &summary.timing_s;
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
    let scores = evaluate(&paths)?;
    if chatty(common.quiet) {
        print_timing(&summary);
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

fn demo(out: Option<PathBuf>, seed: u64, as_json: bool, common: &Common) -> ExitCode {
    match demo_body(out, seed, common) {
        Ok(value) => {
            let text = if as_json {
                serde_json::to_string_pretty(&value).unwrap_or_default()
            } else {
                demo_text(&value)
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

/// The demo's departures from the paper's defaults, so that it runs in about a minute on
/// two cores: gs-init samples 3,000 matches per reference view (the paper's 15,000 are for
/// ~1000x730 photos, 2% of their pixels; 3,000 is 4% of a 320x240 view), and PQ trains on
/// 16,384 vectors (64 per centroid) for 10 iterations instead of faiss's 65,536 for 25.
const DEMO_SETTINGS: [&str; 3] = ["gs_init.budget=3000", "pq.sample=16384", "pq.iters=10"];

/// The synth `demo` preset with CLIP-like mask features: per-mask noise 1.5 (cosine to the
/// class prototype about 0.55), 10% of masks pulled toward a wrong class, and noise that
/// grows as sqrt(40000 / area) for masks under 40,000 pixels (half the view), because
/// CLIP embeds small crops less reliably. The preset's own features are nearly noise-free,
/// which leaves nothing for cross-view proposals to fix.
fn demo_scene_config(seed: u64) -> synth::Config {
    let mut c = synth::Config::preset(synth::Preset::Demo, seed);
    c.faults.feature_noise = 1.5;
    c.faults.p_wrong_class = 0.1;
    c.faults.crop_noise_px = 40_000.0;
    c
}

fn demo_body(out: Option<PathBuf>, seed: u64, common: &Common) -> Result<Value, BoxError> {
    let scene = out.unwrap_or_else(|| std::env::temp_dir().join("profuse-demo"));
    let show = chatty(common.quiet);
    let t0 = std::time::Instant::now();
    let synth_config = demo_scene_config(seed);
    let cameras = scene.join("cameras.safetensors");
    // Regenerate unless the same preset and seed are already there (a rerun is then fast).
    let marker = scene.join("gt").join("scene.json");
    let stamp = scene.join(".demo-seed");
    let fresh = std::fs::read_to_string(&stamp).ok().as_deref() == Some(&seed.to_string());
    if common.force || !fresh || !cameras.is_file() || !marker.is_file() {
        if show {
            eprintln!(
                "generating the synthetic demo scene into {}",
                scene.display()
            );
        }
        synth::generate(&synth_config, &scene)?;
        std::fs::write(&stamp, seed.to_string())?;
    }
    let generate_s = t0.elapsed().as_secs_f64();

    let config = Config::default()
        .with_overrides(&DEMO_SETTINGS.map(String::from))?
        .with_overrides(&common.set)?;
    let config = match &common.config {
        Some(_) => load_config(common)?,
        None => config,
    };
    let display = Display::new(show);
    let opts = RunOptions {
        out: common.out_dir.clone(),
        force: common.force,
    };
    let full = run_pipeline(&scene, &config, &opts, &|e| display.event(e))?;
    let mut baseline_config = config.clone();
    baseline_config.fuse.no_proposals = true;
    let baseline = run_pipeline(&scene, &baseline_config, &opts, &|e| display.event(e))?;
    let scores = evaluate(&Paths::new(&scene, &full.out, false))?;
    let base_scores = evaluate(&Paths::new(&scene, &baseline.out, true))?;
    if show {
        print_timing(&full);
    }

    let pick = |m: &std::collections::BTreeMap<String, Value>, k: &str| {
        m.get(k).cloned().unwrap_or(Value::Null)
    };
    let mut timing = Map::new();
    timing.insert("generate".into(), json!(generate_s));
    for (k, v) in &full.timing_s {
        timing.insert(k.clone(), json!(v));
    }
    for l in &baseline.stages {
        if l.stage.ends_with("_baseline") {
            timing.insert(l.stage.clone(), json!(l.seconds));
        }
    }
    timing.insert("wall".into(), json!(t0.elapsed().as_secs_f64()));
    let overlays = full.out.join("query").join("overlay");
    let value = json!({
        "scene": scene,
        "out": full.out,
        "lerf_miou": pick(&scores, "lerf_miou"),
        "lerf_acc25": pick(&scores, "lerf_acc25"),
        "baseline_lerf_miou": pick(&base_scores, "lerf_miou"),
        "baseline_lerf_acc25": pick(&base_scores, "lerf_acc25"),
        "scannet_miou19": pick(&scores, "scannet_miou19"),
        "scannet_miou15": pick(&scores, "scannet_miou15"),
        "scannet_miou10": pick(&scores, "scannet_miou10"),
        "baseline_scannet_miou19": pick(&base_scores, "scannet_miou19"),
        "proposals_ari": pick(&scores, "proposals_ari"),
        "init_median_surface_dist_rel": pick(&scores, "init_median_surface_dist_rel"),
        "timing_s": Value::Object(timing),
        "overlays": overlays,
        "metrics": scores,
        "baseline_metrics": base_scores,
    });
    write_json(&full.out.join("demo.json"), &value)?;
    Ok(value)
}

fn demo_text(v: &Value) -> String {
    let num = |k: &str| {
        v[k].as_f64()
            .map_or("n/a".to_string(), |x| format!("{x:.2}"))
    };
    let t = |k: &str| {
        v["timing_s"][k]
            .as_f64()
            .map_or("n/a".to_string(), |x| format!("{x:.2} s"))
    };
    format!(
        "ProFuse demo on the synthetic scene {scene}\n\
         \n\
         3D object selection (LERF-OVS protocol, eval frames x class prompts)\n\
         \x20 ProFuse (3D Context Proposals)   mIoU {m}  Acc@0.25 {a}\n\
         \x20 --no-proposals baseline           mIoU {bm}  Acc@0.25 {ba}\n\
         Point-cloud understanding (ScanNet protocol on the labelled mesh)\n\
         \x20 mIoU 19 classes {s19}  15 classes {s15}  10 classes {s10}\n\
         Pre-registration\n\
         \x20 proposals ARI {ari}   initial Gaussians' median distance to the surface {d} of the scene extent\n\
         Time: geometry {tg}, semantics {ts}, indexing {ti}, total {tt} (wall {tw})\n\
         Selections over the rendered views: {ov}/<frame>/<prompt>.png",
        scene = v["scene"].as_str().unwrap_or(""),
        m = num("lerf_miou"),
        a = num("lerf_acc25"),
        bm = num("baseline_lerf_miou"),
        ba = num("baseline_lerf_acc25"),
        s19 = num("scannet_miou19"),
        s15 = num("scannet_miou15"),
        s10 = num("scannet_miou10"),
        ari = num("proposals_ari"),
        d = v["init_median_surface_dist_rel"]
            .as_f64()
            .map_or("n/a".into(), |x| format!("{:.2e}", x)),
        tg = t("geometry"),
        ts = t("semantics"),
        ti = t("indexing"),
        tt = t("total"),
        tw = t("wall"),
        ov = v["overlays"].as_str().unwrap_or(""),
    )
}

//! `query`: open-vocabulary 3D selection (paper §3.4, §4.2). Scores every Gaussian's
//! descriptor against text prompts, selects the active Gaussians in 3D, and writes per
//! view activation masks (PNG), overlays and the selection files.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error goes to stderr and the exit code is 1; bad input writes nothing.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::{Args, Parser, Subcommand};
use profuse_bench::query as bench;
use profuse_formats::FileKind;
use profuse_query::{
    stats, DescriptorPath, Inputs, Layout, PromptSelection, QueryOptions, Rule, ScoreInputs,
    ScoreKind, ViewSelection, DEFAULT_GAMMA, DEFAULT_TOP_K,
};
use profuse_tools::{chatty, init_threads, progress_bar, run, BoxError};
use serde_json::{json, Value};

#[derive(Debug, Parser)]
#[command(
    name = "query",
    version,
    about = "Open-vocabulary 3D selection: prompt scores, active Gaussians, per-view masks",
    long_about = "Scores every Gaussian's language descriptor (a features or pq file) against \
                  text prompts (a prompts file), selects the active Gaussians directly in 3D \
                  (score >= threshold, or a top fraction), and writes for each view an \
                  activation mask: pixel p is selected when the active Gaussians among its \
                  top-K contributors carry at least gamma of its blending weight (paper eq. \
                  actmask). Each view's top-K is rendered once for all prompts. Prints one \
                  JSON report on stdout."
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
    /// Select Gaussians for prompts and write selections, masks and overlays. Outputs with
    /// `--layout prompt` (default): OUT/<prompt>/selection.safetensors,
    /// OUT/<prompt>/masks/<stem>.png (8-bit grey, 0 or 255), OUT/<prompt>/overlay/<stem>.png;
    /// with `--layout lerf` (what the LERF-OVS evaluation reads): OUT/<stem>/<prompt>.png,
    /// OUT/selection/<prompt>.safetensors, OUT/overlay/<stem>/<prompt>.png. <stem> is the
    /// file stem of the view's image name.
    Run(RunArgs),
    /// Score prompts without rendering: per prompt the score distribution and the best
    /// Gaussians (with --pq and cosine, found by an ADC shortlist re-ranked with the
    /// decoded descriptors, paper §3.4); optionally every valid Gaussian's score as a
    /// selection file per prompt.
    Scores(ScoresArgs),
    /// Benchmark on synthetic data: cosine and relevancy scoring of exact (F16) and PQ
    /// descriptors, selection, and activation masks from a top-K buffer; one JSON object.
    Bench {
        #[command(flatten)]
        params: bench::Params,
        /// Worker threads (default: rayon's).
        #[arg(long)]
        threads: Option<usize>,
    },
}

#[derive(Debug, Args)]
struct DescriptorArgs {
    /// Per-Gaussian descriptors: a profuse.features file (exact scores).
    #[arg(long, conflicts_with = "pq", required_unless_present = "pq")]
    features: Option<PathBuf>,
    /// Per-Gaussian descriptors: a profuse.pq file (ADC scores = cosines with the decoded
    /// descriptors).
    #[arg(long)]
    pq: Option<PathBuf>,
    /// Prompt embeddings (profuse.prompts), in the descriptors' embedding space.
    #[arg(long)]
    prompts: PathBuf,
}

impl DescriptorArgs {
    fn source(&self) -> Result<DescriptorPath, BoxError> {
        match (&self.features, &self.pq) {
            (Some(f), None) => Ok(DescriptorPath::Features(f.clone())),
            (None, Some(p)) => Ok(DescriptorPath::Pq(p.clone())),
            _ => Err("give exactly one of --features and --pq".into()),
        }
    }
}

#[derive(Debug, Args)]
struct PromptArgs {
    /// A prompt name of the prompts file to query (repeat for several; all share one
    /// render pass).
    #[arg(long = "prompt", value_name = "NAME")]
    prompt_names: Vec<String>,
    /// Query every prompt with a class id >= 0 (the file's `class_ids`).
    #[arg(long, conflicts_with_all = ["prompt_names", "all_prompts"])]
    all_classes: bool,
    /// Query every prompt except the canonical negatives (object, things, stuff, texture).
    #[arg(long, conflicts_with = "prompt_names")]
    all_prompts: bool,
    /// Score: `cosine` = <q, f> (paper), `relevancy` = LERF's min over the canonical
    /// negatives of softmax(10 [cos(q,f), cos(n,f)])_0.
    #[arg(long, value_enum, default_value = "cosine")]
    score: ScoreKind,
}

impl PromptArgs {
    fn selection(&self) -> Result<PromptSelection, BoxError> {
        if self.all_classes {
            Ok(PromptSelection::AllClasses)
        } else if self.all_prompts {
            Ok(PromptSelection::All)
        } else if !self.prompt_names.is_empty() {
            Ok(PromptSelection::Names(self.prompt_names.clone()))
        } else {
            Err("give --prompt NAME (repeatable), --all-classes or --all-prompts".into())
        }
    }
}

#[derive(Debug, Args)]
struct RunArgs {
    /// The Gaussians the descriptors belong to (profuse.gaussians).
    #[arg(long)]
    gaussians: PathBuf,
    /// The cameras of the views to render (profuse.cameras).
    #[arg(long)]
    cameras: PathBuf,
    #[command(flatten)]
    descriptors: DescriptorArgs,
    #[command(flatten)]
    prompt: PromptArgs,
    /// Active set: Gaussians with score >= T. Required for cosine unless --top-frac is
    /// given (the paper tunes tau by a grid search); relevancy defaults to 0.5 (the
    /// prompt beats every canonical negative).
    #[arg(
        long,
        value_name = "T",
        conflicts_with = "top_frac",
        allow_hyphen_values = true
    )]
    threshold: Option<f32>,
    /// Active set: the best fraction F in [0, 1] of the Gaussians with a descriptor (ties
    /// to the lower id).
    #[arg(long, value_name = "F")]
    top_frac: Option<f64>,
    /// Silhouette threshold: a pixel is in the mask when the blending weights of the
    /// active Gaussians among its top-K contributors sum to >= G.
    #[arg(long, value_name = "G", default_value_t = DEFAULT_GAMMA)]
    gamma: f32,
    /// Top-K contributors per pixel (1..=256).
    #[arg(long, default_value_t = DEFAULT_TOP_K as u16, value_parser = clap::value_parser!(u16).range(1..=256))]
    k: u16,
    /// Views to write, as indices into the cameras file (comma-separated; default all).
    #[arg(long, value_delimiter = ',', conflicts_with = "views_from_labels")]
    views: Vec<usize>,
    /// Write only the views whose image stem has a label file DIR/<stem>.json (the
    /// LERF-style gt/label/ folder of the evaluation frames).
    #[arg(long, value_name = "DIR")]
    views_from_labels: Option<PathBuf>,
    /// Render at this multiple of each camera's image size (intrinsics scaled to keep the
    /// field of view).
    #[arg(long, value_name = "S")]
    scale: Option<f64>,
    /// Output layout (see the command help).
    #[arg(long, value_enum, default_value = "prompt")]
    layout: Layout,
    /// Do not write overlays (skips the colour render).
    #[arg(long)]
    no_overlay: bool,
    /// Output directory: built next to it and swapped in whole (an existing one must be
    /// empty or an earlier query output, and is replaced).
    #[arg(long)]
    out: PathBuf,
}

#[derive(Debug, Args)]
struct ScoresArgs {
    #[command(flatten)]
    descriptors: DescriptorArgs,
    #[command(flatten)]
    prompt: PromptArgs,
    /// Best Gaussians listed per prompt.
    #[arg(long, default_value_t = 10)]
    top: usize,
    /// ADC shortlist re-ranked with the decoded descriptors (--pq with cosine only).
    #[arg(long, default_value_t = profuse_pq::DEFAULT_SHORTLIST)]
    shortlist: usize,
    /// Also write DIR/<prompt>.safetensors: a selection of every Gaussian with a
    /// descriptor and its score.
    #[arg(long, value_name = "DIR")]
    out_dir: Option<PathBuf>,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| match cli.command {
        Command::Run(a) => run_query(a, quiet),
        Command::Scores(a) => scores(a),
        Command::Bench { params, threads } => {
            init_threads(threads)?;
            bench::run(&params)
        }
    })
}

fn run_query(a: RunArgs, quiet: bool) -> Result<Value, BoxError> {
    let t0 = Instant::now();
    let source = a.descriptors.source()?;
    let inputs = Inputs::load(&a.gaussians, &a.cameras, &source, &a.descriptors.prompts)?;
    let load_s = t0.elapsed().as_secs_f64();
    let rule = match (a.threshold, a.top_frac) {
        (Some(t), _) => Some(Rule::Threshold(t)),
        (None, Some(f)) => Some(Rule::TopFraction(f)),
        (None, None) => None,
    };
    let views = if let Some(dir) = &a.views_from_labels {
        ViewSelection::FromLabels(dir.clone())
    } else if a.views.is_empty() {
        ViewSelection::All
    } else {
        ViewSelection::List(a.views.clone())
    };
    let options = QueryOptions {
        prompts: a.prompt.selection()?,
        score: a.prompt.score,
        rule,
        gamma: a.gamma,
        k: usize::from(a.k),
        scale: a.scale,
        views,
        layout: a.layout,
        overlay: !a.no_overlay,
    };
    let plan = inputs.plan(&options)?;
    let bar = progress_bar(chatty(quiet), plan.views.len() as u64, "query", "views");
    bar.set_message(format!("{} prompts", plan.prompts.len()));
    let report = plan.run_replacing(&inputs.gaussians, &a.out, &mut |_, _| bar.inc(1));
    bar.finish_and_clear();
    let report = report?;
    let mut value = serde_json::to_value(&report)?;
    value["out"] = json!(a.out.to_string_lossy());
    value["gaussians"] = json!(inputs.gaussians.len());
    value["descriptors"] = json!(source.path().to_string_lossy());
    value["load_s"] = json!(load_s);
    value["total_s"] = json!(t0.elapsed().as_secs_f64());
    Ok(value)
}

fn scores(a: ScoresArgs) -> Result<Value, BoxError> {
    let source = a.descriptors.source()?;
    let inputs = ScoreInputs::load(&source, &a.descriptors.prompts)?;
    let kind: ScoreKind = a.prompt.score;
    let which = inputs.resolve_prompts(&a.prompt.selection()?)?;
    let t0 = Instant::now();
    let all = inputs.scores(&which, kind)?;
    let score_s = t0.elapsed().as_secs_f64();
    if let Some(dir) = &a.out_dir {
        std::fs::create_dir_all(dir)
            .map_err(|e| format!("{}: cannot create directory: {e}", dir.display()))?;
    }
    let mut prompts = Vec::new();
    for (&q, s) in which.iter().zip(&all) {
        let stats = stats::prompt_scores(&inputs, q, s, kind, a.top, a.shortlist)?;
        let mut entry = serde_json::to_value(&stats)?;
        if let Some(dir) = &a.out_dir {
            let name = profuse_query::file_name_of(&stats.prompt, Layout::Prompt)?;
            let path = dir.join(format!("{name}.safetensors"));
            stats::every_valid_selection(&stats.prompt, kind, s)?.write(&path)?;
            entry["file"] = json!(path.to_string_lossy());
        }
        prompts.push(entry);
    }
    Ok(json!({
        "score": kind,
        "descriptors": source.path().to_string_lossy(),
        "gaussians": inputs.descriptors().len(),
        "top_method": match (&source, kind) {
            (DescriptorPath::Pq(_), ScoreKind::Cosine) => "adc_shortlist_exact_rerank",
            _ => "full_scan",
        },
        "prompts": prompts,
        "score_s": score_s,
    }))
}

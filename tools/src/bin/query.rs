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

use clap::{Args, Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use profuse_formats::label_space::CANONICAL_NEGATIVES;
use profuse_formats::{f16, Features, FileKind, Floats, Prompts, Selection};
use profuse_query::{
    activation, score_prompts, select, ActiveSet, DescriptorPath, DescriptorSet, Descriptors,
    Inputs, Layout, Membership, PromptSelection, QueryOptions, Rule, ScoreInputs, ScoreKind,
    ViewSelection, DEFAULT_GAMMA, DEFAULT_TOP_K,
};
use profuse_tools::{chatty, peak_rss_mb, run, BoxError};
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
    Bench(BenchArgs),
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
    score: Score,
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

#[derive(Debug, Clone, Copy, ValueEnum)]
enum Score {
    /// <q, f>, both normalised (paper §3.4).
    Cosine,
    /// LERF relevancy against the canonical negatives in the prompts file.
    Relevancy,
}

impl From<Score> for ScoreKind {
    fn from(s: Score) -> ScoreKind {
        match s {
            Score::Cosine => ScoreKind::Cosine,
            Score::Relevancy => ScoreKind::Relevancy,
        }
    }
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum LayoutArg {
    /// OUT/<prompt>/{selection.safetensors, masks/<stem>.png, overlay/<stem>.png}.
    Prompt,
    /// OUT/<stem>/<prompt>.png, OUT/selection/<prompt>.safetensors,
    /// OUT/overlay/<stem>/<prompt>.png (the LERF-OVS evaluation's PRED/<frame>/<query>.png).
    Lerf,
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
    layout: LayoutArg,
    /// Do not write overlays (skips the colour render).
    #[arg(long)]
    no_overlay: bool,
    /// Output directory (created; existing files of the same names are replaced).
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

#[derive(Debug, Args)]
struct BenchArgs {
    /// Gaussians with PQ codes.
    #[arg(long, default_value_t = 1_000_000)]
    gaussians: usize,
    /// Gaussians with exact F16 descriptors (N x D x 2 bytes are allocated).
    #[arg(long, default_value_t = 200_000)]
    exact_gaussians: usize,
    /// Descriptor dimension D.
    #[arg(long, default_value_t = 512)]
    dim: usize,
    /// PQ sub-quantisers M (D must be a multiple).
    #[arg(long, default_value_t = 128)]
    m: usize,
    /// Prompts scored together.
    #[arg(long, default_value_t = 4)]
    prompts: usize,
    /// Width of the synthetic top-K buffer.
    #[arg(long, default_value_t = 1920)]
    width: usize,
    /// Height of the synthetic top-K buffer.
    #[arg(long, default_value_t = 1080)]
    height: usize,
    /// K of the synthetic top-K buffer.
    #[arg(long, default_value_t = 10)]
    k: usize,
    /// Repetitions per measurement (the fastest is reported).
    #[arg(long, default_value_t = 3)]
    repeat: usize,
    /// Worker threads (default: rayon's).
    #[arg(long)]
    threads: Option<usize>,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| match cli.command {
        Command::Run(a) => run_query(a, quiet),
        Command::Scores(a) => scores(a),
        Command::Bench(a) => bench(a),
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
        score: a.prompt.score.into(),
        rule,
        gamma: a.gamma,
        k: usize::from(a.k),
        scale: a.scale,
        views,
        layout: match a.layout {
            LayoutArg::Prompt => Layout::Prompt,
            LayoutArg::Lerf => Layout::Lerf,
        },
        overlay: !a.no_overlay,
    };
    let plan = inputs.plan(&options)?;
    let bar = if chatty(quiet) {
        let pb = ProgressBar::new(plan.views.len() as u64);
        if let Ok(style) = ProgressStyle::with_template(
            "query {bar:40} {pos}/{len} views [{elapsed} < {eta}] {msg}",
        ) {
            pb.set_style(style);
        }
        pb.set_message(format!("{} prompts", plan.prompts.len()));
        pb
    } else {
        ProgressBar::hidden()
    };
    let report = plan.run(&inputs.gaussians, &a.out, &mut |_, _| bar.inc(1));
    bar.finish_and_clear();
    let report = report?;
    let mut value = serde_json::to_value(&report)?;
    value["out"] = json!(a.out);
    value["gaussians"] = json!(inputs.gaussians.len());
    value["descriptors"] = json!(source.path());
    value["load_s"] = json!(load_s);
    value["total_s"] = json!(t0.elapsed().as_secs_f64());
    Ok(value)
}

fn scores(a: ScoresArgs) -> Result<Value, BoxError> {
    let source = a.descriptors.source()?;
    let inputs = ScoreInputs::load(&source, &a.descriptors.prompts)?;
    let kind: ScoreKind = a.prompt.score.into();
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
        let name = &inputs.prompts.names[q];
        let mut finite: Vec<f32> = s.iter().copied().filter(|v| v.is_finite()).collect();
        finite.sort_by(|x, y| x.total_cmp(y));
        let top = best(&inputs, q, s, kind, a.top, a.shortlist)?;
        let mut entry = json!({
            "prompt": name,
            "valid": finite.len(),
            "min": finite.first(),
            "p50": quantile(&finite, 0.5),
            "p90": quantile(&finite, 0.9),
            "p99": quantile(&finite, 0.99),
            "p999": quantile(&finite, 0.999),
            "max": finite.last(),
            "mean": (!finite.is_empty())
                .then(|| finite.iter().map(|v| f64::from(*v)).sum::<f64>() / finite.len() as f64),
            "top": top.iter().map(|(g, v)| json!([g, v])).collect::<Vec<_>>(),
        });
        if let Some(dir) = &a.out_dir {
            let all = select(s, Rule::Threshold(f32::MIN))?;
            let path = dir.join(format!(
                "{}.safetensors",
                profuse_query::file_name_of(name, Layout::Prompt)?
            ));
            score_file(name, kind, &all, s.len()).write(&path)?;
            entry["file"] = json!(path);
        }
        prompts.push(entry);
    }
    Ok(json!({
        "score": kind,
        "descriptors": source.path(),
        "gaussians": inputs.descriptors().len(),
        "top_method": match (&source, kind) {
            (DescriptorPath::Pq(_), ScoreKind::Cosine) => "adc_shortlist_exact_rerank",
            _ => "full_scan",
        },
        "prompts": prompts,
        "score_s": score_s,
    }))
}

/// The `n` best Gaussians of a prompt: for PQ cosine, the paper's ADC shortlist
/// re-ranked by the decoded descriptors; otherwise from the full scores.
fn best(
    inputs: &ScoreInputs,
    q: usize,
    scores: &[f32],
    kind: ScoreKind,
    n: usize,
    shortlist: usize,
) -> Result<Vec<(u32, f32)>, BoxError> {
    if let (DescriptorSet::Pq(pq), ScoreKind::Cosine) = (&inputs.descriptors, kind) {
        return Ok(profuse_pq::search(
            pq,
            inputs.prompts.embedding(q),
            shortlist,
            n,
        )?);
    }
    let mut ranked: Vec<(u32, f32)> = scores
        .iter()
        .enumerate()
        .filter(|(_, v)| v.is_finite())
        .map(|(g, v)| (g as u32, *v))
        .collect();
    ranked.sort_by(|x, y| y.1.total_cmp(&x.1).then(x.0.cmp(&y.0)));
    ranked.truncate(n);
    Ok(ranked)
}

fn quantile(sorted: &[f32], p: f64) -> Option<f32> {
    (!sorted.is_empty()).then(|| sorted[((sorted.len() - 1) as f64 * p).round() as usize])
}

fn score_file(prompt: &str, kind: ScoreKind, all: &ActiveSet, n: usize) -> Selection {
    Selection {
        prompt: prompt.to_string(),
        num_gaussians: n,
        gaussian_ids: all.ids.clone().into(),
        scores: all.scores.clone().into(),
        extra: [
            ("score".to_string(), kind.name().to_string()),
            ("threshold".to_string(), "-inf".to_string()),
            ("rule".to_string(), "every valid Gaussian".to_string()),
        ]
        .into_iter()
        .collect(),
    }
}

fn bench(a: BenchArgs) -> Result<Value, BoxError> {
    if let Some(t) = a.threads {
        profuse_pq::rayon::ThreadPoolBuilder::new()
            .num_threads(t)
            .build_global()?;
    }
    if a.dim == 0 || a.m == 0 || !a.dim.is_multiple_of(a.m) {
        return Err(format!("--dim {} must be a positive multiple of --m {}", a.dim, a.m).into());
    }
    let d = a.dim;
    let mut rng = SplitMix(0x9e37_79b9);
    // Prompts: random unit vectors, plus the four canonical negatives for relevancy.
    let mut names: Vec<String> = (0..a.prompts).map(|i| format!("prompt_{i}")).collect();
    names.extend(CANONICAL_NEGATIVES.map(String::from));
    let embeddings: Vec<f32> = (0..names.len() * d).map(|_| rng.normal()).collect();
    let prompts = Prompts {
        names,
        dim: d,
        embeddings: embeddings.into(),
        ..Default::default()
    };
    let which: Vec<usize> = (0..a.prompts).collect();

    // Exact F16 descriptors.
    let t = Instant::now();
    let exact = random_features(&mut rng, a.exact_gaussians, d);
    let make_exact_s = t.elapsed().as_secs_f64();
    let desc = Descriptors::Features(&exact);
    let exact_cos = fastest(a.repeat, || {
        score_prompts(desc, &prompts, &which, ScoreKind::Cosine)
    })?;
    let exact_rel = fastest(a.repeat, || {
        score_prompts(desc, &prompts, &which, ScoreKind::Relevancy)
    })?;
    drop(exact);

    // PQ codes over random centroids (ADC cost does not depend on the data).
    let pq = random_pq(&mut rng, a.gaussians, d, a.m)?;
    let desc = Descriptors::Pq(&pq);
    let one = [0usize];
    let pq_cos1 = fastest(a.repeat, || {
        score_prompts(desc, &prompts, &one, ScoreKind::Cosine)
    })?;
    let pq_cos = fastest(a.repeat, || {
        score_prompts(desc, &prompts, &which, ScoreKind::Cosine)
    })?;
    let pq_rel = fastest(a.repeat, || {
        score_prompts(desc, &prompts, &which, ScoreKind::Relevancy)
    })?;
    let scores = score_prompts(desc, &prompts, &one, ScoreKind::Cosine)?;
    let sel_thr = fastest(a.repeat, || select(&scores[0], Rule::Threshold(0.05)))?;
    let sel_frac = fastest(a.repeat, || select(&scores[0], Rule::TopFraction(0.01)))?;
    let search = fastest(a.repeat, || {
        profuse_pq::search(
            &pq,
            prompts.embedding(0),
            profuse_pq::DEFAULT_SHORTLIST,
            100,
        )
    })?;

    // Activation masks from a synthetic top-K buffer: every pixel's K ids random.
    let pixels = a.width * a.height;
    let ids: Vec<u32> = (0..pixels * a.k)
        .map(|_| (rng.next() % a.gaussians.max(1) as u64) as u32)
        .collect();
    let weights: Vec<f32> = (0..pixels * a.k)
        .map(|i| 0.5f32.powi((i % a.k) as i32 + 1))
        .collect();
    let sets: Vec<ActiveSet> = (0..a.prompts)
        .map(|q| select(&scores[0], Rule::TopFraction(0.01 * (q + 1) as f64)))
        .collect::<Result<_, _>>()?;
    let refs: Vec<&ActiveSet> = sets.iter().collect();
    let membership = Membership::new(a.gaussians, &refs);
    let act = fastest(a.repeat, || {
        activation(&ids, &weights, a.width, a.height, a.k, &membership)
    })?;
    Ok(json!({
        "gaussians": a.gaussians,
        "exact_gaussians": a.exact_gaussians,
        "dim": d,
        "m": a.m,
        "prompts": a.prompts,
        "threads": profuse_pq::rayon::current_num_threads(),
        "exact_f16_cosine_s": exact_cos,
        "exact_f16_relevancy_s": exact_rel,
        "exact_make_s": make_exact_s,
        "pq_cosine_1_prompt_s": pq_cos1,
        "pq_cosine_s": pq_cos,
        "pq_relevancy_s": pq_rel,
        "pq_search_top100_s": search,
        "select_threshold_s": sel_thr,
        "select_top_frac_s": sel_frac,
        "activation_s": act,
        "activation_mpix_per_s": pixels as f64 / 1e6 / act,
        "width": a.width,
        "height": a.height,
        "k": a.k,
        "repeat": a.repeat,
        "peak_rss_mb": peak_rss_mb(),
    }))
}

/// Seconds of the fastest of `repeat` runs of `f` (at least one).
fn fastest<T, E: Into<BoxError>>(
    repeat: usize,
    mut f: impl FnMut() -> Result<T, E>,
) -> Result<f64, BoxError> {
    let mut best = f64::INFINITY;
    for _ in 0..repeat.max(1) {
        let t = Instant::now();
        let out = f().map_err(Into::into)?;
        best = best.min(t.elapsed().as_secs_f64());
        drop(out);
    }
    Ok(best)
}

fn random_features(rng: &mut SplitMix, n: usize, d: usize) -> Features {
    let mut rows = Vec::with_capacity(n * d);
    let mut row = vec![0f32; d];
    for _ in 0..n {
        row.iter_mut().for_each(|v| *v = rng.normal());
        let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
        rows.extend(row.iter().map(|v| f16::from_f32(v / norm)));
    }
    Features {
        dim: d,
        features: Floats::F16(rows.into()),
        valid: vec![1u8; n].into(),
        weight_sum: None,
        extra: Default::default(),
    }
}

fn random_pq(
    rng: &mut SplitMix,
    n: usize,
    d: usize,
    m: usize,
) -> Result<profuse_formats::Pq, BoxError> {
    let dsub = d / m;
    let centroids: Vec<f32> = (0..m * profuse_pq::KSUB * dsub)
        .map(|_| rng.normal() / (d as f32).sqrt())
        .collect();
    let book = profuse_pq::Codebook::new(m, dsub, centroids)?;
    let codes: Vec<u8> = (0..n * m).map(|_| rng.next() as u8).collect();
    let norms: Vec<f32> = codes
        .chunks_exact(m)
        .map(|c| book.decoded_norm(c))
        .collect();
    Ok(book.to_pq(codes, norms, vec![1u8; n]))
}

/// SplitMix64: a tiny seeded generator for benchmark data.
struct SplitMix(u64);

impl SplitMix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn uniform(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// A standard normal sample (Box-Muller).
    fn normal(&mut self) -> f32 {
        let (u, v) = (self.uniform(), self.uniform());
        ((-2.0 * (1.0 - u).ln()).sqrt() * (std::f64::consts::TAU * v).cos()) as f32
    }
}

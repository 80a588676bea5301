//! `prep`: the front-end files of the semantic half from real models: SAM automatic masks,
//! mask descriptors (SAM embedding or CLIP image encoder) and CLIP text prompts.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error goes to stderr, the exit code is 1, and nothing is written.

use std::path::Path;
use std::process::ExitCode;

use clap::Parser;
use profuse_formats::{Cameras, FileKind, Masks};
use profuse_prep::amg::{box_scales, AmgParams};
use profuse_prep::clip::{make_prompts, ClipModel};
use profuse_prep::features::{clip_features, sam_features, view_labels};
use profuse_prep::image::load_rgb;
use profuse_prep::masks::{run_masks, MasksJob};
use profuse_prep::preview::overlay;
use profuse_prep::runtime::{environment, find_library, Environment};
use profuse_prep::sam::Sam;
use profuse_prep::shard;
use profuse_tools::{chatty, check_outputs, progress_bar, run, write_png, BoxError};

mod args;
mod matches;
use args::{Cli, Command, FeaturesArgs, MasksArgs};

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
        Command::Merge { shards, out } => merge(&shards, &out),
        Command::Warps(a) => profuse_tools::warps::run(a, show),
        Command::Matches(a) => matches::run(a, &env, threads, show),
    })
}

pub(crate) type EnvFn<'a> = &'a dyn Fn() -> Result<&'static Environment, BoxError>;

/// A progress callback driving a bar over views.
pub(crate) fn bar_progress(bar: &indicatif::ProgressBar) -> impl Fn(usize, usize) + '_ {
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
    if let Some(r) = a.shard.as_ref().filter(|r| r.end > cameras.len()) {
        return Err(format!(
            "--shard {}..{}: the cameras file has {} views",
            r.start,
            r.end,
            cameras.len()
        )
        .into());
    }
    let mut sam = Sam::open(env()?, &a.encoder, &a.decoder, threads)?;
    let job = MasksJob {
        cameras: &cameras,
        images: &a.scene.images,
        params,
        mask_size: a.mask_size,
        views: a.shard.clone().map(|r| r.collect()).or(a.views),
    };
    let bar = progress_bar(show, 0, "prep masks", "views");
    let (mut masks, report) = run_masks(&mut sam, &job, &bar_progress(&bar))?;
    bar.finish_and_clear();
    if let Some(r) = &a.shard {
        shard::mark(&mut masks, r);
    }
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
    let mut input = Masks::read(&a.masks)?;
    if let Some(r) = &a.shard {
        input = shard::restrict(&input, r.clone())?;
    }
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
    let mut result = result;
    if let Some(r) = &a.shard {
        shard::mark(&mut result, r);
    }
    result.write(&a.out)?;
    Ok(serde_json::to_value(report)?)
}

/// `prep merge`.
fn merge(shards: &[std::path::PathBuf], out: &Path) -> Result<serde_json::Value, BoxError> {
    check_outputs([out])?;
    let read = shards
        .iter()
        .map(|p| Ok((p.display().to_string(), Masks::read(p)?)))
        .collect::<Result<Vec<_>, BoxError>>()?;
    let merged = shard::merge(&read)?;
    merged.write(out)?;
    Ok(serde_json::json!({
        "shards": shards.len(),
        "views": merged.num_views(),
        "masks": merged.num_masks(),
        "out": out.display().to_string(),
    }))
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

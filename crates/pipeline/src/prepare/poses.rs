//! The poses stage: cameras from a transforms.json, a COLMAP model, or COLMAP run on the
//! photos; then every photo undistorted and cut to its valid area (the pinhole photos and
//! cameras every later stage reads), with the original cameras kept beside them.

use std::path::{Path, PathBuf};

use profuse_formats::{Cameras, FileKind};
use scene_io::colmap::{colmap_cameras, read_colmap_model, ColmapOptions};
use serde_json::json;

use super::layout::{photos_in, Layout};
use super::{report_json, PrepareError, PrepareOptions, Result};
use crate::error::stage_err;
use crate::run::{stage, Runner, StageLine};
use crate::PipelineError;

/// The scene's cameras once the poses stage is done.
#[derive(Debug, Clone)]
pub(crate) struct Posed {
    /// Pinhole cameras of the cut photos (`SCENE/cameras.safetensors`).
    pub cameras: Cameras,
    /// The original photos' cameras, with their lens (`SCENE/source_cameras.safetensors`),
    /// image names relative to the capture's photo folder.
    pub source: Cameras,
    /// That photo folder.
    pub source_dir: PathBuf,
    /// The COLMAP model the cameras came from (its tracks are the sparse matches).
    pub model: Option<PathBuf>,
    /// Photos of the input without a camera (COLMAP could not register them, or a
    /// transforms.json frame without its file).
    pub unregistered: Vec<PathBuf>,
    /// The same photos, each with the reason (the report's `dropped`).
    pub dropped: Vec<String>,
}

/// `SCENE/cameras.safetensors`.
pub(crate) fn cameras_path(scene: &Path) -> PathBuf {
    scene.join("cameras.safetensors")
}

/// `SCENE/source_cameras.safetensors`.
pub(crate) fn source_cameras_path(scene: &Path) -> PathBuf {
    scene.join("source_cameras.safetensors")
}

/// The photos of the input the scene is made from (every one is checked before any stage
/// runs). For a COLMAP model or a transforms.json, the photos its views name; a named
/// photo missing on disk is an error (COLMAP) or a dropped frame (transforms.json, whose
/// importer skips frames without their file and fails when none is left).
pub(crate) fn input_photos(layout: &Layout) -> Result<Vec<PathBuf>> {
    let photos = match layout {
        Layout::Photos { images } => photos_in(images),
        Layout::Colmap { images, model } => {
            let m = read_colmap_model(model).map_err(stage_err("poses"))?;
            let mut names: Vec<&str> = m.images.iter().map(|i| i.name.as_str()).collect();
            names.sort_unstable();
            let mut photos = Vec::with_capacity(names.len());
            for name in names {
                let parts =
                    scene_io::scene_relative_parts(name).map_err(|why| PrepareError::Photos {
                        path: model.display().to_string(),
                        detail: format!("image name {name:?} {why}"),
                    })?;
                let path = images.join(parts.iter().collect::<PathBuf>());
                if !path.is_file() {
                    return Err(PrepareError::Photos {
                        path: path.display().to_string(),
                        detail: format!(
                            "is missing: the COLMAP model {} registers image {name:?}, which \
                             is not on disk under {}",
                            model.display(),
                            images.display()
                        ),
                    });
                }
                photos.push(path);
            }
            photos
        }
        Layout::Transforms { json } => {
            let (cams, _) = scene_io::read_transforms(json).map_err(stage_err("poses"))?;
            let base = json.parent().unwrap_or(Path::new("."));
            cams.image_names.iter().map(|n| base.join(n)).collect()
        }
    };
    if photos.is_empty() {
        return Err(PrepareError::Photos {
            path: String::new(),
            detail: "the capture has no photos".into(),
        });
    }
    Ok(photos)
}

/// Runs the sfm stage (photos only, with `sfm`, the backend found before anything was
/// written) and the poses stage on `photos` ([`input_photos`]); returns the scene's
/// cameras.
pub(crate) fn poses(
    r: &Runner<'_>,
    opts: &PrepareOptions,
    layout: &Layout,
    photos: &[PathBuf],
    sfm: Option<&profuse_sfm::Backend>,
    lines: &mut Vec<StageLine>,
) -> Result<Posed> {
    let scene = &opts.scene;
    let (source_file, source_dir, model) = match (layout, sfm) {
        (Layout::Photos { images }, Some(backend)) => {
            let model = super::sfm::sfm_stage(r, opts, backend, images, photos, lines)?;
            (model.clone(), images.clone(), Some(model))
        }
        (Layout::Photos { .. }, None) => {
            return Err(PrepareError::Tool {
                detail: "a folder of photos needs COLMAP for its poses".into(),
            })
        }
        (Layout::Colmap { images, model }, _) => {
            (model.clone(), images.clone(), Some(model.clone()))
        }
        (Layout::Transforms { json }, _) => (
            json.clone(),
            json.parent().unwrap_or(Path::new(".")).to_path_buf(),
            None,
        ),
    };
    let mut inputs = vec![source_file.clone()];
    inputs.extend(photos.iter().cloned());
    let images_dir = scene.join("images");
    let outputs = vec![
        cameras_path(scene),
        source_cameras_path(scene),
        images_dir.clone(),
    ];
    let line = stage(
        r,
        "poses",
        json!({"layout": layout.name(), "crop": true}),
        inputs,
        outputs,
        || {
            let source = source_cameras(layout, model.as_deref())?;
            // A rerun replaces the photos as a whole: none of an earlier capture stays.
            if images_dir.exists() {
                std::fs::remove_dir_all(&images_dir).map_err(crate::error::io_err(
                    &images_dir,
                    "cannot replace the folder",
                ))?;
            }
            let (cameras, report) =
                scene_io::undistort::undistort_scene(&source, &source_dir, scene, true)
                    .map_err(stage_err("poses"))?;
            cameras
                .write(cameras_path(scene))
                .map_err(stage_err("poses"))?;
            source
                .write(source_cameras_path(scene))
                .map_err(stage_err("poses"))?;
            Ok(json!({
                "views": cameras.len(),
                "distortion": source.distortion.is_some(),
                "undistort": report_json(&report),
            }))
        },
    )?;
    lines.push(line);
    let cameras = Cameras::read(cameras_path(scene)).map_err(stage_err("poses"))?;
    let source = Cameras::read(source_cameras_path(scene)).map_err(stage_err("poses"))?;
    let unregistered = unregistered_photos(photos, &source, &source_dir);
    let why = match layout {
        Layout::Transforms { .. } => "no camera (the transforms.json frame was skipped)",
        _ => "no camera (COLMAP could not register it; left out of the scene)",
    };
    let dropped = unregistered
        .iter()
        .map(|p| format!("{}: {why}", p.display()))
        .collect();
    Ok(Posed {
        cameras,
        source,
        source_dir,
        model,
        unregistered,
        dropped,
    })
}

/// The cameras of the original photos, with their lens.
fn source_cameras(layout: &Layout, model: Option<&Path>) -> Result<Cameras, PipelineError> {
    match (layout, model) {
        (Layout::Transforms { json }, _) => Ok(scene_io::read_transforms(json)
            .map_err(stage_err("poses"))?
            .0),
        (_, Some(model)) => {
            let m = read_colmap_model(model).map_err(stage_err("poses"))?;
            // The model's image names are relative to the images folder itself.
            let options = ColmapOptions {
                images_prefix: String::new(),
                ..ColmapOptions::default()
            };
            colmap_cameras(&m, &options).map_err(stage_err("poses"))
        }
        (_, None) => Err(PipelineError::Stage {
            stage: "poses",
            source: "no pose source".into(),
        }),
    }
}

/// Photos of the input that no view names.
fn unregistered_photos(photos: &[PathBuf], source: &Cameras, source_dir: &Path) -> Vec<PathBuf> {
    let named: std::collections::BTreeSet<PathBuf> = source
        .image_names
        .iter()
        .map(|n| source_dir.join(n))
        .collect();
    photos
        .iter()
        .filter(|p| !named.contains(*p))
        .cloned()
        .collect()
}

/// The stem of a photo or image name.
fn stem(name: &str) -> String {
    Path::new(name)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// Every held-out name must name a photo of the input (by file name or stem).
pub(crate) fn check_held_out_names(photos: &[PathBuf], names: &[String]) -> Result<()> {
    let stems: Vec<String> = photos.iter().map(|p| stem(&p.to_string_lossy())).collect();
    match names.iter().find(|n| !stems.contains(&stem(n))) {
        Some(name) => Err(PrepareError::Option {
            option: "--held-out",
            detail: format!(
                "{name:?} names no photo of the capture ({} photos)",
                photos.len()
            ),
        }),
        None => Ok(()),
    }
}

/// The view indices of the held-out photos, named by file name or stem (of the original
/// photo or of the scene's image); an unknown name is an error, and so is a held-out photo
/// without a camera ([`PrepareError::HeldOutUnposed`]): a selection cannot be rendered into
/// it.
pub(crate) fn held_out_views(posed: &Posed, names: &[String]) -> Result<Vec<usize>> {
    let cameras = &posed.cameras;
    let mut views = Vec::new();
    for name in names {
        let wanted = stem(name);
        if let Some(photo) = posed
            .unregistered
            .iter()
            .find(|p| stem(&p.to_string_lossy()) == wanted)
        {
            return Err(PrepareError::HeldOutUnposed {
                photo: photo.display().to_string(),
                name: name.clone(),
                posed: cameras.len(),
                photos: cameras.len() + posed.unregistered.len(),
            });
        }
        let v = cameras
            .image_names
            .iter()
            .position(|n| stem(n) == wanted)
            .ok_or_else(|| PrepareError::Option {
                option: "--held-out",
                detail: format!(
                    "{name:?} names no view of the scene ({} views)",
                    cameras.len()
                ),
            })?;
        if !views.contains(&v) {
            views.push(v);
        }
    }
    views.sort_unstable();
    Ok(views)
}

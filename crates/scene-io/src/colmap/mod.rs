//! COLMAP sparse model (text or binary) → [`Cameras`] and seeded [`Gaussians`].
//!
//! Conventions converted:
//! * COLMAP poses are already world-to-camera in OpenCV axes: `R` from `qvec` (w, x, y, z,
//!   normalised), `t = tvec`.
//! * COLMAP puts the image origin at the top-left corner of the top-left pixel (pixel
//!   centres at +0.5), the same as ours: `cx`, `cy` are copied unchanged.
//! * Distortion: SIMPLE_RADIAL gives k1, RADIAL k1 k2, OPENCV k1 k2 p1 p2, FULL_OPENCV
//!   only when k3..k6 are zero; fisheye and other models are errors naming the model.
//!   `distortion` is written when any view has a non-zero coefficient.
//! * Image names are `images_prefix` + COLMAP's name; views are sorted by name so the
//!   output does not depend on COLMAP's image ids. A name that is absolute or has a `..`
//!   component is an error ([`crate::scene_relative_parts`]), and so is a model without
//!   any registered image.
//! * A directory with only some of the model files is an error naming the missing ones.
//!   Text files are read up to [`ColmapOptions::max_text_bytes`].
//!
//! Points seed Gaussians the way INRIA 3DGS initialises from SfM points
//! ([`seed_gaussians`]); their tracks become sparse matches for gs-init
//! ([`track_matches`]).

mod binary;
mod model;
mod text;
mod tracks;

use std::collections::BTreeMap;
use std::num::NonZeroUsize;
use std::path::{Path, PathBuf};

use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::SquaredEuclidean;
use profuse_formats::camera::{pose_row, quaternion_to_rotation, rgb8_to_sh_dc};
use profuse_formats::{Cameras, Gaussians};
use serde::Serialize;

pub use model::{
    CameraModel, ColmapCamera, ColmapFormat, ColmapImage, ColmapModel, ColmapPoint, ModelFiles,
};
pub use tracks::{
    track_matches, TrackOptions, TrackReport, DEFAULT_MIN_SHARED, DEFAULT_NEIGHBOURS,
};

use crate::error::{invalid, missing, unsupported, Result, SceneError};
use crate::fsutil::{check_image_name, show};

/// Degree-0 SH basis constant: colour = `SH_C0` · dc + 0.5.
pub use profuse_formats::camera::SH_C0;

/// Opacity every seeded Gaussian starts with (INRIA: `inverse_sigmoid(0.1)`).
pub const SEED_OPACITY: f64 = 0.1;

/// Lower bound of the mean squared neighbour distance (INRIA clamps `distCUDA2` at 1e-7),
/// so duplicate points do not get a zero (log −inf) scale.
pub const MIN_MEAN_SQUARED_DISTANCE: f64 = 1e-7;

/// Default cap on each file of a text model, [`ColmapOptions::max_text_bytes`] (2 GiB;
/// reading a text model takes about 3x its size in memory).
pub const MAX_TEXT_BYTES: u64 = 2 << 30;

/// Import options.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ColmapOptions {
    /// Prepended to COLMAP's image names to make them relative to the scene directory
    /// (default `images/`; empty for none).
    pub images_prefix: String,
    /// Largest `cameras.txt`/`images.txt`/`points3D.txt` read (default
    /// [`MAX_TEXT_BYTES`]); a bigger file is an error, not an attempt to fill memory.
    pub max_text_bytes: u64,
}

impl Default for ColmapOptions {
    fn default() -> Self {
        ColmapOptions {
            images_prefix: "images/".to_string(),
            max_text_bytes: MAX_TEXT_BYTES,
        }
    }
}

/// What [`import_colmap`] found.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ColmapReport {
    /// `text` or `binary`.
    pub format: String,
    /// COLMAP cameras (intrinsics sets).
    pub cameras: usize,
    /// Registered images imported as views.
    pub views: usize,
    /// 3D points (= seeded Gaussians).
    pub points: usize,
    /// Whether the cameras carry lens distortion.
    pub distortion: bool,
}

/// Cameras and seeded Gaussians of one sparse model.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapImport {
    pub cameras: Cameras,
    pub gaussians: Gaussians,
    pub report: ColmapReport,
}

/// Finds the model files in `dir`: binary when `cameras.bin`, `images.bin` and
/// `points3D.bin` exist, else text when the three `.txt` files exist. When neither set
/// is complete, the error names the files that are missing from the most complete one.
pub fn find_model(dir: impl AsRef<Path>) -> Result<ModelFiles> {
    let dir = dir.as_ref();
    let sets = [ColmapFormat::Binary, ColmapFormat::Text].map(|format| {
        let ext = format.extension();
        ModelFiles {
            format,
            cameras: dir.join(format!("cameras.{ext}")),
            images: dir.join(format!("images.{ext}")),
            points: dir.join(format!("points3D.{ext}")),
        }
    });
    let present = |files: &ModelFiles| {
        [&files.cameras, &files.images, &files.points]
            .into_iter()
            .filter(|p| p.is_file())
            .count()
    };
    // Binary first; on a tie (both incomplete) the binary set is named.
    let best = sets
        .iter()
        .max_by_key(|f| (present(f), f.format == ColmapFormat::Binary));
    match best {
        Some(files) if present(files) == 3 => Ok(files.clone()),
        Some(files) if present(files) > 0 => Err(incomplete_model(dir, files)),
        _ => {
            let hint = if dir.join("0").is_dir() {
                " (the directory has a `0/` subdirectory: did you mean sparse/0?)"
            } else {
                ""
            };
            Err(missing(
                &show(dir),
                "COLMAP model files",
                format!(
                    "cameras.bin, images.bin, points3D.bin or cameras.txt, images.txt, points3D.txt{hint}"
                ),
            ))
        }
    }
}

/// The error of a model directory with some but not all files of one format.
fn incomplete_model(dir: &Path, files: &ModelFiles) -> SceneError {
    let name = |p: &Path| {
        p.file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    let all = [&files.cameras, &files.images, &files.points];
    let (found, absent): (Vec<_>, Vec<_>) = all.into_iter().partition(|p| p.is_file());
    let list = |v: &[&PathBuf]| v.iter().map(|p| name(p)).collect::<Vec<_>>().join(", ");
    let why = if absent.iter().any(|p| **p == files.images) {
        "images holds every registered image and its pose: without it there are no views to import"
    } else if absent.iter().any(|p| **p == files.cameras) {
        "cameras holds the intrinsics the images refer to"
    } else {
        "points3D holds the sparse points (export the whole model, e.g. `colmap model_converter --output_type BIN`)"
    };
    missing(
        &show(dir),
        list(&absent),
        format!(
            "the {} model files cameras, images and points3D; found only {} ({why})",
            files.format.name(),
            list(&found)
        ),
    )
}

/// Reads a sparse model from a directory (format auto-detected, see [`find_model`]),
/// text files up to [`MAX_TEXT_BYTES`].
pub fn read_colmap_model(dir: impl AsRef<Path>) -> Result<ColmapModel> {
    read_colmap_model_capped(dir, MAX_TEXT_BYTES)
}

/// [`read_colmap_model`] with text files capped at `max_text_bytes`.
pub fn read_colmap_model_capped(dir: impl AsRef<Path>, max_text_bytes: u64) -> Result<ColmapModel> {
    let files = find_model(dir)?;
    let (cameras, images, points) = match files.format {
        ColmapFormat::Binary => (
            binary::read_cameras(&files.cameras)?,
            binary::read_images(&files.images)?,
            binary::read_points(&files.points)?,
        ),
        ColmapFormat::Text => (
            text::read_cameras(&files.cameras, max_text_bytes)?,
            text::read_images(&files.images, max_text_bytes)?,
            text::read_points(&files.points, max_text_bytes)?,
        ),
    };
    Ok(ColmapModel {
        files,
        cameras,
        images,
        points,
    })
}

/// Reads a sparse model and converts it.
pub fn import_colmap(dir: impl AsRef<Path>, options: &ColmapOptions) -> Result<ColmapImport> {
    let model = read_colmap_model_capped(dir, options.max_text_bytes)?;
    let cameras = colmap_cameras(&model, options)?;
    let gaussians = colmap_gaussians(&model);
    let report = ColmapReport {
        format: model.files.format.name().to_string(),
        cameras: model.cameras.len(),
        views: cameras.len(),
        points: model.points.len(),
        distortion: cameras.distortion.is_some(),
    };
    Ok(ColmapImport {
        cameras,
        gaussians,
        report,
    })
}

/// The registered images in view order: sorted by name, the order of [`colmap_cameras`]
/// (view `v` is the `v`-th image of this list). An error when the model has no image or
/// two images share a name.
pub fn view_order(model: &ColmapModel) -> Result<Vec<&ColmapImage>> {
    let images_label = show(&model.files.images);
    if model.images.is_empty() {
        return Err(invalid(
            &images_label,
            "images",
            "the model has no registered image, so there are no views to import",
        ));
    }
    let mut order: Vec<&ColmapImage> = model.images.iter().collect();
    order.sort_by(|a, b| a.name.cmp(&b.name));
    if let Some(pair) = order
        .windows(2)
        .find(|w| w.first().map(|a| &a.name) == w.get(1).map(|b| &b.name))
    {
        let name = pair.first().map_or("", |a| a.name.as_str());
        return Err(invalid(
            &images_label,
            "NAME",
            format!("image name {name:?} appears twice"),
        ));
    }
    Ok(order)
}

/// The registered images as cameras, sorted by image name ([`view_order`]).
pub fn colmap_cameras(model: &ColmapModel, options: &ColmapOptions) -> Result<Cameras> {
    let images_label = show(&model.files.images);
    let cameras_label = show(&model.files.cameras);
    let order = view_order(model)?;

    let mut names = Vec::with_capacity(order.len());
    let mut sizes = Vec::with_capacity(order.len());
    let mut intrinsics = Vec::with_capacity(order.len());
    let mut distortion = Vec::with_capacity(order.len());
    let mut poses = Vec::with_capacity(order.len());
    for image in order {
        let field = format!("image {} ({})", image.id, image.name);
        let camera = model.cameras.get(&image.camera_id).ok_or_else(|| {
            invalid(
                &images_label,
                &field,
                format!("camera_id {} is not in {cameras_label}", image.camera_id),
            )
        })?;
        let (k, d) = camera_intrinsics(camera, &cameras_label)?;
        let r = quaternion_to_rotation(image.qvec).ok_or_else(|| {
            invalid(
                &images_label,
                &field,
                format!("qvec {:?} is zero or not finite", image.qvec),
            )
        })?;
        check_image_name(&images_label, &format!("{field} NAME"), &image.name)?;
        let name = join_prefix(&options.images_prefix, &image.name);
        check_image_name(
            &images_label,
            &format!("{field} NAME with --images-prefix"),
            &name,
        )?;
        names.push(name);
        sizes.push(camera_size(camera, &cameras_label)?);
        intrinsics.push(k);
        distortion.push(d);
        poses.push(pose_row(&r, &image.tvec));
    }
    let distorted = distortion.iter().any(|d| d.iter().any(|c| *c != 0.0));
    Ok(Cameras {
        image_names: names,
        image_size: sizes.into(),
        intrinsics: intrinsics.into(),
        world_to_camera: poses.into(),
        distortion: distorted.then(|| distortion.into()),
        extra: BTreeMap::from([(
            "source".to_string(),
            format!("colmap_{}", model.files.format.name()),
        )]),
    })
}

fn join_prefix(prefix: &str, name: &str) -> String {
    let prefix = prefix.trim_end_matches('/');
    if prefix.is_empty() {
        name.to_string()
    } else {
        format!("{prefix}/{name}")
    }
}

fn camera_size(camera: &ColmapCamera, label: &str) -> Result<[u32; 2]> {
    let fit = |v: u64| u32::try_from(v).ok().filter(|v| *v > 0);
    match (fit(camera.width), fit(camera.height)) {
        (Some(w), Some(h)) => Ok([w, h]),
        _ => Err(invalid(
            label,
            format!("camera {} WIDTH/HEIGHT", camera.id),
            format!(
                "{}x{}, expected 1..=4294967295 pixels each",
                camera.width, camera.height
            ),
        )),
    }
}

/// `[fx, fy, cx, cy]` and `[k1, k2, p1, p2]` of a camera (COLMAP's principal point is
/// already in our corner-origin convention).
fn camera_intrinsics(camera: &ColmapCamera, label: &str) -> Result<([f64; 4], [f64; 4])> {
    let p = |i: usize| camera.params.get(i).copied().unwrap_or(0.0);
    let out = match camera.model {
        CameraModel::SimplePinhole => ([p(0), p(0), p(1), p(2)], [0.0; 4]),
        CameraModel::Pinhole => ([p(0), p(1), p(2), p(3)], [0.0; 4]),
        CameraModel::SimpleRadial => ([p(0), p(0), p(1), p(2)], [p(3), 0.0, 0.0, 0.0]),
        CameraModel::Radial => ([p(0), p(0), p(1), p(2)], [p(3), p(4), 0.0, 0.0]),
        CameraModel::Opencv => ([p(0), p(1), p(2), p(3)], [p(4), p(5), p(6), p(7)]),
        CameraModel::FullOpencv if (8..12).all(|i| p(i) == 0.0) => {
            ([p(0), p(1), p(2), p(3)], [p(4), p(5), p(6), p(7)])
        }
        other => {
            return Err(unsupported(
                label,
                "camera model",
                format!(
                    "camera {} uses {} (readable: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV with k3..k6 = 0); undistort the images with COLMAP first",
                    camera.id,
                    other.name()
                ),
            ))
        }
    };
    if out.0[0] <= 0.0 || out.0[1] <= 0.0 {
        return Err(invalid(
            label,
            format!("camera {} PARAMS", camera.id),
            format!("focal lengths {}, {}: expected > 0", out.0[0], out.0[1]),
        ));
    }
    Ok(out)
}

/// The model's points (sorted by point id) as seeded Gaussians.
pub fn colmap_gaussians(model: &ColmapModel) -> Gaussians {
    let mut points: Vec<&ColmapPoint> = model.points.iter().collect();
    points.sort_by_key(|p| p.id);
    let xyz: Vec<[f64; 3]> = points.iter().map(|p| p.xyz).collect();
    let rgb: Vec<[u8; 3]> = points.iter().map(|p| p.rgb).collect();
    let mut g = seed_gaussians(&xyz, &rgb);
    g.extra.insert(
        "source".to_string(),
        format!("colmap_{}_points3D", model.files.format.name()),
    );
    g
}

/// Gaussians seeded from coloured points as INRIA 3DGS does: mean = point; `sh_dc` =
/// (rgb/255 − 0.5) / [`SH_C0`]; isotropic log scale = ln √(mean squared distance to the 3
/// nearest other points, clamped at [`MIN_MEAN_SQUARED_DISTANCE`]); identity rotation;
/// opacity logit = ln(0.1 / 0.9). Points must be finite (COLMAP readers check this).
pub fn seed_gaussians(points: &[[f64; 3]], colors: &[[u8; 3]]) -> Gaussians {
    let mean_sq = mean_squared_neighbour_distance(points);
    let logit = (SEED_OPACITY / (1.0 - SEED_OPACITY)).ln() as f32;
    let n = points.len().min(colors.len());
    Gaussians {
        means: points
            .iter()
            .take(n)
            .map(|p| p.map(|c| c as f32))
            .collect::<Vec<_>>()
            .into(),
        log_scales: mean_sq
            .iter()
            .take(n)
            .map(|d| [(0.5 * d.ln()) as f32; 3])
            .collect::<Vec<_>>()
            .into(),
        rotations: vec![[1.0, 0.0, 0.0, 0.0]; n].into(),
        opacity_logits: vec![logit; n].into(),
        sh_dc: colors
            .iter()
            .take(n)
            .map(|c| c.map(rgb8_to_sh_dc))
            .collect::<Vec<_>>()
            .into(),
        sh_degree: 0,
        sh_rest: None,
        class_ids: None,
        extra: BTreeMap::new(),
    }
}

/// Per point, the mean squared distance to its 3 nearest other points (fewer when the
/// cloud is smaller), at least [`MIN_MEAN_SQUARED_DISTANCE`].
pub fn mean_squared_neighbour_distance(points: &[[f64; 3]]) -> Vec<f64> {
    let k = 3.min(points.len().saturating_sub(1));
    let Some(query_len) = NonZeroUsize::new(k + 1).filter(|_| k > 0) else {
        return vec![MIN_MEAN_SQUARED_DISTANCE; points.len()];
    };
    let tree: ImmutableKdTree<f64, u64, 3, 32> = ImmutableKdTree::new_from_slice(points);
    points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            // Ask for k + 1 so the point itself can be dropped; with more than k + 1
            // duplicates it may not be among them, and then k zero distances are right.
            let found = tree.nearest_n::<SquaredEuclidean>(p, query_len);
            let nearest: Vec<f64> = found
                .iter()
                .filter(|nb| nb.item != i as u64)
                .take(k)
                .map(|nb| nb.distance)
                .collect();
            let mean = nearest.iter().sum::<f64>() / nearest.len().max(1) as f64;
            mean.max(MIN_MEAN_SQUARED_DISTANCE)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn neighbour_distances_exclude_self_and_clamp_duplicates() {
        let pts = [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 2.0, 0.0],
            [0.0, 0.0, 3.0],
            [10.0, 0.0, 0.0],
        ];
        let d = mean_squared_neighbour_distance(&pts);
        assert!((d[0] - (1.0 + 4.0 + 9.0) / 3.0).abs() < 1e-12);
        let dup = vec![[1.0, 1.0, 1.0]; 100];
        assert!(mean_squared_neighbour_distance(&dup)
            .iter()
            .all(|d| *d == MIN_MEAN_SQUARED_DISTANCE));
        assert_eq!(
            mean_squared_neighbour_distance(&[[0.0; 3]]),
            vec![MIN_MEAN_SQUARED_DISTANCE]
        );
        assert!(mean_squared_neighbour_distance(&[]).is_empty());
        let two = mean_squared_neighbour_distance(&[[0.0; 3], [0.0, 0.0, 2.0]]);
        assert_eq!(two, vec![4.0, 4.0]);
    }

    #[test]
    fn seeded_gaussians_match_inria_initialisation() {
        let g = seed_gaussians(&[[0.0; 3], [2.0, 0.0, 0.0]], &[[255, 0, 128], [0, 0, 0]]);
        assert_eq!(g.len(), 2);
        assert!((g.log_scales[0][0] - 2.0f32.ln()).abs() < 1e-6);
        assert!((g.sh_dc[0][0] - (0.5 / SH_C0) as f32).abs() < 1e-6);
        assert!((g.opacity(0) - 0.1).abs() < 1e-6);
        assert_eq!(g.rotations[1], [1.0, 0.0, 0.0, 0.0]);
    }
}

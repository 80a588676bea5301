//! LLFF `poses_bounds.npy` scenes (the NeRF "forward-facing" format) → [`Cameras`].
//!
//! `poses_bounds.npy` is an (N, 17) float array, one row per image: a 3x5 matrix
//! `[R | C | hwf]` flattened row-major, then the near and far depth bounds. `R`'s columns
//! are the camera's axes in world coordinates in LLFF's order **[down, right, back]**, `C`
//! is the camera centre, and `hwf` = (height, width, focal) of the full-resolution images
//! (LLFF's `imgs2poses.py` takes them from COLMAP).
//!
//! Conventions converted:
//! * Our camera axes are OpenCV's [right, down, forward], so the camera-to-world rotation
//!   is `[R₁, R₀, −R₂]` (columns), then `R_w2c = R_c2wᵀ`, `t = −R_w2c C`. (NeRF's
//!   `load_llff.py` makes the OpenGL [right, up, back] = `[R₁, −R₀, R₂]` instead; the
//!   transforms.json importer's `diag(1, −1, −1)` takes that to the same matrix.)
//! * Rotations are snapped to the nearest rotation within
//!   [`REORTHONORMALIZE_TOLERANCE`](crate::geometry::REORTHONORMALIZE_TOLERANCE), like
//!   the other text-derived poses; worse is an error naming the row.
//! * Images: row `i` is the `i`-th file, in sorted name order, of `images/` (factor 1) or
//!   `images_<factor>/` whose name ends in `JPG`, `jpg` or `png` (exactly the listing of
//!   `load_llff.py`); the counts must agree. Image names are `images[_<factor>]/<file>`.
//! * Intrinsics: each view's size is read from its image header and must be the
//!   full-resolution `w/factor × h/factor` to within rounding (LLFF's `minify` resizes by
//!   `100/factor` %). Focal lengths are scaled by the actual ratio per axis
//!   (`fx = f · W_img / w`, `fy = f · H_img / h`, which is NeRF's `f / factor` for exact
//!   multiples). LLFF stores no principal point and assumes the image centre: `cx =
//!   W_img / 2`, `cy = H_img / 2` in our corner-origin convention (COLMAP's, from which
//!   LLFF's poses come). No lens distortion.
//! * The depth bounds have no place in a cameras file; they must be finite and are
//!   summarised in the report.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use profuse_formats::Cameras;
use serde::Serialize;

use crate::error::{invalid, missing, Result, SceneError};
use crate::fsutil::{image_dimensions, list_dir, show};
use crate::geometry::{snap_to_rotation, world_to_camera_from_c2w, Mat3};
use crate::npy::read_npy;

/// Options of [`import_llff`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LlffOptions {
    /// Downscale factor: 1 reads `images/`, N > 1 reads `images_N/`.
    pub factor: u32,
}

impl Default for LlffOptions {
    fn default() -> Self {
        LlffOptions { factor: 1 }
    }
}

/// What [`import_llff`] did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LlffReport {
    /// Views imported (= rows of `poses_bounds.npy`).
    pub views: usize,
    /// The downscale factor used.
    pub factor: u32,
    /// The image folder, relative to the scene directory (`images`, `images_8`).
    pub images_dir: String,
    /// Smallest near bound of any view.
    pub near_min: f64,
    /// Largest far bound of any view.
    pub far_max: f64,
}

/// Values per row of `poses_bounds.npy`: a 3x5 matrix and 2 bounds.
const ROW: usize = 17;

/// Imports an LLFF scene: `scene` is the directory holding `poses_bounds.npy` (or that
/// file itself); image names are relative to that directory.
pub fn import_llff(
    scene: impl AsRef<Path>,
    options: &LlffOptions,
) -> Result<(Cameras, LlffReport)> {
    let given = scene.as_ref();
    let (dir, npy) = if given.is_dir() {
        (given.to_path_buf(), given.join("poses_bounds.npy"))
    } else {
        let dir = match given.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        (dir, given.to_path_buf())
    };
    let label = show(&npy);
    if options.factor == 0 {
        return Err(invalid(
            &label,
            "factor",
            "0, expected a downscale factor >= 1",
        ));
    }
    if !npy.is_file() {
        return Err(missing(
            &show(&dir),
            "poses_bounds.npy",
            "the (N, 17) LLFF poses and bounds array",
        ));
    }
    let rows = read_rows(&npy, &label)?;
    let images_dir = if options.factor == 1 {
        "images".to_string()
    } else {
        format!("images_{}", options.factor)
    };
    let images = list_images(&dir, &images_dir, rows.len())?;

    let mut names = Vec::with_capacity(rows.len());
    let (mut sizes, mut intrinsics, mut poses) = (Vec::new(), Vec::new(), Vec::new());
    let (mut near_min, mut far_max) = (f64::INFINITY, f64::NEG_INFINITY);
    for (i, (row, (file, path))) in rows.iter().zip(&images).enumerate() {
        let size = image_dimensions(path)?;
        intrinsics.push(row_intrinsics(row, size, options.factor, i, &label, path)?);
        poses.push(row_pose(row, i, &label)?);
        sizes.push(size);
        names.push(format!("{images_dir}/{file}"));
        near_min = near_min.min(row[15]);
        far_max = far_max.max(row[16]);
    }
    let cameras = Cameras {
        image_names: names,
        image_size: sizes.into(),
        intrinsics: intrinsics.into(),
        world_to_camera: poses.into(),
        distortion: None,
        extra: BTreeMap::from([("source".to_string(), "llff".to_string())]),
    };
    let report = LlffReport {
        views: rows.len(),
        factor: options.factor,
        images_dir,
        near_min,
        far_max,
    };
    Ok((cameras, report))
}

/// The rows of `poses_bounds.npy`, checked for shape and finiteness.
fn read_rows(npy: &Path, label: &str) -> Result<Vec<[f64; ROW]>> {
    let array = read_npy(npy)?;
    match (array.shape.as_slice(), array.dtype().is_float()) {
        ([n, ROW], true) if *n > 0 => {}
        _ => {
            return Err(invalid(
                label,
                "array",
                format!(
                    "shape {:?} dtype {}, expected a float (N, 17) array with N >= 1 (3x5 [R | C | hwf] row-major + near, far per image)",
                    array.shape,
                    array.dtype().code()
                ),
            ))
        }
    }
    let flat = array.to_f64_vec();
    if let Some(i) = flat.iter().position(|v| !v.is_finite()) {
        return Err(SceneError::NonFinite {
            path: label.to_string(),
            field: format!("row {} column {}", i / ROW, i % ROW),
            index: i / ROW,
            value: flat[i].to_string(),
        });
    }
    Ok(flat
        .chunks_exact(ROW)
        .map(|c| std::array::from_fn(|j| c[j]))
        .collect())
}

/// `dir/images_dir` files in LLFF's order (sorted; names ending in JPG, jpg or png), as
/// (file name, path); their number must be `expected`.
fn list_images(dir: &Path, images_dir: &str, expected: usize) -> Result<Vec<(String, PathBuf)>> {
    let folder = dir.join(images_dir);
    if !folder.is_dir() {
        let present: Vec<String> = list_dir(dir)?
            .iter()
            .filter(|p| p.is_dir())
            .filter_map(|p| p.file_name()?.to_str().map(str::to_string))
            .filter(|n| n == "images" || n.starts_with("images_"))
            .collect();
        return Err(missing(
            &show(dir),
            format!("directory `{images_dir}/`"),
            format!(
                "the images of this factor (LLFF's minify, e.g. `mogrify -resize` by 100/factor %); image folders present: {present:?}"
            ),
        ));
    }
    let images: Vec<(String, PathBuf)> = list_dir(&folder)?
        .into_iter()
        .filter_map(|p| {
            let name = p.file_name()?.to_str()?.to_string();
            let keep = ["JPG", "jpg", "png"].iter().any(|e| name.ends_with(e));
            (keep && p.is_file()).then_some((name, p))
        })
        .collect();
    if images.len() != expected {
        return Err(invalid(
            &show(&folder),
            "images",
            format!(
                "{} image files (*JPG, *jpg, *png), but poses_bounds.npy has {expected} rows; row i is the i-th image in name order",
                images.len()
            ),
        ));
    }
    for (name, _) in &images {
        crate::fsutil::check_image_name(&show(&folder), "image file", name)?;
    }
    Ok(images)
}

/// `[fx, fy, cx, cy]` of row `i` for an image of `size` at downscale `factor`.
fn row_intrinsics(
    row: &[f64; ROW],
    size: [u32; 2],
    factor: u32,
    i: usize,
    label: &str,
    image: &Path,
) -> Result<[f64; 4]> {
    // hwf is column 4 of the 3x5 matrix: elements 4, 9, 14.
    let (h, w, f) = (row[4], row[9], row[14]);
    if h < 1.0 || w < 1.0 || f <= 0.0 {
        return Err(invalid(
            label,
            format!("row {i} hwf"),
            format!("height {h}, width {w}, focal {f}: expected sizes >= 1 and a focal length > 0"),
        ));
    }
    let (wi, hi) = (f64::from(size[0]), f64::from(size[1]));
    let scale = f64::from(factor);
    if (wi - w / scale).abs() >= 1.0 || (hi - h / scale).abs() >= 1.0 {
        return Err(invalid(
            &show(image),
            "image size",
            format!(
                "{}x{}, but row {i} of {label} gives {w}x{h} at full resolution, i.e. about {:.1}x{:.1} at factor {factor}",
                size[0],
                size[1],
                w / scale,
                h / scale
            ),
        ));
    }
    Ok([f * wi / w, f * hi / h, wi / 2.0, hi / 2.0])
}

/// World-to-camera row of row `i`: LLFF [down, right, back] → OpenCV [right, down, forward].
fn row_pose(row: &[f64; ROW], i: usize, label: &str) -> Result<[f64; 12]> {
    let m = |r: usize, c: usize| row[r * 5 + c];
    let r_cv: Mat3 = std::array::from_fn(|r| [m(r, 1), m(r, 0), -m(r, 2)]);
    let r_cv = snap_to_rotation(&r_cv).map_err(|e| {
        invalid(
            label,
            format!("row {i} rotation [down, right, back]"),
            e.to_string(),
        )
    })?;
    Ok(world_to_camera_from_c2w(&r_cv, [m(0, 3), m(1, 3), m(2, 3)]))
}

//! instant-ngp / NeRF `transforms.json` → [`Cameras`].
//!
//! Conventions converted:
//! * `transform_matrix` is camera-to-world in OpenGL camera axes (x right, y up, z
//!   backward). OpenCV axes are x right, y down, z forward, so
//!   `c2w_cv = c2w_gl · diag(1, −1, −1, 1)` (negate the y and z columns), then invert:
//!   `R = R_c2wᵀ`, `t = −R C`.
//! * Rotations printed with limited precision are snapped to the nearest rotation when
//!   within [`REORTHONORMALIZE_TOLERANCE`](crate::geometry::REORTHONORMALIZE_TOLERANCE); larger deviations are errors naming the frame.
//! * `cx`, `cy` use the corner-origin pixel convention (instant-ngp's default principal
//!   point is `w/2, h/2`, the image centre in that convention), the same as ours: copied
//!   unchanged; they default to `w/2`, `h/2`.
//! * Focal lengths: `fl_x`/`fl_y`, else `camera_angle_x`/`camera_angle_y`
//!   (`f = 0.5·w / tan(0.5·angle)`), else square pixels (`fl_y = fl_x`).
//! * Every intrinsic key may be overridden per frame (a frame's own key wins).
//! * `k1 k2 p1 p2` become `distortion` when any is non-zero; fisheye models and `k3`/`k4`
//!   cannot be represented and are errors.
//!
//! Image names are `file_path` relative to the JSON's directory, which is the scene
//! directory. A `file_path` without an extension that does not exist is tried with
//! `.png`, then `.jpg` (the NeRF-synthetic style). Frames whose image is missing are
//! skipped with a warning in the report. A `file_path` that is absolute or has a `..`
//! component is an error ([`crate::scene_relative_parts`]: image paths stay inside the
//! scene folder). The JSON is read up to [`crate::MAX_JSON_BYTES`] (64 MiB).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use profuse_formats::Cameras;
use serde::Serialize;
use serde_json::{Map, Value};

use crate::error::{invalid, missing, unsupported, Result, SceneError};
use crate::fsutil::{check_image_name, image_dimensions, read_text_capped, show, MAX_JSON_BYTES};
use crate::geometry::{snap_to_rotation, world_to_camera_from_c2w, Mat3};

/// What [`read_transforms`] did.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct TransformsReport {
    /// Frames listed in the JSON.
    pub frames: usize,
    /// Views imported.
    pub views: usize,
    /// Frames skipped because their image file does not exist.
    pub skipped: usize,
    /// Whether the cameras carry lens distortion.
    pub distortion: bool,
    /// One line per skipped frame (the library never prints).
    pub warnings: Vec<String>,
}

/// Reads a `transforms.json`; image names are relative to its directory.
pub fn read_transforms(path: impl AsRef<Path>) -> Result<(Cameras, TransformsReport)> {
    let path = path.as_ref();
    let label = show(path);
    let json: Value =
        serde_json::from_str(&read_text_capped(path, MAX_JSON_BYTES, "")?).map_err(|source| {
            SceneError::Json {
                path: label.clone(),
                source,
            }
        })?;
    let top = json
        .as_object()
        .ok_or_else(|| invalid(&label, "top level", "expected a JSON object"))?;
    let frames = top
        .get("frames")
        .and_then(Value::as_array)
        .ok_or_else(|| missing(&label, "key `frames`", "an array of frames"))?;
    let base = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };

    let mut views = Vec::new();
    let mut warnings = Vec::new();
    for (i, frame) in frames.iter().enumerate() {
        let frame = frame
            .as_object()
            .ok_or_else(|| invalid(&label, format!("frames[{i}]"), "expected a JSON object"))?;
        let keys = Keys {
            top,
            frame,
            index: i,
            label: &label,
        };
        let Some((name, image_path)) = keys.image(&base)? else {
            let file = frame
                .get("file_path")
                .and_then(Value::as_str)
                .unwrap_or_default();
            warnings.push(format!(
                "frames[{i}]: image {file:?} not found in {}; frame skipped",
                base.display()
            ));
            continue;
        };
        let (size, intrinsics, distortion) = keys.intrinsics(&image_path)?;
        let pose = keys.world_to_camera()?;
        views.push((name, size, intrinsics, distortion, pose));
    }
    if views.is_empty() {
        return Err(invalid(
            &label,
            "frames",
            "no frame has an existing image file",
        ));
    }

    let distorted = views.iter().any(|v| v.3.iter().any(|c| *c != 0.0));
    let report = TransformsReport {
        frames: frames.len(),
        views: views.len(),
        skipped: warnings.len(),
        distortion: distorted,
        warnings,
    };
    let cameras = Cameras {
        image_names: views.iter().map(|v| v.0.clone()).collect(),
        image_size: views.iter().map(|v| v.1).collect::<Vec<_>>().into(),
        intrinsics: views.iter().map(|v| v.2).collect::<Vec<_>>().into(),
        world_to_camera: views.iter().map(|v| v.4).collect::<Vec<_>>().into(),
        distortion: distorted.then(|| views.iter().map(|v| v.3).collect::<Vec<_>>().into()),
        extra: BTreeMap::from([("source".to_string(), "transforms.json".to_string())]),
    };
    Ok((cameras, report))
}

/// Key lookup with per-frame overrides and errors that name the key and frame.
struct Keys<'a> {
    top: &'a Map<String, Value>,
    frame: &'a Map<String, Value>,
    index: usize,
    label: &'a str,
}

impl Keys<'_> {
    fn field(&self, key: &str) -> String {
        format!("frames[{}].{key} (or top-level {key})", self.index)
    }

    /// A number from one object; `null` counts as absent.
    fn number_in(&self, obj: &Map<String, Value>, key: &str) -> Result<Option<f64>> {
        match obj.get(key) {
            None | Some(Value::Null) => Ok(None),
            Some(v) => v
                .as_f64()
                .filter(|x| x.is_finite())
                .map(Some)
                .ok_or_else(|| {
                    invalid(self.label, self.field(key), format!("{v} is not a number"))
                }),
        }
    }

    /// The frame's value, else the top-level one.
    fn number(&self, key: &str) -> Result<Option<f64>> {
        match self.number_in(self.frame, key)? {
            Some(v) => Ok(Some(v)),
            None => self.number_in(self.top, key),
        }
    }

    fn string(&self, key: &str) -> Option<&str> {
        self.frame
            .get(key)
            .or_else(|| self.top.get(key))
            .and_then(Value::as_str)
    }

    /// The image name (relative to the JSON's directory) and path, or `None` when the
    /// file does not exist.
    fn image(&self, base: &Path) -> Result<Option<(String, PathBuf)>> {
        let file = self
            .frame
            .get("file_path")
            .and_then(Value::as_str)
            .ok_or_else(|| {
                missing(
                    self.label,
                    format!("frames[{}].file_path", self.index),
                    "a relative image path string",
                )
            })?;
        let field = format!("frames[{}].file_path", self.index);
        let parts = check_image_name(self.label, &field, file)?;
        let name = parts.join("/");
        let path = base.join(parts.iter().collect::<PathBuf>());
        if path.is_file() {
            return Ok(Some((name, path)));
        }
        if Path::new(&name).extension().is_none() {
            for ext in ["png", "jpg"] {
                let candidate = path.with_extension(ext);
                if candidate.is_file() {
                    return Ok(Some((format!("{name}.{ext}"), candidate)));
                }
            }
        }
        Ok(None)
    }

    /// Image size, `[fx, fy, cx, cy]` and `[k1, k2, p1, p2]` of this frame.
    fn intrinsics(&self, image: &Path) -> Result<([u32; 2], [f64; 4], [f64; 4])> {
        self.reject_unsupported_models()?;
        let size = match (self.number("w")?, self.number("h")?) {
            (Some(w), Some(h)) => [self.pixels(w, "w")?, self.pixels(h, "h")?],
            _ => image_dimensions(image)?,
        };
        let (w, h) = (f64::from(size[0]), f64::from(size[1]));
        let fx = match self.focal("fl_x", "camera_angle_x", w)? {
            Some(f) => f,
            None => self.focal("fl_y", "camera_angle_y", h)?.ok_or_else(|| {
                missing(
                    self.label,
                    self.field("fl_x"),
                    "fl_x, fl_y, camera_angle_x or camera_angle_y",
                )
            })?,
        };
        let fy = self.focal("fl_y", "camera_angle_y", h)?.unwrap_or(fx);
        for (f, key) in [(fx, "fl_x"), (fy, "fl_y")] {
            if f <= 0.0 {
                return Err(invalid(
                    self.label,
                    self.field(key),
                    format!("focal length {f}, expected > 0"),
                ));
            }
        }
        let cx = self.number("cx")?.unwrap_or(w / 2.0);
        let cy = self.number("cy")?.unwrap_or(h / 2.0);
        let mut distortion = [0.0; 4];
        for (slot, key) in distortion.iter_mut().zip(["k1", "k2", "p1", "p2"]) {
            *slot = self.number(key)?.unwrap_or(0.0);
        }
        Ok((size, [fx, fy, cx, cy], distortion))
    }

    /// Focal length from `fl_key`, else from `angle_key` and the image extent; the
    /// frame's own keys win over the top level's.
    fn focal(&self, fl_key: &str, angle_key: &str, extent: f64) -> Result<Option<f64>> {
        let from_angle = |angle: f64| -> Result<f64> {
            if angle <= 0.0 || angle >= std::f64::consts::PI {
                return Err(invalid(
                    self.label,
                    self.field(angle_key),
                    format!("{angle} rad, expected an angle in (0, π)"),
                ));
            }
            Ok(0.5 * extent / (0.5 * angle).tan())
        };
        for obj in [self.frame, self.top] {
            if let Some(f) = self.number_in(obj, fl_key)? {
                return Ok(Some(f));
            }
            if let Some(a) = self.number_in(obj, angle_key)? {
                return from_angle(a).map(Some);
            }
        }
        Ok(None)
    }

    fn pixels(&self, v: f64, key: &str) -> Result<u32> {
        if v >= 1.0 && v.fract() == 0.0 && v <= f64::from(u32::MAX) {
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            Ok(v as u32)
        } else {
            Err(invalid(
                self.label,
                self.field(key),
                format!("{v}, expected a whole number of pixels >= 1"),
            ))
        }
    }

    fn reject_unsupported_models(&self) -> Result<()> {
        let what = format!("camera model in frames[{}]", self.index);
        if let Some(model) = self.string("camera_model") {
            if !matches!(model, "OPENCV" | "PINHOLE" | "SIMPLE_PINHOLE") {
                return Err(unsupported(
                    self.label,
                    what,
                    format!("camera_model {model:?} (OPENCV, PINHOLE or SIMPLE_PINHOLE are read)"),
                ));
            }
        }
        if self
            .frame
            .get("is_fisheye")
            .or_else(|| self.top.get("is_fisheye"))
            == Some(&Value::Bool(true))
        {
            return Err(unsupported(
                self.label,
                what,
                "is_fisheye = true (only OpenCV radial-tangential k1 k2 p1 p2)",
            ));
        }
        for key in ["k3", "k4"] {
            if self.number(key)?.is_some_and(|k| k != 0.0) {
                return Err(unsupported(
                    self.label,
                    what,
                    format!("non-zero {key} (only k1 k2 p1 p2 are represented)"),
                ));
            }
        }
        Ok(())
    }

    /// `transform_matrix` (OpenGL camera-to-world) as our world-to-camera row.
    fn world_to_camera(&self) -> Result<[f64; 12]> {
        let field = format!("frames[{}].transform_matrix", self.index);
        let rows = self
            .frame
            .get("transform_matrix")
            .and_then(Value::as_array)
            .ok_or_else(|| missing(self.label, &field, "a 4x4 (or 3x4) camera-to-world matrix"))?;
        let bad = || {
            invalid(
                self.label,
                &field,
                "expected 3 or 4 rows of 4 finite numbers",
            )
        };
        if rows.len() != 3 && rows.len() != 4 {
            return Err(bad());
        }
        let mut m = [[0.0f64; 4]; 3];
        for (row, value) in m.iter_mut().zip(rows) {
            let cells = value.as_array().filter(|c| c.len() == 4).ok_or_else(bad)?;
            for (slot, cell) in row.iter_mut().zip(cells) {
                *slot = cell.as_f64().filter(|x| x.is_finite()).ok_or_else(bad)?;
            }
        }
        // OpenGL → OpenCV camera axes: negate the camera's y and z axes (columns 1, 2).
        let r_gl: Mat3 = std::array::from_fn(|i| std::array::from_fn(|j| m[i][j]));
        let r_cv: Mat3 = std::array::from_fn(|i| [r_gl[i][0], -r_gl[i][1], -r_gl[i][2]]);
        let r_cv =
            snap_to_rotation(&r_cv).map_err(|e| invalid(self.label, &field, e.to_string()))?;
        let centre = [m[0][3], m[1][3], m[2][3]];
        Ok(world_to_camera_from_c2w(&r_cv, centre))
    }
}

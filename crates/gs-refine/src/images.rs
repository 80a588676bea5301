//! Training targets: the photos of the views, read once and box-filtered to the training
//! scale, kept as f32 RGB in [0, 1].

use std::path::{Path, PathBuf};

use crate::error::{RefineError, Result};

/// One view's target image at the training resolution.
#[derive(Debug, Clone, PartialEq)]
pub struct Target {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `[H, W, 3]` values in [0, 1].
    pub rgb: Vec<f32>,
}

/// The file of an image name under `root`: `root/name` when it exists, else
/// `root/<file name of name>` (gs-init's lookup: a scene directory or the image folder).
pub fn image_path(root: &Path, name: &str) -> PathBuf {
    let direct = root.join(name);
    if direct.is_file() {
        return direct;
    }
    match Path::new(name).file_name() {
        Some(file) if root.join(file).is_file() => root.join(file),
        _ => direct,
    }
}

/// Training size of a `w × h` image at `scale` (rounded, at least one pixel).
pub fn scaled_size([w, h]: [u32; 2], scale: f64) -> [u32; 2] {
    let s = |v: u32| ((f64::from(v) * scale).round() as u32).max(1);
    [s(w), s(h)]
}

/// Reads view `view`'s image, checks its size against the camera's `size`, and resamples it
/// to `to` by area averaging (each output pixel the mean of the input area it covers).
pub fn load_target(path: &Path, view: usize, size: [u32; 2], to: [u32; 2]) -> Result<Target> {
    let err = |reason: String| RefineError::Image {
        path: path.display().to_string(),
        view,
        reason,
    };
    let img = image::open(path).map_err(|e| err(e.to_string()))?.to_rgb8();
    if [img.width(), img.height()] != size {
        return Err(RefineError::ImageSize {
            path: path.display().to_string(),
            view,
            got: [img.width(), img.height()],
            expected: size,
        });
    }
    let src: Vec<f32> = img.as_raw().iter().map(|v| f32::from(*v) / 255.0).collect();
    Ok(Target {
        width: to[0],
        height: to[1],
        rgb: resample(&src, size, to),
    })
}

/// Area-average resampling of `[H, W, 3]` from `from` to `to` (exact copy when equal).
pub fn resample(src: &[f32], from: [u32; 2], to: [u32; 2]) -> Vec<f32> {
    if from == to {
        return src.to_vec();
    }
    let (sw, sh) = (from[0] as usize, from[1] as usize);
    let (tw, th) = (to[0] as usize, to[1] as usize);
    let (rx, ry) = (sw as f64 / tw as f64, sh as f64 / th as f64);
    // Weights of the source cells overlapping [a, b).
    let cover = |a: f64, b: f64, n: usize| -> Vec<(usize, f64)> {
        let lo = a.floor() as usize;
        let hi = (b.ceil() as usize).min(n);
        (lo..hi)
            .map(|i| (i, (b.min(i as f64 + 1.0) - a.max(i as f64)).max(0.0)))
            .filter(|(_, w)| *w > 0.0)
            .collect()
    };
    let cols: Vec<Vec<(usize, f64)>> = (0..tw)
        .map(|x| cover(x as f64 * rx, (x + 1) as f64 * rx, sw))
        .collect();
    let mut out = vec![0.0f32; tw * th * 3];
    for y in 0..th {
        let rows = cover(y as f64 * ry, (y + 1) as f64 * ry, sh);
        for (x, cw) in cols.iter().enumerate() {
            let mut acc = [0.0f64; 3];
            let mut wsum = 0.0;
            for &(sy, wy) in &rows {
                for &(sx, wx) in cw {
                    let w = wx * wy;
                    let p = (sy * sw + sx) * 3;
                    for c in 0..3 {
                        acc[c] += w * f64::from(src[p + c]);
                    }
                    wsum += w;
                }
            }
            for c in 0..3 {
                out[(y * tw + x) * 3 + c] = (acc[c] / wsum) as f32;
            }
        }
    }
    out
}

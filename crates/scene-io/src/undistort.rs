//! Undistortion of images and scenes, so that every stage after import sees pinhole
//! cameras (SPEC.md §3.3). The lens model itself (OpenCV's radial-tangential k1, k2, p1,
//! p2), its Newton inverse and the pixel-level helpers are [`profuse_formats::camera`]'s
//! [`distort`](profuse_formats::camera::distort),
//! [`undistort`](profuse_formats::camera::undistort), [`distort_pixel`] and
//! [`undistort_pixel`], re-exported here.
//!
//! Images are undistorted by inverse mapping: each pixel centre of the pinhole output
//! (same size and intrinsics as the input) is distorted into the input and sampled
//! bilinearly; output pixels whose source lies outside the input are black.
//!
//! ```
//! use scene_io::undistort::{distort_pixel, undistort_pixel};
//!
//! let intrinsics = [1375.5, 1374.5, 554.6, 965.3];
//! let lens = [0.0578, -0.0805, -0.00098, 0.00016];
//! let p = [100.25, 1800.5];
//! let d = distort_pixel(&intrinsics, &lens, p);
//! let back = undistort_pixel(&intrinsics, &lens, d).expect("inside the model's range");
//! assert!((back[0] - p[0]).abs() < 1e-6 && (back[1] - p[1]).abs() < 1e-6);
//! ```

use std::path::{Path, PathBuf};

use profuse_formats::camera::pixel_centre;
pub use profuse_formats::camera::{distort_pixel, undistort_pixel, Lens};
use profuse_formats::Cameras;
use serde::Serialize;

use crate::error::{Result, SceneError};
use crate::fsutil::{check_image_name, open_image, show, write_atomically};

/// Undistorts an interleaved RGB8 image to the pinhole camera with the same size and
/// intrinsics: output pixel centre `(x + 0.5, y + 0.5)` is distorted into the input and
/// sampled bilinearly (input pixel centres at +0.5, edge pixels clamped within half a pixel
/// of the border); black where the source falls outside the input.
pub fn undistort_rgb(
    rgb: &[u8],
    width: usize,
    height: usize,
    intrinsics: [f64; 4],
    lens: Lens,
) -> Vec<u8> {
    let mut out = vec![0u8; width * height * 3];
    if rgb.len() < width * height * 3 {
        return out;
    }
    for (y, row) in out.chunks_exact_mut(width * 3).enumerate() {
        for (x, px) in row.chunks_exact_mut(3).enumerate() {
            let [su, sv] = distort_pixel(&intrinsics, &lens, pixel_centre(x, y));
            if let Some(c) = sample_bilinear(rgb, width, height, su, sv) {
                px.copy_from_slice(&c);
            }
        }
    }
    out
}

/// Bilinear sample of an RGB8 image at pixel position `(u, v)` (centres at +0.5); `None`
/// outside `[0, width] x [0, height]`.
fn sample_bilinear(rgb: &[u8], width: usize, height: usize, u: f64, v: f64) -> Option<[u8; 3]> {
    if !(u >= 0.0 && v >= 0.0 && u <= width as f64 && v <= height as f64) {
        return None;
    }
    let fx = (u - 0.5).clamp(0.0, (width - 1) as f64);
    let fy = (v - 0.5).clamp(0.0, (height - 1) as f64);
    let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(width - 1), (y0 + 1).min(height - 1));
    let (tx, ty) = (fx - x0 as f64, fy - y0 as f64);
    let at = |x: usize, y: usize, c: usize| f64::from(rgb[(y * width + x) * 3 + c]);
    let mut out = [0u8; 3];
    for (c, o) in out.iter_mut().enumerate() {
        let top = at(x0, y0, c) * (1.0 - tx) + at(x1, y0, c) * tx;
        let bottom = at(x0, y1, c) * (1.0 - tx) + at(x1, y1, c) * tx;
        *o = (top * (1.0 - ty) + bottom * ty).round().clamp(0.0, 255.0) as u8;
    }
    Some(out)
}

/// The same cameras as pinhole ones (the `distortion` tensor dropped), for use with
/// undistorted images and keypoints.
pub fn pinhole(cameras: &Cameras) -> Cameras {
    Cameras {
        distortion: None,
        ..cameras.clone()
    }
}

/// What [`undistort_scene`] did.
#[derive(Debug, Clone, Default, Serialize)]
pub struct UndistortReport {
    /// Images written.
    pub images: usize,
    /// Views whose lens was the identity (copied through the same resampling).
    pub identity_lens: usize,
}

/// Undistorts every image of a scene: reads `scene_dir/<image_names[v]>`, writes
/// `out_dir/images/<stem>.png` (PNG, so no second lossy step) and returns the pinhole
/// cameras naming those files (`images/<stem>.png`, relative to `out_dir`). Views without
/// a lens model (or cameras without `distortion`) are re-encoded unchanged.
pub fn undistort_scene(
    cameras: &Cameras,
    scene_dir: &Path,
    out_dir: &Path,
) -> Result<(Cameras, UndistortReport)> {
    let images_dir = out_dir.join("images");
    std::fs::create_dir_all(&images_dir)
        .map_err(|e| crate::error::io_err(&show(&images_dir), "cannot create the directory", e))?;
    let mut report = UndistortReport::default();
    let mut names = Vec::with_capacity(cameras.len());
    for (v, name) in cameras.image_names.iter().enumerate() {
        let parts = check_image_name(&show(scene_dir), &format!("image_names[{v}]"), name)?;
        let src = scene_dir.join(parts.iter().collect::<PathBuf>());
        let label = show(&src);
        let img = open_image(&src)?
            .decode()
            .map_err(|source| SceneError::Image {
                path: label.clone(),
                source,
            })?
            .to_rgb8();
        let (w, h) = (img.width() as usize, img.height() as usize);
        if [img.width(), img.height()] != cameras.image_size[v] {
            return Err(crate::error::invalid(
                &label,
                "image size",
                format!(
                    "{w}x{h}, but the cameras file says {:?}",
                    cameras.image_size[v]
                ),
            ));
        }
        let lens = cameras.distortion.as_ref().map_or([0.0; 4], |d| d[v]);
        if lens == [0.0; 4] {
            report.identity_lens += 1;
        }
        let rgb = undistort_rgb(img.as_raw(), w, h, cameras.intrinsics[v], lens);
        let stem = Path::new(name)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| format!("view{v:05}"));
        let rel = format!("images/{stem}.png");
        let dst = out_dir.join(&rel);
        let png =
            profuse_formats::png::encode(&rgb, w as u32, h as u32, image::ExtendedColorType::Rgb8)
                .map_err(|source| SceneError::Image {
                    path: show(&dst),
                    source,
                })?;
        write_atomically(&dst, |out| out.write_all(&png))?;
        names.push(rel);
        report.images += 1;
    }
    let mut out = pinhole(cameras);
    out.image_names = names;
    Ok((out, report))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn zero_lens_is_the_identity_on_images() {
        let (w, h) = (7, 5);
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 7 % 256) as u8).collect();
        let out = undistort_rgb(&rgb, w, h, [5.0, 5.0, 3.5, 2.5], [0.0; 4]);
        assert_eq!(out, rgb);
    }
}

//! OpenCV's radial-tangential lens model (k1, k2, p1, p2) and its inverse, so that every
//! stage after import sees pinhole cameras (SPEC.md §3.3).
//!
//! The model maps undistorted normalised coordinates `(x, y) = ((u − cx)/fx, (v − cy)/fy)` to
//! distorted ones:
//!
//! ```text
//! r² = x² + y²,  s = 1 + k1 r² + k2 r⁴
//! x_d = x s + 2 p1 x y + p2 (r² + 2 x²)
//! y_d = y s + p1 (r² + 2 y²) + 2 p2 x y
//! ```
//!
//! It has no closed-form inverse. OpenCV's `undistortPoints` runs a fixed number of
//! fixed-point iterations and returns whatever it reached; here the inverse is Newton's
//! method on the 2x2 Jacobian, run to convergence (|residual| < 1e-12 in normalised units,
//! far below a thousandth of a pixel), and a point is *rejected* when it does not converge
//! or lands where the model folds over (the Jacobian's determinant is not positive, e.g.
//! beyond the radius where a negative k2 makes the radial factor turn back). A keypoint
//! there has no unique undistorted position, and silently keeping OpenCV's guess would
//! feed a wrong ray to triangulation.
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
//! let (u, v) = (100.25, 1800.5);
//! let (ud, vd) = distort_pixel(intrinsics, lens, u, v);
//! let (u2, v2) = undistort_pixel(intrinsics, lens, ud, vd).expect("inside the model's range");
//! assert!((u2 - u).abs() < 1e-6 && (v2 - v).abs() < 1e-6);
//! ```

use std::path::Path;

use image::ImageEncoder;

use profuse_formats::Cameras;
use serde::Serialize;

use crate::error::{Result, SceneError};
use crate::fsutil::{show, write_atomically};

/// OpenCV k1, k2, p1, p2.
pub type Lens = [f64; 4];

/// Newton iterations before giving up.
const MAX_ITERATIONS: usize = 50;
/// Convergence tolerance on the residual, in normalised image units.
const TOLERANCE: f64 = 1e-12;

/// Applies the lens model to undistorted normalised coordinates.
pub fn distort(lens: Lens, x: f64, y: f64) -> (f64, f64) {
    let [k1, k2, p1, p2] = lens;
    let r2 = x * x + y * y;
    let s = 1.0 + k1 * r2 + k2 * r2 * r2;
    (
        x * s + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
        y * s + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
    )
}

/// The Jacobian `∂(x_d, y_d)/∂(x, y)` of [`distort`], row-major.
fn jacobian(lens: Lens, x: f64, y: f64) -> [f64; 4] {
    let [k1, k2, p1, p2] = lens;
    let r2 = x * x + y * y;
    let s = 1.0 + k1 * r2 + k2 * r2 * r2;
    // ∂s/∂x = (k1 + 2 k2 r²) · 2x, and likewise for y.
    let ds = 2.0 * (k1 + 2.0 * k2 * r2);
    let (dsdx, dsdy) = (ds * x, ds * y);
    [
        s + x * dsdx + 2.0 * p1 * y + 6.0 * p2 * x,
        x * dsdy + 2.0 * p1 * x + 2.0 * p2 * y,
        y * dsdx + 2.0 * p1 * x + 2.0 * p2 * y,
        s + y * dsdy + 6.0 * p1 * y + 2.0 * p2 * x,
    ]
}

/// Inverts [`distort`] by Newton's method; `None` when the iteration does not converge or
/// converges where the model is not locally invertible (Jacobian determinant <= 0).
pub fn undistort(lens: Lens, xd: f64, yd: f64) -> Option<(f64, f64)> {
    if !(xd.is_finite() && yd.is_finite()) {
        return None;
    }
    let (mut x, mut y) = (xd, yd);
    for _ in 0..MAX_ITERATIONS {
        let (fx, fy) = distort(lens, x, y);
        let (rx, ry) = (fx - xd, fy - yd);
        let [a, b, c, d] = jacobian(lens, x, y);
        let det = a * d - b * c;
        if rx.abs() < TOLERANCE && ry.abs() < TOLERANCE {
            return (det > 0.0).then_some((x, y));
        }
        if det.is_nan() || det.abs() < 1e-300 {
            return None;
        }
        x -= (d * rx - b * ry) / det;
        y -= (a * ry - c * rx) / det;
        if !(x.is_finite() && y.is_finite()) {
            return None;
        }
    }
    None
}

/// Distorts a pinhole pixel position `(u, v)` (SPEC.md §3.3 pixel coordinates) of a camera
/// with `intrinsics = [fx, fy, cx, cy]`.
pub fn distort_pixel(intrinsics: [f64; 4], lens: Lens, u: f64, v: f64) -> (f64, f64) {
    let [fx, fy, cx, cy] = intrinsics;
    let (xd, yd) = distort(lens, (u - cx) / fx, (v - cy) / fy);
    (xd * fx + cx, yd * fy + cy)
}

/// The pinhole pixel position of a distorted pixel position; `None` where [`undistort`]
/// rejects it.
pub fn undistort_pixel(intrinsics: [f64; 4], lens: Lens, u: f64, v: f64) -> Option<(f64, f64)> {
    let [fx, fy, cx, cy] = intrinsics;
    let (x, y) = undistort(lens, (u - cx) / fx, (v - cy) / fy)?;
    Some((x * fx + cx, y * fy + cy))
}

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
            let (su, sv) = distort_pixel(intrinsics, lens, x as f64 + 0.5, y as f64 + 0.5);
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
        let src = scene_dir.join(name);
        let label = show(&src);
        let img = image::open(&src)
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
        let mut png = Vec::new();
        image::codecs::png::PngEncoder::new(&mut png)
            .write_image(&rgb, w as u32, h as u32, image::ExtendedColorType::Rgb8)
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

    const FOX: Lens = [0.0578421, -0.0805099, -0.000980296, 0.00015575];

    #[test]
    fn distort_matches_the_opencv_formula_on_a_hand_case() {
        // x = 0.3, y = -0.2: r² = 0.13, s = 1 + 0.1·0.13 + 0.01·0.0169 = 1.013169.
        let (xd, yd) = distort([0.1, 0.01, 0.001, 0.002], 0.3, -0.2);
        let xe = 0.3 * 1.013169 + 2.0 * 0.001 * 0.3 * -0.2 + 0.002 * (0.13 + 2.0 * 0.09);
        let ye = -0.2 * 1.013169 + 0.001 * (0.13 + 2.0 * 0.04) + 2.0 * 0.002 * 0.3 * -0.2;
        assert!((xd - xe).abs() < 1e-15 && (yd - ye).abs() < 1e-15);
    }

    #[test]
    fn jacobian_agrees_with_finite_differences() {
        for &(x, y) in &[(0.1, 0.2), (-0.4, 0.3), (0.0, -0.6)] {
            let j = jacobian(FOX, x, y);
            let h = 1e-7;
            let (ax, ay) = distort(FOX, x + h, y);
            let (bx, by) = distort(FOX, x - h, y);
            let (cx, cy) = distort(FOX, x, y + h);
            let (dx, dy) = distort(FOX, x, y - h);
            let num = [
                (ax - bx) / (2.0 * h),
                (cx - dx) / (2.0 * h),
                (ay - by) / (2.0 * h),
                (cy - dy) / (2.0 * h),
            ];
            for (a, b) in j.iter().zip(num) {
                assert!((a - b).abs() < 1e-7, "{j:?} vs {num:?}");
            }
        }
    }

    #[test]
    fn undistort_inverts_distort_over_the_fox_image() {
        let k = [1375.52, 1374.49, 554.558, 965.268];
        let mut worst: f64 = 0.0;
        for v in (0..1920).step_by(37) {
            for u in (0..1080).step_by(29) {
                let (u, v) = (f64::from(u) + 0.5, f64::from(v) + 0.5);
                let (ud, vd) = distort_pixel(k, FOX, u, v);
                let (u2, v2) = undistort_pixel(k, FOX, ud, vd).unwrap();
                worst = worst.max((u2 - u).abs()).max((v2 - v).abs());
            }
        }
        assert!(worst < 1e-8, "worst round-trip error {worst} px");
    }

    #[test]
    fn points_beyond_the_fold_are_rejected() {
        // s = 1 − r²: r_d = r − r³ peaks at r = 1/√3 (r_d ≈ 0.385); beyond it no inverse.
        let lens = [-1.0, 0.0, 0.0, 0.0];
        assert!(undistort(lens, 0.3, 0.0).is_some());
        assert!(undistort(lens, 0.5, 0.0).is_none());
        assert!(undistort(lens, f64::NAN, 0.0).is_none());
    }

    #[test]
    fn zero_lens_is_the_identity_on_images() {
        let (w, h) = (7, 5);
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 7 % 256) as u8).collect();
        let out = undistort_rgb(&rgb, w, h, [5.0, 5.0, 3.5, 2.5], [0.0; 4]);
        assert_eq!(out, rgb);
    }
}

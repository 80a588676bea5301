//! Decoded RGB images and the bilinear resampling every model input is made with.

use std::path::Path;

use crate::error::{PrepError, Result};

/// An 8-bit RGB image, row-major, 3 bytes per pixel.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbImage {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// `height * width * 3` bytes.
    pub pixels: Vec<u8>,
}

impl RgbImage {
    /// The pixel's channel `c` at (x, y).
    #[inline]
    pub fn at(&self, x: usize, y: usize, c: usize) -> u8 {
        self.pixels[(y * self.width + x) * 3 + c]
    }
}

/// Reads and decodes an image file (PNG or JPEG) as RGB.
pub fn load_rgb(path: &Path) -> Result<RgbImage> {
    let err = |message: String| PrepError::Image {
        path: path.to_path_buf(),
        message,
    };
    let img = image::ImageReader::open(path)
        .map_err(|e| err(e.to_string()))?
        .with_guessed_format()
        .map_err(|e| err(e.to_string()))?
        .decode()
        .map_err(|e| err(e.to_string()))?
        .into_rgb8();
    Ok(RgbImage {
        width: img.width() as usize,
        height: img.height() as usize,
        pixels: img.into_raw(),
    })
}

/// Source taps of bilinear resampling from `src` to `dst` samples with half-pixel
/// centres (OpenCV's INTER_LINEAR, no antialiasing): for each output sample the two
/// input indices and the weight of the second.
pub fn taps(src: usize, dst: usize) -> Vec<(usize, usize, f32)> {
    let ratio = src as f64 / dst as f64;
    (0..dst)
        .map(|i| {
            let s = ((i as f64 + 0.5) * ratio - 0.5).max(0.0);
            let i0 = (s.floor() as usize).min(src - 1);
            let i1 = (i0 + 1).min(src - 1);
            (i0, i1, (s - i0 as f64) as f32)
        })
        .collect()
}

/// Bilinear resampling of a region of `img` (x0, y0, w, h) to `dw x dh`, channel `c`
/// through `f(value) -> out` into a planar buffer `out[c][y][x]` of row stride `stride`.
pub(crate) fn resample_planar(
    img: &RgbImage,
    region: (usize, usize, usize, usize),
    size: (usize, usize),
    stride: usize,
    plane: usize,
    out: &mut [f32],
    f: impl Fn(usize, f32) -> f32,
) {
    let (x0, y0, w, h) = region;
    let (dw, dh) = size;
    let xs = taps(w, dw);
    let ys = taps(h, dh);
    for (y, &(ya, yb, fy)) in ys.iter().enumerate() {
        for (x, &(xa, xb, fx)) in xs.iter().enumerate() {
            for c in 0..3 {
                let p = |xx: usize, yy: usize| f32::from(img.at(x0 + xx, y0 + yy, c));
                let top = p(xa, ya) * (1.0 - fx) + p(xb, ya) * fx;
                let bottom = p(xa, yb) * (1.0 - fx) + p(xb, yb) * fx;
                out[c * plane + y * stride + x] = f(c, top * (1.0 - fy) + bottom * fy);
            }
        }
    }
}

//! Binary image masks: polygon rasterisation on pixel centres, PNG reading, IoU.
//!
//! # The pixel-centre rule
//!
//! Pixel (x, y) covers `[x, x+1) × [y, y+1)` (origin at the top-left image corner, y down),
//! and belongs to a polygon iff its centre `(x + 0.5, y + 0.5)` is inside by the
//! **even-odd** rule: a ray from the centre towards +x crosses the boundary an odd number
//! of times. An edge `a → b` is crossed when `(a.y > c.y) != (b.y > c.y)` and the crossing
//! lies strictly right of the centre. The test is an exact sign test on cross products
//! (no division), so it is exact for coordinates on a half-pixel grid (integer pixel
//! corners, as synth and LangSplat's labels use).
//!
//! **Ties**: a centre exactly on the boundary is classified like the point infinitesimally
//! to its right and below, so it is inside on a left or top edge and outside on a right
//! or bottom edge (the top-left rule of GPU rasterisers). Adjacent polygons sharing an
//! edge therefore never both own a pixel, and a pixel-aligned square `[x0, x1] × [y0, y1]`
//! covers exactly `(x1 − x0) · (y1 − y0)` pixels even when its edges pass through centres.
//! Doubled "bridge" edges (traversed once each way, as synth uses to join holes) cancel.

use std::path::Path;

use crate::{MetricsError, Result};

/// A binary mask of `width × height` pixels, row-major.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Mask {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `pixels[y * width + x]`: whether pixel (x, y) is selected.
    pub pixels: Vec<bool>,
}

impl Mask {
    /// An empty (all false) mask.
    pub fn empty(width: u32, height: u32) -> Mask {
        Mask {
            width,
            height,
            pixels: vec![false; width as usize * height as usize],
        }
    }

    /// Number of selected pixels.
    pub fn count(&self) -> u64 {
        self.pixels.iter().filter(|p| **p).count() as u64
    }

    /// Adds the pixels of `other` (same size; smaller overlaps are cut).
    pub fn union_with(&mut self, other: &Mask) {
        for (a, b) in self.pixels.iter_mut().zip(&other.pixels) {
            *a |= *b;
        }
    }

    /// Number of pixels selected in both masks.
    pub fn intersection(&self, other: &Mask) -> u64 {
        self.pixels
            .iter()
            .zip(&other.pixels)
            .filter(|(a, b)| **a && **b)
            .count() as u64
    }
}

/// Whether the crossing of edge `a → b` (which straddles the row `y = py`) lies strictly
/// right of `px`: sign of `((a.x − px)·dy + (py − a.y)·dx) · dy`, no division.
fn crossing_right_of(a: [f64; 2], b: [f64; 2], px: f64, py: f64) -> bool {
    let dy = b[1] - a[1];
    let num = (a[0] - px) * dy + (py - a[1]) * (b[0] - a[0]);
    (num > 0.0 && dy > 0.0) || (num < 0.0 && dy < 0.0)
}

/// Rasterises a closed polygon (vertices in pixel coordinates; the last vertex connects
/// to the first) with the pixel-centre even-odd rule of the module documentation.
/// Fewer than three vertices give an empty mask; non-finite vertices are skipped by the
/// crossing test (callers validate them, see [`crate::lerf::read_label_file`]).
///
/// ```
/// use profuse_metrics::mask::rasterize_polygon;
/// // The square [1, 3] x [1, 3] covers pixels 1..3 x 1..3.
/// let m = rasterize_polygon(&[[1.0, 1.0], [3.0, 1.0], [3.0, 3.0], [1.0, 3.0]], 4, 4);
/// assert_eq!(m.count(), 4);
/// assert!(m.pixels[1 * 4 + 1] && m.pixels[2 * 4 + 2] && !m.pixels[3 * 4 + 3]);
/// ```
pub fn rasterize_polygon(points: &[[f64; 2]], width: u32, height: u32) -> Mask {
    let mut mask = Mask::empty(width, height);
    if points.len() < 3 || width == 0 {
        return mask;
    }
    let w = width as usize;
    let (lo, hi) = points
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), p| {
            (l.min(p[1]), h.max(p[1]))
        });
    if !(lo.is_finite() && hi.is_finite()) {
        return mask;
    }
    // Rows whose centre can lie in [lo, hi].
    let first = (lo - 0.5).ceil().max(0.0) as usize;
    let last = ((hi - 0.5).floor().min(f64::from(height) - 1.0)).max(-1.0);
    if last < 0.0 {
        return mask;
    }
    // toggles[k]: crossings whose first pixel not left of them is k; pixel x is inside iff
    // the crossings with k > x are odd in number.
    let mut toggles = vec![0u32; w + 1];
    for y in first..=last as usize {
        let py = y as f64 + 0.5;
        toggles.iter_mut().for_each(|t| *t = 0);
        let mut any = false;
        for (i, &a) in points.iter().enumerate() {
            let b = points[(i + 1) % points.len()];
            if (a[1] > py) == (b[1] > py) {
                continue;
            }
            let xx = a[0] + (py - a[1]) * (b[0] - a[0]) / (b[1] - a[1]);
            if !xx.is_finite() {
                continue;
            }
            // Guess k = #{x : x + 0.5 < xx}, then settle it with the exact test.
            let mut k = (xx - 0.5).ceil().clamp(0.0, w as f64) as usize;
            while k > 0 && !crossing_right_of(a, b, k as f64 - 0.5, py) {
                k -= 1;
            }
            while k < w && crossing_right_of(a, b, k as f64 + 0.5, py) {
                k += 1;
            }
            toggles[k] += 1;
            any = true;
        }
        if !any {
            continue;
        }
        let row = &mut mask.pixels[y * w..(y + 1) * w];
        let mut parity = 0u32;
        for x in (0..w).rev() {
            parity += toggles[x + 1];
            row[x] = parity % 2 == 1;
        }
    }
    mask
}

/// Reads a PNG (or any format the `image` crate decodes) as a mask: a pixel is selected
/// when any colour channel is non-zero (alpha is ignored). The size must be
/// `width × height`, else [`MetricsError::MaskSize`].
pub fn read_mask_png(path: &Path, width: u32, height: u32) -> Result<Mask> {
    let shown = || path.display().to_string();
    let img = image::ImageReader::open(path)
        .map_err(crate::error::io_err(path, "cannot open mask"))?
        .with_guessed_format()
        .map_err(crate::error::io_err(path, "cannot read mask"))?
        .decode()
        .map_err(|source| MetricsError::Image {
            path: shown(),
            source,
        })?;
    if img.width() != width || img.height() != height {
        return Err(MetricsError::MaskSize {
            path: shown(),
            width,
            height,
            found_width: img.width(),
            found_height: img.height(),
        });
    }
    let pixels = match img {
        image::DynamicImage::ImageLuma8(b) => b.into_raw().into_iter().map(|v| v != 0).collect(),
        other => other
            .to_rgb16()
            .pixels()
            .map(|p| p.0 != [0, 0, 0])
            .collect(),
    };
    Ok(Mask {
        width,
        height,
        pixels,
    })
}

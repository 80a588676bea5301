//! Label-map previews for checking masks by eye: the photo at the mask grid with each
//! mask in its own colour blended at one half, mask borders dark, uncovered pixels grey.

use crate::image::{taps, RgbImage};

/// A fixed colour per view-local mask index (SplitMix64 of the index, channels 40..255).
pub fn mask_colour(label: u16) -> [u8; 3] {
    let mut z = u64::from(label).wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    [0, 8, 16].map(|s| 40 + ((z >> s) & 0xFF) as u8 % 216)
}

/// The overlay (RGB, `grid` = (height, width)) of a label map over its photo.
pub fn overlay(img: &RgbImage, labels: &[u16], grid: (usize, usize)) -> Vec<u8> {
    let (h, w) = grid;
    let xs = taps(img.width, w);
    let ys = taps(img.height, h);
    let mut out = vec![0u8; h * w * 3];
    for y in 0..h {
        for x in 0..w {
            let l = labels[y * w + x];
            let border = (x + 1 < w && labels[y * w + x + 1] != l)
                || (y + 1 < h && labels[(y + 1) * w + x] != l);
            for c in 0..3 {
                let p = f32::from(img.at(xs[x].0, ys[y].0, c));
                let v = if l == u16::MAX {
                    0.3 * p + 0.7 * 128.0
                } else if border {
                    0.2 * p
                } else {
                    0.5 * p + 0.5 * f32::from(mask_colour(l)[c])
                };
                out[(y * w + x) * 3 + c] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    out
}

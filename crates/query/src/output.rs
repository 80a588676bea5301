//! Atomic PNG writes (temporary file in the target directory, renamed into place) and
//! the overlay image.

use std::io::Write;
use std::path::Path;

use image::ExtendedColorType;

use crate::error::{io_err, QueryError, Result};

/// Colour the selection is tinted with in overlays.
pub const OVERLAY_TINT: [f32; 3] = [1.0, 0.1, 0.1];
/// Share of the tint in a selected overlay pixel.
pub const OVERLAY_MIX: f32 = 0.55;

/// Writes an 8-bit PNG (`Rgb8` or `L8`) atomically.
pub(crate) fn write_png(
    path: &Path,
    width: usize,
    height: usize,
    data: &[u8],
    color: ExtendedColorType,
) -> Result<()> {
    let bytes = profuse_formats::png::encode(data, width as u32, height as u32, color).map_err(
        |source| QueryError::Image {
            path: path.display().to_string(),
            source,
        },
    )?;
    profuse_formats::write_atomically(path, |mut f| f.write_all(&bytes))
        .map_err(|(action, e)| io_err(path, action)(e))
}

/// The rendered colour (f32 RGB in [0, 1], [H, W, 3]) with the pixels of `mask` (255 =
/// selected) tinted: `(1 − m)·rgb + m·tint`, m = [`OVERLAY_MIX`]; other pixels unchanged.
pub fn overlay(rgb: &[f32], mask: &[u8]) -> Vec<u8> {
    rgb.chunks_exact(3)
        .zip(mask)
        .flat_map(|(c, &m)| {
            let mix = if m > 0 { OVERLAY_MIX } else { 0.0 };
            std::array::from_fn::<u8, 3, _>(|i| to_u8((1.0 - mix) * c[i] + mix * OVERLAY_TINT[i]))
        })
        .collect()
}

/// [0, 1] → 0..=255, rounded, clamped (NaN → 0).
pub(crate) fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// Creates a directory and its parents.
pub(crate) fn create_dir(path: &Path) -> Result<()> {
    std::fs::create_dir_all(path).map_err(io_err(path, "cannot create directory"))
}

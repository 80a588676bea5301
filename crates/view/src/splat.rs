//! The scene in the viewer's compact form: antimatter15's `.splat` rows (what gsplat.js
//! reads), 32 bytes per Gaussian, in Gaussian id order so that row i is Gaussian i and a
//! selection's ids index the rows directly.
//!
//! Row layout (little-endian): position f32×3, scale f32×3 (standard deviations, exp of
//! the log scales), colour RGBA u8×4 (RGB = 0.5 + C0·sh_dc clamped to [0, 1], A = the
//! opacity sigmoid), rotation u8×4 (the unit quaternion w, x, y, z, each mapped by
//! round(q·128 + 128) clamped to 0..=255; the reader decodes (b − 128)/128).
//! Higher SH bands are dropped: the viewer shows the view-independent colour.

use profuse_formats::camera::sh_dc_to_colour;
use profuse_formats::Gaussians;

/// Bytes of one row.
pub const SPLAT_ROW_BYTES: usize = 32;

/// Converts every Gaussian to one `.splat` row, in id order.
pub fn splat_bytes(g: &Gaussians) -> Vec<u8> {
    let mut out = Vec::with_capacity(g.len() * SPLAT_ROW_BYTES);
    for i in 0..g.len() {
        for c in g.means[i] {
            out.extend_from_slice(&c.to_le_bytes());
        }
        for s in g.log_scales[i] {
            out.extend_from_slice(&s.exp().to_le_bytes());
        }
        for c in g.sh_dc[i] {
            out.push(unit_to_byte(sh_dc_to_colour(f64::from(c))));
        }
        out.push(unit_to_byte(sigmoid(f64::from(g.opacity_logits[i]))));
        out.extend_from_slice(&quaternion_bytes(g.rotations[i]));
    }
    out
}

/// The opacity of a logit.
pub fn sigmoid(logit: f64) -> f64 {
    1.0 / (1.0 + (-logit).exp())
}

/// A value of [0, 1] (clamped) as a byte, rounded to nearest.
pub fn unit_to_byte(v: f64) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// The quaternion (w, x, y, z), normalised, as the four rotation bytes. The format
/// guarantees a non-zero quaternion.
pub fn quaternion_bytes(q: [f32; 4]) -> [u8; 4] {
    let norm = q.iter().map(|v| f64::from(*v).powi(2)).sum::<f64>().sqrt();
    q.map(|v| {
        (f64::from(v) / norm * 128.0 + 128.0)
            .round()
            .clamp(0.0, 255.0) as u8
    })
}

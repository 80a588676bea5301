//! The single-precision splat the tile loop reads (one cache line), and the sink projection
//! writes splats into.

use super::*;

/// A projected Gaussian in the single-precision form the tile loop uses, with the pixel
/// rectangle it can change (one 64-byte cache line).
#[derive(Debug, Clone, Copy)]
#[repr(C, align(64))]
pub(crate) struct Splat {
    pub x: f32,
    pub y: f32,
    pub a: f32,
    pub b: f32,
    pub c: f32,
    pub opacity: f32,
    pub color: [f32; 3],
    pub depth: f32,
    pub id: u32,
    /// 2 a (ln(255 · opacity) + margin): a pixel row dy has pixels with alpha >= 1/255 only
    /// where 2 a tau − det dy² >= 0.
    pub two_a_tau: f32,
    /// a c − b² of the single-precision conic.
    pub det: f32,
    /// 1 / a, or 0 when the per-row spans cannot be trusted (then whole rect rows are
    /// visited).
    pub inv_a: f32,
    /// Inclusive pixel rectangle (inside the image and the 3-sigma tiles) outside which the
    /// Gaussian has alpha < 1/255 everywhere: x0, x1, y0, y1.
    pub rect: [u16; 4],
}

/// Margin added to ln(255·opacity) when bounding the footprint, far above any f32 rounding
/// of the per-pixel test.
pub(super) const TAU_MARGIN: f64 = 0.05;

/// Slack, in pixels, of a splat's rectangle beyond the ellipse bound when the tile loop
/// solves per-row spans: that of the spans themselves (`raster::SPAN_SLACK`), far above the
/// f64 rounding of the bound (TAU_MARGIN adds more).
pub(super) const RECT_SLACK: f64 = 1.0 / 64.0;

impl Splat {
    // Rendering goes through `project_chunk`; this is its reference in the tests.
    #[cfg_attr(not(test), allow(dead_code))]
    /// The tile-loop form of `p`, or `None` when no pixel of the image can reach alpha >= 1/255.
    /// `tau` is [`footprint_tau`] of its opacity.
    pub fn new(p: &Projected, tau: f64, width: u32, height: u32) -> Option<Splat> {
        let opacity = p.opacity as f32;
        // alpha = min(0.99, o · exp(power)) <= o with power <= 0: never drawn.
        if opacity.is_nan() || opacity < ALPHA_MIN {
            return None;
        }
        let [u, v] = p.center;
        let [a, b, c] = p.conic.map(|x| x as f32);
        let (x, y) = (u as f32, v as f32);
        // The per-pixel arithmetic needs finite single-precision parameters (a centre
        // beyond f32 range with a footprint on the image needs a covariance beyond it too).
        if ![x, y, a, b, c].iter().all(|v| v.is_finite()) {
            return None;
        }
        let det = a * c - b * b;
        let two_a_tau = 2.0 * a * tau as f32;
        let inv_a = 1.0 / a;
        let spans =
            a > 0.0 && det > 0.0 && det.is_finite() && two_a_tau.is_finite() && inv_a.is_finite();
        // Axis-aligned extent of the ellipse {½ dᵀ Σ⁻¹ d <= tau}: sqrt(2 tau Σ_xx). Where the
        // tile loop solves each row's span, the rectangle only has to be as safe as those
        // spans (the same slack); where it visits whole rows, it is widened by a pixel.
        let slack = if spans { RECT_SLACK } else { 1.0 };
        let ex = (2.0 * tau * p.cov2d[0]).sqrt();
        let ey = (2.0 * tau * p.cov2d[2]).sqrt();
        let span = |c: f64, e: f64, t0: u32, t1: u32, size: u32| -> Option<[u16; 2]> {
            // Pixel centres px + 0.5 within [c − e − slack, c + e + slack].
            let lo = ceil(c - e - 0.5 - slack);
            let hi = floor(c + e - 0.5 + slack);
            let lo = lo.max(f64::from(t0) * TILE as f64).max(0.0);
            let hi = hi
                .min(f64::from(t1) * TILE as f64 + (TILE - 1) as f64)
                .min(f64::from(size) - 1.0);
            (lo <= hi).then_some([lo as u16, hi as u16])
        };
        let [x0, x1] = span(u, ex, p.tiles[0], p.tiles[1], width)?;
        let [y0, y1] = span(v, ey, p.tiles[2], p.tiles[3], height)?;
        Some(Splat {
            x,
            y,
            a,
            b,
            c,
            opacity,
            color: p.color.map(|x| x as f32),
            depth: p.depth as f32,
            id: p.id,
            two_a_tau,
            det,
            inv_a: if spans { inv_a } else { 0.0 },
            rect: [x0, x1, y0, y1],
        })
    }
}

/// Where [`project_chunk`] puts the splats it keeps, in slot order, each with its slot.
pub(crate) trait SplatSink {
    fn push(&mut self, slot: usize, splat: Splat);
}

/// Appends (the tests' sink).
impl SplatSink for Vec<Splat> {
    #[inline(always)]
    fn push(&mut self, _slot: usize, splat: Splat) {
        Vec::push(self, splat);
    }
}

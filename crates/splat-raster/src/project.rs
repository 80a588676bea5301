//! Per-Gaussian work: view-independent preparation (3D covariance, opacity) and the EWA
//! projection into one view.

use profuse_formats::Gaussians;

use crate::camera::ViewCamera;
use crate::error::{RasterError, Result};
use crate::sh::eval_sh;
use crate::{ALPHA_MIN, FRUSTUM_CLAMP, LOW_PASS, NEAR_PLANE, SIGMA_EXTENT, TILE};

/// One Gaussian projected into one view, in double precision (INRIA's `preprocessCUDA`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Projected {
    /// Index of the Gaussian.
    pub id: u32,
    /// Projected mean `(u, v)` in pixels, SPEC convention: `u = fx X/Z + cx`, pixel
    /// `(px, py)` has its centre at `(px + 0.5, py + 0.5)`.
    pub center: [f64; 2],
    /// Camera-space z of the mean.
    pub depth: f64,
    /// 2D covariance `[xx, xy, yy]` in pixels², including the 0.3 low-pass.
    pub cov2d: [f64; 3],
    /// Its inverse `[a, b, c]`: power = −½(a dx² + c dy²) − b dx dy.
    pub conic: [f64; 3],
    /// ceil(3 · sqrt(largest eigenvalue)) in pixels.
    pub radius: f64,
    /// Tiles touched by the square `[u − r, u + r] × [v − r, v + r]`, inclusive, clamped to
    /// the tile grid: `[tx0, tx1, ty0, ty1]`, tile of coordinate x = floor(x / 16).
    pub tiles: [u32; 4],
    /// RGB colour from the SH (view dependent for degree > 0), clamped at 0.
    pub color: [f64; 3],
    /// sigmoid(opacity logit).
    pub opacity: f64,
}

/// View-independent data of every Gaussian.
#[derive(Debug, Clone)]
pub(crate) struct Prepared {
    /// Upper triangle of Σ = R S Sᵀ Rᵀ: xx, xy, xz, yy, yz, zz.
    pub cov3d: Vec<[f64; 6]>,
    /// sigmoid(opacity logit).
    pub opacity: Vec<f64>,
    /// ln(255 · opacity) + [`TAU_MARGIN`]: the footprint bound of [`Splat::new`], view
    /// independent, so computed once here rather than once per view.
    pub tau: Vec<f64>,
}

pub(crate) fn prepare(g: &Gaussians) -> Result<Prepared> {
    let n = g.len();
    let check_len = |field: &'static str, got: usize, expected: usize| {
        if got == expected {
            Ok(())
        } else {
            Err(RasterError::InconsistentGaussians {
                field,
                got,
                expected,
            })
        }
    };
    check_len("log_scales", g.log_scales.len(), n)?;
    check_len("rotations", g.rotations.len(), n)?;
    check_len("opacity_logits", g.opacity_logits.len(), n)?;
    check_len("sh_dc", g.sh_dc.len(), n)?;
    if g.sh_degree > 3 {
        return Err(RasterError::InconsistentGaussians {
            field: "sh_degree",
            got: g.sh_degree,
            expected: 3,
        });
    }
    let rest_len = g.sh_rest.as_ref().map_or(0, |r| r.len());
    check_len("sh_rest", rest_len, n * g.sh_rest_coeffs() * 3)?;

    let non_finite = |index: usize, field: &'static str, value: String| {
        Err(RasterError::NonFiniteGaussian {
            index,
            field,
            value,
        })
    };
    for i in 0..n {
        if !g.means[i].iter().all(|v| v.is_finite()) {
            return non_finite(i, "means", format!("{:?}", g.means[i]));
        }
        if !g.log_scales[i].iter().all(|v| v.is_finite()) {
            return non_finite(i, "log_scales", format!("{:?}", g.log_scales[i]));
        }
        if !g.rotations[i].iter().all(|v| v.is_finite()) {
            return non_finite(i, "rotations", format!("{:?}", g.rotations[i]));
        }
        if g.rotations[i].iter().all(|v| *v == 0.0) {
            return Err(RasterError::ZeroRotation { index: i });
        }
        if g.opacity_logits[i].is_nan() {
            return non_finite(i, "opacity_logits", "NaN".into());
        }
        if !g.sh_dc[i].iter().all(|v| v.is_finite()) {
            return non_finite(i, "sh_dc", format!("{:?}", g.sh_dc[i]));
        }
    }
    if let Some(rest) = &g.sh_rest {
        let per = g.sh_rest_coeffs() * 3;
        if let Some(pos) = rest.iter().position(|v| !v.is_finite()) {
            return non_finite(pos / per, "sh_rest", format!("{}", rest[pos]));
        }
    }

    let cov3d = (0..n)
        .map(|i| covariance_3d(g.log_scales[i], g.rotations[i]))
        .collect();
    let opacity: Vec<f64> = g
        .opacity_logits
        .iter()
        .map(|l| 1.0 / (1.0 + (-f64::from(*l)).exp()))
        .collect();
    let tau = opacity.iter().map(|&o| footprint_tau(o)).collect();
    Ok(Prepared {
        cov3d,
        opacity,
        tau,
    })
}

/// ln(255 · opacity) + [`TAU_MARGIN`]: pixels with ½ dᵀ Σ⁻¹ d > tau have alpha < 1/255.
pub(crate) fn footprint_tau(opacity: f64) -> f64 {
    (255.0 * opacity).ln() + TAU_MARGIN
}

/// Σ = R S Sᵀ Rᵀ from log-scales and a (w, x, y, z) quaternion, normalised here.
/// Returns the upper triangle xx, xy, xz, yy, yz, zz.
pub fn covariance_3d(log_scales: [f32; 3], q: [f32; 4]) -> [f64; 6] {
    let [w, x, y, z] = q.map(f64::from);
    let n = (w * w + x * x + y * y + z * z).sqrt();
    let (w, x, y, z) = (w / n, x / n, y / n, z / n);
    let r = [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ];
    let s = log_scales.map(|l| f64::from(l).exp());
    // M = R S: column j of R scaled by s_j; Σ = M Mᵀ.
    let m: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| r[i][j] * s[j]));
    let e = |i: usize, j: usize| m[i][0] * m[j][0] + m[i][1] * m[j][1] + m[i][2] * m[j][2];
    [e(0, 0), e(0, 1), e(0, 2), e(1, 1), e(1, 2), e(2, 2)]
}

/// `x.floor()` without a libm call (baseline x86-64 has no rounding instruction, and the
/// call showed in profiles of million-Gaussian views). Exact: below 2^52 in magnitude the
/// truncating casts are exact, beyond it every f64 is an integer; NaN stays NaN.
#[inline]
pub(crate) fn floor(x: f64) -> f64 {
    if x.abs() < 4_503_599_627_370_496.0 {
        let t = x as i64 as f64;
        if t > x {
            t - 1.0
        } else {
            t
        }
    } else {
        x
    }
}

/// `x.ceil()` without a libm call, exact as [`floor`].
#[inline]
pub(crate) fn ceil(x: f64) -> f64 {
    -floor(-x)
}

/// Projects Gaussian `i` into `cam`; `None` when it is culled (near plane, degenerate 2D
/// covariance, off the tile grid).
pub(crate) fn project(
    g: &Gaussians,
    prep: &Prepared,
    cam: &ViewCamera,
    campos: [f64; 3],
    i: usize,
) -> Option<Projected> {
    let mean = g.means[i].map(f64::from);
    let p = cam.to_camera(mean);
    let z = p[2];
    // INRIA `in_frustum`: z <= 0.2 is culled (NaN is culled too).
    if z.is_nan() || z <= NEAR_PLANE {
        return None;
    }
    let [fx, fy, cx, cy] = cam.intrinsics;
    let (w, h) = (f64::from(cam.width), f64::from(cam.height));
    let u = fx * p[0] / z + cx;
    let v = fy * p[1] / z + cy;

    // EWA: Jacobian of the perspective projection at the mean, with x/z and y/z clamped to
    // 1.3 x the half field of view (INRIA `computeCov2D`). The tangent range of the image is
    // [−cx/fx, (w − cx)/fx]; it is widened by 1.3 about its middle, which for a centred
    // principal point is INRIA's ±1.3·tan(fov/2).
    let clamp_tan = |t: f64, c: f64, f: f64, size: f64| {
        let (lo, hi) = (-c / f, (size - c) / f);
        let (mid, half) = (0.5 * (lo + hi), 0.5 * (hi - lo));
        t.clamp(mid - FRUSTUM_CLAMP * half, mid + FRUSTUM_CLAMP * half)
    };
    let tx = clamp_tan(p[0] / z, cx, fx, w) * z;
    let ty = clamp_tan(p[1] / z, cy, fy, h) * z;
    let j = [
        [fx / z, 0.0, -fx * tx / (z * z)],
        [0.0, fy / z, -fy * ty / (z * z)],
    ];
    // T = J W (2x3), W = world-to-camera rotation.
    let r = &cam.rotation;
    let t: [[f64; 3]; 2] = std::array::from_fn(|a| {
        std::array::from_fn(|b| j[a][0] * r[0][b] + j[a][1] * r[1][b] + j[a][2] * r[2][b])
    });
    let [sxx, sxy, sxz, syy, syz, szz] = prep.cov3d[i];
    let sigma = [[sxx, sxy, sxz], [sxy, syy, syz], [sxz, syz, szz]];
    // cov2d = T Σ Tᵀ
    let ts: [[f64; 3]; 2] = std::array::from_fn(|a| {
        std::array::from_fn(|b| {
            t[a][0] * sigma[0][b] + t[a][1] * sigma[1][b] + t[a][2] * sigma[2][b]
        })
    });
    let e = |a: usize, b: usize| ts[a][0] * t[b][0] + ts[a][1] * t[b][1] + ts[a][2] * t[b][2];
    let ca = e(0, 0) + LOW_PASS;
    let cb = e(0, 1);
    let cc = e(1, 1) + LOW_PASS;
    let det = ca * cc - cb * cb;
    if det.is_nan() || det <= 0.0 || !det.is_finite() || !ca.is_finite() || !cc.is_finite() {
        return None;
    }
    let conic = [cc / det, -cb / det, ca / det];
    let mid = 0.5 * (ca + cc);
    let disc = (mid * mid - det).max(0.1).sqrt();
    let lambda = (mid + disc).max(mid - disc);
    let radius = ceil(SIGMA_EXTENT * lambda.sqrt());

    let (tiles_x, tiles_y) = cam.tiles();
    let tile_range = |c: f64, n: usize| -> Option<[u32; 2]> {
        let lo = floor((c - radius) / TILE as f64);
        let hi = floor((c + radius) / TILE as f64);
        let last = (n - 1) as f64;
        if !(hi >= 0.0 && lo <= last) {
            return None;
        }
        Some([lo.max(0.0) as u32, hi.min(last) as u32])
    };
    let [tx0, tx1] = tile_range(u, tiles_x)?;
    let [ty0, ty1] = tile_range(v, tiles_y)?;

    let color = {
        let d = [
            mean[0] - campos[0],
            mean[1] - campos[1],
            mean[2] - campos[2],
        ];
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let dir = if n > 0.0 {
            [d[0] / n, d[1] / n, d[2] / n]
        } else {
            [0.0, 0.0, 1.0]
        };
        let per = g.sh_rest_coeffs() * 3;
        let rest = g
            .sh_rest
            .as_ref()
            .map_or(&[][..], |r| &r[i * per..(i + 1) * per]);
        eval_sh(g.sh_degree, g.sh_dc[i], rest, dir)
    };
    Some(Projected {
        id: i as u32,
        center: [u, v],
        depth: z,
        cov2d: [ca, cb, cc],
        conic,
        radius,
        tiles: [tx0, tx1, ty0, ty1],
        color,
        opacity: prep.opacity[i],
    })
}

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
const TAU_MARGIN: f64 = 0.05;

/// Slack, in pixels, of a splat's rectangle beyond the ellipse bound when the tile loop
/// solves per-row spans: that of the spans themselves (`raster::SPAN_SLACK`), far above the
/// f64 rounding of the bound (TAU_MARGIN adds more).
const RECT_SLACK: f64 = 1.0 / 64.0;

impl Splat {
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

#[cfg(test)]
mod tests {
    use super::{ceil, floor};

    #[test]
    fn floor_and_ceil_equal_libm_bit_for_bit_except_the_sign_of_zero() {
        let mut values = vec![
            0.0,
            0.5,
            1.0,
            1.5,
            -0.5,
            -1.0,
            -1.5,
            2.0f64.powi(52) - 0.5,
            -(2.0f64.powi(52) - 0.5),
            2.0f64.powi(52),
            2.0f64.powi(53) + 2.0,
            -1e300,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::MIN_POSITIVE,
            -f64::MIN_POSITIVE,
        ];
        // A deterministic spread over magnitudes and fractions.
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..10_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            let mag = (x >> 11) as f64 / (1u64 << 53) as f64 * 2f64.powi((x % 60) as i32);
            values.push(if x & 1 == 0 { mag } else { -mag });
        }
        for v in values {
            // -0.0 == 0.0: the sign of a zero result is irrelevant to the callers.
            assert_eq!(floor(v), v.floor(), "floor({v:e})");
            assert_eq!(ceil(v), v.ceil(), "ceil({v:e})");
        }
        assert!(floor(f64::NAN).is_nan() && ceil(f64::NAN).is_nan());
    }
}

//! Per-Gaussian work: view-independent preparation (3D covariance, opacity) and the EWA
//! projection into one view.

use std::ops::Range;

use profuse_formats::{camera, Gaussians};

use crate::camera::ViewCamera;
use crate::error::{RasterError, Result};
use crate::sh::eval_sh;
use crate::simd::{prefetch, Level};
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

/// View-independent data of every Gaussian, stored by *slot*: the Gaussians in the Morton
/// order of their means ([`spatial_order`]), not in id order.
///
/// Why: a tile's splats are the Gaussians near one line of sight, and the blend reads each
/// of them from the view's splat buffer, which projection fills in slot order. In id order
/// (whatever order the file has: a synthetic scene's or a densified one's is spatially
/// random) those reads are scattered over the whole buffer and stall on memory; in Morton
/// order a tile's splats lie in a few runs. Depth ties are still broken by id
/// (`sort_by_depth`), so the slot order changes no output bit.
#[derive(Debug, Clone)]
pub(crate) struct Prepared {
    /// The key of each slot in the spatial order: Morton code above the Gaussian id (see
    /// [`Prepared::id`]). Kept whole rather than narrowed to the ids: freeing the sort's
    /// key buffer raised glibc's dynamic mmap threshold, and fuse bench's peak RSS by
    /// ~100 MB (later mid-size buffers came from the heap and stayed).
    pub order: Vec<u64>,
    /// The mean of each slot's Gaussian.
    pub means: Vec<[f32; 3]>,
    /// Upper triangle of Σ = R S Sᵀ Rᵀ: xx, xy, xz, yy, yz, zz.
    pub cov3d: Vec<[f64; 6]>,
    /// sigmoid(opacity logit).
    pub opacity: Vec<f64>,
    /// ln(255 · opacity) + [`TAU_MARGIN`]: the footprint bound of [`Splat::new`], view
    /// independent, so computed once here rather than once per view.
    pub tau: Vec<f64>,
    /// An upper bound on the largest eigenvalue of Σ (the largest scale², with a margin,
    /// see [`var_bound`]) for the off-image pre-cull of [`project_chunk`], or
    /// [`NEVER_DRAWN`] where the single-precision opacity is NaN or below 1/255 (such a
    /// Gaussian never becomes a [`Splat`] in any view).
    pub var_max: Vec<f32>,
    /// The colour as a [`Splat`] holds it when it is view independent (SH degree 0): what
    /// [`eval_sh`] returns, in single precision. Empty for SH degree > 0.
    pub color0: Vec<[f32; 3]>,
    /// The bounds of each run of [`CULL_GROUP`] slots (the last one may be shorter) for
    /// the per-view group cull of [`project_chunk`].
    pub groups: Vec<CullGroup>,
}

/// Slots per [`CullGroup`]: 8 projection batches. The slots are in Morton order, so a
/// group's Gaussians lie close together and a view often sees all or none of them.
pub(crate) const CULL_GROUP: usize = 64;

/// A bounding sphere of the means of a run of slots and the largest variance bound of
/// those that may be drawn, from which one test per view tells that no Gaussian of the run
/// can become a [`Splat`] ([`ViewConsts::group_culled`]).
#[derive(Debug, Clone, Copy)]
pub(crate) struct CullGroup {
    center: [f64; 3],
    /// At least the distance of every mean from `center`.
    radius: f64,
    /// The largest [`Prepared::var_max`] of the run's Gaussians that may be drawn (NaN
    /// if one is NaN, -1 if none may be drawn).
    var_max: f64,
}

impl CullGroup {
    fn new(means: &[[f32; 3]], var_max: &[f32]) -> Self {
        let (lo, hi) = means.iter().fold(
            ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]),
            |(lo, hi), m| {
                let m = m.map(f64::from);
                (
                    std::array::from_fn(|a| lo[a].min(m[a])),
                    std::array::from_fn(|a| hi[a].max(m[a])),
                )
            },
        );
        let center: [f64; 3] = std::array::from_fn(|a| 0.5 * (lo[a] + hi[a]));
        let radius = means
            .iter()
            .map(|m| {
                let d: [f64; 3] = std::array::from_fn(|a| f64::from(m[a]) - center[a]);
                (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
            })
            .fold(0.0, f64::max);
        let var_max = var_max
            .iter()
            .filter(|&&v| may_be_drawn(v))
            .map(|&v| f64::from(v))
            .fold(f64::from(NEVER_DRAWN), |a, v| {
                if a.is_nan() || v.is_nan() {
                    f64::NAN
                } else {
                    a.max(v)
                }
            });
        CullGroup {
            center,
            // The rounding of the distances is ~1e-16 relative; the test's margin is far
            // wider, and this one keeps the bound a bound by itself.
            radius: radius * (1.0 + 1e-12),
            var_max,
        }
    }
}

/// [`Prepared::var_max`] of a Gaussian that is never drawn.
const NEVER_DRAWN: f32 = -1.0;

/// Whether a [`Prepared::var_max`] is not [`NEVER_DRAWN`] (not negative).
#[inline(always)]
fn may_be_drawn(var_max: f32) -> bool {
    (var_max >= 0.0) | var_max.is_nan()
}

/// Checks what `prepare` (and so `Rasterizer::new`) requires of the Gaussians, without
/// preparing anything: consistent lengths, SH degree <= 3, finite means, log-scales,
/// rotations and SH, no zero quaternion, no NaN opacity logit (±inf is allowed).
pub fn check_gaussians(g: &Gaussians) -> Result<()> {
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
    Ok(())
}

pub(crate) fn prepare(g: &Gaussians) -> Result<Prepared> {
    check_gaussians(g)?;
    let order = spatial_order(&g.means);
    let by_slot = || order.iter().map(|&k| key_id(k) as usize);
    let cov3d = by_slot()
        .map(|i| covariance_3d(g.log_scales[i], g.rotations[i]))
        .collect();
    let opacity: Vec<f64> = by_slot().map(|i| opacity_of(g.opacity_logits[i])).collect();
    let tau = opacity.iter().map(|&o| footprint_tau(o)).collect();
    let var_max: Vec<f32> = by_slot()
        .zip(&opacity)
        .map(|(i, &o)| {
            let o = o as f32;
            if o.is_nan() || o < ALPHA_MIN {
                NEVER_DRAWN
            } else {
                var_bound(g.log_scales[i])
            }
        })
        .collect();
    let color0 = if g.sh_degree == 0 {
        // Degree 0 ignores the direction (see `eval_sh`); any unit vector will do.
        by_slot()
            .map(|i| eval_sh(0, g.sh_dc[i], &[], [0.0, 0.0, 1.0]).map(|x| x as f32))
            .collect()
    } else {
        Vec::new()
    };
    let means: Vec<[f32; 3]> = by_slot().map(|i| g.means[i]).collect();
    let groups = means
        .chunks(CULL_GROUP)
        .zip(var_max.chunks(CULL_GROUP))
        .map(|(m, v)| CullGroup::new(m, v))
        .collect();
    Ok(Prepared {
        means,
        order,
        cov3d,
        opacity,
        tau,
        var_max,
        color0,
        groups,
    })
}

/// Bits per axis of the Morton code of [`spatial_order`]: 1024 cells per axis of the
/// scene's bounding box, far finer than a tile's share of a scene.
const MORTON_BITS: u32 = 10;

/// The keys (Morton code << 32 | id) of the Gaussians in ascending order, i.e. the ids in
/// the Morton (Z-curve) order of their means, quantised to [`MORTON_BITS`] per axis over the
/// means' bounding box, equal codes by id. The means are finite ([`prepare`] checked them).
/// Deterministic: every key is unique.
pub(crate) fn spatial_order(means: &[[f32; 3]]) -> Vec<u64> {
    let (lo, hi) = means.iter().fold(
        ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]),
        |(lo, hi), m| {
            (
                std::array::from_fn(|a| lo[a].min(m[a])),
                std::array::from_fn(|a| hi[a].max(m[a])),
            )
        },
    );
    let cells = (1u32 << MORTON_BITS) as f64;
    let quantise = |a: usize, x: f32| -> u64 {
        let extent = f64::from(hi[a]) - f64::from(lo[a]);
        if extent > 0.0 {
            // In [0, cells) up to the rounding at the top end, which the min catches.
            ((f64::from(x) - f64::from(lo[a])) / extent * cells).min(cells - 1.0) as u64
        } else {
            0
        }
    };
    let mut keys: Vec<u64> = means
        .iter()
        .enumerate()
        .map(|(i, m)| {
            let code = (0..3).fold(0u64, |c, a| c | (spread_bits(quantise(a, m[a])) << a));
            (code << 32) | i as u64
        })
        .collect();
    keys.sort_unstable();
    keys
}

/// The Gaussian id of a [`spatial_order`] key.
pub(crate) fn key_id(key: u64) -> u32 {
    key as u32
}

impl Prepared {
    /// The Gaussian id of slot `slot`.
    #[inline(always)]
    pub fn id(&self, slot: usize) -> u32 {
        key_id(self.order[slot])
    }
}

/// The low [`MORTON_BITS`] bits of `x` moved to every third bit (bit j to bit 3j).
fn spread_bits(x: u64) -> u64 {
    (0..MORTON_BITS).fold(0, |s, j| s | (((x >> j) & 1) << (3 * j)))
}

/// sigmoid(logit) in double precision: the opacity of [`Prepared`] and [`project`].
fn opacity_of(logit: f32) -> f64 {
    1.0 / (1.0 + (-f64::from(logit)).exp())
}

/// An upper bound on the largest eigenvalue of the Σ that [`covariance_3d`] computes from
/// these log-scales: exp(2 max log s). Σ = R S² Rᵀ with R orthonormal up to rounding, so
/// its eigenvalues are the s_j² up to a relative error of a few 1e-16; rounding the bound
/// to f32 loses at most 6e-8 relative. Both are covered by the 1e-6 margin of
/// [`ViewConsts::cull_gain`]. Huge scales give +inf: never pre-culled.
fn var_bound(log_scales: [f32; 3]) -> f32 {
    let l = log_scales
        .iter()
        .fold(f64::NEG_INFINITY, |m, &l| m.max(f64::from(l)));
    (2.0 * l).exp() as f32
}

/// ln(255 · opacity) + [`TAU_MARGIN`]: pixels with ½ dᵀ Σ⁻¹ d > tau have alpha < 1/255.
pub(crate) fn footprint_tau(opacity: f64) -> f64 {
    (255.0 * opacity).ln() + TAU_MARGIN
}

/// Σ = R S Sᵀ Rᵀ from log-scales and a (w, x, y, z) quaternion, normalised here.
/// Returns the upper triangle xx, xy, xz, yy, yz, zz; all NaN for a zero or non-finite
/// quaternion (whose normalisation would leave NaN in every row of R anyway).
pub fn covariance_3d(log_scales: [f32; 3], q: [f32; 4]) -> [f64; 6] {
    let r = camera::quaternion_to_rotation(q.map(f64::from)).unwrap_or([[f64::NAN; 3]; 3]);
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
/// covariance, off the tile grid). The reference path, by id: it computes the
/// view-independent values of [`Prepared`] itself, with the same expressions.
pub(crate) fn project(
    g: &Gaussians,
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
    let [u, v] = camera::project(&cam.intrinsics, p);
    let EwaJacobian { t, .. } = ewa_jacobian(cam, p);
    let [sxx, sxy, sxz, syy, syz, szz] = covariance_3d(g.log_scales[i], g.rotations[i]);
    let sigma = [[sxx, sxy, sxz], [sxy, syy, syz], [sxz, syz, szz]];
    let Footprint {
        cov2d,
        conic,
        radius,
    } = footprint(&t, &sigma)?;
    let tiles = screen_tiles(cam, [u, v], radius)?;
    let color = sh_color(g, campos, i, mean);
    Some(Projected {
        id: i as u32,
        center: [u, v],
        depth: z,
        cov2d,
        conic,
        radius,
        tiles,
        color,
        opacity: opacity_of(g.opacity_logits[i]),
    })
}

/// T = J W, the perspective Jacobian J at the camera-space mean `p` times the
/// world-to-camera rotation W (INRIA `computeCov2D`), with x/z and y/z clamped to
/// [`tangent_range`], and what the clamp did (gs-refine's backward pass needs it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EwaJacobian {
    /// T (2 x 3).
    pub t: [[f64; 3]; 2],
    /// The clamped x/z and y/z.
    pub tan: [f64; 2],
    /// Whether x/z (y/z) lay outside its range and was clamped.
    pub clamped: [bool; 2],
}

/// [`EwaJacobian`] of camera-space point `p` (z > 0) in `cam`.
pub fn ewa_jacobian(cam: &ViewCamera, p: [f64; 3]) -> EwaJacobian {
    let [fx, fy, cx, cy] = cam.intrinsics;
    let z = p[2];
    let clamp_tan = |t: f64, c: f64, f: f64, size: u32| {
        let [lo, hi] = tangent_range(c, f, f64::from(size));
        (t.clamp(lo, hi), !(lo..=hi).contains(&t))
    };
    let (tan_x, clamped_x) = clamp_tan(p[0] / z, cx, fx, cam.width);
    let (tan_y, clamped_y) = clamp_tan(p[1] / z, cy, fy, cam.height);
    let (tx, ty) = (tan_x * z, tan_y * z);
    let j = [
        [fx / z, 0.0, -fx * tx / (z * z)],
        [0.0, fy / z, -fy * ty / (z * z)],
    ];
    let r = &cam.rotation;
    EwaJacobian {
        t: std::array::from_fn(|a| {
            std::array::from_fn(|b| j[a][0] * r[0][b] + j[a][1] * r[1][b] + j[a][2] * r[2][b])
        }),
        tan: [tan_x, tan_y],
        clamped: [clamped_x, clamped_y],
    }
}

/// The range to which [`Rasterizer::project`](crate::Rasterizer::project) clamps x/z (or
/// y/z) in the perspective Jacobian, for principal point `c`, focal length `f` and image
/// size `size` along that axis: the image's tangent range [−c/f, (size − c)/f] widened by
/// [`FRUSTUM_CLAMP`] about its middle, which for a centred principal point is INRIA's
/// ±1.3·tan(fov/2).
pub fn tangent_range(c: f64, f: f64, size: f64) -> [f64; 2] {
    let (lo, hi) = (-c / f, (size - c) / f);
    let (mid, half) = (0.5 * (lo + hi), 0.5 * (hi - lo));
    [mid - FRUSTUM_CLAMP * half, mid + FRUSTUM_CLAMP * half]
}

/// The screen footprint of a Gaussian (INRIA `computeCov2D` and the radius of
/// `preprocessCUDA`), from T = J W (the perspective Jacobian at the mean times the
/// world-to-camera rotation, 2 x 3) and its 3D covariance Σ.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Footprint {
    /// T Σ Tᵀ + 0.3 I (the low-pass), `[xx, xy, yy]` in pixels².
    pub cov2d: [f64; 3],
    /// Its inverse `[a, b, c]`: power = −½(a dx² + c dy²) − b dx dy.
    pub conic: [f64; 3],
    /// ceil(3 √λ) with λ = mid + max(√(mid² − det), √0.1), mid = (xx + yy) / 2.
    pub radius: f64,
}

/// [`Footprint`] of T and Σ; `None` where the 2D covariance is degenerate (det <= 0, or
/// anything non-finite), which [`Rasterizer::project`](crate::Rasterizer::project) culls.
/// The operations and their order are the renderer's, so gs-refine's differentiable
/// projection gets the same bits.
pub fn footprint(t: &[[f64; 3]; 2], sigma: &[[f64; 3]; 3]) -> Option<Footprint> {
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
    let mid = 0.5 * (ca + cc);
    let disc = (mid * mid - det).max(0.1).sqrt();
    let lambda = (mid + disc).max(mid - disc);
    Some(Footprint {
        cov2d: [ca, cb, cc],
        conic: [cc / det, -cb / det, ca / det],
        radius: ceil(SIGMA_EXTENT * lambda.sqrt()),
    })
}

/// The tiles `[tx0, tx1, ty0, ty1]` of `cam`'s grid (inclusive, clamped) that the square
/// of half-side `radius` about `center` touches; `None` when it misses the grid.
pub fn screen_tiles(cam: &ViewCamera, center: [f64; 2], radius: f64) -> Option<[u32; 4]> {
    let (tiles_x, tiles_y) = cam.tiles();
    let [tx0, tx1] = tile_span(center[0], radius, tiles_x)?;
    let [ty0, ty1] = tile_span(center[1], radius, tiles_y)?;
    Some([tx0, tx1, ty0, ty1])
}

/// The tiles `[first, last]` (inclusive, clamped to `0..n`) that `[c − radius, c +
/// radius]` touches, tile of x = floor(x / 16); `None` when it misses all `n`.
fn tile_span(c: f64, radius: f64, n: usize) -> Option<[u32; 2]> {
    let lo = floor((c - radius) / TILE as f64);
    let hi = floor((c + radius) / TILE as f64);
    let last = n.checked_sub(1)? as f64;
    if !(hi >= 0.0 && lo <= last) {
        return None;
    }
    Some([lo.max(0.0) as u32, hi.min(last) as u32])
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

/// Projects the Gaussians in [`Prepared`] slots `slots` into the camera of `view` and
/// appends, in slot order, the [`Splat`] of each one that [`project`] followed by
/// [`Splat::new`] keeps: bit for bit the same values (the same operations in the same
/// order; the unit tests compare the two paths), for less work: per-view constants are
/// computed once ([`ViewConsts`]), runs of [`CULL_GROUP`] slots wholly behind the camera or
/// beside the image are skipped after one test per run ([`ViewConsts::group_culled`]),
/// Gaussians far off the image are rejected by a conservative bound before the EWA
/// projection (see [`ViewConsts::surely_off_grid`]),
/// degree-0 colours come from [`Prepared::color0`], no colour at all is evaluated when the
/// view is not shaded (the splats then carry black: a render without a colour output never
/// reads it, and spherical harmonics of degree 3 cost several times the rest of the
/// projection), no [`Projected`] is built, and the Gaussians go through the arithmetic
/// [`BATCH`] at a time, lane by lane without branches (see [`ViewConsts::project_lanes`]),
/// which the compiler turns into vector instructions: 8 lanes with AVX-512 where `level`
/// has it, 2 with SSE2 otherwise. Every lane performs the IEEE double-precision operations
/// of the scalar formula, so the width changes no bit.
pub(crate) fn project_chunk(
    view: &ViewConsts,
    g: &Gaussians,
    prep: &Prepared,
    slots: Range<usize>,
    level: Level,
    out: &mut impl SplatSink,
) {
    let tail = match level {
        Level::Portable => project_batches(view, g, prep, slots.clone(), out),
        // SAFETY: `Level::Avx512` is only made after `Level::detect` found AVX-512 F and DQ
        // on this CPU, which is all `project_batches_avx512` needs.
        #[cfg(target_arch = "x86_64")]
        #[allow(unsafe_code)]
        Level::Avx512 => unsafe { project_batches_avx512(view, g, prep, slots.clone(), out) },
    };
    for i in tail..slots.end {
        let mut lane = ProjectedLanes::<1>::default();
        view.project_lanes(prep, i, &mut lane);
        lane.emit(view, g, prep, i, out);
    }
}

/// Gaussians per batch of [`project_chunk`]: one AVX-512 vector of f64.
const BATCH: usize = 8;

/// [`project_batches`] compiled for AVX-512, where its lane loops become 8-lane vectors.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq")]
fn project_batches_avx512(
    view: &ViewConsts,
    g: &Gaussians,
    prep: &Prepared,
    slots: Range<usize>,
    out: &mut impl SplatSink,
) -> usize {
    project_batches(view, g, prep, slots, out)
}

/// Projects the whole batches of `slots`; returns where the remainder (fewer than [`BATCH`]
/// Gaussians) starts.
#[inline(always)]
fn project_batches(
    view: &ViewConsts,
    g: &Gaussians,
    prep: &Prepared,
    slots: Range<usize>,
    out: &mut impl SplatSink,
) -> usize {
    let mut first = slots.start;
    let mut lanes = ProjectedLanes::<BATCH>::default();
    let harmonics = view.shade && prep.color0.is_empty();
    // The group of the last batch tested and whether the view culls it.
    let mut culled = (usize::MAX, false);
    while first + BATCH <= slots.end {
        if harmonics {
            prefetch_harmonics(
                g,
                prep,
                first + SH_PREFETCH_AHEAD..first + SH_PREFETCH_AHEAD + BATCH,
            );
        }
        let group = first / CULL_GROUP;
        if group == (first + BATCH - 1) / CULL_GROUP {
            if culled.0 != group {
                culled = (
                    group,
                    prep.groups.get(group).is_some_and(|c| view.group_culled(c)),
                );
            }
            if culled.1 {
                first += BATCH;
                continue;
            }
        }
        // A batch of Gaussians that are never drawn (zero opacity) costs nothing.
        if prep.var_max[first..first + BATCH]
            .iter()
            .any(|&v| may_be_drawn(v))
        {
            view.project_lanes(prep, first, &mut lanes);
            lanes.emit(view, g, prep, first, out);
        }
        first += BATCH;
    }
    first
}

/// Slots ahead of the batch being projected whose spherical harmonics are prefetched.
const SH_PREFETCH_AHEAD: usize = 8 * BATCH;

/// Asks for the colour coefficients of the Gaussians in `slots` (those beyond the slots
/// are ignored). They are stored in id order, which the slot order scatters over the whole
/// file: without the hint each Gaussian's colour waited on a few cache misses, and the
/// colour took most of a shaded projection's time.
#[inline(always)]
fn prefetch_harmonics(g: &Gaussians, prep: &Prepared, slots: Range<usize>) {
    let per = g.sh_rest_coeffs() * 3;
    let rest = g.sh_rest.as_deref().unwrap_or(&[]);
    for slot in slots.take_while(|&s| s < prep.order.len()) {
        let id = prep.id(slot) as usize;
        if let Some(dc) = g.sh_dc.get(id) {
            prefetch(dc);
        }
        if let Some(row) = rest.get(id * per..(id + 1) * per) {
            // One hint per 64-byte line the row touches (16 floats), and its last one.
            for c in row.iter().step_by(16).chain(row.last()) {
                prefetch(c);
            }
        }
    }
}

/// What [`ViewConsts::project_lanes`] computes for `L` consecutive Gaussians, lane l for
/// the l-th: whether [`project`] + [`Splat::new`] keep it, and the values of its
/// [`Splat`] (meaningless in lanes that are not kept).
#[derive(Debug, Clone, Copy)]
struct ProjectedLanes<const L: usize> {
    keep: [bool; L],
    /// The f64 intermediates: centre, depth, 2D covariance, conic, radius.
    u: [f64; L],
    v: [f64; L],
    z: [f64; L],
    cov2d: [[f64; L]; 3],
    conic: [[f64; L]; 3],
    radius: [f64; L],
    /// Tile range tx0, tx1, ty0, ty1.
    tiles: [[u32; L]; 4],
    /// The single-precision conic a, b, c, its det, 2 a tau and the inverse of a (0 when
    /// the spans cannot be trusted).
    abc: [[f32; L]; 3],
    det: [f32; L],
    two_a_tau: [f32; L],
    inv_a: [f32; L],
    /// Pixel rectangle x0, x1, y0, y1.
    rect: [[u16; L]; 4],
}

impl<const L: usize> Default for ProjectedLanes<L> {
    fn default() -> Self {
        ProjectedLanes {
            keep: [false; L],
            u: [0.0; L],
            v: [0.0; L],
            z: [0.0; L],
            cov2d: [[0.0; L]; 3],
            conic: [[0.0; L]; 3],
            radius: [0.0; L],
            tiles: [[0; L]; 4],
            abc: [[0.0; L]; 3],
            det: [0.0; L],
            two_a_tau: [0.0; L],
            inv_a: [0.0; L],
            rect: [[0; L]; 4],
        }
    }
}

impl<const L: usize> ProjectedLanes<L> {
    /// Appends the [`Splat`] of every kept lane (Gaussian `first + l`), in lane order;
    /// black unless `view` is shaded.
    #[inline(always)]
    fn emit(
        &self,
        view: &ViewConsts,
        g: &Gaussians,
        prep: &Prepared,
        first: usize,
        out: &mut impl SplatSink,
    ) {
        for l in 0..L {
            if !self.keep[l] {
                continue;
            }
            let i = first + l;
            let id = prep.id(i);
            let color = match prep.color0.get(i) {
                _ if !view.shade => [0.0; 3],
                Some(c) => *c,
                None => {
                    let mean = prep.means[i].map(f64::from);
                    sh_color(g, view.campos, id as usize, mean).map(|x| x as f32)
                }
            };
            #[cfg(test)]
            tests::trace(Projected {
                id,
                center: [self.u[l], self.v[l]],
                depth: self.z[l],
                cov2d: self.cov2d.map(|c| c[l]),
                conic: self.conic.map(|c| c[l]),
                radius: self.radius[l],
                tiles: self.tiles.map(|t| t[l]),
                color: [0.0; 3], // compared as the splat's f32 colour
                opacity: prep.opacity[i],
            });
            let [a, b, c] = self.abc.map(|v| v[l]);
            out.push(
                i,
                Splat {
                    x: self.u[l] as f32,
                    y: self.v[l] as f32,
                    a,
                    b,
                    c,
                    opacity: prep.opacity[i] as f32,
                    color,
                    depth: self.z[l] as f32,
                    id,
                    two_a_tau: self.two_a_tau[l],
                    det: self.det[l],
                    inv_a: self.inv_a[l],
                    rect: self.rect.map(|r| r[l]),
                },
            );
        }
    }
}

/// What [`project`] and [`Splat::new`] compute from the camera alone, computed once per
/// view with the same expressions (the tests tamper with them), and whether the splats
/// get their colour.
pub(crate) struct ViewConsts {
    rotation: [[f64; 3]; 3],
    translation: [f64; 3],
    focal: [f64; 2],
    principal: [f64; 2],
    /// Bounds of the clamped x/z and y/z (`clamp_tan` of [`project`]).
    tan_x: [f64; 2],
    tan_y: [f64; 2],
    /// 0.0 · rotation[0][b] and 0.0 · rotation[1][b]: the products of the structural zeros
    /// of J in T = J W. They are ±0, but adding one can still change the sign of a zero
    /// sum (+0 + −0 = +0), so T keeps them and stays bit-identical by construction.
    zero_r0: [f64; 3],
    zero_r1: [f64; 3],
    tiles: [usize; 2],
    /// Width and height of the tile grid in pixels (tiles · [`TILE`]).
    grid: [f64; 2],
    /// The constant G of the pre-cull bound λmax(T Σ Tᵀ) <= G · var_max / z².
    cull_gain: f64,
    width: u32,
    height: u32,
    /// The camera centre (the view direction of the colour).
    campos: [f64; 3],
    /// Whether the splats get their colour (see [`project_chunk`]).
    shade: bool,
    /// The half-spaces of [`ViewConsts::group_culled`]: camera depth, and the image's
    /// left, right, top and bottom sides.
    depth_plane: CullPlane,
    side_planes: [CullPlane; 4],
}

/// A linear function of the world position, a·p + b, with the Euclidean norm of a and
/// the magnitudes of the terms it sums (|a| and |b| bound them component-wise) for a
/// rounding margin.
#[derive(Debug, Clone, Copy)]
struct CullPlane {
    a: [f64; 3],
    b: f64,
    norm: f64,
    a_abs: [f64; 3],
    b_abs: f64,
}

impl CullPlane {
    /// s·f·(camera axis `axis`) + k·(camera z): the camera axes are rows of R plus t.
    fn new(r: &[[f64; 3]; 3], t: &[f64; 3], [s, f]: [f64; 2], axis: usize, k: f64) -> Self {
        let a: [f64; 3] = std::array::from_fn(|j| s * f * r[axis][j] + k * r[2][j]);
        CullPlane {
            a,
            b: s * f * t[axis] + k * t[2],
            norm: (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt(),
            a_abs: std::array::from_fn(|j| (f * r[axis][j]).abs() + (k * r[2][j]).abs()),
            b_abs: (f * t[axis]).abs() + (k * t[2]).abs(),
        }
    }

    /// An upper bound of the function over `group`'s sphere plus `extra`, and the
    /// magnitude of the terms behind it.
    #[inline(always)]
    fn max_over(&self, group: &CullGroup, extra: f64) -> (f64, f64) {
        let c = group.center;
        let reach = group.radius * self.norm;
        let at_center = self.a[0] * c[0] + self.a[1] * c[1] + self.a[2] * c[2] + self.b;
        let magnitude = self.a_abs[0] * c[0].abs()
            + self.a_abs[1] * c[1].abs()
            + self.a_abs[2] * c[2].abs()
            + self.b_abs;
        (at_center + reach + extra, magnitude + reach + extra)
    }
}

/// Pixels added to the footprint bound of the group cull: at least
/// 3 √0.62 + 2 = 4.36 (the parts of the pre-cull's radius bound that do not scale with 1/z)
/// and a little more (0.64 pixel) for the rounding of u and v.
const GROUP_CULL_PIXELS: f64 = 5.0;

/// The relative margin of the group cull's tests: far above the rounding of the values
/// compared (a few 1e-16 of the magnitudes summed).
const GROUP_CULL_MARGIN: f64 = 1e-6;

impl ViewConsts {
    pub(crate) fn new(cam: &ViewCamera, shade: bool) -> Self {
        let [fx, fy, cx, cy] = cam.intrinsics;
        let (w, h) = (f64::from(cam.width), f64::from(cam.height));
        let tan_x = tangent_range(cx, fx, w);
        let tan_y = tangent_range(cy, fy, h);
        let r = cam.rotation;
        let (tiles_x, tiles_y) = cam.tiles();
        let grid = [(tiles_x * TILE) as f64, (tiles_y * TILE) as f64];

        // Pre-cull gain. With τ = the clamped x/z, y/z (|τx| <= Cx, |τy| <= Cy),
        // J = [[fx, 0, −fx τx], [0, fy, −fy τy]] / z, and Gershgorin on J Jᵀ gives
        // ‖J‖² <= (max(fx²(1 + Cx²), fy²(1 + Cy²)) + fx fy Cx Cy) / z²; Gershgorin on WᵀW
        // bounds ‖W‖² (1 for a rotation, but the file's matrix is not checked to be one).
        // λmax(T Σ Tᵀ) <= ‖J‖² ‖W‖² λmax(Σ) <= G var_max / z². The 1e-6 margin covers every
        // rounding on both sides (each a few 1e-16 relative, or 6e-8 for var_max's f32).
        let c_x = tan_x[0].abs().max(tan_x[1].abs());
        let c_y = tan_y[0].abs().max(tan_y[1].abs());
        let jj =
            (fx * fx * (1.0 + c_x * c_x)).max(fy * fy * (1.0 + c_y * c_y)) + fx * fy * c_x * c_y;
        let wtw = |a: usize, b: usize| r[0][a] * r[0][b] + r[1][a] * r[1][b] + r[2][a] * r[2][b];
        let ww = (0..3)
            .map(|a| (0..3).map(|b| wtw(a, b).abs()).sum::<f64>())
            .fold(0.0, f64::max);
        Self {
            rotation: r,
            translation: cam.translation,
            focal: [fx, fy],
            principal: [cx, cy],
            tan_x,
            tan_y,
            zero_r0: r[0].map(|x| 0.0 * x),
            zero_r1: r[1].map(|x| 0.0 * x),
            tiles: [tiles_x, tiles_y],
            grid,
            cull_gain: jj * ww * (1.0 + 1e-6),
            width: cam.width,
            height: cam.height,
            campos: cam.center(),
            shade,
            depth_plane: CullPlane::new(&r, &cam.translation, [0.0, 0.0], 0, 1.0),
            side_planes: side_planes(
                &r,
                &cam.translation,
                [fx, fy, cx, cy],
                grid,
                GROUP_CULL_PIXELS,
            ),
        }
    }

    /// Whether no Gaussian of `group` can become a [`Splat`] in this view, so that its
    /// slots need no projection; `false` decides nothing.
    ///
    /// Why it never culls a Gaussian that [`project`] and [`Splat::new`] keep: each
    /// Gaussian of the group has its mean p in the group's sphere and a variance bound
    /// var <= the group's var_max (or is never drawn). The tests are on linear functions of
    /// p, whose maximum over the sphere is the value at the centre plus radius · |a|:
    /// - depth: if z < NEAR_PLANE everywhere in the sphere, [`project`] rejects every mean;
    /// - a side, e.g. the left: with S = 3 √(G var_max) (G: the pre-cull's gain), if
    ///   fx x + (cx + P) z + S < 0 everywhere (x, z: camera coordinates, P =
    ///   [`GROUP_CULL_PIXELS`]), then a Gaussian either has z <= NEAR_PLANE (rejected) or,
    ///   dividing by z > 0, u + P + 3 √(G var) / z < 0. Its pre-cull radius
    ///   rb = 3 √(G var / z² + 0.62) + 2 is at most 3 √(G var) / z + 4.36, so
    ///   u + rb < −0.64 and u < −2: [`ViewConsts::surely_off_grid`] rejects it (and it
    ///   never rejects a Gaussian that [`project`] keeps). The other sides alike, with
    ///   −fx x − (cx − P − grid width) z + S for the right side, and fy, cy, y for the
    ///   rows;
    /// - every test asks for a margin of [`GROUP_CULL_MARGIN`] times the magnitude of the
    ///   terms summed, which covers the rounding of the bound here and of u, v, z, rb in
    ///   the per-Gaussian tests (relative errors of a few 1e-16);
    /// - NaN anywhere makes the comparisons false: no cull.
    #[inline(always)]
    fn group_culled(&self, group: &CullGroup) -> bool {
        if group.var_max < 0.0 {
            // Every Gaussian of the group is never drawn.
            return true;
        }
        if group.var_max.is_nan() {
            return false;
        }
        let (z_max, z_mag) = self.depth_plane.max_over(group, 0.0);
        if z_max < NEAR_PLANE - GROUP_CULL_MARGIN * (z_mag + NEAR_PLANE) {
            return true;
        }
        let s = SIGMA_EXTENT * (self.cull_gain * group.var_max).sqrt();
        self.side_planes.iter().any(|p| {
            let (v, mag) = p.max_over(group, s);
            v < -GROUP_CULL_MARGIN * mag
        })
    }

    /// Whether the 3-sigma square of [`project`] surely misses the tile grid, so that
    /// [`project`] returns `None`; `false` decides nothing (the exact test follows).
    ///
    /// Why it never rejects a Gaussian that [`project`] keeps:
    /// - its λ = mid + max(√(mid² − det), √0.1) is at most λmax(cov2d) (1 + 4e-8) + √0.1
    ///   (4e-8: the rounding of mid² − det), and cov2d = T Σ Tᵀ + 0.3 I, so
    ///   λ <= λmax(T Σ Tᵀ) (1 + 4e-8) + 0.6163, which is below λb = G var / z² + 0.62 (the
    ///   1e-6 margin of G covers the 4e-8 and the rounding of λb itself);
    /// - its radius r = ceil(3 √λ) <= 3 √λ + 1 is below rb − 1, with rb = 3 √λb + 2;
    /// - if fl(u + rb) < 0, then u + r < −1 and its last tile floor(fl(u + r) / 16) is
    ///   negative; if fl(u − rb) > the grid width, then u − r > grid width + 1 and its
    ///   first tile lies past the last one; the same for v;
    /// - NaN anywhere makes every comparison false: no pre-cull.
    #[inline(always)]
    fn surely_off_grid(&self, u: f64, v: f64, z: f64, var: f32) -> bool {
        let [gw, gh] = self.grid;
        // Non-short-circuit `&` and `|`, so that a lane loop computes it without branches;
        // the division is then done for Gaussians on the grid too, and ignored.
        let off = (u < -2.0) | (v < -2.0) | (u > gw + 2.0) | (v > gh + 2.0);
        let lambda_bound = self.cull_gain * f64::from(var) / (z * z) + 0.62;
        let rb = SIGMA_EXTENT * lambda_bound.sqrt() + 2.0;
        off & ((u + rb < 0.0) | (u - rb > gw) | (v + rb < 0.0) | (v - rb > gh))
    }

    /// [`project`] then [`Splat::new`] for Gaussians `first..first + L`, written out with
    /// the per-view constants, lane by lane and without branches (every test is a lane of
    /// `keep`; the values of a lane that is not kept are computed anyway and unused), so
    /// that the loop over the lanes vectorises.
    #[inline(always)]
    fn project_lanes<const L: usize>(
        &self,
        prep: &Prepared,
        first: usize,
        out: &mut ProjectedLanes<L>,
    ) {
        let means = &prep.means[first..first + L];
        let var_max = &prep.var_max[first..first + L];
        let cov3d = &prep.cov3d[first..first + L];
        let taus = &prep.tau[first..first + L];
        let (r, t) = (&self.rotation, &self.translation);
        let ([fx, fy], [cx, cy]) = (self.focal, self.principal);
        for l in 0..L {
            let var = var_max[l];
            let mean = means[l].map(f64::from);
            let cam_axis =
                |a: usize| r[a][0] * mean[0] + r[a][1] * mean[1] + r[a][2] * mean[2] + t[a];
            let z = cam_axis(2);
            // NEVER_DRAWN (`Splat::new` rejects it whatever the view); `project`'s near
            // plane (false for NaN).
            let in_front = may_be_drawn(var) & (z > NEAR_PLANE);
            let (px, py) = (cam_axis(0), cam_axis(1));
            let [u, v] = camera::project(&[fx, fy, cx, cy], [px, py, z]);
            let on_grid = !self.surely_off_grid(u, v, z, var);

            // EWA, as in `project`.
            let tx = clamp(px / z, self.tan_x) * z;
            let ty = clamp(py / z, self.tan_y) * z;
            let z2 = z * z;
            let (j00, j02) = (fx / z, -fx * tx / z2);
            let (j11, j12) = (fy / z, -fy * ty / z2);
            let t0: [f64; 3] =
                std::array::from_fn(|b| j00 * r[0][b] + self.zero_r1[b] + j02 * r[2][b]);
            let t1: [f64; 3] =
                std::array::from_fn(|b| self.zero_r0[b] + j11 * r[1][b] + j12 * r[2][b]);
            let [sxx, sxy, sxz, syy, syz, szz] = cov3d[l];
            let sigma = [[sxx, sxy, sxz], [sxy, syy, syz], [sxz, syz, szz]];
            let times_sigma = |t: &[f64; 3]| -> [f64; 3] {
                std::array::from_fn(|b| {
                    t[0] * sigma[0][b] + t[1] * sigma[1][b] + t[2] * sigma[2][b]
                })
            };
            let (ts0, ts1) = (times_sigma(&t0), times_sigma(&t1));
            let dot = |a: &[f64; 3], b: &[f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
            let ca = dot(&ts0, &t0) + LOW_PASS;
            let cb = dot(&ts0, &t1);
            let cc = dot(&ts1, &t1) + LOW_PASS;
            let det = ca * cc - cb * cb;
            // `project`'s test, in fewer instructions: `x <= MAX` is `x < inf` for every x,
            // both false for NaN.
            let regular =
                (det > 0.0) & (det <= f64::MAX) & (ca.abs() <= f64::MAX) & (cc.abs() <= f64::MAX);
            let conic = [cc / det, -cb / det, ca / det];
            let mid = 0.5 * (ca + cc);
            let disc = max_bound(mid * mid - det, 0.1).sqrt();
            let lambda = (mid + disc).max(mid - disc);
            let radius = ceil_non_negative(SIGMA_EXTENT * lambda.sqrt());
            let (tiles_x, [tx0, tx1]) = tile_lanes(u, radius, self.tiles[0]);
            let (tiles_y, [ty0, ty1]) = tile_lanes(v, radius, self.tiles[1]);

            // `Splat::new` (its opacity test is `var >= 0`, above).
            let [a, b, c] = conic.map(|x| x as f32);
            let (x, y) = (u as f32, v as f32);
            let finite =
                x.is_finite() & y.is_finite() & a.is_finite() & b.is_finite() & c.is_finite();
            let tau = taus[l];
            let det32 = a * c - b * b;
            let two_a_tau = 2.0 * a * tau as f32;
            let inv_a = 1.0 / a;
            let spans = (a > 0.0)
                & (det32 > 0.0)
                & (det32 <= f32::MAX)
                & (two_a_tau.abs() <= f32::MAX)
                & (inv_a.abs() <= f32::MAX);
            let slack = if spans { RECT_SLACK } else { 1.0 };
            let ex = (2.0 * tau * ca).sqrt();
            let ey = (2.0 * tau * cc).sqrt();
            let (rect_x, [x0, x1]) = rect_lanes(u, ex, slack, tx0, tx1, self.width);
            let (rect_y, [y0, y1]) = rect_lanes(v, ey, slack, ty0, ty1, self.height);

            out.keep[l] =
                in_front & on_grid & regular & tiles_x & tiles_y & finite & rect_x & rect_y;
            out.u[l] = u;
            out.v[l] = v;
            out.z[l] = z;
            out.cov2d[0][l] = ca;
            out.cov2d[1][l] = cb;
            out.cov2d[2][l] = cc;
            for (o, c) in out.conic.iter_mut().zip(conic) {
                o[l] = c;
            }
            out.radius[l] = radius;
            for (o, t) in out.tiles.iter_mut().zip([tx0, tx1, ty0, ty1]) {
                o[l] = t;
            }
            for (o, v) in out.abc.iter_mut().zip([a, b, c]) {
                o[l] = v;
            }
            out.det[l] = det32;
            out.two_a_tau[l] = two_a_tau;
            out.inv_a[l] = if spans { inv_a } else { 0.0 };
            for (o, v) in out.rect.iter_mut().zip([x0, x1, y0, y1]) {
                o[l] = v;
            }
        }
    }
}

/// The four side tests of [`ViewConsts::group_culled`] for the camera (R, t, intrinsics)
/// and tile grid `[gw, gh]` in pixels, with `pixels` in place of [`GROUP_CULL_PIXELS`]
/// (the tests loosen it).
fn side_planes(
    r: &[[f64; 3]; 3],
    t: &[f64; 3],
    [fx, fy, cx, cy]: [f64; 4],
    [gw, gh]: [f64; 2],
    pixels: f64,
) -> [CullPlane; 4] {
    [
        CullPlane::new(r, t, [1.0, fx], 0, cx + pixels),
        CullPlane::new(r, t, [-1.0, fx], 0, gw + pixels - cx),
        CullPlane::new(r, t, [1.0, fy], 1, cy + pixels),
        CullPlane::new(r, t, [-1.0, fy], 1, gh + pixels - cy),
    ]
}

/// `x.clamp(range[0], range[1])` for a range that is not NaN and ordered, written as
/// selects (f64::clamp asserts the order on every call): NaN stays NaN.
#[inline(always)]
fn clamp(x: f64, range: [f64; 2]) -> f64 {
    let x = if x < range[0] { range[0] } else { x };
    if x > range[1] {
        range[1]
    } else {
        x
    }
}

/// The inclusive tile range of [`project`] covered by `[c − radius, c + radius]`, `None`
/// when it misses the `n` tiles ([`tile_lanes`]).
#[cfg(test)]
fn tile_range(c: f64, radius: f64, n: usize) -> Option<[u32; 2]> {
    let (hit, range) = tile_lanes(c, radius, n);
    hit.then_some(range)
}

/// [`project`]'s tile range without branches: whether `[c − radius, c + radius]` meets
/// the `n` tiles, and the range (meaningless when it does not). Without its floors: with
/// y = (c ± radius) / 16, floor(y) >= 0 ⟺ y >= 0 and floor(y) <= n − 1 ⟺ y < n (both false
/// for NaN), and on the clamped values, which are >= 0, `as u32` truncates, i.e. floors.
#[inline(always)]
fn tile_lanes(c: f64, radius: f64, n: usize) -> (bool, [u32; 2]) {
    let lo = (c - radius) / TILE as f64;
    let hi = (c + radius) / TILE as f64;
    let in_grid = (hi >= 0.0) & (lo < n as f64);
    (
        in_grid,
        [
            max_bound(lo, 0.0) as u32,
            min_bound(hi, (n - 1) as f64) as u32,
        ],
    )
}

/// The pixel span of [`Splat::new`] along one axis, `None` when it is empty
/// ([`rect_lanes`]).
#[cfg(test)]
fn rect_span(c: f64, e: f64, slack: f64, t0: u32, t1: u32, size: u32) -> Option<[u16; 2]> {
    let (some, span) = rect_lanes(c, e, slack, t0, t1, size);
    some.then_some(span)
}

/// The pixel span of [`Splat::new`] along one axis without branches: whether it is not
/// empty, and the span (meaningless when it is). Its ceil and floor come after the clamps
/// rather than before: they commute with max/min against the integer bounds (NaN
/// included: f64::max/min return the bound), and the clamped values lie in [0, size − 1]
/// when the span is not empty, where `as u16` truncates exactly.
#[inline(always)]
fn rect_lanes(c: f64, e: f64, slack: f64, t0: u32, t1: u32, size: u32) -> (bool, [u16; 2]) {
    let lo = max_bound(
        max_bound(c - e - 0.5 - slack, f64::from(t0) * TILE as f64),
        0.0,
    );
    let hi = min_bound(
        min_bound(
            c + e - 0.5 + slack,
            f64::from(t1) * TILE as f64 + (TILE - 1) as f64,
        ),
        f64::from(size) - 1.0,
    );
    // ceil(lo) <= floor(hi) needs lo <= hi; then 0 <= lo <= hi <= size − 1 < 2^15 (and
    // the increment below cannot wrap; where lo > hi its value is not used).
    let (lo_floor, hi_floor) = (lo as u16, hi as u16);
    let lo_ceil = if f64::from(lo_floor) < lo {
        lo_floor.wrapping_add(1)
    } else {
        lo_floor
    };
    ((lo <= hi) & (lo_ceil <= hi_floor), [lo_ceil, hi_floor])
}

/// `x.max(bound)` for a bound that is not NaN, in one instruction (maxsd) rather than five:
/// NaN gives the bound in both.
#[inline(always)]
fn max_bound(x: f64, bound: f64) -> f64 {
    if x > bound {
        x
    } else {
        bound
    }
}

/// `x.min(bound)` for a bound that is not NaN, as [`max_bound`].
#[inline(always)]
fn min_bound(x: f64, bound: f64) -> f64 {
    if x < bound {
        x
    } else {
        bound
    }
}

/// [`ceil`] of an `x >= 0` (or NaN) without the saturating float-to-int conversion: below
/// 2^52, adding and subtracting 2^52 rounds x to an integer exactly.
#[inline(always)]
fn ceil_non_negative(x: f64) -> f64 {
    const TWO_52: f64 = 4_503_599_627_370_496.0;
    if x < TWO_52 {
        let r = (x + TWO_52) - TWO_52;
        if r < x {
            r + 1.0
        } else {
            r
        }
    } else {
        x
    }
}

/// The view-dependent SH colour of [`project`].
fn sh_color(g: &Gaussians, campos: [f64; 3], i: usize, mean: [f64; 3]) -> [f64; 3] {
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
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use crate::camera::{look_at, pinhole_intrinsics};

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
            if v >= 0.0 {
                assert_eq!(ceil_non_negative(v), v.ceil(), "ceil_non_negative({v:e})");
            }
        }
        assert!(floor(f64::NAN).is_nan() && ceil(f64::NAN).is_nan());
        assert!(ceil_non_negative(f64::NAN).is_nan());
    }

    thread_local! {
        /// The f64 intermediates of `ViewConsts::splat` for each splat it returns.
        static TRACE: std::cell::RefCell<Vec<Projected>> =
            const { std::cell::RefCell::new(Vec::new()) };
    }

    pub(super) fn trace(p: Projected) {
        TRACE.with(|t| t.borrow_mut().push(p));
    }

    /// Bits of the f64 fields of a projection (the colour is compared in f32, as splat).
    fn projected_bits(p: &Projected) -> Vec<u64> {
        [p.center, [p.depth, p.radius]]
            .iter()
            .flatten()
            .chain(&p.cov2d)
            .chain(&p.conic)
            .chain(&[p.opacity])
            .map(|v| v.to_bits())
            .chain(p.tiles.map(u64::from))
            .chain([u64::from(p.id)])
            .collect()
    }

    /// Deterministic xorshift64* numbers.
    struct Rng(u64);
    impl Rng {
        fn unit(&mut self) -> f64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
        }
        fn range(&mut self, lo: f64, hi: f64) -> f64 {
            lo + (hi - lo) * self.unit()
        }
        fn pick(&mut self, n: usize) -> usize {
            ((self.unit() * n as f64) as usize).min(n - 1)
        }
    }

    fn camera(w: u32, h: u32, intrinsics: [f64; 4], eye: [f64; 3], target: [f64; 3]) -> ViewCamera {
        let m = look_at(eye, target, [0.0, 0.0, 1.0]).unwrap();
        let (rotation, translation) = camera::pose_from_row(&m);
        ViewCamera {
            rotation,
            translation,
            intrinsics,
            width: w,
            height: h,
        }
    }

    /// Cameras with odd image sizes (partial tiles), a decentred principal point and
    /// fx != fy, an axis-aligned one (exact zeros in W), and a matrix that is not a
    /// rotation (scaled by 1.3; only finiteness is checked, so the bound must hold anyway).
    fn cameras() -> Vec<ViewCamera> {
        let mut cams = vec![
            camera(
                330,
                250,
                pinhole_intrinsics(330, 250, 60.0),
                [0.0, -4.0, 1.0],
                [0.0; 3],
            ),
            camera(
                207,
                131,
                [150.0, 210.0, 40.0, 90.0],
                [3.0, 1.0, 0.5],
                [0.0, 0.0, 0.3],
            ),
            // Signed zeros in W (see `ViewConsts::zero_r0`).
            ViewCamera {
                rotation: [[1.0, -0.0, 0.0], [-0.0, 1.0, -0.0], [0.0, -0.0, 1.0]],
                translation: [0.0, 0.0, 4.0],
                intrinsics: pinhole_intrinsics(256, 160, 90.0),
                width: 256,
                height: 160,
            },
        ];
        let mut scaled = cams[0];
        scaled.rotation = scaled.rotation.map(|r| r.map(|x| 1.3 * x));
        scaled.translation = scaled.translation.map(|x| 1.3 * x);
        cams.push(scaled);
        cams
    }

    /// Gaussians placed relative to each of `cams` (through their camera frame): behind
    /// the camera, straddling the near plane, far off the image, centred just outside the
    /// tile grid with a 3-sigma footprint that may or may not reach it, on the image, on
    /// tile borders; with huge and tiny, isotropic and flat scales, random and identity
    /// rotations, and opacities around 1/255 (and 0 and 1).
    fn scene(cams: &[ViewCamera], per_camera: usize, seed: u64) -> Gaussians {
        let mut rng = Rng(seed);
        let mut g = Gaussians::default();
        let (mut means, mut log_scales, mut rotations, mut logits, mut dc) =
            (vec![], vec![], vec![], vec![], vec![]);
        // logit(1/255) and the logits around it.
        let edge = (1.0f64 / 254.0).ln();
        for cam in cams.iter().take(3) {
            let [fx, fy, cx, cy] = cam.intrinsics;
            let (w, h) = (f64::from(cam.width), f64::from(cam.height));
            let (gw, gh) = ((w / 16.0).ceil() * 16.0, (h / 16.0).ceil() * 16.0);
            for i in 0..per_camera {
                let kind = i % 8;
                let mut log_s = rng.range(-5.0, -1.0);
                let mut z = rng.range(0.5, 8.0);
                let (mut u, mut v) = (rng.range(0.0, w), rng.range(0.0, h));
                match kind {
                    0 => z = rng.range(-3.0, 0.2), // behind or at the near plane
                    1 => {
                        z = rng.range(0.19, 0.6); // straddling the near plane
                        log_s = rng.range(-3.0, 0.0);
                    }
                    2 => {
                        // far off the image, huge or ordinary
                        u = rng.range(-30.0 * w, 30.0 * w);
                        v = rng.range(-30.0 * h, 30.0 * h);
                        log_s = rng.range(-4.0, 3.0);
                    }
                    3 | 4 => {
                        // just outside the grid: the 3-sigma radius r ≈ 3 s f / z, the
                        // distance to the grid 0..1.3 r
                        log_s = rng.range(-3.5, -0.5);
                        let r = 3.0 * log_s.exp() * fx.max(fy) / z;
                        let d = rng.range(0.0, 1.3) * r;
                        match rng.pick(4) {
                            0 => u = -d,
                            1 => u = gw + d,
                            2 => v = -d,
                            _ => v = gh + d,
                        }
                    }
                    5 => {
                        // on tile borders
                        u = 16.0 * (u / 16.0).round();
                        v = 16.0 * (v / 16.0).round() + if i % 3 == 0 { 1e-3 } else { 0.0 };
                    }
                    6 => {
                        log_s = if i % 5 == 0 {
                            9.0
                        } else {
                            rng.range(-14.0, -9.0)
                        }
                    }
                    _ => {
                        // on the optical axis or one of its image lines
                        match i % 3 {
                            0 => (u, v) = (cx, cy),
                            1 => u = cx,
                            _ => v = cy,
                        }
                    }
                }
                let pc = [(u - cx) * z / fx, (v - cy) * z / fy, z];
                let (r, t) = (cam.rotation, cam.translation);
                means.push(std::array::from_fn(|a| {
                    (0..3).map(|b| r[b][a] * (pc[b] - t[b])).sum::<f64>() as f32
                }));
                let flat = i % 3 == 0;
                log_scales.push(std::array::from_fn(|a| {
                    let extra = if flat && a == 2 {
                        -4.0
                    } else {
                        rng.range(-0.3, 0.3)
                    };
                    (log_s + extra) as f32
                }));
                rotations.push(if i % 4 == 0 || kind == 7 {
                    [1.0, 0.0, 0.0, 0.0]
                } else {
                    std::array::from_fn(|_| rng.range(-1.0, 1.0) as f32)
                });
                logits.push(match i % 13 {
                    0 => f32::INFINITY,
                    1 => f32::NEG_INFINITY,
                    2..=5 => (edge + rng.range(-2e-6, 2e-6)) as f32,
                    _ => rng.range(-4.0, 6.0) as f32,
                });
                dc.push(std::array::from_fn(|_| rng.range(-2.0, 2.0) as f32));
            }
        }
        g.means = means.into();
        g.log_scales = log_scales.into();
        g.rotations = rotations.into();
        g.opacity_logits = logits.into();
        g.sh_dc = dc.into();
        g
    }

    fn with_degree(g: &Gaussians, degree: usize, seed: u64) -> Gaussians {
        let mut rng = Rng(seed);
        let mut g = g.clone();
        g.sh_degree = degree;
        g.sh_rest = (degree > 0).then(|| {
            let n = g.len() * g.sh_rest_coeffs() * 3;
            (0..n)
                .map(|_| rng.range(-0.5, 0.5) as f32)
                .collect::<Vec<_>>()
                .into()
        });
        g
    }

    /// The fields of a splat as bits.
    fn bits(s: &Splat) -> Vec<u32> {
        let mut b: Vec<u32> = [s.x, s.y, s.a, s.b, s.c, s.opacity]
            .iter()
            .chain(&s.color)
            .chain(&[s.depth, s.two_a_tau, s.det, s.inv_a])
            .map(|v| v.to_bits())
            .collect();
        b.push(s.id);
        b.extend(s.rect.map(u32::from));
        b
    }

    /// The splats of the Gaussians in `slots` by `project` + `Splat::new`, one Gaussian at
    /// a time, by id.
    fn reference(
        g: &Gaussians,
        prep: &Prepared,
        cam: &ViewCamera,
        slots: Range<usize>,
    ) -> Vec<Splat> {
        slots
            .filter_map(|slot| {
                project(g, cam, cam.center(), prep.id(slot) as usize)
                    .and_then(|p| Splat::new(&p, footprint_tau(p.opacity), cam.width, cam.height))
            })
            .collect()
    }

    /// Chunks as `bin` makes them, plus ranges that do not start at 0 or are empty.
    fn chunks(n: usize) -> Vec<Range<usize>> {
        vec![0..n / 3, n / 3..n / 3, n / 3..n - 5, n - 5..n]
    }

    /// Where the two paths differ: (camera, id range, first differing position).
    fn mismatches(
        g: &Gaussians,
        prep: &Prepared,
        cams: &[ViewCamera],
        tamper: impl Fn(&mut ViewConsts),
    ) -> Vec<String> {
        let mut bad = Vec::new();
        let mut levels = vec![Level::Portable];
        if Level::detect() != Level::Portable {
            levels.push(Level::detect());
        }
        for (c, cam) in cams.iter().enumerate() {
            let mut view = ViewConsts::new(cam, true);
            tamper(&mut view);
            for (level, ids) in levels
                .iter()
                .flat_map(|&level| chunks(g.len()).into_iter().map(move |ids| (level, ids)))
            {
                let want = reference(g, prep, cam, ids.clone());
                // Appends after what is there.
                let mut got = vec![want.first().copied().unwrap_or(Splat::filler()); 2];
                TRACE.with(|t| t.borrow_mut().clear());
                project_chunk(&view, g, prep, ids.clone(), level, &mut got);
                let got = &got[2..];
                let (mut wb, mut gb): (Vec<_>, Vec<_>) = (
                    want.iter()
                        .map(|s| bits(s).iter().map(|&b| u64::from(b)).collect())
                        .collect(),
                    got.iter()
                        .map(|s| bits(s).iter().map(|&b| u64::from(b)).collect())
                        .collect(),
                );
                // And the f64 values behind them, which the f32 rounding would mostly hide.
                wb.extend(want.iter().map(|s| {
                    projected_bits(&project(g, cam, cam.center(), s.id as usize).unwrap())
                }));
                gb.extend(
                    TRACE.with(|t| t.borrow().iter().map(projected_bits).collect::<Vec<_>>()),
                );
                if wb != gb {
                    let at = wb.iter().zip(&gb).position(|(a, b)| a != b);
                    bad.push(format!(
                        "camera {c}, {level:?}, ids {ids:?}: {} vs {} splats, first difference at {at:?}",
                        want.len(),
                        got.len()
                    ));
                }
            }
        }
        bad
    }

    impl Splat {
        fn filler() -> Splat {
            Splat {
                x: 1.0,
                y: 2.0,
                a: 3.0,
                b: 4.0,
                c: 5.0,
                opacity: 0.5,
                color: [0.1; 3],
                depth: 7.0,
                id: 99,
                two_a_tau: 1.0,
                det: 1.0,
                inv_a: 1.0,
                rect: [0; 4],
            }
        }
    }

    #[test]
    fn chunk_projection_equals_project_then_splat_new_bit_for_bit() {
        let cams = cameras();
        let base = scene(&cams, 1200, 7);
        for degree in 0..=3 {
            let g = with_degree(&base, degree, 100 + degree as u64);
            let prep = prepare(&g).unwrap();
            assert_eq!(prep.color0.len(), if degree == 0 { g.len() } else { 0 });
            let bad = mismatches(&g, &prep, &cams, |_| {});
            assert!(bad.is_empty(), "SH degree {degree}: {bad:#?}");
        }
    }

    /// Without `shade` the chunk projection keeps the same splats with the same geometry
    /// and carries black, for every SH degree.
    #[test]
    fn chunk_projection_without_shading_differs_only_in_colour() {
        let cams = cameras();
        let base = scene(&cams, 1200, 7);
        for degree in 0..=3 {
            let g = with_degree(&base, degree, 200 + degree as u64);
            let prep = prepare(&g).unwrap();
            for cam in &cams {
                let project = |shade: bool| {
                    let mut out: Vec<Splat> = Vec::new();
                    let view = ViewConsts::new(cam, shade);
                    project_chunk(&view, &g, &prep, 0..g.len(), Level::detect(), &mut out);
                    out
                };
                let (lit, plain) = (project(true), project(false));
                assert!(!lit.is_empty());
                assert_eq!(lit.len(), plain.len(), "SH degree {degree}");
                for (a, b) in lit.iter().zip(&plain) {
                    assert_eq!(b.color, [0.0; 3]);
                    assert_eq!(
                        bits(&Splat {
                            color: [0.0; 3],
                            ..*a
                        }),
                        bits(b),
                        "SH degree {degree}"
                    );
                }
                assert!(lit.iter().any(|s| s.color != [0.0; 3]));
            }
        }
    }

    /// The scene exercises every branch: survivors, near-plane culls, exact culls of
    /// Gaussians whose centre lies off the grid, pre-culls, never-drawn opacities; and
    /// the comparison above has the power to catch a pre-cull bound that is too tight
    /// (its gain scaled by 0.6, where this scene needs 0.68; the additive margins of the
    /// bound cannot be caught end to end: `Splat::new` rejects those Gaussians anyway).
    #[test]
    fn the_scene_exercises_the_pre_cull_and_a_too_tight_bound_is_caught() {
        let cams = cameras();
        let g = with_degree(&scene(&cams, 1200, 7), 0, 1);
        let prep = prepare(&g).unwrap();
        let n = g.len();
        for cam in &cams {
            let view = ViewConsts::new(cam, true);
            let kept = reference(&g, &prep, cam, 0..n);
            let kept_ids: std::collections::HashSet<u32> = kept.iter().map(|s| s.id).collect();
            let (mut near, mut pre_culled, mut off_kept, mut off_exact_culled, mut never) =
                (0, 0, 0, 0, 0);
            for slot in 0..n {
                let i = prep.id(slot) as usize;
                if prep.var_max[slot] < 0.0 {
                    never += 1;
                    continue;
                }
                let p = cam.to_camera(g.means[i].map(f64::from));
                if p[2] <= NEAR_PLANE {
                    near += 1;
                    continue;
                }
                let [u, v] = camera::project(&cam.intrinsics, p);
                let off_grid =
                    u < -2.0 || v < -2.0 || u > view.grid[0] + 2.0 || v > view.grid[1] + 2.0;
                if view.surely_off_grid(u, v, p[2], prep.var_max[slot]) {
                    pre_culled += 1;
                    assert!(!kept_ids.contains(&(i as u32)), "pre-culled {i} is kept");
                } else if off_grid && kept_ids.contains(&(i as u32)) {
                    off_kept += 1;
                } else if off_grid {
                    off_exact_culled += 1;
                }
            }
            let counts = [
                kept.len(),
                near,
                pre_culled,
                off_kept,
                off_exact_culled,
                never,
            ];
            assert!(counts.iter().all(|&c| c >= 20), "{counts:?}");
        }
        let too_tight = mismatches(&g, &prep, &cams, |v| v.cull_gain *= 0.6);
        assert!(!too_tight.is_empty());
    }

    /// Small Gaussians filling a box around the test cameras (a densely covered scene, in
    /// which Morton-ordered runs of slots are compact), one in 50 large.
    fn cloud(n: usize, seed: u64) -> Gaussians {
        let mut rng = Rng(seed);
        let mut pick = |lo: f64, hi: f64| rng.range(lo, hi) as f32;
        let (mut means, mut log_scales, mut rotations, mut logits, mut dc) =
            (vec![], vec![], vec![], vec![], vec![]);
        for i in 0..n {
            let big = if i % 50 == 0 { 3.0 } else { 0.0 };
            means.push([0; 3].map(|_| pick(-12.0, 12.0)));
            log_scales.push([0; 3].map(|_| pick(-4.0, -2.0) + big));
            rotations.push([0; 4].map(|_| pick(-1.0, 1.0)));
            logits.push(pick(-6.0, 6.0));
            dc.push([0; 3].map(|_| pick(-2.0, 2.0)));
        }
        Gaussians {
            means: means.into(),
            log_scales: log_scales.into(),
            rotations: rotations.into(),
            opacity_logits: logits.into(),
            sh_dc: dc.into(),
            ..Default::default()
        }
    }

    /// The group cull (`ViewConsts::group_culled`) on a densely covered scene: every
    /// camera culls groups both behind it and beside the image, no culled group holds a
    /// Gaussian that the reference keeps, the projection equals the reference bit for bit,
    /// and a cull loosened by 100 pixels per side is caught.
    #[test]
    fn a_dense_scene_exercises_the_group_cull_and_a_loose_one_is_caught() {
        let cams = cameras();
        let g = cloud(12_000, 5);
        let prep = prepare(&g).unwrap();
        let n = g.len();
        assert_eq!(prep.groups.len(), n.div_ceil(CULL_GROUP));
        for cam in &cams {
            let view = ViewConsts::new(cam, true);
            let kept: std::collections::HashSet<u32> = reference(&g, &prep, cam, 0..n)
                .iter()
                .map(|s| s.id)
                .collect();
            let (mut behind, mut beside) = (0, 0);
            for (k, group) in prep.groups.iter().enumerate() {
                if !view.group_culled(group) {
                    continue;
                }
                let slots = k * CULL_GROUP..((k + 1) * CULL_GROUP).min(n);
                for slot in slots.clone() {
                    assert!(!kept.contains(&prep.id(slot)), "culled slot {slot} is kept");
                }
                let depths = slots.map(|s| cam.to_camera(prep.means[s].map(f64::from))[2]);
                if depths.fold(f64::NEG_INFINITY, f64::max) <= NEAR_PLANE {
                    behind += 1;
                } else {
                    beside += 1;
                }
            }
            assert!(
                kept.len() >= 500 && behind >= 10 && beside >= 10,
                "{} kept, {behind} groups culled behind, {beside} beside",
                kept.len()
            );
        }
        assert_eq!(mismatches(&g, &prep, &cams, |_| {}), Vec::<String>::new());
        let loose = mismatches(&g, &prep, &cams, |v| {
            let ([fx, fy], [cx, cy]) = (v.focal, v.principal);
            let pixels = GROUP_CULL_PIXELS - 100.0;
            v.side_planes = side_planes(
                &v.rotation,
                &v.translation,
                [fx, fy, cx, cy],
                v.grid,
                pixels,
            );
        });
        assert!(!loose.is_empty());
    }

    /// The Morton order against a reference that spells each code out as a string of
    /// bits (bit j of x, y, z, from the top), on random means with duplicates, a flat axis
    /// and the bounding box's corners.
    #[test]
    fn spatial_order_is_the_morton_order_then_id() {
        let mut rng = Rng(11);
        let mut next = || rng.unit() as f32;
        let mut means: Vec<[f32; 3]> = (0..3000)
            .map(|_| [next() * 8.0 - 4.0, next() * 0.01, 2.5])
            .collect();
        means.extend_from_within(100..400);
        means.push([-4.0, 0.0, 2.5]);
        means.push([4.0, 0.01, 2.5]);
        let axis = |a: usize| means.iter().map(move |m| f64::from(m[a]));
        let lo = [0, 1].map(|a| axis(a).fold(f64::INFINITY, f64::min));
        let hi = [0, 1].map(|a| axis(a).fold(f64::NEG_INFINITY, f64::max));
        let cell = |a: usize, x: f32| -> u32 {
            let t = (f64::from(x) - lo[a]) / (hi[a] - lo[a]);
            ((t * 1024.0) as u32).min(1023)
        };
        let spelled = |m: &[f32; 3]| -> String {
            let q = [cell(0, m[0]), cell(1, m[1]), 0];
            (0..MORTON_BITS)
                .rev()
                .flat_map(|j| (0..3).rev().map(move |a| (q[a] >> j) & 1))
                .map(|b| if b == 1 { '1' } else { '0' })
                .collect()
        };
        let mut want: Vec<(String, u32)> = means
            .iter()
            .enumerate()
            .map(|(i, m)| (spelled(m), i as u32))
            .collect();
        want.sort();
        let want: Vec<u32> = want.into_iter().map(|(_, i)| i).collect();
        let got: Vec<u32> = spatial_order(&means).into_iter().map(key_id).collect();
        assert_eq!(got, want);
        // Duplicated means stay in id order, next to each other.
        let at = |id: u32| got.iter().position(|&g| g == id).unwrap();
        assert!(at(150) < at(3050) && at(3050) == at(150) + 1);
        assert_eq!(spatial_order(&[]), Vec::<u64>::new());
        assert_eq!(spatial_order(&[[1.0; 3]; 3]), vec![0, 1, 2]);
    }

    /// `tile_range` and `rect_span` drop floors and ceils that `project` and `Splat::new`
    /// take; compare with those formulas where it matters: integers, half-integers and
    /// their neighbours, NaN, infinities, huge values.
    #[test]
    fn floor_free_tile_and_rect_ranges_equal_the_floored_formulas() {
        let reference_rect = |c: f64, e: f64, slack: f64, t0: u32, t1: u32, size: u32| {
            let lo = ceil(c - e - 0.5 - slack);
            let hi = floor(c + e - 0.5 + slack);
            let lo = lo.max(f64::from(t0) * TILE as f64).max(0.0);
            let hi = hi
                .min(f64::from(t1) * TILE as f64 + (TILE - 1) as f64)
                .min(f64::from(size) - 1.0);
            (lo <= hi).then_some([lo as u16, hi as u16])
        };
        let mut xs = vec![
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            1e300,
            -1e300,
            0.0,
            -0.0,
        ];
        for k in -40..80 {
            let base = f64::from(k) * 8.0;
            for d in [0.0, 0.5, 1.0 / 64.0, -1.0 / 64.0, 1e-9, -1e-9, 3.7, -3.7] {
                xs.push(base + d);
                xs.push(base + d + 0.5);
            }
        }
        let radii = [3.0, 4.0, 16.0, 17.0, 100.0, 1e300, f64::INFINITY];
        let (mut checked, mut some) = (0, 0);
        for &c in &xs {
            for &r in &radii {
                for n in [1, 3, 20] {
                    let want = tile_span(c, r, n);
                    assert_eq!(tile_range(c, r, n), want, "tile_range({c}, {r}, {n})");
                    checked += 1;
                    some += usize::from(want.is_some());
                }
            }
            for &e in &[0.0, 0.3, 1.0, 2.5, 40.0, f64::INFINITY, f64::NAN] {
                for slack in [RECT_SLACK, 1.0] {
                    for (t0, t1, size) in [(0, 0, 7), (0, 2, 40), (1, 3, 64), (2, 19, 300)] {
                        let want = reference_rect(c, e, slack, t0, t1, size);
                        let got = rect_span(c, e, slack, t0, t1, size);
                        assert_eq!(
                            got, want,
                            "rect_span({c}, {e}, {slack}, {t0}, {t1}, {size})"
                        );
                        checked += 1;
                        some += usize::from(want.is_some());
                    }
                }
            }
        }
        assert!(
            some > checked / 10 && some < checked - checked / 10,
            "{some} of {checked}"
        );
    }
}

//! Per-Gaussian work: view-independent preparation (3D covariance, opacity) and the EWA
//! projection into one view. Here: the reference projection by id ([`project`]) and its EWA
//! math; `prepared` (the view-independent data, in slot order), `view` (per-view constants,
//! pre-culls, the lane-by-lane projection), `chunk` (batches of lanes over a chunk of slots)
//! and `splat` (what the tile loop reads).

use std::ops::Range;

use profuse_formats::{camera, Gaussians};

use crate::camera::ViewCamera;
use crate::error::{RasterError, Result};
use crate::sh::eval_sh;
use crate::simd::{prefetch, Level};
use crate::{ALPHA_MIN, FRUSTUM_CLAMP, LOW_PASS, NEAR_PLANE, SIGMA_EXTENT, TILE};

mod chunk;
mod prepared;
mod splat;
mod view;

pub(crate) use chunk::*;
pub use prepared::*;
pub(crate) use splat::*;
pub(crate) use view::*;

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

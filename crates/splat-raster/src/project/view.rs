//! Per-view constants of the projection, the group and off-grid pre-culls, and the lane-by-lane
//! (branch-free) projection of a batch.

use super::*;

/// What [`project`] and [`Splat::new`] compute from the camera alone, computed once per
/// view with the same expressions (the tests tamper with them), and whether the splats
/// get their colour.
pub(crate) struct ViewConsts {
    pub(super) rotation: [[f64; 3]; 3],
    pub(super) translation: [f64; 3],
    pub(super) focal: [f64; 2],
    pub(super) principal: [f64; 2],
    /// Bounds of the clamped x/z and y/z (`clamp_tan` of [`project`]).
    pub(super) tan_x: [f64; 2],
    pub(super) tan_y: [f64; 2],
    /// 0.0 · rotation[0][b] and 0.0 · rotation[1][b]: the products of the structural zeros
    /// of J in T = J W. They are ±0, but adding one can still change the sign of a zero
    /// sum (+0 + −0 = +0), so T keeps them and stays bit-identical by construction.
    pub(super) zero_r0: [f64; 3],
    pub(super) zero_r1: [f64; 3],
    pub(super) tiles: [usize; 2],
    /// Width and height of the tile grid in pixels (tiles · [`TILE`]).
    pub(super) grid: [f64; 2],
    /// The constant G of the pre-cull bound λmax(T Σ Tᵀ) <= G · var_max / z².
    pub(super) cull_gain: f64,
    pub(super) width: u32,
    pub(super) height: u32,
    /// The camera centre (the view direction of the colour).
    pub(super) campos: [f64; 3],
    /// Whether the splats get their colour (see [`project_chunk`]).
    pub(super) shade: bool,
    /// The half-spaces of [`ViewConsts::group_culled`]: camera depth, and the image's
    /// left, right, top and bottom sides.
    pub(super) depth_plane: CullPlane,
    pub(super) side_planes: [CullPlane; 4],
}

/// A linear function of the world position, a·p + b, with the Euclidean norm of a and
/// the magnitudes of the terms it sums (|a| and |b| bound them component-wise) for a
/// rounding margin.
#[derive(Debug, Clone, Copy)]
pub(super) struct CullPlane {
    pub(super) a: [f64; 3],
    pub(super) b: f64,
    pub(super) norm: f64,
    pub(super) a_abs: [f64; 3],
    pub(super) b_abs: f64,
}

impl CullPlane {
    /// s·f·(camera axis `axis`) + k·(camera z): the camera axes are rows of R plus t.
    pub(super) fn new(
        r: &[[f64; 3]; 3],
        t: &[f64; 3],
        [s, f]: [f64; 2],
        axis: usize,
        k: f64,
    ) -> Self {
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
    pub(super) fn max_over(&self, group: &CullGroup, extra: f64) -> (f64, f64) {
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
pub(super) const GROUP_CULL_PIXELS: f64 = 5.0;

/// The relative margin of the group cull's tests: far above the rounding of the values
/// compared (a few 1e-16 of the magnitudes summed).
pub(super) const GROUP_CULL_MARGIN: f64 = 1e-6;

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
    pub(super) fn group_culled(&self, group: &CullGroup) -> bool {
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
    pub(super) fn surely_off_grid(&self, u: f64, v: f64, z: f64, var: f32) -> bool {
        let [gw, gh] = self.grid;
        // Non-short-circuit `&` and `|`, so that a lane loop computes it without branches;
        // the division is then done for Gaussians on the grid too, and ignored.
        let off = (u < -2.0) | (v < -2.0) | (u > gw + 2.0) | (v > gh + 2.0);
        let lambda_bound = self.cull_gain * f64::from(var) / (z * z) + 0.62;
        let rb = SIGMA_EXTENT * lambda_bound.sqrt() + 2.0;
        off & ((u + rb < 0.0) | (u - rb > gw) | (v + rb < 0.0) | (v - rb > gh))
    }

    /// The 2D covariance `[a, b, c]` (of `[[a, b], [b, c]]`, low-pass included) of a
    /// Gaussian at camera coordinates (px, py, z) with 3D covariance `cov3d`: EWA, as in
    /// [`project`]. A step of [`ViewConsts::project_lanes`], inlined into its lane loop.
    #[inline(always)]
    fn ewa_cov2d(&self, [px, py, z]: [f64; 3], cov3d: [f64; 6]) -> [f64; 3] {
        let r = &self.rotation;
        let [fx, fy] = self.focal;
        let tx = clamp(px / z, self.tan_x) * z;
        let ty = clamp(py / z, self.tan_y) * z;
        let z2 = z * z;
        let (j00, j02) = (fx / z, -fx * tx / z2);
        let (j11, j12) = (fy / z, -fy * ty / z2);
        let t0: [f64; 3] = std::array::from_fn(|b| j00 * r[0][b] + self.zero_r1[b] + j02 * r[2][b]);
        let t1: [f64; 3] = std::array::from_fn(|b| self.zero_r0[b] + j11 * r[1][b] + j12 * r[2][b]);
        let [sxx, sxy, sxz, syy, syz, szz] = cov3d;
        let sigma = [[sxx, sxy, sxz], [sxy, syy, syz], [sxz, syz, szz]];
        let times_sigma = |t: &[f64; 3]| -> [f64; 3] {
            std::array::from_fn(|b| t[0] * sigma[0][b] + t[1] * sigma[1][b] + t[2] * sigma[2][b])
        };
        let (ts0, ts1) = (times_sigma(&t0), times_sigma(&t1));
        let dot = |a: &[f64; 3], b: &[f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let ca = dot(&ts0, &t0) + LOW_PASS;
        let cb = dot(&ts0, &t1);
        let cc = dot(&ts1, &t1) + LOW_PASS;
        [ca, cb, cc]
    }

    /// [`project`] then [`Splat::new`] for Gaussians `first..first + L`, written out with
    /// the per-view constants, lane by lane and without branches (every test is a lane of
    /// `keep`; the values of a lane that is not kept are computed anyway and unused), so
    /// that the loop over the lanes vectorises.
    #[inline(always)]
    pub(super) fn project_lanes<const L: usize>(
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

            let [ca, cb, cc] = self.ewa_cov2d([px, py, z], cov3d[l]);
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
pub(super) fn side_planes(
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
pub(super) fn clamp(x: f64, range: [f64; 2]) -> f64 {
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
pub(super) fn tile_range(c: f64, radius: f64, n: usize) -> Option<[u32; 2]> {
    let (hit, range) = tile_lanes(c, radius, n);
    hit.then_some(range)
}

/// [`project`]'s tile range without branches: whether `[c − radius, c + radius]` meets
/// the `n` tiles, and the range (meaningless when it does not). Without its floors: with
/// y = (c ± radius) / 16, floor(y) >= 0 ⟺ y >= 0 and floor(y) <= n − 1 ⟺ y < n (both false
/// for NaN), and on the clamped values, which are >= 0, `as u32` truncates, i.e. floors.
#[inline(always)]
pub(super) fn tile_lanes(c: f64, radius: f64, n: usize) -> (bool, [u32; 2]) {
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
pub(super) fn rect_span(
    c: f64,
    e: f64,
    slack: f64,
    t0: u32,
    t1: u32,
    size: u32,
) -> Option<[u16; 2]> {
    let (some, span) = rect_lanes(c, e, slack, t0, t1, size);
    some.then_some(span)
}

/// The pixel span of [`Splat::new`] along one axis without branches: whether it is not
/// empty, and the span (meaningless when it is). Its ceil and floor come after the clamps
/// rather than before: they commute with max/min against the integer bounds (NaN
/// included: f64::max/min return the bound), and the clamped values lie in [0, size − 1]
/// when the span is not empty, where `as u16` truncates exactly.
#[inline(always)]
pub(super) fn rect_lanes(
    c: f64,
    e: f64,
    slack: f64,
    t0: u32,
    t1: u32,
    size: u32,
) -> (bool, [u16; 2]) {
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
pub(super) fn max_bound(x: f64, bound: f64) -> f64 {
    if x > bound {
        x
    } else {
        bound
    }
}

/// `x.min(bound)` for a bound that is not NaN, as [`max_bound`].
#[inline(always)]
pub(super) fn min_bound(x: f64, bound: f64) -> f64 {
    if x < bound {
        x
    } else {
        bound
    }
}

/// [`ceil`] of an `x >= 0` (or NaN) without the saturating float-to-int conversion: below
/// 2^52, adding and subtracting 2^52 rounds x to an integer exactly.
#[inline(always)]
pub(super) fn ceil_non_negative(x: f64) -> f64 {
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

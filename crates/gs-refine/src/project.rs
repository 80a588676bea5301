//! splat-raster's per-Gaussian projection (`preprocessCUDA`) in `f64`, with the
//! intermediates its backward pass needs, and that backward pass: gradients of the screen
//! quantities (centre, conic, colour, opacity) pulled back to the mean, log-scales,
//! quaternion, opacity logit and SH coefficients.
//!
//! The forward takes the clamped Jacobian, the 2D footprint and the tiles from
//! `splat_raster` ([`ewa_jacobian`], [`footprint`], [`screen_tiles`]) and repeats the rest of
//! its operations in the same order, so the screen quantities are bit-identical to
//! `Rasterizer::project` (the integration tests compare).

use profuse_formats::camera;
use splat_raster::sh::{SH_C0, SH_C1, SH_C2, SH_C3};
use splat_raster::{
    ewa_jacobian, footprint, screen_tiles, EwaJacobian, Footprint, ViewCamera, NEAR_PLANE,
};

use crate::params::{rest_coeffs, Params};

/// Screen-space gradient of one Gaussian in one view: d/d(u, v, a, b, c, opacity, r, g, b)
/// where (a, b, c) is the conic of the power −½(a dx² + c dy²) − b dx dy.
pub type ScreenGrad = [f64; 9];

/// A projected Gaussian with everything its backward pass needs.
#[derive(Debug, Clone, Copy)]
pub struct Proj {
    /// Pixel centre (u, v).
    pub center: [f64; 2],
    /// Camera z.
    pub depth: f64,
    /// 2D covariance with the low-pass: xx, xy, yy.
    pub cov2d: [f64; 3],
    /// Inverse of `cov2d`: a, b, c.
    pub conic: [f64; 3],
    /// Tiles of the 3-sigma square, inclusive, clamped: tx0, tx1, ty0, ty1.
    pub tiles: [u32; 4],
    /// Clamped SH colour.
    pub color: [f64; 3],
    /// sigmoid(logit).
    pub opacity: f64,
}

/// Intermediates of the projection kept for the backward pass.
struct Inter {
    p: [f64; 3],
    /// Whether x/z (y/z) was clamped in the Jacobian, and the clamped tangent.
    clamped: [bool; 2],
    tan: [f64; 2],
    t: [[f64; 3]; 2],
    sigma: [[f64; 3]; 3],
    rot: [[f64; 3]; 3],
    scale: [f64; 3],
    /// Normalised quaternion and the norm it was divided by.
    qn: [f64; 4],
    qnorm: f64,
}

/// Projects Gaussian `i`; `None` when splat-raster culls it (near plane, degenerate 2D
/// covariance, 3-sigma square off the tile grid).
pub fn project(p: &Params, cam: &ViewCamera, campos: [f64; 3], i: usize) -> Option<Proj> {
    project_inner(p, cam, campos, i).map(|(pr, _)| pr)
}

fn project_inner(
    g: &Params,
    cam: &ViewCamera,
    campos: [f64; 3],
    i: usize,
) -> Option<(Proj, Inter)> {
    let mean = g.means[i].map(f64::from);
    let p = cam.to_camera(mean);
    let z = p[2];
    if z.is_nan() || z <= NEAR_PLANE {
        return None;
    }
    let [u, v] = camera::project(&cam.intrinsics, p);
    let EwaJacobian { t, tan, clamped } = ewa_jacobian(cam, p);
    let (rot, scale, qn, qnorm) = rotation_scale(g.log_scales[i], g.rotations[i])?;
    let m: [[f64; 3]; 3] = std::array::from_fn(|a| std::array::from_fn(|b| rot[a][b] * scale[b]));
    let e3 = |a: usize, b: usize| m[a][0] * m[b][0] + m[a][1] * m[b][1] + m[a][2] * m[b][2];
    let [sxx, sxy, sxz, syy, syz, szz] =
        [e3(0, 0), e3(0, 1), e3(0, 2), e3(1, 1), e3(1, 2), e3(2, 2)];
    let sigma = [[sxx, sxy, sxz], [sxy, syy, syz], [sxz, syz, szz]];
    let Footprint {
        cov2d,
        conic,
        radius,
    } = footprint(&t, &sigma)?;
    let tiles = screen_tiles(cam, [u, v], radius)?;
    let color = sh_color(g, i, campos, mean);
    let opacity = g.opacity(i);
    Some((
        Proj {
            center: [u, v],
            depth: z,
            cov2d,
            conic,
            tiles,
            color,
            opacity,
        },
        Inter {
            p,
            clamped,
            tan,
            t,
            sigma,
            rot,
            scale,
            qn,
            qnorm,
        },
    ))
}

type RotScale = ([[f64; 3]; 3], [f64; 3], [f64; 4], f64);

/// R (from the normalised quaternion, profuse_formats::camera's formula), the scales, the
/// normalised quaternion and its norm.
fn rotation_scale(log_scales: [f32; 3], q: [f32; 4]) -> Option<RotScale> {
    let q = q.map(f64::from);
    let rot = camera::quaternion_to_rotation(q)?;
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    Some((
        rot,
        log_scales.map(|l| f64::from(l).exp()),
        q.map(|x| x / n),
        n,
    ))
}

/// Unit direction from the camera centre to the mean, and the distance.
fn view_dir(campos: [f64; 3], mean: [f64; 3]) -> ([f64; 3], f64) {
    let d = [
        mean[0] - campos[0],
        mean[1] - campos[1],
        mean[2] - campos[2],
    ];
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    (d.map(|x| x / n), n)
}

fn sh_color(g: &Params, i: usize, campos: [f64; 3], mean: [f64; 3]) -> [f64; 3] {
    let dir = if g.sh_degree == 0 {
        [0.0, 0.0, 1.0]
    } else {
        view_dir(campos, mean).0
    };
    let rest = if g.sh_degree == 0 { &[][..] } else { g.rest(i) };
    splat_raster::sh::eval_sh(g.sh_degree, g.sh_dc[i], rest, dir)
}

/// Gradient of one Gaussian's parameters in one view.
#[derive(Debug, Clone, Copy, Default)]
pub struct ParamGrad {
    /// d/d mean.
    pub mean: [f64; 3],
    /// d/d log-scales.
    pub log_scale: [f64; 3],
    /// d/d quaternion.
    pub rotation: [f64; 4],
    /// d/d opacity logit.
    pub opacity_logit: f64,
    /// d/d DC.
    pub sh_dc: [f64; 3],
}

/// Pulls the screen gradient `gs` of Gaussian `i` back to its parameters; the higher SH
/// coefficients' gradient is added to `rest` (`3 * rest_coeffs` values). Zero where the
/// Gaussian is culled.
pub fn backward(
    g: &Params,
    cam: &ViewCamera,
    campos: [f64; 3],
    i: usize,
    gs: &ScreenGrad,
    rest: &mut [f64],
) -> ParamGrad {
    let mut out = ParamGrad::default();
    let Some((pr, it)) = project_inner(g, cam, campos, i) else {
        return out;
    };
    let [fx, fy, _, _] = cam.intrinsics;
    let [px, py, z] = it.p;
    // Centre: u = fx x/z + cx, v = fy y/z + cy.
    let mut dp = [
        gs[0] * fx / z,
        gs[1] * fy / z,
        -gs[0] * fx * px / (z * z) - gs[1] * fy * py / (z * z),
    ];
    // Conic (a, b, c) = (cc, −cb, ca) / det → 2D covariance (ca, cb, cc).
    let [ca, cb, cc] = pr.cov2d;
    let det = ca * cc - cb * cb;
    let d2 = det * det;
    let [ga, gb, gc] = [gs[2], gs[3], gs[4]];
    let g_ca = ga * (-cc * cc / d2) + gb * (cb * cc / d2) + gc * (1.0 / det - ca * cc / d2);
    let g_cc = ga * (1.0 / det - cc * ca / d2) + gb * (cb * ca / d2) + gc * (-ca * ca / d2);
    let g_cb = ga * (2.0 * cc * cb / d2)
        + gb * (-1.0 / det - 2.0 * cb * cb / d2)
        + gc * (2.0 * ca * cb / d2);
    // cov2d = T Σ Tᵀ: symmetric gradient G (off-diagonal halves of g_cb).
    let gm = [[g_ca, 0.5 * g_cb], [0.5 * g_cb, g_cc]];
    let t = &it.t;
    let gsigma: [[f64; 3]; 3] = std::array::from_fn(|a| {
        std::array::from_fn(|b| {
            (0..2)
                .map(|k| (0..2).map(|l| t[k][a] * gm[k][l] * t[l][b]).sum::<f64>())
                .sum()
        })
    });
    // dL/dT = 2 G T Σ, then T = J W: dL/dJ = dL/dT Wᵀ.
    let ts: [[f64; 3]; 2] = std::array::from_fn(|a| {
        std::array::from_fn(|b| (0..3).map(|k| t[a][k] * it.sigma[k][b]).sum())
    });
    let gt: [[f64; 3]; 2] = std::array::from_fn(|a| {
        std::array::from_fn(|b| 2.0 * (gm[a][0] * ts[0][b] + gm[a][1] * ts[1][b]))
    });
    let r = &cam.rotation;
    let gj: [[f64; 3]; 2] =
        std::array::from_fn(|a| std::array::from_fn(|k| (0..3).map(|b| gt[a][b] * r[k][b]).sum()));
    // J = [[fx/z, 0, −fx tx/z²], [0, fy/z, −fy ty/z²]], tx = clamp(x/z)·z.
    let (tx, ty) = (it.tan[0] * z, it.tan[1] * z);
    let z2 = z * z;
    let z3 = z2 * z;
    let mut g_z = -gj[0][0] * fx / z2 - gj[1][1] * fy / z2
        + gj[0][2] * 2.0 * fx * tx / z3
        + gj[1][2] * 2.0 * fy * ty / z3;
    let g_tx = -gj[0][2] * fx / z2;
    let g_ty = -gj[1][2] * fy / z2;
    // Unclamped: tx = x (the z/z cancels); clamped: tx = tan·z.
    if it.clamped[0] {
        g_z += g_tx * it.tan[0];
    } else {
        dp[0] += g_tx;
    }
    if it.clamped[1] {
        g_z += g_ty * it.tan[1];
    } else {
        dp[1] += g_ty;
    }
    dp[2] += g_z;
    // p = W m + t.
    out.mean = std::array::from_fn(|b| (0..3).map(|a| r[a][b] * dp[a]).sum());
    scale_rotation_backward(&it, &gsigma, &mut out);
    let o = pr.opacity;
    out.opacity_logit = gs[5] * o * (1.0 - o);
    let mean = g.means[i].map(f64::from);
    let gdir = sh_backward(g, i, campos, mean, [gs[6], gs[7], gs[8]], &mut out, rest);
    if g.sh_degree > 0 {
        let (dir, n) = view_dir(campos, mean);
        let dot = dir[0] * gdir[0] + dir[1] * gdir[1] + dir[2] * gdir[2];
        for a in 0..3 {
            out.mean[a] += (gdir[a] - dir[a] * dot) / n;
        }
    }
    out
}

/// Σ = M Mᵀ, M = R S → log-scales and the quaternion (through its normalisation).
fn scale_rotation_backward(it: &Inter, gsigma: &[[f64; 3]; 3], out: &mut ParamGrad) {
    let (rot, s) = (&it.rot, &it.scale);
    let m: [[f64; 3]; 3] = std::array::from_fn(|a| std::array::from_fn(|b| rot[a][b] * s[b]));
    // dL/dM = (G + Gᵀ) M.
    let gmm: [[f64; 3]; 3] = std::array::from_fn(|a| {
        std::array::from_fn(|b| {
            (0..3)
                .map(|k| (gsigma[a][k] + gsigma[k][a]) * m[k][b])
                .sum()
        })
    });
    let mut gr = [[0.0; 3]; 3];
    for a in 0..3 {
        for b in 0..3 {
            gr[a][b] = gmm[a][b] * s[b];
            out.log_scale[b] += gmm[a][b] * rot[a][b] * s[b];
        }
    }
    let [w, x, y, z] = it.qn;
    let gq = [
        2.0 * (-z * gr[0][1] + y * gr[0][2] + z * gr[1][0] - x * gr[1][2] - y * gr[2][0]
            + x * gr[2][1]),
        2.0 * (y * gr[0][1] + z * gr[0][2] + y * gr[1][0] - 2.0 * x * gr[1][1] - w * gr[1][2]
            + z * gr[2][0]
            + w * gr[2][1]
            - 2.0 * x * gr[2][2]),
        2.0 * (-2.0 * y * gr[0][0] + x * gr[0][1] + w * gr[0][2] + x * gr[1][0] + z * gr[1][2]
            - w * gr[2][0]
            + z * gr[2][1]
            - 2.0 * y * gr[2][2]),
        2.0 * (-2.0 * z * gr[0][0] - w * gr[0][1] + x * gr[0][2] + w * gr[1][0]
            - 2.0 * z * gr[1][1]
            + y * gr[1][2]
            + x * gr[2][0]
            + y * gr[2][1]),
    ];
    let dot = it.qn.iter().zip(&gq).map(|(a, b)| a * b).sum::<f64>();
    out.rotation = std::array::from_fn(|k| (gq[k] - it.qn[k] * dot) / it.qnorm);
}

/// SH colour backward: coefficient gradients into `out.sh_dc` and `rest`; returns the
/// gradient with respect to the unit view direction.
fn sh_backward(
    g: &Params,
    i: usize,
    campos: [f64; 3],
    mean: [f64; 3],
    gcol: [f64; 3],
    out: &mut ParamGrad,
    rest: &mut [f64],
) -> [f64; 3] {
    let deg = g.sh_degree;
    let dir = if deg == 0 {
        [0.0, 0.0, 1.0]
    } else {
        view_dir(campos, mean).0
    };
    let (basis, dbasis) = basis_and_grad(deg, dir);
    let nk = rest_coeffs(deg);
    let coef = if deg == 0 { &[][..] } else { g.rest(i) };
    let mut gdir = [0.0; 3];
    for ch in 0..3 {
        // Recompute the unclamped value: the clamp max(0, ·) passes no gradient below 0.
        let mut acc = SH_C0 * f64::from(g.sh_dc[i][ch]);
        for k in 1..=nk {
            acc += basis[k] * f64::from(coef[3 * (k - 1) + ch]);
        }
        if acc + 0.5 < 0.0 {
            continue;
        }
        out.sh_dc[ch] = SH_C0 * gcol[ch];
        for k in 1..=nk {
            rest[3 * (k - 1) + ch] += basis[k] * gcol[ch];
            let cv = f64::from(coef[3 * (k - 1) + ch]) * gcol[ch];
            for a in 0..3 {
                gdir[a] += dbasis[k][a] * cv;
            }
        }
    }
    gdir
}

/// The SH basis of splat_raster::sh (index 0 unused) and its gradient w.r.t. the direction.
fn basis_and_grad(degree: usize, [x, y, z]: [f64; 3]) -> ([f64; 16], [[f64; 3]; 16]) {
    let mut b = [0.0; 16];
    let mut d = [[0.0; 3]; 16];
    if degree == 0 {
        return (b, d);
    }
    let c1 = SH_C1;
    b[1] = -c1 * y;
    b[2] = c1 * z;
    b[3] = -c1 * x;
    d[1] = [0.0, -c1, 0.0];
    d[2] = [0.0, 0.0, c1];
    d[3] = [-c1, 0.0, 0.0];
    if degree == 1 {
        return (b, d);
    }
    let (xx, yy, zz) = (x * x, y * y, z * z);
    let (xy, yz, xz) = (x * y, y * z, x * z);
    let c = SH_C2;
    b[4] = c[0] * xy;
    b[5] = c[1] * yz;
    b[6] = c[2] * (2.0 * zz - xx - yy);
    b[7] = c[3] * xz;
    b[8] = c[4] * (xx - yy);
    d[4] = [c[0] * y, c[0] * x, 0.0];
    d[5] = [0.0, c[1] * z, c[1] * y];
    d[6] = [-2.0 * c[2] * x, -2.0 * c[2] * y, 4.0 * c[2] * z];
    d[7] = [c[3] * z, 0.0, c[3] * x];
    d[8] = [2.0 * c[4] * x, -2.0 * c[4] * y, 0.0];
    if degree == 2 {
        return (b, d);
    }
    let c = SH_C3;
    b[9] = c[0] * y * (3.0 * xx - yy);
    b[10] = c[1] * xy * z;
    b[11] = c[2] * y * (4.0 * zz - xx - yy);
    b[12] = c[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
    b[13] = c[4] * x * (4.0 * zz - xx - yy);
    b[14] = c[5] * z * (xx - yy);
    b[15] = c[6] * x * (xx - 3.0 * yy);
    d[9] = [c[0] * 6.0 * xy, c[0] * (3.0 * xx - 3.0 * yy), 0.0];
    d[10] = [c[1] * yz, c[1] * xz, c[1] * xy];
    d[11] = [
        c[2] * (-2.0 * xy),
        c[2] * (4.0 * zz - xx - 3.0 * yy),
        c[2] * 8.0 * yz,
    ];
    d[12] = [
        c[3] * (-6.0 * xz),
        c[3] * (-6.0 * yz),
        c[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy),
    ];
    d[13] = [
        c[4] * (4.0 * zz - 3.0 * xx - yy),
        c[4] * (-2.0 * xy),
        c[4] * 8.0 * xz,
    ];
    d[14] = [c[5] * 2.0 * xz, c[5] * (-2.0 * yz), c[5] * (xx - yy)];
    d[15] = [c[6] * (3.0 * xx - 3.0 * yy), c[6] * (-6.0 * xy), 0.0];
    (b, d)
}

//! The 3DGS photometric loss, (1 − λ) L1 + λ (1 − SSIM) with λ = 0.2, and its gradient.
//!
//! SSIM as in the 3DGS code (`ssim` of `utils/loss_utils.py`): per channel, an 11 × 11
//! Gaussian window with σ = 1.5 applied as a same-size convolution with zero padding,
//! C1 = 0.01², C2 = 0.03², the map averaged over every pixel and channel. The window is
//! separable and symmetric, and zero-padded same-size convolution with a symmetric kernel
//! is its own adjoint, so the backward pass is three more convolutions.

use rayon::prelude::*;

/// Weight of the D-SSIM term.
pub const LAMBDA_DSSIM: f64 = 0.2;
/// Window side.
pub const WINDOW: usize = 11;
/// Window standard deviation.
pub const SIGMA: f64 = 1.5;
const C1: f64 = 0.01 * 0.01;
const C2: f64 = 0.03 * 0.03;

/// The normalised 1D window.
fn kernel() -> [f64; WINDOW] {
    let half = (WINDOW / 2) as f64;
    let mut k: [f64; WINDOW] =
        std::array::from_fn(|i| (-((i as f64 - half).powi(2)) / (2.0 * SIGMA * SIGMA)).exp());
    let s: f64 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= s);
    k
}

/// Same-size separable convolution with zero padding of one `w × h` plane (rows in
/// parallel; each output is a fixed-order sum, so thread-count independent).
fn blur(src: &[f64], w: usize, h: usize, out: &mut Vec<f64>) {
    let k = kernel();
    let r = WINDOW / 2;
    let mut tmp = vec![0.0; w * h];
    // Each pass adds tap j to every output it reaches (ascending j: a fixed order per
    // output), as whole-row multiply-adds that vectorise.
    tmp.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let s = &src[y * w..(y + 1) * w];
        for (j, kv) in k.iter().enumerate() {
            // Output x reads s[x + j − r]: x in [r − j, w + r − j) ∩ [0, w).
            let lo = r.saturating_sub(j);
            let hi = (w + r).saturating_sub(j).min(w);
            if lo >= hi {
                continue;
            }
            let src_lo = lo + j - r;
            for (o, v) in row[lo..hi].iter_mut().zip(&s[src_lo..src_lo + (hi - lo)]) {
                *o += kv * v;
            }
        }
    });
    out.clear();
    out.resize(w * h, 0.0);
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (j, kv) in k.iter().enumerate() {
            let yy = y as isize + j as isize - r as isize;
            if yy < 0 || yy as usize >= h {
                continue;
            }
            let s = &tmp[yy as usize * w..(yy as usize + 1) * w];
            for (o, v) in row.iter_mut().zip(s) {
                *o += kv * v;
            }
        }
    });
}

/// Loss value, its parts, and the gradient with respect to the rendered image.
#[derive(Debug, Clone, Default)]
pub struct LossOut {
    /// (1 − λ) L1 + λ (1 − SSIM).
    pub loss: f64,
    /// Mean absolute error.
    pub l1: f64,
    /// Mean SSIM.
    pub ssim: f64,
    /// Mean squared error (for PSNR; not part of the loss).
    pub mse: f64,
}

/// The loss of `render` against `target` (both `[H, W, 3]`, values in [0, 1] nominally),
/// writing d loss / d render into `grad`.
pub fn loss_and_grad(
    render: &[f32],
    target: &[f32],
    w: usize,
    h: usize,
    grad: &mut Vec<f32>,
) -> LossOut {
    let n = (w * h * 3) as f64;
    let mut out = LossOut::default();
    grad.clear();
    grad.resize(w * h * 3, 0.0);
    let mut g64 = vec![0.0f64; w * h * 3];
    for (i, (r, t)) in render.iter().zip(target).enumerate() {
        let d = f64::from(*r) - f64::from(*t);
        out.l1 += d.abs();
        out.mse += d * d;
        g64[i] = (1.0 - LAMBDA_DSSIM) * d.signum() * f64::from(u8::from(d != 0.0)) / n;
    }
    out.l1 /= n;
    out.mse /= n;
    let mut ssim_sum = 0.0;
    for ch in 0..3 {
        let x: Vec<f64> = render
            .iter()
            .skip(ch)
            .step_by(3)
            .map(|v| f64::from(*v))
            .collect();
        let y: Vec<f64> = target
            .iter()
            .skip(ch)
            .step_by(3)
            .map(|v| f64::from(*v))
            .collect();
        let gx = ssim_channel(&x, &y, w, h, -LAMBDA_DSSIM / n, &mut ssim_sum);
        for (p, g) in gx.iter().enumerate() {
            g64[p * 3 + ch] += g;
        }
    }
    out.ssim = ssim_sum / n;
    out.loss = (1.0 - LAMBDA_DSSIM) * out.l1 + LAMBDA_DSSIM * (1.0 - out.ssim);
    for (g, v) in grad.iter_mut().zip(&g64) {
        *g = *v as f32;
    }
    out
}

/// One channel's SSIM map: adds its sum to `sum` and returns `scale` · d(Σ map)/dx.
fn ssim_channel(x: &[f64], y: &[f64], w: usize, h: usize, scale: f64, sum: &mut f64) -> Vec<f64> {
    let (mut mx, mut my, mut exx, mut eyy, mut exy) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    blur(x, w, h, &mut mx);
    blur(y, w, h, &mut my);
    let sq = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(p, q)| p * q).collect::<Vec<_>>();
    blur(&sq(x, x), w, h, &mut exx);
    blur(&sq(y, y), w, h, &mut eyy);
    blur(&sq(x, y), w, h, &mut exy);
    // Per pixel: dS/dμx (total, through σ²x and σxy), dS/dE[x²], dS/dE[xy].
    let mut g_mu = vec![0.0; w * h];
    let mut g_xx = vec![0.0; w * h];
    let mut g_xy = vec![0.0; w * h];
    for p in 0..w * h {
        let (ux, uy) = (mx[p], my[p]);
        let sxx = exx[p] - ux * ux;
        let syy = eyy[p] - uy * uy;
        let sxy = exy[p] - ux * uy;
        let a1 = 2.0 * ux * uy + C1;
        let a2 = 2.0 * sxy + C2;
        let b1 = ux * ux + uy * uy + C1;
        let b2 = sxx + syy + C2;
        let s = a1 * a2 / (b1 * b2);
        *sum += s;
        let d_sxy = 2.0 * a1 / (b1 * b2);
        let d_sxx = -s / b2;
        let d_ux = 2.0 * uy * a2 / (b1 * b2) - 2.0 * ux * s / b1;
        g_mu[p] = scale * (d_ux + d_sxx * (-2.0 * ux) + d_sxy * (-uy));
        g_xx[p] = scale * d_sxx;
        g_xy[p] = scale * d_sxy;
    }
    let (mut bm, mut bxx, mut bxy) = (Vec::new(), Vec::new(), Vec::new());
    blur(&g_mu, w, h, &mut bm);
    blur(&g_xx, w, h, &mut bxx);
    blur(&g_xy, w, h, &mut bxy);
    (0..w * h)
        .map(|p| bm[p] + 2.0 * x[p] * bxx[p] + y[p] * bxy[p])
        .collect()
}

/// PSNR in dB of a mean squared error on [0, 1] values.
pub fn psnr(mse: f64) -> f64 {
    if mse <= 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    }
}

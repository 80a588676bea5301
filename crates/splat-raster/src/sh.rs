//! Real spherical harmonics up to degree 3 with the constants and sign conventions of the
//! INRIA 3DGS code (`computeColorFromSH`).

/// Degree-0 constant (SPEC.md §4.2: colour = `SH_C0` · dc + 0.5).
pub use profuse_formats::camera::SH_C0;
/// Degree-1 constant.
pub const SH_C1: f64 = 0.488_602_511_902_919_9;
/// Degree-2 constants.
pub const SH_C2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
/// Degree-3 constants.
pub const SH_C3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// RGB colour of one Gaussian seen along the unit direction `dir` (from the camera centre
/// to the mean): `max(0, Σ_k Y_k(dir) · sh_k + 0.5)`. `dc` is the degree-0 coefficient,
/// `rest` the higher ones coefficient-major (`rest[3 * (k - 1) + channel]`, k = 1..), at
/// least as many as `degree` needs.
pub fn eval_sh(degree: usize, dc: [f32; 3], rest: &[f32], dir: [f64; 3]) -> [f64; 3] {
    let mut out = [0.0f64; 3];
    let basis = sh_basis(degree, dir);
    for (c, o) in out.iter_mut().enumerate() {
        let mut acc = SH_C0 * f64::from(dc[c]);
        for (k, y) in basis.iter().enumerate().skip(1) {
            if k > coeffs(degree) {
                break;
            }
            acc += y * f64::from(rest[3 * (k - 1) + c]);
        }
        *o = (acc + 0.5).max(0.0);
    }
    out
}

/// Coefficients beyond DC per channel for a degree.
fn coeffs(degree: usize) -> usize {
    match degree {
        0 => 0,
        1 => 3,
        2 => 8,
        _ => 15,
    }
}

/// The 16 basis values (unused ones zero); index 0 is unused (the DC term is separate).
fn sh_basis(degree: usize, [x, y, z]: [f64; 3]) -> [f64; 16] {
    let mut b = [0.0; 16];
    if degree == 0 {
        return b;
    }
    b[1] = -SH_C1 * y;
    b[2] = SH_C1 * z;
    b[3] = -SH_C1 * x;
    if degree == 1 {
        return b;
    }
    let (xx, yy, zz) = (x * x, y * y, z * z);
    let (xy, yz, xz) = (x * y, y * z, x * z);
    b[4] = SH_C2[0] * xy;
    b[5] = SH_C2[1] * yz;
    b[6] = SH_C2[2] * (2.0 * zz - xx - yy);
    b[7] = SH_C2[3] * xz;
    b[8] = SH_C2[4] * (xx - yy);
    if degree == 2 {
        return b;
    }
    b[9] = SH_C3[0] * y * (3.0 * xx - yy);
    b[10] = SH_C3[1] * xy * z;
    b[11] = SH_C3[2] * y * (4.0 * zz - xx - yy);
    b[12] = SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
    b[13] = SH_C3[4] * x * (4.0 * zz - xx - yy);
    b[14] = SH_C3[5] * z * (xx - yy);
    b[15] = SH_C3[6] * x * (xx - 3.0 * yy);
    b
}

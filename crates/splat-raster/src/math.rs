//! The exponential of the per-pixel blend.

/// exp(x) in single precision without a libm call, so that the per-pixel loop vectorises:
/// Cody-Waite range reduction x = k ln 2 + r, |r| <= ½ ln 2, the Cephes `expf` polynomial
/// for e^r, and 2^k built in the exponent bits. Inputs are clamped to [−87.3, 88] (the
/// normal range); the relative error is below 2.5e-7 (about 2 ulp, the accuracy class of
/// CUDA's `expf`). Branch-free and deterministic.
// LN2_HI is exact (355/512); max/min rather than clamp so that NaN maps to a bound as in
// the SIMD version.
#[allow(clippy::excessive_precision, clippy::manual_clamp)]
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_375;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // 1.5 · 2^23: adding it rounds x·log2(e) to the nearest integer k, which then sits in the
    // low mantissa bits (bits = 0x4B40_0000 + k), so no float-to-int conversion is needed.
    const ROUND: f32 = 12_582_912.0;
    let x = x.max(-87.336_54).min(88.0);
    let t = x * LOG2E + ROUND;
    let k = t - ROUND;
    let r = x - k * LN2_HI - k * LN2_LO;
    let mut p = 1.987_569_1e-4f32;
    p = p * r + 1.398_199_9e-3;
    p = p * r + 8.333_452e-3;
    p = p * r + 4.166_579_6e-2;
    p = p * r + 1.666_666_5e-1;
    p = p * r + 0.5;
    let y = p * r * r + r + 1.0;
    // 2^k: biased exponent k + 127 in bits 23..31.
    let scale = f32::from_bits(t.to_bits().wrapping_sub(0x4B40_0000 - 127) << 23);
    y * scale
}

/// [`exp`] on 4 lanes at once: the same operations in the same order, so every lane is
/// bit-identical to the scalar function.
#[cfg_attr(not(test), allow(dead_code))]
#[inline(always)]
pub(crate) fn exp4(x: wide::f32x4) -> wide::f32x4 {
    use wide::f32x4;
    exp4_in_range(x.max(f32x4::splat(-87.336_54)).min(f32x4::splat(88.0)))
}

/// [`exp4`] without its clamps: bit-identical to [`exp`] for x in [−87.336_54, 88] (where
/// the clamps change nothing); other lanes get unspecified values (no trap), for callers
/// that bound x themselves or ignore those lanes.
#[allow(clippy::excessive_precision)]
#[inline(always)]
pub(crate) fn exp4_in_range(x: wide::f32x4) -> wide::f32x4 {
    use wide::{f32x4, i32x4};
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_375;
    const LN2_LO: f32 = -2.121_944_4e-4;
    const ROUND: f32 = 12_582_912.0;
    let t = x * f32x4::splat(LOG2E) + f32x4::splat(ROUND);
    let k = t - f32x4::splat(ROUND);
    let r = x - k * f32x4::splat(LN2_HI) - k * f32x4::splat(LN2_LO);
    let mut p = f32x4::splat(1.987_569_1e-4);
    p = p * r + f32x4::splat(1.398_199_9e-3);
    p = p * r + f32x4::splat(8.333_452e-3);
    p = p * r + f32x4::splat(4.166_579_6e-2);
    p = p * r + f32x4::splat(1.666_666_5e-1);
    p = p * r + f32x4::splat(0.5);
    let y = p * r * r + r + f32x4::splat(1.0);
    let bits: i32x4 = bytemuck::cast(t);
    let scale: f32x4 = bytemuck::cast((bits - i32x4::splat(0x4B40_0000 - 127)) << 23);
    y * scale
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn simd_exp_is_bit_identical_to_scalar_exp_and_accurate() {
        let mut xs: Vec<f32> = (0..200_000).map(|i| -100.0 + i as f32 * 1e-3).collect();
        xs.extend([
            0.0,
            -0.0,
            -87.336_54,
            -87.4,
            88.0,
            89.0,
            1e-30,
            -1e-30,
            f32::MIN,
        ]);
        for c in xs.chunks(4) {
            let mut a = [0.0f32; 4];
            a[..c.len()].copy_from_slice(c);
            let v = exp4(wide::f32x4::new(a)).to_array();
            let unclamped = exp4_in_range(wide::f32x4::new(a)).to_array();
            for ((x, y), u) in a.iter().zip(v).zip(unclamped) {
                let s = exp(*x);
                assert_eq!(s.to_bits(), y.to_bits(), "exp({x}): scalar {s} vs simd {y}");
                if (-87.336_54..=88.0).contains(x) {
                    assert_eq!(s.to_bits(), u.to_bits(), "exp({x}) without clamps: {u}");
                }
                if (-87.3..=88.0).contains(x) {
                    let want = f64::from(*x).exp();
                    let rel = ((f64::from(s) - want) / want).abs();
                    assert!(rel < 2.5e-7, "exp({x}) = {s}, want {want}, rel {rel:e}");
                }
            }
        }
    }
}

//! The lane types of the tile blend: the portable 4-lane `wide::f32x4` (SSE2 on any
//! x86-64, NEON on aarch64) and, on x86-64 CPUs that have it (checked at run time), a
//! 16-lane AVX-512 type whose unit is a 4 x 4 pixel block.
//!
//! Both run the same generic blend code and perform the same IEEE single-precision
//! operations in the same order on every lane (no fused multiply-add, NaN rules of min/max
//! as `wide`'s), so the rendered bytes do not depend on which one ran.

use std::ops::{Add, BitAnd, BitOr, Mul, Not, Sub};

use wide::{f32x4, CmpGe, CmpGt, CmpLe, CmpLt};

use crate::math::{exp4, exp4_in_range};

/// A vector of `N` f32 lanes and its lane mask.
pub(crate) trait Lanes:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self>
{
    /// Lane mask (one bit or one all-ones lane per lane).
    type Mask: Copy
        + BitAnd<Output = Self::Mask>
        + BitOr<Output = Self::Mask>
        + Not<Output = Self::Mask>;
    /// Number of lanes.
    const N: usize;
    fn splat(x: f32) -> Self;
    /// The first `N` values of `s` (panics if it is shorter).
    fn load(s: &[f32]) -> Self;
    /// Stores into the first `N` values of `s` (panics if it is shorter).
    fn store(self, s: &mut [f32]);
    // The general min, max and exp are the blend's reference semantics: the constant and
    // unclamped forms it runs are tested against them lane for lane.
    /// Lanewise minimum; a NaN lane of `self` gives `rhs`'s lane, a NaN lane of `rhs`
    /// gives `self`'s (as `wide`).
    #[cfg_attr(not(test), allow(dead_code))]
    fn min(self, rhs: Self) -> Self;
    /// Lanewise maximum, NaN rules as [`Lanes::min`].
    #[cfg_attr(not(test), allow(dead_code))]
    fn max(self, rhs: Self) -> Self;
    fn lt(self, rhs: Self) -> Self::Mask;
    fn le(self, rhs: Self) -> Self::Mask;
    fn gt(self, rhs: Self) -> Self::Mask;
    fn ge(self, rhs: Self) -> Self::Mask;
    /// `t` in the lanes of `m`, `f` elsewhere (bit patterns moved unchanged).
    fn select(m: Self::Mask, t: Self, f: Self) -> Self;
    /// [`crate::math::exp`] on every lane, bit-identical to it.
    #[cfg_attr(not(test), allow(dead_code))]
    fn exp(self) -> Self;
    /// [`Lanes::exp`] without its clamps: bit-identical to it on lanes in
    /// [−87.336_54, 88], unspecified values (no trap) on the others.
    fn exp_in_range(self) -> Self;
    /// [`Lanes::max`] with every lane of `rhs` equal to `c`, which is not NaN.
    fn max_c(self, c: f32) -> Self;
    /// [`Lanes::min`] with every lane of `rhs` equal to `c`, which is not NaN.
    fn min_c(self, c: f32) -> Self;
    /// Lane l holds (l mod [`UNIT_W`]) + 0.5: the pixel-centre column offsets within a
    /// blend unit.
    #[inline(always)]
    fn unit_columns() -> Self {
        Self::load(&UNIT_CENTRES[0])
    }
    /// Lane l holds ⌊l / [`UNIT_W`]⌋ + 0.5: the pixel-centre row offsets within a unit.
    #[inline(always)]
    fn unit_rows() -> Self {
        Self::load(&UNIT_CENTRES[1])
    }
    /// Writes the lanes of `m`, in lane order, to the start of `dst`, and fills the rest of
    /// its first N values with unspecified ones (panics if it holds fewer); returns how
    /// many lanes `m` has.
    fn compress_store(self, m: Self::Mask, dst: &mut [f32]) -> usize;
    /// The lanes whose bit pattern has any bit of `bits` set.
    fn any_bits(self, bits: u32) -> Self::Mask;
    /// The mask as bits, lane l in bit l.
    fn bits(m: Self::Mask) -> u32;
    /// The mask with lane l set where bit l of `bits` is (bits from N on are ignored).
    fn from_bits(bits: u32) -> Self::Mask;
    /// The lanes `first..=last` (both < N <= 16, first <= last).
    #[inline(always)]
    fn span(first: usize, last: usize) -> Self::Mask {
        Self::from_bits(bit_range(first, last))
    }
}

/// Bits `first..=last` set (`first <= last < 31`): a span of lanes, pixels or rows.
#[inline(always)]
pub(crate) const fn bit_range(first: usize, last: usize) -> u32 {
    (2u32 << last) - (1u32 << first)
}

/// Columns of a blend unit: a unit of N lanes covers `UNIT_W` adjacent pixels of each of
/// N / `UNIT_W` adjacent rows (lane l at column l mod `UNIT_W`, row ⌊l / `UNIT_W`⌋): 4 x 1
/// pixels with 4 lanes, 4 x 4 with 16. A square unit wastes fewer lanes on the small
/// footprints that dominate dense scenes than a 16 x 1 tile row does (a 3-pixel splat
/// covers 3 rows of one 4 x 4 unit, against 3 row units with 3 of 16 lanes each).
pub(crate) const UNIT_W: usize = 4;

/// Lane l's column (row 0) and row (row 1) centre offsets within a unit, for up to 16 lanes.
const UNIT_CENTRES: [[f32; 16]; 2] = {
    let mut c = [[0.0f32; 16]; 2];
    let mut l = 0;
    while l < 16 {
        c[0][l] = (l % UNIT_W) as f32 + 0.5;
        c[1][l] = (l / UNIT_W) as f32 + 0.5;
        l += 1;
    }
    c
};

/// The 4-lane masks, indexed by their bits (lane l in bit l).
const MASK4: [f32x4; 16] = {
    let mut m = [f32x4::ZERO; 16];
    let on = f32::from_bits(u32::MAX);
    let mut bits = 0;
    while bits < 16 {
        let mut v = [0.0f32; 4];
        let mut l = 0;
        while l < 4 {
            if bits & (1 << l) != 0 {
                v[l] = on;
            }
            l += 1;
        }
        m[bits] = f32x4::new(v);
        bits += 1;
    }
    m
};

impl Lanes for f32x4 {
    type Mask = f32x4;
    const N: usize = 4;

    #[inline(always)]
    fn splat(x: f32) -> Self {
        f32x4::splat(x)
    }
    #[inline(always)]
    fn load(s: &[f32]) -> Self {
        match s {
            [a, b, c, d, ..] => f32x4::new([*a, *b, *c, *d]),
            _ => panic!("a 4-lane load from {} values", s.len()),
        }
    }
    #[inline(always)]
    fn store(self, s: &mut [f32]) {
        s[..4].copy_from_slice(self.as_array_ref());
    }
    #[inline(always)]
    fn min(self, rhs: Self) -> Self {
        f32x4::min(self, rhs)
    }
    #[inline(always)]
    fn max(self, rhs: Self) -> Self {
        f32x4::max(self, rhs)
    }
    #[inline(always)]
    fn lt(self, rhs: Self) -> Self {
        self.cmp_lt(rhs)
    }
    #[inline(always)]
    fn le(self, rhs: Self) -> Self {
        self.cmp_le(rhs)
    }
    #[inline(always)]
    fn gt(self, rhs: Self) -> Self {
        self.cmp_gt(rhs)
    }
    #[inline(always)]
    fn ge(self, rhs: Self) -> Self {
        self.cmp_ge(rhs)
    }
    #[inline(always)]
    fn select(m: Self, t: Self, f: Self) -> Self {
        m.blend(t, f)
    }
    #[inline(always)]
    fn exp(self) -> Self {
        exp4(self)
    }
    #[inline(always)]
    fn exp_in_range(self) -> Self {
        exp4_in_range(self)
    }
    #[inline(always)]
    fn max_c(self, c: f32) -> Self {
        f32x4::max(self, f32x4::splat(c))
    }
    #[inline(always)]
    fn min_c(self, c: f32) -> Self {
        f32x4::min(self, f32x4::splat(c))
    }
    #[inline(always)]
    fn compress_store(self, m: Self, dst: &mut [f32]) -> usize {
        let (dst, bits) = (&mut dst[..4], Self::bits(m));
        // Every lane is written; the count only moves past the lanes of m.
        let mut n = 0;
        for (l, v) in self.to_array().into_iter().enumerate() {
            dst[n] = v;
            n += (bits >> l & 1) as usize;
        }
        n
    }
    #[inline(always)]
    fn any_bits(self, bits: u32) -> Self {
        let hit = self.to_array().map(|v| v.to_bits() & bits != 0);
        Self::from_bits(hit.iter().rev().fold(0, |m, &h| m << 1 | u32::from(h)))
    }
    #[inline(always)]
    fn bits(m: Self) -> u32 {
        m.move_mask() as u32
    }
    #[inline(always)]
    fn from_bits(bits: u32) -> Self {
        MASK4[(bits & 15) as usize]
    }
}

/// Hints the CPU to bring `value`'s cache line into all cache levels (a no-op where there
/// is no such instruction).
#[inline(always)]
pub(crate) fn prefetch<T>(value: &T) {
    #[cfg(target_arch = "x86_64")]
    #[allow(unsafe_code)]
    // SAFETY: a prefetch never faults and has no effect visible to the program; SSE is
    // part of the x86-64 baseline.
    unsafe {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        _mm_prefetch::<_MM_HINT_T0>((value as *const T).cast::<i8>());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = value;
}

/// Which lane type the blend uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Level {
    /// `wide::f32x4`, everywhere.
    Portable,
    /// [`avx512::F32x16`]; only chosen after the CPU was checked.
    #[cfg(target_arch = "x86_64")]
    Avx512,
}

impl Level {
    /// The widest level this CPU runs (AVX-512 F + DQ for the 16-lane type).
    pub(crate) fn detect() -> Level {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512dq")
        {
            return Level::Avx512;
        }
        Level::Portable
    }

    /// Number of lanes of a blend group.
    pub(crate) fn lanes(self) -> usize {
        match self {
            Level::Portable => 4,
            #[cfg(target_arch = "x86_64")]
            Level::Avx512 => 16,
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
pub(crate) mod avx512 {
    //! The 16-lane type. Its operations call AVX-512 intrinsics without checking the CPU:
    //! they are only reached through functions compiled with `#[target_feature(enable =
    //! "avx512f,avx512dq")]`, which are only called after [`super::Level::detect`] found
    //! both features (the SAFETY argument of every `unsafe` block below).

    use std::arch::x86_64::*;
    use std::ops::{Add, Mul, Sub};

    use super::Lanes;

    #[derive(Debug, Clone, Copy)]
    pub(crate) struct F32x16(__m512);

    /// A 16-lane mask.
    #[derive(Debug, Clone, Copy)]
    pub(crate) struct M16(pub(crate) u16);

    impl std::ops::BitAnd for M16 {
        type Output = M16;
        #[inline(always)]
        fn bitand(self, o: M16) -> M16 {
            M16(self.0 & o.0)
        }
    }
    impl std::ops::BitOr for M16 {
        type Output = M16;
        #[inline(always)]
        fn bitor(self, o: M16) -> M16 {
            M16(self.0 | o.0)
        }
    }
    impl std::ops::Not for M16 {
        type Output = M16;
        #[inline(always)]
        fn not(self) -> M16 {
            M16(!self.0)
        }
    }

    macro_rules! binop {
        ($tr:ident, $f:ident, $intr:ident) => {
            impl $tr for F32x16 {
                type Output = F32x16;
                #[inline(always)]
                fn $f(self, o: F32x16) -> F32x16 {
                    // SAFETY: see the module doc.
                    F32x16(unsafe { $intr(self.0, o.0) })
                }
            }
        };
    }
    binop!(Add, add, _mm512_add_ps);
    binop!(Sub, sub, _mm512_sub_ps);
    binop!(Mul, mul, _mm512_mul_ps);

    impl F32x16 {
        #[inline(always)]
        fn cmp<const P: i32>(self, o: F32x16) -> M16 {
            // SAFETY: see the module doc.
            M16(unsafe { _mm512_cmp_ps_mask::<P>(self.0, o.0) })
        }
        #[inline(always)]
        fn is_nan(self) -> M16 {
            self.cmp::<_CMP_UNORD_Q>(self)
        }
    }

    impl Lanes for F32x16 {
        type Mask = M16;
        const N: usize = 16;

        #[inline(always)]
        fn splat(x: f32) -> Self {
            // SAFETY: see the module doc.
            F32x16(unsafe { _mm512_set1_ps(x) })
        }
        #[inline(always)]
        fn load(s: &[f32]) -> Self {
            let s = &s[..16];
            // SAFETY: 16 readable values (checked above); the feature, see the module doc.
            F32x16(unsafe { _mm512_loadu_ps(s.as_ptr()) })
        }
        #[inline(always)]
        fn store(self, s: &mut [f32]) {
            let s = &mut s[..16];
            // SAFETY: 16 writable values (checked above); the feature, see the module doc.
            unsafe { _mm512_storeu_ps(s.as_mut_ptr(), self.0) }
        }
        #[inline(always)]
        fn min(self, rhs: Self) -> Self {
            // vminps returns its second operand where either is NaN; `wide` then keeps
            // self where rhs is NaN.
            // SAFETY: see the module doc.
            let m = F32x16(unsafe { _mm512_min_ps(self.0, rhs.0) });
            Self::select(rhs.is_nan(), self, m)
        }
        #[inline(always)]
        fn max(self, rhs: Self) -> Self {
            // SAFETY: see the module doc.
            let m = F32x16(unsafe { _mm512_max_ps(self.0, rhs.0) });
            Self::select(rhs.is_nan(), self, m)
        }
        #[inline(always)]
        fn lt(self, rhs: Self) -> M16 {
            self.cmp::<_CMP_LT_OQ>(rhs)
        }
        #[inline(always)]
        fn le(self, rhs: Self) -> M16 {
            self.cmp::<_CMP_LE_OQ>(rhs)
        }
        #[inline(always)]
        fn gt(self, rhs: Self) -> M16 {
            self.cmp::<_CMP_GT_OQ>(rhs)
        }
        #[inline(always)]
        fn ge(self, rhs: Self) -> M16 {
            self.cmp::<_CMP_GE_OQ>(rhs)
        }
        #[inline(always)]
        fn select(m: M16, t: Self, f: Self) -> Self {
            // SAFETY: see the module doc.
            F32x16(unsafe { _mm512_mask_blend_ps(m.0, f.0, t.0) })
        }
        #[inline(always)]
        fn max_c(self, c: f32) -> Self {
            // vmaxps returns its second operand where either is NaN: `c` where self is,
            // as `wide`, and `c` is never NaN.
            // SAFETY: see the module doc.
            F32x16(unsafe { _mm512_max_ps(self.0, _mm512_set1_ps(c)) })
        }
        #[inline(always)]
        fn min_c(self, c: f32) -> Self {
            // SAFETY: see the module doc.
            F32x16(unsafe { _mm512_min_ps(self.0, _mm512_set1_ps(c)) })
        }
        #[inline(always)]
        fn exp(self) -> Self {
            self.max_c(-87.336_54).min_c(88.0).exp_in_range()
        }
        #[inline(always)]
        #[allow(clippy::excessive_precision)]
        fn exp_in_range(self) -> Self {
            // The operations of `math::exp` after its clamps, in its order.
            const LOG2E: f32 = std::f32::consts::LOG2_E;
            const LN2_HI: f32 = 0.693_359_375;
            const LN2_LO: f32 = -2.121_944_4e-4;
            const ROUND: f32 = 12_582_912.0;
            let s = Self::splat;
            let x = self;
            let t = x * s(LOG2E) + s(ROUND);
            let k = t - s(ROUND);
            let r = x - k * s(LN2_HI) - k * s(LN2_LO);
            let mut p = s(1.987_569_1e-4);
            p = p * r + s(1.398_199_9e-3);
            p = p * r + s(8.333_452e-3);
            p = p * r + s(4.166_579_6e-2);
            p = p * r + s(1.666_666_5e-1);
            p = p * r + s(0.5);
            let y = p * r * r + r + s(1.0);
            // SAFETY: see the module doc.
            let scale = unsafe {
                let bits = _mm512_castps_si512(t.0);
                let e = _mm512_sub_epi32(bits, _mm512_set1_epi32(0x4B40_0000 - 127));
                F32x16(_mm512_castsi512_ps(_mm512_slli_epi32::<23>(e)))
            };
            y * scale
        }
        #[inline(always)]
        fn compress_store(self, m: M16, dst: &mut [f32]) -> usize {
            let dst = &mut dst[..16];
            // The register form and a plain store: the memory form of vcompressps is
            // microcoded on some CPUs (Zen 4), tens of times slower.
            // SAFETY: 16 writable values (checked above); the feature, see the module doc.
            unsafe {
                let packed = _mm512_maskz_compress_ps(m.0, self.0);
                _mm512_storeu_ps(dst.as_mut_ptr(), packed);
            }
            m.0.count_ones() as usize
        }
        #[inline(always)]
        fn any_bits(self, bits: u32) -> M16 {
            // SAFETY: see the module doc.
            M16(unsafe {
                _mm512_test_epi32_mask(_mm512_castps_si512(self.0), _mm512_set1_epi32(bits as i32))
            })
        }
        #[inline(always)]
        fn bits(m: M16) -> u32 {
            u32::from(m.0)
        }
        #[inline(always)]
        fn from_bits(bits: u32) -> M16 {
            M16(bits as u16)
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// Every operation of the 16-lane type against the portable one, lane by lane, bit for
    /// bit (skipped on CPUs without AVX-512).
    #[cfg(target_arch = "x86_64")]
    #[allow(unsafe_code)]
    #[test]
    fn avx512_lanes_equal_portable_lanes_bit_for_bit() {
        if Level::detect() != Level::Avx512 {
            eprintln!("skipped: this CPU has no AVX-512 F + DQ");
            return;
        }
        // SAFETY: the features were detected above.
        unsafe { compare_avx512() }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512dq")]
    fn compare_avx512() {
        use avx512::F32x16;
        let mut xs: Vec<f32> = (0..100_000).map(|i| -100.0 + i as f32 * 1.9e-3).collect();
        xs.extend([
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            0.0,
            -0.0,
            1e-40,
            88.5,
            -87.5,
            0.99,
            1e-4,
        ]);
        while !xs.len().is_multiple_of(16) {
            xs.push(0.25);
        }
        let ys: Vec<f32> = xs.iter().rev().copied().collect();
        let bits4 = |v: f32x4| v.to_array().map(f32::to_bits);
        for (x, y) in xs.chunks_exact(16).zip(ys.chunks_exact(16)) {
            let (a, b) = (F32x16::load(x), F32x16::load(y));
            let wide: [F32x16; 11] = [
                a + b,
                a - b,
                a * b,
                a.min(b),
                a.max(b),
                a.exp(),
                {
                    let m = a.lt(b) | (a.ge(b) & b.le(a) & !a.gt(b));
                    F32x16::select(m, a, b)
                },
                a.max_c(-40.0),
                a.min_c(0.99),
                a.max_c(-40.0).min_c(0.0).exp_in_range(),
                F32x16::select(
                    F32x16::from_bits(0x5A5A),
                    F32x16::splat(1.0),
                    F32x16::splat(0.0),
                ),
            ];
            for (q, (x4, y4)) in x.chunks_exact(4).zip(y.chunks_exact(4)).enumerate() {
                let (a4, b4) = (f32x4::load(x4), f32x4::load(y4));
                let m4 = a4.lt(b4) | (a4.ge(b4) & b4.le(a4) & !a4.gt(b4));
                let narrow = [
                    a4 + b4,
                    a4 - b4,
                    a4 * b4,
                    Lanes::min(a4, b4),
                    Lanes::max(a4, b4),
                    Lanes::exp(a4),
                    f32x4::select(m4, a4, b4),
                    // The constant forms equal the general ones (NaN rules included).
                    Lanes::max(a4, f32x4::splat(-40.0)),
                    Lanes::min(a4, f32x4::splat(0.99)),
                    // exp without clamps equals exp where the input is in range.
                    Lanes::exp(a4.max_c(-40.0).min_c(0.0)),
                    f32x4::select(
                        f32x4::from_bits((0x5A5A >> (4 * q)) & 15),
                        f32x4::splat(1.0),
                        f32x4::splat(0.0),
                    ),
                ];
                for (w, n) in wide.iter().zip(narrow) {
                    let mut out = [0.0f32; 16];
                    w.store(&mut out);
                    let got: [u32; 4] = std::array::from_fn(|l| out[q * 4 + l].to_bits());
                    assert_eq!(got, bits4(n), "inputs {x4:?} {y4:?}");
                }
            }
        }
        for first in 0..16 {
            for last in first..16 {
                let bits = F32x16::bits(F32x16::span(first, last));
                let expected: u32 = (first..=last).map(|l| 1u32 << l).sum();
                assert_eq!(bits, expected, "span {first}..={last}");
            }
        }
        for bits in [0u32, 1, 0x8000, 0xFFFF, 0x5A5A, 0x1234] {
            assert_eq!(F32x16::bits(F32x16::from_bits(bits)), bits);
        }
        // Packing and bit tests against the portable lanes, four at a time.
        let patterns: Vec<f32> = (0..16u32)
            .map(|l| f32::from_bits(l * 0x0101_0011))
            .collect();
        for mask in [0u32, 1, 0x8000, 0xFFFF, 0x5A5A, 0x1234, 0x0F0F] {
            let mut wide = [f32::NAN; 16];
            let n = F32x16::load(&xs[..16]).compress_store(F32x16::from_bits(mask), &mut wide);
            let (mut narrow, mut m) = ([f32::NAN; 20], 0);
            for q in 0..4 {
                let lanes = f32x4::load(&xs[4 * q..]);
                m += lanes.compress_store(f32x4::from_bits(mask >> (4 * q)), &mut narrow[m..]);
            }
            assert_eq!(n, mask.count_ones() as usize);
            assert_eq!(
                (n, wide[..n].to_vec()),
                (m, narrow[..m].to_vec()),
                "{mask:#x}"
            );
        }
        for bit in [1u32, 0x10, 0x100, 0x8000, 0x1_0000, 0x8000_0000] {
            let wide = F32x16::bits(F32x16::load(&patterns).any_bits(bit));
            let narrow = (0..4).fold(0, |acc, q| {
                let m = f32x4::bits(f32x4::load(&patterns[4 * q..]).any_bits(bit));
                acc | m << (4 * q)
            });
            let want = (0..16).fold(0, |acc, l| {
                acc | u32::from(patterns[l].to_bits() & bit != 0) << l
            });
            assert_eq!((wide, narrow), (want, want), "{bit:#x}");
        }
        let (mut c, mut r) = ([0.0f32; 16], [0.0f32; 16]);
        F32x16::unit_columns().store(&mut c);
        F32x16::unit_rows().store(&mut r);
        assert_eq!((c[0], c[3], c[4], c[15]), (0.5, 3.5, 0.5, 3.5));
        assert_eq!((r[0], r[3], r[4], r[15]), (0.5, 0.5, 1.5, 3.5));
    }

    #[test]
    fn portable_spans_and_masks_round_trip() {
        for first in 0..4 {
            for last in first..4 {
                let m = f32x4::span(first, last);
                let expected: u32 = (first..=last).map(|l| 1u32 << l).sum();
                assert_eq!(f32x4::bits(m), expected);
            }
        }
        for bits in 0..16 {
            assert_eq!(f32x4::bits(f32x4::from_bits(bits)), bits);
        }
        // Four lanes make a 4 x 1 unit: one row.
        let (mut c, mut r) = ([0.0f32; 4], [0.0f32; 4]);
        f32x4::unit_columns().store(&mut c);
        f32x4::unit_rows().store(&mut r);
        assert_eq!(c, [0.5, 1.5, 2.5, 3.5]);
        assert_eq!(r, [0.5; 4]);
    }
}

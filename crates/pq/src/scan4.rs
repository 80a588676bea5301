//! The 4-bit scan of [`crate::FastScan`]: 16-entry u8 lookup tables held in SIMD
//! registers and indexed by byte shuffles, 32 vectors a block.
//!
//! Layout (built once per pq by `FastScan::new`): a block of 32 vectors holds, for every
//! pair `p` of sub-quantisers, 32 bytes; the byte of vector `v` sits at
//! [`byte_of_vector`]`(v)` and carries the 4-bit code of sub-quantiser `2p` in its low
//! nibble and that of `2p + 1` in its high nibble. The position puts vectors `w` and
//! `w + 16` in the two bytes of 16-bit word `w`, so after the lookups the low bytes of
//! the words are vectors 0..16 in order and the high bytes vectors 16..32: widening to
//! u16 needs one mask and one shift, and the scores come out in vector order.
//!
//! Tables: `lo[p]` is the 16 entries of sub-quantiser `2p` twice (32 bytes, one copy per
//! 128-bit lane, since byte shuffles do not cross lanes), `hi[p]` those of `2p + 1`.
//! Entries are at most 127, so the two lookups of a pair add in u8 without overflow;
//! pairs add in u16, and the caller keeps `pairs x 254 <= 65535`.
//!
//! Every kernel computes integer sums, so the AVX-512, AVX2 and portable kernels give the
//! same scores (tested).

/// Vectors per block.
pub(crate) const BLOCK: usize = 32;

/// Byte position of vector `v` (0..32) inside a pair's 32 bytes.
pub(crate) fn byte_of_vector(v: usize) -> usize {
    2 * (v % 16) + v / 16
}

/// Which kernel scans: chosen at run time from the CPU's features.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Kernel {
    Portable,
    #[cfg(target_arch = "x86_64")]
    Avx2,
    #[cfg(target_arch = "x86_64")]
    Avx512,
}

impl Kernel {
    /// The widest kernel this CPU runs.
    pub(crate) fn detect() -> Kernel {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512bw") {
                return Kernel::Avx512;
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                return Kernel::Avx2;
            }
        }
        Kernel::Portable
    }

    /// Name for reports.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Kernel::Portable => "portable",
            #[cfg(target_arch = "x86_64")]
            Kernel::Avx2 => "avx2",
            #[cfg(target_arch = "x86_64")]
            Kernel::Avx512 => "avx512",
        }
    }
}

/// Scores every block of `packed` (`blocks x pairs x 32` bytes) into `scores` (32 a
/// block) and each block's largest score into `maxima`.
///
/// # Panics
/// If the lengths disagree, `pairs` is odd, or the kernel is not supported by this CPU.
pub(crate) fn scan(
    kernel: Kernel,
    packed: &[u8],
    lo: &[u8],
    hi: &[u8],
    pairs: usize,
    scores: &mut [u16],
    maxima: &mut [u16],
) {
    let blocks = maxima.len();
    assert!(pairs.is_multiple_of(2), "pairs are scanned two at a time");
    assert_eq!(packed.len(), blocks * pairs * BLOCK, "packed length");
    assert_eq!(scores.len(), blocks * BLOCK, "scores length");
    assert_eq!(lo.len(), pairs * BLOCK, "low table length");
    assert_eq!(hi.len(), pairs * BLOCK, "high table length");
    match kernel {
        Kernel::Portable => portable(packed, lo, hi, pairs, scores, maxima),
        #[cfg(target_arch = "x86_64")]
        Kernel::Avx2 => x86::avx2(packed, lo, hi, pairs, scores, maxima),
        #[cfg(target_arch = "x86_64")]
        Kernel::Avx512 => x86::avx512(packed, lo, hi, pairs, scores, maxima),
    }
}

fn portable(
    packed: &[u8],
    lo: &[u8],
    hi: &[u8],
    pairs: usize,
    scores: &mut [u16],
    maxima: &mut [u16],
) {
    for ((block, out), max) in packed
        .chunks_exact(pairs * BLOCK)
        .zip(scores.chunks_exact_mut(BLOCK))
        .zip(maxima.iter_mut())
    {
        for (v, o) in out.iter_mut().enumerate() {
            let at = byte_of_vector(v);
            *o = (0..pairs)
                .map(|p| {
                    let byte = block[p * BLOCK + at];
                    u16::from(lo[p * BLOCK + usize::from(byte & 15)])
                        + u16::from(hi[p * BLOCK + usize::from(byte >> 4)])
                })
                .sum();
        }
        *max = out.iter().copied().max().unwrap_or(0);
    }
}

#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod x86 {
    use std::arch::x86_64::*;

    use super::BLOCK;

    pub(super) fn avx2(
        packed: &[u8],
        lo: &[u8],
        hi: &[u8],
        pairs: usize,
        scores: &mut [u16],
        maxima: &mut [u16],
    ) {
        assert!(std::arch::is_x86_feature_detected!("avx2"));
        // SAFETY: AVX2 is present (checked above); `scan` checked every length.
        unsafe { avx2_blocks(packed, lo, hi, pairs, scores, maxima) }
    }

    pub(super) fn avx512(
        packed: &[u8],
        lo: &[u8],
        hi: &[u8],
        pairs: usize,
        scores: &mut [u16],
        maxima: &mut [u16],
    ) {
        assert!(std::arch::is_x86_feature_detected!("avx512bw"));
        // SAFETY: AVX-512 F and BW are present (checked above); `scan` checked every length.
        unsafe { avx512_blocks(packed, lo, hi, pairs, scores, maxima) }
    }

    /// # Safety
    /// AVX2 is present; `packed` holds `maxima.len()` blocks of `pairs x 32` bytes,
    /// `scores` 32 values a block, `lo` and `hi` `pairs x 32` bytes.
    #[target_feature(enable = "avx2")]
    unsafe fn avx2_blocks(
        packed: &[u8],
        lo: &[u8],
        hi: &[u8],
        pairs: usize,
        scores: &mut [u16],
        maxima: &mut [u16],
    ) {
        let nibble = _mm256_set1_epi8(0x0f);
        let low_byte = _mm256_set1_epi16(0x00ff);
        for ((block, out), max) in packed
            .chunks_exact(pairs * BLOCK)
            .zip(scores.chunks_exact_mut(BLOCK))
            .zip(maxima.iter_mut())
        {
            let (mut first, mut second) = (_mm256_setzero_si256(), _mm256_setzero_si256());
            for p in 0..pairs {
                // SAFETY: p < pairs, so every load reads 32 bytes inside its slice.
                let (x, tl, th) = unsafe {
                    (
                        _mm256_loadu_si256(block.as_ptr().add(p * BLOCK).cast()),
                        _mm256_loadu_si256(lo.as_ptr().add(p * BLOCK).cast()),
                        _mm256_loadu_si256(hi.as_ptr().add(p * BLOCK).cast()),
                    )
                };
                let low = _mm256_and_si256(x, nibble);
                let high = _mm256_and_si256(_mm256_srli_epi16::<4>(x), nibble);
                let r =
                    _mm256_add_epi8(_mm256_shuffle_epi8(tl, low), _mm256_shuffle_epi8(th, high));
                first = _mm256_add_epi16(first, _mm256_and_si256(r, low_byte));
                second = _mm256_add_epi16(second, _mm256_srli_epi16::<8>(r));
            }
            *max = store_block(out, first, second);
        }
    }

    /// # Safety
    /// As [`avx2_blocks`], with AVX-512 F and BW instead of AVX2 and `pairs` even.
    #[target_feature(enable = "avx512f,avx512bw,avx2")]
    unsafe fn avx512_blocks(
        packed: &[u8],
        lo: &[u8],
        hi: &[u8],
        pairs: usize,
        scores: &mut [u16],
        maxima: &mut [u16],
    ) {
        let nibble = _mm512_set1_epi8(0x0f);
        for ((block, out), max) in packed
            .chunks_exact(pairs * BLOCK)
            .zip(scores.chunks_exact_mut(BLOCK))
            .zip(maxima.iter_mut())
        {
            // Two pairs a register: lanes 0-1 hold pair p, lanes 2-3 pair p + 1.
            let (mut words, mut second) = (_mm512_setzero_si512(), _mm512_setzero_si512());
            let mut p = 0;
            while p < pairs {
                // SAFETY: p + 2 <= pairs, so every load reads 64 bytes inside its slice.
                let (x, tl, th) = unsafe {
                    (
                        _mm512_loadu_si512(block.as_ptr().add(p * BLOCK).cast()),
                        _mm512_loadu_si512(lo.as_ptr().add(p * BLOCK).cast()),
                        _mm512_loadu_si512(hi.as_ptr().add(p * BLOCK).cast()),
                    )
                };
                let low = _mm512_and_si512(x, nibble);
                let high = _mm512_and_si512(_mm512_srli_epi16::<4>(x), nibble);
                let r =
                    _mm512_add_epi8(_mm512_shuffle_epi8(tl, low), _mm512_shuffle_epi8(th, high));
                // Whole words (low byte + 256 x high byte, modulo 2^16) and the high
                // bytes; the low bytes' sum is recovered once a block, below, instead of
                // masking every step.
                words = _mm512_add_epi16(words, r);
                second = _mm512_add_epi16(second, _mm512_srli_epi16::<8>(r));
                p += 2;
            }
            // Low sum = words − 256 x high sum (mod 2^16, exact: the low sum < 2^16).
            let first = _mm512_sub_epi16(words, _mm512_slli_epi16::<8>(second));
            let fold = |v: __m512i| {
                _mm256_add_epi16(_mm512_castsi512_si256(v), _mm512_extracti64x4_epi64::<1>(v))
            };
            let (first, second) = (fold(first), fold(second));
            *max = store_block(out, first, second);
        }
    }

    /// Stores a block's 32 scores (vectors 0..16, then 16..32) and returns the largest.
    #[target_feature(enable = "avx2")]
    fn store_block(out: &mut [u16], first: __m256i, second: __m256i) -> u16 {
        assert!(out.len() >= 32);
        // SAFETY: `out` holds at least 32 u16 = two 256-bit stores.
        unsafe {
            _mm256_storeu_si256(out.as_mut_ptr().cast(), first);
            _mm256_storeu_si256(out.as_mut_ptr().add(16).cast(), second);
        }
        max_u16(_mm256_max_epu16(first, second))
    }

    /// Largest of 16 u16 lanes: `minpos` finds the smallest of 8, so it runs on the
    /// complements.
    #[target_feature(enable = "avx2")]
    fn max_u16(v: __m256i) -> u16 {
        let half = _mm_max_epu16(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
        let ones = _mm_set1_epi16(-1);
        let min_of_complement = _mm_minpos_epu16(_mm_xor_si128(half, ones));
        !(_mm_extract_epi16::<0>(min_of_complement) as u16)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pseudo(i: usize) -> u8 {
        ((i.wrapping_mul(2_654_435_761) >> 13) & 0xff) as u8
    }

    #[test]
    fn positions_are_a_permutation_putting_v_and_v_plus_16_in_one_word() {
        let mut seen = [false; BLOCK];
        for v in 0..BLOCK {
            seen[byte_of_vector(v)] = true;
        }
        assert!(seen.iter().all(|&s| s));
        for w in 0..16 {
            assert_eq!(byte_of_vector(w), 2 * w);
            assert_eq!(byte_of_vector(w + 16), 2 * w + 1);
        }
    }

    #[test]
    fn portable_scores_are_table_sums() {
        let pairs = 2;
        let packed: Vec<u8> = (0..pairs * BLOCK).map(pseudo).collect();
        let table = |p: usize, hi: bool| -> Vec<u8> {
            let one: Vec<u8> = (0..16)
                .map(|j| ((p * 31 + j * 7 + usize::from(hi) * 3) % 128) as u8)
                .collect();
            one.iter().chain(&one).copied().collect()
        };
        let lo: Vec<u8> = (0..pairs).flat_map(|p| table(p, false)).collect();
        let hi: Vec<u8> = (0..pairs).flat_map(|p| table(p, true)).collect();
        let (mut s, mut m) = (vec![0u16; BLOCK], vec![0u16; 1]);
        scan(Kernel::Portable, &packed, &lo, &hi, pairs, &mut s, &mut m);
        for v in 0..BLOCK {
            let mut want = 0u16;
            for p in 0..pairs {
                let b = packed[p * BLOCK + byte_of_vector(v)];
                want += u16::from(table(p, false)[usize::from(b & 15)]);
                want += u16::from(table(p, true)[usize::from(b >> 4)]);
            }
            assert_eq!(s[v], want, "vector {v}");
        }
        assert_eq!(m[0], *s.iter().max().unwrap_or(&0));
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn simd_kernels_give_the_portable_scores() {
        // Entries up to 127 and 256 pairs reach 65,024, near the u16 limit.
        for (pairs, blocks) in [(2usize, 1usize), (4, 3), (64, 5), (256, 2)] {
            let packed: Vec<u8> = (0..blocks * pairs * BLOCK).map(|i| pseudo(i + 7)).collect();
            // 16 entries per sub-quantiser, copied into both 128-bit lanes.
            let lanes = |salt: usize| -> Vec<u8> {
                (0..pairs * BLOCK)
                    .map(|i| {
                        let entry = (i / BLOCK) * 16 + i % 16;
                        if pairs == 256 {
                            127
                        } else {
                            pseudo(entry + salt) & 127
                        }
                    })
                    .collect()
            };
            let (lo, hi) = (lanes(0), lanes(999));
            let (mut want, mut want_max) = (vec![0u16; blocks * BLOCK], vec![0u16; blocks]);
            scan(
                Kernel::Portable,
                &packed,
                &lo,
                &hi,
                pairs,
                &mut want,
                &mut want_max,
            );
            let mut kernels = Vec::new();
            if std::arch::is_x86_feature_detected!("avx2") {
                kernels.push(Kernel::Avx2);
            }
            if std::arch::is_x86_feature_detected!("avx512bw") {
                kernels.push(Kernel::Avx512);
            }
            for k in kernels {
                let (mut got, mut got_max) = (vec![0u16; blocks * BLOCK], vec![0u16; blocks]);
                scan(k, &packed, &lo, &hi, pairs, &mut got, &mut got_max);
                assert_eq!(got, want, "{} pairs {pairs}", k.name());
                assert_eq!(got_max, want_max, "{} pairs {pairs}", k.name());
            }
        }
    }
}

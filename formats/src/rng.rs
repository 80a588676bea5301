//! The one seeded generator of the workspace: SplitMix64 (Steele, Lea, Flood 2014; Vigna's
//! `splitmix64.c`), with the few draws the stages need.
//!
//! The stages' synthetic data, samples and tie-breaks must never change with a
//! third-party crate's version or with thread scheduling, so they derive every stream from
//! a key of their own (seed, purpose, index) and draw from this generator. How a crate
//! turns its key into a starting state stays with the crate: the written bytes depend on
//! it, and the crates' keyings differ. Lives in the formats crate next to [`crate::camera`]
//! because it is the one dependency-free crate every stage already uses.
//!
//! # Example
//!
//! ```
//! use profuse_formats::rng::{splitmix64, SplitMix64};
//!
//! // Vigna's reference output for state 0.
//! let mut rng = SplitMix64::new(0);
//! assert_eq!(rng.next_u64(), 0xE220_A839_7B1D_CDAF);
//! assert_eq!(splitmix64(0), 0xE220_A839_7B1D_CDAF);
//! let u = rng.unit();
//! assert!((0.0..1.0).contains(&u));
//! assert!(rng.below(10) < 10);
//! ```

/// The increment of SplitMix64's counter (2⁶⁴ / φ, odd).
pub const GOLDEN_GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

/// SplitMix64's output function: a bijection on u64 with good avalanche (the
/// `splitmix64` step without the counter increment).
#[inline]
pub const fn splitmix64_mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// One full SplitMix64 step of state `z`: the mix of `z + GOLDEN_GAMMA`. As a hash of a
/// word it keys streams by counters and indices.
#[inline]
pub const fn splitmix64(z: u64) -> u64 {
    splitmix64_mix(z.wrapping_add(GOLDEN_GAMMA))
}

/// A uniform number in [0, 1) from the top 53 bits of a word.
#[inline]
pub fn unit_from_bits(x: u64) -> f64 {
    (x >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// A SplitMix64 stream.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SplitMix64 {
    state: u64,
}

impl SplitMix64 {
    /// The stream starting after `state` (its first output is [`splitmix64`]`(state)`).
    pub const fn new(state: u64) -> Self {
        SplitMix64 { state }
    }

    /// The next 64 random bits.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(GOLDEN_GAMMA);
        splitmix64_mix(self.state)
    }

    /// Uniform in [0, 1) with 53 random bits.
    #[inline]
    pub fn unit(&mut self) -> f64 {
        unit_from_bits(self.next_u64())
    }

    /// Uniform integer in `0..n` (n >= 1) by Lemire's multiply-high: bias below n / 2⁶⁴.
    #[inline]
    pub fn below(&mut self, n: usize) -> usize {
        ((u128::from(self.next_u64()) * n as u128) >> 64) as usize
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Vigna's `splitmix64.c`, written out independently: x += γ; z = x; two xor-shift
    /// multiplies; final xor-shift.
    fn reference(x: &mut u64) -> u64 {
        *x = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = *x;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    #[test]
    fn stream_equals_the_reference_algorithm_and_known_outputs() {
        // Published first outputs for seed 0 (e.g. the test vectors of Java's
        // SplittableRandom-compatible ports).
        let mut r = SplitMix64::new(0);
        let first: Vec<u64> = (0..3).map(|_| r.next_u64()).collect();
        assert_eq!(
            first,
            [
                0xE220_A839_7B1D_CDAF,
                0x6E78_9E6A_A1B9_65F4,
                0x06C4_5D18_8009_454F
            ]
        );
        for seed in [1u64, 42, u64::MAX, 0x0123_4567_89AB_CDEF] {
            let (mut a, mut x) = (SplitMix64::new(seed), seed);
            for _ in 0..100 {
                assert_eq!(a.next_u64(), reference(&mut x));
            }
            assert_eq!(splitmix64(seed), reference(&mut seed.clone()));
        }
    }

    #[test]
    fn draws_stay_in_range_and_are_roughly_uniform() {
        let mut r = SplitMix64::new(7);
        let n = 20_000;
        let u: Vec<f64> = (0..n).map(|_| r.unit()).collect();
        assert!(u.iter().all(|x| (0.0..1.0).contains(x)));
        let mean = u.iter().sum::<f64>() / n as f64;
        assert!((mean - 0.5).abs() < 0.01, "{mean}");
        let mut counts = [0usize; 7];
        for _ in 0..n {
            counts[r.below(7)] += 1;
        }
        // Each of 7 bins expects n/7 ≈ 2857 (sd ≈ 50).
        assert!(
            counts.iter().all(|&c| c.abs_diff(n / 7) < 300),
            "{counts:?}"
        );
        assert_eq!(unit_from_bits(u64::MAX), 1.0 - f64::EPSILON / 2.0);
        assert_eq!(unit_from_bits(0), 0.0);
    }
}

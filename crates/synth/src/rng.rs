//! Seeded randomness that never depends on a third-party crate's version or on thread
//! scheduling: SplitMix64 streams whose state is derived by hashing a *key* (seed, purpose,
//! indices). Every random decision of the generator is a pure function of its key. The
//! generator is the workspace's one SplitMix64 ([`profuse_formats::rng`]); the keying is
//! this crate's own (the written scenes depend on it).

use profuse_formats::rng::{splitmix64 as mix, unit_from_bits, SplitMix64};

/// Hashes a sequence of words into one 64-bit key (order-sensitive).
pub(crate) fn key(parts: &[u64]) -> u64 {
    let mut h = 0x243F_6A88_85A3_08D3_u64;
    for p in parts {
        h = mix(h.rotate_left(23) ^ mix(*p));
    }
    h
}

/// A uniform number in [0, 1) from a key (53 random bits).
pub(crate) fn unit(parts: &[u64]) -> f64 {
    unit_from_bits(key(parts))
}

/// 64-bit FNV-1a of a string, to key randomness by names.
pub(crate) fn name_hash(s: &str) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325_u64;
    for b in s.bytes() {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// Purposes, so that streams of different decisions never share a key.
pub(crate) mod tag {
    pub const LAYOUT: u64 = 1;
    pub const CAMERAS: u64 = 2;
    pub const PROTOTYPE: u64 = 3;
    pub const PROMPT: u64 = 4;
    pub const DROP: u64 = 10;
    pub const MERGE: u64 = 11;
    pub const SPLIT: u64 = 12;
    pub const JITTER: u64 = 13;
    pub const UNASSIGNED: u64 = 14;
    pub const FEATURE: u64 = 15;
    pub const WRONG_CLASS: u64 = 16;
    pub const CERTAINTY: u64 = 20;
    pub const WARP_NOISE: u64 = 21;
    pub const OUTLIER: u64 = 22;
    pub const GAUSSIANS: u64 = 30;
}

/// A SplitMix64 stream with a spare normal.
#[derive(Debug, Clone)]
pub(crate) struct Rng {
    stream: SplitMix64,
    spare: Option<f64>,
}

impl Rng {
    /// The stream of a key.
    pub(crate) fn new(parts: &[u64]) -> Self {
        Rng {
            stream: SplitMix64::new(key(parts)),
            spare: None,
        }
    }

    /// Uniform in [0, 1).
    pub(crate) fn unit(&mut self) -> f64 {
        self.stream.unit()
    }

    /// Uniform in [lo, hi).
    pub(crate) fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    /// Uniform integer in 0..n (n >= 1), by multiply-shift (bias below 2^-32 for our n).
    pub(crate) fn below(&mut self, n: usize) -> usize {
        self.stream.below(n)
    }

    /// Standard normal (Box–Muller, both values used).
    pub(crate) fn normal(&mut self) -> f64 {
        if let Some(s) = self.spare.take() {
            return s;
        }
        let u1 = 1.0 - self.unit(); // (0, 1]
        let u2 = self.unit();
        let r = (-2.0 * u1.ln()).sqrt();
        let a = std::f64::consts::TAU * u2;
        self.spare = Some(r * a.sin());
        r * a.cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_are_reproducible_and_distinct() {
        let mut a = Rng::new(&[1, 2, 3]);
        let mut b = Rng::new(&[1, 2, 3]);
        let mut c = Rng::new(&[1, 3, 2]);
        let xa: Vec<u64> = (0..4).map(|_| a.stream.next_u64()).collect();
        let xb: Vec<u64> = (0..4).map(|_| b.stream.next_u64()).collect();
        let xc: Vec<u64> = (0..4).map(|_| c.stream.next_u64()).collect();
        assert_eq!(xa, xb);
        assert_ne!(xa, xc);
    }

    #[test]
    fn normal_has_unit_variance() {
        let mut r = Rng::new(&[7]);
        let n = 20000;
        let v: Vec<f64> = (0..n).map(|_| r.normal()).collect();
        let mean = v.iter().sum::<f64>() / n as f64;
        let var = v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / n as f64;
        assert!(mean.abs() < 0.03, "{mean}");
        assert!((var - 1.0).abs() < 0.05, "{var}");
        let u: Vec<f64> = (0..n).map(|_| r.unit()).collect();
        assert!(u.iter().all(|x| (0.0..1.0).contains(x)));
        assert!((0..1000).all(|_| r.below(3) < 3));
    }
}

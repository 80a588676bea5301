//! SplitMix64 streams keyed by (seed, purpose, index): every random decision depends only
//! on its key, never on thread scheduling or on a third-party RNG's version.

/// SplitMix64's finaliser (a bijection on u64 with good avalanche).
const fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Purposes, so that streams of different decisions never coincide.
pub(crate) mod purpose {
    pub const KMEANS: u64 = 1;
    pub const SAMPLE: u64 = 2;
}

/// A SplitMix64 generator.
#[derive(Debug, Clone)]
pub(crate) struct Rng(u64);

impl Rng {
    /// The stream of a key.
    pub fn keyed(parts: &[u64]) -> Rng {
        let state = parts
            .iter()
            .fold(0x6A09_E667_F3BC_C908u64, |h, p| mix(h ^ mix(*p)));
        Rng(state)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix(self.0)
    }

    /// Uniform in [0, 1) with 53 random bits.
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform integer in [0, n) (Lemire's multiply-high; bias below 2^-64 · n).
    pub fn below(&mut self, n: usize) -> usize {
        ((u128::from(self.next_u64()) * n as u128) >> 64) as usize
    }
}

/// `budget` distinct indices of `0..n` chosen uniformly (partial Fisher–Yates), sorted;
/// all of them when `n` is not larger than the budget.
pub(crate) fn sample(n: usize, budget: usize, rng: &mut Rng) -> Vec<usize> {
    if n <= budget {
        return (0..n).collect();
    }
    let mut idx: Vec<usize> = (0..n).collect();
    for k in 0..budget {
        let pick = k + rng.below(n - k);
        idx.swap(k, pick);
    }
    idx.truncate(budget);
    idx.sort_unstable();
    idx
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sampling_is_distinct_sorted_and_keyed() {
        let a = sample(1000, 100, &mut Rng::keyed(&[0, 1, 2]));
        let b = sample(1000, 100, &mut Rng::keyed(&[0, 1, 2]));
        let c = sample(1000, 100, &mut Rng::keyed(&[0, 1, 3]));
        assert_eq!(a, b);
        assert_ne!(a, c);
        assert_eq!(a.len(), 100);
        assert!(a.windows(2).all(|w| w[0] < w[1]));
        // Roughly uniform: the mean index is near the middle.
        let mean = a.iter().sum::<usize>() as f64 / 100.0;
        assert!((mean - 500.0).abs() < 100.0, "{mean}");
        assert_eq!(sample(5, 10, &mut Rng::keyed(&[1])), vec![0, 1, 2, 3, 4]);
    }

    #[test]
    fn below_stays_in_range_and_unit_in_unit_interval() {
        let mut r = Rng::keyed(&[9]);
        for n in [1usize, 2, 7, 1000] {
            for _ in 0..1000 {
                assert!(r.below(n) < n);
            }
        }
        for _ in 0..1000 {
            let u = r.unit();
            assert!((0.0..1.0).contains(&u));
        }
    }
}

//! SplitMix64 streams keyed by (seed, purpose, index): every random decision depends only
//! on its key, never on thread scheduling or on a third-party RNG's version. The generator
//! is the workspace's ([`profuse_formats::rng`]); the keying is gs-init's own (the written
//! Gaussians depend on it).

use profuse_formats::rng::{splitmix64_mix as mix, SplitMix64};

/// Purposes, so that streams of different decisions never coincide.
pub(crate) mod purpose {
    pub const KMEANS: u64 = 1;
    pub const SAMPLE: u64 = 2;
}

/// A SplitMix64 generator.
pub(crate) type Rng = SplitMix64;

/// The stream of a key.
pub(crate) fn keyed(parts: &[u64]) -> Rng {
    let state = parts
        .iter()
        .fold(0x6A09_E667_F3BC_C908u64, |h, p| mix(h ^ mix(*p)));
    SplitMix64::new(state)
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
        let a = sample(1000, 100, &mut keyed(&[0, 1, 2]));
        let b = sample(1000, 100, &mut keyed(&[0, 1, 2]));
        let c = sample(1000, 100, &mut keyed(&[0, 1, 3]));
        assert_eq!(a, b);
        assert_ne!(a, c);
        assert_eq!(a.len(), 100);
        assert!(a.windows(2).all(|w| w[0] < w[1]));
        // Roughly uniform: the mean index is near the middle.
        let mean = a.iter().sum::<usize>() as f64 / 100.0;
        assert!((mean - 500.0).abs() < 100.0, "{mean}");
        assert_eq!(sample(5, 10, &mut keyed(&[1])), vec![0, 1, 2, 3, 4]);
    }

    #[test]
    fn below_stays_in_range_and_unit_in_unit_interval() {
        let mut r = keyed(&[9]);
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

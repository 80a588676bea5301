//! Faiss-compatible product quantisation of Gaussian descriptors with an ADC shortlist
//! and exact re-rank (paper §3.4, "Inference Procedure").
//!
//! # Design
//!
//! Every Gaussian carries a unit 512-d language descriptor; stored as f32 that is 2 KiB a
//! Gaussian. Like Dr. Splat, ProFuse stores it product-quantised: the vector is cut into
//! M sub-vectors of `dsub = D / M` dimensions and each is replaced by the index of the
//! nearest of 256 centroids of its sub-quantiser, so a Gaussian costs M bytes (128 for
//! the default PQ128x8 over 512-d) plus a 4-byte norm.
//!
//! * **Layout** (SPEC.md §4.8): centroids `[M, 256, dsub]` are faiss's
//!   `ProductQuantizer.centroids`; code `c[n, m]` selects centroid `m, c[n, m]` for
//!   dimensions `m·dsub..(m+1)·dsub`. Loading our centroids into
//!   `faiss.ProductQuantizer(D, M, 8)` gives the same codes and decodes
//!   (`python/test_faiss_compat.py`).
//! * **Training** ([`train`]) is faiss's `Clustering` per sub-quantiser: a seeded uniform
//!   sample of at most 65536 valid vectors (faiss's 256 points per centroid x 256),
//!   initial centroids = 256 distinct random sample points (faiss's init, not k-means++:
//!   with 256 points per centroid Lloyd's iterations matter more than the seeding), 25
//!   Lloyd iterations, empty clusters re-seeded by splitting a large one with a ±1/1024
//!   perturbation (faiss's `split_clusters`). Hamerly's distance bounds skip the points
//!   whose nearest centroid provably did not move (with a margin far above f32 rounding),
//!   which saves a quarter of the training time and changes no bit (tested against
//!   scanning every point). Sub-quantisers train in parallel, each sequentially with its
//!   own ChaCha8 stream, so the codebook is identical for any thread count.
//! * **Encoding** ([`Codebook::encode`]) picks per sub-vector the centroid of smallest
//!   `sum_j (x_j - c_j)^2` (faiss's `fvec_L2sqr` formula in f32), the lower index on ties.
//!   The file also stores each vector's decoded norm, so that cosine scores need no
//!   decoding: `cos(q, x̂) = <q, x̂> / (|q| |x̂|)`.
//! * **Scoring** ([`adc_scores`], [`search`]): a [`LookupTable`] holds the query's inner
//!   product with every centroid (`[M, 256]` f32, 128 KiB for M = 128, L2-resident);
//!   the inner product with a decoded vector is a sum of M table entries (asymmetric
//!   distance computation: the query is never quantised). The pass over all codes sums
//!   four codes side by side (four independent addition chains), reading each code eight
//!   bytes at a time, in parallel chunks of 64 K codes; a bounded heap per chunk keeps
//!   the candidates. [`search`] keeps the `shortlist` best ADC scores and re-ranks them by
//!   the exact cosine with the decoded vectors in f64. With f32 tables the ADC score equals
//!   the decoded cosine up to f32 rounding, so the shortlist only has to absorb rounding
//!   near the k-th score; the default ([`DEFAULT_SHORTLIST`] = 1000) leaves a wide margin
//!   at a re-rank cost well under a millisecond.
//! * **Fast scan** ([`FastScan`]): the centroids of each sub-quantiser grouped into 16
//!   give every vector 4-bit codes (built in memory once per pq; the file is unchanged),
//!   scanned with 16-entry tables in SIMD registers like faiss's fast-scan; the 8-bit ADC
//!   scores the candidates and the exact re-rank gives the exact top k (see the
//!   `fastscan` module for how the candidates are bounded).
//! * **Invalid descriptors** (`features.valid == 0`) are never trained on and get codes 0,
//!   norm 0 and `valid` 0; they decode to zeros, score 0 and are never returned by
//!   [`search`].
//!
//! # Example: train, encode, query
//!
//! ```
//! use profuse_pq::{decode, search, synthetic::Clustered, train, FastScan, TrainParams};
//!
//! // 2000 clustered unit vectors in 32-d (every 10th invalid), PQ with M = 8, dsub = 4.
//! let gen = Clustered::new(32, 20, 0.5, 7);
//! let features = gen.features(2000, 10);
//! let params = TrainParams { m: 8, iters: 10, ..TrainParams::default() };
//! let codebook = train(&features, &params)?;
//! let pq = codebook.encode_features(&features)?;
//! assert_eq!(pq.codes.len(), 2000 * 8);
//! assert_eq!(pq.valid[9], 0);
//!
//! // Decoded vectors approximate the originals.
//! let mut x = vec![0f32; 32];
//! decode(&pq, 0, &mut x);
//! let original = gen.vectors(0, 1);
//! let cos: f32 = x.iter().zip(&original).map(|(a, b)| a * b).sum::<f32>() / pq.norms[0];
//! assert!(cos > 0.9, "{cos}");
//!
//! // A query near class 3 finds vectors of class 3.
//! let q = gen.query(3, 0.3, 0);
//! let top = search(&pq, &q, 200, 10)?;
//! assert_eq!(top.len(), 10);
//! assert!(top.iter().all(|&(id, _)| gen.class_of(u64::from(id)) == 3));
//!
//! // The fast scan (4-bit first pass, prepared once) finds the same top 10.
//! let fast = FastScan::new(&pq)?;
//! let (fast_top, stats) = fast.search(&pq, &q, 10)?;
//! assert_eq!(fast_top, top);
//! assert!(stats.candidates >= 10);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

mod adc;
mod codebook;
mod error;
mod fastscan;
pub mod job;
mod scan4;
pub mod synthetic;
mod train;

pub use adc::{
    adc_scores, adc_shortlist, decode, decode_all, exact_cosine, rank_order, search, top_n,
    LookupTable, DEFAULT_SHORTLIST,
};
pub use codebook::Codebook;
pub use error::PqError;
pub use fastscan::{FastScan, FastScanStats};
pub use profuse_formats::{Pq, KSUB};
/// Re-exported so tools can size the thread pool without naming rayon.
pub use rayon;
pub use train::{train, train_vectors, TrainParams};

use profuse_formats::Features;

/// Mean cosine between each valid descriptor and its decoded vector (1 is lossless);
/// `None` when no vector is valid.
///
/// # Panics
/// If `features` and `pq` differ in length or dimension.
pub fn reconstruction_cosine(features: &Features, pq: &Pq) -> Option<f64> {
    use rayon::prelude::*;
    assert_eq!(features.len(), pq.len(), "vector count");
    assert_eq!(features.dim, pq.dim(), "dimension");
    let d = features.dim;
    // Per-vector values summed sequentially afterwards: the same result for any thread count.
    let cosines: Vec<Option<f64>> = (0..features.len())
        .into_par_iter()
        .map_init(
            || (vec![0f32; d], vec![0f32; d]),
            |(x, y), i| {
                (features.valid[i] == 1 && pq.valid[i] == 1).then(|| {
                    features.features.read_into(i * d, x);
                    decode(pq, i, y);
                    cosine_f64(x, y)
                })
            },
        )
        .collect();
    let valid: Vec<f64> = cosines.into_iter().flatten().collect();
    (!valid.is_empty()).then(|| valid.iter().sum::<f64>() / valid.len() as f64)
}

/// Dot product of two descriptors in f32 with eight partial sums combined in a fixed
/// order (vectorises; the result depends only on the inputs). `query` and
/// `vertex-transfer` score descriptors against prompts with it.
pub fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..8 {
            acc[l] += x[l] * y[l];
        }
    }
    let mut tail = 0.0f32;
    for (x, y) in ra.iter().zip(rb) {
        tail += x * y;
    }
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7])) + tail
}

/// [`dot`] of `a` with each vector of `b`, into `out` (`out.len() == b.len()`, every
/// vector at least as long as `a`). Each result has exactly [`dot`]'s bits: the same
/// eight partial sums in the same order, IEEE products and sums with no fused
/// multiply-add. The vectors go up to six at a time through independent accumulators, which
/// hides the add latency that bounds a single [`dot`], and with AVX (checked at run
/// time) each group of eight partial sums is one register: scoring a row against
/// several prompts costs little more than one product.
pub fn dots(a: &[f32], b: &[&[f32]], out: &mut [f32]) {
    assert_eq!(out.len(), b.len(), "one output per vector");
    let (mut rest_b, mut rest_out) = (b, out);
    while !rest_b.is_empty() {
        let k = rest_b.len().min(6);
        let (group, tail) = rest_b.split_at(k);
        let (o, o_tail) = std::mem::take(&mut rest_out).split_at_mut(k);
        let g = |j: usize| group[j];
        match k {
            1 => finish(a, lanes::<1>(a, [g(0)]), group, o),
            2 => finish(a, lanes::<2>(a, [g(0), g(1)]), group, o),
            3 => finish(a, lanes::<3>(a, [g(0), g(1), g(2)]), group, o),
            4 => finish(a, lanes::<4>(a, [g(0), g(1), g(2), g(3)]), group, o),
            5 => finish(a, lanes::<5>(a, [g(0), g(1), g(2), g(3), g(4)]), group, o),
            _ => finish(
                a,
                lanes::<6>(a, [g(0), g(1), g(2), g(3), g(4), g(5)]),
                group,
                o,
            ),
        }
        (rest_b, rest_out) = (tail, o_tail);
    }
}

/// [`dot`]'s combination of its eight partial sums and the tail past the last group.
fn finish<const K: usize>(a: &[f32], sums: [[f32; 8]; K], b: &[&[f32]], out: &mut [f32]) {
    let n = a.len();
    let whole = n - n % 8;
    for ((o, acc), v) in out.iter_mut().zip(&sums).zip(b) {
        let mut tail = 0.0f32;
        for (x, y) in a[whole..].iter().zip(&v[whole..n]) {
            tail += x * y;
        }
        *o = ((acc[0] + acc[4]) + (acc[1] + acc[5]))
            + ((acc[2] + acc[6]) + (acc[3] + acc[7]))
            + tail;
    }
}

/// The eight partial sums of [`dot`] for each of `K` vectors (whole groups of eight
/// elements only; the caller adds the tail).
fn lanes<const K: usize>(a: &[f32], b: [&[f32]; K]) -> [[f32; 8]; K] {
    let n = a.len();
    let b = b.map(|v| &v[..n]);
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        return avx::lanes(a, b);
    }
    portable_lanes(a, b)
}

fn portable_lanes<const K: usize>(a: &[f32], b: [&[f32]; K]) -> [[f32; 8]; K] {
    use wide::f32x8;
    // Explicit 8-lane vectors (lane l sums the products of the elements l mod 8, as
    // `dot`'s acc[l]); the compiler's own vectoriser would interleave the vectors instead.
    let (xs, _) = a.as_chunks::<8>();
    let ys = b.map(|v| v.as_chunks::<8>().0);
    let mut acc = [f32x8::ZERO; K];
    for (i, x) in xs.iter().enumerate() {
        let x = f32x8::from(*x);
        for (acc, y) in acc.iter_mut().zip(&ys) {
            *acc += x * f32x8::from(y[i]);
        }
    }
    acc.map(|v| v.to_array())
}

#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod avx {
    //! [`super::portable_lanes`] with 256-bit registers: `_mm256_mul_ps` then
    //! `_mm256_add_ps` per lane, the same IEEE operations in the same order.

    use std::arch::x86_64::*;

    pub(super) fn lanes<const K: usize>(a: &[f32], b: [&[f32]; K]) -> [[f32; 8]; K] {
        assert!(std::arch::is_x86_feature_detected!("avx"));
        assert!(b.iter().all(|v| v.len() == a.len()));
        // SAFETY: AVX is present (checked above) and every vector has `a.len()` elements.
        unsafe { lanes_avx(a, b) }
    }

    /// # Safety
    /// The CPU has AVX, and every vector of `b` has `a.len()` elements.
    #[target_feature(enable = "avx")]
    unsafe fn lanes_avx<const K: usize>(a: &[f32], b: [&[f32]; K]) -> [[f32; 8]; K] {
        let whole = a.len() - a.len() % 8;
        let mut acc = [_mm256_setzero_ps(); K];
        let mut i = 0;
        while i < whole {
            // SAFETY: i + 8 <= whole <= len of `a` and of every vector of `b`.
            let x = unsafe { _mm256_loadu_ps(a.as_ptr().add(i)) };
            for (acc, v) in acc.iter_mut().zip(&b) {
                let y = unsafe { _mm256_loadu_ps(v.as_ptr().add(i)) };
                *acc = _mm256_add_ps(*acc, _mm256_mul_ps(x, y));
            }
            i += 8;
        }
        let mut out = [[0.0f32; 8]; K];
        for (o, acc) in out.iter_mut().zip(acc) {
            // SAFETY: `o` holds eight f32.
            unsafe { _mm256_storeu_ps(o.as_mut_ptr(), acc) };
        }
        out
    }
}

/// Cosine of two vectors in f64 (0 when either is zero).
pub fn cosine_f64(a: &[f32], b: &[f32]) -> f64 {
    let (mut ab, mut aa, mut bb) = (0f64, 0f64, 0f64);
    for (&x, &y) in a.iter().zip(b) {
        let (x, y) = (f64::from(x), f64::from(y));
        ab += x * y;
        aa += x * x;
        bb += y * y;
    }
    if aa > 0.0 && bb > 0.0 {
        ab / (aa.sqrt() * bb.sqrt())
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::{dot, dots, portable_lanes};

    #[test]
    fn dot_matches_a_plain_sum_for_every_length() {
        for n in 0..40 {
            let a: Vec<f32> = (0..n).map(|i| (i as f32 * 0.37).sin()).collect();
            let b: Vec<f32> = (0..n).map(|i| (i as f32 * 0.91).cos()).collect();
            let want: f64 = a
                .iter()
                .zip(&b)
                .map(|(x, y)| f64::from(*x) * f64::from(*y))
                .sum();
            assert!((f64::from(dot(&a, &b)) - want).abs() < 1e-5, "n = {n}");
        }
    }

    #[test]
    fn dots_have_the_bits_of_dot_for_every_length_and_count() {
        for n in 0..70 {
            let v = |k: f32| -> Vec<f32> { (0..n).map(|i| (i as f32 * k).sin() * 3.0).collect() };
            let a = v(0.37);
            let b: Vec<Vec<f32>> = (0..7).map(|j| v(0.91 + 0.77 * j as f32)).collect();
            for count in 0..=b.len() {
                let refs: Vec<&[f32]> = b[..count].iter().map(Vec::as_slice).collect();
                let mut got = vec![f32::NAN; count];
                dots(&a, &refs, &mut got);
                for (g, b) in got.iter().zip(&refs) {
                    assert_eq!(
                        g.to_bits(),
                        dot(&a, b).to_bits(),
                        "n = {n}, count = {count}"
                    );
                }
            }
            // The portable lanes equal the run-time chosen ones.
            let four = [b[0].as_slice(), &b[1], &b[2], &b[3]];
            assert_eq!(portable_lanes(&a, four), super::lanes(&a, four), "n = {n}");
        }
    }
}

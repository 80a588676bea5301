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
//! * **Invalid descriptors** (`features.valid == 0`) are never trained on and get codes 0,
//!   norm 0 and `valid` 0; they decode to zeros, score 0 and are never returned by
//!   [`search`].
//!
//! # Example: train, encode, query
//!
//! ```
//! use profuse_pq::{decode, search, synthetic::Clustered, train, TrainParams};
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
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

mod adc;
mod codebook;
mod error;
pub mod job;
pub mod synthetic;
mod train;

pub use adc::{
    adc_scores, adc_shortlist, decode, decode_all, exact_cosine, rank_order, search, top_n,
    LookupTable, DEFAULT_SHORTLIST,
};
pub use codebook::Codebook;
pub use error::PqError;
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
    use super::dot;

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
}

//! Seeded k-means training of the M sub-quantisers, faiss `Clustering` style.

use profuse_formats::{Features, KSUB};
use rand::RngCore;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::codebook::{argmin_first, nearest, sub_distances, transpose, Codebook};
use crate::PqError;

/// Training parameters; the defaults are the paper's / faiss's. As serde, the pipeline's
/// `[pq]` section.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainParams {
    /// Sub-quantisers M (D must be a multiple). Default 128 (Dr. Splat's PQ128x8 over 512-d).
    pub m: usize,
    /// Lloyd iterations per sub-quantiser. Default 25 (faiss `ClusteringParameters::niter`).
    pub iters: usize,
    /// Most training vectors, drawn uniformly without replacement from the valid rows.
    /// Default 65536 = 256 centroids x 256 (faiss's `max_points_per_centroid` x ksub).
    pub sample: usize,
    /// Seed of the sample draw, the initial centroids and the empty-cluster splits.
    /// Default 1234 (faiss's default clustering seed; faiss's RNG is not reproduced).
    pub seed: u64,
}

impl Default for TrainParams {
    fn default() -> Self {
        TrainParams {
            m: 128,
            iters: 25,
            sample: 65536,
            seed: 1234,
        }
    }
}

/// Relative perturbation of a split centroid (faiss's `EPS = 1 / 1024`).
const SPLIT_EPS: f32 = 1.0 / 1024.0;

/// Trains a codebook on the valid rows of a features file.
pub fn train(features: &Features, params: &TrainParams) -> Result<Codebook, PqError> {
    let d = features.dim;
    check_params(d, params)?;
    let valid_rows: Vec<usize> = (0..features.len())
        .filter(|&i| features.valid[i] == 1)
        .collect();
    let rows = sample_rows(&valid_rows, params)?;
    let mut data = vec![0f32; rows.len() * d];
    for (out, &r) in data.chunks_exact_mut(d).zip(&rows) {
        features.features.read_into(r * d, out);
    }
    train_sample(&data, d, params)
}

/// Trains a codebook on row-major vectors `[n, dim]` (all rows count as valid; more than
/// `params.sample` rows are subsampled as in [`train`]).
pub fn train_vectors(
    vectors: &[f32],
    dim: usize,
    params: &TrainParams,
) -> Result<Codebook, PqError> {
    check_params(dim, params)?;
    if !vectors.len().is_multiple_of(dim) {
        return Err(PqError::FeatureDim {
            got: vectors.len() % dim,
            expected: dim,
        });
    }
    let all: Vec<usize> = (0..vectors.len() / dim).collect();
    let rows = sample_rows(&all, params)?;
    if rows.len() == all.len() {
        return train_sample(vectors, dim, params);
    }
    let mut data = vec![0f32; rows.len() * dim];
    for (out, &r) in data.chunks_exact_mut(dim).zip(&rows) {
        out.copy_from_slice(&vectors[r * dim..(r + 1) * dim]);
    }
    train_sample(&data, dim, params)
}

fn check_params(dim: usize, params: &TrainParams) -> Result<(), PqError> {
    if params.m == 0 || dim == 0 || !dim.is_multiple_of(params.m) {
        return Err(PqError::DimNotDivisible { dim, m: params.m });
    }
    if params.sample < KSUB {
        return Err(PqError::SampleTooSmall {
            sample: params.sample,
            needed: KSUB,
        });
    }
    Ok(())
}

/// The training rows: all of `candidates` when they fit the sample, else a seeded
/// uniform subset, in ascending order.
fn sample_rows(candidates: &[usize], params: &TrainParams) -> Result<Vec<usize>, PqError> {
    if candidates.len() < KSUB {
        return Err(PqError::TooFewVectors {
            valid: candidates.len(),
            needed: KSUB,
        });
    }
    if candidates.len() <= params.sample {
        return Ok(candidates.to_vec());
    }
    let mut rng = rng_for(params.seed, 0);
    let mut picked: Vec<usize> = distinct_indices(&mut rng, candidates.len(), params.sample)
        .into_iter()
        .map(|i| candidates[i])
        .collect();
    picked.sort_unstable();
    Ok(picked)
}

/// Runs k-means on each subspace of the sample (one rayon task per sub-quantiser, each
/// sequential with its own RNG stream, so the result does not depend on thread count).
fn train_sample(data: &[f32], dim: usize, params: &TrainParams) -> Result<Codebook, PqError> {
    let m = params.m;
    let dsub = dim / m;
    let n = data.len() / dim;
    let per_sub: Vec<Vec<f32>> = (0..m)
        .into_par_iter()
        .map(|s| {
            let mut points = Vec::with_capacity(n * dsub);
            for row in data.chunks_exact(dim) {
                points.extend_from_slice(&row[s * dsub..(s + 1) * dsub]);
            }
            kmeans(
                &points,
                dsub,
                params.iters,
                &mut rng_for(params.seed, s as u64 + 1),
            )
        })
        .collect();
    let mut cb = Codebook::new(m, dsub, per_sub.concat())?;
    let meta = cb.metadata_mut();
    meta.insert("train_samples".into(), n.to_string());
    meta.insert("seed".into(), params.seed.to_string());
    meta.insert("kmeans_iters".into(), params.iters.to_string());
    meta.insert(
        "generator".into(),
        format!("profuse-pq {}", env!("CARGO_PKG_VERSION")),
    );
    Ok(cb)
}

/// Lloyd's k-means with 256 centroids on `points` `[n, dsub]` (n >= 256), faiss style:
/// initial centroids are 256 distinct random points; each iteration assigns every point
/// to its nearest centroid (ties to the lower index), moves each centroid to the mean of
/// its points (f64 sums in point order), and re-seeds each empty cluster by splitting a
/// cluster picked with probability growing with its size (faiss `split_clusters`).
/// Stops early at a fixed point (an assignment that repeats with no split in between),
/// which changes nothing but the time taken. Hamerly's bounds skip the points whose
/// nearest centroid provably did not change (see [`Bounds`]); the result is bit-identical
/// to scanning every point.
pub(crate) fn kmeans(points: &[f32], dsub: usize, iters: usize, rng: &mut ChaCha8Rng) -> Vec<f32> {
    kmeans_with(points, dsub, iters, rng, true).0
}

fn kmeans_with(
    points: &[f32],
    dsub: usize,
    iters: usize,
    rng: &mut ChaCha8Rng,
    use_bounds: bool,
) -> (Vec<f32>, usize) {
    let n = points.len() / dsub;
    let mut centroids = Vec::with_capacity(KSUB * dsub);
    for i in distinct_indices(rng, n, KSUB) {
        centroids.extend_from_slice(&points[i * dsub..(i + 1) * dsub]);
    }
    let mut assign = vec![0u8; n];
    let mut bounds = Bounds::new(n);
    let mut split_last = true;
    let mut scans = 0;
    for _ in 0..iters {
        let ct = transpose(&centroids, 1, dsub);
        let changed = if use_bounds {
            bounds.assign(points, dsub, &centroids, &ct, &mut assign)
        } else {
            scans += n;
            assign_all(points, dsub, &ct, &mut assign)
        };
        // Same assignment as last time and no split since: the update would reproduce
        // the current centroids, and so would every later iteration.
        if !changed && !split_last {
            break;
        }
        let previous = centroids.clone();
        let mut counts = update_means(points, dsub, &assign, &mut centroids);
        split_last = split_empty_clusters(&mut centroids, &mut counts, dsub, n, rng) > 0;
        if use_bounds {
            bounds.centroids_moved(&previous, &centroids, dsub, &assign);
        }
    }
    (centroids, scans + bounds.scans)
}

/// Assigns every point to its nearest centroid; whether any assignment changed.
fn assign_all(points: &[f32], dsub: usize, ct: &[f32], assign: &mut [u8]) -> bool {
    let mut dist = [0f32; KSUB];
    let mut changed = false;
    for (a, x) in assign.iter_mut().zip(points.chunks_exact(dsub)) {
        let k = nearest(x, ct, &mut dist);
        changed |= k != *a;
        *a = k;
    }
    changed
}

/// Moves each centroid with points to their mean (f64 sums in point order); returns the
/// cluster sizes. Empty clusters keep their centroid.
fn update_means(
    points: &[f32],
    dsub: usize,
    assign: &[u8],
    centroids: &mut [f32],
) -> [usize; KSUB] {
    let mut sums = vec![0f64; KSUB * dsub];
    let mut counts = [0usize; KSUB];
    for (&a, x) in assign.iter().zip(points.chunks_exact(dsub)) {
        let a = a as usize;
        counts[a] += 1;
        for (s, &v) in sums[a * dsub..(a + 1) * dsub].iter_mut().zip(x) {
            *s += f64::from(v);
        }
    }
    for k in 0..KSUB {
        if counts[k] > 0 {
            let inv = 1.0 / counts[k] as f64;
            for j in 0..dsub {
                centroids[k * dsub + j] = (sums[k * dsub + j] * inv) as f32;
            }
        }
    }
    counts
}

/// Relative margin by which a bound must clear the test before a point is skipped: far
/// above the ~3e-7 relative error of an f32 squared distance of a few terms, so a skipped
/// point's f32 distances have a unique minimum at its current centroid.
const BOUND_MARGIN: f64 = 1e-5;

/// Hamerly's per-point bounds on exact Euclidean distances: `upper[i]` >= distance to the
/// assigned centroid, `lower[i]` <= distance to every other centroid. A point whose upper
/// bound is below (with [`BOUND_MARGIN`]) its lower bound, or below half the gap from
/// its centroid to the nearest other centroid, keeps its centroid without a scan. After a
/// move by `delta_k`, `upper += delta_assigned` and `lower -= max delta` keep the bounds
/// valid (triangle inequality). Bounds are f64; f32-derived values get a 1e-6 relative
/// widening.
#[derive(Debug)]
struct Bounds {
    upper: Vec<f64>,
    lower: Vec<f64>,
    /// Full scans of 256 centroids done so far.
    scans: usize,
}

impl Bounds {
    fn new(n: usize) -> Self {
        // No information yet: every point is scanned in the first iteration.
        Bounds {
            upper: vec![f64::INFINITY; n],
            lower: vec![0.0; n],
            scans: 0,
        }
    }

    fn assign(
        &mut self,
        points: &[f32],
        dsub: usize,
        centroids: &[f32],
        ct: &[f32],
        assign: &mut [u8],
    ) -> bool {
        let half_gap = half_gaps(centroids, dsub);
        let mut dist = [0f32; KSUB];
        let mut changed = false;
        for (i, x) in points.chunks_exact(dsub).enumerate() {
            let a = assign[i] as usize;
            let z = self.lower[i].max(half_gap[a]) * (1.0 - BOUND_MARGIN);
            if self.upper[i] < z {
                continue;
            }
            if self.upper[i].is_finite() {
                self.upper[i] = dist_f64(x, &centroids[a * dsub..(a + 1) * dsub]) * (1.0 + 1e-12);
                if self.upper[i] < z {
                    continue;
                }
            }
            self.scans += 1;
            sub_distances(x, ct, &mut dist);
            let k = argmin_first(&dist);
            let best = dist[k as usize];
            dist[k as usize] = f32::INFINITY;
            let second = min_f32(&dist);
            self.upper[i] = f64::from(best).sqrt() * (1.0 + 1e-6);
            self.lower[i] = f64::from(second).sqrt() * (1.0 - 1e-6);
            changed |= k != assign[i];
            assign[i] = k;
        }
        changed
    }

    fn centroids_moved(&mut self, before: &[f32], after: &[f32], dsub: usize, assign: &[u8]) {
        let delta: Vec<f64> = before
            .chunks_exact(dsub)
            .zip(after.chunks_exact(dsub))
            .map(|(b, a)| dist_f64(b, a) * (1.0 + 1e-12))
            .collect();
        let max = delta.iter().fold(0.0f64, |m, &d| m.max(d));
        for ((u, l), &a) in self.upper.iter_mut().zip(&mut self.lower).zip(assign) {
            *u += delta[a as usize];
            *l = (*l - max).max(0.0);
        }
    }
}

/// Minimum of 256 values (lane-wise, so it vectorises).
fn min_f32(v: &[f32; KSUB]) -> f32 {
    let mut lanes = [f32::INFINITY; 16];
    for chunk in v.chunks_exact(16) {
        for (l, &x) in lanes.iter_mut().zip(chunk) {
            *l = if x < *l { x } else { *l };
        }
    }
    lanes
        .iter()
        .fold(f32::INFINITY, |a, &b| if b < a { b } else { a })
}

/// Half the distance from each centroid to its nearest other centroid (rounded down).
fn half_gaps(centroids: &[f32], dsub: usize) -> [f64; KSUB] {
    let mut gap = [f64::INFINITY; KSUB];
    for k in 0..KSUB {
        let ck = &centroids[k * dsub..(k + 1) * dsub];
        for j in k + 1..KSUB {
            let d = dist_f64(ck, &centroids[j * dsub..(j + 1) * dsub]);
            gap[k] = gap[k].min(d);
            gap[j] = gap[j].min(d);
        }
    }
    gap.map(|g| 0.5 * g * (1.0 - 1e-12))
}

/// Euclidean distance in f64.
fn dist_f64(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(&x, &y)| (f64::from(x) - f64::from(y)).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// faiss `split_clusters`: each empty cluster takes a copy of a cluster `cj` chosen by
/// walking the clusters cyclically and accepting `cj` with probability
/// `(size - 1) / (n - 256)`; the two copies are pushed apart by a relative `±EPS` per
/// coordinate (alternating signs) and share the points' count. Returns the number of
/// splits.
fn split_empty_clusters(
    centroids: &mut [f32],
    counts: &mut [usize; KSUB],
    dsub: usize,
    n: usize,
    rng: &mut ChaCha8Rng,
) -> usize {
    let spare = (n - KSUB).max(1) as f32;
    let mut splits = 0;
    for ci in 0..KSUB {
        if counts[ci] != 0 {
            continue;
        }
        // n >= 256 points in at most 255 non-empty clusters: some cluster has two or
        // more, so the walk ends.
        let mut cj = 0;
        loop {
            let p = (counts[cj] as f32 - 1.0) / spare;
            if unit_f32(rng) < p {
                break;
            }
            cj = (cj + 1) % KSUB;
        }
        for j in 0..dsub {
            let v = centroids[cj * dsub + j];
            let (up, down) = (v * (1.0 + SPLIT_EPS), v * (1.0 - SPLIT_EPS));
            let (new_ci, new_cj) = if j % 2 == 0 { (up, down) } else { (down, up) };
            centroids[ci * dsub + j] = new_ci;
            centroids[cj * dsub + j] = new_cj;
        }
        counts[ci] = counts[cj] / 2;
        counts[cj] -= counts[ci];
        splits += 1;
    }
    splits
}

/// A ChaCha8 stream for (seed, purpose): stream 0 draws the sample, stream s + 1 serves
/// sub-quantiser s. ChaCha8's output is fixed by its specification, and the bounded draws
/// below are our own, so results do not change with `rand` versions.
fn rng_for(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    rng
}

/// Uniform in `0..n` by multiply-shift (bias below 2^-40 for the sizes used here).
fn below(rng: &mut ChaCha8Rng, n: usize) -> usize {
    ((u128::from(rng.next_u64()) * n as u128) >> 64) as usize
}

/// Uniform in [0, 1) with 24 random bits.
fn unit_f32(rng: &mut ChaCha8Rng) -> f32 {
    (rng.next_u32() >> 8) as f32 * (1.0 / (1u32 << 24) as f32)
}

/// `k` distinct indices of `0..n` (k <= n) in draw order, by a partial Fisher-Yates
/// shuffle.
fn distinct_indices(rng: &mut ChaCha8Rng, n: usize, k: usize) -> Vec<usize> {
    let mut perm: Vec<usize> = (0..n).collect();
    for i in 0..k.min(n) {
        let j = i + below(rng, n - i);
        perm.swap(i, j);
    }
    perm.truncate(k.min(n));
    perm
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distinct_indices_are_distinct_and_in_range() {
        let mut rng = rng_for(5, 0);
        let mut v = distinct_indices(&mut rng, 1000, 300);
        assert_eq!(v.len(), 300);
        v.sort_unstable();
        v.dedup();
        assert_eq!(v.len(), 300);
        assert!(v.iter().all(|&i| i < 1000));
    }

    #[test]
    fn kmeans_on_exactly_256_points_returns_them() {
        let pts: Vec<f32> = (0..512).map(|i| (i * 7 % 512) as f32 * 0.25).collect();
        let mut c = kmeans(&pts, 2, 5, &mut rng_for(1, 1));
        let mut p = pts.clone();
        let sort_pairs = |v: &mut Vec<f32>| {
            let mut pairs: Vec<[f32; 2]> = v.chunks_exact(2).map(|c| [c[0], c[1]]).collect();
            pairs.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
            *v = pairs.concat();
        };
        sort_pairs(&mut c);
        sort_pairs(&mut p);
        assert_eq!(c, p);
    }

    #[test]
    fn hamerly_bounds_give_the_bits_of_scanning_every_point() {
        // Uniform points, clustered points, and heavy duplicates (which force splits).
        let mut rng = rng_for(9, 0);
        let uniform: Vec<f32> = (0..3000 * 4).map(|_| unit_f32(&mut rng)).collect();
        let clustered: Vec<f32> = (0..4000 * 4)
            .map(|i| ((i / 4) % 40) as f32 * 0.1 + 0.01 * unit_f32(&mut rng))
            .collect();
        let duplicates: Vec<f32> = (0..1000 * 3).map(|i| ((i / 3) % 300) as f32).collect();
        for (name, pts, dsub) in [
            ("uniform", &uniform, 4),
            ("clustered", &clustered, 4),
            ("duplicates", &duplicates, 3),
        ] {
            let (fast, fast_scans) = kmeans_with(pts, dsub, 25, &mut rng_for(2, 1), true);
            let (plain, plain_scans) = kmeans_with(pts, dsub, 25, &mut rng_for(2, 1), false);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&fast), bits(&plain), "{name}");
            // The bounds do skip work.
            assert!(
                2 * fast_scans < plain_scans,
                "{name}: {fast_scans} vs {plain_scans}"
            );
        }
    }

    #[test]
    fn empty_clusters_are_split_from_populated_ones() {
        // Cluster 0 holds 300 - 254 points, clusters 1..=254 one each, 255 is empty.
        let mut counts = [1usize; KSUB];
        counts[0] = 46;
        counts[255] = 0;
        let mut centroids: Vec<f32> = (0..KSUB * 2).map(|i| i as f32 + 1.0).collect();
        let splits = split_empty_clusters(&mut centroids, &mut counts, 2, 300, &mut rng_for(3, 1));
        assert_eq!(splits, 1);
        // Only cluster 0 has more than one point, so it is the one split.
        assert_eq!((counts[0], counts[255]), (23, 23));
        assert_eq!(counts.iter().sum::<usize>(), 300);
        let e = SPLIT_EPS;
        assert_eq!(&centroids[510..512], &[1.0 * (1.0 + e), 2.0 * (1.0 - e)]);
        assert_eq!(&centroids[0..2], &[1.0 * (1.0 - e), 2.0 * (1.0 + e)]);
    }
}

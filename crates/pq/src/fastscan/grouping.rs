//! The 4-bit codes of the first pass: each sub-quantiser's 256 centroids grouped into 16 by a
//! usage-weighted k-means, and every vector's codes packed as group nibbles in blocks.

use super::*;

/// How many valid vectors use each code, `[M, 256]` (integer sums: any thread count).
pub(super) fn code_usage(pq: &Pq) -> Vec<u64> {
    let m = pq.m;
    let n = pq.len();
    (0..n.div_ceil(USAGE_CHUNK))
        .into_par_iter()
        .map(|chunk| {
            let mut counts = vec![0u32; m * KSUB];
            for i in chunk * USAGE_CHUNK..((chunk + 1) * USAGE_CHUNK).min(n) {
                if pq.valid[i] == 1 {
                    for (s, &c) in pq.codes[i * m..(i + 1) * m].iter().enumerate() {
                        counts[s * KSUB + usize::from(c)] += 1;
                    }
                }
            }
            counts
        })
        .fold(
            || vec![0u64; m * KSUB],
            |mut acc, counts| {
                for (a, c) in acc.iter_mut().zip(counts) {
                    *a += u64::from(c);
                }
                acc
            },
        )
        .reduce(
            || vec![0u64; m * KSUB],
            |mut a, b| {
                for (x, y) in a.iter_mut().zip(b) {
                    *x += y;
                }
                a
            },
        )
}

/// One sub-quantiser's grouping.
pub(super) struct Grouping {
    pub(super) group_of: [u8; KSUB],
    /// `[16, dsub]`.
    pub(super) centroids: Vec<f32>,
}

/// Groups 256 centroids (`[256, dsub]`) into 16 by a k-means weighted by `usage`:
/// initial centres the 16 most used centroids (ties to the lower index), then Lloyd
/// iterations (nearest centre in f64, ties to the lower group) until nothing moves.
/// A group's centroid is the usage-weighted mean of its members (their plain mean if
/// none is used).
pub(super) fn group_centroids(cents: &[f32], usage: &[u64], dsub: usize) -> Grouping {
    let point = |k: usize| &cents[k * dsub..(k + 1) * dsub];
    let mut order: Vec<usize> = (0..KSUB).collect();
    order.sort_by(|&a, &b| usage[b].cmp(&usage[a]).then(a.cmp(&b)));
    let mut centres: Vec<Vec<f64>> = order[..GROUPS]
        .iter()
        .map(|&k| point(k).iter().map(|&x| f64::from(x)).collect())
        .collect();
    let mut group_of = [0u8; KSUB];
    for iter in 0..=GROUP_ITERS {
        let mut moved = false;
        for (k, g) in group_of.iter_mut().enumerate() {
            let nearest = nearest_centre(point(k), &centres);
            moved |= nearest != *g;
            *g = nearest;
        }
        if iter > 0 && !moved {
            break;
        }
        centres = group_means(cents, usage, &group_of, dsub, &centres);
    }
    Grouping {
        group_of,
        centroids: centres.iter().flatten().map(|&x| x as f32).collect(),
    }
}

pub(super) fn nearest_centre(p: &[f32], centres: &[Vec<f64>]) -> u8 {
    let mut best = (f64::INFINITY, 0u8);
    for (g, c) in centres.iter().enumerate() {
        let d: f64 = p
            .iter()
            .zip(c)
            .map(|(&x, &y)| (f64::from(x) - y).powi(2))
            .sum();
        if d < best.0 {
            best = (d, g as u8);
        }
    }
    best.1
}

/// Usage-weighted mean of each group's members (plain mean where no member is used;
/// the old centre where the group is empty).
pub(super) fn group_means(
    cents: &[f32],
    usage: &[u64],
    group_of: &[u8; KSUB],
    dsub: usize,
    old: &[Vec<f64>],
) -> Vec<Vec<f64>> {
    (0..GROUPS)
        .map(|g| {
            let members: Vec<usize> = (0..KSUB)
                .filter(|&k| usize::from(group_of[k]) == g)
                .collect();
            let total: u64 = members.iter().map(|&k| usage[k]).sum();
            if members.is_empty() {
                return old[g].clone();
            }
            let weight = |k: usize| if total > 0 { usage[k] as f64 } else { 1.0 };
            let sum_w: f64 = members.iter().map(|&k| weight(k)).sum();
            (0..dsub)
                .map(|j| {
                    members
                        .iter()
                        .map(|&k| weight(k) * f64::from(cents[k * dsub + j]))
                        .sum::<f64>()
                        / sum_w
                })
                .collect()
        })
        .collect()
}

/// The 4-bit codes of every vector in scan layout, `[blocks, pairs, 32]`; padding
/// vectors and sub-quantisers get nibble 0.
pub(super) fn pack(pq: &Pq, group_of: &[[u8; KSUB]], pairs: usize) -> HugeBytes {
    let (n, m) = (pq.len(), pq.m);
    let per_block = pairs * BLOCK;
    let mut packed = HugeBytes::zeroed(n.div_ceil(BLOCK) * per_block);
    packed
        .par_chunks_mut(per_block)
        .enumerate()
        .for_each(|(b, block)| {
            for v in 0..BLOCK.min(n - b * BLOCK) {
                let i = b * BLOCK + v;
                let code = &pq.codes[i * m..(i + 1) * m];
                let at = byte_of_vector(v);
                for p in 0..pairs {
                    let nib = |s: usize| code.get(s).map_or(0, |&c| group_of[s][usize::from(c)]);
                    block[p * BLOCK + at] = nib(2 * p) | nib(2 * p + 1) << 4;
                }
            }
        });
    packed
}

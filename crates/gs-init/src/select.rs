//! Reference views by k-means over camera poses, and each reference's neighbours by pose
//! distance.
//!
//! EDGS clusters flattened 4x4 view matrices, which mixes unit-free rotation entries with
//! translations in scene units (and `t = −R·C` depends on the rotation too). Here a pose
//! is the 6-vector `(C / s, a)`: the camera centre `C` divided by the spread `s` of all
//! centres (root mean square distance from their mean, so the positions have unit scale
//! in any scene unit) and the unit optical axis `a`. One unit of position therefore
//! weighs like the difference between two viewing directions about 60° apart.

use crate::geometry::View;
use crate::rng::{keyed, purpose, Rng};

/// Independent k-means runs; the one with the smallest inertia wins (scikit-learn's
/// `n_init = 10`, as in EDGS).
pub const KMEANS_RESTARTS: u64 = 10;
/// Lloyd iterations per run at most (they stop earlier when assignments settle).
pub const KMEANS_ITERATIONS: usize = 100;

/// A pose as a point of the clustering space.
pub type PoseFeature = [f64; 6];

/// The pose feature of every view.
pub fn pose_features(views: &[View]) -> Vec<PoseFeature> {
    let centers: Vec<[f64; 3]> = views.iter().map(View::center).collect();
    let n = centers.len().max(1) as f64;
    let mean: [f64; 3] = std::array::from_fn(|i| centers.iter().map(|c| c[i]).sum::<f64>() / n);
    let spread = (centers
        .iter()
        .map(|c| (0..3).map(|i| (c[i] - mean[i]).powi(2)).sum::<f64>())
        .sum::<f64>()
        / n)
        .sqrt();
    let s = if spread > 0.0 && spread.is_finite() {
        spread
    } else {
        1.0
    };
    views
        .iter()
        .zip(&centers)
        .map(|(v, c)| {
            let a = v.axis();
            [c[0] / s, c[1] / s, c[2] / s, a[0], a[1], a[2]]
        })
        .collect()
}

/// Squared Euclidean distance between two pose features.
pub fn pose_distance2(a: &PoseFeature, b: &PoseFeature) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// Up to `count` reference views among `candidates` (view ids): all of them when there
/// are not more than `count`, else the candidate nearest each centroid of a seeded
/// k-means (k-means++ seeding, [`KMEANS_RESTARTS`] runs, best inertia) over their pose
/// features; a centroid whose nearest view is taken already gets the next nearest.
/// Sorted ascending. Deterministic for a seed.
pub fn select_references(
    features: &[PoseFeature],
    candidates: &[usize],
    count: usize,
    seed: u64,
) -> Vec<usize> {
    let mut refs: Vec<usize> = if candidates.len() <= count {
        candidates.to_vec()
    } else {
        let points: Vec<PoseFeature> = candidates.iter().map(|&v| features[v]).collect();
        let centroids = kmeans(&points, count, seed);
        let mut taken = vec![false; points.len()];
        let mut chosen = Vec::with_capacity(count);
        for c in &centroids {
            let best = (0..points.len()).filter(|&i| !taken[i]).min_by(|&i, &j| {
                pose_distance2(&points[i], c)
                    .total_cmp(&pose_distance2(&points[j], c))
                    .then(i.cmp(&j))
            });
            if let Some(i) = best {
                taken[i] = true;
                chosen.push(candidates[i]);
            }
        }
        chosen
    };
    refs.sort_unstable();
    refs.dedup();
    refs
}

/// The `k` views of `options` nearest to view `reference` by pose distance (ties by
/// view id), in order of distance.
pub fn nearest_views(
    features: &[PoseFeature],
    reference: usize,
    options: &[usize],
    k: usize,
) -> Vec<usize> {
    let mut by_distance: Vec<(f64, usize)> = options
        .iter()
        .filter(|&&j| j != reference)
        .map(|&j| (pose_distance2(&features[reference], &features[j]), j))
        .collect();
    by_distance.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    by_distance.into_iter().take(k).map(|(_, j)| j).collect()
}

/// Seeded k-means: the centroids of the best of [`KMEANS_RESTARTS`] runs (the points
/// themselves when `k` is not smaller than their number).
pub fn kmeans(points: &[PoseFeature], k: usize, seed: u64) -> Vec<PoseFeature> {
    if k == 0 || points.is_empty() {
        return Vec::new();
    }
    if k >= points.len() {
        return points.to_vec();
    }
    let mut best: Option<(f64, Vec<PoseFeature>)> = None;
    for run in 0..KMEANS_RESTARTS {
        let mut rng = keyed(&[seed, purpose::KMEANS, run]);
        let (inertia, centroids) = lloyd(points, seeds_plus_plus(points, k, &mut rng));
        if best.as_ref().is_none_or(|(b, _)| inertia < *b) {
            best = Some((inertia, centroids));
        }
    }
    best.map(|(_, c)| c).unwrap_or_default()
}

/// k-means++ seeding: the first centre uniformly, each next one with probability
/// proportional to the squared distance to the nearest centre so far.
fn seeds_plus_plus(points: &[PoseFeature], k: usize, rng: &mut Rng) -> Vec<PoseFeature> {
    let mut centres = vec![points[rng.below(points.len())]];
    let mut d2: Vec<f64> = points
        .iter()
        .map(|p| pose_distance2(p, &centres[0]))
        .collect();
    while centres.len() < k {
        let total: f64 = d2.iter().sum();
        let next = if total > 0.0 {
            let mut target = rng.unit() * total;
            let mut pick = points.len() - 1;
            for (i, d) in d2.iter().enumerate() {
                if target < *d {
                    pick = i;
                    break;
                }
                target -= d;
            }
            pick
        } else {
            rng.below(points.len())
        };
        centres.push(points[next]);
        for (d, p) in d2.iter_mut().zip(points) {
            *d = d.min(pose_distance2(p, &points[next]));
        }
    }
    centres
}

/// Lloyd iterations from the given centres until the assignment settles; returns the
/// inertia (sum of squared distances to the assigned centre) and the centres. An empty
/// cluster takes the point farthest from its centre (ties by index).
fn lloyd(points: &[PoseFeature], mut centres: Vec<PoseFeature>) -> (f64, Vec<PoseFeature>) {
    let k = centres.len();
    let mut assign = vec![usize::MAX; points.len()];
    for _ in 0..KMEANS_ITERATIONS {
        let mut changed = false;
        for (p, a) in points.iter().zip(assign.iter_mut()) {
            let nearest = nearest_centre(p, &centres);
            if *a != nearest {
                *a = nearest;
                changed = true;
            }
        }
        if !changed {
            break;
        }
        let mut sums = vec![[0.0; 6]; k];
        let mut counts = vec![0usize; k];
        for (p, &a) in points.iter().zip(&assign) {
            counts[a] += 1;
            for (s, x) in sums[a].iter_mut().zip(p) {
                *s += x;
            }
        }
        for c in 0..k {
            if counts[c] > 0 {
                centres[c] = sums[c].map(|s| s / counts[c] as f64);
            } else {
                let far = (0..points.len())
                    .max_by(|&i, &j| {
                        let di = pose_distance2(&points[i], &centres[assign[i]]);
                        let dj = pose_distance2(&points[j], &centres[assign[j]]);
                        di.total_cmp(&dj).then(j.cmp(&i))
                    })
                    .unwrap_or(0);
                centres[c] = points[far];
                assign[far] = c;
            }
        }
    }
    let inertia = points
        .iter()
        .map(|p| pose_distance2(p, &centres[nearest_centre(p, &centres)]))
        .sum();
    (inertia, centres)
}

fn nearest_centre(p: &PoseFeature, centres: &[PoseFeature]) -> usize {
    (0..centres.len())
        .min_by(|&i, &j| {
            pose_distance2(p, &centres[i])
                .total_cmp(&pose_distance2(p, &centres[j]))
                .then(i.cmp(&j))
        })
        .unwrap_or(0)
}

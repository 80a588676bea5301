//! Distance of reconstructed points (e.g. Gaussian centres) to an exact surface, and
//! robust summaries of those distances.
//!
//! The surface is a distance function supplied by the caller (for synthetic scenes,
//! `synth::Scene::distance_to_surface`), so this crate needs no geometry library and no
//! scene generator: the metric is the bookkeeping, the geometry is the scene's.

use rayon::prelude::*;
use serde::Serialize;

/// Summary of point-to-surface distances. Statistics are over the finite distances only;
/// with none, every statistic is NaN (written as `null` in JSON).
#[derive(Debug, Clone, Serialize)]
pub struct DistanceSummary {
    /// Number of finite distances summarised.
    pub count: usize,
    /// Median (linear interpolation between the two middle values for even counts).
    pub median: f64,
    /// Arithmetic mean (summed in f64 in index order).
    pub mean: f64,
    /// 90th percentile, linear interpolation between closest ranks (NumPy's default).
    pub p90: f64,
    /// The length the distances are compared to (e.g. the scene's bounding-box diagonal).
    pub extent: f64,
    /// `median / extent`.
    pub median_rel: f64,
}

/// Distances of points to a surface, `distance(p)` for each point (e.g.
/// `|p| scene.distance_to_surface(p)` for a synth scene), in parallel, deterministic (each
/// entry depends on its point only).
///
/// ```
/// use profuse_metrics::surface::surface_distances;
/// // The plane z = 0.
/// let d = surface_distances(&[[1.0, 2.0, 0.5], [0.0, 0.0, -2.0]], |p| p[2].abs());
/// assert_eq!(d, vec![0.5, 2.0]);
/// ```
pub fn surface_distances(
    points: &[[f32; 3]],
    distance: impl Fn([f64; 3]) -> f64 + Sync,
) -> Vec<f32> {
    surface_distances_with_progress(points, distance, |_| {})
}

/// [`surface_distances`], calling `progress(n)` after each finished block of `n` points
/// (from worker threads, in any order), e.g. to advance a progress bar.
pub fn surface_distances_with_progress(
    points: &[[f32; 3]],
    distance: impl Fn([f64; 3]) -> f64 + Sync,
    progress: impl Fn(usize) + Sync,
) -> Vec<f32> {
    let blocks: Vec<Vec<f32>> = points
        .par_chunks(PROGRESS_BLOCK)
        .map(|block| {
            let d = block
                .iter()
                .map(|p| distance(p.map(f64::from)) as f32)
                .collect();
            progress(block.len());
            d
        })
        .collect();
    blocks.concat()
}

/// Points per parallel task (and per progress report).
const PROGRESS_BLOCK: usize = 2048;

/// Length of the diagonal of a box of side lengths `size`: the extent distances are
/// compared to. For a synth scene, `size` is its `room_size`, the room's inner box
/// `[−x/2, x/2] × [−y/2, y/2] × [0, z]`, which contains every object.
///
/// ```
/// assert_eq!(profuse_metrics::surface::scene_extent([2.0, 3.0, 6.0]), 7.0);
/// ```
pub fn scene_extent(size: [f64; 3]) -> f64 {
    size.iter().map(|v| v * v).sum::<f64>().sqrt()
}

/// Quantile `q` in [0, 1] of sorted values, interpolating linearly between closest ranks.
fn quantile(sorted: &[f64], q: f64) -> f64 {
    match sorted.len() {
        0 => f64::NAN,
        n => {
            let pos = q * (n - 1) as f64;
            let lo = pos.floor() as usize;
            let hi = pos.ceil() as usize;
            sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
        }
    }
}

/// Median, mean and 90th percentile of the finite `distances`, and the median relative
/// to `extent`.
///
/// ```
/// use profuse_metrics::surface::summarize;
/// let s = summarize(&[0.4, 0.1, 0.2, 0.3, f32::NAN], 2.0);
/// assert_eq!(s.count, 4);
/// assert!((s.median - 0.25).abs() < 1e-6 && (s.median_rel - 0.125).abs() < 1e-6);
/// ```
pub fn summarize(distances: &[f32], extent: f64) -> DistanceSummary {
    let mut sorted: Vec<f64> = distances
        .iter()
        .filter(|d| d.is_finite())
        .map(|&d| f64::from(d))
        .collect();
    let mean = if sorted.is_empty() {
        f64::NAN
    } else {
        sorted.iter().sum::<f64>() / sorted.len() as f64
    };
    sorted.sort_by(f64::total_cmp);
    let median = quantile(&sorted, 0.5);
    DistanceSummary {
        count: sorted.len(),
        median,
        mean,
        p90: quantile(&sorted, 0.9),
        extent,
        median_rel: median / extent,
    }
}

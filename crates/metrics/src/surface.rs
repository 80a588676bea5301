//! Distance of reconstructed points (e.g. Gaussian centres) to the exact surface of a
//! synthetic scene, and robust summaries of those distances.

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

/// Distances of points to the exact synth surface (`synth::Scene::distance_to_surface`),
/// in parallel, deterministic (each entry depends on its point only).
pub fn surface_distances(points: &[[f32; 3]], scene: &synth::Scene) -> Vec<f32> {
    surface_distances_with_progress(points, scene, |_| {})
}

/// [`surface_distances`], calling `progress(n)` after each finished block of `n` points
/// (from worker threads, in any order), e.g. to advance a progress bar.
pub fn surface_distances_with_progress(
    points: &[[f32; 3]],
    scene: &synth::Scene,
    progress: impl Fn(usize) + Sync,
) -> Vec<f32> {
    let blocks: Vec<Vec<f32>> = points
        .par_chunks(PROGRESS_BLOCK)
        .map(|block| {
            let d = block
                .iter()
                .map(|p| scene.distance_to_surface(p.map(f64::from)) as f32)
                .collect();
            progress(block.len());
            d
        })
        .collect();
    blocks.concat()
}

/// Points per parallel task (and per progress report).
const PROGRESS_BLOCK: usize = 2048;

/// Length of the diagonal of the scene's bounding box: the room's inner box
/// `[−x/2, x/2] × [−y/2, y/2] × [0, z]`, which contains every object.
pub fn scene_extent(scene: &synth::Scene) -> f64 {
    scene.room_size.iter().map(|v| v * v).sum::<f64>().sqrt()
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

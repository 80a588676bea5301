//! `metrics bench`: throughput of every metric on generated data (no files): ScanNet
//! evaluation, ARI, polygon rasterisation + IoU, surface distances in synth's demo room.

use std::time::Instant;

use profuse_formats::rng::SplitMix64;
use profuse_metrics::cluster::adjusted_rand_index;
use profuse_metrics::mask::rasterize_polygon;
use profuse_metrics::scannet::{evaluate, ClassSet};
use profuse_metrics::surface::{scene_extent, summarize, surface_distances_with_progress};
use serde_json::{json, Value};

use crate::common;
use crate::BoxError;

/// The benchmark's parameters (the `metrics bench` arguments).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::Args)]
pub struct Params {
    /// Vertices of the ScanNet evaluation.
    #[arg(long, default_value_t = 1_000_000)]
    pub vertices: usize,
    /// Items of the ARI / cluster scores.
    #[arg(long, default_value_t = 1_000_000)]
    pub items: usize,
    /// Frame width of the LERF rasterisation.
    #[arg(long, default_value_t = 986)]
    pub width: u32,
    /// Frame height of the LERF rasterisation.
    #[arg(long, default_value_t = 728)]
    pub height: u32,
    /// Polygons (of 200 vertices each) rasterised and scored.
    #[arg(long, default_value_t = 200)]
    pub polygons: usize,
    /// Points of the surface-distance benchmark (in synth's demo room).
    #[arg(long, default_value_t = 100_000)]
    pub points: usize,
}

/// Runs the benchmark; `show` prints each part's seconds on stderr.
pub fn run(p: &Params, show: bool) -> Result<Value, BoxError> {
    let Params {
        vertices,
        items,
        width,
        height,
        polygons,
        points,
    } = *p;
    let mut rng = SplitMix64::new(42);
    let mut next = |m: u64| rng.next_u64() % m.max(1);

    // ScanNet: labels 0..=40, predictions -1..=40, 80 % correct.
    let truth: Vec<u32> = (0..vertices).map(|_| next(41) as u32).collect();
    let pred: Vec<i32> = truth
        .iter()
        .map(|&t| {
            if next(5) == 0 {
                next(42) as i32 - 1
            } else {
                t as i32
            }
        })
        .collect();
    let t = Instant::now();
    let mut scannet_miou = Vec::new();
    for set in ClassSet::PAPER {
        scannet_miou.push(evaluate(&pred, &truth, set)?.miou);
    }
    let scannet_s = t.elapsed().as_secs_f64();
    if show {
        eprintln!("scannet: {scannet_s:.3} s");
    }

    // ARI: 1000 truth objects, predictions 90 % right, 5 % unassigned.
    let objects: Vec<u32> = (0..items).map(|_| next(1000) as u32).collect();
    let clusters: Vec<u32> = objects
        .iter()
        .map(|&o| match next(20) {
            0 => u32::MAX,
            1 => next(1000) as u32,
            _ => o,
        })
        .collect();
    let t = Instant::now();
    let ari = adjusted_rand_index(&clusters, &objects)?;
    let ari_s = t.elapsed().as_secs_f64();
    if show {
        eprintln!("ari: {ari_s:.3} s");
    }

    // LERF: star-shaped 200-gon per polygon, rasterised and scored against a shifted copy.
    let t = Instant::now();
    let iou_sum = star_polygon_ious(polygons, width, height, &mut next);
    let lerf_s = t.elapsed().as_secs_f64();
    if show {
        eprintln!("lerf: {lerf_s:.3} s");
    }

    // Surface: points in synth's demo room.
    let scene = synth::Scene::generate(&synth::Config::preset(synth::Preset::Demo, 0))?;
    let pts = room_points(points, scene.room_size, &mut next);
    let t = Instant::now();
    let d = surface_distances_with_progress(&pts, |p| scene.distance_to_surface(p), |_| {});
    let surface_s = t.elapsed().as_secs_f64();
    let median = summarize(&d, scene_extent(scene.room_size)).median;

    let rate = |n: usize, s: f64| if s > 0.0 { n as f64 / s } else { f64::NAN };
    Ok(json!({
        "cores": std::thread::available_parallelism().map_or(1, |n| n.get()),
        "rayon_num_threads": std::env::var("RAYON_NUM_THREADS").ok(),
        "scannet": {"vertices": vertices, "sets": 3, "seconds": scannet_s,
                    "vertices_per_s": rate(vertices * 3, scannet_s), "miou": scannet_miou},
        "ari": {"items": items, "seconds": ari_s, "items_per_s": rate(items, ari_s), "ari": ari},
        "lerf": {"width": width, "height": height, "pairs": polygons, "seconds": lerf_s,
                 "pairs_per_s": rate(polygons, lerf_s),
                 "mean_iou": if polygons > 0 { iou_sum / polygons as f64 } else { f64::NAN }},
        "surface": {"points": points, "objects": scene.len(), "seconds": surface_s,
                    "points_per_s": rate(points, surface_s), "median": median},
        "peak_rss_mb": common::peak_rss_mb(),
    }))
}

/// The LERF part: `polygons` star-shaped 200-gons at random places of a `width` x `height`
/// grid, each rasterised and scored against a shifted copy; returns the sum of the IoUs.
/// `next(m)` draws in `0..m`.
fn star_polygon_ious(
    polygons: usize,
    width: u32,
    height: u32,
    next: &mut dyn FnMut(u64) -> u64,
) -> f64 {
    let mut iou_sum = 0.0;
    for k in 0..polygons {
        let (cx, cy) = (
            next(u64::from(width)) as f64,
            next(u64::from(height)) as f64,
        );
        let r = 20.0 + next(200) as f64;
        let star = |dx: f64| -> Vec<[f64; 2]> {
            (0..200)
                .map(|i| {
                    let a = i as f64 * std::f64::consts::TAU / 200.0;
                    let rr = r * (1.0 + 0.3 * (5.0 * a + k as f64).sin());
                    [cx + dx + rr * a.cos(), cy + rr * a.sin()]
                })
                .collect()
        };
        let gt = rasterize_polygon(&star(0.0), width, height);
        let pr = rasterize_polygon(&star(r * 0.2), width, height);
        let i = gt.intersection(&pr);
        let u = gt.count() + pr.count() - i;
        if u > 0 {
            iou_sum += i as f64 / u as f64;
        }
    }
    iou_sum
}

/// The surface part's `points` uniform points in a room of `room_size` (centred on the
/// vertical axis, floor at z = 0). `next(m)` draws in `0..m`.
fn room_points(
    points: usize,
    [sx, sy, sz]: [f64; 3],
    next: &mut dyn FnMut(u64) -> u64,
) -> Vec<[f32; 3]> {
    (0..points)
        .map(|_| {
            let u = |s: f64, m: &mut dyn FnMut(u64) -> u64| {
                (m(1 << 20) as f64 / f64::from(1 << 20) * s) as f32
            };
            [
                u(sx, &mut *next) - (sx / 2.0) as f32,
                u(sy, &mut *next) - (sy / 2.0) as f32,
                u(sz, &mut *next),
            ]
        })
        .collect()
}

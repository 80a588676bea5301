//! `warp-graph bench`: the association on synthetic Voronoi label maps with exact shift
//! warps (the crate's `synthetic` scenes); ordered view pairs per second, CPU seconds,
//! peak memory and the ARI of the proposals against the true cells.

use std::time::Instant;

use serde_json::{json, Value};
use warp_graph::{synthetic, Association, FlatParams, Inputs, Params};

use crate::common;
use crate::BoxError;

/// The benchmark's parameters (the `warp-graph bench` arguments).
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct BenchParams {
    /// Image and mask width.
    #[arg(long, default_value_t = 1000)]
    pub width: usize,
    /// Image and mask height.
    #[arg(long, default_value_t = 730)]
    pub height: usize,
    /// Views.
    #[arg(long, default_value_t = 8)]
    pub views: usize,
    /// Mean masks (Voronoi cells) per view.
    #[arg(long, default_value_t = 100)]
    pub masks_per_view: usize,
    /// Warp grid = image subsampled by this step (1 = one warp cell per pixel).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub grid_step: u64,
    /// Views paired with each view on either side (both directions).
    #[arg(long, default_value_t = 1)]
    pub neighbours: usize,
    /// Run the association this many times and report the fastest.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub repeat: u64,
    #[command(flatten)]
    pub params: FlatParams,
}

/// Runs the benchmark; `progress` gets (view pairs done, view pairs).
pub fn run(b: &BenchParams, progress: &(dyn Fn(usize, usize) + Sync)) -> Result<Value, BoxError> {
    let cfg = synthetic::Config {
        views: b.views,
        width: b.width,
        height: b.height,
        grid_step: b.grid_step as usize,
        masks_per_view: b.masks_per_view,
        neighbours: b.neighbours,
        warp_noise: 0.5,
        ..synthetic::Config::default()
    };
    let params = Params::from(b.params);
    let t = Instant::now();
    let scene = synthetic::scene(&cfg);
    let generate_s = t.elapsed().as_secs_f64();
    let input_mb = (scene.masks.labels.len() * 2
        + (scene.matches.warp.len() + scene.matches.certainty.len()) * 4) as f64
        / (1024.0 * 1024.0);
    let association = Association::new(Inputs::new(&scene.masks, &scene.matches), &params)?;
    let (mut best, mut best_cpu) = (f64::INFINITY, 0.0);
    let mut outcome = None;
    for _ in 0..b.repeat {
        let (t, cpu) = (Instant::now(), common::process_cpu_s());
        let o = association.run(progress)?;
        let wall = t.elapsed().as_secs_f64();
        if wall < best {
            (best, best_cpu) = (wall, common::process_cpu_s() - cpu);
        }
        outcome = Some(o);
    }
    let o = outcome.ok_or("no run")?;
    let scores = profuse_metrics::cluster::proposal_scores(&o.proposals, &scene.truth)?;
    let pairs = o.report.pairs;
    Ok(json!({
        "width": cfg.width,
        "height": cfg.height,
        "grid": o.report.grid,
        "views": cfg.views,
        "masks": o.report.masks,
        "masks_per_view": o.report.masks as f64 / cfg.views.max(1) as f64,
        "pairs": pairs,
        "threads": splat_raster::rayon::current_num_threads(),
        "visibility": o.report.visibility,
        "sampling": o.report.sampling,
        "seconds": best,
        "cpu_s": best_cpu,
        "pairs_per_s": pairs as f64 / best,
        "mcells_per_s": o.report.cells.total as f64 / best / 1e6,
        "edges_tested": o.report.edges_tested,
        "edges_accepted": o.report.edges_accepted,
        "proposals": o.report.components.proposals,
        "ari": scores.ari,
        "generate_s": generate_s,
        "input_mb": input_mb,
        "peak_rss_mb": common::peak_rss_mb(),
    }))
}

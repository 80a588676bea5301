//! `gs-refine bench`: the cost of one refinement iteration on a real scene — forward,
//! loss, backward and Adam at a chosen scale of one view — as one JSON object.

use std::path::PathBuf;
use std::time::Instant;

use gs_refine::loss::loss_and_grad;
use gs_refine::views::load_views;
use gs_refine::{backward, forward, Config, Grads, Params, Trainer, ViewState};
use profuse_formats::{Cameras, FileKind, Gaussians};
use serde_json::{json, Value};

use crate::common;
use crate::BoxError;

/// The benchmark's parameters (the `gs-refine bench` arguments).
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct BenchParams {
    /// Gaussians file (profuse.gaussians), e.g. examples/fox.sh's gaussians.safetensors.
    #[arg(long)]
    pub gaussians: PathBuf,
    /// Cameras file (profuse.cameras).
    #[arg(long)]
    pub cameras: PathBuf,
    /// Folder the cameras' image names are relative to.
    #[arg(long)]
    pub images: PathBuf,
    /// View to time.
    #[arg(long, default_value_t = 0)]
    pub view: usize,
    /// Image scale (0.5 of the fox's 1080 x 1920 photos = 540 x 960).
    #[arg(long, default_value_t = 0.5)]
    pub scale: f64,
    /// Timed repetitions of each phase; the median is reported.
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u64).range(1..))]
    pub repeat: u64,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Runs the benchmark.
pub fn run(b: &BenchParams) -> Result<Value, BoxError> {
    let g = Gaussians::read(&b.gaussians)?;
    let cams = Cameras::read(&b.cameras)?;
    let params = Params::from_gaussians(&g)?;
    let exclude: Vec<usize> = (0..cams.len()).filter(|v| *v != b.view).collect();
    let views = load_views(&cams, &b.images, b.scale, &exclude)?;
    let (_, cam, target) = views.first().ok_or("no such view")?.clone();
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut st = ViewState::default();
    let mut grads = Grads::zeros(&params);
    let mut dl = Vec::new();
    let (mut fwd, mut loss, mut bwd) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..b.repeat {
        let t0 = Instant::now();
        forward(&params, &cam, [0.0; 3], &mut st);
        let t1 = Instant::now();
        loss_and_grad(st.color(), &target.rgb, w, h, &mut dl);
        let t2 = Instant::now();
        grads.clear();
        backward(&params, &cam, [0.0; 3], &mut st, &dl, &mut grads);
        let t3 = Instant::now();
        fwd.push((t1 - t0).as_secs_f64());
        loss.push((t2 - t1).as_secs_f64());
        bwd.push((t3 - t2).as_secs_f64());
    }
    let config = Config {
        iterations: b.repeat as usize,
        ..Config::default()
    };
    let mut tr = Trainer::new(params, views, config)?;
    let t0 = Instant::now();
    for _ in 0..b.repeat {
        tr.step();
    }
    let iter_s = t0.elapsed().as_secs_f64() / b.repeat as f64;
    let (forward_ms, backward_ms) = (median(fwd) * 1e3, median(bwd) * 1e3);
    Ok(json!({
        "gaussians": g.len(),
        "width": w,
        "height": h,
        "visible": st.visible(),
        "tile_pairs": st.pairs(),
        "threads": rayon_threads(),
        "forward_ms": forward_ms,
        "loss_ms": median(loss) * 1e3,
        "backward_ms": backward_ms,
        "backward_over_forward": backward_ms / forward_ms,
        "iters_per_s": 1.0 / iter_s,
        "peak_rss_mb": common::peak_rss_mb(),
    }))
}

fn rayon_threads() -> usize {
    splat_raster::rayon::current_num_threads()
}

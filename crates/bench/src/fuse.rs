//! `fuse bench`: registration (render + accumulate + finish) on a synth `scale` scene with
//! its ground-truth Gaussians and proposals from its ground-truth objects.

use std::path::{Path, PathBuf};
use std::time::Instant;

use profuse_formats::{Cameras, FileKind, Gaussians, Masks};
use profuse_fuse::job::Register;
use profuse_fuse::{
    accumulate, finish, Groups, MemberWeight, Orphans, Precision, Scene, ViewReport,
};
use serde::Serialize;
use serde_json::{json, Value};

use crate::common::{self, SceneDir};
use crate::BoxError;

/// The benchmark's parameters (the `fuse bench` arguments).
#[derive(Debug, Clone, PartialEq, Serialize, clap::Args)]
pub struct Params {
    /// Ground-truth Gaussians of the scene.
    #[arg(long, default_value_t = 1_000_000)]
    pub gaussians: usize,
    /// Views.
    #[arg(long, default_value_t = 200)]
    pub views: usize,
    /// Image (and mask) width.
    #[arg(long, default_value_t = 1000)]
    pub width: u32,
    /// Image (and mask) height.
    #[arg(long, default_value_t = 730)]
    pub height: u32,
    /// Top-K (1..=256).
    #[arg(long, default_value_t = profuse_fuse::DEFAULT_K, value_parser = common::top_k)]
    pub k: usize,
    /// Scene seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Keep the scene in this directory and reuse it when it already holds a scene of
    /// these sizes (default: a temporary directory, removed afterwards).
    #[arg(long)]
    pub scene_dir: Option<PathBuf>,
    /// Also write the features next to the scene (timed separately as `write_s`).
    #[arg(long)]
    pub write: bool,
    /// Register with every mask as its own group (the baseline) instead of proposals.
    #[arg(long, conflicts_with = "registration")]
    pub no_proposals: bool,
    /// `proposals` (paper) or `blend` (see `fuse run --help`).
    #[arg(long, default_value = "proposals", value_parser = common::choice::<Register>)]
    pub registration: Register,
}

/// The files the benchmark reads from its scene.
const FILES: [&str; 2] = ["masks.safetensors", "gt/gaussians.safetensors"];

/// The synth configuration of the benchmark scene (no matches: registration does not
/// read them).
pub fn scene_config(
    gaussians: usize,
    views: usize,
    width: u32,
    height: u32,
    seed: u64,
) -> synth::Config {
    let mut c = synth::Config::preset(synth::Preset::Scale, seed);
    c.gaussians = gaussians;
    c.views = views;
    c.width = width;
    c.height = height;
    c.write_matches = false;
    c
}

/// Per-view rasterizer counters.
#[derive(Debug, Default)]
struct RenderCounters {
    visible: Vec<usize>,
    tile_pairs: Vec<usize>,
}

/// Runs the benchmark; `on_view` sees every rendered view (for a progress bar).
pub fn run(
    p: &Params,
    show: bool,
    on_view: &mut dyn FnMut(&ViewReport),
) -> Result<Value, BoxError> {
    let config = scene_config(p.gaussians, p.views, p.width, p.height, p.seed);
    let dir = SceneDir::new(p.scene_dir.as_deref(), "fuse");
    let generate_s = common::generate_in_child(dir.path(), &config, &FILES, show)?;
    let dir = dir.path().to_path_buf();

    let t0 = Instant::now();
    let gaussians = Gaussians::read(dir.join("gt/gaussians.safetensors"))?;
    let cameras = Cameras::read(dir.join("cameras.safetensors"))?;
    let masks = Masks::read(dir.join("masks.safetensors"))?;
    let groups = bench_groups(p, &dir, &masks)?;
    let scene = Scene::new(&gaussians, &cameras, &masks);
    let load_s = t0.elapsed().as_secs_f64();

    let mut counters = RenderCounters::default();
    let t0 = Instant::now();
    let cpu0 = common::process_cpu_s();
    let partial = accumulate(&scene, &groups, p.k, 0..cameras.len(), &mut |r| {
        if r.rendered {
            counters.visible.push(r.render.visible);
            counters.tile_pairs.push(r.render.tile_pairs);
        }
        on_view(r)
    })?;
    let precision = Precision::of(&masks.features);
    let reg = finish(&partial, precision);
    let seconds = t0.elapsed().as_secs_f64();
    let cpu_s = common::process_cpu_s() - cpu0;
    let write_s = if p.write {
        let t = Instant::now();
        reg.features.write(dir.join("features.safetensors"))?;
        Some(t.elapsed().as_secs_f64())
    } else {
        None
    };
    let s = &reg.summary;
    let t = partial.timings();
    Ok(json!({
        "seconds": seconds,
        "cpu_s": cpu_s,
        "peak_rss_mb": common::peak_rss_mb(),
        "views_per_s": cameras.len() as f64 / seconds,
        "gaussians": gaussians.len(),
        "views": cameras.len(),
        "width": masks.width,
        "height": masks.height,
        "k": p.k,
        "grouping": groups.grouping.name(),
        "threads": splat_raster::rayon::current_num_threads(),
        "load_s": load_s,
        "generate_s": generate_s,
        "write_s": write_s,
        "scene_dir": p.scene_dir,
        "valid": s.valid,
        "nnz": s.nnz,
        "groups": s.groups,
        "groups_with_descriptor": s.groups_with_descriptor,
        "masks": s.masks,
        "assigned_masks": s.assigned_masks,
        "mask_mass": {
            "masks_with_mass": s.masks_with_mass,
            "total": s.mass_total,
            "min": s.mass_min,
            "median": s.mass_median,
            "max": s.mass_max,
        },
        "pixels": s.pixels,
        "hits": s.hits,
        "feature_dim": partial.dim(),
        "precision": precision.name(),
        "finish_s": s.finish_s,
        "raster_s": t.raster_s,
        "accumulate_s": t.accumulate_s,
        "compact_s": t.compact_s,
        "render": {
            "median_visible": common::median_count(&mut counters.visible),
            "median_tile_pairs": common::median_count(&mut counters.tile_pairs),
        },
    }))
}

/// The grouping registered: one group per mask with `--no-proposals`, else the scene's
/// ground-truth objects as proposals (`gt/mask_objects.json` under `dir`), registered as
/// `p.registration` says.
fn bench_groups(p: &Params, dir: &Path, masks: &Masks) -> Result<Groups, BoxError> {
    if p.no_proposals {
        return Ok(Groups::per_mask(masks));
    }
    let proposals = profuse_fuse::testing::proposals_from_mask_objects(
        dir.join("gt/mask_objects.json"),
        masks,
        1,
    )?;
    // Ground-truth proposals carry no shares: every member weighs its mass.
    let name = "ground-truth proposals";
    let build = match p.registration {
        Register::Proposals => Groups::from_proposals,
        Register::Blend => Groups::blend,
    };
    Ok(build(
        masks,
        &proposals,
        Orphans::Ignore,
        MemberWeight::Mass,
        name,
    )?)
}

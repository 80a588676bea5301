//! `gs-init bench`: an initialisation of a synthetic scene (generated into a temporary
//! folder, removed afterwards) or of a scene directory; points per second and peak memory.

use std::path::PathBuf;
use std::time::Instant;

use gs_init::{initialise_files, FlatParams, Inputs, Params};
use serde_json::{json, Value};

use crate::common::{self, SceneDir};
use crate::BoxError;

/// The benchmark's parameters (the `gs-init bench` arguments).
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct BenchParams {
    /// Scene directory (SPEC.md §6) instead of a generated synthetic scene.
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Preset of the generated scene: tiny, demo or scale.
    #[arg(long, default_value = "demo", conflicts_with = "scene")]
    pub preset: String,
    /// Seed of the generated scene.
    #[arg(long, default_value_t = 0, conflicts_with = "scene")]
    pub scene_seed: u64,
    /// Run this many times and report the fastest (robust to other load).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u64).range(1..))]
    pub repeat: u64,
    #[command(flatten)]
    pub params: FlatParams,
}

/// Runs the benchmark; `progress` gets (reference views done, reference views).
pub fn run(b: &BenchParams, progress: &(dyn Fn(usize, usize) + Sync)) -> Result<Value, BoxError> {
    let tmp = SceneDir::new(None, "gs-init");
    let mut generate_s = None;
    let dir = match &b.scene {
        Some(d) => d.clone(),
        None => {
            let mut config = synth::Config::preset(synth::Preset::parse(&b.preset)?, b.scene_seed);
            config.write_masks = false;
            config.gaussians = 0;
            let t0 = Instant::now();
            synth::generate(&config, tmp.path())?;
            generate_s = Some(t0.elapsed().as_secs_f64());
            tmp.path().to_path_buf()
        }
    };
    let inputs = Inputs::scene(&dir)?;
    let params = Params::from(b.params);
    let mut best = f64::INFINITY;
    let mut report = None;
    for _ in 0..b.repeat {
        let t0 = Instant::now();
        let (_, r) = initialise_files(&inputs, &params, progress)?;
        best = best.min(t0.elapsed().as_secs_f64());
        report = Some(r);
    }
    let report = report.ok_or("no run")?;
    let scene = match &b.scene {
        Some(d) => json!(d),
        None => json!(format!("synth {} seed {}", b.preset, b.scene_seed)),
    };
    Ok(json!({
        "points_per_s": report.triangulated as f64 / best,
        "dlt_solves_per_s": report.dlt_solves as f64 / best,
        "seconds": best,
        "repeat": b.repeat,
        "threads": gs_init::rayon::current_num_threads(),
        "peak_rss_mb": common::peak_rss_mb(),
        "mode": report.mode,
        "views": report.views,
        "references": report.references.len(),
        "sampled": report.sampled,
        "triangulated": report.triangulated,
        "dlt_solves": report.dlt_solves,
        "kept": report.kept,
        "rejected": report.rejected,
        "median_reproj_px": report.median_reproj_px,
        "scene": scene,
        "generate_s": generate_s,
        "params": report.params,
    }))
}

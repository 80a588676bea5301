//! `gs-init`: triangulate confident matches into initial 3D Gaussians (paper §3.1), and
//! benchmark it.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error (naming the file) goes to stderr, the exit code is 1, and nothing
//! is written.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::str::FromStr;
use std::time::Instant;

use clap::{Args, Parser, Subcommand};
use gs_init::{initialise_files, Inputs, MatchFile, Params, Report, Scale};
use indicatif::{ProgressBar, ProgressStyle};
use profuse_formats::FileKind;
use profuse_tools::{chatty, peak_rss_mb, run, warn, BoxError};
use serde_json::{json, Value};

#[derive(Debug, Parser)]
#[command(
    name = "gs-init",
    version,
    about = "Triangulate confident matches into initial 3D Gaussians (ProFuse §3.1 / EDGS)",
    long_about = "Triangulate confident dense (profuse.matches) or sparse (profuse.sparse_matches) \
                  correspondences into initial 3D Gaussians (ProFuse §3.1, after EDGS). Dense: \
                  reference views by seeded k-means over camera poses, each triangulated against \
                  its nearest views by pose that it has match pairs with. Sparse: every listed pair, \
                  each match between its two views. Up to --budget confident matches are sampled per \
                  reference (seeded), triangulated by linear DLT, gated (non-finite, behind a \
                  camera, reprojection error, triangulation angle), and become Gaussians coloured \
                  from the reference image (SH degree 0, identity rotation, opacity 0.5). Output is \
                  byte-identical for any thread count (RAYON_NUM_THREADS). Prints one JSON report on \
                  stdout: counts that add up (sampled = kept + rejected.total) and the parameters."
)]
struct Cli {
    /// Do not print progress or warnings on stderr.
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Initialise Gaussians from cameras, images and matches; write a gaussians file.
    Run {
        /// Cameras file (profuse.cameras).
        #[arg(long)]
        cameras: PathBuf,
        /// Folder that cameras.image_names are relative to (the scene directory), or the
        /// folder holding the image files themselves. Only reference views' images are read.
        #[arg(long)]
        images: PathBuf,
        /// Dense matches file (profuse.matches).
        #[arg(
            long,
            required_unless_present = "sparse_matches",
            conflicts_with = "sparse_matches"
        )]
        matches: Option<PathBuf>,
        /// Sparse matches file (profuse.sparse_matches).
        #[arg(long)]
        sparse_matches: Option<PathBuf>,
        /// Gaussians file to write (profuse.gaussians, SH degree 0).
        #[arg(long)]
        out: PathBuf,
        /// Also write the JSON report to this file.
        #[arg(long)]
        report_json: Option<PathBuf>,
        #[command(flatten)]
        params: ParamArgs,
    },
    /// Time an initialisation of a synthetic scene (generated into a temporary folder and
    /// removed afterwards) or of a scene directory; print points per second and peak
    /// memory as one JSON object.
    Bench {
        /// Scene directory (SPEC.md §6) instead of a generated synthetic scene.
        #[arg(long)]
        scene: Option<PathBuf>,
        /// Preset of the generated scene: tiny, demo or scale.
        #[arg(long, default_value = "demo", conflicts_with = "scene")]
        preset: String,
        /// Seed of the generated scene.
        #[arg(long, default_value_t = 0, conflicts_with = "scene")]
        scene_seed: u64,
        /// Worker threads (default: rayon's, i.e. RAYON_NUM_THREADS or the core count).
        #[arg(long)]
        threads: Option<usize>,
        /// Run this many times and report the fastest (robust to other load).
        #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u64).range(1..))]
        repeat: u64,
        #[command(flatten)]
        params: ParamArgs,
    },
}

/// The parameters of `gs_init::Params`; defaults are the paper's (EDGS's) values.
#[derive(Debug, Clone, Args)]
struct ParamArgs {
    /// Reference views chosen by k-means over camera poses (dense matches only).
    #[arg(long, default_value_t = Params::default().references, help_heading = "Parameters")]
    references: usize,
    /// Neighbours per reference by pose distance, among views it has pairs with (dense only).
    #[arg(long, default_value_t = Params::default().neighbours, help_heading = "Parameters")]
    neighbours: usize,
    /// A match is confident when its certainty is above this.
    #[arg(long, default_value_t = Params::default().certainty_threshold, help_heading = "Parameters")]
    certainty_threshold: f64,
    /// Confident matches sampled per reference view.
    #[arg(long, default_value_t = Params::default().budget, help_heading = "Parameters")]
    budget: usize,
    /// Seed of the reference k-means and of the sampling.
    #[arg(long, default_value_t = Params::default().seed, help_heading = "Parameters")]
    seed: u64,
    /// Largest reprojection error in pixels accepted in each of the two views.
    #[arg(long, default_value_t = Params::default().max_reproj_px, help_heading = "Parameters")]
    max_reproj_px: f64,
    /// Smallest angle in degrees between the two viewing rays at the point.
    #[arg(long, default_value_t = Params::default().min_angle_deg, help_heading = "Parameters")]
    min_angle_deg: f64,
    /// A point needs camera z > near in both views (scene units).
    #[arg(long, default_value_t = Params::default().near, help_heading = "Parameters")]
    near: f64,
    /// Initial scale rule: `pixels[:P]` (σ = P reference pixels at the point's depth,
    /// P = 1 by default), `distance[:F]` (σ = F × distance to the reference camera, EDGS:
    /// F = 0.0005) or `knn[:K]` (σ = RMS distance to the K nearest Gaussians, 3DGS: K = 3).
    #[arg(
        long,
        default_value = "pixels:1",
        value_name = "RULE",
        help_heading = "Parameters"
    )]
    scale: ScaleArg,
}

impl ParamArgs {
    fn params(&self) -> Params {
        Params {
            references: self.references,
            neighbours: self.neighbours,
            certainty_threshold: self.certainty_threshold,
            budget: self.budget,
            seed: self.seed,
            max_reproj_px: self.max_reproj_px,
            min_angle_deg: self.min_angle_deg,
            near: self.near,
            scale: self.scale.0,
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct ScaleArg(Scale);

impl FromStr for ScaleArg {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let (mode, value) = match s.split_once(':') {
            Some((m, v)) => (m, Some(v)),
            None => (s, None),
        };
        let number = |default: f64| -> Result<f64, String> {
            value.map_or(Ok(default), |v| {
                v.parse::<f64>()
                    .map_err(|e| format!("`{v}` is not a number: {e}"))
            })
        };
        let scale = match mode {
            "pixels" => Scale::Pixels {
                pixels: number(1.0)?,
            },
            "distance" => Scale::Distance {
                factor: number(0.0005)?,
            },
            "knn" => Scale::Knn {
                k: value.map_or(Ok(3), |v| {
                    v.parse::<usize>()
                        .map_err(|e| format!("`{v}` is not a count: {e}"))
                })?,
            },
            other => {
                return Err(format!(
                    "unknown scale rule `{other}`: expected pixels[:P], distance[:F] or knn[:K]"
                ))
            }
        };
        Ok(ScaleArg(scale))
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| execute(cli.command, quiet))
}

fn execute(command: Command, quiet: bool) -> Result<Value, BoxError> {
    match command {
        Command::Run {
            cameras,
            images,
            matches,
            sparse_matches,
            out,
            report_json,
            params,
        } => {
            let matches = match (matches, sparse_matches) {
                (Some(m), _) => MatchFile::Dense(m),
                (None, Some(s)) => MatchFile::Sparse(s),
                (None, None) => return Err("give --matches or --sparse-matches".into()),
            };
            let inputs = Inputs {
                cameras,
                images,
                matches,
            };
            let params = params.params();
            let t0 = Instant::now();
            let (gaussians, report) =
                with_progress(chatty(quiet), |p| initialise_files(&inputs, &params, p))?;
            let seconds = t0.elapsed().as_secs_f64();
            if report.kept == 0 {
                warn(quiet, "no point survived: the gaussians file is empty");
            }
            if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
                std::fs::create_dir_all(parent)
                    .map_err(|e| format!("cannot create {}: {e}", parent.display()))?;
            }
            gaussians.write(&out)?;
            let mut value = report_value(&report)?;
            value["out"] = json!(out);
            value["seconds"] = json!(seconds);
            if let Some(path) = report_json {
                write_json(&path, &value)?;
            }
            Ok(value)
        }
        Command::Bench {
            scene,
            preset,
            scene_seed,
            threads,
            repeat,
            params,
        } => {
            if let Some(n) = threads {
                gs_init::rayon::ThreadPoolBuilder::new()
                    .num_threads(n)
                    .build_global()?;
            }
            let generated = match &scene {
                Some(_) => None,
                None => Some(GeneratedScene::new(&preset, scene_seed)?),
            };
            let dir = match (&scene, &generated) {
                (Some(d), _) => d.clone(),
                (None, Some(g)) => g.dir.clone(),
                (None, None) => return Err("no scene".into()),
            };
            let inputs = Inputs::scene(&dir)?;
            let params = params.params();
            let mut best = f64::INFINITY;
            let mut report = None;
            for _ in 0..repeat {
                let t0 = Instant::now();
                let (_, r) =
                    with_progress(chatty(quiet), |p| initialise_files(&inputs, &params, p))?;
                best = best.min(t0.elapsed().as_secs_f64());
                report = Some(r);
            }
            let report = report.ok_or("no run")?;
            Ok(json!({
                "points_per_s": report.triangulated as f64 / best,
                "dlt_solves_per_s": report.dlt_solves as f64 / best,
                "seconds": best,
                "repeat": repeat,
                "threads": gs_init::rayon::current_num_threads(),
                "peak_rss_mb": peak_rss_mb(),
                "mode": report.mode,
                "views": report.views,
                "references": report.references.len(),
                "sampled": report.sampled,
                "triangulated": report.triangulated,
                "dlt_solves": report.dlt_solves,
                "kept": report.kept,
                "rejected": report.rejected,
                "median_reproj_px": report.median_reproj_px,
                "scene": scene.map_or_else(|| json!(format!("synth {preset} seed {scene_seed}")), |d| json!(d)),
                "generate_s": generated.as_ref().map(|g| g.seconds),
                "params": report.params,
            }))
        }
    }
}

/// Runs `f` with a progress callback that drives a bar over the reference views.
fn with_progress<T>(show: bool, f: impl FnOnce(&(dyn Fn(usize, usize) + Sync)) -> T) -> T {
    if !show {
        return f(&|_, _| {});
    }
    let bar = ProgressBar::new(0);
    if let Ok(style) = ProgressStyle::with_template(
        "gs-init {bar:40} {pos}/{len} reference views [{elapsed} < {eta}]",
    ) {
        bar.set_style(style);
    }
    let result = f(&|done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    });
    bar.finish_and_clear();
    result
}

fn report_value(report: &Report) -> Result<Value, BoxError> {
    Ok(serde_json::to_value(report)?)
}

/// Writes pretty JSON atomically.
fn write_json(path: &Path, value: &Value) -> Result<(), BoxError> {
    let text = serde_json::to_string_pretty(value)? + "\n";
    profuse_tools::write_file(path, text.as_bytes())
}

/// A synthetic scene in a temporary folder, removed on drop.
struct GeneratedScene {
    dir: PathBuf,
    seconds: f64,
}

impl GeneratedScene {
    fn new(preset: &str, seed: u64) -> Result<GeneratedScene, BoxError> {
        let dir = std::env::temp_dir().join(format!("gs-init-bench-{}", std::process::id()));
        let mut config = synth::Config::preset(synth::Preset::parse(preset)?, seed);
        config.write_masks = false;
        config.gaussians = 0;
        let t0 = Instant::now();
        // Made before generating, so that a failed generation is cleaned up too.
        let mut scene = GeneratedScene { dir, seconds: 0.0 };
        synth::generate(&config, &scene.dir)?;
        scene.seconds = t0.elapsed().as_secs_f64();
        Ok(scene)
    }
}

impl Drop for GeneratedScene {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

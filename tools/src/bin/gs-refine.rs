//! `gs-refine`: photometric refinement of 3D Gaussians on the CPU (3DGS loss and Adam, no
//! densification), and its benchmark.
//!
//! Every input and output is a command-line argument. On success one JSON summary goes to
//! stdout; a progress bar with the loss and PSNR goes to stderr when it is a terminal and
//! `--quiet` is not given. On failure the error goes to stderr, the exit code is 1, and
//! nothing is written.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use gs_refine::job::{self, Job, JobParams};
use gs_refine::views::load_views;
use gs_refine::Params;
use profuse_bench::gs_refine as bench;
use profuse_formats::{Cameras, FileKind, Gaussians};
use profuse_metrics::photo::{side_by_side, to_u8};
use profuse_tools::{chatty, init_threads, progress_bar, run, write_png, BoxError};
use serde_json::{json, Value};

#[derive(Debug, Parser)]
#[command(
    name = "gs-refine",
    version,
    about = "Refine 3D Gaussians against photos on the CPU (3DGS loss and Adam, no densification)",
    long_about = "Refine 3D Gaussians against the photos of their views on the CPU: the backward \
                  pass of splat-raster's forward, the 3DGS loss 0.8 L1 + 0.2 D-SSIM, Adam with the \
                  3DGS learning rates (position rate x scene extent, decaying exponentially 100x \
                  over the run), one view per iteration in a seeded shuffled order, no \
                  densification. Output is byte-identical for a given seed and any thread count."
)]
struct Cli {
    /// Do not print progress on stderr.
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Refine a gaussians file; write the refined one.
    Run(RunArgs),
    /// Render views (e.g. held-out ones) at a scale and compare with their photos: PSNR
    /// over every pixel and coverage (alpha > 0.5) per view, side-by-side PNGs.
    Eval {
        /// Gaussians file.
        #[arg(long)]
        gaussians: PathBuf,
        /// Cameras file.
        #[arg(long)]
        cameras: PathBuf,
        /// Folder the cameras' image names are relative to.
        #[arg(long)]
        images: PathBuf,
        /// Views to evaluate, e.g. 10,25,40.
        #[arg(long, value_delimiter = ',', required = true)]
        views: Vec<usize>,
        /// Image scale in (0, 1].
        #[arg(long, default_value_t = 0.5)]
        scale: f64,
        /// Folder for view_NNN.png (render left, photo right).
        #[arg(long)]
        out_dir: Option<PathBuf>,
    },
    /// Time forward, loss and backward of one view (default 540 x 960 of a fox photo) and
    /// whole iterations; one JSON object with iters_per_s, forward_ms, backward_ms,
    /// peak_rss_mb.
    Bench {
        #[command(flatten)]
        params: bench::BenchParams,
        /// Worker threads (default: rayon's).
        #[arg(long)]
        threads: Option<usize>,
    },
}

#[derive(Debug, clap::Args)]
struct RunArgs {
    /// Gaussians to refine (profuse.gaussians).
    #[arg(long, required_unless_present = "resume")]
    gaussians: Option<PathBuf>,
    /// Start from this gaussians file instead (a --save-every snapshot or an earlier
    /// output); the Adam moments start from zero again.
    #[arg(long)]
    resume: Option<PathBuf>,
    /// Cameras file (profuse.cameras), pinhole.
    #[arg(long)]
    cameras: PathBuf,
    /// Folder the cameras' image names are relative to (or holding the images).
    #[arg(long)]
    images: PathBuf,
    /// Refined gaussians file to write.
    #[arg(long)]
    out: PathBuf,
    /// Also write the refined Gaussians as an INRIA PLY.
    #[arg(long)]
    ply: Option<PathBuf>,
    /// Iterations, one view each.
    #[arg(long, default_value_t = 2000)]
    iterations: usize,
    /// Training image scale in (0, 1] (intrinsics rescaled, photos area-averaged).
    #[arg(long, default_value_t = 0.5)]
    scale: f64,
    /// Write the current Gaussians to --out every N iterations (0: only at the end).
    #[arg(long, default_value_t = 0)]
    save_every: usize,
    /// Views (0-based ids) left out of training, e.g. held-out test views: 10,25,40.
    #[arg(long, value_delimiter = ',')]
    exclude: Vec<usize>,
    /// Seed of the view order.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Remove Gaussians with opacity below --prune-opacity every N iterations (0: never).
    #[arg(long, default_value_t = 0)]
    prune_every: usize,
    /// Opacity threshold of the pruning (and of the densification's pruning).
    #[arg(long, default_value_t = 0.005)]
    prune_opacity: f64,
    /// Raise the SH degree to D (0..=3) before training; the new coefficients start at
    /// zero (colours unchanged) and learn view-dependent colour. Never lowers the input's.
    #[arg(long, default_value_t = 0)]
    sh_degree: usize,
    /// 3DGS densification up to iteration N (0: none): every --densify-every iterations
    /// from --densify-from, Gaussians whose mean NDC positional gradient reaches
    /// --densify-grad are cloned (largest scale <= --percent-dense x scene extent) or split
    /// in two at 1/1.6 of the scale; those below --prune-opacity are removed.
    #[arg(long, default_value_t = 0)]
    densify_until: usize,
    /// First iteration that densifies.
    #[arg(long, default_value_t = 500)]
    densify_from: usize,
    /// Densify every N iterations.
    #[arg(long, default_value_t = 100)]
    densify_every: usize,
    /// Mean NDC positional gradient norm at which a Gaussian is densified (3DGS: 0.0002).
    #[arg(long, default_value_t = 0.0002)]
    densify_grad: f64,
    /// Largest scale, as a share of the scene extent, up to which a Gaussian is cloned
    /// rather than split (3DGS: 0.01).
    #[arg(long, default_value_t = 0.01)]
    percent_dense: f64,
    /// Densification never grows the scene past N Gaussians (0: no cap); the candidates
    /// with the largest gradients go first.
    #[arg(long, default_value_t = 0)]
    max_gaussians: usize,
    /// Worker threads (default: rayon's); results do not depend on it.
    #[arg(long)]
    threads: Option<usize>,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| match cli.command {
        Command::Run(args) => refine(args, quiet),
        Command::Eval {
            gaussians,
            cameras,
            images,
            views,
            scale,
            out_dir,
        } => eval(
            &gaussians,
            &cameras,
            &images,
            &views,
            scale,
            out_dir.as_deref(),
        ),
        Command::Bench { params, threads } => {
            init_threads(threads)?;
            bench::run(&params)
        }
    })
}

fn refine(a: RunArgs, quiet: bool) -> Result<Value, BoxError> {
    init_threads(a.threads)?;
    let mut outs = vec![a.out.as_path()];
    outs.extend(a.ply.as_deref());
    profuse_tools::check_outputs(outs)?;
    let input = a
        .resume
        .clone()
        .or(a.gaussians.clone())
        .ok_or("give --gaussians")?;
    let job = Job {
        gaussians: input,
        cameras: a.cameras,
        images: a.images,
        out: a.out,
        exclude: a.exclude,
        save_every: a.save_every,
    };
    let params = JobParams {
        iterations: a.iterations,
        scale: a.scale,
        seed: a.seed,
        prune_every: a.prune_every,
        prune_opacity: a.prune_opacity,
        sh_degree: a.sh_degree,
        densify_until: a.densify_until,
        densify_from: a.densify_from,
        densify_every: a.densify_every,
        densify_grad: a.densify_grad,
        percent_dense: a.percent_dense,
        max_gaussians: a.max_gaussians,
    };
    let bar = progress_bar(chatty(quiet), a.iterations as u64, "gs-refine", "it");
    let report = job::run(&job, &params, &mut |it, loss, psnr| {
        bar.set_position(it as u64);
        bar.set_message(format!("loss {loss:.4} psnr {psnr:.2} dB"));
    });
    bar.finish_and_clear();
    let report = report?;
    if let Some(ply) = &a.ply {
        scene_io::ply::write_inria_ply(ply, &Gaussians::read(&report.out)?)?;
    }
    let mut value = serde_json::to_value(&report)?;
    value["ply"] = json!(a.ply.as_ref().map(|p| p.to_string_lossy()));
    Ok(value)
}

fn eval(
    gaussians: &Path,
    cameras: &Path,
    images: &Path,
    ids: &[usize],
    scale: f64,
    out_dir: Option<&Path>,
) -> Result<Value, BoxError> {
    let g = Gaussians::read(gaussians)?;
    let cams = Cameras::read(cameras)?;
    let exclude: Vec<usize> = (0..cams.len()).filter(|v| !ids.contains(v)).collect();
    let p = Params::from_gaussians(&g)?;
    let mut rows = Vec::new();
    for view in load_views(&cams, images, scale, &exclude)? {
        let e = gs_refine::views::evaluate(&p, &view);
        let (w, h) = (view.1.width, view.1.height);
        let mut png = None;
        if let Some(dir) = out_dir {
            std::fs::create_dir_all(dir)?;
            let u8s = |v: &[f32]| v.iter().map(|x| to_u8(*x)).collect::<Vec<u8>>();
            let both = side_by_side(&u8s(&e.render), &u8s(&view.2.rgb), w as usize, h as usize);
            let path = dir.join(format!("view_{:03}.png", e.view));
            write_png(&path, &both, 2 * w, h, image::ExtendedColorType::Rgb8)?;
            png = Some(path.to_string_lossy().into_owned());
        }
        rows.push(json!({"view": e.view, "psnr": e.psnr, "coverage": e.coverage, "png": png}));
    }
    let n = rows.len().max(1) as f64;
    let mean = |k: &str| rows.iter().filter_map(|r| r[k].as_f64()).sum::<f64>() / n;
    Ok(
        json!({"psnr": mean("psnr"), "coverage": mean("coverage"), "width_height_scale": scale, "views": rows}),
    )
}

//! `splat-raster`: render Gaussians on the CPU (colour, depth, alpha PNGs), dump a view's
//! per-pixel top-K contributors, and benchmark the rasterizer.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error goes to stderr and the exit code is 1.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{Parser, Subcommand};
use image::ExtendedColorType;
use profuse_bench::raster as bench;
use profuse_formats::FileKind;
use profuse_metrics::photo::{psnr_covered, side_by_side, to_u8};
use profuse_tools::scene::{load_scene, resolve_view, ViewArgs};
use profuse_tools::{chatty, check_outputs, init_threads, run, write_png, Bars, BoxError};
use serde_json::{json, Value};
use splat_raster::{DepthMode, Rasterizer, RenderOptions, ViewRender};

#[derive(Debug, Parser)]
#[command(
    name = "splat-raster",
    version,
    about = "CPU rasterizer for 3D Gaussians: PNG renders, per-pixel top-K dumps, benchmarks",
    long_about = "CPU tile rasterizer for 3D Gaussians (the INRIA 3DGS forward pass): render colour, \
                  depth and alpha PNGs of a view, dump a view's per-pixel top-K contributors \
                  (Gaussian ids and blend weights), or benchmark. SCENE is a gaussians \
                  .safetensors file or an INRIA 3DGS .ply (chosen by extension). Views come from \
                  a cameras file (--cameras, --view) or from an orbit camera around the \
                  Gaussians (--orbit-angle) for scenes without cameras. Prints one JSON report \
                  on stdout."
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
    /// Render one view to PNG: colour (8-bit RGB), depth (16-bit grey, normalised depth
    /// Σωz/Σω scaled so the farthest pixel is 65535; the scale is in the report), alpha
    /// (8-bit grey). Colour only when no output flag is given.
    Render {
        /// Gaussians: .safetensors (profuse.gaussians) or INRIA .ply.
        scene: PathBuf,
        #[command(flatten)]
        view: ViewArgs,
        /// Directory for the PNGs (created if missing).
        #[arg(long)]
        out_dir: PathBuf,
        /// Write `<stem>_color.png`.
        #[arg(long)]
        color: bool,
        /// Write `<stem>_depth.png`.
        #[arg(long)]
        depth: bool,
        /// Write `<stem>_alpha.png`.
        #[arg(long)]
        alpha: bool,
        /// A photo of the same view (same size): write `<stem>_side_by_side.png` (render
        /// left, photo right) and report `psnr_covered`, the PSNR of the render against the
        /// photo over the pixels it covers (accumulated alpha > 0.5).
        #[arg(long, value_name = "IMAGE")]
        photo: Option<PathBuf>,
    },
    /// Dump the top-K contributors of one view to a `profuse.topk` file (SPEC.md §4.14):
    /// `ids` U32 [H,W,K] (4294967295 = none), `weights` F32 [H,W,K] (descending, ties in
    /// depth order), `transmittance` F32 [H,W].
    Topk {
        /// Gaussians: .safetensors (profuse.gaussians) or INRIA .ply.
        scene: PathBuf,
        #[command(flatten)]
        view: ViewArgs,
        /// Contributors kept per pixel (1..=256).
        #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u16).range(1..=256))]
        k: u16,
        /// The .safetensors file to write.
        #[arg(long)]
        out: PathBuf,
    },
    /// Render N orbit views colour-only, with top-K 10 and with top-K 40; print median
    /// seconds per view (wall clock, and CPU seconds summed over threads as `*_cpu_s`),
    /// throughput and peak memory as one JSON object.
    Bench {
        #[command(flatten)]
        params: bench::Params,
        /// Worker threads (default: rayon's, i.e. RAYON_NUM_THREADS or the core count).
        #[arg(long)]
        threads: Option<usize>,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| execute(cli.command, quiet))
}

/// What `render` writes.
struct RenderOutputs {
    out_dir: PathBuf,
    color: bool,
    depth: bool,
    alpha: bool,
    photo: Option<PathBuf>,
}

fn execute(command: Command, quiet: bool) -> Result<Value, BoxError> {
    match command {
        Command::Render {
            scene,
            view,
            out_dir,
            color,
            depth,
            alpha,
            photo,
        } => {
            let outputs = RenderOutputs {
                out_dir,
                color: color || !(depth || alpha) || photo.is_some(),
                depth,
                alpha,
                photo,
            };
            render(&scene, &view, &outputs, quiet)
        }
        Command::Topk {
            scene,
            view,
            k,
            out,
        } => check_outputs([out.as_path()])
            .and_then(|()| topk(&scene, &view, usize::from(k), &out, quiet)),
        Command::Bench { params, threads } => {
            init_threads(threads)?;
            let t0 = Instant::now();
            let g = load_scene(&params.scene, quiet)?;
            bench::run(
                &params,
                &g,
                t0.elapsed().as_secs_f64(),
                &Bars::new(chatty(quiet)),
            )
        }
    }
}

fn render(
    scene: &Path,
    view: &ViewArgs,
    o: &RenderOutputs,
    quiet: bool,
) -> Result<Value, BoxError> {
    let g = load_scene(scene, quiet)?;
    let (cams, v, stem, view_json) = resolve_view(&g, view)?;
    let opts = RenderOptions {
        color: o.color,
        depth: [DepthMode::None, DepthMode::Normalized][usize::from(o.depth)],
        alpha: true,
        ..RenderOptions::default()
    };
    let t0 = Instant::now();
    let out = Rasterizer::new(&g)?.render_view(&cams, v, &opts)?;
    let render_s = t0.elapsed().as_secs_f64();
    if chatty(quiet) {
        eprintln!("rendered {stem} in {render_s:.3} s");
    }
    std::fs::create_dir_all(&o.out_dir)?;
    let (w, h) = (out.width() as u32, out.height() as u32);
    let file = |what: &str| o.out_dir.join(format!("{stem}_{what}.png"));
    let shown = |what: &str| json!(file(what).to_string_lossy());
    let mut files = serde_json::Map::new();
    let mut report = json!({});
    let rgb: Vec<u8> = out
        .color()
        .unwrap_or_default()
        .iter()
        .map(|v| to_u8(*v))
        .collect();
    if o.color {
        write_png(&file("color"), &rgb, w, h, ExtendedColorType::Rgb8)?;
        files.insert("color".into(), shown("color"));
    }
    if let Some((depth, scale, max)) = out.depth_u16() {
        let bytes: Vec<u8> = depth.iter().flat_map(|q| q.to_ne_bytes()).collect();
        write_png(&file("depth"), &bytes, w, h, ExtendedColorType::L16)?;
        files.insert("depth".into(), shown("depth"));
        report["depth_scale"] = json!(scale);
        report["depth_max"] = json!(max);
        report["depth_note"] =
            json!("depth = pixel value * depth_scale (camera z, Σωz/Σω); 0 = nothing hit");
    }
    let a = out.alpha().unwrap_or_default();
    if o.alpha {
        let px: Vec<u8> = a.iter().map(|v| to_u8(*v)).collect();
        write_png(&file("alpha"), &px, w, h, ExtendedColorType::L8)?;
        files.insert("alpha".into(), shown("alpha"));
    }
    if let Some(photo) = &o.photo {
        let img = read_photo(photo, w, h)?;
        report["psnr_covered"] = json!(psnr_covered(&rgb, img.as_raw(), a));
        let side = side_by_side(&rgb, img.as_raw(), w as usize, h as usize);
        write_png(
            &file("side_by_side"),
            &side,
            2 * w,
            h,
            ExtendedColorType::Rgb8,
        )?;
        files.insert("side_by_side".into(), shown("side_by_side"));
    }
    let coverage = a.iter().filter(|v| **v > 0.5).count() as f64 / a.len().max(1) as f64;
    report["scene"] = json!(scene.to_string_lossy());
    report["gaussians"] = json!(g.len());
    report["view"] = view_json;
    report["width"] = json!(w);
    report["height"] = json!(h);
    report["visible"] = json!(out.stats().visible);
    report["tile_pairs"] = json!(out.stats().tile_pairs);
    report["coverage"] = json!(coverage);
    report["render_s"] = json!(render_s);
    report["files"] = Value::Object(files);
    Ok(report)
}

/// A photo of the rendered view's size, as RGB8.
fn read_photo(photo: &Path, w: u32, h: u32) -> Result<image::RgbImage, BoxError> {
    let img = image::open(photo)
        .map_err(|e| format!("{}: cannot read the photo: {e}", photo.display()))?
        .to_rgb8();
    if img.dimensions() != (w, h) {
        let (pw, ph) = img.dimensions();
        return Err(format!(
            "{}: the photo is {pw}x{ph}, the rendered view {w}x{h}",
            photo.display()
        )
        .into());
    }
    Ok(img)
}

fn topk(
    scene: &Path,
    view: &ViewArgs,
    k: usize,
    path: &Path,
    quiet: bool,
) -> Result<Value, BoxError> {
    let g = load_scene(scene, quiet)?;
    let (cams, v, stem, view_json) = resolve_view(&g, view)?;
    let opts = RenderOptions {
        color: false,
        transmittance: true,
        top_k: Some(k),
        ..RenderOptions::default()
    };
    let t0 = Instant::now();
    let out: ViewRender = Rasterizer::new(&g)?.render_view(&cams, v, &opts)?;
    let render_s = t0.elapsed().as_secs_f64();
    if chatty(quiet) {
        eprintln!("rendered {stem} with K = {k} in {render_s:.3} s");
    }
    let mut file = out
        .to_topk_file(g.len())
        .ok_or("the render has no top-K buffers")?;
    file.extra.insert("view".into(), stem.clone());
    file.extra
        .insert("scene".into(), scene.display().to_string());
    file.extra.insert(
        "generator".into(),
        format!("splat-raster {}", env!("CARGO_PKG_VERSION")),
    );
    file.extra.insert("k".into(), k.to_string());
    file.extra
        .insert("view_camera".into(), view_json.to_string());
    file.write(path)?;
    let (filled, full) = out.topk_fill();
    Ok(json!({
        "scene": scene.to_string_lossy(),
        "gaussians": g.len(),
        "view": view_json,
        "width": out.width(),
        "height": out.height(),
        "k": k,
        "visible": out.stats().visible,
        "top_k_slots_filled": filled,
        "pixels_with_k_hits": full,
        "render_s": render_s,
        "out": path.to_string_lossy(),
    }))
}

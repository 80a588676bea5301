//! `splat-raster`: render Gaussians on the CPU (colour, depth, alpha PNGs), dump a view's
//! per-pixel top-K contributors, and benchmark the rasterizer.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error goes to stderr and the exit code is 1.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{Args, Parser, Subcommand, ValueEnum};
use profuse_formats::{Cameras, FileKind, Gaussians};
use profuse_tools::{chatty, peak_rss_mb, run, warn, BoxError};
use serde_json::{json, Value};
use splat_raster::{camera, DepthMode, Rasterizer, RenderOptions, Simd, ViewRender};

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
        /// Gaussians: .safetensors (profuse.gaussians) or INRIA .ply.
        scene: PathBuf,
        /// Image width.
        #[arg(long, default_value_t = 1920)]
        width: u32,
        /// Image height.
        #[arg(long, default_value_t = 1080)]
        height: u32,
        /// Orbit views per configuration.
        #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u64).range(1..))]
        views: u64,
        /// Worker threads (default: rayon's, i.e. RAYON_NUM_THREADS or the core count).
        #[arg(long)]
        threads: Option<usize>,
        /// Render every view this many times and keep the fastest (robust to other load).
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
        repeat: u64,
        /// Run only this configuration (for profiling): 0 = colour only, else top-K K.
        #[arg(long, hide = true)]
        only: Option<usize>,
        /// SIMD width of the blend: `auto` (the widest this CPU runs), `portable` (4 lanes,
        /// any CPU) or `avx512` (16 lanes; an error where unsupported). The output is the
        /// same bytes for each; this compares their speed.
        #[arg(long, value_enum, default_value = "auto")]
        simd: SimdArg,
        #[command(flatten)]
        orbit: OrbitArgs,
    },
}

#[derive(Debug, Args)]
struct ViewArgs {
    /// Cameras file (profuse.cameras); pick the view with --view.
    #[arg(
        long,
        conflicts_with = "orbit_angle",
        required_unless_present = "orbit_angle"
    )]
    cameras: Option<PathBuf>,
    /// View index in the cameras file.
    #[arg(long, default_value_t = 0, requires = "cameras")]
    view: usize,
    /// Orbit camera instead of a cameras file: azimuth in degrees around the up axis.
    #[arg(long, value_name = "DEG")]
    orbit_angle: Option<f64>,
    /// Orbit image width.
    #[arg(long, default_value_t = 640, requires = "orbit_angle")]
    width: u32,
    /// Orbit image height.
    #[arg(long, default_value_t = 480, requires = "orbit_angle")]
    height: u32,
    #[command(flatten)]
    orbit: OrbitArgs,
}

#[derive(Debug, Clone, Args)]
struct OrbitArgs {
    /// Orbit elevation in degrees above the plane perpendicular to the up axis.
    #[arg(long, default_value_t = 20.0, value_name = "DEG")]
    elevation: f64,
    /// World axis that points up in orbit views (INRIA/COLMAP scenes are usually -y).
    #[arg(long, value_enum, default_value = "-y", allow_hyphen_values = true)]
    up: UpAxis,
    /// Orbit horizontal field of view in degrees.
    #[arg(long, default_value_t = 50.0, value_name = "DEG")]
    fov: f64,
    /// Orbit distance as a multiple of the robust radius (90th percentile distance of the
    /// means from their per-axis median).
    #[arg(long, default_value_t = 2.5)]
    distance: f64,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum SimdArg {
    Auto,
    Portable,
    Avx512,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum UpAxis {
    #[value(name = "x")]
    X,
    #[value(name = "-x")]
    NegX,
    #[value(name = "y")]
    Y,
    #[value(name = "-y")]
    NegY,
    #[value(name = "z")]
    Z,
    #[value(name = "-z")]
    NegZ,
}

impl UpAxis {
    fn vector(self) -> [f64; 3] {
        match self {
            UpAxis::X => [1.0, 0.0, 0.0],
            UpAxis::NegX => [-1.0, 0.0, 0.0],
            UpAxis::Y => [0.0, 1.0, 0.0],
            UpAxis::NegY => [0.0, -1.0, 0.0],
            UpAxis::Z => [0.0, 0.0, 1.0],
            UpAxis::NegZ => [0.0, 0.0, -1.0],
        }
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| execute(cli.command, quiet))
}

fn execute(command: Command, quiet: bool) -> Result<Value, BoxError> {
    let show = chatty(quiet);
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
            let g = load_scene(&scene, quiet)?;
            let (cams, v, stem, view_json) = resolve_view(&g, &view)?;
            let color = color || !(depth || alpha) || photo.is_some();
            let opts = RenderOptions {
                color,
                depth: if depth {
                    DepthMode::Normalized
                } else {
                    DepthMode::None
                },
                alpha: true,
                ..RenderOptions::default()
            };
            let raster = Rasterizer::new(&g)?;
            let t0 = Instant::now();
            let out = raster.render_view(&cams, v, &opts)?;
            let render_s = t0.elapsed().as_secs_f64();
            if show {
                eprintln!("rendered {stem} in {render_s:.3} s");
            }
            std::fs::create_dir_all(&out_dir)?;
            let mut files = serde_json::Map::new();
            let mut report = json!({});
            if let Some(c) = out.color().filter(|_| color) {
                let path = out_dir.join(format!("{stem}_color.png"));
                let rgb: Vec<u8> = c.iter().map(|v| to_u8(*v)).collect();
                write_png(&path, &rgb, &out, image::ExtendedColorType::Rgb8)?;
                files.insert("color".into(), json!(path));
            }
            if let Some(d) = out.depth() {
                let path = out_dir.join(format!("{stem}_depth.png"));
                let max = d.iter().cloned().fold(0.0f32, f32::max);
                let scale = if max > 0.0 {
                    f64::from(max) / 65535.0
                } else {
                    0.0
                };
                let px: Vec<u8> = d
                    .iter()
                    .flat_map(|v| {
                        let q = if scale > 0.0 {
                            (f64::from(*v) / scale).round().clamp(0.0, 65535.0) as u16
                        } else {
                            0
                        };
                        q.to_ne_bytes()
                    })
                    .collect();
                write_png(&path, &px, &out, image::ExtendedColorType::L16)?;
                files.insert("depth".into(), json!(path));
                report["depth_scale"] = json!(scale);
                report["depth_max"] = json!(max);
                report["depth_note"] =
                    json!("depth = pixel value * depth_scale (camera z, Σωz/Σω); 0 = nothing hit");
            }
            let a = out.alpha().unwrap_or_default();
            if alpha {
                let path = out_dir.join(format!("{stem}_alpha.png"));
                let px: Vec<u8> = a.iter().map(|v| to_u8(*v)).collect();
                write_png(&path, &px, &out, image::ExtendedColorType::L8)?;
                files.insert("alpha".into(), json!(path));
            }
            let coverage = a.iter().filter(|v| **v > 0.5).count() as f64 / a.len().max(1) as f64;
            if let (Some(photo), Some(c)) = (&photo, out.color()) {
                let (psnr, side) = compare_with_photo(photo, c, a, &out)?;
                let path = out_dir.join(format!("{stem}_side_by_side.png"));
                let (w, h) = side.dimensions();
                encode_png(&path, side.as_raw(), w, h, image::ExtendedColorType::Rgb8)?;
                files.insert("side_by_side".into(), json!(path));
                report["psnr_covered"] = json!(psnr);
            }
            report["scene"] = json!(scene);
            report["gaussians"] = json!(g.len());
            report["view"] = view_json;
            report["width"] = json!(out.width());
            report["height"] = json!(out.height());
            report["visible"] = json!(out.stats().visible);
            report["tile_pairs"] = json!(out.stats().tile_pairs);
            report["coverage"] = json!(coverage);
            report["render_s"] = json!(render_s);
            report["files"] = Value::Object(files);
            Ok(report)
        }
        Command::Topk {
            scene,
            view,
            k,
            out: path,
        } => {
            let k = usize::from(k);
            let g = load_scene(&scene, quiet)?;
            let (cams, v, stem, view_json) = resolve_view(&g, &view)?;
            let opts = RenderOptions {
                color: false,
                transmittance: true,
                top_k: Some(k),
                ..RenderOptions::default()
            };
            let raster = Rasterizer::new(&g)?;
            let t0 = Instant::now();
            let out = raster.render_view(&cams, v, &opts)?;
            let render_s = t0.elapsed().as_secs_f64();
            if show {
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
            file.write(&path)?;
            let ids = out.topk_ids().unwrap_or_default();
            let hits = ids
                .iter()
                .filter(|i| **i != splat_raster::NO_GAUSSIAN)
                .count();
            let full = ids
                .chunks_exact(k)
                .filter(|c| c[k - 1] != splat_raster::NO_GAUSSIAN)
                .count();
            Ok(json!({
                "scene": scene,
                "gaussians": g.len(),
                "view": view_json,
                "width": out.width(),
                "height": out.height(),
                "k": k,
                "visible": out.stats().visible,
                "top_k_slots_filled": hits,
                "pixels_with_k_hits": full,
                "render_s": render_s,
                "out": path,
            }))
        }
        Command::Bench {
            scene,
            width,
            height,
            views,
            threads,
            repeat,
            only,
            simd,
            orbit,
        } => {
            if let Some(n) = threads {
                splat_raster::rayon::ThreadPoolBuilder::new()
                    .num_threads(n)
                    .build_global()?;
            }
            let t0 = Instant::now();
            let g = load_scene(&scene, quiet)?;
            let load_s = t0.elapsed().as_secs_f64();
            let t0 = Instant::now();
            let mut raster = Rasterizer::new(&g)?;
            let prepare_s = t0.elapsed().as_secs_f64();
            match simd {
                SimdArg::Auto => {}
                SimdArg::Portable => raster.set_simd(Simd::Portable)?,
                SimdArg::Avx512 => raster.set_simd(Simd::Avx512)?,
            }
            let ext = camera::scene_extent(&g).ok_or("the scene has no Gaussians")?;
            let poses = (0..views)
                .map(|i| orbit_pose(&ext, &orbit, 360.0 * i as f64 / views as f64))
                .collect::<Result<Vec<_>, BoxError>>()?;
            let cams = camera::cameras_from_poses(
                &poses,
                width,
                height,
                camera::pinhole_intrinsics(width, height, orbit.fov),
            );
            let mut results = serde_json::Map::new();
            let mut medians = Vec::new();
            let mut visible = Vec::new();
            let mut pairs = Vec::new();
            let configs: Vec<(String, Option<usize>)> = match only {
                None => vec![
                    ("color_s".into(), None),
                    ("topk10_s".into(), Some(10)),
                    ("topk40_s".into(), Some(40)),
                ],
                Some(0) => vec![("color_s".into(), None)],
                Some(k) => vec![(format!("topk{k}_s"), Some(k))],
            };
            for (name, k) in configs {
                let opts = RenderOptions {
                    top_k: k,
                    ..RenderOptions::default()
                };
                // One untimed warm-up view (page faults of fresh buffers, thread start).
                let mut out = ViewRender::default();
                raster.render_view_into(&cams, 0, &opts, &mut out)?;
                let mut times = Vec::new();
                let mut cpus = Vec::new();
                for v in 0..cams.len() {
                    // The fastest of `repeat` renders of the view: other load on the machine
                    // only ever slows a render down.
                    let (mut best, mut best_cpu) = (f64::INFINITY, f64::INFINITY);
                    for _ in 0..repeat {
                        let cpu0 = process_cpu_s();
                        let t = Instant::now();
                        raster.render_view_into(&cams, v, &opts, &mut out)?;
                        best = best.min(t.elapsed().as_secs_f64());
                        best_cpu = best_cpu.min(process_cpu_s() - cpu0);
                    }
                    times.push(best);
                    cpus.push(best_cpu);
                    if k.is_none() {
                        visible.push(out.stats().visible);
                        pairs.push(out.stats().tile_pairs);
                    }
                    if show {
                        eprint!("\r\x1b[2K{name}: view {}/{}", v + 1, cams.len());
                    }
                }
                let cpu = median(&mut cpus);
                let med = median(&mut times);
                results.insert(name.replace("_s", "_cpu_s"), json!(cpu));
                results.insert(name, json!(med));
                medians.push(med);
                drop(out);
            }
            if show {
                eprintln!();
            }
            if let [color, topk10, topk40] = medians[..] {
                let mpix = f64::from(width) * f64::from(height) / 1e6;
                results.insert("mpix_per_s".into(), json!(mpix / topk10));
                results.insert("topk10_over_color".into(), json!(topk10 / color));
                results.insert("topk40_over_color".into(), json!(topk40 / color));
            }
            results.insert("peak_rss_mb".into(), json!(peak_rss_mb()));
            results.insert("gaussians".into(), json!(g.len()));
            results.insert("width".into(), json!(width));
            results.insert("height".into(), json!(height));
            results.insert("views".into(), json!(views));
            results.insert("repeat".into(), json!(repeat));
            results.insert(
                "threads".into(),
                json!(splat_raster::rayon::current_num_threads()),
            );
            results.insert("visible_median".into(), json!(median_usize(&mut visible)));
            results.insert("tile_pairs_median".into(), json!(median_usize(&mut pairs)));
            results.insert("simd".into(), json!(raster.simd().name()));
            results.insert("load_s".into(), json!(load_s));
            results.insert("prepare_s".into(), json!(prepare_s));
            results.insert("scene".into(), json!(scene));
            Ok(Value::Object(results))
        }
    }
}

/// Reads a gaussians file or an INRIA PLY (by extension).
fn load_scene(path: &Path, quiet: bool) -> Result<Gaussians, BoxError> {
    let is_ply = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("ply"));
    if is_ply {
        let (g, report) = scene_io::ply::read_inria_ply(path)?;
        if report.clamped_opacity > 0 {
            warn(
                quiet,
                &format!(
                    "{}: clamped {} non-finite opacity logits to ±20",
                    path.display(),
                    report.clamped_opacity
                ),
            );
        }
        Ok(g)
    } else {
        Ok(Gaussians::read(path)?)
    }
}

/// The cameras, view index, output stem and report entry of the requested view.
fn resolve_view(
    g: &Gaussians,
    args: &ViewArgs,
) -> Result<(Cameras, usize, String, Value), BoxError> {
    if let Some(path) = &args.cameras {
        let cams = Cameras::read(path)?;
        if args.view >= cams.len() {
            return Err(format!(
                "--view {} is out of range: {} has {} views",
                args.view,
                path.display(),
                cams.len()
            )
            .into());
        }
        let name = cams.image_names[args.view].clone();
        Ok((
            cams,
            args.view,
            format!("view_{:03}", args.view),
            json!({"cameras": path, "index": args.view, "image_name": name}),
        ))
    } else {
        let angle = args.orbit_angle.ok_or("give --cameras or --orbit-angle")?;
        let ext = camera::scene_extent(g).ok_or("the scene has no Gaussians to orbit")?;
        let pose = orbit_pose(&ext, &args.orbit, angle)?;
        let intr = camera::pinhole_intrinsics(args.width, args.height, args.orbit.fov);
        let cams = camera::cameras_from_poses(&[pose], args.width, args.height, intr);
        let center = cams.center(0);
        Ok((
            cams,
            0,
            format!("orbit_{angle:.0}"),
            json!({
                "orbit_angle": angle,
                "elevation": args.orbit.elevation,
                "up": format!("{:?}", args.orbit.up.vector()),
                "target": ext.median,
                "radius_p90": ext.radius_p90,
                "distance": args.orbit.distance * ext.radius_p90,
                "camera_center": center,
                "intrinsics": intr,
            }),
        ))
    }
}

fn orbit_pose(
    ext: &camera::SceneExtent,
    orbit: &OrbitArgs,
    angle: f64,
) -> Result<[f64; 12], BoxError> {
    let radius = if ext.radius_p90 > 0.0 {
        ext.radius_p90
    } else {
        1.0
    };
    camera::orbit_pose(
        ext.median,
        orbit.distance * radius,
        orbit.up.vector(),
        angle,
        orbit.elevation,
    )
    .ok_or_else(|| "cannot build an orbit camera (zero distance?)".into())
}

fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// PSNR (dB, 8-bit peak) of the rendered colour against a photo over the pixels whose
/// accumulated alpha exceeds 0.5 (`None` when none does), and the render and the photo
/// side by side.
fn compare_with_photo(
    photo: &Path,
    color: &[f32],
    alpha: &[f32],
    out: &ViewRender,
) -> Result<(Option<f64>, image::RgbImage), BoxError> {
    let img = image::open(photo)
        .map_err(|e| format!("{}: cannot read the photo: {e}", photo.display()))?
        .to_rgb8();
    let (w, h) = (out.width() as u32, out.height() as u32);
    if img.dimensions() != (w, h) {
        return Err(format!(
            "{}: the photo is {}x{}, the rendered view {w}x{h}",
            photo.display(),
            img.width(),
            img.height()
        )
        .into());
    }
    let (mut se, mut n) = (0.0f64, 0usize);
    let mut side = image::RgbImage::new(2 * w, h);
    for (i, (px, a)) in img.pixels().zip(alpha).enumerate() {
        let (x, y) = (i as u32 % w, i as u32 / w);
        let r = [0, 1, 2].map(|c| to_u8(color[i * 3 + c]));
        side.put_pixel(x, y, image::Rgb(r));
        side.put_pixel(w + x, y, *px);
        if *a > 0.5 {
            for c in 0..3 {
                let d = f64::from(r[c]) - f64::from(px[c]);
                se += d * d;
            }
            n += 1;
        }
    }
    let psnr = (n > 0).then(|| {
        let mse = se / (3 * n) as f64;
        if mse > 0.0 {
            10.0 * (255.0f64 * 255.0 / mse).log10()
        } else {
            f64::INFINITY
        }
    });
    Ok((psnr, side))
}

/// Writes a PNG of the view's size atomically.
fn write_png(
    path: &Path,
    data: &[u8],
    out: &ViewRender,
    color: image::ExtendedColorType,
) -> Result<(), BoxError> {
    encode_png(path, data, out.width() as u32, out.height() as u32, color)
}

/// Encodes a PNG and writes it atomically.
fn encode_png(
    path: &Path,
    data: &[u8],
    width: u32,
    height: u32,
    color: image::ExtendedColorType,
) -> Result<(), BoxError> {
    use image::ImageEncoder;
    let mut bytes = Vec::new();
    image::codecs::png::PngEncoder::new(&mut bytes)
        .write_image(data, width, height, color)
        .map_err(|e| format!("cannot encode {}: {e}", path.display()))?;
    profuse_tools::write_file(path, &bytes)
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        0.0
    } else if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

fn median_usize(v: &mut [usize]) -> usize {
    v.sort_unstable();
    v.get(v.len() / 2).copied().unwrap_or(0)
}

/// CPU time of all the process's threads so far, in seconds (sum of the per-thread
/// run times in /proc/self/task/*/schedstat; 0 where unavailable). Lets the benchmark
/// report CPU seconds per view, which other load on the machine does not inflate.
fn process_cpu_s() -> f64 {
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else {
        return 0.0;
    };
    dir.filter_map(|e| e.ok())
        .filter_map(|e| std::fs::read_to_string(e.path().join("schedstat")).ok())
        .filter_map(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .sum::<f64>()
        / 1e9
}

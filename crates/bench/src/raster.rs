//! `splat-raster bench`: render orbit views colour-only, with top-K 10 and with top-K 40;
//! median seconds per view (wall clock and CPU), throughput and peak memory. Also the
//! orbit camera arguments the tool's `render` and `topk` share with it.

use std::path::PathBuf;
use std::time::Instant;

use profuse_formats::{Cameras, Gaussians};
use serde_json::{json, Map, Value};
use splat_raster::{camera, Phases, Rasterizer, RenderOptions, RenderStats, Simd, ViewRender};

use crate::common::{self, Progress};
use crate::BoxError;

/// A world axis, for the orbit's up direction.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum UpAxis {
    /// +x.
    #[value(name = "x")]
    X,
    /// −x.
    #[value(name = "-x")]
    NegX,
    /// +y.
    #[value(name = "y")]
    Y,
    /// −y (INRIA/COLMAP scenes).
    #[value(name = "-y")]
    NegY,
    /// +z.
    #[value(name = "z")]
    Z,
    /// −z.
    #[value(name = "-z")]
    NegZ,
}

impl UpAxis {
    /// The unit vector.
    pub fn vector(self) -> [f64; 3] {
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

/// An orbit camera around the Gaussians, for scenes without cameras.
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct OrbitArgs {
    /// Orbit elevation in degrees above the plane perpendicular to the up axis.
    #[arg(long, default_value_t = 20.0, value_name = "DEG")]
    pub elevation: f64,
    /// World axis that points up in orbit views (INRIA/COLMAP scenes are usually -y).
    #[arg(long, value_enum, default_value = "-y", allow_hyphen_values = true)]
    pub up: UpAxis,
    /// Orbit horizontal field of view in degrees.
    #[arg(long, default_value_t = 50.0, value_name = "DEG")]
    pub fov: f64,
    /// Orbit distance as a multiple of the robust radius (90th percentile distance of the
    /// means from their per-axis median).
    #[arg(long, default_value_t = 2.5)]
    pub distance: f64,
}

impl OrbitArgs {
    /// The camera-to-world pose at `angle` degrees of azimuth around the scene's median.
    pub fn pose(&self, ext: &camera::SceneExtent, angle: f64) -> Result<[f64; 12], BoxError> {
        let radius = if ext.radius_p90 > 0.0 {
            ext.radius_p90
        } else {
            1.0
        };
        camera::orbit_pose(
            ext.median,
            self.distance * radius,
            self.up.vector(),
            angle,
            self.elevation,
        )
        .ok_or_else(|| "cannot build an orbit camera (zero distance?)".into())
    }
}

/// SIMD width of the blend.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SimdArg {
    /// The widest this CPU runs.
    Auto,
    /// 4 lanes, any CPU.
    Portable,
    /// 16 lanes (an error where unsupported).
    Avx512,
}

/// The benchmark's parameters (the `splat-raster bench` arguments).
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct Params {
    /// Gaussians: .safetensors (profuse.gaussians) or INRIA .ply.
    pub scene: PathBuf,
    /// Image width.
    #[arg(long, default_value_t = 1920)]
    pub width: u32,
    /// Image height.
    #[arg(long, default_value_t = 1080)]
    pub height: u32,
    /// Orbit views per configuration.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u64).range(1..))]
    pub views: u64,
    /// Render every view this many times and keep the fastest (robust to other load).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub repeat: u64,
    /// Run only this configuration (for profiling): 0 = colour only, else top-K K.
    #[arg(long, hide = true)]
    pub only: Option<usize>,
    /// SIMD width of the blend: `auto` (the widest this CPU runs), `portable` (4 lanes,
    /// any CPU) or `avx512` (16 lanes; an error where unsupported). The output is the
    /// same bytes for each; this compares their speed.
    #[arg(long, value_enum, default_value = "auto")]
    pub simd: SimdArg,
    #[command(flatten)]
    pub orbit: OrbitArgs,
}

/// The timed configurations: (report key, top-K).
fn configs(only: Option<usize>) -> Vec<(String, Option<usize>)> {
    match only {
        None => vec![
            ("color_s".into(), None),
            ("topk10_s".into(), Some(10)),
            ("topk40_s".into(), Some(40)),
        ],
        Some(0) => vec![("color_s".into(), None)],
        Some(k) => vec![(format!("topk{k}_s"), Some(k))],
    }
}

/// Lanes of the blend's pixel groups.
fn lanes(raster: &Rasterizer<'_>) -> f64 {
    match raster.simd() {
        Simd::Portable => 4.0,
        Simd::Avx512 => 16.0,
    }
}

/// Runs the benchmark on Gaussians already loaded (`load_s` seconds).
pub fn run(
    p: &Params,
    g: &Gaussians,
    load_s: f64,
    progress: &dyn Progress,
) -> Result<Value, BoxError> {
    let t0 = Instant::now();
    let mut raster = Rasterizer::new(g)?;
    let prepare_s = t0.elapsed().as_secs_f64();
    match p.simd {
        SimdArg::Auto => {}
        SimdArg::Portable => raster.set_simd(Simd::Portable)?,
        SimdArg::Avx512 => raster.set_simd(Simd::Avx512)?,
    }
    let ext = camera::scene_extent(g).ok_or("the scene has no Gaussians")?;
    let poses = (0..p.views)
        .map(|i| p.orbit.pose(&ext, 360.0 * i as f64 / p.views as f64))
        .collect::<Result<Vec<_>, BoxError>>()?;
    let intrinsics = camera::pinhole_intrinsics(p.width, p.height, p.orbit.fov);
    let cams = camera::cameras_from_poses(&poses, p.width, p.height, intrinsics);
    let mut results = Map::new();
    let mut medians = Vec::new();
    let (mut visible, mut pairs) = (Vec::new(), Vec::new());
    for (name, k) in configs(p.only) {
        let opts = RenderOptions {
            top_k: k,
            ..RenderOptions::default()
        };
        // One untimed warm-up view (page faults of fresh buffers, thread start).
        let mut out = ViewRender::default();
        raster.render_view_into(&cams, 0, &opts, &mut out)?;
        let mut samples = Samples::default();
        progress.start(&name, cams.len() as u64);
        for v in 0..cams.len() {
            let best = best_render(&raster, &cams, v, &opts, p.repeat, &mut out)?;
            samples.add(best, lanes(&raster));
            if k.is_none() {
                visible.push(out.stats().visible);
                pairs.push(out.stats().tile_pairs);
            }
            progress.inc(1);
        }
        progress.finish();
        medians.push(samples.report(name, &mut results));
    }
    if let [color, topk10, topk40] = medians[..] {
        let mpix = f64::from(p.width) * f64::from(p.height) / 1e6;
        results.insert("mpix_per_s".into(), json!(mpix / topk10));
        results.insert("topk10_over_color".into(), json!(topk10 / color));
        results.insert("topk40_over_color".into(), json!(topk40 / color));
    }
    let rest = json!({
        "peak_rss_mb": common::peak_rss_mb(),
        "gaussians": g.len(),
        "width": p.width,
        "height": p.height,
        "views": p.views,
        "repeat": p.repeat,
        "threads": splat_raster::rayon::current_num_threads(),
        "visible_median": common::median_count(&mut visible),
        "tile_pairs_median": common::median_count(&mut pairs),
        "simd": raster.simd().name(),
        "load_s": load_s,
        "prepare_s": prepare_s,
        "scene": p.scene,
    });
    if let Value::Object(rest) = rest {
        results.extend(rest);
    }
    Ok(Value::Object(results))
}

/// The fastest of `repeat` renders of view `v` into `out`: wall and CPU seconds (each the
/// least), and the stats and phases of the fastest. Other load on the machine only ever
/// slows a render down.
fn best_render(
    raster: &Rasterizer<'_>,
    cams: &Cameras,
    v: usize,
    opts: &RenderOptions,
    repeat: u64,
    out: &mut ViewRender,
) -> Result<BestRender, BoxError> {
    let (mut best, mut best_cpu) = (f64::INFINITY, f64::INFINITY);
    let (mut best_stats, mut best_phases) = (out.stats(), out.phases());
    for _ in 0..repeat {
        let cpu0 = common::process_cpu_s();
        let t = Instant::now();
        raster.render_view_into(cams, v, opts, out)?;
        let wall = t.elapsed().as_secs_f64();
        if wall < best {
            (best_stats, best_phases) = (out.stats(), out.phases());
        }
        best = best.min(wall);
        best_cpu = best_cpu.min(common::process_cpu_s() - cpu0);
    }
    Ok(BestRender {
        wall: best,
        cpu: best_cpu,
        stats: best_stats,
        phases: best_phases,
    })
}

/// One view's fastest render (see [`best_render`]).
struct BestRender {
    wall: f64,
    cpu: f64,
    stats: RenderStats,
    phases: Phases,
}

/// The per-view samples of one render configuration.
#[derive(Default)]
struct Samples {
    times: Vec<f64>,
    cpus: Vec<f64>,
    /// Project, sort, bucket and blend, in milliseconds.
    phases: [Vec<f64>; 4],
    groups: Vec<f64>,
    blends: Vec<f64>,
    rates: Vec<f64>,
    occupancy: Vec<f64>,
    inserted: Vec<f64>,
}

impl Samples {
    /// Adds one view's fastest render; `lanes`: of the blend's pixel groups.
    fn add(&mut self, best: BestRender, lanes: f64) {
        self.times.push(best.wall);
        self.cpus.push(best.cpu);
        let ph = best.phases;
        for (all, d) in self
            .phases
            .iter_mut()
            .zip([ph.project, ph.sort, ph.bucket, ph.blend])
        {
            all.push(d.as_secs_f64() * 1e3);
        }
        let c = best.stats.counts;
        if c.groups > 0 {
            self.groups.push(c.groups as f64);
            self.blends.push(c.blends as f64);
            self.rates.push(c.blends as f64 / best.cpu);
            self.occupancy
                .push(c.live_lanes as f64 / (c.groups as f64 * lanes));
            self.inserted.push(c.inserted as f64);
        }
    }

    /// Inserts the medians into `results` under names made from `name` (`…_s`); returns
    /// the median wall seconds per view.
    fn report(mut self, name: String, results: &mut Map<String, Value>) -> f64 {
        let med = common::median(&mut self.times);
        results.insert(
            name.replace("_s", "_cpu_s"),
            json!(common::median(&mut self.cpus)),
        );
        let [mut project, mut sort, mut bucket, mut blend] = self.phases;
        results.insert(
            name.replace("_s", "_phases_ms"),
            json!({
                "project": common::median(&mut project),
                "sort": common::median(&mut sort),
                "bucket": common::median(&mut bucket),
                "blend": common::median(&mut blend),
            }),
        );
        if !self.blends.is_empty() {
            results.insert(
                name.replace("_s", "_counts"),
                json!({
                    "groups": common::median(&mut self.groups),
                    "blends": common::median(&mut self.blends),
                    "blends_per_cpu_s": common::median(&mut self.rates),
                    "lane_occupancy": common::median(&mut self.occupancy),
                    "inserted": common::median(&mut self.inserted),
                }),
            );
        }
        results.insert(name, json!(med));
        med
    }
}

//! `fuse`: register proposal descriptors onto Gaussians (ProFuse paper §3.3) from the
//! rasterizer's top-K weights; shard the views and merge partial sums; benchmark.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error goes to stderr, the exit code is 1 and no output file is written.

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use profuse_formats::{Cameras, FileKind, Gaussians, Masks, Proposals};
use profuse_fuse::{
    accumulate, finish, merge, Groups, Names, Orphans, PartialSums, Precision, Registration, Scene,
    ViewReport, DEFAULT_K,
};
use profuse_tools::{chatty, peak_rss_mb, run, BoxError};
use serde_json::{json, Value};

#[derive(Debug, Parser)]
#[command(
    name = "fuse",
    version,
    about = "Register proposal descriptors onto Gaussians from top-K ray weights (ProFuse §3.3)",
    long_about = "Register language descriptors onto 3D Gaussians without training (ProFuse §3.3). \
                  Every view is rendered at the mask grid with its per-pixel top-K contributors \
                  (Gaussian id, weight ω = T·α); in one pass the masks' masses μ = Σ ω and a \
                  sparse Gaussian x proposal weight matrix W = Σ ω are accumulated (exactly, in \
                  fixed point). Then each proposal's descriptor is the normalised μ-weighted sum \
                  of its member masks' features, and each Gaussian's the normalised W-weighted \
                  sum of the descriptors of the proposals it was rendered into. Views can be \
                  processed in shards (--views, --partial-out) and merged (`fuse merge`) with a \
                  result identical to one run. Prints one JSON report on stdout."
)]
struct Cli {
    /// Do not print progress on stderr.
    #[arg(long, global = true)]
    quiet: bool,
    /// Worker threads (default: rayon's, i.e. RAYON_NUM_THREADS or the core count). The
    /// results do not depend on it.
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Register descriptors (all views, or a shard of them) and write the features and/or
    /// the shard's partial sums.
    Run(RunArgs),
    /// Add up partial-sums files of disjoint view shards that together cover every view,
    /// and write the features: byte-identical to an unsharded `fuse run`.
    Merge {
        /// Partial-sums files written by `fuse run --partial-out`.
        #[arg(required = true)]
        partials: Vec<PathBuf>,
        /// The features file to write (profuse.features).
        #[arg(long)]
        out: PathBuf,
        /// Storage precision of the descriptors (auto = that of the mask features).
        #[arg(long, value_enum, default_value = "auto")]
        precision: PrecisionArg,
    },
    /// Benchmark registration on a synthetic scene (synth preset `scale`, generated in a
    /// child process into a temporary or given directory; generation is not timed and its
    /// memory is not counted). Prints seconds (render + accumulate + finish), the split,
    /// views per second, nonzero W entries and peak RSS.
    Bench(BenchArgs),
    /// (Internal) generate the benchmark scene; run by `bench` in a child process.
    #[command(hide = true)]
    GenerateBenchScene {
        #[arg(long)]
        out: PathBuf,
        #[arg(long)]
        gaussians: usize,
        #[arg(long)]
        views: usize,
        #[arg(long)]
        width: u32,
        #[arg(long)]
        height: u32,
        #[arg(long)]
        seed: u64,
    },
}

#[derive(Debug, clap::Args)]
struct RunArgs {
    /// Gaussians (profuse.gaussians) to register descriptors onto.
    #[arg(long)]
    gaussians: PathBuf,
    /// Cameras of the views (profuse.cameras).
    #[arg(long)]
    cameras: PathBuf,
    /// Masks with their features (profuse.masks), view v = view v of the cameras.
    #[arg(long)]
    masks: PathBuf,
    /// 3D Context Proposals (profuse.proposals) grouping the masks.
    #[arg(long, required_unless_present = "no_proposals")]
    proposals: Option<PathBuf>,
    /// No proposals: every mask registers its own feature (the Dr. Splat-style baseline).
    #[arg(long, conflicts_with_all = ["proposals", "orphans", "registration"])]
    no_proposals: bool,
    /// What a mask's pixels register. `proposals` (paper): the proposal's descriptor
    /// f̄_P = normalise(Σ μ_k f_k over its masks). `blend`: per mask m,
    /// normalise(α f̄_P + (1 − α) f_m / |f_m|) with α = clamp(a_m / c_P, 0, 1),
    /// a_m = cos(f_m, f̄_P) and c_P the μ-weighted mean of a_k over the proposal: a mask as
    /// coherent as the proposal's average member keeps f̄_P, one orthogonal to it keeps
    /// its own feature, so the minority object of an impure proposal is not overwritten.
    /// W then has one column per mask (like --no-proposals), which costs memory and time.
    #[arg(long, value_enum, default_value = "proposals")]
    registration: RegistrationArg,
    /// The features file to write (profuse.features: descriptors, valid, weight_sum).
    #[arg(long, required_unless_present = "partial_out")]
    out: Option<PathBuf>,
    /// Write this run's exact partial sums (profuse.fuse_partial) for `fuse merge`.
    #[arg(long)]
    partial_out: Option<PathBuf>,
    /// Top-K contributors per pixel (1..=256).
    #[arg(long, default_value_t = DEFAULT_K as u16, value_parser = clap::value_parser!(u16).range(1..=256))]
    k: u16,
    /// Masks without a proposal: make each its own proposal with its own feature (default:
    /// masks the grouping leaves out keep their evidence), or ignore their pixels (paper).
    #[arg(long, value_enum, default_value = "singleton")]
    orphans: OrphansArg,
    /// Process only views a..b (half-open): a shard; with --out the features come from
    /// these views alone.
    #[arg(long, value_name = "A..B", value_parser = parse_range)]
    views: Option<Range<usize>>,
    /// Storage precision of the descriptors (auto = that of the mask features).
    #[arg(long, value_enum, default_value = "auto")]
    precision: PrecisionArg,
}

#[derive(Debug, clap::Args)]
struct BenchArgs {
    /// Ground-truth Gaussians of the scene.
    #[arg(long, default_value_t = 1_000_000)]
    gaussians: usize,
    /// Views.
    #[arg(long, default_value_t = 200)]
    views: usize,
    /// Image (and mask) width.
    #[arg(long, default_value_t = 1000)]
    width: u32,
    /// Image (and mask) height.
    #[arg(long, default_value_t = 730)]
    height: u32,
    /// Top-K.
    #[arg(long, default_value_t = DEFAULT_K as u16, value_parser = clap::value_parser!(u16).range(1..=256))]
    k: u16,
    /// Scene seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Keep the scene in this directory and reuse it when it already holds a scene of
    /// these sizes (default: a temporary directory, removed afterwards).
    #[arg(long)]
    scene_dir: Option<PathBuf>,
    /// Also write the features next to the scene (timed separately as `write_s`).
    #[arg(long)]
    write: bool,
    /// Register with every mask as its own group (the baseline) instead of proposals.
    #[arg(long, conflicts_with = "registration")]
    no_proposals: bool,
    /// `proposals` (paper) or `blend` (see `fuse run --help`).
    #[arg(long, value_enum, default_value = "proposals")]
    registration: RegistrationArg,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum RegistrationArg {
    /// Every pixel of a mask registers its proposal's descriptor (paper).
    Proposals,
    /// Every mask registers its proposal's descriptor blended with its own feature by how
    /// well it agrees with the proposal.
    Blend,
}

impl RegistrationArg {
    /// The groups of this registration over `proposals`.
    fn groups(
        self,
        masks: &Masks,
        proposals: &Proposals,
        orphans: Orphans,
        name: &str,
    ) -> profuse_fuse::Result<Groups> {
        match self {
            RegistrationArg::Proposals => Groups::from_proposals(masks, proposals, orphans, name),
            RegistrationArg::Blend => Groups::blend(masks, proposals, orphans, name),
        }
    }
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum OrphansArg {
    /// Pixels of masks without a proposal register nothing.
    Ignore,
    /// Every mask without a proposal is a proposal of its own.
    Singleton,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum PrecisionArg {
    /// The precision of the mask features.
    Auto,
    F16,
    F32,
}

impl PrecisionArg {
    fn resolve(self, masks: &profuse_formats::Floats) -> Precision {
        match self {
            PrecisionArg::Auto => Precision::of(masks),
            PrecisionArg::F16 => Precision::F16,
            PrecisionArg::F32 => Precision::F32,
        }
    }
}

fn parse_range(s: &str) -> Result<Range<usize>, String> {
    let err = || format!("expected A..B with integers A < B, got {s:?}");
    let (a, b) = s.split_once("..").ok_or_else(err)?;
    let (a, b): (usize, usize) = (a.parse().map_err(|_| err())?, b.parse().map_err(|_| err())?);
    if a >= b {
        return Err(err());
    }
    Ok(a..b)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    run(|| {
        if let Some(n) = cli.threads {
            rayon_pool(n)?;
        }
        execute(cli.command, cli.quiet)
    })
}

fn rayon_pool(threads: usize) -> Result<(), BoxError> {
    splat_raster::rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build_global()?;
    Ok(())
}

fn execute(command: Command, quiet: bool) -> Result<Value, BoxError> {
    let show = chatty(quiet);
    match command {
        Command::Run(args) => run_command(args, show),
        Command::Merge {
            partials,
            out,
            precision,
        } => merge_command(&partials, &out, precision, show),
        Command::Bench(args) => bench(args, show),
        Command::GenerateBenchScene {
            out,
            gaussians,
            views,
            width,
            height,
            seed,
        } => {
            let config = bench_config(gaussians, views, width, height, seed);
            let summary = synth::generate(&config, &out)?;
            Ok(serde_json::to_value(&summary)?)
        }
    }
}

fn name(p: &Path) -> String {
    p.display().to_string()
}

fn run_command(a: RunArgs, show: bool) -> Result<Value, BoxError> {
    let t0 = Instant::now();
    let gaussians = Gaussians::read(&a.gaussians)?;
    let cameras = Cameras::read(&a.cameras)?;
    let masks = Masks::read(&a.masks)?;
    let groups = match &a.proposals {
        Some(path) if !a.no_proposals => {
            let proposals = Proposals::read(path)?;
            let orphans = match a.orphans {
                OrphansArg::Ignore => Orphans::Ignore,
                OrphansArg::Singleton => Orphans::Singleton,
            };
            a.registration
                .groups(&masks, &proposals, orphans, &name(path))?
        }
        _ => Groups::per_mask(&masks),
    };
    let scene = Scene::new(&gaussians, &cameras, &masks).named(Names {
        gaussians: name(&a.gaussians),
        cameras: name(&a.cameras),
        masks: name(&a.masks),
    });
    let load_s = t0.elapsed().as_secs_f64();
    let views = a.views.clone().unwrap_or(0..cameras.len());
    let k = usize::from(a.k);
    let t1 = Instant::now();
    let partial = accumulate_with_progress(
        &scene,
        &groups,
        k,
        views.clone(),
        show,
        &mut RenderCounters::default(),
    )?;
    let mut report = json!({
        "gaussians": gaussians.len(),
        "views": [views.start, views.end],
        "k": k,
        "grouping": groups.grouping.name(),
        "orphans": groups.grouping.orphans_name(),
        "load_s": load_s,
    });
    if let Some(path) = &a.partial_out {
        partial.write(path)?;
        report["partial_out"] = json!(path);
    }
    if let Some(out) = &a.out {
        let precision = a.precision.resolve(&masks.features);
        let reg = finish(&partial, precision);
        let seconds = t1.elapsed().as_secs_f64();
        reg.features.write(out)?;
        add_summary(&mut report, &reg, &partial, precision);
        report["seconds"] = json!(seconds);
        report["out"] = json!(out);
    } else {
        report["nnz"] = json!(partial.weights().nnz());
        report["pixels"] = json!(partial.counts().pixels);
        report["hits"] = json!(partial.counts().hits);
        report["seconds"] = json!(t1.elapsed().as_secs_f64());
        add_timings(&mut report, &partial);
    }
    Ok(report)
}

fn merge_command(
    partials: &[PathBuf],
    out: &Path,
    precision: PrecisionArg,
    show: bool,
) -> Result<Value, BoxError> {
    let t0 = Instant::now();
    let parts = partials
        .iter()
        .map(PartialSums::read)
        .collect::<Result<Vec<_>, _>>()?;
    let names: Vec<String> = partials.iter().map(|p| name(p)).collect();
    let merged = merge(&parts, &names)?;
    drop(parts);
    if !merged.is_complete() {
        return Err(profuse_fuse::FuseError::MissingViews {
            missing: merged.missing_views(),
            views: merged.num_views(),
        }
        .into());
    }
    if show {
        eprintln!("merged {} partial files", partials.len());
    }
    let precision = precision.resolve(merged.mask_features());
    let reg = finish(&merged, precision);
    let seconds = t0.elapsed().as_secs_f64();
    reg.features.write(out)?;
    let mut report = json!({
        "partials": partials,
        "gaussians": merged.num_gaussians(),
        "views": [0, merged.num_views()],
        "k": merged.k(),
        "grouping": merged.groups().grouping.name(),
        "orphans": merged.groups().grouping.orphans_name(),
        "seconds": seconds,
        "out": out,
    });
    add_summary(&mut report, &reg, &merged, precision);
    Ok(report)
}

/// Per-view rasterizer counters, collected for the benchmark report.
#[derive(Debug, Default)]
struct RenderCounters {
    visible: Vec<usize>,
    tile_pairs: Vec<usize>,
}

impl RenderCounters {
    fn json(mut self) -> Value {
        json!({
            "median_visible": median(&mut self.visible),
            "median_tile_pairs": median(&mut self.tile_pairs),
        })
    }
}

fn median(v: &mut [usize]) -> usize {
    v.sort_unstable();
    v.get(v.len() / 2).copied().unwrap_or(0)
}

/// [`accumulate`] with a progress bar on stderr when `show`.
fn accumulate_with_progress(
    scene: &Scene<'_>,
    groups: &Groups,
    k: usize,
    views: Range<usize>,
    show: bool,
    counters: &mut RenderCounters,
) -> Result<PartialSums, BoxError> {
    let bar = if show {
        let pb = ProgressBar::new(views.len() as u64);
        if let Ok(style) = ProgressStyle::with_template(
            "fuse {bar:40} {pos}/{len} views [{elapsed} < {eta}] {msg}",
        ) {
            pb.set_style(style);
        }
        pb
    } else {
        ProgressBar::hidden()
    };
    let mut on_view = |r: &ViewReport| {
        bar.inc(1);
        bar.set_message(format!("{} pairs", r.nnz));
        if r.rendered {
            counters.visible.push(r.render.visible);
            counters.tile_pairs.push(r.render.tile_pairs);
        }
    };
    let partial = accumulate(scene, groups, k, views, &mut on_view);
    bar.finish_and_clear();
    Ok(partial?)
}

/// CPU seconds used so far by all threads of this process (0 where unavailable).
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

fn add_timings(report: &mut Value, p: &PartialSums) {
    report["raster_s"] = json!(p.timings().raster_s);
    report["accumulate_s"] = json!(p.timings().accumulate_s);
    report["compact_s"] = json!(p.timings().compact_s);
}

fn add_summary(report: &mut Value, reg: &Registration, p: &PartialSums, precision: Precision) {
    let s = &reg.summary;
    report["valid"] = json!(s.valid);
    report["nnz"] = json!(s.nnz);
    report["groups"] = json!(s.groups);
    report["groups_with_descriptor"] = json!(s.groups_with_descriptor);
    report["masks"] = json!(s.masks);
    report["assigned_masks"] = json!(s.assigned_masks);
    report["mask_mass"] = json!({
        "masks_with_mass": s.masks_with_mass,
        "total": s.mass_total,
        "min": s.mass_min,
        "median": s.mass_median,
        "max": s.mass_max,
    });
    report["pixels"] = json!(s.pixels);
    report["hits"] = json!(s.hits);
    report["feature_dim"] = json!(p.dim());
    report["precision"] = json!(precision.name());
    report["finish_s"] = json!(s.finish_s);
    add_timings(report, p);
}

// ---------------------------------------------------------------------------------------
// bench

fn bench_config(
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

/// Removes a temporary benchmark directory when dropped.
struct TempScene(Option<PathBuf>);

impl Drop for TempScene {
    fn drop(&mut self) {
        if let Some(d) = &self.0 {
            let _ = std::fs::remove_dir_all(d);
        }
    }
}

/// Whether `dir` holds a benchmark scene generated with exactly `config`.
fn scene_matches(dir: &Path, config: &synth::Config) -> bool {
    let Ok(text) = std::fs::read_to_string(dir.join("gt/scene.json")) else {
        return false;
    };
    let Ok(json) = serde_json::from_str::<Value>(&text) else {
        return false;
    };
    serde_json::to_value(config).is_ok_and(|c| json["parameters"] == c)
        && dir.join("masks.safetensors").exists()
        && dir.join("gt/gaussians.safetensors").exists()
}

fn bench(a: BenchArgs, show: bool) -> Result<Value, BoxError> {
    let config = bench_config(a.gaussians, a.views, a.width, a.height, a.seed);
    let (dir, _cleanup) = match &a.scene_dir {
        Some(d) => (d.clone(), TempScene(None)),
        None => {
            let d = std::env::temp_dir().join(format!("profuse-fuse-bench-{}", std::process::id()));
            (d.clone(), TempScene(Some(d)))
        }
    };
    let mut generate_s = None;
    if !scene_matches(&dir, &config) {
        if show {
            eprintln!("generating the scene in {} (not timed) ...", dir.display());
        }
        let t0 = Instant::now();
        // A child process, so that the generator's memory does not count in peak_rss_mb.
        let status = std::process::Command::new(std::env::current_exe()?)
            .arg("generate-bench-scene")
            .arg("--out")
            .arg(&dir)
            .args(["--gaussians", &a.gaussians.to_string()])
            .args(["--views", &a.views.to_string()])
            .args(["--width", &a.width.to_string()])
            .args(["--height", &a.height.to_string()])
            .args(["--seed", &a.seed.to_string()])
            .stdout(std::process::Stdio::null())
            .status()?;
        if !status.success() {
            return Err(
                format!("generating the benchmark scene in {} failed", dir.display()).into(),
            );
        }
        generate_s = Some(t0.elapsed().as_secs_f64());
    }

    let t0 = Instant::now();
    let gaussians = Gaussians::read(dir.join("gt/gaussians.safetensors"))?;
    let cameras = Cameras::read(dir.join("cameras.safetensors"))?;
    let masks = Masks::read(dir.join("masks.safetensors"))?;
    let groups = if a.no_proposals {
        Groups::per_mask(&masks)
    } else {
        let proposals = profuse_fuse::testing::proposals_from_mask_objects(
            dir.join("gt/mask_objects.json"),
            &masks,
            1,
        )?;
        a.registration.groups(
            &masks,
            &proposals,
            Orphans::Ignore,
            "ground-truth proposals",
        )?
    };
    let scene = Scene::new(&gaussians, &cameras, &masks);
    let load_s = t0.elapsed().as_secs_f64();

    let k = usize::from(a.k);
    let mut counters = RenderCounters::default();
    let t0 = Instant::now();
    let cpu0 = process_cpu_s();
    let partial =
        accumulate_with_progress(&scene, &groups, k, 0..cameras.len(), show, &mut counters)?;
    let precision = Precision::of(&masks.features);
    let reg = finish(&partial, precision);
    let seconds = t0.elapsed().as_secs_f64();
    let cpu_s = process_cpu_s() - cpu0;
    let write_s = if a.write {
        let t = Instant::now();
        reg.features.write(dir.join("features.safetensors"))?;
        Some(t.elapsed().as_secs_f64())
    } else {
        None
    };
    let mut report = json!({
        "seconds": seconds,
        "cpu_s": cpu_s,
        "peak_rss_mb": peak_rss_mb(),
        "views_per_s": cameras.len() as f64 / seconds,
        "gaussians": gaussians.len(),
        "views": cameras.len(),
        "width": masks.width,
        "height": masks.height,
        "k": k,
        "grouping": groups.grouping.name(),
        "threads": splat_raster::rayon::current_num_threads(),
        "load_s": load_s,
        "generate_s": generate_s,
        "write_s": write_s,
        "scene_dir": a.scene_dir,
    });
    add_summary(&mut report, &reg, &partial, precision);
    report["render"] = counters.json();
    Ok(report)
}

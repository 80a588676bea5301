//! `metrics`: the evaluation protocols of the ProFuse paper and of the pipeline's stages.
//!
//! Every input is a command-line argument; each subcommand prints one JSON object on
//! stdout. Progress goes to stderr when it is a terminal and `--quiet` is not given. On
//! failure the error (naming the file and field) goes to stderr and the exit code is 1.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use profuse_formats::{FileKind, Gaussians, Proposals, VertexLabels};
use profuse_metrics::cluster::{adjusted_rand_index, proposal_scores, read_mask_objects};
use profuse_metrics::lerf::{evaluate_scene, mean_over_scenes, read_label_dir, PredDir};
use profuse_metrics::mask::{
    fill_poly_as, fits_int32, rasterize_polygon, reference_vertices, OpenCvFill,
};
use profuse_metrics::scannet::{evaluate, ground_truth_labels, ClassSet};
use profuse_metrics::surface::{scene_extent, summarize, surface_distances_with_progress};
use profuse_tools::{chatty, peak_rss_mb, run, warn, BoxError};
use serde_json::{json, Map, Value};

#[derive(Debug, Parser)]
#[command(
    name = "metrics",
    version,
    about = "Evaluation: ScanNet mIoU/mAcc, LERF-OVS selection IoU, proposal clustering, surface distance",
    long_about = "Evaluation protocols of the ProFuse paper and of the pipeline's stages. \
                  `scannet`: per-vertex labels against a labelled mesh (19/15/10-class NYU40 \
                  sets, paper Table 2). `lerf`: predicted PNG masks against LangSplat label \
                  polygons (mIoU, Acc@0.25, paper Table 1). `proposals`: 3D Context Proposals \
                  against synth's per-mask ground truth (ARI, purity, completeness). \
                  `surface`: distance of Gaussian centres to a synth scene's exact surface. \
                  `bench`: throughput of each metric. Each prints one JSON object on stdout; \
                  the definitions are in crates/metrics/README.md."
)]
struct Cli {
    /// Do not print progress or warnings on stderr.
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum SetArg {
    /// The 19 classes of OpenGaussian's protocol.
    #[value(name = "19")]
    S19,
    /// The 15-class subset.
    #[value(name = "15")]
    S15,
    /// The 10-class subset.
    #[value(name = "10")]
    S10,
    /// Every NYU40 class (not a paper setting; synth scenes also have ceiling and lamp).
    #[value(name = "40")]
    S40,
    /// The paper's three sets: 19, 15 and 10.
    #[value(name = "all")]
    All,
}

impl SetArg {
    fn sets(self) -> Vec<ClassSet> {
        match self {
            SetArg::S19 => vec![ClassSet::Nyu19],
            SetArg::S15 => vec![ClassSet::Nyu15],
            SetArg::S10 => vec![ClassSet::Nyu10],
            SetArg::S40 => vec![ClassSet::Nyu40],
            SetArg::All => ClassSet::PAPER.to_vec(),
        }
    }
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum OpenCvArg {
    /// OpenCV >= 4.11 (the default rule of `metrics lerf`).
    Current,
    /// OpenCV <= 4.7.
    Legacy,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// ScanNet point-cloud understanding: mIoU and mAcc (per-class recall) in percent,
    /// averaged over the set's classes present in the ground truth, with a per-class table.
    /// Vertices whose ground truth is outside the set (or 0, unannotated) are ignored; a
    /// prediction of -1 or outside the set is wrong.
    Scannet {
        /// Predicted labels: a vertex_labels file (.safetensors, labels I32, -1 = none).
        #[arg(long)]
        pred: PathBuf,
        /// Ground truth: a mesh file with `labels` (.safetensors), a ScanNet
        /// `*_vh_clean_2.labels.ply`, or a NumPy export (directory with one
        /// `*_vert_all.npy` and its `*_sem_label_all.npy`, or that prefix).
        #[arg(long)]
        mesh: PathBuf,
        /// Class set: 19, 15, 10, 40 (every NYU40 class) or all (= 19, 15 and 10).
        #[arg(long, value_enum, default_value = "all")]
        set: SetArg,
    },
    /// LERF-OVS 3D object selection: IoU per (frame, query) of predicted PNG masks
    /// (PRED/<frame_stem>/<query>.png, non-zero = selected; '/' and '\' in a query become
    /// '_') against the label polygons (rasterised as the reference evaluation does:
    /// int32 truncation, then cv2.fillPoly with the outline included; same-category objects
    /// unioned).
    /// mIoU and Acc@0.25 (IoU > 0.25, strict) in percent per scene and averaged over
    /// scenes; a missing PNG scores IoU 0. Give --labels and --pred once per scene, in the
    /// same order.
    Lerf {
        /// Label directory of a scene (LangSplat `label/<scene>/` or synth `gt/label/`):
        /// one `<frame_stem>.json` per evaluation frame. Repeat for several scenes.
        #[arg(long, required = true, num_args = 1)]
        labels: Vec<PathBuf>,
        /// Prediction directory of the scene given by the --labels at the same position.
        #[arg(long, required = true, num_args = 1)]
        pred: Vec<PathBuf>,
        /// Evaluate only these queries (default: every category of every frame).
        #[arg(long, num_args = 1..)]
        queries: Option<Vec<String>>,
        /// Leave the per-pair rows out of the report (per-query summaries stay).
        #[arg(long)]
        no_rows: bool,
    },
    /// 3D Context Proposals against synth's ground truth: adjusted Rand index, purity and
    /// completeness of the mask -> proposal assignment (unassigned masks = singletons;
    /// masks on no object excluded).
    Proposals {
        /// Proposals file (profuse.proposals) written by warp-graph.
        #[arg(long)]
        proposals: PathBuf,
        /// synth's `gt/mask_objects.json`: `masks[i].object` is the truth of global mask i.
        #[arg(long)]
        truth: PathBuf,
    },
    /// Rasterises polygons with the LERF-OVS ground-truth rule (int32 truncation of every
    /// coordinate, then cv2.fillPoly semantics: outline included) and prints each mask as
    /// row runs. Input: JSON `{"cases": [{"width": W, "height": H, "polygon": [[x, y],
    /// ...]}, ...]}`. Output: `{"cases": N, "masks": [{"pixels": n, "runs": [[y, x_begin,
    /// x_end), ...]}, ...]}` (x_end exclusive). Used to check the rasteriser against OpenCV.
    Rasterize {
        /// The JSON file of polygons.
        #[arg(long)]
        polygons: PathBuf,
        /// Which OpenCV's fillPoly to reproduce: `current` (>= 4.11) or `legacy` (<= 4.7);
        /// they differ only for polygons with vertices outside the image.
        #[arg(long, value_enum, default_value = "current")]
        opencv: OpenCvArg,
    },
    /// Distance of Gaussian centres to the exact surface of a synth scene: count, median,
    /// mean, 90th percentile (metres), and the median relative to the room's diagonal.
    Surface {
        /// Gaussians: .safetensors (profuse.gaussians) or INRIA .ply.
        #[arg(long)]
        gaussians: PathBuf,
        /// synth's `gt/scene.json`.
        #[arg(long)]
        scene: PathBuf,
    },
    /// Throughput of every metric on generated data (no files): ScanNet evaluation, ARI,
    /// polygon rasterisation + IoU, surface distances; prints seconds, rates and peak
    /// memory as one JSON object.
    Bench {
        /// Vertices of the ScanNet evaluation.
        #[arg(long, default_value_t = 1_000_000)]
        vertices: usize,
        /// Items of the ARI / cluster scores.
        #[arg(long, default_value_t = 1_000_000)]
        items: usize,
        /// Frame width of the LERF rasterisation.
        #[arg(long, default_value_t = 986)]
        width: u32,
        /// Frame height of the LERF rasterisation.
        #[arg(long, default_value_t = 728)]
        height: u32,
        /// Polygons (of 200 vertices each) rasterised and scored.
        #[arg(long, default_value_t = 200)]
        polygons: usize,
        /// Points of the surface-distance benchmark (in synth's demo room).
        #[arg(long, default_value_t = 100_000)]
        points: usize,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| execute(cli.command, quiet))
}

fn execute(command: Command, quiet: bool) -> Result<Value, BoxError> {
    match command {
        Command::Scannet { pred, mesh, set } => scannet(&pred, &mesh, set),
        Command::Lerf {
            labels,
            pred,
            queries,
            no_rows,
        } => lerf(&labels, &pred, queries.as_deref(), !no_rows, quiet),
        Command::Proposals { proposals, truth } => proposals_cmd(&proposals, &truth),
        Command::Rasterize { polygons, opencv } => rasterize(
            &polygons,
            match opencv {
                OpenCvArg::Current => OpenCvFill::Current,
                OpenCvArg::Legacy => OpenCvFill::Legacy,
            },
        ),
        Command::Surface { gaussians, scene } => surface(&gaussians, &scene, quiet),
        Command::Bench {
            vertices,
            items,
            width,
            height,
            polygons,
            points,
        } => bench(vertices, items, (width, height), polygons, points, quiet),
    }
}

fn path_str(p: &Path) -> String {
    p.display().to_string()
}

fn scannet(pred: &Path, mesh: &Path, set: SetArg) -> Result<Value, BoxError> {
    let labels = VertexLabels::read(pred)?;
    let truth = ground_truth_labels(
        &scene_io::scannet::read_labelled_mesh(mesh)?,
        mesh.display(),
    )?;
    let pred_labels = labels.labels.to_vec();
    let mut sets = Map::new();
    for s in set.sets() {
        let scores = evaluate(&pred_labels, &truth, s)?;
        sets.insert(s.name().to_string(), serde_json::to_value(scores)?);
    }
    Ok(json!({
        "pred": path_str(pred),
        "mesh": path_str(mesh),
        "vertices": truth.len(),
        "sets": sets,
    }))
}

fn lerf(
    labels: &[PathBuf],
    preds: &[PathBuf],
    queries: Option<&[String]>,
    rows: bool,
    quiet: bool,
) -> Result<Value, BoxError> {
    if labels.len() != preds.len() {
        return Err(format!(
            "--labels is given {} times but --pred {} times; give one prediction directory per label directory",
            labels.len(),
            preds.len()
        )
        .into());
    }
    let bar = progress_bar(chatty(quiet), labels.len() as u64, "scenes");
    let mut scenes = Vec::with_capacity(labels.len());
    for (l, p) in labels.iter().zip(preds) {
        if !p.is_dir() {
            warn(
                quiet,
                &format!(
                    "{}: no such prediction directory; every pair scores IoU 0",
                    p.display()
                ),
            );
        }
        let scene = read_label_dir(l)?;
        scenes.push(evaluate_scene(
            &scene,
            &PredDir { dir: p.clone() },
            queries,
        )?);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let mean = mean_over_scenes(&scenes);
    let mut scene_values = Vec::with_capacity(scenes.len());
    for (s, (l, p)) in scenes.iter().zip(labels.iter().zip(preds)) {
        let mut v = serde_json::to_value(s)?;
        if let Some(obj) = v.as_object_mut() {
            if !rows {
                obj.remove("rows");
            }
            obj.insert("labels".into(), path_str(l).into());
            obj.insert("pred".into(), path_str(p).into());
        }
        scene_values.push(v);
    }
    Ok(json!({
        "miou": mean.miou,
        "acc25": mean.acc25,
        "scenes_scored": mean.scenes,
        "queries": queries,
        "scenes": scene_values,
    }))
}

#[derive(serde::Deserialize)]
struct RasterCases {
    cases: Vec<RasterCase>,
}

#[derive(serde::Deserialize)]
struct RasterCase {
    width: u32,
    height: u32,
    polygon: Vec<[f64; 2]>,
}

/// Largest mask side `rasterize` accepts (the label files' limit).
const MAX_RASTER_SIDE: u32 = profuse_metrics::lerf::MAX_SIDE;

fn rasterize(path: &Path, variant: OpenCvFill) -> Result<Value, BoxError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("{}: cannot read polygons: {e}", path.display()))?;
    let input: RasterCases = serde_json::from_str(&text).map_err(|e| {
        format!(
            "{}: expected {{\"cases\": [{{\"width\", \"height\", \"polygon\": [[x, y], ...]}}]}}: {e}",
            path.display()
        )
    })?;
    let mut masks = Vec::with_capacity(input.cases.len());
    for (i, case) in input.cases.iter().enumerate() {
        if !(1..=MAX_RASTER_SIDE).contains(&case.width)
            || !(1..=MAX_RASTER_SIDE).contains(&case.height)
        {
            return Err(format!(
                "{}: cases[{i}]: {}x{}, expected each side in 1..={MAX_RASTER_SIDE}",
                path.display(),
                case.width,
                case.height
            )
            .into());
        }
        if let Some(k) = case
            .polygon
            .iter()
            .position(|p| !p.iter().all(|&v| fits_int32(v)))
        {
            return Err(format!(
                "{}: cases[{i}].polygon[{k}]: {:?} does not fit int32 after truncation",
                path.display(),
                case.polygon[k]
            )
            .into());
        }
        let m = fill_poly_as(
            &reference_vertices(&case.polygon),
            case.width,
            case.height,
            variant,
        );
        let w = m.width as usize;
        let mut runs = Vec::new();
        for (y, row) in m.pixels.chunks(w.max(1)).enumerate() {
            let mut x = 0;
            while x < row.len() {
                if row[x] {
                    let begin = x;
                    while x < row.len() && row[x] {
                        x += 1;
                    }
                    runs.push(json!([y, begin, x]));
                } else {
                    x += 1;
                }
            }
        }
        masks.push(json!({"pixels": m.count(), "runs": runs}));
    }
    Ok(json!({"cases": masks.len(), "masks": masks}))
}

fn proposals_cmd(proposals: &Path, truth: &Path) -> Result<Value, BoxError> {
    let p = Proposals::read(proposals)?;
    let t = read_mask_objects(truth)?;
    let scores = proposal_scores(&p, &t).map_err(|e| format!("{}: {e}", proposals.display()))?;
    let mut objects: Vec<u32> = t.iter().copied().filter(|&o| o != u32::MAX).collect();
    objects.sort_unstable();
    objects.dedup();
    let mut v = serde_json::to_value(&scores)?;
    if let Some(obj) = v.as_object_mut() {
        obj.insert("proposals_file".into(), path_str(proposals).into());
        obj.insert("truth_file".into(), path_str(truth).into());
        obj.insert("masks".into(), t.len().into());
        obj.insert("proposals".into(), p.len().into());
        obj.insert("truth_objects".into(), objects.len().into());
    }
    Ok(v)
}

fn load_gaussians(path: &Path, quiet: bool) -> Result<Gaussians, BoxError> {
    if path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("ply"))
    {
        let (g, report) = scene_io::ply::read_inria_ply(path)?;
        if report.clamped_opacity > 0 {
            warn(
                quiet,
                &format!(
                    "{}: clamped {} non-finite opacity logits",
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

fn surface(gaussians: &Path, scene_path: &Path, quiet: bool) -> Result<Value, BoxError> {
    let g = load_gaussians(gaussians, quiet)?;
    let scene = synth::Scene::from_json(scene_path)?;
    let bar = progress_bar(chatty(quiet), g.len() as u64, "points");
    let start = Instant::now();
    let d = surface_distances_with_progress(
        &g.means,
        |p| scene.distance_to_surface(p),
        |n| bar.inc(n as u64),
    );
    bar.finish_and_clear();
    let summary = summarize(&d, scene_extent(scene.room_size));
    let mut v = serde_json::to_value(&summary)?;
    if let Some(obj) = v.as_object_mut() {
        obj.insert("gaussians_file".into(), path_str(gaussians).into());
        obj.insert("scene_file".into(), path_str(scene_path).into());
        obj.insert("gaussians".into(), g.len().into());
        obj.insert("seconds".into(), start.elapsed().as_secs_f64().into());
    }
    Ok(v)
}

fn progress_bar(show: bool, len: u64, unit: &'static str) -> ProgressBar {
    if !show {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new(len);
    if let Ok(style) =
        ProgressStyle::with_template("{elapsed_precise} [{bar:40}] {pos}/{len} {msg} ({eta})")
    {
        pb.set_style(style.progress_chars("=> "));
    }
    pb.set_message(unit);
    pb
}

/// SplitMix64: dependency-free deterministic data for the benchmark.
fn splitmix(state: &AtomicU64) -> u64 {
    let mut z = state
        .fetch_add(0x9E37_79B9_7F4A_7C15, Ordering::Relaxed)
        .wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn bench(
    vertices: usize,
    items: usize,
    (width, height): (u32, u32),
    polygons: usize,
    points: usize,
    quiet: bool,
) -> Result<Value, BoxError> {
    let show = chatty(quiet);
    let rng = AtomicU64::new(42);
    let mut next = |m: u64| splitmix(&rng) % m.max(1);

    // ScanNet: labels 0..=40, predictions -1..=40, 80 % correct.
    let truth: Vec<u32> = (0..vertices).map(|_| next(41) as u32).collect();
    let pred: Vec<i32> = truth
        .iter()
        .map(|&t| {
            if next(5) == 0 {
                next(42) as i32 - 1
            } else {
                t as i32
            }
        })
        .collect();
    let t = Instant::now();
    let mut scannet_miou = Vec::new();
    for set in ClassSet::PAPER {
        scannet_miou.push(evaluate(&pred, &truth, set)?.miou);
    }
    let scannet_s = t.elapsed().as_secs_f64();
    if show {
        eprintln!("scannet: {scannet_s:.3} s");
    }

    // ARI: 1000 truth objects, predictions 90 % right, 5 % unassigned.
    let objects: Vec<u32> = (0..items).map(|_| next(1000) as u32).collect();
    let clusters: Vec<u32> = objects
        .iter()
        .map(|&o| match next(20) {
            0 => u32::MAX,
            1 => next(1000) as u32,
            _ => o,
        })
        .collect();
    let t = Instant::now();
    let ari = adjusted_rand_index(&clusters, &objects)?;
    let ari_s = t.elapsed().as_secs_f64();
    if show {
        eprintln!("ari: {ari_s:.3} s");
    }

    // LERF: star-shaped 200-gon per polygon, rasterised and scored against a shifted copy.
    let t = Instant::now();
    let mut iou_sum = 0.0;
    for k in 0..polygons {
        let (cx, cy) = (
            next(u64::from(width)) as f64,
            next(u64::from(height)) as f64,
        );
        let r = 20.0 + next(200) as f64;
        let star = |dx: f64| -> Vec<[f64; 2]> {
            (0..200)
                .map(|i| {
                    let a = i as f64 * std::f64::consts::TAU / 200.0;
                    let rr = r * (1.0 + 0.3 * (5.0 * a + k as f64).sin());
                    [cx + dx + rr * a.cos(), cy + rr * a.sin()]
                })
                .collect()
        };
        let gt = rasterize_polygon(&star(0.0), width, height);
        let pr = rasterize_polygon(&star(r * 0.2), width, height);
        let i = gt.intersection(&pr);
        let u = gt.count() + pr.count() - i;
        if u > 0 {
            iou_sum += i as f64 / u as f64;
        }
    }
    let lerf_s = t.elapsed().as_secs_f64();
    if show {
        eprintln!("lerf: {lerf_s:.3} s");
    }

    // Surface: points in synth's demo room.
    let scene = synth::Scene::generate(&synth::Config::preset(synth::Preset::Demo, 0))?;
    let [sx, sy, sz] = scene.room_size;
    let pts: Vec<[f32; 3]> = (0..points)
        .map(|_| {
            let u = |s: f64, m: &mut dyn FnMut(u64) -> u64| {
                (m(1 << 20) as f64 / f64::from(1 << 20) * s) as f32
            };
            [
                u(sx, &mut next) - (sx / 2.0) as f32,
                u(sy, &mut next) - (sy / 2.0) as f32,
                u(sz, &mut next),
            ]
        })
        .collect();
    let t = Instant::now();
    let d = surface_distances_with_progress(&pts, |p| scene.distance_to_surface(p), |_| {});
    let surface_s = t.elapsed().as_secs_f64();
    let median = summarize(&d, scene_extent(scene.room_size)).median;

    let rate = |n: usize, s: f64| if s > 0.0 { n as f64 / s } else { f64::NAN };
    Ok(json!({
        "cores": std::thread::available_parallelism().map_or(1, |n| n.get()),
        "rayon_num_threads": std::env::var("RAYON_NUM_THREADS").ok(),
        "scannet": {"vertices": vertices, "sets": 3, "seconds": scannet_s,
                    "vertices_per_s": rate(vertices * 3, scannet_s), "miou": scannet_miou},
        "ari": {"items": items, "seconds": ari_s, "items_per_s": rate(items, ari_s), "ari": ari},
        "lerf": {"width": width, "height": height, "pairs": polygons, "seconds": lerf_s,
                 "pairs_per_s": rate(polygons, lerf_s),
                 "mean_iou": if polygons > 0 { iou_sum / polygons as f64 } else { f64::NAN }},
        "surface": {"points": points, "objects": scene.len(), "seconds": surface_s,
                    "points_per_s": rate(points, surface_s), "median": median},
        "peak_rss_mb": peak_rss_mb(),
    }))
}

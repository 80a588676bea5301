//! `metrics`: the evaluation protocols of the ProFuse paper and of the pipeline's stages.
//!
//! Every input is a command-line argument; each subcommand prints one JSON object on
//! stdout. Progress goes to stderr when it is a terminal and `--quiet` is not given. On
//! failure the error (naming the file and field) goes to stderr and the exit code is 1.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{Parser, Subcommand, ValueEnum};
use profuse_bench::metrics as bench;
use profuse_formats::{FileKind, Proposals, VertexLabels};
use profuse_metrics::cluster::{member_scores, proposal_scores, read_mask_objects};
use profuse_metrics::lerf::{evaluate_scene, mean_over_scenes, read_label_dir, PredDir};
use profuse_metrics::mask::OpenCvFill;
use profuse_metrics::raster_cases;
use profuse_metrics::scannet::{evaluate, ground_truth_labels, ClassSet};
use profuse_metrics::surface::{scene_extent, summarize, surface_distances_with_progress};
use profuse_tools::scene::load_scene;
use profuse_tools::{chatty, progress_bar, run, warn, BoxError};
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

/// `19`, `15`, `10` (the paper's sets), `40` (every NYU40 class; synth scenes also have
/// ceiling and lamp) or `all` (19, 15 and 10).
fn class_sets(text: &str) -> Result<Vec<ClassSet>, String> {
    match (text, ClassSet::parse(text)) {
        ("all", _) => Ok(ClassSet::PAPER.to_vec()),
        (_, Some(set)) => Ok(vec![set]),
        _ => Err(format!("expected 19, 15, 10, 40 or all, got {text:?}")),
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
        #[arg(long, default_value = "all")]
        set: String,
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
    /// completeness of the mask -> instance assignment (`mask_instance`: members and
    /// attached masks; `mask_proposal` when the file has none; unassigned masks =
    /// singletons; masks on no object excluded), and under "members" the same for the
    /// members alone.
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
    Bench(bench::Params),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| execute(cli.command, quiet))
}

fn execute(command: Command, quiet: bool) -> Result<Value, BoxError> {
    match command {
        Command::Scannet { pred, mesh, set } => scannet(&pred, &mesh, &class_sets(&set)?),
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
        Command::Bench(params) => bench::run(&params, chatty(quiet)),
    }
}

fn path_str(p: &Path) -> String {
    p.display().to_string()
}

fn scannet(pred: &Path, mesh: &Path, classes: &[ClassSet]) -> Result<Value, BoxError> {
    let labels = VertexLabels::read(pred)?;
    let truth = ground_truth_labels(
        &scene_io::scannet::read_labelled_mesh(mesh)?,
        mesh.display(),
    )?;
    let pred_labels = labels.labels.to_vec();
    let mut sets = Map::new();
    for &s in classes {
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
        let (l, p) = (labels.len(), preds.len());
        let msg = format!("--labels is given {l} times but --pred {p} times; give one prediction directory per label directory");
        return Err(msg.into());
    }
    let bar = progress_bar(chatty(quiet), labels.len() as u64, "lerf", "scenes");
    let mut scenes = Vec::with_capacity(labels.len());
    for (l, p) in labels.iter().zip(preds) {
        if !p.is_dir() {
            let msg = format!(
                "{}: no such prediction directory; every pair scores IoU 0",
                p.display()
            );
            warn(quiet, &msg);
        }
        let scene = read_label_dir(l)?;
        let pred = PredDir { dir: p.clone() };
        scenes.push(evaluate_scene(&scene, &pred, queries)?);
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

fn rasterize(path: &Path, variant: OpenCvFill) -> Result<Value, BoxError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("{}: cannot read polygons: {e}", path.display()))?;
    let report = raster_cases::rasterize_cases(&text, &path_str(path), variant)?;
    Ok(serde_json::to_value(report)?)
}

fn proposals_cmd(proposals: &Path, truth: &Path) -> Result<Value, BoxError> {
    let p = Proposals::read(proposals)?;
    let t = read_mask_objects(truth)?;
    let scores = proposal_scores(&p, &t).map_err(|e| format!("{}: {e}", proposals.display()))?;
    let members = member_scores(&p, &t).map_err(|e| format!("{}: {e}", proposals.display()))?;
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
        obj.insert("members".into(), serde_json::to_value(&members)?);
    }
    Ok(v)
}

fn surface(gaussians: &Path, scene_path: &Path, quiet: bool) -> Result<Value, BoxError> {
    let g = load_scene(gaussians, quiet)?;
    let scene = synth::Scene::from_json(scene_path)?;
    let bar = progress_bar(chatty(quiet), g.len() as u64, "surface", "points");
    let start = Instant::now();
    let distance = |p: [f64; 3]| scene.distance_to_surface(p);
    let d = surface_distances_with_progress(&g.means, distance, |n| bar.inc(n as u64));
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

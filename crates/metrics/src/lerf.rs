//! LERF-OVS open-vocabulary 3D object selection (paper §4.2, Table 1), with the protocol of
//! LangSplat / OpenGaussian.
//!
//! * Ground truth: one LangSplat label JSON per evaluation frame,
//!   `{"info": {"name", "width", "height"}, "objects": [{"category", "segmentation":
//!   [[x, y], ...], "bbox"}]}` (extra fields are ignored). Each object's polygon is
//!   rasterised as the reference evaluation does (LangSplat's `polygon_to_mask`:
//!   coordinates truncated to int32, then `cv2.fillPoly`, outline included; see
//!   [`crate::mask`]); objects of the same category are unioned into one mask per
//!   (frame, category), as its `stack_mask` does.
//! * Pairs: every (frame, category) of the ground truth, optionally restricted to a list
//!   of queries. A category whose polygons cover no pixel (empty, or entirely outside the
//!   image) has nothing to find; such pairs are skipped and counted in `empty_gt`.
//! * Predictions: a binary mask per pair, from a [`MaskSource`]; [`PredDir`] reads
//!   `PRED_DIR/<frame_stem>/<query_file_name(query)>.png`, where `frame_stem` is the label
//!   file's name without `.json` (e.g. `frame_00041`) and [`query_file_name`] is the query
//!   text with path separators replaced. Non-zero = selected. A missing prediction is an
//!   empty mask (IoU 0); a prediction of another size is an error.
//! * IoU = |P ∩ G| / |P ∪ G| per pair; scene mIoU = mean over its pairs; Acc@0.25 = share
//!   of pairs with IoU **strictly greater** than 0.25 (LangSplat's `iou > 0.25`; the paper's
//!   text says "at least", its reference code uses `>`); the final scores are the means
//!   over scenes. Scene and mean scores are in percent, per-pair IoUs are fractions.
//! * Threshold: [`grid_search`] evaluates every threshold of a grid with masks produced on
//!   demand and returns all rows and the best (highest mean mIoU; ties: higher Acc@0.25,
//!   then the earlier threshold).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{invalid, io_err};
use crate::mask::{fits_int32, rasterize_polygon, read_mask_png, Mask};
use crate::{MetricsError, Result};

/// IoU above which (strictly) a pair counts for Acc@0.25.
pub const ACC_IOU: f64 = 0.25;

/// Largest accepted image side in a label file (guards the mask allocation).
pub const MAX_SIDE: u32 = 1 << 15;

/// One ground-truth object of a label file.
#[derive(Debug, Clone, PartialEq)]
pub struct LabelObject {
    /// The category = the text query that should select it.
    pub category: String,
    /// Polygon vertices (x, y), pixels, origin at the top-left image corner.
    pub polygon: Vec<[f64; 2]>,
}

/// One evaluation frame: a parsed label file.
#[derive(Debug, Clone, PartialEq)]
pub struct LabelFrame {
    /// The label file's name without `.json`; names the frame's prediction folder.
    pub stem: String,
    /// `info.name`, the image the labels belong to.
    pub image_name: String,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// The objects, in file order.
    pub objects: Vec<LabelObject>,
}

#[derive(Deserialize)]
struct LabelJson {
    info: InfoJson,
    objects: Vec<ObjectJson>,
}

#[derive(Deserialize)]
struct InfoJson {
    name: String,
    width: u32,
    height: u32,
}

#[derive(Deserialize)]
struct ObjectJson {
    category: String,
    segmentation: Vec<[f64; 2]>,
}

/// Reads and validates one LangSplat label file.
pub fn read_label_file(path: impl AsRef<Path>) -> Result<LabelFrame> {
    let path = path.as_ref();
    let text = std::fs::read_to_string(path).map_err(io_err(path, "cannot read label file"))?;
    let stem = path
        .file_name()
        .and_then(|n| n.to_str())
        .map(|n| n.strip_suffix(".json").unwrap_or(n).to_string())
        .ok_or_else(|| invalid(path.display(), "file name", "not valid UTF-8"))?;
    parse_label_json(&text, stem, &path.display().to_string())
}

/// Parses the text of a label file; `stem` names the frame, `shown` the source in errors.
pub fn parse_label_json(text: &str, stem: String, shown: &str) -> Result<LabelFrame> {
    let json: LabelJson = serde_json::from_str(text).map_err(|source| MetricsError::Json {
        path: shown.to_string(),
        expected: "LangSplat label file ({info: {name, width, height}, objects: [{category, segmentation}]})",
        source,
    })?;
    let (w, h) = (json.info.width, json.info.height);
    if !(1..=MAX_SIDE).contains(&w) || !(1..=MAX_SIDE).contains(&h) {
        return Err(invalid(
            shown,
            "info.width/info.height",
            format!("{w}x{h}, expected each side in 1..={MAX_SIDE}"),
        ));
    }
    let mut objects = Vec::with_capacity(json.objects.len());
    for (i, o) in json.objects.into_iter().enumerate() {
        if o.category.is_empty() {
            return Err(invalid(
                shown,
                format!("objects[{i}].category"),
                "empty, expected the query text",
            ));
        }
        // The reference casts the coordinates to int32 with NumPy, which raises on
        // non-finite values and on values outside int32; reject those here too.
        if let Some(k) = o
            .segmentation
            .iter()
            .position(|p| !p.iter().all(|&v| fits_int32(v)))
        {
            return Err(invalid(
                shown,
                format!("objects[{i}].segmentation[{k}]"),
                format!(
                    "{:?}: expected finite coordinates within int32 after truncation",
                    o.segmentation[k]
                ),
            ));
        }
        objects.push(LabelObject {
            category: o.category,
            polygon: o.segmentation,
        });
    }
    Ok(LabelFrame {
        stem,
        image_name: json.info.name,
        width: w,
        height: h,
        objects,
    })
}

/// A scene's evaluation frames.
#[derive(Debug, Clone, PartialEq)]
pub struct LabelScene {
    /// The scene name (the label directory's name).
    pub name: String,
    /// The frames, in file-name order.
    pub frames: Vec<LabelFrame>,
}

/// Reads every `*.json` of a directory (a LangSplat `label/<scene>/` folder or synth's
/// `gt/label/`), in file-name order. An empty directory is an error.
pub fn read_label_dir(dir: impl AsRef<Path>) -> Result<LabelScene> {
    let dir = dir.as_ref();
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io_err(dir, "cannot list label directory"))?
        .map(|e| e.map(|e| e.path()))
        .collect::<std::io::Result<_>>()
        .map_err(io_err(dir, "cannot list label directory"))?;
    files.retain(|p| p.extension().is_some_and(|e| e == "json") && p.is_file());
    files.sort();
    if files.is_empty() {
        return Err(invalid(
            dir.display(),
            "*.json",
            "no label files, expected one LangSplat label JSON per evaluation frame",
        ));
    }
    let frames = files.iter().map(read_label_file).collect::<Result<_>>()?;
    let name = dir
        .canonicalize()
        .ok()
        .and_then(|d| d.file_name().map(|n| n.to_string_lossy().into_owned()))
        .unwrap_or_else(|| dir.display().to_string());
    Ok(LabelScene { name, frames })
}

/// The ground-truth mask of every category of a frame (each polygon rasterised with the
/// reference rule, [`rasterize_polygon`]; same-category objects unioned), sorted by
/// category.
pub fn category_masks(frame: &LabelFrame) -> BTreeMap<String, Mask> {
    let mut out: BTreeMap<String, Mask> = BTreeMap::new();
    for o in &frame.objects {
        let m = rasterize_polygon(&o.polygon, frame.width, frame.height);
        match out.get_mut(&o.category) {
            Some(acc) => acc.union_with(&m),
            None => {
                out.insert(o.category.clone(), m);
            }
        }
    }
    out
}

/// The file name (without `.png`) of a query's mask: the query text with `/`, `\` and
/// control characters (NUL included) replaced by `_` (and `_` prefixed to an empty, `.` or `..` result). Writers of
/// prediction folders (the `query` tool) use the same function.
pub fn query_file_name(query: &str) -> String {
    let name = profuse_formats::label_space::prompt_file_stem(query);
    if matches!(name.as_str(), "" | "." | "..") {
        format!("_{name}")
    } else {
        name
    }
}

/// The path of a predicted mask in the prediction-directory convention:
/// `pred_dir/<frame_stem>/<query_file_name(query)>.png`.
pub fn prediction_path(pred_dir: &Path, frame_stem: &str, query: &str) -> PathBuf {
    pred_dir
        .join(frame_stem)
        .join(format!("{}.png", query_file_name(query)))
}

/// Produces the predicted mask of a (frame, query) pair; `Ok(None)` = no prediction
/// (scored as an empty mask). Implemented by [`PredDir`] and by every closure
/// `Fn(&LabelFrame, &str) -> Result<Option<Mask>>`.
pub trait MaskSource: Sync {
    /// The prediction for `query` in `frame`, of size `frame.width × frame.height`.
    fn predicted(&self, frame: &LabelFrame, query: &str) -> Result<Option<Mask>>;
}

impl<F> MaskSource for F
where
    F: Fn(&LabelFrame, &str) -> Result<Option<Mask>> + Sync,
{
    fn predicted(&self, frame: &LabelFrame, query: &str) -> Result<Option<Mask>> {
        self(frame, query)
    }
}

/// Predicted masks stored as PNGs under a directory (see [`prediction_path`]).
#[derive(Debug, Clone)]
pub struct PredDir {
    /// The prediction directory.
    pub dir: PathBuf,
}

impl MaskSource for PredDir {
    fn predicted(&self, frame: &LabelFrame, query: &str) -> Result<Option<Mask>> {
        let path = prediction_path(&self.dir, &frame.stem, query);
        if !path.is_file() {
            return Ok(None);
        }
        read_mask_png(&path, frame.width, frame.height).map(Some)
    }
}

/// The score of one (frame, query) pair.
#[derive(Debug, Clone, Serialize)]
pub struct PairScore {
    /// Frame stem.
    pub frame: String,
    /// Query (= category).
    pub query: String,
    /// IoU as a fraction in [0, 1].
    pub iou: f64,
    /// Ground-truth pixels.
    pub gt_pixels: u64,
    /// Predicted pixels.
    pub pred_pixels: u64,
    /// Pixels in both.
    pub intersection: u64,
    /// Whether the prediction was missing (scored as empty).
    pub missing: bool,
}

/// Per-query summary within a scene.
#[derive(Debug, Clone, Serialize)]
pub struct QueryRow {
    /// The query.
    pub query: String,
    /// Frames in which it was evaluated.
    pub pairs: usize,
    /// Mean IoU over those frames, percent.
    pub miou: f64,
    /// Share of those frames with IoU > 0.25, percent.
    pub acc25: f64,
}

/// Scores of one scene.
#[derive(Debug, Clone, Serialize)]
pub struct SceneScores {
    /// Scene name.
    pub name: String,
    /// Mean IoU over the pairs, percent (NaN / `null` without pairs).
    pub miou: f64,
    /// Share of pairs with IoU > 0.25, percent.
    pub acc25: f64,
    /// Frames read.
    pub frames: usize,
    /// (frame, query) pairs scored.
    pub pairs: usize,
    /// Pairs without a prediction (scored IoU 0).
    pub missing: usize,
    /// Ground-truth categories skipped because their polygons cover no pixel.
    pub empty_gt: usize,
    /// Per query, sorted by query.
    pub per_query: Vec<QueryRow>,
    /// Every pair, by frame then query.
    pub rows: Vec<PairScore>,
}

fn iou(intersection: u64, a: u64, b: u64) -> f64 {
    let union = a + b - intersection;
    if union == 0 {
        0.0
    } else {
        intersection as f64 / union as f64
    }
}

/// (mIoU, Acc@0.25) in percent of a list of IoUs; NaN for an empty list.
fn aggregate(ious: impl Iterator<Item = f64> + Clone) -> (f64, f64) {
    let n = ious.clone().count();
    if n == 0 {
        return (f64::NAN, f64::NAN);
    }
    let sum: f64 = ious.clone().sum();
    let hits = ious.filter(|&v| v > ACC_IOU).count();
    (100.0 * sum / n as f64, 100.0 * hits as f64 / n as f64)
}

fn score_frame(
    frame: &LabelFrame,
    source: &impl MaskSource,
    queries: Option<&[String]>,
) -> Result<(Vec<PairScore>, usize)> {
    let mut rows = Vec::new();
    let mut empty = 0;
    for (query, gt) in category_masks(frame) {
        if queries.is_some_and(|q| !q.contains(&query)) {
            continue;
        }
        let gt_pixels = gt.count();
        if gt_pixels == 0 {
            empty += 1;
            continue;
        }
        let pred = source.predicted(frame, &query)?;
        if let Some(p) = &pred {
            if (p.width, p.height) != (frame.width, frame.height)
                || p.pixels.len() != gt.pixels.len()
            {
                return Err(MetricsError::MaskSize {
                    path: format!("prediction for {}/{query}", frame.stem),
                    width: frame.width,
                    height: frame.height,
                    found_width: p.width,
                    found_height: p.height,
                });
            }
        }
        let (pred_pixels, intersection) = pred
            .as_ref()
            .map_or((0, 0), |p| (p.count(), p.intersection(&gt)));
        rows.push(PairScore {
            frame: frame.stem.clone(),
            iou: iou(intersection, gt_pixels, pred_pixels),
            query,
            gt_pixels,
            pred_pixels,
            intersection,
            missing: pred.is_none(),
        });
    }
    Ok((rows, empty))
}

/// Scores a scene: every (frame, category) pair (restricted to `queries` when given)
/// against the masks of `source`. Frames are processed in parallel; the result does not
/// depend on the thread count.
pub fn evaluate_scene(
    scene: &LabelScene,
    source: &impl MaskSource,
    queries: Option<&[String]>,
) -> Result<SceneScores> {
    let per_frame: Vec<(Vec<PairScore>, usize)> = scene
        .frames
        .par_iter()
        .map(|f| score_frame(f, source, queries))
        .collect::<Result<_>>()?;
    let empty_gt = per_frame.iter().map(|(_, e)| e).sum();
    let rows: Vec<PairScore> = per_frame.into_iter().flat_map(|(r, _)| r).collect();
    let mut by_query: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
    for r in &rows {
        by_query.entry(&r.query).or_default().push(r.iou);
    }
    let per_query = by_query
        .into_iter()
        .map(|(q, v)| {
            let (miou, acc25) = aggregate(v.iter().copied());
            QueryRow {
                query: q.to_string(),
                pairs: v.len(),
                miou,
                acc25,
            }
        })
        .collect();
    let (miou, acc25) = aggregate(rows.iter().map(|r| r.iou));
    Ok(SceneScores {
        name: scene.name.clone(),
        miou,
        acc25,
        frames: scene.frames.len(),
        pairs: rows.len(),
        missing: rows.iter().filter(|r| r.missing).count(),
        empty_gt,
        per_query,
        rows,
    })
}

/// The final LERF-OVS scores: means of the scenes' scores.
#[derive(Debug, Clone, Serialize)]
pub struct LerfMean {
    /// Mean over scenes of the scene mIoU, percent.
    pub miou: f64,
    /// Mean over scenes of the scene Acc@0.25, percent.
    pub acc25: f64,
    /// Scenes averaged (those with at least one pair).
    pub scenes: usize,
}

/// Averages scene scores (scenes without pairs are skipped; NaN when none is left).
pub fn mean_over_scenes(scenes: &[SceneScores]) -> LerfMean {
    let used: Vec<&SceneScores> = scenes.iter().filter(|s| s.pairs > 0).collect();
    let avg = |f: fn(&SceneScores) -> f64| {
        if used.is_empty() {
            f64::NAN
        } else {
            used.iter().map(|s| f(s)).sum::<f64>() / used.len() as f64
        }
    };
    LerfMean {
        miou: avg(|s| s.miou),
        acc25: avg(|s| s.acc25),
        scenes: used.len(),
    }
}

/// One threshold of a grid search.
#[derive(Debug, Clone, Serialize)]
pub struct GridRow {
    /// The selection threshold τ.
    pub threshold: f64,
    /// Mean over scenes, percent.
    pub miou: f64,
    /// Mean over scenes, percent.
    pub acc25: f64,
    /// Pairs without a prediction, over all scenes.
    pub missing: usize,
    /// Per scene (name, mIoU, Acc@0.25).
    pub scenes: Vec<(String, f64, f64)>,
}

/// All rows of a grid search and the best one.
#[derive(Debug, Clone, Serialize)]
pub struct GridSearch {
    /// The best row (highest mIoU; ties: higher Acc@0.25, then the earlier threshold).
    pub best: GridRow,
    /// Every threshold, in grid order.
    pub rows: Vec<GridRow>,
}

struct AtThreshold<'a, F> {
    masks: &'a F,
    threshold: f64,
    scene: usize,
}

impl<F> MaskSource for AtThreshold<'_, F>
where
    F: Fn(f64, usize, &LabelFrame, &str) -> Result<Option<Mask>> + Sync,
{
    fn predicted(&self, frame: &LabelFrame, query: &str) -> Result<Option<Mask>> {
        (self.masks)(self.threshold, self.scene, frame, query)
    }
}

/// Evaluates every threshold of `grid` over all `scenes`: `masks(threshold, scene_index,
/// frame, query)` produces the prediction (e.g. by selecting Gaussians with score ≥ τ and
/// rendering their activation). Errors on an empty grid or a non-finite threshold.
pub fn grid_search<F>(
    scenes: &[LabelScene],
    grid: &[f64],
    queries: Option<&[String]>,
    masks: F,
) -> Result<GridSearch>
where
    F: Fn(f64, usize, &LabelFrame, &str) -> Result<Option<Mask>> + Sync,
{
    if let Some(bad) = grid.iter().find(|t| !t.is_finite()) {
        return Err(invalid(
            "<grid>",
            "threshold",
            format!("{bad}, expected finite"),
        ));
    }
    let mut rows = Vec::with_capacity(grid.len());
    for &threshold in grid {
        let scored = scenes
            .iter()
            .enumerate()
            .map(|(scene, s)| {
                let source = AtThreshold {
                    masks: &masks,
                    threshold,
                    scene,
                };
                evaluate_scene(s, &source, queries)
            })
            .collect::<Result<Vec<_>>>()?;
        let mean = mean_over_scenes(&scored);
        rows.push(GridRow {
            threshold,
            miou: mean.miou,
            acc25: mean.acc25,
            missing: scored.iter().map(|s| s.missing).sum(),
            scenes: scored
                .iter()
                .map(|s| (s.name.clone(), s.miou, s.acc25))
                .collect(),
        });
    }
    let better = |a: &GridRow, b: &GridRow| {
        // NaN (no pairs) ranks below every number.
        let key = |r: &GridRow| {
            (
                if r.miou.is_nan() {
                    f64::NEG_INFINITY
                } else {
                    r.miou
                },
                if r.acc25.is_nan() {
                    f64::NEG_INFINITY
                } else {
                    r.acc25
                },
            )
        };
        key(a) > key(b)
    };
    let best = rows
        .iter()
        .fold(None::<&GridRow>, |best, r| match best {
            Some(b) if !better(r, b) => Some(b),
            _ => Some(r),
        })
        .cloned()
        .ok_or_else(|| invalid("<grid>", "thresholds", "empty grid, expected at least one"))?;
    Ok(GridSearch { best, rows })
}

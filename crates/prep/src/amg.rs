//! SAM's automatic mask generator on one view, and the flattening of its overlapping masks
//! into the non-overlapping label map of the masks file.
//!
//! The steps are those of SAM's `SamAutomaticMaskGenerator` without crops (`crop_n_layers
//! = 0`): a regular point grid; one decoder call per point; keep a mask when its predicted
//! IoU is `> pred_iou_thresh` and its stability score (IoU of the masks thresholded at
//! `mask_threshold ± stability_offset`) is `>= stability_thresh`; binarise at
//! `mask_threshold`; box NMS by predicted IoU; small-region post-processing (fill holes and
//! drop islands under `min_region_area`, then a second NMS that prefers unchanged masks).
//! The decoder export returns one (its best) mask per prompt, where SAM's own generator
//! asks for three; that is the one difference.

use serde::Serialize;

use crate::error::Result;
use crate::rle::{connected_components, Rle};
use crate::sam::{Embedding, Prompt, Sam};

/// Parameters of the automatic mask generator (defaults: SAM's, with a small-region area).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct AmgParams {
    /// Points per side of the prompt grid (SAM: 32, i.e. 1024 decoder calls per view).
    pub points_per_side: usize,
    /// Keep masks whose predicted IoU is above this (SAM: 0.88).
    pub pred_iou_thresh: f32,
    /// Keep masks whose stability score is at least this (SAM: 0.95).
    pub stability_thresh: f32,
    /// Logit offset of the stability score (SAM: 1.0).
    pub stability_offset: f32,
    /// Logit threshold of a mask pixel (SAM: 0.0).
    pub mask_threshold: f32,
    /// Box IoU above which the lower-scored mask is suppressed (SAM: 0.7).
    pub box_nms_thresh: f32,
    /// Holes and islands smaller than this many mask-grid pixels are removed (SAM's
    /// `min_mask_region_area`; SAM's default 0 turns it off, ours is 100).
    pub min_region_area: usize,
    /// Extra box prompts (not in SAM's generator): for each fraction s here, every grid
    /// point also prompts with a square box of side s times the image's shorter side
    /// centred on it (clipped to the image). Empty by default.
    pub box_scales: [f32; MAX_BOX_SCALES],
}

/// The box scales of [`AmgParams`] from a list: at most [`MAX_BOX_SCALES`], each > 0.
pub fn box_scales(list: &[f32]) -> Result<[f32; MAX_BOX_SCALES]> {
    if list.len() > MAX_BOX_SCALES || list.iter().any(|s| !(*s > 0.0 && s.is_finite())) {
        return Err(crate::error::input(
            "box scales",
            format!("{list:?}: at most {MAX_BOX_SCALES} fractions, each finite and > 0"),
        ));
    }
    let mut out = [0.0; MAX_BOX_SCALES];
    out[..list.len()].copy_from_slice(list);
    Ok(out)
}

/// Most box scales ([`AmgParams::box_scales`]; unused entries are 0).
pub const MAX_BOX_SCALES: usize = 4;

impl Default for AmgParams {
    fn default() -> Self {
        AmgParams {
            points_per_side: 32,
            pred_iou_thresh: 0.88,
            stability_thresh: 0.95,
            stability_offset: 1.0,
            mask_threshold: 0.0,
            box_nms_thresh: 0.7,
            min_region_area: 100,
            box_scales: [0.0; MAX_BOX_SCALES],
        }
    }
}

/// One mask of the generator.
#[derive(Debug, Clone, PartialEq)]
pub struct SamMask {
    /// The binary mask on the mask grid, run-length encoded.
    pub mask: Rle,
    /// Decoder's predicted IoU.
    pub pred_iou: f32,
    /// Stability score.
    pub stability: f32,
    /// Bounding box (x0, y0, x1, y1), inclusive pixel indices.
    pub bbox: [usize; 4],
    /// Pixel count.
    pub area: usize,
    /// Index of the prompt (grid point first, then box prompts) that gave it.
    pub point: usize,
}

/// Counts of each filtering step of one view.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct AmgCounts {
    /// Prompts decoded.
    pub prompts: usize,
    /// Kept after the predicted-IoU filter.
    pub after_iou: usize,
    /// Kept after the stability filter (and non-empty).
    pub after_stability: usize,
    /// Kept after the first box NMS.
    pub after_nms: usize,
    /// Kept after small-region removal and the second NMS.
    pub after_regions: usize,
}

/// SAM's point grid in image pixels: `n x n` points at `(i + 0.5) / n` of width and
/// height, row by row.
pub fn point_grid(n: usize, width: usize, height: usize) -> Vec<(f64, f64)> {
    let mut pts = Vec::with_capacity(n * n);
    for j in 0..n {
        for i in 0..n {
            let fx = (i as f64 + 0.5) / n as f64;
            let fy = (j as f64 + 0.5) / n as f64;
            pts.push((fx * width as f64, fy * height as f64));
        }
    }
    pts
}

/// The prompts of a view: the grid points, then for each box scale the grid points with
/// their boxes.
pub fn prompts(p: &AmgParams, width: usize, height: usize) -> Vec<Prompt> {
    let grid = point_grid(p.points_per_side, width, height);
    let mut out: Vec<Prompt> = grid.iter().map(|&pt| pt.into()).collect();
    let short = width.min(height) as f64;
    for &s in p.box_scales.iter().filter(|s| **s > 0.0) {
        let half = f64::from(s) * short / 2.0;
        out.extend(grid.iter().map(|&(x, y)| Prompt {
            point: (x, y),
            bbox: Some([
                (x - half).max(0.0),
                (y - half).max(0.0),
                (x + half).min(width as f64),
                (y + half).min(height as f64),
            ]),
        }));
    }
    out
}

/// Stability score of mask logits: |l > t + o| / |l > t − o| (0 for an empty union).
pub fn stability_score(logits: &[f32], threshold: f32, offset: f32) -> f32 {
    let (hi, lo) = (threshold + offset, threshold - offset);
    let mut inter = 0u64;
    let mut union = 0u64;
    for &l in logits {
        inter += u64::from(l > hi);
        union += u64::from(l > lo);
    }
    if union == 0 {
        0.0
    } else {
        inter as f32 / union as f32
    }
}

/// IoU of two inclusive boxes with torchvision's area convention ((x1 − x0)(y1 − y0)),
/// as SAM's NMS computes it on its inclusive mask boxes.
pub fn box_iou(a: &[usize; 4], b: &[usize; 4]) -> f64 {
    let area = |r: &[usize; 4]| ((r[2] - r[0]) * (r[3] - r[1])) as f64;
    let ix0 = a[0].max(b[0]);
    let iy0 = a[1].max(b[1]);
    let ix1 = a[2].min(b[2]);
    let iy1 = a[3].min(b[3]);
    let inter = if ix1 > ix0 && iy1 > iy0 {
        ((ix1 - ix0) * (iy1 - iy0)) as f64
    } else {
        0.0
    };
    let union = area(a) + area(b) - inter;
    if union > 0.0 {
        inter / union
    } else {
        0.0
    }
}

/// Greedy NMS: indices kept, highest score first (ties: lower index first); a box is
/// suppressed when its IoU with a kept box is above `thresh`.
pub fn nms(boxes: &[[usize; 4]], scores: &[f32], thresh: f32) -> Vec<usize> {
    let mut order: Vec<usize> = (0..boxes.len()).collect();
    order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]).then(a.cmp(&b)));
    let mut kept: Vec<usize> = Vec::new();
    for i in order {
        if kept
            .iter()
            .all(|&k| box_iou(&boxes[i], &boxes[k]) <= f64::from(thresh))
        {
            kept.push(i);
        }
    }
    kept
}

/// Runs the generator on one view's embedding at mask grid `grid` = (height, width).
pub fn generate(
    sam: &mut Sam,
    emb: &Embedding,
    grid: (usize, usize),
    p: &AmgParams,
) -> Result<(Vec<SamMask>, AmgCounts)> {
    let points = prompts(p, emb.image_width, emb.image_height);
    let (h, w) = grid;
    let keep = |i: usize, logits: &[f32], iou: f32| -> Option<(bool, Option<SamMask>)> {
        if iou <= p.pred_iou_thresh {
            return Some((false, None));
        }
        let stability = stability_score(logits, p.mask_threshold, p.stability_offset);
        if stability < p.stability_thresh {
            return Some((true, None));
        }
        let bits: Vec<bool> = logits.iter().map(|l| *l > p.mask_threshold).collect();
        let mask = Rle::encode(&bits);
        let bbox = mask.bbox(w)?;
        Some((
            true,
            Some(SamMask {
                area: mask.area(),
                mask,
                pred_iou: iou,
                stability,
                bbox,
                point: i,
            }),
        ))
    };
    let decoded = sam.decode_points(emb, &points, grid, &keep)?;
    let mut counts = AmgCounts {
        prompts: points.len(),
        ..AmgCounts::default()
    };
    let mut cands = Vec::new();
    for (passed_iou, m) in decoded.into_iter().flatten() {
        counts.after_iou += usize::from(passed_iou);
        cands.extend(m);
    }
    counts.after_stability = cands.len();
    let boxes: Vec<[usize; 4]> = cands.iter().map(|m| m.bbox).collect();
    let scores: Vec<f32> = cands.iter().map(|m| m.pred_iou).collect();
    let mut cands = take(cands, nms(&boxes, &scores, p.box_nms_thresh));
    counts.after_nms = cands.len();
    if p.min_region_area > 0 {
        cands = remove_small_regions_all(cands, (h, w), p);
    }
    counts.after_regions = cands.len();
    Ok((cands, counts))
}

/// The candidates at `idx`, in that order.
fn take(cands: Vec<SamMask>, idx: Vec<usize>) -> Vec<SamMask> {
    let mut slots: Vec<Option<SamMask>> = cands.into_iter().map(Some).collect();
    idx.into_iter().filter_map(|i| slots[i].take()).collect()
}

/// SAM's `postprocess_small_regions`: per mask fill small holes then drop small islands;
/// then NMS with score 1 for unchanged and 0 for changed masks (ties by the order of the
/// first NMS), so that an unchanged mask wins over a cleaned duplicate.
fn remove_small_regions_all(
    cands: Vec<SamMask>,
    grid: (usize, usize),
    p: &AmgParams,
) -> Vec<SamMask> {
    let (h, w) = grid;
    let mut cleaned = Vec::with_capacity(cands.len());
    let mut scores = Vec::with_capacity(cands.len());
    for m in cands {
        let bits = m.mask.decode(h * w);
        let (bits, holes_changed) = remove_small_regions(&bits, (h, w), p.min_region_area, true);
        let (bits, islands_changed) = remove_small_regions(&bits, (h, w), p.min_region_area, false);
        let changed = holes_changed || islands_changed;
        scores.push(if changed { 0.0 } else { 1.0 });
        let mask = Rle::encode(&bits);
        let Some(bbox) = mask.bbox(w) else {
            scores.pop();
            continue;
        };
        cleaned.push(SamMask {
            area: mask.area(),
            mask,
            bbox,
            ..m
        });
    }
    let boxes: Vec<[usize; 4]> = cleaned.iter().map(|m| m.bbox).collect();
    let keep = nms(&boxes, &scores, p.box_nms_thresh);
    take(cleaned, keep)
}

/// SAM's `remove_small_regions` (8-connected components): with `holes`, components of
/// the background smaller than `area` become mask; else components of the mask smaller
/// than `area` are removed, keeping the largest one if all are small. Returns the new
/// mask and whether it changed.
pub fn remove_small_regions(
    bits: &[bool],
    grid: (usize, usize),
    area: usize,
    holes: bool,
) -> (Vec<bool>, bool) {
    let working: Vec<bool> = bits.iter().map(|b| *b != holes).collect();
    let (labels, sizes) = connected_components(&working, grid);
    let small: Vec<bool> = sizes.iter().map(|s| *s < area).collect();
    if !small.iter().any(|s| *s) {
        return (bits.to_vec(), false);
    }
    let out: Vec<bool> = if holes {
        // Mask pixels stay; small background components are filled.
        labels
            .iter()
            .map(|l| *l == 0 || small[(*l - 1) as usize])
            .collect()
    } else {
        let mut keep: Vec<bool> = small.iter().map(|s| !*s).collect();
        if !keep.iter().any(|k| *k) {
            if let Some((i, _)) = sizes
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(&a.0)))
            {
                keep[i] = true;
            }
        }
        labels
            .iter()
            .map(|l| *l > 0 && keep[(*l - 1) as usize])
            .collect()
    };
    (out, true)
}

/// Flattens overlapping masks into one label map: masks are painted in order of
/// decreasing area (ties: higher predicted IoU, then grid order), so a smaller mask lies
/// on top of any larger one that contains it ("later mask wins"); masks left with no
/// visible pixel are dropped. Returns the label map (view-local index per pixel,
/// `u16::MAX` = none) and the kept masks in label order.
pub fn label_map(masks: Vec<SamMask>, grid: (usize, usize)) -> (Vec<u16>, Vec<SamMask>) {
    let (h, w) = grid;
    let mut order = masks;
    order.sort_by(|a, b| {
        b.area
            .cmp(&a.area)
            .then(b.pred_iou.total_cmp(&a.pred_iou))
            .then(a.point.cmp(&b.point))
    });
    let mut owner = vec![u32::MAX; h * w];
    for (k, m) in order.iter().enumerate() {
        m.mask.for_each_set(|i| owner[i] = k as u32);
    }
    let mut visible = vec![0usize; order.len()];
    for o in owner.iter().filter(|o| **o != u32::MAX) {
        visible[*o as usize] += 1;
    }
    let mut new_index = vec![u16::MAX; order.len()];
    let mut kept = Vec::new();
    for (k, m) in order.into_iter().enumerate() {
        if visible[k] > 0 && kept.len() < usize::from(u16::MAX) {
            new_index[k] = kept.len() as u16;
            kept.push(m);
        }
    }
    let labels = owner
        .iter()
        .map(|o| {
            if *o == u32::MAX {
                u16::MAX
            } else {
                new_index[*o as usize]
            }
        })
        .collect();
    (labels, kept)
}

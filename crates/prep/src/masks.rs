//! `prep masks`: the automatic mask generator over the views of a cameras file, streamed
//! view by view, written as one masks file whose features are the SAM-embedding mask
//! descriptors (the masks kind requires a feature row per mask and the embedding is at
//! hand; `prep features --clip-image` replaces them).

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

use profuse_formats::{Cameras, FileKind, Floats, Labels, Masks};
use serde::Serialize;

use crate::amg::{generate, label_map, AmgCounts, AmgParams};
use crate::error::{input, Result};
use crate::image::RgbImage;
use crate::pool::pool_embedding;
use crate::sam::{secs, Sam, EMBED_DIM};

/// Mask grid (height, width) of an image for a longest side of `mask_size`: the image
/// scaled so that its longest side is `mask_size` (`floor(x + 0.5)`), never upscaled.
pub fn mask_grid(width: usize, height: usize, mask_size: usize) -> (usize, usize) {
    let longest = width.max(height);
    let target = mask_size.min(longest).max(1);
    let side =
        |s: usize| ((s as f64 * target as f64 / longest as f64 + 0.5).floor() as usize).max(1);
    (side(height), side(width))
}

/// One view's figures.
#[derive(Debug, Clone, Serialize)]
pub struct ViewReport {
    /// View index in the cameras file.
    pub view: usize,
    /// Masks in its label map.
    pub masks: usize,
    /// Fraction of label-map pixels that belong to a mask.
    pub coverage: f64,
    /// Seconds: image decode, encoder, decoder calls (with filtering), the rest.
    pub load_s: f64,
    /// Encoder seconds.
    pub encoder_s: f64,
    /// Decoder and filtering seconds.
    pub decoder_s: f64,
    /// Counts of the filtering steps.
    pub counts: AmgCounts,
}

/// The report of a run (printed as JSON by the tool).
#[derive(Debug, Clone, Serialize)]
pub struct MasksReport {
    /// Views in the file.
    pub views: usize,
    /// Views that were segmented.
    pub segmented_views: usize,
    /// Total masks.
    pub masks: usize,
    /// Masks of each segmented view, in view order.
    pub masks_per_view: Vec<usize>,
    /// Label-map grid [height, width].
    pub grid: [usize; 2],
    /// Generator parameters.
    pub params: AmgParams,
    /// Decoder worker sessions.
    pub workers: usize,
    /// Wall seconds of the whole run.
    pub seconds: f64,
    /// Mean seconds per segmented view.
    pub seconds_per_view: f64,
    /// Total encoder seconds.
    pub encoder_s: f64,
    /// Total decoder (and filtering) seconds.
    pub decoder_s: f64,
    /// Per view.
    pub per_view: Vec<ViewReport>,
}

/// What to segment.
#[derive(Debug, Clone)]
pub struct MasksJob<'a> {
    /// The cameras file's content (image names and sizes).
    pub cameras: &'a Cameras,
    /// Directory the cameras' image names are relative to.
    pub images: &'a Path,
    /// Generator parameters.
    pub params: AmgParams,
    /// Longest side of the label-map grid (the decoder's output size).
    pub mask_size: usize,
    /// Views to segment (`None`: all); the others get an empty label map (no masks), so
    /// that held-out views keep their index.
    pub views: Option<Vec<usize>>,
}

/// Runs the generator on every selected view and returns the masks file content. The
/// label maps accumulate (V x H x W x 2 bytes); images and embeddings are held for one view
/// at a time. `progress(done, total)` is called after each view.
pub fn run_masks(
    sam: &mut Sam,
    job: &MasksJob<'_>,
    progress: &dyn Fn(usize, usize),
) -> Result<(Masks, MasksReport)> {
    let start = Instant::now();
    let cams = job.cameras;
    let v_all = cams.len();
    let selected = selected_views(job.views.as_deref(), v_all)?;
    if v_all == 0 {
        return Err(input("cameras", "has no views"));
    }
    let size0 = cams.image_size[0];
    let grid = mask_grid(size0[0] as usize, size0[1] as usize, job.mask_size);
    let plane = grid.0 * grid.1;
    let mut labels: Vec<u16> = Vec::with_capacity(v_all * plane);
    let mut offsets = vec![0u32];
    let mut features: Vec<f32> = Vec::new();
    let mut per_view = Vec::new();
    for v in 0..v_all {
        if !selected[v] {
            labels.extend(std::iter::repeat_n(u16::MAX, plane));
            offsets.push(offsets[v]);
            continue;
        }
        let t = Instant::now();
        let img = load_view(job, v)?;
        let load_s = secs(t);
        let view_grid = mask_grid(img.width, img.height, job.mask_size);
        if view_grid != grid {
            return Err(input(
                format!("view {v} ({})", cams.image_names[v]),
                format!(
                    "is {}x{}, whose mask grid {}x{} differs from view 0's {}x{}; all views \
                     must share one aspect ratio",
                    img.width, img.height, view_grid.1, view_grid.0, grid.1, grid.0
                ),
            ));
        }
        let (view_labels, feats, report) = segment_view(sam, &img, grid, &job.params, v)?;
        let count = feats.len() / EMBED_DIM;
        labels.extend_from_slice(&view_labels);
        features.extend_from_slice(&feats);
        offsets.push(offsets[v] + count as u32);
        per_view.push(ViewReport { load_s, ..report });
        progress(per_view.len(), selected.iter().filter(|s| **s).count());
    }
    let masks = Masks {
        view_names: cams.image_names.clone(),
        width: grid.1,
        height: grid.0,
        labels: Labels::U16(labels.into()),
        mask_offsets: offsets.into(),
        features: Floats::F32(features.into()),
        dim: EMBED_DIM,
        extra: metadata(&job.params),
    };
    masks.validate("<prep masks>")?;
    let seconds = secs(start);
    let n = per_view.len().max(1) as f64;
    let report = MasksReport {
        views: v_all,
        segmented_views: per_view.len(),
        masks: masks.num_masks(),
        masks_per_view: per_view.iter().map(|r| r.masks).collect(),
        grid: [grid.0, grid.1],
        params: job.params,
        workers: sam.workers(),
        seconds,
        seconds_per_view: per_view
            .iter()
            .map(|r| r.load_s + r.encoder_s + r.decoder_s)
            .sum::<f64>()
            / n,
        encoder_s: per_view.iter().map(|r| r.encoder_s).sum(),
        decoder_s: per_view.iter().map(|r| r.decoder_s).sum(),
        per_view,
    };
    Ok((masks, report))
}

/// Segments one decoded image: label map, SAM-embedding features [masks, 256], figures.
pub fn segment_view(
    sam: &mut Sam,
    img: &RgbImage,
    grid: (usize, usize),
    params: &AmgParams,
    view: usize,
) -> Result<(Vec<u16>, Vec<f32>, ViewReport)> {
    let t = Instant::now();
    let emb = sam.encode(img)?;
    let encoder_s = secs(t);
    let t = Instant::now();
    let (found, counts) = generate(sam, &emb, grid, params)?;
    let (labels, kept) = label_map(found, grid);
    let feats = pool_embedding(&emb, &labels, grid, kept.len());
    let decoder_s = secs(t);
    let covered = labels.iter().filter(|l| **l != u16::MAX).count();
    Ok((
        labels,
        feats,
        ViewReport {
            view,
            masks: kept.len(),
            coverage: covered as f64 / (grid.0 * grid.1) as f64,
            load_s: 0.0,
            encoder_s,
            decoder_s,
            counts,
        },
    ))
}

/// Reads view `v`'s image (relative to the job's image directory).
pub fn load_view(job: &MasksJob<'_>, v: usize) -> Result<RgbImage> {
    crate::image::load_view_image(job.images, job.cameras, v)
}

/// Which views are selected, checked against the view count.
pub fn selected_views(views: Option<&[usize]>, count: usize) -> Result<Vec<bool>> {
    let Some(views) = views else {
        return Ok(vec![true; count]);
    };
    let mut sel = vec![false; count];
    for &v in views {
        if v >= count {
            return Err(input(
                "--views",
                format!("view {v} does not exist (the cameras file has {count})"),
            ));
        }
        sel[v] = true;
    }
    Ok(sel)
}

/// Metadata recording how the file was made.
fn metadata(params: &AmgParams) -> BTreeMap<String, String> {
    BTreeMap::from([
        (
            "generator".to_string(),
            "prep masks (SAM automatic mask generator)".to_string(),
        ),
        ("feature".to_string(), "sam_embedding".to_string()),
        (
            "amg_params".to_string(),
            serde_json::to_string(params).unwrap_or_default(),
        ),
        (
            "label_rule".to_string(),
            "masks painted by decreasing area, smaller on top; masks left without pixels dropped"
                .to_string(),
        ),
    ])
}

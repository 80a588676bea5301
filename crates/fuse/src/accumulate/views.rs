//! The view loop of registration: each view rendered at the mask grid with its tiles
//! summed as they come (step 1), and merged into W (steps 2 and 3) while the next view
//! renders.

use std::ops::Range;
use std::time::Instant;

use profuse_formats::{Labels, Masks};
use splat_raster::{ListScratch, Rasterizer, RenderOptions, RenderStats};

use super::{Accumulator, HitCounts, LabelPlane, TileHits, ViewContext, ViewRows};
use crate::error::{FuseError, Result};
use crate::{check_groups, grid_camera, Groups, PartialSums, Scene, Timings, ViewReport};

/// Completes a view's report with the accumulator's state after it was merged, and adds
/// its times to `timings`.
fn finish_report(
    mut report: ViewReport,
    acc: &Accumulator,
    rows: &[ViewRows; 2],
    timings: &mut Timings,
) -> ViewReport {
    report.nnz = acc.nnz();
    report.accumulator_bytes = acc.heap_bytes();
    report.view_buffer_bytes =
        acc.scratch_bytes() + rows.iter().map(ViewRows::heap_bytes).sum::<usize>();
    timings.raster_s += report.raster_s;
    timings.accumulate_s += report.accumulate_s;
    report
}

/// Checks the scene, that the groups cover its masks and that `views` is a non-empty range
/// of its views.
fn check_job(scene: &Scene<'_>, groups: &Groups, views: &Range<usize>) -> Result<()> {
    scene.check()?;
    check_groups(scene, groups)?;
    let num_views = scene.cameras.len();
    if views.start >= views.end || views.end > num_views {
        return Err(FuseError::ViewRange {
            start: views.start,
            end: views.end,
            views: num_views,
        });
    }
    Ok(())
}

/// Renders `views` one at a time at the mask grid with top-K `k` and accumulates the mask
/// masses and W into exact partial sums; `progress` is called after every view.
pub fn accumulate(
    scene: &Scene<'_>,
    groups: &Groups,
    k: usize,
    views: Range<usize>,
    progress: &mut dyn FnMut(&ViewReport),
) -> Result<PartialSums> {
    check_job(scene, groups, &views)?;
    let masks = scene.masks;
    let names = &scene.names;
    let render_err = |source| FuseError::Render {
        cameras: names.cameras.clone(),
        source,
    };
    let raster = top_k_rasterizer(scene, k)?;
    let bad_masks = |detail| FuseError::BadMasks {
        masks: names.masks.clone(),
        detail,
    };

    let mut acc = Accumulator::new(scene.gaussians.len(), masks.num_masks(), groups.num_groups);
    let mut scratch = ListScratch::default();
    let mut timings = Timings::default();
    // Two sets of row buffers: view v's tile sums are merged into W (`end_view`) while
    // view v + 1 renders into the other set. W's sums are exact and views are merged in
    // order, so the overlap changes nothing in the result.
    let mut rows = [ViewRows::default(), ViewRows::default()];
    let mut pending: Option<(ViewContext<'_>, ViewReport)> = None;
    for (i, view) in views.clone().enumerate() {
        let labels = view_labels(masks, view);
        let mut report = unrendered_report(view);
        let [a, b] = &mut rows;
        let (current, previous) = if i % 2 == 0 { (a, &*b) } else { (b, &*a) };
        let merge = |acc: &mut Accumulator, pending: Option<(ViewContext<'_>, ViewReport)>| {
            pending
                .map(|(ctx, mut report)| {
                    let t0 = Instant::now();
                    report.counts = acc.end_view(&ctx, previous)?;
                    report.accumulate_s = t0.elapsed().as_secs_f64();
                    Ok::<_, String>(report)
                })
                .transpose()
        };
        if !labels.any_mask() {
            // Nothing to render (a view without masks cannot contribute).
            let merged = merge(&mut acc, pending.take()).map_err(bad_masks)?;
            for r in merged.into_iter().chain([report]) {
                progress(&finish_report(r, &acc, &rows, &mut timings));
            }
            continue;
        }
        let cam = grid_camera(scene.cameras, view, masks.width as u32, masks.height as u32)
            .map_err(render_err)?;
        let ctx = view_context(&acc, masks, groups, labels, k, view).map_err(bad_masks)?;
        let previous_view = pending.take();
        let (merged, rendered) = rayon::join(
            || merge(&mut acc, previous_view),
            || {
                let t0 = Instant::now();
                // Each tile's lists are summed as soon as they are rendered, while in cache.
                let stats = raster.render_tiles(
                    &cam,
                    view,
                    k,
                    &mut scratch,
                    current.begin(),
                    |tile, row| ctx.sum_tile(&TileHits::from(tile), row),
                );
                (stats, t0.elapsed().as_secs_f64())
            },
        );
        let merged = merged.map_err(bad_masks)?;
        let (stats, raster_s) = rendered;
        report.render = stats.map_err(render_err)?;
        report.rendered = true;
        report.raster_s = raster_s;
        if let Some(r) = merged {
            progress(&finish_report(r, &acc, &rows, &mut timings));
        }
        pending = Some((ctx, report));
    }
    if let Some((ctx, mut report)) = pending.take() {
        let t0 = Instant::now();
        // A view still pending was rendered by the last iteration.
        let last = &rows[(views.len() - 1) % 2];
        report.counts = acc.end_view(&ctx, last).map_err(bad_masks)?;
        report.accumulate_s = t0.elapsed().as_secs_f64();
        progress(&finish_report(report, &acc, &rows, &mut timings));
    }
    partial_sums(scene, groups, k, views, acc, timings)
}

/// The rasterizer of the scene's Gaussians, with top-K `k` checked to be a valid render
/// of the lists alone (no colour).
fn top_k_rasterizer<'g>(scene: &Scene<'g>, k: usize) -> Result<Rasterizer<'g>> {
    let names = &scene.names;
    let raster = Rasterizer::new(scene.gaussians).map_err(|source| FuseError::Gaussians {
        gaussians: names.gaussians.clone(),
        source,
    })?;
    let opts = RenderOptions {
        color: false,
        top_k: Some(k),
        ..RenderOptions::default()
    };
    opts.validate().map_err(|source| FuseError::Render {
        cameras: names.cameras.clone(),
        source,
    })?;
    Ok(raster)
}

/// The label map of `view`, in its stored dtype.
fn view_labels(masks: &Masks, view: usize) -> LabelPlane<'_> {
    let plane = masks.width * masks.height;
    match &masks.labels {
        Labels::U16(b) => LabelPlane::U16(&b[view * plane..(view + 1) * plane]),
        Labels::U32(b) => LabelPlane::U32(&b[view * plane..(view + 1) * plane]),
    }
}

/// The report of `view` before it is rendered and merged.
fn unrendered_report(view: usize) -> ViewReport {
    ViewReport {
        view,
        rendered: false,
        raster_s: 0.0,
        accumulate_s: 0.0,
        counts: HitCounts::default(),
        nnz: 0,
        accumulator_bytes: 0,
        view_buffer_bytes: 0,
        render: RenderStats::default(),
    }
}

/// The accumulator's per-view context of `view` (its labels, masks and their groups and
/// pixel-weight factors).
fn view_context<'a>(
    acc: &Accumulator,
    masks: &Masks,
    groups: &'a Groups,
    labels: LabelPlane<'a>,
    k: usize,
    view: usize,
) -> Result<ViewContext<'a>, String> {
    acc.view_context(
        labels,
        masks.width,
        masks.mask_offsets[view],
        &groups.mask_group,
        &groups.pixel_weight,
        masks.masks_in_view(view),
        k,
        view,
    )
}

/// Compacts the accumulator (its time goes into `timings`) into the partial sums of
/// `views`.
fn partial_sums(
    scene: &Scene<'_>,
    groups: &Groups,
    k: usize,
    views: Range<usize>,
    acc: Accumulator,
    mut timings: Timings,
) -> Result<PartialSums> {
    let masks = scene.masks;
    let t0 = Instant::now();
    let counts = acc.counts();
    let (weights, mask_mass) = acc.finish()?;
    timings.compact_s = t0.elapsed().as_secs_f64();
    Ok(PartialSums {
        num_gaussians: scene.gaussians.len(),
        num_views: scene.cameras.len(),
        k,
        views: views.map(|v| v as u32).collect(),
        groups: groups.clone(),
        mask_features: masks.features.clone(),
        dim: masks.dim,
        mask_mass,
        weights,
        counts,
        timings,
    })
}

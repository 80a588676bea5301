//! Binning of projected Gaussians into 16x16 tiles and the per-tile front-to-back blend.

use std::sync::Mutex;

use profuse_formats::{Cameras, Gaussians};
use rayon::prelude::*;

use wide::{f32x4, CmpGe, CmpGt, CmpLe, CmpLt};

use crate::camera::ViewCamera;
use crate::error::{RasterError, Result};
use crate::math::exp4;
use crate::project::{prepare, project, Prepared, Projected, Splat};
use crate::{ALPHA_MAX, ALPHA_MIN, MAX_TOP_K, NO_GAUSSIAN, TILE, T_MIN};

const TILE_PIXELS: usize = TILE * TILE;

/// [`NO_GAUSSIAN`] as the f32 bit pattern the SIMD lists carry ids in.
const NO_ID_BITS: f32x4 = f32x4::new([f32::from_bits(NO_GAUSSIAN); 4]);

/// What to accumulate into the depth output.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DepthMode {
    /// No depth output.
    #[default]
    None,
    /// Σ ω z (INRIA's expected depth, not normalised; background contributes 0).
    Accumulated,
    /// Σ ω z / Σ ω (0 where nothing was hit).
    Normalized,
}

/// Which outputs to produce. Outputs that are off cost neither time nor memory.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderOptions {
    /// RGB colour, f32 [H, W, 3]: Σ ω c + T_final · background.
    pub color: bool,
    /// Depth, f32 [H, W].
    pub depth: DepthMode,
    /// Accumulated alpha 1 − T_final, f32 [H, W].
    pub alpha: bool,
    /// Final transmittance T_final, f32 [H, W].
    pub transmittance: bool,
    /// Per-pixel top-K contributors (ids u32 [H, W, K], weights f32 [H, W, K]); `None` = off.
    /// K must be in 1..=[`MAX_TOP_K`]. When nothing else is requested, a pixel stops as
    /// soon as its list is final (T <= its K-th weight): the same lists, less work.
    pub top_k: Option<usize>,
    /// Background colour added with the final transmittance.
    pub background: [f32; 3],
}

impl Default for RenderOptions {
    /// Colour only, black background.
    fn default() -> Self {
        RenderOptions {
            color: true,
            depth: DepthMode::None,
            alpha: false,
            transmittance: false,
            top_k: None,
            background: [0.0; 3],
        }
    }
}

impl RenderOptions {
    /// Every output, with the given K.
    pub fn all(k: usize) -> Self {
        RenderOptions {
            color: true,
            depth: DepthMode::Accumulated,
            alpha: true,
            transmittance: true,
            top_k: Some(k),
            background: [0.0; 3],
        }
    }

    /// Checks K.
    pub fn validate(&self) -> Result<()> {
        match self.top_k {
            Some(0) => Err(RasterError::TopKZero),
            Some(k) if k > MAX_TOP_K => Err(RasterError::TopKTooLarge { k, max: MAX_TOP_K }),
            _ => Ok(()),
        }
    }
}

/// Counters of one rendered view.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RenderStats {
    /// Gaussians that survived culling (near plane, degenerate covariance, off-screen,
    /// opacity < 1/255).
    pub visible: usize,
    /// (tile, Gaussian) pairs after binning.
    pub tile_pairs: usize,
}

/// The outputs of one view. Buffers are reused when the same `ViewRender` is rendered
/// into again ([`Rasterizer::render_view_into`]), so streaming views costs one allocation.
#[derive(Debug, Default)]
pub struct ViewRender {
    view: usize,
    width: usize,
    height: usize,
    opts: RenderOptions,
    stats: RenderStats,
    color: Vec<f32>,
    depth: Vec<f32>,
    alpha: Vec<f32>,
    transmittance: Vec<f32>,
    ids: Vec<u32>,
    weights: Vec<f32>,
    scratch: ViewScratch,
}

impl ViewRender {
    /// The view index this was rendered from.
    pub fn view(&self) -> usize {
        self.view
    }
    /// Image width.
    pub fn width(&self) -> usize {
        self.width
    }
    /// Image height.
    pub fn height(&self) -> usize {
        self.height
    }
    /// The options it was rendered with.
    pub fn options(&self) -> &RenderOptions {
        &self.opts
    }
    /// Counters.
    pub fn stats(&self) -> RenderStats {
        self.stats
    }
    /// K of the top-K buffers (0 when they are off).
    pub fn k(&self) -> usize {
        self.opts.top_k.unwrap_or(0)
    }
    /// RGB colour, row-major [H, W, 3].
    pub fn color(&self) -> Option<&[f32]> {
        self.opts.color.then_some(&self.color[..])
    }
    /// Depth [H, W] (see [`DepthMode`]).
    pub fn depth(&self) -> Option<&[f32]> {
        (self.opts.depth != DepthMode::None).then_some(&self.depth[..])
    }
    /// Accumulated alpha 1 − T_final, [H, W].
    pub fn alpha(&self) -> Option<&[f32]> {
        self.opts.alpha.then_some(&self.alpha[..])
    }
    /// Final transmittance, [H, W].
    pub fn transmittance(&self) -> Option<&[f32]> {
        self.opts.transmittance.then_some(&self.transmittance[..])
    }
    /// Top-K Gaussian ids [H, W, K]; [`NO_GAUSSIAN`] pads pixels with fewer hits.
    pub fn topk_ids(&self) -> Option<&[u32]> {
        self.opts.top_k.map(|_| &self.ids[..])
    }
    /// Top-K weights ω = T·α [H, W, K], descending per pixel, ties in depth order; 0 pads.
    pub fn topk_weights(&self) -> Option<&[f32]> {
        self.opts.top_k.map(|_| &self.weights[..])
    }
    /// The K ids and weights of pixel (`x`, `y`); `None` if top-K is off or out of bounds.
    pub fn topk(&self, x: usize, y: usize) -> Option<(&[u32], &[f32])> {
        let k = self.opts.top_k?;
        if x >= self.width || y >= self.height {
            return None;
        }
        let i = (y * self.width + x) * k;
        Some((&self.ids[i..i + k], &self.weights[i..i + k]))
    }

    /// The top-K buffers and final transmittance as a `profuse.topk` file (SPEC.md §4.14)
    /// whose ids index `num_gaussians` Gaussians; `None` unless both outputs were rendered.
    /// Copies the buffers.
    pub fn to_topk_file(&self, num_gaussians: usize) -> Option<profuse_formats::TopK> {
        let k = self.opts.top_k?;
        let transmittance = self.transmittance()?;
        Some(profuse_formats::TopK {
            num_gaussians,
            width: self.width,
            height: self.height,
            k,
            ids: self.ids.clone().into(),
            weights: self.weights.clone().into(),
            transmittance: transmittance.to_vec().into(),
            extra: Default::default(),
        })
    }

    fn resize(&mut self, view: usize, cam: &ViewCamera, opts: &RenderOptions) {
        let (w, h) = (cam.width as usize, cam.height as usize);
        let n = w * h;
        self.view = view;
        self.width = w;
        self.height = h;
        self.opts = *opts;
        // Every in-image pixel is written by its tile, so buffers of the right length are
        // reused as they are (no clearing pass).
        let size = |v: &mut Vec<f32>, on: bool, len: usize| {
            let len = if on { len } else { 0 };
            v.truncate(len);
            v.resize(len, 0.0);
        };
        size(&mut self.color, opts.color, n * 3);
        size(&mut self.depth, opts.depth != DepthMode::None, n);
        size(&mut self.alpha, opts.alpha, n);
        size(&mut self.transmittance, opts.transmittance, n);
        let k = opts.top_k.unwrap_or(0);
        size(&mut self.weights, k > 0, n * k);
        self.ids.truncate(n * k);
        self.ids.resize(n * k, NO_GAUSSIAN);
    }
}

/// Gaussians projected per job of [`Rasterizer::bin`] (a power of two: the key packs the
/// position within the chunk into the low bits).
const PROJECT_CHUNK: usize = 1 << CHUNK_BITS;
const CHUNK_BITS: u32 = 14;

/// Sort key of a splat: its camera depth (positive, finite: the bits of a positive f32
/// order as the value) above its position, chunk-major. Chunks cover ascending id ranges,
/// so equal depths order by id, as the (depth, id) rule requires.
fn depth_key(sp: &Splat, chunk: usize, index: usize) -> u64 {
    (u64::from(sp.depth.to_bits()) << 32) | ((chunk as u64) << CHUNK_BITS) | index as u64
}

/// (chunk, index) of a [`depth_key`].
fn key_position(key: u64) -> (usize, usize) {
    let pos = (key & u64::from(u32::MAX)) as usize;
    (pos >> CHUNK_BITS, pos & (PROJECT_CHUNK - 1))
}

/// Per-view binning buffers, reused between views.
#[derive(Debug, Default)]
struct ViewScratch {
    /// Projected splats of each chunk of [`PROJECT_CHUNK`] Gaussians, in id order, with
    /// their [`depth_key`]s (computed by the chunk's job while its splats are in cache).
    chunks: Vec<(Vec<Splat>, Vec<u64>)>,
    /// [`depth_key`]s of the splats of `chunks`, sorted.
    keys: Vec<u64>,
    /// The splats in (depth, id) order.
    splats: Vec<Splat>,
    row_start: Vec<usize>,
    row_entries: Vec<u32>,
    tiles: Mutex<Vec<TileScratch>>,
}

/// The rasterizer of one Gaussian set: holds the view-independent per-Gaussian data
/// (3D covariances, opacities) and renders any number of views.
#[derive(Debug)]
pub struct Rasterizer<'g> {
    gaussians: &'g Gaussians,
    prep: Prepared,
}

impl<'g> Rasterizer<'g> {
    /// Validates the Gaussians (lengths, finite parameters, non-zero quaternions; opacity
    /// logits may be ±inf) and precomputes their 3D covariances and opacities.
    pub fn new(gaussians: &'g Gaussians) -> Result<Self> {
        Ok(Rasterizer {
            gaussians,
            prep: prepare(gaussians)?,
        })
    }

    /// The Gaussians.
    pub fn gaussians(&self) -> &'g Gaussians {
        self.gaussians
    }

    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.gaussians.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.gaussians.is_empty()
    }

    /// Projects Gaussian `index` into `cam`; `None` when culled (behind the near plane
    /// z <= 0.2, degenerate 2D covariance, or its 3-sigma square misses the tile grid).
    pub fn project(&self, cam: &ViewCamera, index: usize) -> Option<Projected> {
        if index >= self.len() {
            return None;
        }
        project(self.gaussians, &self.prep, cam, cam.center(), index)
    }

    /// Renders view `view` of `cameras` into a new [`ViewRender`].
    pub fn render_view(
        &self,
        cameras: &Cameras,
        view: usize,
        opts: &RenderOptions,
    ) -> Result<ViewRender> {
        let mut out = ViewRender::default();
        self.render_view_into(cameras, view, opts, &mut out)?;
        Ok(out)
    }

    /// Renders view `view` of `cameras` into `out`, reusing its buffers.
    pub fn render_view_into(
        &self,
        cameras: &Cameras,
        view: usize,
        opts: &RenderOptions,
        out: &mut ViewRender,
    ) -> Result<()> {
        let cam = ViewCamera::from_cameras(cameras, view)?;
        self.render_camera_into(&cam, view, opts, out)
    }

    /// Renders an explicit camera into `out` (`view` is only recorded in `out`).
    pub fn render_camera_into(
        &self,
        cam: &ViewCamera,
        view: usize,
        opts: &RenderOptions,
        out: &mut ViewRender,
    ) -> Result<()> {
        opts.validate()?;
        cam.check(view)?;
        out.resize(view, cam, opts);
        self.bin(cam, &mut out.scratch);
        let stats = RenderStats {
            visible: out.scratch.splats.len(),
            tile_pairs: 0,
        };
        out.stats = stats;
        let pairs = blend(cam, opts, out);
        out.stats.tile_pairs = pairs;
        Ok(())
    }

    /// Renders `views` one after the other (each in parallel over tiles) and calls `f` with
    /// each; only one view's buffers exist at a time and they are reused. Stops at the
    /// first error, from rendering or from `f`.
    pub fn for_each_view<I, F, E>(
        &self,
        cameras: &Cameras,
        views: I,
        opts: &RenderOptions,
        mut f: F,
    ) -> Result<(), E>
    where
        I: IntoIterator<Item = usize>,
        F: FnMut(usize, &ViewRender) -> Result<(), E>,
        E: From<RasterError>,
    {
        let mut out = ViewRender::default();
        for view in views {
            self.render_view_into(cameras, view, opts, &mut out)?;
            f(view, &out)?;
        }
        Ok(())
    }

    /// Projects every Gaussian, sorts the survivors by (depth, id) and buckets them by
    /// tile row (each row's list stays in depth order).
    ///
    /// Gaussians are projected in fixed chunks into reused per-chunk buffers (no per-view
    /// allocation, and the chunking does not depend on the thread count), the survivors
    /// are ordered by sorting 8-byte keys (depth bits, chunk, index) rather than moving the
    /// 64-byte splats around, and are gathered once into depth order.
    fn bin(&self, cam: &ViewCamera, s: &mut ViewScratch) {
        let campos = cam.center();
        let (w, h) = (cam.width, cam.height);
        let chunks = self.len().div_ceil(PROJECT_CHUNK);
        s.chunks.resize_with(chunks, Default::default);
        s.chunks
            .par_iter_mut()
            .enumerate()
            .for_each(|(c, (out, keys))| {
                out.clear();
                let ids = c * PROJECT_CHUNK..((c + 1) * PROJECT_CHUNK).min(self.len());
                out.extend(ids.filter_map(|i| {
                    project(self.gaussians, &self.prep, cam, campos, i)
                        .and_then(|p| Splat::new(&p, self.prep.tau[i], w, h))
                }));
                keys.clear();
                keys.extend(out.iter().enumerate().map(|(i, sp)| depth_key(sp, c, i)));
            });
        s.keys.clear();
        for (_, keys) in &s.chunks {
            s.keys.extend_from_slice(keys);
        }
        // Unique keys (ids differ), so the unstable sort is deterministic.
        s.keys.par_sort_unstable();
        s.splats.clear();
        let chunks = &s.chunks;
        s.splats.par_extend(s.keys.par_iter().map(|&key| {
            let (c, i) = key_position(key);
            chunks[c].0[i]
        }));

        let (_, tiles_y) = cam.tiles();
        s.row_start.clear();
        s.row_start.resize(tiles_y + 1, 0);
        for sp in &s.splats {
            for ty in usize::from(sp.rect[2]) / TILE..usize::from(sp.rect[3]) / TILE + 1 {
                s.row_start[ty + 1] += 1;
            }
        }
        for ty in 0..tiles_y {
            s.row_start[ty + 1] += s.row_start[ty];
        }
        s.row_entries.clear();
        s.row_entries.resize(s.row_start[tiles_y], 0);
        let mut fill = s.row_start.clone();
        for (idx, sp) in s.splats.iter().enumerate() {
            let rows = usize::from(sp.rect[2]) / TILE..usize::from(sp.rect[3]) / TILE + 1;
            for f in &mut fill[rows] {
                s.row_entries[*f] = idx as u32;
                *f += 1;
            }
        }
    }
}

/// Output slices of one tile row (16 image rows, or fewer at the bottom).
struct RowOut<'a> {
    ty: usize,
    color: Option<&'a mut [f32]>,
    depth: Option<&'a mut [f32]>,
    alpha: Option<&'a mut [f32]>,
    transmittance: Option<&'a mut [f32]>,
    ids: Option<&'a mut [u32]>,
    weights: Option<&'a mut [f32]>,
}

fn row_chunks<T>(buf: &mut [T], row_len: usize, rows: usize) -> Vec<Option<&mut [T]>> {
    if buf.is_empty() || row_len == 0 {
        (0..rows).map(|_| None).collect()
    } else {
        buf.chunks_mut(row_len * TILE).map(Some).collect()
    }
}

/// Rasterises every tile of the view in parallel over tile rows; returns the number of
/// (tile, Gaussian) pairs.
fn blend(cam: &ViewCamera, opts: &RenderOptions, out: &mut ViewRender) -> usize {
    let (tiles_x, tiles_y) = cam.tiles();
    let w = out.width;
    let k = opts.top_k.unwrap_or(0);
    let mut color = row_chunks(&mut out.color, w * 3, tiles_y).into_iter();
    let mut depth = row_chunks(&mut out.depth, w, tiles_y).into_iter();
    let mut alpha = row_chunks(&mut out.alpha, w, tiles_y).into_iter();
    let mut trans = row_chunks(&mut out.transmittance, w, tiles_y).into_iter();
    let mut ids = row_chunks(&mut out.ids, w * k, tiles_y).into_iter();
    let mut weights = row_chunks(&mut out.weights, w * k, tiles_y).into_iter();
    let rows: Vec<RowOut<'_>> = (0..tiles_y)
        .map(|ty| RowOut {
            ty,
            color: color.next().flatten(),
            depth: depth.next().flatten(),
            alpha: alpha.next().flatten(),
            transmittance: trans.next().flatten(),
            ids: ids.next().flatten(),
            weights: weights.next().flatten(),
        })
        .collect();
    let scratch = &out.scratch;
    let ctx = Ctx {
        splats: &scratch.splats,
        width: w,
        height: out.height,
        tiles_x,
        k,
        lists_only: k > 0
            && !opts.color
            && opts.depth == DepthMode::None
            && !opts.alpha
            && !opts.transmittance,
        opts,
    };
    rows.into_par_iter()
        .map_init(
            || Pooled::take(&scratch.tiles, tiles_x, k),
            |st, row| {
                let entries =
                    &scratch.row_entries[scratch.row_start[row.ty]..scratch.row_start[row.ty + 1]];
                render_row(&ctx, entries, row, st.get())
            },
        )
        .sum()
}

/// A tile scratch borrowed from the view's pool and given back when dropped.
struct Pooled<'a> {
    st: Option<TileScratch>,
    pool: &'a Mutex<Vec<TileScratch>>,
}

impl<'a> Pooled<'a> {
    fn take(pool: &'a Mutex<Vec<TileScratch>>, tiles_x: usize, k: usize) -> Self {
        let st = pool.lock().ok().and_then(|mut p| p.pop());
        let mut st = st.unwrap_or_default();
        st.reset(tiles_x, k);
        Pooled { st: Some(st), pool }
    }

    fn get(&mut self) -> &mut TileScratch {
        self.st.get_or_insert_with(TileScratch::default)
    }
}

impl Drop for Pooled<'_> {
    fn drop(&mut self) {
        if let (Some(st), Ok(mut pool)) = (self.st.take(), self.pool.lock()) {
            pool.push(st);
        }
    }
}

/// The output slots of one tile's top-K lists: pixel (row, col) of the tile owns the K
/// slots at `row * stride + base + col * k` of its tile row's buffers.
struct TopKOut<'a> {
    k: usize,
    /// W · K: one image row of lists.
    stride: usize,
    /// x0 · K: the tile's first column.
    base: usize,
    w: &'a mut [f32],
    id: &'a mut [u32],
}

/// Scratch of one worker, reused across tiles and views: the per-pixel blend state of one
/// tile and its top-K lists (structure of arrays in 4-pixel SIMD groups), and the
/// row-to-tile bucketing buffers.
///
/// The lists are kept rank-major per group (`lw[group * K + r]` holds rank r of the
/// group's 4 pixels), so one insertion serves every lane of a group that has a candidate
/// with SIMD compares and blends, without per-lane branches; they start as padding
/// (weight 0, [`NO_GAUSSIAN`]), so a list that is not full needs no fill count, and the
/// K-th rank is the bar a newcomer must beat. They reach the output once per tile.
#[derive(Debug, Default)]
struct TileScratch {
    /// Transmittance (in groups of [`LANES`] pixels, row-major within the tile).
    t: Vec<f32x4>,
    /// Σ ω c per channel.
    r: Vec<f32x4>,
    g: Vec<f32x4>,
    b: Vec<f32x4>,
    /// Σ ω z.
    depth: Vec<f32x4>,
    /// Σ ω.
    wsum: Vec<f32x4>,
    /// Lane mask (all bits set) once the pixel has stopped (T would fall below 1e-4).
    done: Vec<f32x4>,
    /// Top-K weights, `[group][rank]`, each lane sorted by descending weight.
    lw: Vec<f32x4>,
    /// Top-K Gaussian ids beside `lw`, as f32 bit patterns (only ever moved by blends).
    lid: Vec<f32x4>,
    tile_start: Vec<usize>,
    tile_entries: Vec<u32>,
}

impl TileScratch {
    fn reset(&mut self, tiles_x: usize, k: usize) {
        self.lw.resize(TILE_GROUPS * k, f32x4::ZERO);
        self.lid.resize(TILE_GROUPS * k, NO_ID_BITS);
        for v in [
            &mut self.t,
            &mut self.r,
            &mut self.g,
            &mut self.b,
            &mut self.depth,
            &mut self.wsum,
            &mut self.done,
        ] {
            v.resize(TILE_GROUPS, f32x4::ZERO);
        }
        self.tile_start.resize(tiles_x + 1, 0);
    }

    fn clear_tile(&mut self, topk: bool) {
        self.t.fill(f32x4::ONE);
        for v in [
            &mut self.r,
            &mut self.g,
            &mut self.b,
            &mut self.depth,
            &mut self.wsum,
            &mut self.done,
        ] {
            v.fill(f32x4::ZERO);
        }
        if topk {
            self.lw.fill(f32x4::ZERO);
            self.lid.fill(NO_ID_BITS);
        }
    }
}

struct Ctx<'a> {
    splats: &'a [Splat],
    width: usize,
    height: usize,
    tiles_x: usize,
    k: usize,
    /// Only the top-K lists are wanted (no colour, depth, alpha or T, as registration
    /// renders): a pixel then stops as soon as its list is final (see `blend_span`).
    lists_only: bool,
    opts: &'a RenderOptions,
}

/// Renders the tiles of one tile row; returns its (tile, Gaussian) pair count.
fn render_row(ctx: &Ctx<'_>, entries: &[u32], mut row: RowOut<'_>, st: &mut TileScratch) -> usize {
    // Bucket the row's splats (depth-sorted) by tile column, keeping the order.
    let tiles_x = ctx.tiles_x;
    let mut start = std::mem::take(&mut st.tile_start);
    let mut list = std::mem::take(&mut st.tile_entries);
    start.clear();
    start.resize(tiles_x + 1, 0);
    for &e in entries {
        let r = ctx.splats[e as usize].rect;
        for tx in usize::from(r[0]) / TILE..usize::from(r[1]) / TILE + 1 {
            start[tx + 1] += 1;
        }
    }
    for tx in 0..tiles_x {
        start[tx + 1] += start[tx];
    }
    let total = start[tiles_x];
    list.clear();
    list.resize(total, 0);
    let mut fill = start.clone();
    for &e in entries {
        let r = ctx.splats[e as usize].rect;
        for tx in usize::from(r[0]) / TILE..usize::from(r[1]) / TILE + 1 {
            list[fill[tx]] = e;
            fill[tx] += 1;
        }
    }

    let y0 = row.ty * TILE;
    let y1 = (y0 + TILE).min(ctx.height); // exclusive
    for tx in 0..tiles_x {
        let x0 = tx * TILE;
        let x1 = (x0 + TILE).min(ctx.width);
        let tile = &list[start[tx]..start[tx + 1]];
        let k = ctx.k;
        let rect = [x0, x1, y0, y1];
        if let (true, Some(w), Some(id)) =
            (k > 0, row.weights.as_deref_mut(), row.ids.as_deref_mut())
        {
            let mut out = TopKOut {
                k,
                stride: ctx.width * k,
                base: x0 * k,
                w,
                id,
            };
            if tile.is_empty() {
                // Nothing to sort or transpose: every list is padding.
                blend_tile::<false, false>(ctx, tile, rect, st);
                pad_lists(&mut out, x1 - x0, y1 - y0);
            } else {
                if ctx.lists_only {
                    blend_tile::<true, true>(ctx, tile, rect, st);
                } else {
                    blend_tile::<true, false>(ctx, tile, rect, st);
                }
                write_lists(&mut out, x1 - x0, y1 - y0, st);
            }
        } else {
            blend_tile::<false, false>(ctx, tile, rect, st);
        }
        write_tile(ctx, &mut row, rect, st);
    }
    st.tile_start = start;
    st.tile_entries = list;
    total
}

/// Writes padding (weight 0, [`NO_GAUSSIAN`]) into every list of a `cols` x `rows` tile
/// (one fill per tile row: its lists are adjacent in the output).
fn pad_lists(out: &mut TopKOut<'_>, cols: usize, rows: usize) {
    for row in 0..rows {
        let first = row * out.stride + out.base;
        let slots = first..first + cols * out.k;
        if let Some(w) = out.w.get_mut(slots.clone()) {
            w.fill(0.0);
        }
        if let Some(id) = out.id.get_mut(slots) {
            id.fill(NO_GAUSSIAN);
        }
    }
}

/// Copies a finished tile's lists (padding included) from their group-major SIMD form into
/// the output's per-pixel form, for the `cols` x `rows` pixels inside the image.
fn write_lists(out: &mut TopKOut<'_>, cols: usize, rows: usize, st: &TileScratch) {
    let k = out.k;
    for row in 0..rows {
        for col in 0..cols {
            let group = (row * ROW_GROUPS + col / LANES) * k;
            let (Some(sw), Some(sid)) = (st.lw.get(group..group + k), st.lid.get(group..group + k))
            else {
                continue;
            };
            let slot = row * out.stride + out.base + col * k;
            let lane = col % LANES;
            if let Some(dw) = out.w.get_mut(slot..slot + k) {
                for (d, s) in dw.iter_mut().zip(sw) {
                    *d = s.as_array_ref()[lane];
                }
            }
            if let Some(did) = out.id.get_mut(slot..slot + k) {
                for (d, s) in did.iter_mut().zip(sid) {
                    *d = s.as_array_ref()[lane].to_bits();
                }
            }
        }
    }
}

/// Front-to-back blend of one tile's depth-sorted splats. (Not inlined: the two
/// instantiations stay separate functions, which keeps the SIMD loop's register allocation
/// independent of the caller and makes profiles readable.)
#[inline(never)]
fn blend_tile<const TOPK: bool, const CUTOFF: bool>(
    ctx: &Ctx<'_>,
    list: &[u32],
    [x0, x1, y0, y1]: [usize; 4],
    st: &mut TileScratch,
) {
    st.clear_tile(TOPK);
    let live = ((x1 - x0) * (y1 - y0)) as u32;
    let mut stopped = 0u32;
    for &e in list {
        let s = &ctx.splats[e as usize];
        let [rx0, rx1, ry0, ry1] = s.rect.map(usize::from);
        let (cx0, cx1) = (rx0.max(x0), rx1.min(x1 - 1));
        let (cy0, cy1) = (ry0.max(y0), ry1.min(y1 - 1));
        if cx0 > cx1 || cy0 > cy1 {
            continue;
        }
        for py in cy0..cy1 + 1 {
            let dy = s.y - (py as f32 + 0.5);
            let (lo, hi) = if s.inv_a > 0.0 {
                // Pixels of this row with ½ dᵀ C d <= tau (tau has a margin, see `Splat`):
                // solve the quadratic in dx, widen by SPAN_SLACK for rounding.
                let disc = s.two_a_tau - s.det * dy * dy;
                if disc.is_nan() || disc < 0.0 {
                    continue;
                }
                let half = disc.sqrt() * s.inv_a;
                let mid = s.x - 0.5 + s.b * dy * s.inv_a;
                let (lo_f, hi_f) = (mid - half - SPAN_SLACK, mid + half + SPAN_SLACK);
                // ceil and floor without libm calls (the bounds are within [cx0, cx1] here,
                // so the casts are exact truncations of small non-negative values).
                if hi_f < cx0 as f32 || lo_f > cx1 as f32 {
                    continue;
                }
                let lo = if lo_f > cx0 as f32 {
                    let t = lo_f as i32;
                    t + i32::from((t as f32) < lo_f)
                } else {
                    cx0 as i32
                };
                let hi = (hi_f as i32).min(cx1 as i32);
                if hi < lo {
                    continue;
                }
                (lo as usize, hi as usize)
            } else {
                (cx0, cx1)
            };
            let (lo, hi) = (lo - x0, hi - x0);
            stopped += blend_span::<TOPK, CUTOFF>(s, x0, py - y0, lo, hi, dy, st);
        }
        if stopped == live {
            break;
        }
    }
}

/// Extra width, in pixels, of each per-row span beyond the solved ellipse bounds: far above
/// the f32 rounding of those bounds (the exponent margin of `Splat::two_a_tau` adds more).
const SPAN_SLACK: f32 = 1.0 / 64.0;

/// Pixels per SIMD group of the blend (SSE2 width; a tile row is 4 groups).
const LANES: usize = 4;
/// Groups per tile row.
const ROW_GROUPS: usize = TILE / LANES;
/// Groups per tile.
const TILE_GROUPS: usize = TILE_PIXELS / LANES;

/// The pixels of a group, as plain floats.
fn flat(v: &[f32x4]) -> &[f32] {
    bytemuck::cast_slice(v)
}

/// One splat over the pixels `lo..=hi` (tile-local columns) of tile row `row`, whose first
/// column is image column `x0`: INRIA's per-pixel step on whole 4-pixel groups (lanes
/// outside `lo..=hi` masked off, groups whose pixels have all stopped skipped). With `TOPK`,
/// pixels whose weight beats their list's K-th enter their top-K list. Returns how many
/// pixels stopped.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn blend_span<const TOPK: bool, const CUTOFF: bool>(
    s: &Splat,
    x0: usize,
    row: usize,
    lo: usize,
    hi: usize,
    dy: f32,
    st: &mut TileScratch,
) -> u32 {
    let q = Lane {
        sx: f32x4::splat(s.x),
        a: f32x4::splat(s.a),
        b: f32x4::splat(s.b),
        // c·dy·dy rounds exactly as inside the scalar power expression.
        cdy: f32x4::splat(s.c * dy * dy),
        dy: f32x4::splat(dy),
        o: f32x4::splat(s.opacity),
        color: s.color.map(f32x4::splat),
        z: f32x4::splat(s.depth),
    };
    let mut stops = 0;
    // K of the lists (TILE_GROUPS groups of K ranks; 0 without top-K).
    let k = st.lw.len() / TILE_GROUPS;
    let id = f32x4::splat(f32::from_bits(s.id));
    for gi in lo / LANES..hi / LANES + 1 {
        let i = row * ROW_GROUPS + gi;
        let (Some(t), Some(r), Some(g), Some(b), Some(d), Some(ws), Some(done)) = (
            st.t.get_mut(i),
            st.r.get_mut(i),
            st.g.get_mut(i),
            st.b.get_mut(i),
            st.depth.get_mut(i),
            st.wsum.get_mut(i),
            st.done.get_mut(i),
        ) else {
            continue;
        };
        let c0 = gi * LANES;
        let valid = LANE_VALID[(lo.max(c0) - c0) * LANES + (hi.min(c0 + LANES - 1) - c0)];
        let live = valid & !*done;
        if live.move_mask() == 0 {
            // Every pixel of the group has stopped or lies outside the span.
            continue;
        }
        let px = f32x4::splat((x0 + c0) as f32) + LANE_CENTRE;
        let (n, w) = blend_group(&q, live, px, t, r, g, b, d, ws, done);
        stops += n;
        if TOPK {
            let list = i * k..(i + 1) * k;
            if let (Some(lw), Some(lid)) = (st.lw.get_mut(list.clone()), st.lid.get_mut(list)) {
                // Lanes whose weight beats the pixel's K-th (0 while the list is not full);
                // usually few, often none.
                let kth = lw[k - 1];
                let cand = w.cmp_gt(kth);
                let kth = if cand.move_mask() != 0 {
                    insert_group(lw, lid, cand, w, id)
                } else {
                    kth
                };
                if CUTOFF {
                    // A later contributor weighs ω = T·α < T (α <= 0.99, T never grows), so
                    // once T <= the K-th weight of a full list (> 0) nothing can enter: the
                    // pixel's list is final and it stops here.
                    let full = kth.cmp_gt(f32x4::ZERO);
                    let settled = live & full & t.cmp_le(kth) & !*done;
                    *done |= settled;
                    stops += settled.move_mask().count_ones();
                }
            }
        }
    }
    stops
}

/// Inserts (w, id) into the sorted lists of the lanes in `cand` of one group (`lw[r]`,
/// `lid[r]`: rank r of the 4 lists); returns the new K-th weights. Ranks are rewritten from
/// the last upwards, all candidate lanes at once: rank r takes rank r − 1's entry in lanes
/// whose newcomer sits above r, the newcomer in lanes where it sits exactly at r, and keeps
/// its entry elsewhere; the pass stops at the first rank no lane shifts into. A newcomer
/// goes after the entries of equal weight (strict >), so ties keep depth order, and a full
/// list drops its last entry: the same lists as inserting one pixel at a time.
#[inline(always)]
fn insert_group(lw: &mut [f32x4], lid: &mut [f32x4], cand: f32x4, w: f32x4, id: f32x4) -> f32x4 {
    let mut r = lw.len() - 1;
    // Lanes whose newcomer belongs at rank r or above.
    let mut at_or_above = cand & w.cmp_gt(lw[r]);
    loop {
        let above = if r > 0 {
            cand & w.cmp_gt(lw[r - 1])
        } else {
            f32x4::ZERO
        };
        let (prev_w, prev_id) = if r > 0 {
            (lw[r - 1], lid[r - 1])
        } else {
            (lw[r], lid[r])
        };
        lw[r] = above.blend(prev_w, at_or_above.blend(w, lw[r]));
        lid[r] = above.blend(prev_id, at_or_above.blend(id, lid[r]));
        if r == 0 || above.move_mask() == 0 {
            break;
        }
        at_or_above = above;
        r -= 1;
    }
    lw[lw.len() - 1]
}

/// Pixel-centre offsets of the lanes: lane l of a group starting at column c has its centre
/// at c + l + 0.5 (exact in f32, the same value as `(c + l) as f32 + 0.5`).
const LANE_CENTRE: f32x4 = f32x4::new([0.5, 1.5, 2.5, 3.5]);

/// Lane masks for the columns `first..=last` of a group, indexed `first * LANES + last`.
const LANE_VALID: [f32x4; LANES * LANES] = {
    let mut m = [f32x4::ZERO; LANES * LANES];
    let on = f32::from_bits(u32::MAX);
    let mut first = 0;
    while first < LANES {
        let mut last = first;
        while last < LANES {
            let mut v = [0.0f32; LANES];
            let mut l = first;
            while l <= last {
                v[l] = on;
                l += 1;
            }
            m[first * LANES + last] = f32x4::new(v);
            last += 1;
        }
        first += 1;
    }
    m
};

/// Per-splat, per-row constants of [`blend_group`], broadcast to all lanes.
struct Lane {
    sx: f32x4,
    a: f32x4,
    b: f32x4,
    cdy: f32x4,
    dy: f32x4,
    o: f32x4,
    color: [f32x4; 3],
    z: f32x4,
}

/// INRIA's per-pixel step for 4 adjacent pixels with centres `px` (pixels outside `live`
/// are left alone): power = −½(a dx² + c dy²) − b dx dy, α = min(0.99, o·exp(power)), skip
/// power > 0 or α < 1/255, stop if T(1 − α) < 1e-4, else ω = T·α and the sums grow by ω.
/// Every lane performs the same IEEE operations in the same order as the scalar reference,
/// and masked lanes add ω = 0 (the sums are finite and >= 0, so x + 0 = x bit for bit): the
/// result equals a scalar per-pixel loop exactly.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn blend_group(
    q: &Lane,
    live: f32x4,
    px: f32x4,
    t: &mut f32x4,
    r: &mut f32x4,
    g: &mut f32x4,
    b: &mut f32x4,
    d: &mut f32x4,
    ws: &mut f32x4,
    done: &mut f32x4,
) -> (u32, f32x4) {
    let dx = q.sx - px;
    let power = f32x4::splat(-0.5) * (q.a * dx * dx + q.cdy) - q.b * dx * q.dy;
    let alpha = (q.o * exp4(power)).min(f32x4::splat(ALPHA_MAX));
    let ok = live & power.cmp_le(f32x4::ZERO) & alpha.cmp_ge(f32x4::splat(ALPHA_MIN));
    let tj = *t;
    let test_t = tj * (f32x4::ONE - alpha);
    let low = test_t.cmp_lt(f32x4::splat(T_MIN));
    let contrib = ok & !low;
    let w = contrib.blend(alpha * tj, f32x4::ZERO);
    *r += q.color[0] * w;
    *g += q.color[1] * w;
    *b += q.color[2] * w;
    *d += q.z * w;
    *ws += w;
    *t = contrib.blend(test_t, tj);
    let stop = ok & low;
    *done |= stop;
    (stop.move_mask().count_ones(), w)
}

/// Copies a finished tile into the tile row's output slices.
fn write_tile(ctx: &Ctx<'_>, row: &mut RowOut<'_>, [x0, x1, y0, y1]: [usize; 4], st: &TileScratch) {
    let w = ctx.width;
    let bg = ctx.opts.background;
    let normalized = ctx.opts.depth == DepthMode::Normalized;
    let nx = x1 - x0;
    for py in y0..y1 {
        let s0 = (py - y0) * TILE;
        let src = s0..s0 + nx;
        let o = (py - y0) * w + x0;
        let t = &flat(&st.t)[src.clone()];
        if let Some(c) = row.color.as_deref_mut() {
            let it = flat(&st.r)[src.clone()]
                .iter()
                .zip(&flat(&st.g)[src.clone()])
                .zip(&flat(&st.b)[src.clone()])
                .zip(t);
            for (dst, (((r, g), b), t)) in c[o * 3..(o + nx) * 3].chunks_exact_mut(3).zip(it) {
                dst[0] = r + t * bg[0];
                dst[1] = g + t * bg[1];
                dst[2] = b + t * bg[2];
            }
        }
        if let Some(dd) = row.depth.as_deref_mut() {
            let it = flat(&st.depth)[src.clone()]
                .iter()
                .zip(&flat(&st.wsum)[src.clone()]);
            for (dst, (z, ws)) in dd[o..o + nx].iter_mut().zip(it) {
                *dst = if !normalized {
                    *z
                } else if *ws > 0.0 {
                    z / ws
                } else {
                    0.0
                };
            }
        }
        if let Some(a) = row.alpha.as_deref_mut() {
            for (dst, t) in a[o..o + nx].iter_mut().zip(t) {
                *dst = 1.0 - t;
            }
        }
        if let Some(tr) = row.transmittance.as_deref_mut() {
            tr[o..o + nx].copy_from_slice(t);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{depth_key, key_position, Splat, PROJECT_CHUNK};

    fn splat_at(depth: f32) -> Splat {
        Splat {
            x: 0.0,
            y: 0.0,
            a: 1.0,
            b: 0.0,
            c: 1.0,
            opacity: 0.5,
            color: [0.0; 3],
            depth,
            id: 0,
            two_a_tau: 1.0,
            det: 1.0,
            inv_a: 1.0,
            rect: [0; 4],
        }
    }

    #[test]
    fn depth_keys_order_by_depth_then_chunk_then_index_and_round_trip() {
        let last = PROJECT_CHUNK - 1;
        let mut keys = vec![
            (depth_key(&splat_at(2.0), 0, 5), (0, 5)),
            (depth_key(&splat_at(0.25), 7, last), (7, last)),
            (depth_key(&splat_at(1.0), 3, 0), (3, 0)),
            (depth_key(&splat_at(1.0), 2, last), (2, last)),
            (depth_key(&splat_at(1.0), 2, 4), (2, 4)),
            (depth_key(&splat_at(1.0e30), 0, 0), (0, 0)),
        ];
        keys.sort_unstable();
        let order: Vec<(usize, usize)> = keys.iter().map(|k| k.1).collect();
        assert_eq!(
            order,
            [(7, last), (2, 4), (2, last), (3, 0), (0, 5), (0, 0)],
            "depth first, equal depths by (chunk, index), i.e. by Gaussian id"
        );
        for (key, pos) in keys {
            assert_eq!(key_position(key), pos);
        }
    }
}

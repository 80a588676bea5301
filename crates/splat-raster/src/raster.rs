//! Binning of projected Gaussians into 16x16 tiles and the per-tile front-to-back blend.

use std::sync::Mutex;
use std::time::{Duration, Instant};

use profuse_formats::{Cameras, Gaussians};
use rayon::prelude::*;

use wide::f32x4;

use crate::camera::ViewCamera;
use crate::error::{RasterError, Result};
use crate::project::{
    prepare, project, project_chunk, Prepared, Projected, Splat, SplatSink, ViewConsts,
};
#[cfg(target_arch = "x86_64")]
use crate::simd::avx512::F32x16;
use crate::simd::{bit_range, prefetch, Lanes, Level, UNIT_W};
use crate::{ALPHA_MAX, ALPHA_MIN, MAX_TOP_K, NO_GAUSSIAN, TILE, T_MIN};

const TILE_PIXELS: usize = TILE * TILE;
/// Blend units per tile row of units ([`UNIT_W`] pixels wide each).
const UNITS_PER_ROW: usize = TILE / UNIT_W;

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
    /// Work counts of the blend: zero unless the crate is built with the `counters`
    /// feature (they cost a few instructions per pixel group).
    pub counts: BlendCounts,
}

/// Wall time of the phases of one render, in order ([`ViewRender::phases`],
/// [`ListScratch::phases`]; kept apart from the deterministic [`RenderStats`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Phases {
    /// Projecting every Gaussian (culling, EWA covariance, SH colour) and making the sort
    /// keys.
    pub project: Duration,
    /// Sorting the splats' records (depth key, rectangle) by depth.
    pub sort: Duration,
    /// Bucketing the depth-ordered splats by tile row.
    pub bucket: Duration,
    /// Everything per tile row, in parallel: bucketing by tile, blending, top-K
    /// insertion and writing the outputs.
    pub blend: Duration,
}

/// What the blend did, summed over the view's tiles (with the `counters` feature).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct BlendCounts {
    /// Pixel groups evaluated (a blend unit's N pixels against one splat: 4 x 1 with 4
    /// lanes, 4 x 4 with 16).
    pub groups: u64,
    /// Lanes of those groups that were live (inside the splat's span and not stopped).
    pub live_lanes: u64,
    /// (pixel, Gaussian) blends that contributed: ω = T·α > 0.
    pub blends: u64,
    /// Contributions that entered a top-K list.
    pub inserted: u64,
}

impl BlendCounts {
    fn add(self, o: BlendCounts) -> BlendCounts {
        BlendCounts {
            groups: self.groups + o.groups,
            live_lanes: self.live_lanes + o.live_lanes,
            blends: self.blends + o.blends,
            inserted: self.inserted + o.inserted,
        }
    }
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
    phases: Phases,
    color: Vec<f32>,
    depth: Vec<f32>,
    alpha: Vec<f32>,
    transmittance: Vec<f32>,
    ids: Vec<u32>,
    weights: Vec<f32>,
    /// Per tile (row-major): its lists in `ids` and `weights` are all padding, as the
    /// previous render left them. An empty tile of the next render with the same width,
    /// height and K then skips rewriting them (on an orbit around an object most of the
    /// image is background, and padding an empty tile's lists writes K x 8 bytes per
    /// pixel).
    padded: Vec<bool>,
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
    /// Wall time of the phases of the render (not deterministic, unlike the stats).
    pub fn phases(&self) -> Phases {
        self.phases
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
    /// Depth quantised to 16 bits so that the largest depth is 65535: the values, the
    /// scale (depth = value · scale; 0 when nothing was hit) and the largest depth.
    pub fn depth_u16(&self) -> Option<(Vec<u16>, f64, f32)> {
        let d = self.depth()?;
        let max = d.iter().copied().fold(0.0f32, f32::max);
        let scale = if max > 0.0 {
            f64::from(max) / 65535.0
        } else {
            0.0
        };
        let q = d
            .iter()
            .map(|v| {
                if scale > 0.0 {
                    (f64::from(*v) / scale).round().clamp(0.0, 65535.0) as u16
                } else {
                    0
                }
            })
            .collect();
        Some((q, scale, max))
    }
    /// Top-K slots holding a Gaussian, and pixels whose K slots are all filled (0, 0 when
    /// top-K is off).
    pub fn topk_fill(&self) -> (usize, usize) {
        let (Some(ids), k) = (self.topk_ids(), self.k()) else {
            return (0, 0);
        };
        let filled = ids.iter().filter(|i| **i != NO_GAUSSIAN).count();
        let full = ids
            .chunks_exact(k.max(1))
            .filter(|c| c[c.len() - 1] != NO_GAUSSIAN)
            .count();
        (filled, full)
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
        let k = opts.top_k.unwrap_or(0);
        // The padded flags describe the buffers only as laid out by the previous render.
        let same_layout = (self.width, self.height, self.k()) == (w, h, k);
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
        size(&mut self.weights, k > 0, n * k);
        self.ids.truncate(n * k);
        self.ids.resize(n * k, NO_GAUSSIAN);
        if !same_layout {
            self.padded.clear();
        }
        let (tiles_x, tiles_y) = cam.tiles();
        self.padded.resize(tiles_x * tiles_y, false);
    }
}

/// Reusable buffers of [`Rasterizer::render_tiles`] (binning and per-worker tile scratch).
#[derive(Debug, Default)]
pub struct ListScratch(ViewScratch);

impl ListScratch {
    /// Wall time of the phases of the last [`Rasterizer::render_tiles`] with this scratch
    /// (the blend phase includes the consumer's work).
    pub fn phases(&self) -> Phases {
        self.0.phases
    }
}

/// The top-K lists of one tile, as [`Rasterizer::render_tiles`] hands them over: pixel
/// (`x0 + col`, `y0 + row`) owns the K entries at `(row * TILE + col) * K` of
/// [`TileLists::ids`], [`TileLists::weights`] and [`TileLists::positions`] (descending
/// weight, ties in depth order, padded with [`NO_GAUSSIAN`] and 0), for `col < width`,
/// `row < height`.
#[derive(Debug, Clone, Copy)]
pub struct TileLists<'a> {
    x0: usize,
    y0: usize,
    width: usize,
    height: usize,
    k: usize,
    ids: &'a [u32],
    positions: &'a [u32],
    splat_ids: &'a [u32],
    weights: &'a [f32],
}

impl<'a> TileLists<'a> {
    /// Image column of the tile's first pixel.
    pub fn x0(&self) -> usize {
        self.x0
    }
    /// Image row of the tile's first pixel.
    pub fn y0(&self) -> usize {
        self.y0
    }
    /// Pixels per row inside the image (16 except at the right edge).
    pub fn width(&self) -> usize {
        self.width
    }
    /// Rows inside the image (16 except at the bottom edge).
    pub fn height(&self) -> usize {
        self.height
    }
    /// K.
    pub fn k(&self) -> usize {
        self.k
    }
    /// The ids of every list, `(row * TILE + col) * K + rank`.
    pub fn ids(&self) -> &'a [u32] {
        self.ids
    }
    /// The weights beside [`TileLists::ids`].
    pub fn weights(&self) -> &'a [f32] {
        self.weights
    }
    /// Beside [`TileLists::ids`], each entry's position in [`TileLists::splat_ids`]
    /// ([`NO_GAUSSIAN`] for padding): `splat_ids()[positions()[i]] == ids()[i]`. The
    /// tile's hits of one Gaussian share a position below `splat_ids().len()`, so a
    /// consumer can sum per Gaussian into a dense array instead of a hash table.
    pub fn positions(&self) -> &'a [u32] {
        self.positions
    }
    /// The Gaussian ids of the splats the tile blended, in depth order (each at most once).
    pub fn splat_ids(&self) -> &'a [u32] {
        self.splat_ids
    }
    /// The K ids and weights of tile pixel (`col`, `row`); `None` outside the tile.
    pub fn pixel(&self, col: usize, row: usize) -> Option<(&'a [u32], &'a [f32])> {
        if col >= self.width || row >= self.height {
            return None;
        }
        let i = (row * TILE + col) * self.k;
        Some((
            self.ids.get(i..i + self.k)?,
            self.weights.get(i..i + self.k)?,
        ))
    }
}

/// Slots (Gaussians) projected per job of [`Rasterizer::bin`]: fixed, so that the jobs do
/// not depend on the thread count.
const PROJECT_CHUNK: usize = 1 << 14;

/// Sort key of a splat: its camera depth (positive, finite: the bits of a positive f32
/// order as the value) above its position in the view's splats, which is its Gaussian's
/// slot: equal depths order by slot, and `sort_by_depth` reorders those ties by id, as the
/// (depth, id) rule requires.
fn depth_key(depth: f32, position: u32) -> u64 {
    (u64::from(depth.to_bits()) << 32) | u64::from(position)
}

/// The position of a [`depth_key`].
fn key_position(key: u64) -> u32 {
    key as u32
}

/// Per-view binning buffers, reused between views.
#[derive(Debug, Default)]
struct ViewScratch {
    /// The projected splats, each at its Gaussian's slot (the slots of culled Gaussians
    /// hold stale splats, never read); the tile lists index it. As long as the Gaussians,
    /// so views reuse it.
    splats: Vec<Splat>,
    /// Per chunk: its splats' sort records, in slot order, and their depth range.
    chunks: Vec<ChunkRecords>,
    /// Every splat's sort record in (depth, id) order.
    depth_order: Vec<DepthRecord>,
    row_start: Vec<usize>,
    /// Per tile row, its splats in depth order: index and pixel rectangle (a copy of the
    /// rectangle, so that bucketing the row by tile column reads memory in order).
    row_entries: Vec<RowEntry>,
    tiles: Mutex<Vec<TileScratch>>,
    /// Phase times of the last render with this scratch.
    phases: Phases,
}

/// The rasterizer of one Gaussian set: holds the view-independent per-Gaussian data
/// (3D covariances, opacities) and renders any number of views.
#[derive(Debug)]
pub struct Rasterizer<'g> {
    gaussians: &'g Gaussians,
    prep: Prepared,
    level: Level,
}

/// The SIMD width of the tile blend. Every choice renders the same bytes (the lanes perform
/// the same IEEE operations in the same order); the choice exists for benchmarks and tests.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Simd {
    /// 4 lanes of `wide::f32x4` (SSE2 on x86-64, NEON on aarch64): runs everywhere.
    Portable,
    /// 16 lanes (a 4 x 4 pixel block per unit) with AVX-512 F + DQ, chosen at run time on
    /// x86-64 CPUs that have them.
    Avx512,
}

impl Simd {
    /// Lower-case name (`portable`, `avx512`).
    pub fn name(self) -> &'static str {
        match self {
            Simd::Portable => "portable",
            Simd::Avx512 => "avx512",
        }
    }
}

impl<'g> Rasterizer<'g> {
    /// Validates the Gaussians ([`check_gaussians`](crate::check_gaussians): lengths, finite
    /// parameters, non-zero quaternions; opacity logits may be ±inf) and precomputes their
    /// spatial order, 3D covariances and opacities.
    pub fn new(gaussians: &'g Gaussians) -> Result<Self> {
        Ok(Rasterizer {
            gaussians,
            prep: prepare(gaussians)?,
            level: Level::detect(),
        })
    }

    /// The SIMD width in use: the widest this CPU runs unless [`Rasterizer::set_simd`]
    /// chose another.
    pub fn simd(&self) -> Simd {
        match self.level {
            Level::Portable => Simd::Portable,
            #[cfg(target_arch = "x86_64")]
            Level::Avx512 => Simd::Avx512,
        }
    }

    /// Chooses the SIMD width; an error (and no change) if this CPU cannot run it.
    pub fn set_simd(&mut self, simd: Simd) -> Result<()> {
        self.level = match simd {
            Simd::Portable => Level::Portable,
            Simd::Avx512 => match Level::detect() {
                #[cfg(target_arch = "x86_64")]
                Level::Avx512 => Level::Avx512,
                _ => return Err(RasterError::SimdUnsupported { simd: simd.name() }),
            },
        };
        Ok(())
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
        project(self.gaussians, cam, cam.center(), index)
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
        let mut phases = self.bin(cam, opts.color, &mut out.scratch);
        let visible = out.scratch.depth_order.len();
        let t0 = Instant::now();
        let (tile_pairs, counts) = blend(cam, opts, self.level, out);
        phases.blend = t0.elapsed();
        out.stats = RenderStats {
            visible,
            tile_pairs,
            counts,
        };
        out.phases = phases;
        Ok(())
    }

    /// Renders only the top-K lists of `cam`, tile by tile, and hands every finished 16x16
    /// tile (smaller at the right and bottom edges) to `consume` together with the state
    /// of its tile row: `rows` is resized to the number of tile rows (new entries
    /// `R::default()`), and each row's tiles reach its state in order, from one thread, so
    /// whatever `consume` accumulates per row does not depend on the thread count. The
    /// lists are those of [`Rasterizer::render_camera_into`] with `top_k: Some(k)`, but no
    /// image-sized buffer exists: a tile's lists live in the worker's scratch while
    /// `consume` reads them (registration sums them this way, while they are in cache).
    /// Beside the ids, every entry's position in the tile's splat list
    /// ([`TileLists::positions`], [`TileLists::splat_ids`]) lets a consumer sum per
    /// Gaussian into a dense tile-local array. `scratch` is reused from view to view.
    pub fn render_tiles<R, F>(
        &self,
        cam: &ViewCamera,
        view: usize,
        k: usize,
        scratch: &mut ListScratch,
        rows: &mut Vec<R>,
        consume: F,
    ) -> Result<RenderStats>
    where
        R: Default + Send,
        F: Fn(&TileLists<'_>, &mut R) + Sync,
    {
        let opts = RenderOptions {
            color: false,
            top_k: Some(k),
            ..RenderOptions::default()
        };
        opts.validate()?;
        cam.check(view)?;
        let s = &mut scratch.0;
        let mut phases = self.bin(cam, false, s);
        let t0 = Instant::now();
        let (tiles_x, tiles_y) = cam.tiles();
        rows.truncate(tiles_y);
        rows.resize_with(tiles_y, R::default);
        let s = &*s;
        let ctx = Ctx {
            splats: &s.splats,
            width: cam.width as usize,
            height: cam.height as usize,
            tiles_x,
            k,
            lists_only: true,
            opts: &opts,
            level: self.level,
        };
        let (tile_pairs, counts) = rows
            .par_iter_mut()
            .enumerate()
            .map_init(
                || Pooled::take(&s.tiles, tiles_x, k),
                |st, (ty, state)| {
                    let entries = &s.row_entries[s.row_start[ty]..s.row_start[ty + 1]];
                    consume_row(&ctx, entries, ty, st.get(), state, &consume)
                },
            )
            .reduce(|| (0, BlendCounts::default()), add_rows);
        phases.blend = t0.elapsed();
        let visible = s.depth_order.len();
        scratch.0.phases = phases;
        Ok(RenderStats {
            visible,
            tile_pairs,
            counts,
        })
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
    /// Gaussians are projected in fixed chunks of slots (the chunking does not depend on
    /// the thread count), each straight into its own range of the view's reused splat
    /// buffer, where the tiles read them: the 64-byte splats are never moved into depth
    /// order. They stay in slot order, the Morton order of the Gaussians' means
    /// ([`Prepared`]), in which a tile's splats lie in a few runs of the buffer; depth
    /// order scatters them over all of it. Only 16-byte records (depth key, rectangle),
    /// made while each splat is in cache, are sorted. The splats get their colour only
    /// when `shade` (a render with a colour output).
    fn bin(&self, cam: &ViewCamera, shade: bool, s: &mut ViewScratch) -> Phases {
        let t0 = Instant::now();
        let consts = ViewConsts::new(cam, shade);
        let n = self.len();
        if s.splats.len() != n {
            s.splats.clear();
            s.splats.resize(n, UNUSED_SPLAT);
        }
        s.chunks
            .resize_with(n.div_ceil(PROJECT_CHUNK), Default::default);
        s.splats
            .par_chunks_mut(PROJECT_CHUNK)
            .zip(s.chunks.par_iter_mut())
            .enumerate()
            .for_each(|(c, (splats, records))| {
                let first = c * PROJECT_CHUNK;
                let ids = first..first + splats.len();
                let mut out = ChunkOut::new(splats, first, records);
                project_chunk(
                    &consts,
                    self.gaussians,
                    &self.prep,
                    ids,
                    self.level,
                    &mut out,
                );
            });
        let project = t0.elapsed();
        let t0 = Instant::now();
        // Every position is a slot (the records come from this projection).
        let id_of = |position: u32| self.prep.id(position as usize);
        sort_by_depth(&s.chunks, id_of, &mut s.depth_order);
        let sort = t0.elapsed();

        let t0 = Instant::now();
        let (_, tiles_y) = cam.tiles();
        bucket_by_row(
            &s.depth_order,
            tiles_y,
            ROW_BUCKET_BLOCK,
            &mut s.row_start,
            &mut s.row_entries,
        );
        Phases {
            project,
            sort,
            bucket: t0.elapsed(),
            blend: Duration::ZERO,
        }
    }
}

/// A splat's place in the depth order: its [`depth_key`] and its pixel rectangle (carried
/// along so that bucketing by tile row reads no splat).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
struct DepthRecord {
    key: u64,
    rect: [u16; 4],
}

/// One projection chunk's [`DepthRecord`]s (in slot order) and the range of their depth bits.
#[derive(Debug, Default)]
struct ChunkRecords {
    records: Vec<DepthRecord>,
    depth_bits: Option<(u32, u32)>,
}

/// The [`SplatSink`] of one projection chunk: each splat goes to its slot in the view's
/// splats (culled slots keep whatever they held), and its sort record is made while it is
/// in cache.
struct ChunkOut<'a> {
    splats: &'a mut [Splat],
    first: usize,
    records: &'a mut ChunkRecords,
}

impl<'a> ChunkOut<'a> {
    fn new(splats: &'a mut [Splat], first: usize, records: &'a mut ChunkRecords) -> Self {
        records.records.clear();
        records.depth_bits = None;
        ChunkOut {
            splats,
            first,
            records,
        }
    }
}

impl SplatSink for ChunkOut<'_> {
    #[inline(always)]
    fn push(&mut self, slot: usize, splat: Splat) {
        // The slots of the chunk are `first..first + splats.len()`; ids, and so slots, are
        // u32.
        let position = slot as u32;
        let bits = splat.depth.to_bits();
        self.records.depth_bits = Some(match self.records.depth_bits {
            Some((lo, hi)) => (lo.min(bits), hi.max(bits)),
            None => (bits, bits),
        });
        self.records.records.push(DepthRecord {
            key: depth_key(splat.depth, position),
            rect: splat.rect,
        });
        if let Some(s) = self.splats.get_mut(slot - self.first) {
            *s = splat;
        }
    }
}

/// Average splats per bucket of [`sort_by_depth`]: small enough that a bucket sorts in L1.
const SPLATS_PER_BUCKET: usize = 64;
/// Projection chunks per job of [`sort_by_depth`]'s counting and scattering.
const SORT_BLOCK_CHUNKS: usize = 8;

/// Writes every chunk's records into `out` by (depth, id), `id_of` giving the Gaussian id at
/// each position (a slot).
///
/// One pass of a most-significant-digit radix sort, then a comparison sort per bucket:
/// the buckets are ranges of the depth bits (the top bits of the key) sized to hold
/// [`SPLATS_PER_BUCKET`] splats on average; blocks of chunks count their buckets, then
/// scatter into their own slice of every bucket in parallel; then the buckets are sorted
/// in parallel by key, i.e. by (depth, slot), and each run of equal depths (never split
/// between buckets) is put in id order. The keys are unique (positions differ), so
/// the order is the one sorted order whatever the blocks, buckets or threads.
fn sort_by_depth(
    chunks: &[ChunkRecords],
    id_of: impl Fn(u32) -> u32 + Sync,
    out: &mut Vec<DepthRecord>,
) {
    let visible = chunks.iter().map(|c| c.records.len()).sum();
    // Every record is overwritten below: only a longer view writes the new tail.
    out.resize(visible, DepthRecord::default());
    let Some((lo, hi)) = chunks
        .iter()
        .filter_map(|c| c.depth_bits)
        .reduce(|a, b| (a.0.min(b.0), a.1.max(b.1)))
    else {
        return;
    };
    let buckets_log2 = (visible / SPLATS_PER_BUCKET).max(1).ilog2().min(16);
    let span_bits = u32::BITS - (hi - lo).leading_zeros();
    let shift = span_bits.saturating_sub(buckets_log2);
    let buckets = ((hi - lo) >> shift) as usize + 1;
    let bucket_of = |r: &DepthRecord| (((r.key >> 32) as u32 - lo) >> shift) as usize;
    let blocks: Vec<&[ChunkRecords]> = chunks.chunks(SORT_BLOCK_CHUNKS).collect();
    let counts: Vec<Vec<usize>> = blocks
        .par_iter()
        .map(|block| {
            let mut n = vec![0usize; buckets];
            for r in block.iter().flat_map(|c| &c.records) {
                n[bucket_of(r)] += 1;
            }
            n
        })
        .collect();
    let totals: Vec<usize> = (0..buckets)
        .map(|b| counts.iter().map(|n| n[b]).sum())
        .collect();
    let per_block = carve_by_block(out, &counts, buckets);
    blocks
        .par_iter()
        .zip(per_block)
        .for_each(|(block, mut slices)| {
            let mut fill = vec![0usize; buckets];
            for &r in block.iter().flat_map(|c| &c.records) {
                let b = bucket_of(&r);
                slices[b][fill[b]] = r;
                fill[b] += 1;
            }
        });
    // The whole buckets, carved as one block of their totals.
    let whole = carve_by_block(out, std::slice::from_ref(&totals), buckets).pop();
    whole
        .unwrap_or_default()
        .into_par_iter()
        .with_min_len(64)
        .for_each(|bucket| {
            bucket.sort_unstable_by_key(|r| r.key);
            order_ties_by_id(bucket, &id_of);
        });
}

/// Puts each run of equal depths of a key-sorted `records` in id order (the keys order it
/// by slot). Runs are mostly pairs: f32 depths collide by chance (some 50k splats of a
/// 1M-Gaussian view), and duplicated Gaussians share a depth.
fn order_ties_by_id(records: &mut [DepthRecord], id_of: &impl Fn(u32) -> u32) {
    let depth = |r: &DepthRecord| r.key >> 32;
    let id = |r: &DepthRecord| id_of(key_position(r.key));
    for run in records.chunk_by_mut(|a, b| depth(a) == depth(b)) {
        match run {
            [_] => {}
            [a, b] => {
                if id(a) > id(b) {
                    std::mem::swap(a, b);
                }
            }
            _ => run.sort_unstable_by_key(id),
        }
    }
}

/// Carves `buf` into one slice per (bucket, block), bucket-major and blocks in order within
/// a bucket, `counts[block][bucket]` long; returns each block's slices, bucket by bucket.
/// Blocks that fill their slices in parallel thus write every bucket in block order.
fn carve_by_block<'a, T>(
    buf: &'a mut [T],
    counts: &[Vec<usize>],
    buckets: usize,
) -> Vec<Vec<&'a mut [T]>> {
    let mut per_block: Vec<Vec<&mut [T]>> =
        counts.iter().map(|_| Vec::with_capacity(buckets)).collect();
    let mut rest = buf;
    for b in 0..buckets {
        for (block, n) in counts.iter().enumerate() {
            let (now, later) = std::mem::take(&mut rest).split_at_mut(n[b]);
            per_block[block].push(now);
            rest = later;
        }
    }
    per_block
}

/// Filler of the view's splat buffer in the slots of culled Gaussians (never read).
const UNUSED_SPLAT: Splat = Splat {
    x: 0.0,
    y: 0.0,
    a: 0.0,
    b: 0.0,
    c: 0.0,
    opacity: 0.0,
    color: [0.0; 3],
    depth: 0.0,
    id: u32::MAX,
    two_a_tau: 0.0,
    det: 0.0,
    inv_a: 0.0,
    rect: [0; 4],
};

/// A tile row's entry: the splat's position in the view's splats and its pixel rectangle
/// (carried along so that bucketing reads no splat).
type RowEntry = (u32, [u16; 4]);

/// Splats per job of [`bucket_by_row`] (fixed, so the jobs do not depend on the thread
/// count; the result does not depend on them at all).
const ROW_BUCKET_BLOCK: usize = 1 << 16;

/// Lists the depth-ordered `splats` (their positions and rectangles) of every tile row in
/// order: row ty's entries are `entries[start[ty]..start[ty + 1]]`. Blocks of `block`
/// splats count their rows in parallel, then each block fills its own slice of every row
/// (the slices follow the block order, so every row stays in depth order and the result
/// does not depend on `block`).
fn bucket_by_row(
    splats: &[DepthRecord],
    tiles_y: usize,
    block: usize,
    start: &mut Vec<usize>,
    entries: &mut Vec<RowEntry>,
) {
    let rows_of = |rect: &[u16; 4]| usize::from(rect[2]) / TILE..usize::from(rect[3]) / TILE + 1;
    let block = block.max(1);
    let counts: Vec<Vec<usize>> = splats
        .par_chunks(block)
        .map(|block| {
            let mut n = vec![0usize; tiles_y];
            for r in block {
                for c in &mut n[rows_of(&r.rect)] {
                    *c += 1;
                }
            }
            n
        })
        .collect();
    start.clear();
    start.push(0);
    for ty in 0..tiles_y {
        let row: usize = counts.iter().map(|n| n[ty]).sum();
        start.push(start[ty] + row);
    }
    // Every entry is overwritten below: only a longer view writes the new tail.
    entries.resize(start[tiles_y], (0, [0; 4]));
    let per_block = carve_by_block(entries, &counts, tiles_y);
    splats
        .par_chunks(block)
        .zip(per_block)
        .for_each(|(chunk, mut rows)| {
            let mut fill = vec![0usize; tiles_y];
            for r in chunk {
                for ty in rows_of(&r.rect) {
                    rows[ty][fill[ty]] = (key_position(r.key), r.rect);
                    fill[ty] += 1;
                }
            }
        });
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
    /// The row's tiles' [`ViewRender::padded`] flags.
    padded: &'a mut [bool],
}

fn row_chunks<T>(buf: &mut [T], row_len: usize, rows: usize) -> Vec<Option<&mut [T]>> {
    if buf.is_empty() || row_len == 0 {
        (0..rows).map(|_| None).collect()
    } else {
        buf.chunks_mut(row_len * TILE).map(Some).collect()
    }
}

/// Sums two rows' (tile pair count, blend counts).
fn add_rows(a: (usize, BlendCounts), b: (usize, BlendCounts)) -> (usize, BlendCounts) {
    (a.0 + b.0, a.1.add(b.1))
}

/// Rasterises every tile of the view in parallel over tile rows; returns the number of
/// (tile, Gaussian) pairs and the blend counts.
fn blend(
    cam: &ViewCamera,
    opts: &RenderOptions,
    level: Level,
    out: &mut ViewRender,
) -> (usize, BlendCounts) {
    let (tiles_x, tiles_y) = cam.tiles();
    let w = out.width;
    let k = opts.top_k.unwrap_or(0);
    let mut color = row_chunks(&mut out.color, w * 3, tiles_y).into_iter();
    let mut depth = row_chunks(&mut out.depth, w, tiles_y).into_iter();
    let mut alpha = row_chunks(&mut out.alpha, w, tiles_y).into_iter();
    let mut trans = row_chunks(&mut out.transmittance, w, tiles_y).into_iter();
    let mut ids = row_chunks(&mut out.ids, w * k, tiles_y).into_iter();
    let mut weights = row_chunks(&mut out.weights, w * k, tiles_y).into_iter();
    let mut padded = out.padded.chunks_mut(tiles_x);
    let rows: Vec<RowOut<'_>> = (0..tiles_y)
        .map(|ty| RowOut {
            ty,
            color: color.next().flatten(),
            depth: depth.next().flatten(),
            alpha: alpha.next().flatten(),
            transmittance: trans.next().flatten(),
            ids: ids.next().flatten(),
            weights: weights.next().flatten(),
            padded: padded.next().unwrap_or_default(),
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
        level,
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
        .reduce(|| (0, BlendCounts::default()), add_rows)
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
    /// Beside `id`, the entries' positions in the tile's list; empty where the render
    /// hands out no positions.
    at: &'a mut [u32],
}

/// One 64-byte line of f32 lanes: the scratch arrays are built from these so that every
/// blend group (4 or 16 lanes) sits inside one cache line.
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C, align(64))]
struct Line([f32; 16]);

const LINE: usize = 16;

/// One value per pixel of a tile, row-major.
type PixelLines = [Line; PIXEL_LINES];

/// A tile's per-pixel values as plain floats (a fixed length, so that one range check of a
/// group's offset serves every array).
fn pixels_mut(v: &mut PixelLines) -> &mut [f32; TILE_PIXELS] {
    bytemuck::cast_mut(v)
}

fn pixels(v: &PixelLines) -> &[f32; TILE_PIXELS] {
    bytemuck::cast_ref(v)
}

fn flat(v: &[Line]) -> &[f32] {
    bytemuck::cast_slice(v)
}

fn flat_mut(v: &mut [Line]) -> &mut [f32] {
    bytemuck::cast_slice_mut(v)
}

/// Scratch of one worker, reused across tiles and views: the per-pixel results of one tile
/// and its top-K lists (structure of arrays in SIMD units of N pixels: 4 x 1 with the
/// portable lanes, 4 x 4 with AVX-512), the per-unit splat lists, and the row-to-tile
/// bucketing buffers.
///
/// The per-pixel arrays are row-major over the tile's pixels. The lists are rank-major per
/// unit (`lw[(unit * K + r) * N + lane]` holds rank r of the unit's pixel `lane`), so
/// one insertion serves every lane of a unit that has a candidate with SIMD compares and
/// blends, without per-lane branches; the ranks past a group's longest list (`fill`) count
/// as padding (weight 0, [`NO_GAUSSIAN`]) whatever an earlier tile left there, so the
/// lists are never cleared, a list that is not full needs no per-lane count, and the K-th
/// rank is the bar a newcomer must beat. They reach the output once per tile.
#[derive(Debug, Default)]
struct TileScratch {
    /// Transmittance.
    t: PixelLines,
    /// Σ ω c per channel.
    r: PixelLines,
    g: PixelLines,
    b: PixelLines,
    /// Σ ω z.
    depth: PixelLines,
    /// Σ ω.
    wsum: PixelLines,
    /// Top-K weights, each list sorted by descending weight.
    lw: Vec<Line>,
    /// Beside `lw`, the entries' Gaussian ids (with `lists_carry_ids`) or the positions of
    /// their splats in the tile's list (`list_ids` maps them to Gaussian ids), as f32 bit
    /// patterns (only ever moved by blends); [`NO_GAUSSIAN`] for padding.
    lid: Vec<Line>,
    /// The lists carry Gaussian ids rather than positions: set for image outputs, which
    /// take no positions, so that the output is a plain transposition (one id lookup per
    /// insertion instead of one per output slot).
    lists_carry_ids: bool,
    /// K of the lists.
    k: usize,
    /// Per blend unit of one row (4 lanes): the splats of the tile that reach it, in depth
    /// order (see `blend_tile`).
    units: UnitLists,
    /// The tile's list as 4 x 4 units (16 lanes) select from it, and the positions of the
    /// entries one unit selected (see `blend_tile`).
    rects: TileRects,
    unit_positions: Vec<f32>,
    /// Per blend unit: its lists' ranks from this one on are padding in every lane (they
    /// were never written in this tile: the lists are not cleared between tiles).
    fill: Vec<u16>,
    /// The Gaussian ids of the tile's splats, in the order of its list.
    list_ids: Vec<u32>,
    tile_start: Vec<usize>,
    tile_entries: Vec<RowEntry>,
    /// One tile's lists in pixel-major form, for [`Rasterizer::render_tiles`].
    tile_ids: Vec<u32>,
    tile_positions: Vec<u32>,
    tile_weights: Vec<f32>,
    /// Blend counts of the current tile row (`counters` feature).
    counts: BlendCounts,
}

const PIXEL_LINES: usize = TILE_PIXELS / LINE;
const NO_ID_LINE: Line = Line([f32::from_bits(NO_GAUSSIAN); LINE]);
const ZERO_LINE: Line = Line([0.0; LINE]);

impl TileScratch {
    fn reset(&mut self, tiles_x: usize, k: usize) {
        self.k = k;
        self.lw.resize(PIXEL_LINES * k, ZERO_LINE);
        self.lid.resize(PIXEL_LINES * k, NO_ID_LINE);
        self.tile_start.resize(tiles_x + 1, 0);
    }
}

struct Ctx<'a> {
    splats: &'a [Splat],
    width: usize,
    height: usize,
    tiles_x: usize,
    k: usize,
    /// Only the top-K lists are wanted (no colour, depth, alpha or T, as registration
    /// renders): a pixel then stops as soon as its list is final (see `blend_unit`).
    lists_only: bool,
    opts: &'a RenderOptions,
    level: Level,
}

/// Renders the tiles of one tile row; returns its (tile, Gaussian) pair count and blend
/// counts.
fn render_row(
    ctx: &Ctx<'_>,
    entries: &[RowEntry],
    mut row: RowOut<'_>,
    st: &mut TileScratch,
) -> (usize, BlendCounts) {
    st.counts = BlendCounts::default();
    let tiles_x = ctx.tiles_x;
    let mut start = std::mem::take(&mut st.tile_start);
    let mut list = std::mem::take(&mut st.tile_entries);
    let total = bucket_by_tile(entries, tiles_x, &mut start, &mut list);
    let splats = ctx.splats;
    st.lists_carry_ids = true;

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
                at: &mut [],
            };
            // Cleared before the lists are touched and set once padding is complete, so
            // that the flag never claims more than the buffers hold.
            let flag = row.padded.get_mut(tx);
            let was_padded = flag.is_some_and(|p| std::mem::replace(p, false));
            if tile.is_empty() {
                // Nothing to sort or transpose: every list is padding (and still is where
                // the previous render left this tile empty).
                blend_tile_at::<false, false>(ctx, splats, tile, rect, st);
                if !was_padded {
                    pad_lists(&mut out, x1 - x0, y1 - y0);
                }
            } else {
                if ctx.lists_only {
                    blend_tile_at::<true, true>(ctx, splats, tile, rect, st);
                } else {
                    blend_tile_at::<true, false>(ctx, splats, tile, rect, st);
                }
                match ctx.level.lanes() {
                    4 => write_lists::<4>(&mut out, x1 - x0, y1 - y0, st),
                    _ => write_lists::<16>(&mut out, x1 - x0, y1 - y0, st),
                }
            }
            if let (true, Some(p)) = (tile.is_empty(), row.padded.get_mut(tx)) {
                *p = true;
            }
        } else {
            blend_tile_at::<false, false>(ctx, splats, tile, rect, st);
        }
        write_tile(ctx, &mut row, rect, st);
    }
    st.tile_start = start;
    st.tile_entries = list;
    (total, st.counts)
}

/// Buckets a tile row's splats (depth-sorted) by tile column, keeping the order: tile tx's
/// splats are `list[start[tx]..start[tx + 1]]`. Returns the (tile, splat) pair count.
fn bucket_by_tile(
    entries: &[RowEntry],
    tiles_x: usize,
    start: &mut Vec<usize>,
    list: &mut Vec<RowEntry>,
) -> usize {
    start.clear();
    start.resize(tiles_x + 1, 0);
    for (_, r) in entries {
        for tx in usize::from(r[0]) / TILE..usize::from(r[1]) / TILE + 1 {
            start[tx + 1] += 1;
        }
    }
    for tx in 0..tiles_x {
        start[tx + 1] += start[tx];
    }
    let total = start[tiles_x];
    list.clear();
    list.resize(total, (0, [0; 4]));
    let mut fill = start.clone();
    for &(e, r) in entries {
        for tx in usize::from(r[0]) / TILE..usize::from(r[1]) / TILE + 1 {
            list[fill[tx]] = (e, r);
            fill[tx] += 1;
        }
    }
    total
}

/// Renders the lists of one tile row tile by tile into the worker's tile buffers and hands
/// each tile to `consume` with the row's state; returns the row's (tile, splat) pair count.
fn consume_row<R, F>(
    ctx: &Ctx<'_>,
    entries: &[RowEntry],
    ty: usize,
    st: &mut TileScratch,
    state: &mut R,
    consume: &F,
) -> (usize, BlendCounts)
where
    F: Fn(&TileLists<'_>, &mut R),
{
    st.counts = BlendCounts::default();
    let (tiles_x, k, splats) = (ctx.tiles_x, ctx.k, ctx.splats);
    let mut start = std::mem::take(&mut st.tile_start);
    let mut list = std::mem::take(&mut st.tile_entries);
    let mut ids = std::mem::take(&mut st.tile_ids);
    let mut positions = std::mem::take(&mut st.tile_positions);
    let mut weights = std::mem::take(&mut st.tile_weights);
    ids.resize(TILE_PIXELS * k, NO_GAUSSIAN);
    positions.resize(TILE_PIXELS * k, NO_GAUSSIAN);
    weights.resize(TILE_PIXELS * k, 0.0);
    let total = bucket_by_tile(entries, tiles_x, &mut start, &mut list);
    st.lists_carry_ids = false;
    let y0 = ty * TILE;
    let y1 = (y0 + TILE).min(ctx.height);
    for tx in 0..tiles_x {
        let x0 = tx * TILE;
        let x1 = (x0 + TILE).min(ctx.width);
        let tile = &list[start[tx]..start[tx + 1]];
        let (cols, rows) = (x1 - x0, y1 - y0);
        let mut out = TopKOut {
            k,
            stride: TILE * k,
            base: 0,
            w: &mut weights,
            id: &mut ids,
            at: &mut positions,
        };
        if tile.is_empty() {
            pad_lists(&mut out, cols, rows);
            st.list_ids.clear();
        } else {
            blend_tile_at::<true, true>(ctx, splats, tile, [x0, x1, y0, y1], st);
            match ctx.level.lanes() {
                4 => write_lists::<4>(&mut out, cols, rows, st),
                _ => write_lists::<16>(&mut out, cols, rows, st),
            }
        }
        let lists = TileLists {
            x0,
            y0,
            width: cols,
            height: rows,
            k,
            ids: &ids,
            positions: &positions,
            splat_ids: &st.list_ids,
            weights: &weights,
        };
        consume(&lists, state);
    }
    st.tile_start = start;
    st.tile_entries = list;
    st.tile_ids = ids;
    st.tile_positions = positions;
    st.tile_weights = weights;
    (total, st.counts)
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
        if let Some(at) = out.at.get_mut(slots.clone()) {
            at.fill(NO_GAUSSIAN);
        }
        if let Some(id) = out.id.get_mut(slots) {
            id.fill(NO_GAUSSIAN);
        }
    }
}

/// Copies a finished tile's lists (padding included) from their rank-major SIMD form in
/// units of `N` lanes ([`UNIT_W`] x N / [`UNIT_W`] pixels) into the output's per-pixel
/// form, for the `cols` x `rows` pixels inside the image, with each entry's Gaussian id
/// (and, where `out` takes them, its position in the tile's list).
fn write_lists<const N: usize>(out: &mut TopKOut<'_>, cols: usize, rows: usize, st: &TileScratch) {
    let k = out.k;
    let unit_h = N / UNIT_W;
    let (lw, lid) = (flat(&st.lw), flat(&st.lid));
    let with_positions = !out.at.is_empty();
    for row in 0..rows {
        let slot = row * out.stride + out.base;
        let span = slot..slot + cols * k;
        let (Some(dw), Some(did)) = (out.w.get_mut(span.clone()), out.id.get_mut(span.clone()))
        else {
            continue;
        };
        let mut dat = if with_positions {
            out.at.get_mut(span)
        } else {
            None
        };
        // The row's pixels in runs of UNIT_W, one run per unit of this row.
        for (uc, run_start) in (0..cols).step_by(UNIT_W).enumerate() {
            let run_len = UNIT_W.min(cols - run_start);
            let unit = (row / unit_h) * UNITS_PER_ROW + uc;
            let lane0 = (row % unit_h) * UNIT_W;
            // Ranks from the unit's fill on are padding (not cleared in the scratch).
            let fill = st.fill.get(unit).map_or(0, |&f| usize::from(f)).min(k);
            let first = unit * k * N;
            let (Some(sw), Some(sid)) = (
                lw.get(first..first + fill * N),
                lid.get(first..first + fill * N),
            ) else {
                continue;
            };
            let pixels = run_start * k..(run_start + run_len) * k;
            let (Some(pw), Some(pid)) = (dw.get_mut(pixels.clone()), did.get_mut(pixels.clone()))
            else {
                continue;
            };
            // Rank-major (rank r of the unit's N pixels adjacent) to pixel-major, one
            // pixel's K slots at a time.
            for (lane, pw) in pw.chunks_exact_mut(k).enumerate() {
                transpose_lane::<N>(pw, sw, lane0 + lane, 0.0);
            }
            let pid_f: &mut [f32] = bytemuck::cast_slice_mut(pid);
            for (lane, pid) in pid_f.chunks_exact_mut(k).enumerate() {
                transpose_lane::<N>(pid, sid, lane0 + lane, f32::from_bits(NO_GAUSSIAN));
            }
            if st.lists_carry_ids {
                continue;
            }
            // The scratch held positions in the tile's list: hand them out where asked,
            // and map them to Gaussian ids (padding maps to padding).
            if let Some(pat) = dat.as_deref_mut().and_then(|d| d.get_mut(pixels)) {
                pat.copy_from_slice(pid);
            }
            for id in pid.iter_mut() {
                *id = st
                    .list_ids
                    .get(*id as usize)
                    .copied()
                    .unwrap_or(NO_GAUSSIAN);
            }
        }
    }
}

/// Fills one pixel's K slots `dst` from lane `lane` of the rank-major `src` (rank r at
/// `src[r * N + lane]`, as many ranks as `src` holds), then `pad`.
#[inline(always)]
fn transpose_lane<const N: usize>(dst: &mut [f32], src: &[f32], lane: usize, pad: f32) {
    if lane >= N {
        return;
    }
    let ranks = (src.len() / N).min(dst.len());
    let (head, tail) = dst.split_at_mut(ranks);
    for (d, rank) in head.iter_mut().zip(src.chunks_exact(N)) {
        *d = rank[lane];
    }
    for d in tail {
        *d = pad;
    }
}

/// [`blend_tile`] with the lane type of `ctx.level`.
#[allow(unsafe_code)]
fn blend_tile_at<const TOPK: bool, const CUTOFF: bool>(
    ctx: &Ctx<'_>,
    splats: &[Splat],
    list: &[RowEntry],
    rect: [usize; 4],
    st: &mut TileScratch,
) {
    match ctx.level {
        Level::Portable => blend_tile_portable::<TOPK, CUTOFF>(splats, list, rect, st),
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `Level::Avx512` is only ever chosen after the CPU was found to have
        // AVX-512 F and DQ (`Level::detect`, `Rasterizer::set_simd`).
        Level::Avx512 => unsafe { blend_tile_avx512::<TOPK, CUTOFF>(splats, list, rect, st) },
    }
}

/// The portable instantiation. (Not inlined: each instantiation stays a separate function,
/// which keeps the SIMD loop's register allocation independent of the caller and makes
/// profiles readable.)
#[inline(never)]
fn blend_tile_portable<const TOPK: bool, const CUTOFF: bool>(
    splats: &[Splat],
    list: &[RowEntry],
    rect: [usize; 4],
    st: &mut TileScratch,
) {
    blend_tile::<f32x4, TOPK, CUTOFF>(splats, list, rect, st);
}

/// The AVX-512 instantiation: compiled for those features, so the 16-lane operations
/// inline into it.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq")]
fn blend_tile_avx512<const TOPK: bool, const CUTOFF: bool>(
    splats: &[Splat],
    list: &[RowEntry],
    rect: [usize; 4],
    st: &mut TileScratch,
) {
    blend_tile::<F32x16, TOPK, CUTOFF>(splats, list, rect, st);
}

/// One entry of a blend unit's walk: a splat, as its position in the tile's list, and the
/// unit's lanes inside its footprint (those of its rectangle, or of its row span where
/// spans are solved; lane l in bit l).
#[derive(Debug, Clone, Copy)]
struct UnitEntry {
    at: u32,
    lanes: u32,
}

/// The per-unit splat lists of one tile in one buffer: unit u's entries are
/// `entries[u * stride..][..len[u]]`, where `stride` is the tile's list length (a splat
/// enters a unit at most once).
#[derive(Debug, Default)]
struct UnitLists {
    entries: Vec<UnitEntry>,
    len: Vec<usize>,
    stride: usize,
}

impl UnitLists {
    /// Empties `units` lists for a tile of `list_len` splats.
    fn reset(&mut self, units: usize, list_len: usize) {
        self.stride = list_len;
        let need = units * self.stride;
        if self.entries.len() < need {
            self.entries.resize(need, UnitEntry { at: 0, lanes: 0 });
        }
        self.len.clear();
        self.len.resize(units, 0);
    }

    #[inline(always)]
    fn push(&mut self, unit: usize, entry: UnitEntry) {
        if let Some(len) = self.len.get_mut(unit) {
            if let Some(slot) = self.entries.get_mut(unit * self.stride + *len) {
                *slot = entry;
                *len += 1;
            }
        }
    }

    fn get(&self, unit: usize) -> &[UnitEntry] {
        let len = self.len.get(unit).copied().unwrap_or(0);
        self.entries
            .get(unit * self.stride..unit * self.stride + len)
            .unwrap_or(&[])
    }
}

/// Front-to-back blend of one tile's depth-sorted splats.
///
/// The tile's pixels are cut into units of N pixels: [`UNIT_W`] adjacent columns of
/// N / [`UNIT_W`] adjacent rows (4 x 4 with 16 lanes, 4 x 1 with 4). Each unit walks the
/// splats that reach it in depth order with its whole state (transmittance, colour, depth
/// and weight sums, stopped lanes, the K-th weight) in registers, and stops as soon as
/// every pixel of it has stopped. Walking splats per unit rather than units per splat
/// keeps that state out of memory between blends, so the only chain from one splat to the
/// next is T's few operations and the exponentials of later splats overlap the current
/// one.
///
/// How a unit finds its splats depends on its shape. A 4 x 4 unit selects them from the
/// tile's list just before its walk, testing 16 entries' rectangles at once and packing
/// the positions of those that reach it ([`TileRects`]): no branch per entry, where
/// appending every splat to the list of each unit it reaches took a third of the time of
/// the walks on `fuse bench`'s scene. A unit of one row gets its list from
/// [`distribute_rows`], which cuts each splat to its ellipse's span in every row: with
/// 4-lane compares, selecting would cost more than it saves.
#[inline(always)]
fn blend_tile<V: Lanes, const TOPK: bool, const CUTOFF: bool>(
    splats: &[Splat],
    list: &[RowEntry],
    [x0, x1, y0, y1]: [usize; 4],
    st: &mut TileScratch,
) {
    let unit_h = V::N / UNIT_W;
    let n_units = TILE_PIXELS / V::N;
    st.fill.resize(n_units, 0);
    // Only top-K lists name their splats (by position; the ids come with the output).
    let ids = if TOPK { Some(&mut st.list_ids) } else { None };
    if unit_h > 1 {
        st.rects.build(splats, list, [x0, x1, y0, y1], ids);
    } else {
        st.units.reset(n_units, list.len());
        distribute_rows(splats, list, [x0, x1, y0, y1], &mut st.units, ids);
    }
    let (units, rects, selected) = (&st.units, &st.rects, &mut st.unit_positions);
    let k = st.k;
    let mut out = UnitOut {
        t: pixels_mut(&mut st.t),
        r: pixels_mut(&mut st.r),
        g: pixels_mut(&mut st.g),
        b: pixels_mut(&mut st.b),
        depth: pixels_mut(&mut st.depth),
        wsum: pixels_mut(&mut st.wsum),
        lw: flat_mut(&mut st.lw),
        lid: flat_mut(&mut st.lid),
        ids: st.lists_carry_ids.then_some(&st.list_ids[..]),
        fill: &mut st.fill,
        k,
        counts: &mut st.counts,
    };
    for u in 0..n_units {
        let (r0, c0) = ((u / UNITS_PER_ROW) * unit_h, (u % UNITS_PER_ROW) * UNIT_W);
        if y0 + r0 >= y1 || x0 + c0 >= x1 {
            continue;
        }
        // Lanes inside the image (the tiles at the right and bottom edges may be smaller).
        let (cols, rows) = ((x1 - x0 - c0).min(UNIT_W), (y1 - y0 - r0).min(unit_h));
        let valid = V::from_bits(bit_range(0, cols - 1) * spread_rows(bit_range(0, rows - 1)));
        let place = [x0 + c0, y0 + r0];
        let at = [u, r0 * TILE + c0];
        if unit_h > 1 {
            let n = rects.select::<V>(u, selected);
            let entries = selected[..n].iter().map(|p| {
                let at = p.to_bits();
                UnitEntry {
                    at,
                    lanes: rects.lanes(at, u),
                }
            });
            blend_unit::<V, TOPK, CUTOFF>(splats, list, entries, place, valid, at, &mut out);
        } else {
            let entries = units.get(u).iter().copied();
            blend_unit::<V, TOPK, CUTOFF>(splats, list, entries, place, valid, at, &mut out);
        }
    }
}

/// A tile's list as the 4 x 4 units select from it ([`TileRects::select`]): per entry, the
/// units its rectangle (clipped to the tile) reaches, as bits (unit u in bit u) in an f32
/// bit pattern, so that one integer test checks 16 entries against a unit; its position,
/// also as an f32 bit pattern (both only moved and tested, never computed with); and its
/// rectangle's columns and rows as bits over the tile's 16 (whose nibbles are a unit's
/// lanes). Padded to a multiple of 16 with entries that reach no unit.
#[derive(Debug, Default)]
struct TileRects {
    units: Vec<f32>,
    positions: Vec<f32>,
    /// Column bits in the low 16 bits, row bits in the high 16.
    cols_rows: Vec<u32>,
}

impl TileRects {
    /// The rectangles of the tile `[x0, x1) x [y0, y1)`'s `list`; `ids`, if given, receives
    /// the Gaussian id of every position of the list.
    fn build(
        &mut self,
        splats: &[Splat],
        list: &[RowEntry],
        [x0, x1, y0, y1]: [usize; 4],
        ids: Option<&mut Vec<u32>>,
    ) {
        self.units.clear();
        self.positions.clear();
        self.cols_rows.clear();
        for_each_clipped(
            splats,
            list,
            [x0, x1, y0, y1],
            ids,
            |_, _, clipped| match clipped {
                Some([cx0, cx1, cy0, cy1]) => {
                    self.push([cx0 - x0, cx1 - x0, cy0 - y0, cy1 - y0]);
                }
                None => self.push_nowhere(),
            },
        );
        while !self.units.len().is_multiple_of(16) {
            self.push_nowhere();
        }
    }

    /// Appends an entry with the tile-local rectangle `[c0, c1, r0, r1]` (inclusive, inside
    /// the tile).
    fn push(&mut self, [c0, c1, r0, r1]: [usize; 4]) {
        let (cols, rows) = (bit_range(c0, c1), bit_range(r0, r1));
        // A tile's unit rows are UNITS_PER_ROW = 4 bits apart in `units`, as a unit's rows
        // of lanes are in its lanes: the same spreading.
        let unit_rows = bit_range(r0 / UNIT_W, r1 / UNIT_W);
        let units = bit_range(c0 / UNIT_W, c1 / UNIT_W) * spread_rows(unit_rows);
        self.push_bits(units, cols | rows << 16);
    }

    /// Appends an entry that reaches no unit.
    fn push_nowhere(&mut self) {
        self.push_bits(0, 0);
    }

    fn push_bits(&mut self, units: u32, cols_rows: u32) {
        // A list's positions are u32 (its splats are).
        let at = self.units.len() as u32;
        self.units.push(f32::from_bits(units));
        self.positions.push(f32::from_bits(at));
        self.cols_rows.push(cols_rows);
    }

    /// The positions (as f32 bit patterns) of the entries that reach unit `u` (of 4 x 4
    /// pixels; u = 4 · unit row + unit column) in list order, tested [`Lanes::N`] at a
    /// time and packed without a branch per entry into `out`; returns their count.
    #[inline(always)]
    fn select<V: Lanes>(&self, u: usize, out: &mut Vec<f32>) -> usize {
        // Room for a whole vector past the last entry.
        out.resize(self.units.len() + V::N, 0.0);
        let mut n = 0;
        let chunks = self
            .units
            .chunks_exact(V::N)
            .zip(self.positions.chunks_exact(V::N));
        for (units, at) in chunks {
            let reached = V::load(units).any_bits(1 << u);
            n += V::load(at).compress_store(reached, &mut out[n..]);
        }
        n
    }

    /// The lanes of unit `u` inside the rectangle of the entry at `at` (lane l = row
    /// l / 4, column l mod 4 of the unit, in bit l).
    #[inline(always)]
    fn lanes(&self, at: u32, u: usize) -> u32 {
        let (ur, uc) = (u / UNITS_PER_ROW, u % UNITS_PER_ROW);
        let Some(&cr) = self.cols_rows.get(at as usize) else {
            return 0;
        };
        let c = cr >> (uc * UNIT_W) & 0xF;
        let r = cr >> (16 + ur * UNIT_W) & 0xF;
        c * spread_rows(r)
    }
}

/// Four row bits (rows 0-3 of a unit; a unit of one row has only bit 0) spread to bits 0,
/// 4, 8 and 12: times a row's column bits (< 2^UNIT_W) it repeats them in each of those
/// rows.
#[inline(always)]
fn spread_rows(r: u32) -> u32 {
    (r & 1) | ((r & 2) << 3) | ((r & 4) << 6) | ((r & 8) << 9)
}

/// Appends each splat of the tile's list to the lists of the units of one row (4 lanes)
/// its footprint reaches, with the unit's lanes in the row's span of the α >= 1/255
/// ellipse (the whole rectangle row where the spans cannot be trusted), so that units
/// the ellipse misses get no entry. The pixels of an entry's lanes outside the ellipse
/// fail the alpha test. Entries name their splat by its position in the list; `ids`, if
/// given, receives the Gaussian id of every position.
#[inline(always)]
fn distribute_rows(
    splats: &[Splat],
    list: &[RowEntry],
    [x0, x1, y0, y1]: [usize; 4],
    units: &mut UnitLists,
    ids: Option<&mut Vec<u32>>,
) {
    for_each_clipped(splats, list, [x0, x1, y0, y1], ids, |i, e, clipped| {
        let (Some([cx0, cx1, cy0, cy1]), Some(sp)) = (clipped, splats.get(e as usize)) else {
            return;
        };
        // A tile's list holds each splat at most once, and splat ids are u32: fits.
        let at = i as u32;
        for py in cy0..cy1 + 1 {
            let span = if sp.inv_a > 0.0 {
                row_span(sp, py, cx0, cx1)
            } else {
                Some((cx0, cx1))
            };
            let Some((lo, hi)) = span.map(|(lo, hi)| (lo - x0, hi - x0)) else {
                continue;
            };
            // lo..=hi are tile-local columns.
            for uc in lo / UNIT_W..hi / UNIT_W + 1 {
                let c0 = uc * UNIT_W;
                let (first, last) = (lo.max(c0) - c0, hi.min(c0 + UNIT_W - 1) - c0);
                let lanes = bit_range(first, last);
                units.push((py - y0) * UNITS_PER_ROW + uc, UnitEntry { at, lanes });
            }
        }
    });
}

/// Goes through a tile's list in order: asks for the splat [`PREFETCH_AHEAD`] entries
/// ahead (the list's splats are scattered over the view's: depth order, not screen
/// order), records every entry's Gaussian id in `ids` (if given; cleared first), and
/// calls `f(position, splat index, rectangle)` with the entry's rectangle clipped to the
/// tile `[x0, x1) x [y0, y1)` (image pixels, inclusive; `None` where it misses the tile).
#[inline(always)]
fn for_each_clipped(
    splats: &[Splat],
    list: &[RowEntry],
    [x0, x1, y0, y1]: [usize; 4],
    mut ids: Option<&mut Vec<u32>>,
    mut f: impl FnMut(usize, u32, Option<[usize; 4]>),
) {
    if let Some(ids) = ids.as_deref_mut() {
        ids.clear();
    }
    for (i, &(e, rect)) in list.iter().enumerate() {
        if let Some(ahead) = list
            .get(i + PREFETCH_AHEAD)
            .and_then(|&(a, _)| splats.get(a as usize))
        {
            prefetch(ahead);
        }
        if let Some(ids) = ids.as_deref_mut() {
            ids.push(splats.get(e as usize).map_or(NO_GAUSSIAN, |sp| sp.id));
        }
        let [rx0, rx1, ry0, ry1] = rect.map(usize::from);
        let (cx0, cx1) = (rx0.max(x0), rx1.min(x1 - 1));
        let (cy0, cy1) = (ry0.max(y0), ry1.min(y1 - 1));
        let clipped = (cx0 <= cx1 && cy0 <= cy1).then_some([cx0, cx1, cy0, cy1]);
        f(i, e, clipped);
    }
}

/// The columns of image row `py` within `cx0..=cx1` where `sp` may reach α >= 1/255:
/// the pixels with ½ dᵀ C d <= tau (tau has a margin, see `Splat`), from the quadratic in
/// dx, widened by SPAN_SLACK for rounding; `None` when there are none.
#[inline(always)]
fn row_span(sp: &Splat, py: usize, cx0: usize, cx1: usize) -> Option<(usize, usize)> {
    let dy = sp.y - (py as f32 + 0.5);
    let disc = sp.two_a_tau - sp.det * dy * dy;
    if disc.is_nan() || disc < 0.0 {
        return None;
    }
    let half = disc.sqrt() * sp.inv_a;
    let mid = sp.x - 0.5 + sp.b * dy * sp.inv_a;
    let (lo_f, hi_f) = (mid - half - SPAN_SLACK, mid + half + SPAN_SLACK);
    // ceil and floor without libm calls (the bounds are within [cx0, cx1] here, so the
    // casts are exact truncations of small non-negative values).
    if hi_f < cx0 as f32 || lo_f > cx1 as f32 {
        return None;
    }
    let lo = if lo_f > cx0 as f32 {
        let t = lo_f as i32;
        t + i32::from((t as f32) < lo_f)
    } else {
        cx0 as i32
    };
    let hi = (hi_f as i32).min(cx1 as i32);
    if hi < lo {
        return None;
    }
    Some((lo as usize, hi as usize))
}

/// The power below which no Gaussian reaches α >= 1/255: exp(−40) = 4.2e-18, far below
/// 1/255 even at opacity 1 (opacities are sigmoids, <= 1).
const POWER_FLOOR: f32 = -40.0;

/// How many list entries ahead [`for_each_clipped`] prefetches a splat (at 6 the id reads
/// of `TileRects::build` waited on memory; 16 and 32 measured alike).
const PREFETCH_AHEAD: usize = 16;

/// Extra width, in pixels, of each per-row span beyond the solved ellipse bounds: far above
/// the f32 rounding of those bounds (the exponent margin of `Splat::two_a_tau` adds more).
const SPAN_SLACK: f32 = 1.0 / 64.0;

/// Where a unit's results go: the tile's per-pixel arrays (row-major) and its top-K lists.
struct UnitOut<'a> {
    t: &'a mut [f32; TILE_PIXELS],
    r: &'a mut [f32; TILE_PIXELS],
    g: &'a mut [f32; TILE_PIXELS],
    b: &'a mut [f32; TILE_PIXELS],
    depth: &'a mut [f32; TILE_PIXELS],
    wsum: &'a mut [f32; TILE_PIXELS],
    lw: &'a mut [f32],
    lid: &'a mut [f32],
    /// The Gaussian ids by list position where the lists carry ids, else `None`.
    ids: Option<&'a [u32]>,
    fill: &'a mut [u16],
    k: usize,
    #[cfg_attr(not(feature = "counters"), allow(dead_code))]
    counts: &'a mut BlendCounts,
}

/// The running state of one unit's N pixels.
struct UnitState<V: Lanes> {
    t: V,
    r: V,
    g: V,
    b: V,
    depth: V,
    wsum: V,
    /// Lanes that have stopped (T would fall below 1e-4, or the list is final) or lie
    /// outside the image.
    done: V::Mask,
}

/// One unit (number `unit` of the tile, whose top-left pixel is image pixel (`px0`, `py0`)
/// and tile pixel `at`) over the `entries` that reach it, front to back (taken [`BATCH`]
/// at a time, and no more once every lane has stopped): INRIA's per-pixel step on all
/// lanes at once (lanes outside an entry's footprint masked off). With `TOPK`, pixels
/// whose weight beats their list's K-th enter their top-K list; with `CUTOFF` (lists only)
/// a pixel also stops once its list is final. Writes T, the sums and the lists into
/// `out`.
#[inline(always)]
fn blend_unit<V: Lanes, const TOPK: bool, const CUTOFF: bool>(
    splats: &[Splat],
    list: &[RowEntry],
    mut entries: impl Iterator<Item = UnitEntry>,
    [px0, py0]: [usize; 2],
    valid: V::Mask,
    [unit, at]: [usize; 2],
    out: &mut UnitOut<'_>,
) {
    let n = V::N;
    let zero = V::splat(0.0);
    let mut s = UnitState::<V> {
        t: V::splat(1.0),
        r: zero,
        g: zero,
        b: zero,
        depth: zero,
        wsum: zero,
        done: !valid,
    };
    let all = V::bits(V::span(0, n - 1));
    let k = out.k;
    let lists = unit * n * k..(unit + 1) * n * k;
    let (Some(lw), Some(lid)) = (out.lw.get_mut(lists.clone()), out.lid.get_mut(lists)) else {
        return;
    };
    // The K-th weights of the lists (0 while not full), and the ranks from `fill` on that
    // are padding in every lane (the longest list's length): those ranks still hold an
    // earlier tile's entries, which `insert_group` and `write_lists` never read.
    let mut kth = zero;
    let mut fill = 0usize;
    let px = V::splat(px0 as f32) + V::unit_columns();
    let py = V::splat(py0 as f32) + V::unit_rows();
    // Entries go in batches: first every α of the batch (long chains of exp, independent of
    // the unit's state, so they overlap), then the compositing in depth order (short
    // chains through T). One entry at a time, the out-of-order window held only about two
    // of those exp chains.
    let mut alpha = [zero; BATCH];
    let mut reach = [V::from_bits(0); BATCH];
    let mut pending = [UnitEntry { at: 0, lanes: 0 }; BATCH];
    'walk: loop {
        let mut len = 0;
        for slot in &mut pending {
            let Some(e) = entries.next() else {
                break;
            };
            *slot = e;
            len += 1;
        }
        let batch = &pending[..len];
        for ((e, a), m) in batch.iter().zip(&mut alpha).zip(&mut reach) {
            let lanes = V::from_bits(e.lanes) & !s.done;
            *m = lanes;
            if V::bits(lanes) == 0 {
                continue;
            }
            if let Some(sp) = splat_at(splats, list, e.at) {
                (*a, *m) = footprint_alpha::<V>(sp, lanes, px, py);
            }
        }
        for ((e, &a), &m) in batch.iter().zip(&alpha).zip(&reach) {
            // Lanes in the footprint, with α >= 1/255, not stopped.
            let ok = m & !s.done;
            #[cfg(feature = "counters")]
            let live = V::from_bits(e.lanes) & !s.done;
            #[cfg(feature = "counters")]
            if V::bits(live) != 0 {
                out.counts.groups += 1;
                out.counts.live_lanes += u64::from(V::bits(live).count_ones());
            }
            if V::bits(ok) == 0 {
                // Every lane would add ω = 0 and keep its T, list and state.
                continue;
            }
            // Lists-only renders read nothing of the splat here (its position is the list
            // entry); the others add its colour and depth.
            let shading = if CUTOFF {
                None
            } else {
                let Some(sp) = splat_at(splats, list, e.at) else {
                    continue;
                };
                Some(sp)
            };
            let (stop, w) = composite::<V>(a, ok, shading, &mut s);
            #[cfg(feature = "counters")]
            {
                out.counts.blends += u64::from(V::bits(w.gt(zero)).count_ones());
            }
            s.done = s.done | stop;
            if TOPK {
                // Lanes whose weight beats the pixel's K-th (0 while the list is not full);
                // usually few, often none.
                let cand = w.gt(kth);
                if V::bits(cand) != 0 {
                    #[cfg(feature = "counters")]
                    {
                        out.counts.inserted += u64::from(V::bits(cand).count_ones());
                    }
                    let payload = match out.ids {
                        Some(ids) => ids.get(e.at as usize).copied().unwrap_or(NO_GAUSSIAN),
                        None => e.at,
                    };
                    let id = V::splat(f32::from_bits(payload));
                    kth = insert_group::<V>(lw, lid, k, fill, cand, w, id);
                    // One more entry in each candidate lane (or one replaced when full).
                    fill = (fill + 1).min(k);
                }
                if CUTOFF {
                    // A later contributor weighs ω = T·α < T (α <= 0.99, T never grows), so
                    // once T <= the K-th weight of a full list (> 0) nothing can enter: the
                    // pixel's list is final and it stops here.
                    let full = kth.gt(zero);
                    s.done = s.done | (full & s.t.le(kth));
                }
            }
            if V::bits(s.done) == all {
                break 'walk;
            }
        }
        if len < BATCH {
            break;
        }
    }
    if let Some(f) = out.fill.get_mut(unit) {
        // At most K <= MAX_TOP_K: fits.
        *f = fill as u16;
    }
    store_unit(s.t, out.t, at);
    if !CUTOFF {
        store_unit(s.r, out.r, at);
        store_unit(s.g, out.g, at);
        store_unit(s.b, out.b, at);
        store_unit(s.depth, out.depth, at);
        store_unit(s.wsum, out.wsum, at);
    }
}

/// Stores a unit's lanes into a row-major tile array, from tile pixel `at` (its top-left):
/// [`UNIT_W`] lanes per row.
#[inline(always)]
fn store_unit<V: Lanes>(v: V, dst: &mut [f32; TILE_PIXELS], at: usize) {
    let mut lanes = [0f32; 16];
    v.store(&mut lanes);
    for (j, row) in lanes[..V::N].chunks_exact(UNIT_W).enumerate() {
        if let Some(d) = dst.get_mut(at + j * TILE..at + j * TILE + UNIT_W) {
            d.copy_from_slice(row);
        }
    }
}

/// Inserts (w, id) into the sorted lists of the lanes in `cand` of one group (`lw[r * N..]`,
/// `lid[r * N..]`: rank r of the N lists) whose ranks from `fill` on are padding in every
/// lane (whatever they hold: rank `fill` is read as padding, and later ranks are not
/// read); returns the new K-th weights (0 while the lists are not full). One pass from
/// the first rank to the new last one rewrites every rank in every lane, with no branch
/// on the data: rank r takes the entry carried down from above in the candidate lanes
/// whose newcomer outweighs its entry (the newcomer at the first such rank, then each
/// displaced entry one rank lower) and keeps its entry elsewhere. A newcomer goes after
/// the entries of equal weight (strict >), so ties keep depth order, and a full list
/// drops its last entry: the same lists as inserting one pixel at a time. (The pass
/// always walks every rank, so its loop exit is as predictable as the fill; stopping at
/// the first rank no lane shifts into cost a mispredicted exit a call, which was more.)
#[inline(always)]
fn insert_group<V: Lanes>(
    lw: &mut [f32],
    lid: &mut [f32],
    k: usize,
    fill: usize,
    cand: V::Mask,
    w: V,
    id: V,
) -> V {
    let n = V::N;
    let kept = fill.min(k);
    let (Some(lw), Some(lid)) = (lw.get_mut(..k * n), lid.get_mut(..k * n)) else {
        return V::splat(0.0);
    };
    let (mut carry_w, mut carry_id) = (w, id);
    let mut last_w = V::splat(0.0);
    for (rw, rid) in lw
        .chunks_exact_mut(n)
        .zip(lid.chunks_exact_mut(n))
        .take(kept)
    {
        let (old_w, old_id) = (V::load(rw), V::load(rid));
        let shift = cand & w.gt(old_w);
        last_w = V::select(shift, carry_w, old_w);
        last_w.store(rw);
        V::select(shift, carry_id, old_id).store(rid);
        carry_w = V::select(shift, old_w, carry_w);
        carry_id = V::select(shift, old_id, carry_id);
    }
    if kept < k {
        // Rank `fill` is padding in every lane: the candidates' carried entries land
        // there, the other lanes get explicit padding.
        let (Some(rw), Some(rid)) = (lw.get_mut(kept * n..), lid.get_mut(kept * n..)) else {
            return V::splat(0.0);
        };
        let tail_w = V::select(cand, carry_w, V::splat(0.0));
        tail_w.store(rw);
        V::select(cand, carry_id, V::splat(f32::from_bits(NO_GAUSSIAN))).store(rid);
        // The new K-th weights once this rank is the last one.
        return if kept + 1 < k { V::splat(0.0) } else { tail_w };
    }
    last_w
}

/// Entries whose α [`blend_unit`] computes ahead of compositing them.
const BATCH: usize = 8;

/// The splat at position `at` of a tile's list.
#[inline(always)]
fn splat_at<'a>(splats: &'a [Splat], list: &[RowEntry], at: u32) -> Option<&'a Splat> {
    list.get(at as usize)
        .and_then(|&(e, _)| splats.get(e as usize))
}

/// The first half of INRIA's per-pixel step of splat `sp` for the N pixels of a unit, whose
/// centres are (`px`, `py`) lane by lane: power = −½(a dx² + c dy²) − b dx dy,
/// α = min(0.99, o·exp(power)); returns α and the lanes of `lanes` with power <= 0 and
/// α >= 1/255. Every lane performs the same IEEE operations in the same order as the
/// scalar reference.
#[inline(always)]
fn footprint_alpha<V: Lanes>(sp: &Splat, lanes: V::Mask, px: V, py: V) -> (V, V::Mask) {
    let dy = V::splat(sp.y) - py;
    // c·dy·dy rounds exactly as inside the scalar power expression.
    let cdy = V::splat(sp.c) * dy * dy;
    let dx = V::splat(sp.x) - px;
    let power = V::splat(-0.5) * (V::splat(sp.a) * dx * dx + cdy) - V::splat(sp.b) * dx * dy;
    // Below POWER_FLOOR every α fails the 1/255 test (opacity <= 1), so raising power to
    // it changes no contribution; it keeps o·exp(power) out of the subnormal range, whose
    // products cost a microcode assist each on x86 (the far corners of a thin splat's
    // rectangle reach powers of −1000 and below).
    // Lanes with power > 0 are never drawn, so power is also capped at 0: exp then needs no
    // clamps of its own (bit-identical to math::exp on [−40, 0]).
    let e = power.max_c(POWER_FLOOR).min_c(0.0).exp_in_range();
    let alpha = (V::splat(sp.opacity) * e).min_c(ALPHA_MAX);
    let ok = lanes & power.le(V::splat(0.0)) & alpha.ge(V::splat(ALPHA_MIN));
    (alpha, ok)
}

/// The second half of the per-pixel step, on the lanes `ok` (in the footprint, α >= 1/255,
/// not stopped): stop if T(1 − α) < 1e-4, else ω = T·α, T becomes T(1 − α) and (with a
/// `shading` splat) the sums grow by ω times its colour and depth. Other lanes add ω = 0 (the sums are finite and >= 0, so
/// x + 0 = x bit for bit): the result equals a scalar per-pixel loop exactly. Returns the
/// lanes that stopped and the weights (0 outside the contributing lanes).
#[inline(always)]
fn composite<V: Lanes>(
    alpha: V,
    ok: V::Mask,
    shading: Option<&Splat>,
    s: &mut UnitState<V>,
) -> (V::Mask, V) {
    let test_t = s.t * (V::splat(1.0) - alpha);
    let low = test_t.lt(V::splat(T_MIN));
    let contrib = ok & !low;
    let w = V::select(contrib, alpha * s.t, V::splat(0.0));
    if let Some(sp) = shading {
        s.r = s.r + V::splat(sp.color[0]) * w;
        s.g = s.g + V::splat(sp.color[1]) * w;
        s.b = s.b + V::splat(sp.color[2]) * w;
        s.depth = s.depth + V::splat(sp.depth) * w;
        s.wsum = s.wsum + w;
    }
    s.t = V::select(contrib, test_t, s.t);
    (ok & low, w)
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
        let t = &pixels(&st.t)[src.clone()];
        if let Some(c) = row.color.as_deref_mut() {
            let it = pixels(&st.r)[src.clone()]
                .iter()
                .zip(&pixels(&st.g)[src.clone()])
                .zip(&pixels(&st.b)[src.clone()])
                .zip(t);
            for (dst, (((r, g), b), t)) in c[o * 3..(o + nx) * 3].chunks_exact_mut(3).zip(it) {
                dst[0] = r + t * bg[0];
                dst[1] = g + t * bg[1];
                dst[2] = b + t * bg[2];
            }
        }
        if let Some(dd) = row.depth.as_deref_mut() {
            let it = pixels(&st.depth)[src.clone()]
                .iter()
                .zip(&pixels(&st.wsum)[src.clone()]);
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
    use super::{
        bucket_by_row, depth_key, f32x4, insert_group, key_position, sort_by_depth, ChunkRecords,
        DepthRecord, Lanes, Level, RowEntry, TileRects, NO_GAUSSIAN, TILE, TILE_PIXELS, UNIT_W,
    };

    /// A small LCG: deterministic test values below `m`.
    fn lcg(seed: u64) -> impl FnMut(u32) -> u32 {
        let mut state = seed;
        move |m| {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            ((state >> 33) as u32) % m
        }
    }

    /// Chunks of records as the projection makes them: positions ascending within and
    /// across chunks, depths from `depth`.
    fn chunks_of(sizes: &[usize], mut depth: impl FnMut() -> f32) -> Vec<ChunkRecords> {
        let mut position = 0u32;
        sizes
            .iter()
            .map(|&n| {
                let records: Vec<DepthRecord> = (0..n)
                    .map(|_| {
                        position += 3; // gaps, as where a chunk keeps few of its Gaussians
                        let d = depth();
                        DepthRecord {
                            key: depth_key(d, position),
                            rect: [position as u16, 0, 0, 0],
                        }
                    })
                    .collect();
                let bits = records.iter().map(|r| (r.key >> 32) as u32);
                let depth_bits = bits.clone().min().zip(bits.max());
                ChunkRecords {
                    records,
                    depth_bits,
                }
            })
            .collect()
    }

    /// Sorted by (depth, id), with the ids a shuffle of the positions (slots are not in id
    /// order), so that ties need their own ordering.
    #[test]
    fn sort_by_depth_equals_a_plain_sort_by_depth_then_id() {
        let mut next = lcg(7);
        type Depths = Box<dyn FnMut(&mut dyn FnMut(u32) -> u32) -> f32>;
        let cases: Vec<(&str, Vec<usize>, Depths)> = vec![
            (
                "uniform",
                vec![5000, 3000, 0, 7000],
                Box::new(|n| 1.0 + n(1 << 20) as f32 * 1e-5),
            ),
            (
                "many ties",
                vec![4000, 4000],
                Box::new(|n| 0.5 * (1 + n(7)) as f32),
            ),
            ("one depth", vec![900, 100], Box::new(|_| 3.25)),
            (
                "binades apart",
                vec![2000; 5],
                Box::new(|n| [1e-3, 0.7, 2.0, 1e4][n(4) as usize] * (1.0 + n(1000) as f32 * 1e-3)),
            ),
            ("few", vec![1, 0, 2], Box::new(|n| n(5) as f32 + 0.1)),
            ("none", vec![0, 0], Box::new(|_| 1.0)),
            (
                "many chunks",
                vec![300; 37],
                Box::new(|n| 0.2 + n(1 << 16) as f32 * 1e-3),
            ),
        ];
        for (name, sizes, mut depth) in cases {
            let chunks = chunks_of(&sizes, || depth(&mut next));
            // Positions go up to 3 x the records (`chunks_of`); their ids are a shuffle.
            let positions = 3 * sizes.iter().sum::<usize>() + 1;
            let mut ids: Vec<u32> = (0..positions as u32).collect();
            for i in (1..positions).rev() {
                ids.swap(i, next(i as u32 + 1) as usize);
            }
            let id = |r: &DepthRecord| ids[key_position(r.key) as usize];
            let mut want: Vec<DepthRecord> =
                chunks.iter().flat_map(|c| c.records.clone()).collect();
            want.sort_unstable_by_key(|r| (r.key >> 32, id(r)));
            // A stale, longer buffer from an earlier view.
            let stale = DepthRecord {
                key: 5,
                rect: [7; 4],
            };
            let mut got = vec![stale; 20_000];
            sort_by_depth(&chunks, |p| ids[p as usize], &mut got);
            assert_eq!(got, want, "{name}");
        }
    }

    #[test]
    fn depth_keys_order_by_depth_then_position_and_round_trip() {
        let last = u32::MAX;
        let mut keys = vec![
            (depth_key(2.0, 5), 5),
            (depth_key(0.25, last), last),
            (depth_key(1.0, 70_000), 70_000),
            (depth_key(1.0, 16_383), 16_383),
            (depth_key(1.0, 4), 4),
            (depth_key(1.0e30, 0), 0),
        ];
        keys.sort_unstable();
        let order: Vec<u32> = keys.iter().map(|k| k.1).collect();
        assert_eq!(
            order,
            [last, 4, 16_383, 70_000, 5, 0],
            "depth first, equal depths by position"
        );
        for (key, position) in keys {
            assert_eq!(key_position(key), position);
        }
    }

    /// Sequential reference: every splat appended to each tile row its rectangle spans.
    fn rows_by_sequential_append(splats: &[DepthRecord], tiles_y: usize) -> Vec<Vec<RowEntry>> {
        let mut rows = vec![Vec::new(); tiles_y];
        for r in splats {
            let (top, bottom) = (usize::from(r.rect[2]) / TILE, usize::from(r.rect[3]) / TILE);
            for row in &mut rows[top..=bottom] {
                row.push((key_position(r.key), r.rect));
            }
        }
        rows
    }

    #[test]
    fn row_buckets_equal_sequential_append_for_any_block_size() {
        let tiles_y = 9;
        let height = (tiles_y * TILE) as u32;
        // Deterministic rectangles of every height, some on tile borders.
        let mut next = lcg(0x2545_f491_4f6c_dd1d);
        // Keys are arbitrary: the buckets keep the given (depth) order.
        let splats: Vec<DepthRecord> = (0..500)
            .map(|_| {
                let y0 = next(height);
                let y1 = (y0 + next(3 * TILE as u32 + 1)).min(height - 1);
                let x0 = next(200);
                let rect = [x0 as u16, (x0 + next(40)) as u16, y0 as u16, y1 as u16];
                let key = depth_key(1.0 + next(9) as f32, next(100_000));
                DepthRecord { key, rect }
            })
            .collect();
        let want = rows_by_sequential_append(&splats, tiles_y);
        for block in [1, 3, 64, 499, 500, 1 << 16] {
            // Stale, longer buffers from an earlier view.
            let (mut start, mut entries) = (vec![7], vec![(9, [1; 4]); 2000]);
            bucket_by_row(&splats, tiles_y, block, &mut start, &mut entries);
            assert_eq!(start.len(), tiles_y + 1, "block {block}");
            for (ty, row) in want.iter().enumerate() {
                assert_eq!(
                    &entries[start[ty]..start[ty + 1]],
                    &row[..],
                    "block {block}, row {ty}"
                );
            }
            assert_eq!(entries.len(), want.iter().map(Vec::len).sum::<usize>());
        }
        // No splats: every row empty.
        let (mut start, mut entries) = (Vec::new(), Vec::new());
        bucket_by_row(&[], tiles_y, 4, &mut start, &mut entries);
        assert_eq!((start, entries.len()), (vec![0; tiles_y + 1], 0));
    }

    /// Every 4 x 4 unit's scanned (position, lanes) entries of the tile `rect`'s `list`.
    fn scanned(list: &[RowEntry], rect: [usize; 4]) -> Vec<Vec<(u32, u32)>> {
        let mut rects = TileRects::default();
        rects.build(&[], list, rect, None);
        let mut selected = Vec::new();
        (0..TILE_PIXELS / 16)
            .map(|u| {
                let n = rects.select::<f32x4>(u, &mut selected);
                let entries = selected[..n].iter().map(|p| (p.to_bits(), 0));
                entries.map(|(at, _)| (at, rects.lanes(at, u))).collect()
            })
            .collect()
    }

    /// The per-pixel reference of [`scanned`]: lane l of unit u is tile pixel (column 4 (u
    /// mod 4) + l mod 4, row 4 (u div 4) + l div 4), inside an entry where its image pixel
    /// lies in the entry's rectangle and in the tile.
    fn reference(list: &[RowEntry], [x0, x1, y0, y1]: [usize; 4]) -> Vec<Vec<(u32, u32)>> {
        (0..TILE_PIXELS / 16)
            .map(|u| {
                let mut want = Vec::new();
                for (i, (_, [rx0, rx1, ry0, ry1])) in list.iter().enumerate() {
                    let mut lanes = 0;
                    for l in 0..16 {
                        let x = x0 + UNIT_W * (u % 4) + l % UNIT_W;
                        let y = y0 + UNIT_W * (u / 4) + l / UNIT_W;
                        let in_rect = (usize::from(*rx0)..=usize::from(*rx1)).contains(&x)
                            && (usize::from(*ry0)..=usize::from(*ry1)).contains(&y);
                        if in_rect && x < x1 && y < y1 {
                            lanes |= 1 << l;
                        }
                    }
                    if lanes != 0 {
                        want.push((i as u32, lanes));
                    }
                }
                want
            })
            .collect()
    }

    #[test]
    fn units_scan_every_rectangle_of_a_tile_with_exactly_its_lanes() {
        // One list holding every rectangle inside the tile at (16, 32), in a 16 x 16 tile
        // and in an edge tile cut to 13 x 6 pixels.
        let (x0, y0) = (16, 32);
        let mut list = Vec::new();
        for r0 in 0..TILE {
            for r1 in r0..TILE {
                for c0 in 0..TILE {
                    for c1 in c0..TILE {
                        let r = [x0 + c0, x0 + c1, y0 + r0, y0 + r1].map(|v| v as u16);
                        list.push((list.len() as u32, r));
                    }
                }
            }
        }
        assert_eq!(list.len(), 136 * 136);
        for rect in [[x0, x0 + TILE, y0, y0 + TILE], [x0, x0 + 13, y0, y0 + 6]] {
            let got = scanned(&list, rect);
            assert_eq!(got, reference(&list, rect), "{rect:?}");
            // Every unit meets rectangles (the edge tile's units past column 13 or row 6 meet
            // only lanes outside the image, so none).
            let hit_units = got.iter().filter(|e| !e.is_empty()).count();
            assert_eq!(hit_units, if rect[1] == x0 + TILE { 16 } else { 8 });
        }
    }

    #[test]
    fn units_scan_random_lists_with_rectangles_reaching_beyond_the_tile() {
        // Rectangles of the tile row's splats reach past the tile's sides (and, where the
        // row is the image's last, past its bottom edge); some miss the tile's columns.
        let mut next = lcg(11);
        for len in [1, 15, 16, 17, 100, 333] {
            let list: Vec<RowEntry> = (0..len)
                .map(|i| {
                    let (c0, r0) = (next(80) as u16, 32 + next(20) as u16);
                    let rect = [c0, c0 + next(30) as u16, r0, r0 + next(12) as u16];
                    (i, rect)
                })
                .collect();
            for rect in [[32, 48, 32, 48], [48, 61, 40, 47]] {
                assert_eq!(
                    scanned(&list, rect),
                    reference(&list, rect),
                    "{len} {rect:?}"
                );
            }
        }
    }

    /// Streams of contributions through `insert_group`, N lanes at a time, against sorted
    /// per-pixel lists built one entry at a time (descending weight, a newcomer after equal
    /// weights, the last entry dropped when full, padding `NO_GAUSSIAN` / 0). Weights come
    /// from a few values, so ties are common; candidates are the lanes whose weight beats
    /// their K-th, as in the blend, and ranks past the fill start as garbage.
    fn insertions_match_one_pixel_at_a_time<V: Lanes>() {
        let n = V::N;
        let mut next = lcg(23);
        for k in [1usize, 2, 3, 10, 40] {
            for stream in 0..60 {
                let mut lw = vec![f32::NAN; k * n];
                let mut lid = vec![f32::from_bits(0xDEAD); k * n];
                let mut reference: Vec<Vec<(f32, u32)>> = vec![Vec::new(); n];
                let mut kth = V::splat(0.0);
                let mut fill = 0usize;
                for step in 0..(3 * k + 5) as u32 {
                    let ws: Vec<f32> = (0..n)
                        .map(|_| match next(5) {
                            0 => 0.0,
                            v => v as f32 * if stream % 2 == 0 { 0.25 } else { 0.1 },
                        })
                        .collect();
                    let w = V::load(&ws);
                    let cand = w.gt(kth);
                    if V::bits(cand) == 0 {
                        continue;
                    }
                    let id = V::splat(f32::from_bits(step));
                    kth = insert_group::<V>(&mut lw, &mut lid, k, fill, cand, w, id);
                    fill = (fill + 1).min(k);
                    for (lane, list) in reference.iter_mut().enumerate() {
                        if V::bits(cand) >> lane & 1 == 0 {
                            continue;
                        }
                        let at = list.iter().take_while(|e| e.0 >= ws[lane]).count();
                        list.insert(at, (ws[lane], step));
                        list.truncate(k);
                    }
                    let mut kths = vec![0.0f32; n];
                    kth.store(&mut kths);
                    for (lane, list) in reference.iter().enumerate() {
                        let want = if list.len() == k { list[k - 1].0 } else { 0.0 };
                        assert_eq!(
                            kths[lane], want,
                            "K-th, k {k}, stream {stream}, lane {lane}"
                        );
                        for r in 0..fill {
                            let (w, id) = list.get(r).copied().unwrap_or((0.0, NO_GAUSSIAN));
                            let got = (lw[r * n + lane], lid[r * n + lane].to_bits());
                            assert_eq!(
                                got,
                                (w, id),
                                "k {k}, stream {stream}, lane {lane}, rank {r}"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn group_insertion_equals_sorted_insertion_per_pixel() {
        insertions_match_one_pixel_at_a_time::<f32x4>();
    }

    #[cfg(target_arch = "x86_64")]
    #[allow(unsafe_code)]
    #[test]
    fn group_insertion_equals_sorted_insertion_per_pixel_16_lanes() {
        if Level::detect() != Level::Avx512 {
            eprintln!("skipped: this CPU has no AVX-512 F + DQ");
            return;
        }
        #[target_feature(enable = "avx512f,avx512dq")]
        fn run() {
            insertions_match_one_pixel_at_a_time::<super::F32x16>();
        }
        // SAFETY: the features were detected above.
        unsafe { run() }
    }
}

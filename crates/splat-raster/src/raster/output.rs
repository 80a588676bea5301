//! What a render hands out: its options, statistics and phase times, the view's buffers
//! (colour, depth, alpha, transmittance, top-K) and the per-tile lists of a streamed render.

use super::*;

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
    pub(super) fn add(self, o: BlendCounts) -> BlendCounts {
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
    pub(super) view: usize,
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) opts: RenderOptions,
    pub(super) stats: RenderStats,
    pub(super) phases: Phases,
    pub(super) color: Vec<f32>,
    pub(super) depth: Vec<f32>,
    pub(super) alpha: Vec<f32>,
    pub(super) transmittance: Vec<f32>,
    pub(super) ids: Vec<u32>,
    pub(super) weights: Vec<f32>,
    /// Per tile (row-major): its lists in `ids` and `weights` are all padding, as the
    /// previous render left them. An empty tile of the next render with the same width,
    /// height and K then skips rewriting them (on an orbit around an object most of the
    /// image is background, and padding an empty tile's lists writes K x 8 bytes per
    /// pixel).
    pub(super) padded: Vec<bool>,
    pub(super) scratch: ViewScratch,
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

    pub(super) fn resize(&mut self, view: usize, cam: &ViewCamera, opts: &RenderOptions) {
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
pub struct ListScratch(pub(super) ViewScratch);

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
    pub(super) x0: usize,
    pub(super) y0: usize,
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) k: usize,
    pub(super) ids: &'a [u32],
    pub(super) positions: &'a [u32],
    pub(super) splat_ids: &'a [u32],
    pub(super) weights: &'a [f32],
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

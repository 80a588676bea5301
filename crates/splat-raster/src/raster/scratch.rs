//! A worker's tile scratch: 64-byte lines of per-pixel values, the rank-major top-K lists, and
//! the pool the workers borrow them from.

use super::*;

/// A tile scratch borrowed from the view's pool and given back when dropped.
pub(super) struct Pooled<'a> {
    pub(super) st: Option<TileScratch>,
    pub(super) pool: &'a Mutex<Vec<TileScratch>>,
}

impl<'a> Pooled<'a> {
    pub(super) fn take(pool: &'a Mutex<Vec<TileScratch>>, tiles_x: usize, k: usize) -> Self {
        let st = pool.lock().ok().and_then(|mut p| p.pop());
        let mut st = st.unwrap_or_default();
        st.reset(tiles_x, k);
        Pooled { st: Some(st), pool }
    }

    pub(super) fn get(&mut self) -> &mut TileScratch {
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
/// One 64-byte line of f32 lanes: the scratch arrays are built from these so that every
/// blend group (4 or 16 lanes) sits inside one cache line.
#[derive(Debug, Clone, Copy, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C, align(64))]
pub(super) struct Line([f32; 16]);

pub(super) const LINE: usize = 16;

/// One value per pixel of a tile, row-major.
pub(super) type PixelLines = [Line; PIXEL_LINES];

/// A tile's per-pixel values as plain floats (a fixed length, so that one range check of a
/// group's offset serves every array).
#[inline]
pub(super) fn pixels_mut(v: &mut PixelLines) -> &mut [f32; TILE_PIXELS] {
    bytemuck::cast_mut(v)
}

#[inline]
pub(super) fn pixels(v: &PixelLines) -> &[f32; TILE_PIXELS] {
    bytemuck::cast_ref(v)
}

#[inline]
pub(super) fn flat(v: &[Line]) -> &[f32] {
    bytemuck::cast_slice(v)
}

#[inline]
pub(super) fn flat_mut(v: &mut [Line]) -> &mut [f32] {
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
pub(super) struct TileScratch {
    /// Transmittance.
    pub(super) t: PixelLines,
    /// Σ ω c per channel.
    pub(super) r: PixelLines,
    pub(super) g: PixelLines,
    pub(super) b: PixelLines,
    /// Σ ω z.
    pub(super) depth: PixelLines,
    /// Σ ω.
    pub(super) wsum: PixelLines,
    /// Top-K weights, each list sorted by descending weight.
    pub(super) lw: Vec<Line>,
    /// Beside `lw`, the entries' Gaussian ids (with `lists_carry_ids`) or the positions of
    /// their splats in the tile's list (`list_ids` maps them to Gaussian ids), as f32 bit
    /// patterns (only ever moved by blends); [`NO_GAUSSIAN`] for padding.
    pub(super) lid: Vec<Line>,
    /// The lists carry Gaussian ids rather than positions: set for image outputs, which
    /// take no positions, so that the output is a plain transposition (one id lookup per
    /// insertion instead of one per output slot).
    pub(super) lists_carry_ids: bool,
    /// K of the lists.
    pub(super) k: usize,
    /// Per blend unit of one row (4 lanes): the splats of the tile that reach it, in depth
    /// order (see `blend_tile`).
    pub(super) units: UnitLists,
    /// The tile's list as 4 x 4 units (16 lanes) select from it, and the positions of the
    /// entries one unit selected (see `blend_tile`).
    pub(super) rects: TileRects,
    pub(super) unit_positions: Vec<f32>,
    /// Per blend unit: its lists' ranks from this one on are padding in every lane (they
    /// were never written in this tile: the lists are not cleared between tiles).
    pub(super) fill: Vec<u16>,
    /// The Gaussian ids of the tile's splats, in the order of its list.
    pub(super) list_ids: Vec<u32>,
    pub(super) tile_start: Vec<usize>,
    pub(super) tile_entries: Vec<RowEntry>,
    /// One tile's lists in pixel-major form, for [`Rasterizer::render_tiles`].
    pub(super) tile_ids: Vec<u32>,
    pub(super) tile_positions: Vec<u32>,
    pub(super) tile_weights: Vec<f32>,
    /// Blend counts of the current tile row (`counters` feature).
    pub(super) counts: BlendCounts,
}

pub(super) const PIXEL_LINES: usize = TILE_PIXELS / LINE;
pub(super) const NO_ID_LINE: Line = Line([f32::from_bits(NO_GAUSSIAN); LINE]);
pub(super) const ZERO_LINE: Line = Line([0.0; LINE]);

impl TileScratch {
    pub(super) fn reset(&mut self, tiles_x: usize, k: usize) {
        self.k = k;
        self.lw.resize(PIXEL_LINES * k, ZERO_LINE);
        self.lid.resize(PIXEL_LINES * k, NO_ID_LINE);
        self.tile_start.resize(tiles_x + 1, 0);
    }
}

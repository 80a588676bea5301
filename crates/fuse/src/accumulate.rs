//! The sparse Gaussian x group weight matrix W and the mask masses, accumulated view by
//! view in exact fixed point.
//!
//! One view is added in three steps, each parallel:
//! 1. **Tiles.** Every 16x16 pixel tile sums its hits per (Gaussian, group), and the masks'
//!    masses; ~10x fewer (Gaussian, group, Σq) records than hits come out (neighbouring
//!    pixels share most of their top-K Gaussians). The rasterizer hands each tile over as
//!    soon as its lists are rendered ([`ViewContext::sum_tile`] inside `render_tiles`), so
//!    the lists are read from cache, with each hit's position in the tile's splat list:
//!    the sums go into a dense (position, group) array, an add per hit. Tiles without
//!    positions (the tests' whole-image source) or with too many groups or splats use a
//!    small hash table that stays in L1.
//! 2. **Buckets.** The records are counting-sorted by Gaussian block (4096 Gaussians).
//! 3. **Blocks.** Each block of W adds its bucket: the block's entries (a few hundred KB)
//!    stay in cache, and blocks are disjoint, so no locks.
//!
//! Ids are arbitrary with respect to the screen, so adding hits straight into a W of a
//! million Gaussians would miss the cache on almost every first touch of a Gaussian.
//!
//! Here: the accumulator, its per-view context and W; `views` (the view loop,
//! [`accumulate`]), `tile_sums` (step 1 for one tile) and `tables` (the exact-sum
//! containers: W's blocks, records, the tile's hash table).

use rayon::prelude::*;
use splat_raster::NO_GAUSSIAN;

use crate::error::{FuseError, Result};
use crate::groups::{weigh_hit, NO_GROUP, PIXEL_WEIGHT_ONE};

mod tables;
mod tile_sums;
mod views;

use tables::*;
use tile_sums::*;
pub use views::accumulate;

/// Weights are stored as integers in units of 2^-62: `q = trunc(ω · 2^62)`. Every f32
/// weight ω >= 2^-39 converts exactly (its 24-bit mantissa fits), and the rasterizer's
/// weights are >= 1/255 · 1e-4 ≈ 2^-21.3, so the integer sums are the exact sums of the
/// rendered weights, in any order.
pub const WEIGHT_SCALE: f64 = 4_611_686_018_427_387_904.0;

/// One rendered weight in fixed point; 0 for weights below 2^-62, NaN or negative.
#[inline]
pub fn quantise(w: f32) -> u64 {
    // Saturating float-to-int conversion: weights >= 4 (never rendered) clamp. Below 2^63
    // (every rendered weight) through i64, one instruction on x86-64 where u64 takes a
    // branchy sequence; NaN fails the test and converts to 0 either way.
    let x = f64::from(w) * WEIGHT_SCALE;
    if x < 9_223_372_036_854_775_808.0 {
        (x as i64).max(0) as u64
    } else {
        x as u64
    }
}

/// A fixed-point sum as a real number.
#[inline]
pub fn dequantise(q: u128) -> f64 {
    q as f64 / WEIGHT_SCALE
}

const END: u32 = u32::MAX;
/// log2 of the Gaussians per block of W.
const BLOCK_SHIFT: u32 = 12;
const BLOCK_LEN: usize = 1 << BLOCK_SHIFT;
/// Side of the pixel tiles of step 1 (the rasterizer's tiles).
#[cfg(test)]
const TILE: usize = splat_raster::TILE;
/// Slots of a tile's table (a power of two); it is flushed when half full.
const TABLE_SLOTS: usize = 1024;

/// The hits of one view as whole-image buffers (the tests' tile source).
#[cfg(test)]
#[derive(Debug, Clone, Copy)]
pub(crate) struct ViewHits<'a> {
    /// View-local mask label per pixel of the mask grid.
    pub labels: LabelPlane<'a>,
    /// Global id of the view's first mask.
    pub offset: u32,
    /// Width of the mask grid.
    pub width: usize,
    /// Top-K Gaussian ids [H, W, K].
    pub ids: &'a [u32],
    /// Top-K weights [H, W, K].
    pub weights: &'a [f32],
    /// K.
    pub k: usize,
}

/// One view's label map in its stored dtype.
#[derive(Debug, Clone, Copy)]
pub(crate) enum LabelPlane<'a> {
    U16(&'a [u16]),
    U32(&'a [u32]),
}

impl LabelPlane<'_> {
    /// Whether some pixel has a mask.
    pub fn any_mask(&self) -> bool {
        match self {
            LabelPlane::U16(l) => l.iter().any(|v| *v != u16::MAX),
            LabelPlane::U32(l) => l.iter().any(|v| *v != u32::MAX),
        }
    }

    fn len(&self) -> usize {
        match self {
            LabelPlane::U16(l) => l.len(),
            LabelPlane::U32(l) => l.len(),
        }
    }
}

/// A stored label value: a view-local mask index, or the type's maximum for no mask.
trait Label: Copy {
    fn local(self) -> Option<usize>;
}

impl Label for u16 {
    #[inline]
    fn local(self) -> Option<usize> {
        (self != u16::MAX).then_some(usize::from(self))
    }
}

impl Label for u32 {
    #[inline]
    fn local(self) -> Option<usize> {
        (self != u32::MAX).then_some(self as usize)
    }
}

/// Counters of accumulated views.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct HitCounts {
    /// Mask-grid pixels whose mask registers into a group.
    pub pixels: u64,
    /// Top-K hits of those pixels (the scatter operations into W).
    pub hits: u64,
}

impl HitCounts {
    fn add(&mut self, o: HitCounts) {
        self.pixels += o.pixels;
        self.hits += o.hits;
    }
}

/// What one tile row of a view produced (and the table its tiles are summed in).
#[derive(Debug, Default)]
pub(crate) struct RowOutput {
    records: Vec<Record>,
    mass: Vec<u128>,
    counts: HitCounts,
    error: Option<String>,
    table: TileTable,
    dense: DenseSums,
}

impl RowOutput {
    fn reset(&mut self) {
        self.records.clear();
        self.mass.clear();
        self.counts = HitCounts::default();
        self.error = None;
    }
}

/// The top-K lists of one tile: pixel (`x0 + col`, `y0 + row`) owns the K entries at
/// `(row * row_stride + col) * k` of `ids` and `weights`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct TileHits<'a> {
    pub x0: usize,
    pub y0: usize,
    pub width: usize,
    pub height: usize,
    pub row_stride: usize,
    pub ids: &'a [u32],
    pub weights: &'a [f32],
    /// Beside `ids`, each hit's position in `splat_ids` (the rasterizer's
    /// [`splat_raster::TileLists::positions`]), for the dense sum; `None`: the table.
    pub positions: Option<&'a [u32]>,
    pub splat_ids: &'a [u32],
}

impl<'a> From<&splat_raster::TileLists<'a>> for TileHits<'a> {
    fn from(t: &splat_raster::TileLists<'a>) -> Self {
        TileHits {
            x0: t.x0(),
            y0: t.y0(),
            width: t.width(),
            height: t.height(),
            row_stride: splat_raster::TILE,
            ids: t.ids(),
            weights: t.weights(),
            positions: Some(t.positions()),
            splat_ids: t.splat_ids(),
        }
    }
}

/// What summing the tiles of one view needs: its labels, the groups of its masks, K.
/// Borrows nothing of the accumulator, so tiles can be summed while it lends its rows.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ViewContext<'a> {
    labels: LabelPlane<'a>,
    width: usize,
    height: usize,
    /// Group of each of the view's masks (view-local index).
    groups: &'a [u32],
    /// Pixel-weight factor of each of the view's masks (units of 2^-16,
    /// [`crate::groups::Groups::pixel_weight`]); empty: every factor is 1.
    pixel_weight: &'a [u32],
    /// Global id of the view's first mask.
    start: usize,
    k: usize,
    num_gaussians: usize,
    view: usize,
}

/// The per-tile-row outputs of one view (records, masses, counters), reused from view to
/// view. Separate from the [`Accumulator`], so that one view's rows can be merged into W
/// while the next view's tiles fill another `ViewRows`.
#[derive(Debug, Default)]
pub(crate) struct ViewRows(Vec<RowOutput>);

impl ViewRows {
    /// The rows, cleared, for a tile source to fill through [`ViewContext::sum_tile`].
    pub(crate) fn begin(&mut self) -> &mut Vec<RowOutput> {
        for row in &mut self.0 {
            row.reset();
        }
        &mut self.0
    }

    pub(crate) fn heap_bytes(&self) -> usize {
        self.0
            .iter()
            .map(|r| r.records.capacity() * std::mem::size_of::<Record>() + r.mass.capacity() * 16)
            .sum()
    }
}

/// W (Gaussian x group, sparse) and the mask masses, accumulated in exact fixed point
/// ([`WEIGHT_SCALE`]), so the result does not depend on the order of views, pixels or
/// threads. Memory: 4 bytes per Gaussian, 24 per nonzero (Gaussian, group) pair and 16
/// per mask, plus one view's records sorted by block, reused by every view.
#[derive(Debug)]
pub struct Accumulator {
    num_gaussians: usize,
    num_groups: usize,
    blocks: Vec<Block>,
    mask_mass: Vec<u128>,
    counts: HitCounts,
    /// A view's records, counting-sorted by block.
    sorted: Vec<Record>,
}

impl Accumulator {
    /// An empty accumulator for `num_gaussians` Gaussians, `num_masks` masks and
    /// `num_groups` groups.
    pub fn new(num_gaussians: usize, num_masks: usize, num_groups: usize) -> Self {
        let blocks = (0..num_gaussians.div_ceil(BLOCK_LEN))
            .map(|b| Block::new(BLOCK_LEN.min(num_gaussians - b * BLOCK_LEN)))
            .collect();
        Accumulator {
            num_gaussians,
            num_groups,
            blocks,
            mask_mass: vec![0; num_masks],
            counts: HitCounts::default(),
            sorted: Vec::new(),
        }
    }

    /// Number of nonzero W entries.
    pub fn nnz(&self) -> usize {
        self.blocks.iter().map(|b| b.entries.len()).sum()
    }

    /// Bytes held by W and the masses (capacities, not lengths).
    pub fn heap_bytes(&self) -> usize {
        self.blocks.iter().map(Block::heap_bytes).sum::<usize>()
            + self.mask_mass.capacity() * std::mem::size_of::<u128>()
    }

    /// Bytes of the per-view scratch (a view's sorted records), reused by every view.
    pub fn scratch_bytes(&self) -> usize {
        self.sorted.capacity() * std::mem::size_of::<Record>()
    }

    /// Counters summed over the views accumulated so far.
    pub fn counts(&self) -> HitCounts {
        self.counts
    }

    /// Checks the view's mask range and label plane and returns what summing its tiles
    /// needs: labels `labels` on a grid of `width` columns, masks `offset..offset +
    /// masks_in_view` with groups `mask_group[offset..]` and pixel-weight factors
    /// `pixel_weight[offset..]` (empty: all 1), lists of K = `k`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn view_context<'a>(
        &self,
        labels: LabelPlane<'a>,
        width: usize,
        offset: u32,
        mask_group: &'a [u32],
        pixel_weight: &'a [u32],
        masks_in_view: usize,
        k: usize,
        view: usize,
    ) -> Result<ViewContext<'a>, String> {
        let start = offset as usize;
        let (Some(groups), true) = (
            mask_group.get(start..start + masks_in_view),
            start + masks_in_view <= self.mask_mass.len(),
        ) else {
            return Err(format!(
                "view {view}: masks {start}..{} are beyond the mask table",
                start + masks_in_view
            ));
        };
        let pixel_weight = if pixel_weight.is_empty() {
            pixel_weight
        } else {
            pixel_weight
                .get(start..start + masks_in_view)
                .ok_or_else(|| {
                    format!(
                        "view {view}: masks {start}..{} are beyond the {} pixel weights",
                        start + masks_in_view,
                        pixel_weight.len()
                    )
                })?
        };
        let pixels = labels.len();
        if width == 0 || !pixels.is_multiple_of(width) {
            return Err(format!(
                "view {view}: {pixels} mask pixels are not rows of {width}"
            ));
        }
        Ok(ViewContext {
            labels,
            width,
            height: pixels / width,
            groups,
            pixel_weight,
            start,
            k,
            num_gaussians: self.num_gaussians,
            view,
        })
    }

    /// Adds what the tiles of the view produced: μ(m) += Σ_t ω over every labelled pixel,
    /// and W[g, group(m)] += ω for every top-K hit g of every pixel whose mask m has a
    /// group.
    pub(crate) fn end_view(
        &mut self,
        ctx: &ViewContext<'_>,
        rows: &ViewRows,
    ) -> Result<HitCounts, String> {
        let mut counts = HitCounts::default();
        for row in &rows.0 {
            if let Some(e) = &row.error {
                return Err(format!("view {}: {e}", ctx.view));
            }
            counts.add(row.counts);
            for (m, q) in self.mask_mass[ctx.start..].iter_mut().zip(&row.mass) {
                *m += *q;
            }
        }
        let bounds = bucket_by_block(&rows.0, &mut self.sorted, self.blocks.len());
        let sorted = &self.sorted;
        let jobs: Vec<_> = self
            .blocks
            .iter_mut()
            .zip(bounds.windows(2))
            .map(|(block, w)| (block, &sorted[w[0]..w[1]]))
            .collect();
        jobs.into_par_iter().for_each(|(block, records)| {
            for r in records {
                block.add(r.g as usize & (BLOCK_LEN - 1), r.group, r.sum());
            }
        });
        self.counts.add(counts);
        Ok(counts)
    }

    /// Adds one view whose top-K lists are whole-image buffers (see
    /// [`Accumulator::end_view`] for what is added).
    #[cfg(test)]
    pub(crate) fn add_view(
        &mut self,
        hits: &ViewHits<'_>,
        mask_group: &[u32],
        pixel_weight: &[u32],
        masks_in_view: usize,
        view: usize,
    ) -> Result<HitCounts, String> {
        let ctx = self.view_context(
            hits.labels,
            hits.width,
            hits.offset,
            mask_group,
            pixel_weight,
            masks_in_view,
            hits.k,
            view,
        )?;
        let pixels = hits.labels.len();
        if hits.ids.len() != pixels * hits.k || hits.weights.len() != pixels * hits.k {
            return Err(format!(
                "view {view}: {} top-K ids and {} weights for {pixels} mask pixels with K = {}",
                hits.ids.len(),
                hits.weights.len(),
                hits.k
            ));
        }
        let mut view_rows = ViewRows::default();
        let rows = view_rows.begin();
        rows.resize_with(ctx.height.div_ceil(TILE), RowOutput::default);
        rows.par_iter_mut().enumerate().for_each(|(ty, out)| {
            for x0 in (0..ctx.width).step_by(TILE) {
                let (y0, k) = (ty * TILE, hits.k);
                let first = (y0 * ctx.width + x0) * k;
                let tile = TileHits {
                    x0,
                    y0,
                    width: (ctx.width - x0).min(TILE),
                    height: (ctx.height - y0).min(TILE),
                    row_stride: ctx.width,
                    ids: &hits.ids[first..],
                    weights: &hits.weights[first..],
                    positions: None,
                    splat_ids: &[],
                };
                ctx.sum_tile(&tile, out);
            }
        });
        self.end_view(&ctx, &view_rows)
    }

    /// W[g, group] += q (merging partial sums).
    pub(crate) fn add_entry(&mut self, g: usize, group: u32, q: u128) {
        self.blocks[g >> BLOCK_SHIFT].add(g & (BLOCK_LEN - 1), group, q);
    }

    /// μ(m) += q (merging partial sums).
    pub(crate) fn add_mass(&mut self, m: usize, q: u128) {
        self.mask_mass[m] += q;
    }

    /// Adds counters (merging partial sums).
    pub(crate) fn add_counts(&mut self, c: HitCounts) {
        self.counts.add(c);
    }

    /// The accumulated W as a CSR matrix (rows = Gaussians, columns sorted) and the mask
    /// masses.
    pub(crate) fn finish(self) -> Result<(WeightMatrix, Vec<u128>)> {
        if self.blocks.iter().any(|b| b.overflow) {
            return Err(FuseError::TooManyPairs {
                max: END as usize - 1,
            });
        }
        let mut offsets = Vec::with_capacity(self.num_gaussians + 1);
        offsets.push(0u64);
        let mut total = 0u64;
        for block in &self.blocks {
            for local in 0..block.head.len() {
                total += block.row_len(local);
                offsets.push(total);
            }
        }
        let nnz = total as usize;
        let mut groups = vec![0u32; nnz];
        let mut sums = vec![0u128; nnz];
        // Blocks are independent: fill them in parallel, each block freed once copied, so
        // W is not held twice in full.
        let mut rest_g: &mut [u32] = &mut groups;
        let mut rest_s: &mut [u128] = &mut sums;
        let mut jobs = Vec::with_capacity(self.blocks.len());
        for (b, block) in self.blocks.into_iter().enumerate() {
            let first = b * BLOCK_LEN;
            let len = (offsets[first + block.head.len()] - offsets[first]) as usize;
            let (g_now, g_later) = rest_g.split_at_mut(len);
            let (s_now, s_later) = rest_s.split_at_mut(len);
            rest_g = g_later;
            rest_s = s_later;
            jobs.push((block, g_now, s_now));
        }
        jobs.into_par_iter().for_each(|(block, g_out, s_out)| {
            let block: Block = block;
            let mut row = Vec::new();
            let mut i = 0;
            for local in 0..block.head.len() {
                block.row(local, &mut row);
                for (group, sum) in &row {
                    g_out[i] = *group;
                    s_out[i] = *sum;
                    i += 1;
                }
            }
        });
        Ok((
            WeightMatrix {
                num_groups: self.num_groups,
                offsets,
                groups,
                sums,
            },
            self.mask_mass,
        ))
    }
}

/// Step 2: every row's records, counting-sorted by Gaussian block into `sorted`; returns
/// the `blocks + 1` bounds of the buckets.
fn bucket_by_block(rows: &[RowOutput], sorted: &mut Vec<Record>, blocks: usize) -> Vec<usize> {
    let mut bounds = vec![0usize; blocks + 1];
    for r in rows.iter().flat_map(|row| &row.records) {
        bounds[(r.g >> BLOCK_SHIFT) as usize + 1] += 1;
    }
    for b in 0..blocks {
        bounds[b + 1] += bounds[b];
    }
    sorted.clear();
    sorted.resize(bounds[blocks], Record::default());
    let mut next = bounds.clone();
    for r in rows.iter().flat_map(|row| &row.records) {
        let slot = &mut next[(r.g >> BLOCK_SHIFT) as usize];
        sorted[*slot] = *r;
        *slot += 1;
    }
    bounds
}

/// The sparse Gaussian x group matrix W in CSR form: row g holds the groups with a
/// nonzero sum, in ascending order, and their exact fixed-point sums.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct WeightMatrix {
    /// Number of columns (groups).
    pub num_groups: usize,
    /// Row g's entries are `offsets[g] .. offsets[g + 1]`; N + 1 values.
    pub offsets: Vec<u64>,
    /// Column (group) of every entry.
    pub groups: Vec<u32>,
    /// Σ ω of every entry in units of 2^-62 ([`WEIGHT_SCALE`]).
    pub sums: Vec<u128>,
}

impl WeightMatrix {
    /// Number of rows (Gaussians).
    pub fn rows(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    /// Number of nonzero entries.
    pub fn nnz(&self) -> usize {
        self.groups.len()
    }

    /// Row g: its groups and fixed-point sums.
    pub fn row(&self, g: usize) -> (&[u32], &[u128]) {
        let (a, b) = (self.offsets[g] as usize, self.offsets[g + 1] as usize);
        (&self.groups[a..b], &self.sums[a..b])
    }

    /// W[g, group] as a real number (0 where absent).
    pub fn get(&self, g: usize, group: u32) -> f64 {
        let (groups, sums) = self.row(g);
        groups
            .binary_search(&group)
            .map_or(0.0, |i| dequantise(sums[i]))
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use std::collections::BTreeMap;

    use profuse_formats::rng::SplitMix64;

    use super::*;

    /// Random views with many distinct (Gaussian, group) pairs per tile (so tile tables
    /// flush), ids over several blocks, unlabelled and ungrouped pixels, padded slots, and
    /// per-mask pixel-weight factors (0, 1 and fractions): W (each hit's q times its
    /// mask's factor, floored) and the masses (unweighted) equal a map-based reference.
    #[test]
    fn accumulator_equals_a_map_reference() {
        let (n, w, h, k) = (3 * BLOCK_LEN + 17, 37, 21, 6);
        let masks_per_view = 5;
        let views = 3;
        let mask_group: Vec<u32> = (0..views * masks_per_view)
            .map(|m| if m % 4 == 3 { NO_GROUP } else { (m % 6) as u32 })
            .collect();
        let factors: Vec<u32> = (0..views * masks_per_view)
            .map(|m| match m % 3 {
                0 => PIXEL_WEIGHT_ONE,
                1 => 0,
                _ => 1 + 4099 * m as u32,
            })
            .collect();
        let mut acc = Accumulator::new(n, mask_group.len(), 6);
        let mut w_ref: BTreeMap<(u32, u32), u128> = BTreeMap::new();
        let mut mass_ref = vec![0u128; mask_group.len()];
        let mut state = SplitMix64::new(7);
        for v in 0..views {
            let labels: Vec<u16> = (0..w * h)
                .map(|_| match state.next_u64() % 7 {
                    6 => u16::MAX,
                    l => (l % masks_per_view as u64) as u16,
                })
                .collect();
            let mut ids = vec![NO_GAUSSIAN; w * h * k];
            let mut weights = vec![0f32; w * h * k];
            for px in 0..w * h {
                let filled = (state.next_u64() % (k as u64 + 1)) as usize;
                for t in 0..filled {
                    ids[px * k + t] = (state.next_u64() % n as u64) as u32;
                    weights[px * k + t] = (state.next_u64() % 1000) as f32 / 1024.0;
                }
            }
            let offset = (v * masks_per_view) as u32;
            for px in 0..w * h {
                if labels[px] == u16::MAX {
                    continue;
                }
                let m = offset as usize + usize::from(labels[px]);
                for t in 0..k {
                    let (g, q) = (ids[px * k + t], quantise(weights[px * k + t]));
                    if g == NO_GAUSSIAN {
                        break;
                    }
                    mass_ref[m] += u128::from(q);
                    let weighed = u128::from(q) * u128::from(factors[m]) / 65_536;
                    if mask_group[m] != NO_GROUP && weighed > 0 {
                        *w_ref.entry((g, mask_group[m])).or_default() += weighed;
                    }
                }
            }
            let hits = ViewHits {
                labels: LabelPlane::U16(&labels),
                offset,
                width: w,
                ids: &ids,
                weights: &weights,
                k,
            };
            acc.add_view(&hits, &mask_group, &factors, masks_per_view, v)
                .unwrap();
        }
        assert_eq!(acc.nnz(), w_ref.len());
        let (matrix, mass) = acc.finish().unwrap();
        assert_eq!(mass, mass_ref);
        let mut got = BTreeMap::new();
        for g in 0..n {
            let (groups, sums) = matrix.row(g);
            assert!(groups.windows(2).all(|p| p[0] < p[1]));
            for (group, sum) in groups.iter().zip(sums) {
                got.insert((g as u32, *group), *sum);
            }
        }
        assert_eq!(got, w_ref);
    }

    #[test]
    fn quantise_is_the_saturating_conversion_of_the_scaled_weight() {
        let mut ws = vec![
            0.0f32,
            -0.0,
            -1.0,
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::MIN_POSITIVE,
            1e-30,
            2.0f32.powi(-62),
            2.0f32.powi(-39),
            1.0 / 255.0 * 1e-4,
            0.99,
            1.0,
            1.999_999_9,
            2.0,
            3.999_999_8,
            4.0,
            1e30,
        ];
        let mut state = SplitMix64::new(3);
        ws.extend((0..100_000).map(|_| f32::from_bits(state.next_u64() as u32)));
        for w in ws {
            let reference = (f64::from(w) * WEIGHT_SCALE) as u64;
            assert_eq!(quantise(w), reference, "{w:e}");
        }
    }

    #[test]
    fn entry_sums_carry_past_64_bits() {
        let mut block = Block::new(2);
        let big = u128::from(u64::MAX);
        for _ in 0..3 {
            block.add(1, 7, big);
        }
        block.add(1, 7, 5);
        let mut row = Vec::new();
        block.row(1, &mut row);
        assert_eq!(row, vec![(7, 3 * big + 5)]);
    }

    #[test]
    fn tile_table_flushes_and_sums() {
        let mut table = TileTable::new();
        let mut out = Vec::new();
        for round in 0..3u64 {
            for g in 0..2000u32 {
                table.add(g, g % 3, round + 1, &mut out);
            }
        }
        table.flush(&mut out);
        let mut sums: BTreeMap<(u32, u32), u128> = BTreeMap::new();
        for r in &out {
            *sums.entry((r.g, r.group)).or_default() += r.sum();
        }
        assert_eq!(sums.len(), 2000);
        assert!(sums
            .iter()
            .all(|((g, group), s)| *group == g % 3 && *s == 6));
        assert!(table.slots.iter().all(|s| s.key == TileTable::EMPTY));
        assert_eq!(table.len, 0);
    }

    #[test]
    fn tile_table_sums_carry_into_the_high_half() {
        let mut table = TileTable::new();
        let mut out = Vec::new();
        let big = u64::MAX - 2;
        for _ in 0..5 {
            table.add(9, 4, big, &mut out);
        }
        table.add(9, 4, 11, &mut out);
        table.add(9, 5, 1, &mut out);
        table.flush(&mut out);
        let mut sums: Vec<(u32, u32, u128)> = out.iter().map(|r| (r.g, r.group, r.sum())).collect();
        sums.sort_unstable();
        assert_eq!(sums, [(9, 4, 5 * u128::from(big) + 11), (9, 5, 1)]);
    }

    /// What `sum_random_tile` compares: records summed per key, masses, counts, error,
    /// whether the dense sum ran.
    type TileSums = (
        BTreeMap<(u32, u32), u128>,
        Vec<u128>,
        HitCounts,
        Option<String>,
        bool,
    );

    /// One random tile summed with the rasterizer's positions and without them (the
    /// table).
    fn sum_random_tile(
        [groups, list_len, k]: [usize; 3],
        seed: u64,
        tamper: impl Fn(&mut Vec<u32>, &mut Vec<u16>, &mut Vec<u32>),
    ) -> [TileSums; 2] {
        let (n, masks, w, h) = (50_000usize, 24usize, 29usize, 21usize);
        let mut state = SplitMix64::new(seed);
        let mut next = |m: usize| (state.next_u64() % m as u64) as usize;
        // Masks 0..masks of one view: groups 0..groups, every fifth in none.
        let mask_group: Vec<u32> = (0..masks)
            .map(|m| {
                if m % 5 == 4 {
                    NO_GROUP
                } else {
                    (m % groups) as u32
                }
            })
            .collect();
        let mut labels: Vec<u16> = (0..w * h)
            .map(|_| {
                if next(9) == 0 {
                    u16::MAX
                } else {
                    next(masks) as u16
                }
            })
            .collect();
        let mut splat_ids: Vec<u32> = Vec::new();
        while splat_ids.len() < list_len {
            let id = next(n) as u32;
            if !splat_ids.contains(&id) || list_len > 2000 {
                splat_ids.push(id);
            }
        }
        splat_ids.sort_unstable();
        splat_ids.dedup();
        // The tile at (13, 5): 16 x 16 pixels, lists laid out with a row stride of 16.
        let (x0, y0) = (13, 5);
        let mut ids = vec![NO_GAUSSIAN; TILE * TILE * k];
        let mut positions = vec![NO_GAUSSIAN; TILE * TILE * k];
        let mut weights = vec![0f32; TILE * TILE * k];
        for px in 0..TILE * TILE {
            for r in 0..next(k + 1) {
                let at = next(splat_ids.len());
                positions[px * k + r] = at as u32;
                ids[px * k + r] = splat_ids[at];
                // Zeros, and weights near 4 whose sums carry into the high half.
                weights[px * k + r] = match next(10) {
                    0 => 0.0,
                    1 => 3.999,
                    _ => next(1000) as f32 / 1024.0,
                };
            }
        }
        tamper(&mut positions, &mut labels, &mut splat_ids);
        // Pixel-weight factors: 1, 0 and fractions.
        let factors: Vec<u32> = (0..masks)
            .map(|m| [PIXEL_WEIGHT_ONE, 0, 40_000, 1][m % 4])
            .collect();
        let acc = Accumulator::new(n, masks, groups);
        let ctx = acc
            .view_context(
                LabelPlane::U16(&labels),
                w,
                0,
                &mask_group,
                &factors,
                masks,
                k,
                0,
            )
            .unwrap();
        [Some(&positions[..]), None].map(|positions| {
            let mut out = RowOutput::default();
            let tile = TileHits {
                x0,
                y0,
                width: TILE,
                height: TILE,
                row_stride: TILE,
                ids: &ids,
                weights: &weights,
                positions,
                splat_ids: &splat_ids,
            };
            ctx.sum_tile(&tile, &mut out);
            let mut sums = BTreeMap::new();
            for r in &out.records {
                *sums.entry((r.g, r.group)).or_default() += r.sum();
            }
            let dense = !out.dense.sums.is_empty();
            (sums, out.mass, out.counts, out.error, dense)
        })
    }

    /// The dense tile sum equals the table's sums, masses and counts, with few and many
    /// groups, short and long splat lists, K = 1 and 6; it hands tiles with more groups or
    /// cells than it holds to the table; bad labels, positions and splat ids are errors.
    #[test]
    fn dense_tile_sums_equal_the_table_and_hand_over_what_they_cannot_hold() {
        let (mut ran, mut carried) = ([0, 0], 0);
        for (i, &(groups, list_len, k)) in [
            (1, 5, 6),
            (3, 300, 6),
            (3, 300, 1),
            (DENSE_GROUPS, 2000, 6),
            (DENSE_GROUPS + 1, 300, 6),
            (2, DENSE_CELLS, 6),
        ]
        .iter()
        .enumerate()
        {
            let [dense, table] = sum_random_tile([groups, list_len, k], i as u64, |_, _, _| {});
            assert_eq!(dense.0, table.0, "case {i}: sums");
            assert!(!table.0.is_empty());
            carried += usize::from(table.0.values().any(|&s| s > u128::from(u64::MAX)));
            assert_eq!(
                (&dense.1, dense.2, &dense.3),
                (&table.1, table.2, &table.3),
                "case {i}"
            );
            assert!(table.2.hits > 0 && dense.3.is_none());
            let fits = groups <= DENSE_GROUPS && list_len * groups <= DENSE_CELLS;
            assert_eq!(dense.4, fits, "case {i}: dense sum ran");
            ran[usize::from(fits)] += 1;
        }
        assert_eq!(ran, [2, 4]);
        assert!(carried >= 3, "{carried} cases with sums past 64 bits");
        // A position past the tile's splats.
        let [dense, _] = sum_random_tile([3, 300, 6], 9, |at, _, _| {
            at.iter_mut()
                .filter(|a| **a != NO_GAUSSIAN)
                .for_each(|a| *a = 300);
        });
        let err = dense.3.unwrap_or_default();
        assert!(err.contains("at 300 of the 300 splats"), "{err}");
        // A splat list naming a Gaussian past the scene's.
        let [dense, table] = sum_random_tile([3, 300, 6], 9, |_, _, ids| ids[0] = 60_000);
        let err = dense.3.unwrap_or_default();
        assert!(err.contains("listed Gaussian 60000"), "{err}");
        assert!(table.3.is_none());
        // A label beyond the view's masks: the table reports it.
        let [dense, table] =
            sum_random_tile([3, 300, 6], 9, |_, labels, _| labels[29 * 7 + 15] = 40);
        assert!(dense.3.is_some_and(|e| e.contains("label 40")) && table.3.is_some());
    }

    #[test]
    fn inconsistent_view_buffers_are_errors() {
        let mut acc = Accumulator::new(10, 2, 2);
        let labels = [0u16, 1, 1, 0];
        let hits = ViewHits {
            labels: LabelPlane::U16(&labels),
            offset: 0,
            width: 2,
            ids: &[0, 1, 2],
            weights: &[0.5; 3],
            k: 1,
        };
        assert!(acc.add_view(&hits, &[0, 1], &[], 2, 0).is_err());
        let hits = ViewHits {
            ids: &[0, 1, 2, 11],
            weights: &[0.5; 4],
            ..hits
        };
        let err = acc.add_view(&hits, &[0, 1], &[], 2, 0).unwrap_err();
        assert!(err.contains("Gaussian 11"), "{err}");
        let hits = ViewHits {
            labels: LabelPlane::U16(&[0, 1, 2, 0]),
            ids: &[0, 1, 2, 3],
            ..hits
        };
        let err = acc.add_view(&hits, &[0, 1], &[], 2, 0).unwrap_err();
        assert!(err.contains("label 2"), "{err}");
    }
}

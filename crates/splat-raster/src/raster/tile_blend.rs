//! The front-to-back blend of one tile: its pixels cut into SIMD units, each walking the splats
//! that reach it in depth order with its state in registers, and the top-K insertion.

use super::*;

/// [`blend_tile`] with the lane type of `ctx.level`.
#[allow(unsafe_code)]
pub(super) fn blend_tile_at<const TOPK: bool, const CUTOFF: bool>(
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
pub(super) fn blend_tile_portable<const TOPK: bool, const CUTOFF: bool>(
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
pub(super) fn blend_tile_avx512<const TOPK: bool, const CUTOFF: bool>(
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
pub(super) struct UnitEntry {
    pub(super) at: u32,
    pub(super) lanes: u32,
}

/// The per-unit splat lists of one tile in one buffer: unit u's entries are
/// `entries[u * stride..][..len[u]]`, where `stride` is the tile's list length (a splat
/// enters a unit at most once).
#[derive(Debug, Default)]
pub(super) struct UnitLists {
    pub(super) entries: Vec<UnitEntry>,
    pub(super) len: Vec<usize>,
    pub(super) stride: usize,
}

impl UnitLists {
    /// Empties `units` lists for a tile of `list_len` splats.
    pub(super) fn reset(&mut self, units: usize, list_len: usize) {
        self.stride = list_len;
        let need = units * self.stride;
        if self.entries.len() < need {
            self.entries.resize(need, UnitEntry { at: 0, lanes: 0 });
        }
        self.len.clear();
        self.len.resize(units, 0);
    }

    #[inline(always)]
    pub(super) fn push(&mut self, unit: usize, entry: UnitEntry) {
        if let Some(len) = self.len.get_mut(unit) {
            if let Some(slot) = self.entries.get_mut(unit * self.stride + *len) {
                *slot = entry;
                *len += 1;
            }
        }
    }

    pub(super) fn get(&self, unit: usize) -> &[UnitEntry] {
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
pub(super) fn blend_tile<V: Lanes, const TOPK: bool, const CUTOFF: bool>(
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
pub(super) struct TileRects {
    pub(super) units: Vec<f32>,
    pub(super) positions: Vec<f32>,
    /// Column bits in the low 16 bits, row bits in the high 16.
    pub(super) cols_rows: Vec<u32>,
}

impl TileRects {
    /// The rectangles of the tile `[x0, x1) x [y0, y1)`'s `list`; `ids`, if given, receives
    /// the Gaussian id of every position of the list.
    pub(super) fn build(
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
    pub(super) fn push(&mut self, [c0, c1, r0, r1]: [usize; 4]) {
        let (cols, rows) = (bit_range(c0, c1), bit_range(r0, r1));
        // A tile's unit rows are UNITS_PER_ROW = 4 bits apart in `units`, as a unit's rows
        // of lanes are in its lanes: the same spreading.
        let unit_rows = bit_range(r0 / UNIT_W, r1 / UNIT_W);
        let units = bit_range(c0 / UNIT_W, c1 / UNIT_W) * spread_rows(unit_rows);
        self.push_bits(units, cols | rows << 16);
    }

    /// Appends an entry that reaches no unit.
    pub(super) fn push_nowhere(&mut self) {
        self.push_bits(0, 0);
    }

    pub(super) fn push_bits(&mut self, units: u32, cols_rows: u32) {
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
    pub(super) fn select<V: Lanes>(&self, u: usize, out: &mut Vec<f32>) -> usize {
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
    pub(super) fn lanes(&self, at: u32, u: usize) -> u32 {
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
pub(super) fn spread_rows(r: u32) -> u32 {
    (r & 1) | ((r & 2) << 3) | ((r & 4) << 6) | ((r & 8) << 9)
}

/// Appends each splat of the tile's list to the lists of the units of one row (4 lanes)
/// its footprint reaches, with the unit's lanes in the row's span of the α >= 1/255
/// ellipse (the whole rectangle row where the spans cannot be trusted), so that units
/// the ellipse misses get no entry. The pixels of an entry's lanes outside the ellipse
/// fail the alpha test. Entries name their splat by its position in the list; `ids`, if
/// given, receives the Gaussian id of every position.
#[inline(always)]
pub(super) fn distribute_rows(
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
pub(super) fn for_each_clipped(
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
pub(super) fn row_span(sp: &Splat, py: usize, cx0: usize, cx1: usize) -> Option<(usize, usize)> {
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
pub(super) const POWER_FLOOR: f32 = -40.0;

/// How many list entries ahead [`for_each_clipped`] prefetches a splat (at 6 the id reads
/// of `TileRects::build` waited on memory; 16 and 32 measured alike).
pub(super) const PREFETCH_AHEAD: usize = 16;

/// Extra width, in pixels, of each per-row span beyond the solved ellipse bounds: far above
/// the f32 rounding of those bounds (the exponent margin of `Splat::two_a_tau` adds more).
pub(super) const SPAN_SLACK: f32 = 1.0 / 64.0;

/// Where a unit's results go: the tile's per-pixel arrays (row-major) and its top-K lists.
pub(super) struct UnitOut<'a> {
    pub(super) t: &'a mut [f32; TILE_PIXELS],
    pub(super) r: &'a mut [f32; TILE_PIXELS],
    pub(super) g: &'a mut [f32; TILE_PIXELS],
    pub(super) b: &'a mut [f32; TILE_PIXELS],
    pub(super) depth: &'a mut [f32; TILE_PIXELS],
    pub(super) wsum: &'a mut [f32; TILE_PIXELS],
    pub(super) lw: &'a mut [f32],
    pub(super) lid: &'a mut [f32],
    /// The Gaussian ids by list position where the lists carry ids, else `None`.
    pub(super) ids: Option<&'a [u32]>,
    pub(super) fill: &'a mut [u16],
    pub(super) k: usize,
    #[cfg_attr(not(feature = "counters"), allow(dead_code))]
    pub(super) counts: &'a mut BlendCounts,
}

/// The running state of one unit's N pixels.
pub(super) struct UnitState<V: Lanes> {
    pub(super) t: V,
    pub(super) r: V,
    pub(super) g: V,
    pub(super) b: V,
    pub(super) depth: V,
    pub(super) wsum: V,
    /// Lanes that have stopped (T would fall below 1e-4, or the list is final) or lie
    /// outside the image.
    pub(super) done: V::Mask,
}

/// One unit (number `unit` of the tile, whose top-left pixel is image pixel (`px0`, `py0`)
/// and tile pixel `at`) over the `entries` that reach it, front to back (taken [`BATCH`]
/// at a time, and no more once every lane has stopped): INRIA's per-pixel step on all
/// lanes at once (lanes outside an entry's footprint masked off). With `TOPK`, pixels
/// whose weight beats their list's K-th enter their top-K list; with `CUTOFF` (lists only)
/// a pixel also stops once its list is final. Writes T, the sums and the lists into
/// `out`.
#[inline(always)]
pub(super) fn blend_unit<V: Lanes, const TOPK: bool, const CUTOFF: bool>(
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
    let mut s = UnitState::<V>::new(valid);
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
    let pixel = [
        V::splat(px0 as f32) + V::unit_columns(),
        V::splat(py0 as f32) + V::unit_rows(),
    ];
    // Entries go in batches: first every α of the batch (long chains of exp, independent of
    // the unit's state, so they overlap), then the compositing in depth order (short
    // chains through T). One entry at a time, the out-of-order window held only about two
    // of those exp chains.
    let mut alpha = [zero; BATCH];
    let mut reach = [V::from_bits(0); BATCH];
    let mut pending = [UnitEntry { at: 0, lanes: 0 }; BATCH];
    'walk: loop {
        let len = next_batch(&mut entries, &mut pending);
        let batch = &pending[..len];
        batch_alpha::<V>(batch, splats, list, s.done, pixel, &mut alpha, &mut reach);
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
                    let id = V::splat(f32::from_bits(list_payload(out.ids, e.at)));
                    kth = insert_group::<V>(lw, lid, k, fill, cand, w, id);
                    // One more entry in each candidate lane (or one replaced when full).
                    fill = (fill + 1).min(k);
                }
                if CUTOFF {
                    s.stop_final_lists(kth);
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
    s.store::<CUTOFF>(out, [unit, at], fill);
}

impl<V: Lanes> UnitState<V> {
    /// The state before any splat: T = 1, zero sums; the lanes outside `valid` (the
    /// image) are stopped.
    #[inline(always)]
    pub(super) fn new(valid: V::Mask) -> Self {
        let zero = V::splat(0.0);
        UnitState {
            t: V::splat(1.0),
            r: zero,
            g: zero,
            b: zero,
            depth: zero,
            wsum: zero,
            done: !valid,
        }
    }

    /// Stops the lanes whose top-K list is final (lists-only renders): a later contributor
    /// weighs ω = T·α < T (α <= 0.99, T never grows), so once T <= the K-th weight `kth`
    /// of a full list (> 0) nothing can enter: the pixel's list is final and it stops here.
    #[inline(always)]
    pub(super) fn stop_final_lists(&mut self, kth: V) {
        let full = kth.gt(V::splat(0.0));
        self.done = self.done | (full & self.t.le(kth));
    }

    /// Writes the unit's results into `out`: its lists' fill (the longest list's length)
    /// for unit `unit`, then T and, unless `CUTOFF` (lists only), the sums from tile pixel
    /// `at`.
    #[inline(always)]
    pub(super) fn store<const CUTOFF: bool>(
        &self,
        out: &mut UnitOut<'_>,
        [unit, at]: [usize; 2],
        fill: usize,
    ) {
        if let Some(f) = out.fill.get_mut(unit) {
            // At most K <= MAX_TOP_K: fits.
            *f = fill as u16;
        }
        store_unit(self.t, out.t, at);
        if !CUTOFF {
            store_unit(self.r, out.r, at);
            store_unit(self.g, out.g, at);
            store_unit(self.b, out.b, at);
            store_unit(self.depth, out.depth, at);
            store_unit(self.wsum, out.wsum, at);
        }
    }
}

/// Takes the next [`BATCH`] entries (fewer at the end) into `pending`; returns how many.
#[inline(always)]
pub(super) fn next_batch(
    entries: &mut impl Iterator<Item = UnitEntry>,
    pending: &mut [UnitEntry; BATCH],
) -> usize {
    let mut len = 0;
    for slot in pending {
        let Some(e) = entries.next() else {
            break;
        };
        *slot = e;
        len += 1;
    }
    len
}

/// The first half of a batch of [`blend_unit`]: every entry's α over the unit's lanes
/// (`alpha`) and the lanes it reaches with α >= 1/255 (`reach`), for the lanes of its
/// footprint that are not `done`; an entry reaching no such lane reaches none.
#[inline(always)]
pub(super) fn batch_alpha<V: Lanes>(
    batch: &[UnitEntry],
    splats: &[Splat],
    list: &[RowEntry],
    done: V::Mask,
    [px, py]: [V; 2],
    alpha: &mut [V; BATCH],
    reach: &mut [V::Mask; BATCH],
) {
    for ((e, a), m) in batch.iter().zip(alpha).zip(reach) {
        let lanes = V::from_bits(e.lanes) & !done;
        *m = lanes;
        if V::bits(lanes) == 0 {
            continue;
        }
        if let Some(sp) = splat_at(splats, list, e.at) {
            (*a, *m) = footprint_alpha::<V>(sp, lanes, px, py);
        }
    }
}

/// What a top-K list holds for the entry at list position `at`: its Gaussian id where the
/// lists carry ids (`ids`), else the position.
#[inline(always)]
pub(super) fn list_payload(ids: Option<&[u32]>, at: u32) -> u32 {
    match ids {
        Some(ids) => ids.get(at as usize).copied().unwrap_or(NO_GAUSSIAN),
        None => at,
    }
}

/// Stores a unit's lanes into a row-major tile array, from tile pixel `at` (its top-left):
/// [`UNIT_W`] lanes per row.
#[inline(always)]
pub(super) fn store_unit<V: Lanes>(v: V, dst: &mut [f32; TILE_PIXELS], at: usize) {
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
pub(super) fn insert_group<V: Lanes>(
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
pub(super) const BATCH: usize = 8;

/// The splat at position `at` of a tile's list.
#[inline(always)]
pub(super) fn splat_at<'a>(splats: &'a [Splat], list: &[RowEntry], at: u32) -> Option<&'a Splat> {
    list.get(at as usize)
        .and_then(|&(e, _)| splats.get(e as usize))
}

/// The first half of INRIA's per-pixel step of splat `sp` for the N pixels of a unit, whose
/// centres are (`px`, `py`) lane by lane: power = −½(a dx² + c dy²) − b dx dy,
/// α = min(0.99, o·exp(power)); returns α and the lanes of `lanes` with power <= 0 and
/// α >= 1/255. Every lane performs the same IEEE operations in the same order as the
/// scalar reference.
#[inline(always)]
pub(super) fn footprint_alpha<V: Lanes>(sp: &Splat, lanes: V::Mask, px: V, py: V) -> (V, V::Mask) {
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
pub(super) fn composite<V: Lanes>(
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

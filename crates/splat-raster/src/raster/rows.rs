//! Tile rows in parallel: each row's output slices, its tiles rendered one after the other, and
//! the finished tiles (pixels and top-K lists) copied into the view's buffers.

use super::*;

/// Output slices of one tile row (16 image rows, or fewer at the bottom).
pub(super) struct RowOut<'a> {
    pub(super) ty: usize,
    pub(super) color: Option<&'a mut [f32]>,
    pub(super) depth: Option<&'a mut [f32]>,
    pub(super) alpha: Option<&'a mut [f32]>,
    pub(super) transmittance: Option<&'a mut [f32]>,
    pub(super) ids: Option<&'a mut [u32]>,
    pub(super) weights: Option<&'a mut [f32]>,
    /// The row's tiles' [`ViewRender::padded`] flags.
    pub(super) padded: &'a mut [bool],
}

pub(super) fn row_chunks<T>(buf: &mut [T], row_len: usize, rows: usize) -> Vec<Option<&mut [T]>> {
    if buf.is_empty() || row_len == 0 {
        (0..rows).map(|_| None).collect()
    } else {
        buf.chunks_mut(row_len * TILE).map(Some).collect()
    }
}

/// Sums two rows' (tile pair count, blend counts).
pub(super) fn add_rows(a: (usize, BlendCounts), b: (usize, BlendCounts)) -> (usize, BlendCounts) {
    (a.0 + b.0, a.1.add(b.1))
}

/// Rasterises every tile of the view in parallel over tile rows; returns the number of
/// (tile, Gaussian) pairs and the blend counts.
pub(super) fn blend(
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
/// The output slots of one tile's top-K lists: pixel (row, col) of the tile owns the K
/// slots at `row * stride + base + col * k` of its tile row's buffers.
pub(super) struct TopKOut<'a> {
    pub(super) k: usize,
    /// W · K: one image row of lists.
    pub(super) stride: usize,
    /// x0 · K: the tile's first column.
    pub(super) base: usize,
    pub(super) w: &'a mut [f32],
    pub(super) id: &'a mut [u32],
    /// Beside `id`, the entries' positions in the tile's list; empty where the render
    /// hands out no positions.
    pub(super) at: &'a mut [u32],
}
pub(super) struct Ctx<'a> {
    pub(super) splats: &'a [Splat],
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) tiles_x: usize,
    pub(super) k: usize,
    /// Only the top-K lists are wanted (no colour, depth, alpha or T, as registration
    /// renders): a pixel then stops as soon as its list is final (see `blend_unit`).
    pub(super) lists_only: bool,
    pub(super) opts: &'a RenderOptions,
    pub(super) level: Level,
}

/// Renders the tiles of one tile row; returns its (tile, Gaussian) pair count and blend
/// counts.
pub(super) fn render_row(
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
/// Renders the lists of one tile row tile by tile into the worker's tile buffers and hands
/// each tile to `consume` with the row's state; returns the row's (tile, splat) pair count.
pub(super) fn consume_row<R, F>(
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
pub(super) fn pad_lists(out: &mut TopKOut<'_>, cols: usize, rows: usize) {
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
pub(super) fn write_lists<const N: usize>(
    out: &mut TopKOut<'_>,
    cols: usize,
    rows: usize,
    st: &TileScratch,
) {
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
pub(super) fn transpose_lane<const N: usize>(dst: &mut [f32], src: &[f32], lane: usize, pad: f32) {
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
/// Copies a finished tile into the tile row's output slices.
pub(super) fn write_tile(
    ctx: &Ctx<'_>,
    row: &mut RowOut<'_>,
    [x0, x1, y0, y1]: [usize; 4],
    st: &TileScratch,
) {
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

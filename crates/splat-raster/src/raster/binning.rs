//! Binning: every Gaussian projected in fixed chunks straight into the view's splat buffer, the
//! survivors sorted by (depth, id), then bucketed by tile row and, per row, by tile column.

use super::*;

/// Slots (Gaussians) projected per job of [`Rasterizer::bin`]: fixed, so that the jobs do
/// not depend on the thread count.
pub(super) const PROJECT_CHUNK: usize = 1 << 14;

impl Rasterizer<'_> {
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
    pub(super) fn bin(&self, cam: &ViewCamera, shade: bool, s: &mut ViewScratch) -> Phases {
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

/// Filler of the view's splat buffer in the slots of culled Gaussians (never read).
pub(super) const UNUSED_SPLAT: Splat = Splat {
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
pub(super) type RowEntry = (u32, [u16; 4]);

/// Splats per job of [`bucket_by_row`] (fixed, so the jobs do not depend on the thread
/// count; the result does not depend on them at all).
pub(super) const ROW_BUCKET_BLOCK: usize = 1 << 16;

/// Lists the depth-ordered `splats` (their positions and rectangles) of every tile row in
/// order: row ty's entries are `entries[start[ty]..start[ty + 1]]`. Blocks of `block`
/// splats count their rows in parallel, then each block fills its own slice of every row
/// (the slices follow the block order, so every row stays in depth order and the result
/// does not depend on `block`).
pub(super) fn bucket_by_row(
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

/// Buckets a tile row's splats (depth-sorted) by tile column, keeping the order: tile tx's
/// splats are `list[start[tx]..start[tx + 1]]`. Returns the (tile, splat) pair count.
pub(super) fn bucket_by_tile(
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

//! The rasterizer of one Gaussian set: binning of projected Gaussians into 16x16 tiles and
//! the per-tile front-to-back blend. Its parts: `output` (what a render hands out),
//! `binning` and `sort` (projection, depth order, tile buckets), `rows` (tile rows in
//! parallel and their outputs), `scratch` (a worker's tile buffers) and `tile_blend` (the
//! blend of one tile, SIMD unit by unit).

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

mod binning;
mod output;
mod rows;
mod scratch;
mod sort;
mod tile_blend;

use binning::*;
pub use output::*;
use rows::*;
use scratch::*;
use sort::*;
use tile_blend::*;

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

//! The depth order of a view's splats: sort keys and records, made while each splat is in
//! cache, and the bucketed radix sort by (depth, id).

use super::*;

/// Sort key of a splat: its camera depth (positive, finite: the bits of a positive f32
/// order as the value) above its position in the view's splats, which is its Gaussian's
/// slot: equal depths order by slot, and `sort_by_depth` reorders those ties by id, as the
/// (depth, id) rule requires.
#[inline]
pub(super) fn depth_key(depth: f32, position: u32) -> u64 {
    (u64::from(depth.to_bits()) << 32) | u64::from(position)
}

/// The position of a [`depth_key`].
#[inline]
pub(super) fn key_position(key: u64) -> u32 {
    key as u32
}
/// A splat's place in the depth order: its [`depth_key`] and its pixel rectangle (carried
/// along so that bucketing by tile row reads no splat).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(super) struct DepthRecord {
    pub(super) key: u64,
    pub(super) rect: [u16; 4],
}

/// One projection chunk's [`DepthRecord`]s (in slot order) and the range of their depth bits.
#[derive(Debug, Default)]
pub(super) struct ChunkRecords {
    pub(super) records: Vec<DepthRecord>,
    pub(super) depth_bits: Option<(u32, u32)>,
}

/// The [`SplatSink`] of one projection chunk: each splat goes to its slot in the view's
/// splats (culled slots keep whatever they held), and its sort record is made while it is
/// in cache.
pub(super) struct ChunkOut<'a> {
    pub(super) splats: &'a mut [Splat],
    pub(super) first: usize,
    pub(super) records: &'a mut ChunkRecords,
}

impl<'a> ChunkOut<'a> {
    pub(super) fn new(
        splats: &'a mut [Splat],
        first: usize,
        records: &'a mut ChunkRecords,
    ) -> Self {
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
pub(super) const SPLATS_PER_BUCKET: usize = 64;
/// Projection chunks per job of [`sort_by_depth`]'s counting and scattering.
pub(super) const SORT_BLOCK_CHUNKS: usize = 8;

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
pub(super) fn sort_by_depth(
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
pub(super) fn order_ties_by_id(records: &mut [DepthRecord], id_of: &impl Fn(u32) -> u32) {
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
pub(super) fn carve_by_block<'a, T>(
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

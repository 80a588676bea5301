//! Fast-scan search: a 4-bit first pass over every vector, with 16-entry lookup tables
//! in SIMD registers, whose candidates go through the 8-bit ADC and the exact re-rank of
//! [`crate::search`].
//!
//! # Design
//!
//! The 8-bit pass of [`crate::search`] costs one table load per code byte, from a
//! 128 KiB table: bound by loads, not by memory. faiss's fast-scan instead stores 4-bit
//! codes, so that a sub-quantiser's 16 table entries fit in one SIMD register and a byte
//! shuffle looks up 32 or 64 vectors at once; it is then bound by reading the codes.
//! Here the 4-bit codes come from the 8-bit ones, so the file and its recall stay as
//! they are:
//!
//! * **Coarse codes.** Per sub-quantiser the 256 centroids are grouped into 16 by a
//!   k-means over the centroids weighted by how many vectors use each (usage-weighted
//!   means, so a group's centroid is the mean of the sub-vectors it stands for). A
//!   vector's 4-bit code in a subspace is the group of its 8-bit code. 128 sub-quantisers
//!   give 64 bytes a vector, half of what faiss's fast-scan (256 x 4 bits) reads.
//! * **Layout.** Built once per pq ([`FastScan::new`]), in memory: blocks of 32 vectors,
//!   per pair of sub-quantisers 32 bytes (two nibbles a byte; see the `scan4` module),
//!   in anonymous memory advised for transparent huge pages (the pass streams it: on
//!   4 KiB pages the prefetchers stop at every page boundary).
//! * **Coarse scores.** Per query the groups' inner products with the query, shifted to
//!   start at 0 per subspace and scaled by one factor so that the largest is 127, are
//!   rounded to u8; a vector's coarse score is the u16 sum of its M entries (AVX-512,
//!   AVX2 or portable kernel, chosen at run time; integer sums, so all give the same
//!   scores). Each block also records its largest score.
//! * **Candidates.** Round 0 takes every vector scoring at least the `max(k, 1024)`-th
//!   largest block maximum (at least that many vectors, about the coarse top). Each
//!   candidate gets its 8-bit ADC inner product and cosine, exactly as in
//!   [`crate::search`], and its *residual*: ADC inner product minus the coarse estimate.
//!   Let `c` be the `k`-th best ADC cosine so far less twice the largest possible
//!   difference between an ADC cosine and the exact one (f32 rounding, `adc_slack`), and
//!   `E` the margin: the largest residual seen, or the residuals' mean plus
//!   `sqrt(2 ln V)` standard deviations (about the largest of `V` normal draws, `V` the
//!   valid vectors; a residual is a sum of M nearly independent terms) if that is more.
//!   A vector that is not yet a candidate can only reach the top `k` if its coarse
//!   estimate is at least `c·|q|·norm − E`; every such vector is scored too, and the
//!   rounds repeat until none is left. The margin is measured on the query's own
//!   candidates, not tuned: a vector is missed only if its residual exceeds it. A pass
//!   over every score also keeps the vectors within one more margin below its floor (the
//!   *reserve*): the floor falls a little each round as the margin grows, and the later
//!   rounds, whose floors stay above the reserve's, take their candidates from it
//!   instead of reading every score again (the same candidates; tested).
//! * **Re-rank.** Every candidate whose ADC cosine is at least `c` (at least `k` of
//!   them) is re-ranked by the exact cosine ([`crate::exact_cosine`]), so the result is
//!   the exact top `k` over all vectors (what [`crate::search`] returns when its
//!   shortlist absorbs the rounding), ties by id. Tests compare it with a brute-force
//!   exact top `k`; `pq bench` reports how often it equals [`crate::search`]'s.

use profuse_formats::{Pq, KSUB};
use rayon::prelude::*;

use crate::adc::{check_pq, cosine_of, exact_cosine, top_n, LookupTable};
use crate::scan4::{self, byte_of_vector, Kernel, BLOCK};
use crate::PqError;

mod grouping;

use grouping::*;

/// Groups (4-bit codes) per sub-quantiser.
const GROUPS: usize = 16;
/// Lloyd iterations of the grouping (256 points in dsub dimensions: microseconds each).
const GROUP_ITERS: usize = 25;
/// Blocks scanned per rayon task: 32 K vectors, 2 MiB of 4-bit codes for M = 128.
const BLOCKS_PER_TASK: usize = 1024;
/// Vectors counted per rayon task when measuring code usage.
const USAGE_CHUNK: usize = 8192;
/// Candidates rescored per rayon task.
const RESCORE_CHUNK: usize = 2048;
/// Fewest candidates of round 0: the residuals' spread is measured on at least this many
/// vectors (the standard error of a standard deviation from 1024 samples is about 2%).
const MIN_SAMPLE: usize = 1024;

/// A pq prepared for fast-scan search: the 4-bit coarse codes in SIMD block layout and
/// the grouping that defines them. Build once per pq (it reads every code), then query
/// with [`FastScan::search`] against that same pq.
#[derive(Debug, Clone)]
pub struct FastScan {
    n: usize,
    m: usize,
    dsub: usize,
    /// Valid vectors.
    valid: usize,
    /// Pairs of sub-quantisers in the layout (M rounded up to a multiple of 4, halved).
    pairs: usize,
    /// Group of each 8-bit code, per sub-quantiser.
    group_of: Vec<[u8; KSUB]>,
    /// Whether a group has any member code, per sub-quantiser (bit g).
    used: Vec<u16>,
    /// Group centroids `[M, 16, dsub]`.
    group_centroids: Vec<f32>,
    /// `[blocks, pairs, 32]` bytes.
    packed: HugeBytes,
    /// Smallest and largest decoded norm of a valid vector (1, 1 when none is valid).
    norm_range: (f32, f32),
    kernel: Kernel,
    /// The coarse score buffers, kept between searches.
    scratch: ScratchSlot,
}

/// Zeroed bytes in anonymous memory advised for transparent huge pages, for the packed
/// 4-bit codes that every query streams through: with 4 KiB pages the hardware
/// prefetchers stop at every page boundary (and each page needs a TLB entry), and the
/// 4-bit pass over a million codes took ~2.6-3.2 ms of a fresh process's query against
/// ~1.3-1.5 ms on 2 MiB pages. Falls back to a plain vector where no mapping can be
/// made (then only the speed differs).
#[derive(Debug)]
enum HugeBytes {
    Mapped(memmap2::MmapMut),
    Plain(Vec<u8>),
}

impl HugeBytes {
    fn zeroed(len: usize) -> HugeBytes {
        if len == 0 {
            return HugeBytes::Plain(Vec::new());
        }
        let Ok(map) = memmap2::MmapOptions::new().len(len).map_anon() else {
            return HugeBytes::Plain(vec![0; len]);
        };
        // Best effort: without huge pages these are ordinary pages.
        #[cfg(target_os = "linux")]
        let _ = map.advise(memmap2::Advice::HugePage);
        HugeBytes::Mapped(map)
    }
}

impl std::ops::Deref for HugeBytes {
    type Target = [u8];
    fn deref(&self) -> &[u8] {
        match self {
            HugeBytes::Mapped(m) => m,
            HugeBytes::Plain(v) => v,
        }
    }
}

impl std::ops::DerefMut for HugeBytes {
    fn deref_mut(&mut self) -> &mut [u8] {
        match self {
            HugeBytes::Mapped(m) => m,
            HugeBytes::Plain(v) => v,
        }
    }
}

impl Clone for HugeBytes {
    fn clone(&self) -> Self {
        let mut copy = HugeBytes::zeroed(self.len());
        copy.copy_from_slice(self);
        copy
    }
}

/// The coarse scores of one search (2 bytes a vector) and each block's largest.
#[derive(Debug, Default)]
struct Scratch {
    scores: Vec<u16>,
    maxima: Vec<u16>,
}

impl Scratch {
    /// Buffers for `blocks` blocks, every page written once: a search that writes them
    /// then pays no first-touch page faults (~2 MB a million vectors, ~0.3 ms).
    fn touched(blocks: usize) -> Scratch {
        let mut s = Scratch::default();
        s.size_for(blocks);
        s
    }

    /// Sizes the buffers for `blocks` blocks (a no-op when they are).
    fn size_for(&mut self, blocks: usize) {
        self.scores.resize(blocks * BLOCK, 0);
        self.maxima.resize(blocks, 0);
    }
}

/// [`Scratch`] kept in the index, so that repeated searches reuse touched buffers; a
/// search that finds it in use (another thread searching) makes its own.
#[derive(Debug, Default)]
struct ScratchSlot(std::sync::Mutex<Scratch>);

impl Clone for ScratchSlot {
    fn clone(&self) -> Self {
        let blocks = self.0.lock().map_or(0, |s| s.maxima.len());
        ScratchSlot(std::sync::Mutex::new(Scratch::touched(blocks)))
    }
}

/// What one [`FastScan::search`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct FastScanStats {
    /// Vectors whose 8-bit ADC score was computed (valid candidates of all rounds).
    pub candidates: usize,
    /// Candidate rounds (1 when round 0's candidates already satisfied the margin).
    pub rounds: usize,
    /// The margin: the largest residual (ADC inner product minus coarse estimate) the
    /// last round allowed for.
    pub margin: f64,
    /// Candidates re-ranked by their exact cosine.
    pub reranked: usize,
    /// Milliseconds of the 4-bit scan (tables and every vector's coarse score).
    pub scan_ms: f64,
    /// The scan kernel: `avx512`, `avx2` or `portable`.
    pub kernel: &'static str,
}

impl FastScan {
    /// Groups every sub-quantiser's centroids and packs the 4-bit codes of `pq`.
    pub fn new(pq: &Pq) -> Result<Self, PqError> {
        check_pq(pq)?;
        let (n, m, dsub) = (pq.len(), pq.m, pq.dsub);
        let usage = code_usage(pq);
        let grouped: Vec<Grouping> = (0..m)
            .into_par_iter()
            .map(|s| {
                let cents = &pq.centroids[s * KSUB * dsub..(s + 1) * KSUB * dsub];
                group_centroids(cents, &usage[s * KSUB..(s + 1) * KSUB], dsub)
            })
            .collect();
        let group_of: Vec<[u8; KSUB]> = grouped.iter().map(|g| g.group_of).collect();
        let used = group_of
            .iter()
            .map(|g| g.iter().fold(0u16, |bits, &x| bits | 1 << x))
            .collect();
        let group_centroids = grouped.iter().flat_map(|g| g.centroids.clone()).collect();
        let pairs = m.div_ceil(4) * 2;
        let packed = pack(pq, &group_of, pairs);
        let norms = pq
            .norms
            .iter()
            .zip(pq.valid.iter())
            .filter(|&(_, &v)| v == 1)
            .map(|(&x, _)| x);
        let norm_range = norms
            .fold(None, |r: Option<(f32, f32)>, x| {
                Some(r.map_or((x, x), |(lo, hi)| (lo.min(x), hi.max(x))))
            })
            .unwrap_or((1.0, 1.0));
        Ok(FastScan {
            n,
            m,
            dsub,
            valid: pq.valid.iter().filter(|&&v| v == 1).count(),
            pairs,
            group_of,
            used,
            group_centroids,
            packed,
            norm_range,
            kernel: Kernel::detect(),
            scratch: ScratchSlot(std::sync::Mutex::new(Scratch::touched(n.div_ceil(BLOCK)))),
        })
    }

    /// The group (4-bit code) of 8-bit code `code` of sub-quantiser `s`.
    pub fn group_of(&self, s: usize, code: u8) -> u8 {
        self.group_of[s][usize::from(code)]
    }

    /// Bytes held for the packed 4-bit codes.
    pub fn packed_bytes(&self) -> usize {
        self.packed.len()
    }

    /// The scan kernel this CPU runs: `avx512`, `avx2` or `portable`.
    pub fn kernel(&self) -> &'static str {
        self.kernel.name()
    }

    /// Top-`k` valid vectors by exact cosine with their decoded vectors (computed in
    /// f64), best first, ties by id, like [`crate::search`]: the 4-bit scan finds the
    /// candidates, the 8-bit ADC scores them, and every candidate whose ADC cosine can
    /// still reach the top `k` is re-ranked exactly (module docs). `pq` must be the pq
    /// this was built from.
    pub fn search(
        &self,
        pq: &Pq,
        query: &[f32],
        k: usize,
    ) -> Result<(Vec<(u32, f32)>, FastScanStats), PqError> {
        self.search_rounds(pq, query, k, true)
    }

    /// [`FastScan::search`]; without `reserve` every round reads every score (the
    /// reference the reserve is tested against).
    fn search_rounds(
        &self,
        pq: &Pq,
        query: &[f32],
        k: usize,
        use_reserve: bool,
    ) -> Result<(Vec<(u32, f32)>, FastScanStats), PqError> {
        self.check_same_shape(pq)?;
        let lut = LookupTable::new(pq, query)?;
        let mut stats = FastScanStats {
            candidates: 0,
            rounds: 0,
            margin: 0.0,
            reranked: 0,
            scan_ms: 0.0,
            kernel: self.kernel.name(),
        };
        if k == 0 || self.valid == 0 {
            return Ok((Vec::new(), stats));
        }
        let started = std::time::Instant::now();
        let coarse = CoarseTable::new(self, query);
        let mut own = Scratch::default();
        let mut slot = self.scratch.0.try_lock().ok();
        let buffers = slot.as_deref_mut().unwrap_or(&mut own);
        self.coarse_scores(&coarse, buffers);
        let (scores, maxima) = (&buffers.scores[..], &buffers.maxima[..]);
        stats.scan_ms = started.elapsed().as_secs_f64() * 1e3;
        let mut pool = Candidates::new(self.n, self.valid);
        let first = kth_largest(maxima, k.max(MIN_SAMPLE)).unwrap_or(0);
        let mut fresh = self
            .collect(
                pq,
                scores,
                maxima,
                &pool,
                |u, _| u >= first,
                f64::from(first),
                None,
            )
            .0;
        let slack = adc_slack(self.m);
        let mut bar = f32::NEG_INFINITY;
        let mut reserve = Reserve::default();
        while !fresh.is_empty() {
            stats.rounds += 1;
            pool.add(pq, &lut, &coarse, scores, fresh);
            let Some(threshold) = pool.threshold(k, slack) else {
                // Fewer than k valid candidates: every valid vector is one.
                let every = |_, _| true;
                fresh = self
                    .collect(pq, scores, maxima, &pool, every, f64::NEG_INFINITY, None)
                    .0;
                continue;
            };
            bar = threshold.cosine as f32;
            let need = |norm: f32| coarse.units(threshold.required_ip(lut.query_norm(), norm));
            let (lo_norm, hi_norm) = self.norm_range;
            let lowest = need(lo_norm).min(need(hi_norm));
            let keep = |u: u16, norm: f32| f64::from(u) >= need(norm);
            if reserve.covers(lowest) {
                fresh = reserve.take(pq, scores, keep);
                continue;
            }
            // The later rounds' floors fall as the margin grows (the largest residual
            // among more candidates): keep the vectors within one more margin below
            // this floor, so that those rounds look at them instead of every vector.
            let below = lowest - threshold.margin * coarse.scale;
            let below = use_reserve.then_some(below);
            let (taken, kept) = self.collect(pq, scores, maxima, &pool, keep, lowest, below);
            fresh = taken;
            if let Some(below) = below {
                reserve = Reserve::new(below, kept);
            }
        }
        stats.candidates = pool.len();
        stats.margin = pool.margin;
        // Every candidate whose ADC cosine can still reach the top k (at least k of them).
        let reach: Vec<(u32, f32)> = pool
            .scored()
            .iter()
            .copied()
            .filter(|&(_, c)| c >= bar)
            .collect();
        let best = if reach.len() >= k {
            reach
        } else {
            top_n(pool.scored().to_vec(), k)
        };
        stats.reranked = best.len();
        let reranked: Vec<(u32, f32)> = best
            .par_iter()
            .map(|&(id, _)| (id, exact_cosine(pq, id as usize, query)))
            .collect();
        Ok((top_n(reranked, k), stats))
    }

    fn check_same_shape(&self, pq: &Pq) -> Result<(), PqError> {
        check_pq(pq)?;
        if (pq.len(), pq.m, pq.dsub) != (self.n, self.m, self.dsub) {
            return Err(PqError::Inconsistent(format!(
                "fast-scan index of {} vectors x M {} x dsub {} queried against a pq of {} x {} x {}",
                self.n,
                self.m,
                self.dsub,
                pq.len(),
                pq.m,
                pq.dsub
            )));
        }
        Ok(())
    }

    /// Coarse u16 score of every vector (32 a block, padding included) and each block's
    /// largest, into `out` (every element written).
    fn coarse_scores(&self, coarse: &CoarseTable, out: &mut Scratch) {
        out.size_for(self.n.div_ceil(BLOCK));
        let per_block = self.pairs * BLOCK;
        let Scratch { scores, maxima } = out;
        scores
            .par_chunks_mut(BLOCKS_PER_TASK * BLOCK)
            .zip(maxima.par_chunks_mut(BLOCKS_PER_TASK))
            .zip(self.packed.par_chunks(BLOCKS_PER_TASK * per_block))
            .for_each(|((s, mx), packed)| {
                scan4::scan(
                    self.kernel,
                    packed,
                    &coarse.lo,
                    &coarse.hi,
                    self.pairs,
                    s,
                    mx,
                );
            });
    }

    /// Valid vectors not yet in `pool` whose coarse score `u` passes `keep(u, norm)`,
    /// ascending, and with `reserve` (a floor below `lowest`) the others scoring at
    /// least that floor ([`Reserve`]), ascending. `keep` may only pass scores of at
    /// least `lowest`: blocks whose maximum is below the lower floor are skipped, and
    /// inside a block one integer comparison rejects most vectors before `keep` is asked.
    #[allow(clippy::too_many_arguments)]
    fn collect(
        &self,
        pq: &Pq,
        scores: &[u16],
        maxima: &[u16],
        pool: &Candidates,
        keep: impl Fn(u16, f32) -> bool + Sync,
        lowest: f64,
        reserve: Option<f64>,
    ) -> (Vec<u32>, Vec<u32>) {
        let lowest = reserve.map_or(lowest, |r| r.min(lowest));
        if lowest > f64::from(u16::MAX) {
            return (Vec::new(), Vec::new());
        }
        let floor = lowest.ceil().max(0.0) as u16;
        let keeps_reserve = reserve.is_some();
        let per_task: Vec<(Vec<u32>, Vec<u32>)> = maxima
            .par_chunks(BLOCKS_PER_TASK)
            .enumerate()
            .map(|(task, mx)| {
                let (mut out, mut kept) = (Vec::new(), Vec::new());
                for (i, &max) in mx.iter().enumerate() {
                    if max < floor {
                        continue;
                    }
                    let start = (task * BLOCKS_PER_TASK + i) * BLOCK;
                    let block = &scores[start..start + BLOCK];
                    let mut passing = block
                        .iter()
                        .enumerate()
                        .fold(0u32, |bits, (v, &u)| bits | u32::from(u >= floor) << v);
                    while passing != 0 {
                        let v = passing.trailing_zeros() as usize;
                        passing &= passing - 1;
                        let n = start + v;
                        if n >= self.n || pq.valid[n] != 1 || pool.has(n) {
                            continue;
                        }
                        if keep(block[v], pq.norms[n]) {
                            out.push(n as u32);
                        } else if keeps_reserve {
                            kept.push(n as u32);
                        }
                    }
                }
                (out, kept)
            })
            .collect();
        let (out, kept): (Vec<Vec<u32>>, Vec<Vec<u32>>) = per_task.into_iter().unzip();
        (out.concat(), kept.concat())
    }
}

/// The valid vectors that a full pass over the scores found at or above `floor` but
/// did not take, ascending: every vector outside the pool that scores at least `floor`
/// is here, so a later round whose floor is no lower than this one (its `keep` passes
/// nothing below it) finds all its candidates among them, in the order a full pass
/// would (the same rounds and results, without reading every score again).
#[derive(Default)]
struct Reserve {
    /// None until a pass has filled it.
    floor: Option<f64>,
    ids: Vec<u32>,
}

impl Reserve {
    fn new(floor: f64, ids: Vec<u32>) -> Self {
        // The pass kept integer scores u >= ceil(floor).
        Reserve {
            floor: Some(floor.ceil()),
            ids,
        }
    }

    /// Whether a round whose `keep` passes no score below `lowest` finds all its
    /// candidates here.
    fn covers(&self, lowest: f64) -> bool {
        self.floor.is_some_and(|f| lowest >= f)
    }

    /// The kept vectors now passing `keep` (removed from the reserve), ascending. None of
    /// the kept vectors is in the pool: the pass kept only vectors outside it and apart
    /// from those it took, and the pool grows only by what a pass or `take` hands out.
    fn take(&mut self, pq: &Pq, scores: &[u16], keep: impl Fn(u16, f32) -> bool) -> Vec<u32> {
        let mut taken = Vec::new();
        self.ids.retain(|&id| {
            let n = id as usize;
            if keep(scores[n], pq.norms[n]) {
                taken.push(id);
                return false;
            }
            true
        });
        taken
    }
}

/// Per query: the quantised group tables in scan layout and how to turn a coarse score
/// back into an inner product.
struct CoarseTable {
    lo: Vec<u8>,
    hi: Vec<u8>,
    /// u16 units per unit of inner product.
    scale: f64,
    /// Sum over subspaces of the smallest group inner product.
    offset: f64,
}

impl CoarseTable {
    fn new(fs: &FastScan, query: &[f32]) -> Self {
        let dsub = fs.dsub;
        let table: Vec<[f64; GROUPS]> = (0..fs.m)
            .map(|s| {
                let q = &query[s * dsub..(s + 1) * dsub];
                std::array::from_fn(|g| {
                    let c =
                        &fs.group_centroids[(s * GROUPS + g) * dsub..(s * GROUPS + g + 1) * dsub];
                    q.iter()
                        .zip(c)
                        .map(|(&a, &b)| f64::from(a) * f64::from(b))
                        .sum()
                })
            })
            .collect();
        // Only groups with members count: an empty group's entry is never looked up.
        let span = |s: usize| {
            let used = (0..GROUPS).filter(|&g| fs.used[s] >> g & 1 == 1);
            let lo = used
                .clone()
                .map(|g| table[s][g])
                .fold(f64::INFINITY, f64::min);
            let hi = used.map(|g| table[s][g]).fold(f64::NEG_INFINITY, f64::max);
            (lo, hi)
        };
        let spans: Vec<(f64, f64)> = (0..fs.m).map(span).collect();
        let widest = spans.iter().map(|&(lo, hi)| hi - lo).fold(0.0, f64::max);
        // Two entries add in u8 and `pairs` pair sums in u16, so neither can overflow.
        let max_entry = (65_535 / (2 * fs.pairs)).min(127) as f64;
        let scale = if widest > 0.0 && widest.is_finite() {
            max_entry / widest
        } else {
            1.0
        };
        let mut lo = vec![0u8; fs.pairs * BLOCK];
        let mut hi = vec![0u8; fs.pairs * BLOCK];
        for s in 0..fs.m {
            let tab = if s % 2 == 0 { &mut lo } else { &mut hi };
            let row = &mut tab[(s / 2) * BLOCK..(s / 2 + 1) * BLOCK];
            for g in 0..GROUPS {
                let e = if fs.used[s] >> g & 1 == 1 {
                    ((table[s][g] - spans[s].0) * scale)
                        .round()
                        .clamp(0.0, max_entry) as u8
                } else {
                    0
                };
                row[g] = e;
                row[g + GROUPS] = e;
            }
        }
        let offset = spans.iter().map(|&(lo, _)| lo).sum();
        CoarseTable {
            lo,
            hi,
            scale,
            offset,
        }
    }

    /// The coarse estimate of an inner product, in u16 score units.
    fn units(&self, ip: f64) -> f64 {
        (ip - self.offset) * self.scale
    }

    /// The inner product a coarse score stands for.
    fn inner_product(&self, units: u16) -> f64 {
        f64::from(units) / self.scale + self.offset
    }
}

/// The vectors scored so far: id, ADC cosine, and the largest residual.
struct Candidates {
    scored: Vec<(u32, f32)>,
    member: Vec<u64>,
    /// Largest residual seen.
    largest: f64,
    /// Sum and sum of squares of the residuals (in candidate order: deterministic).
    sum: f64,
    sum_sq: f64,
    /// sqrt(2 ln V) for V valid vectors: about the largest of V standard normal draws.
    extreme: f64,
    margin: f64,
}

/// The ADC cosine a vector must reach to enter the shortlist, and the residual allowed.
struct Threshold {
    cosine: f64,
    margin: f64,
}

impl Threshold {
    /// The smallest coarse inner product that a vector of decoded norm `norm` can have
    /// and still reach the cosine, with the measured margin and f32 rounding slack.
    fn required_ip(&self, query_norm: f32, norm: f32) -> f64 {
        let ip = self.cosine * f64::from(query_norm) * f64::from(norm);
        ip - self.margin - 1e-5 * (ip.abs() + self.margin.abs()) - 1e-6
    }
}

impl Candidates {
    fn new(n: usize, valid: usize) -> Self {
        Candidates {
            scored: Vec::new(),
            member: vec![0; n.div_ceil(64)],
            largest: f64::NEG_INFINITY,
            sum: 0.0,
            sum_sq: 0.0,
            extreme: (2.0 * (valid.max(2) as f64).ln()).sqrt(),
            margin: 0.0,
        }
    }

    fn len(&self) -> usize {
        self.scored.len()
    }

    fn has(&self, n: usize) -> bool {
        self.member[n / 64] >> (n % 64) & 1 == 1
    }

    /// Scores `ids` with the 8-bit ADC and records their residuals.
    fn add(
        &mut self,
        pq: &Pq,
        lut: &LookupTable,
        coarse: &CoarseTable,
        scores: &[u16],
        ids: Vec<u32>,
    ) {
        let mut ips = vec![0f32; ids.len()];
        ids.par_chunks(RESCORE_CHUNK)
            .zip(ips.par_chunks_mut(RESCORE_CHUNK))
            .for_each(|(i, o)| lut.inner_products_of(&pq.codes, i, o));
        let scored = ids.iter().zip(&ips).map(|(&id, &ip)| {
            let n = id as usize;
            let residual = f64::from(ip) - coarse.inner_product(scores[n]);
            (id, cosine_of(ip, lut.query_norm(), pq.norms[n]), residual)
        });
        for (id, cos, residual) in scored {
            self.member[id as usize / 64] |= 1 << (id % 64);
            self.largest = self.largest.max(residual);
            self.sum += residual;
            self.sum_sq += residual * residual;
            self.scored.push((id, cos));
        }
        // The margin must cover the largest residual among all valid vectors, not only
        // among those seen: the mean plus sqrt(2 ln V) standard deviations (the expected
        // largest of V normal draws; a residual sums M nearly independent terms), or the
        // largest seen if that is more.
        let count = self.scored.len().max(1) as f64;
        let mean = self.sum / count;
        let sd = (self.sum_sq / count - mean * mean).max(0.0).sqrt();
        self.margin = self.largest.max(mean + self.extreme * sd).max(0.0);
    }

    /// The lowest ADC cosine that can still reach the top `k` (the `k`-th best so far
    /// less twice `slack`, the largest difference between an ADC cosine and the exact
    /// one) and the margin; `None` when there are fewer than `k` candidates or a
    /// non-finite cosine there.
    fn threshold(&self, k: usize, slack: f64) -> Option<Threshold> {
        if self.scored.len() < k {
            return None;
        }
        let mut cos: Vec<f32> = self.scored.iter().map(|&(_, c)| c).collect();
        let (_, kth, _) = cos.select_nth_unstable_by(k - 1, |a, b| b.total_cmp(a));
        kth.is_finite().then_some(Threshold {
            cosine: f64::from(*kth) - 2.0 * slack,
            margin: self.margin,
        })
    }

    /// Every candidate so far: id and ADC cosine.
    fn scored(&self) -> &[(u32, f32)] {
        &self.scored
    }
}

/// A bound on |ADC cosine − exact cosine| for M sub-quantisers: the M table entries are
/// each rounded once to f32 and summed in f32 (at most (M + 1) roundings of relative size
/// 2^-24 of a sum bounded by sqrt(M) |q| |x| (Cauchy–Schwarz over the subspaces)), the
/// cosine's division adds one more. Against cosines of order 1 this is about 1e-4 for
/// M = 128: the re-rank absorbs it.
fn adc_slack(m: usize) -> f64 {
    let eps = f64::from(f32::EPSILON) / 2.0;
    (m as f64 + 2.0) * eps * (m as f64).sqrt() + 1e-6
}

/// The `k`-th largest value (1-based), `None` when there are fewer than `k`.
fn kth_largest(values: &[u16], k: usize) -> Option<u16> {
    if k == 0 || k > values.len() {
        return None;
    }
    let mut v = values.to_vec();
    let (_, kth, _) = v.select_nth_unstable_by(k - 1, |a, b| b.cmp(a));
    Some(*kth)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::expect_used)]
    use super::{FastScan, HugeBytes, Reserve};
    use crate::synthetic::Clustered;

    /// The reserve only saves reading the scores again: every round takes the candidates
    /// a full pass would, so the candidate count, rounds, margin, re-ranked count and
    /// results all equal the reference's (a reserve that lost or added a vector would
    /// change the count, whether or not the top k moved).
    #[test]
    fn rounds_from_the_reserve_take_what_full_passes_take() {
        let mut later_rounds = 0;
        for (n, classes, seed) in [(100_000usize, 5usize, 42u64)] {
            let gen = Clustered::new(128, classes, 0.62, seed);
            let pq = gen.quick_pq(n, 32).expect("synthetic data trains");
            let fs = FastScan::new(&pq).expect("a valid pq");
            for qi in 0..3 {
                let q = gen.query(qi % classes, 0.5, qi as u64 + 7);
                for k in [100, 1] {
                    let timeless = |mut r: (Vec<(u32, f32)>, super::FastScanStats)| {
                        r.1.scan_ms = 0.0;
                        r
                    };
                    let with = timeless(fs.search_rounds(&pq, &q, k, true).expect("search"));
                    let without = timeless(fs.search_rounds(&pq, &q, k, false).expect("search"));
                    assert_eq!(with, without, "n {n} query {qi} k {k}");
                    later_rounds += with.1.rounds.saturating_sub(2);
                }
            }
        }
        // The reserve serves rounds 3 on: the data must have such rounds.
        assert!(later_rounds > 0, "no query needed a third round");
    }

    /// A reserve kept scores u >= ceil(floor): it covers rounds whose floor is at least
    /// that, and nothing before a pass filled it.
    #[test]
    fn a_reserve_covers_floors_from_its_own_up() {
        assert!(!Reserve::default().covers(f64::INFINITY));
        let r = Reserve::new(10.2, Vec::new());
        assert!(r.covers(11.0) && r.covers(11.5));
        assert!(!r.covers(10.9) && !r.covers(10.2));
    }

    /// Huge-page bytes start zeroed (the packing leaves padding untouched), take writes
    /// across 2 MiB boundaries, and clone into equal bytes.
    #[test]
    fn huge_bytes_are_zeroed_writable_and_clone_equal() {
        let len = (5 << 20) + 3;
        let mut bytes = HugeBytes::zeroed(len);
        assert_eq!(bytes.len(), len);
        assert!(bytes.iter().all(|&b| b == 0));
        for (i, b) in bytes.iter_mut().enumerate().step_by(4093) {
            *b = (i % 251) as u8 + 1;
        }
        let copy = bytes.clone();
        assert_eq!(&copy[..], &bytes[..]);
        assert_eq!(copy[4093 * 600], (4093 * 600 % 251) as u8 + 1);
        assert_eq!(HugeBytes::zeroed(0).len(), 0);
    }
}

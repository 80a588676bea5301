//! Query side: decoding, asymmetric-distance (ADC) scoring with per-subspace lookup
//! tables, shortlist selection and exact re-rank.

use std::cmp::Ordering;
use std::collections::BinaryHeap;

use profuse_formats::{Pq, KSUB};
use rayon::prelude::*;

use crate::PqError;

/// Codes scored per rayon task in the ADC pass (64 K codes = 8 MiB of M = 128 codes).
const SCAN_CHUNK: usize = 1 << 16;

/// Default shortlist size of [`search`]: see the crate README for the recall it gives.
pub const DEFAULT_SHORTLIST: usize = 1000;

/// Decodes vector `n` of a pq file into `out` (D values): the concatenation of its M
/// centroids, or zeros where the vector is invalid (as in the features file).
///
/// # Panics
/// If `n >= pq.len()`, `out.len() != pq.dim()` or the pq's tensors are inconsistent.
pub fn decode(pq: &Pq, n: usize, out: &mut [f32]) {
    assert_eq!(out.len(), pq.dim(), "output length");
    if pq.valid[n] != 1 {
        out.fill(0.0);
        return;
    }
    let (m, dsub) = (pq.m, pq.dsub);
    let code = &pq.codes[n * m..(n + 1) * m];
    for (s, (&c, o)) in code.iter().zip(out.chunks_exact_mut(dsub)).enumerate() {
        let start = (s * KSUB + c as usize) * dsub;
        o.copy_from_slice(&pq.centroids[start..start + dsub]);
    }
}

/// Decodes every vector: `[N, D]` row-major, zero rows where invalid.
pub fn decode_all(pq: &Pq) -> Vec<f32> {
    let d = pq.dim();
    let mut out = vec![0f32; pq.len() * d];
    if d > 0 {
        out.par_chunks_mut(d)
            .enumerate()
            .for_each(|(n, row)| decode(pq, n, row));
    }
    out
}

/// Per-subspace inner products of a query with every centroid, `[M, 256]`: the inner
/// product of the query with a decoded vector is the sum of M table entries.
#[derive(Debug, Clone)]
pub struct LookupTable {
    table: Vec<[f32; KSUB]>,
    query_norm: f32,
}

impl LookupTable {
    /// Builds the table of `query` (D values, any non-zero norm) against a pq's centroids.
    /// Entries are computed in f64 and rounded once.
    pub fn new(pq: &Pq, query: &[f32]) -> Result<Self, PqError> {
        check_pq(pq)?;
        let query_norm = check_query(query, pq.dim())?;
        let dsub = pq.dsub;
        let table = (0..pq.m)
            .map(|s| {
                let q = &query[s * dsub..(s + 1) * dsub];
                let mut row = [0f32; KSUB];
                for (k, r) in row.iter_mut().enumerate() {
                    let start = (s * KSUB + k) * dsub;
                    let c = &pq.centroids[start..start + dsub];
                    *r = dot_f64(q, c) as f32;
                }
                row
            })
            .collect();
        Ok(LookupTable { table, query_norm })
    }

    /// Number of sub-quantisers M.
    pub fn m(&self) -> usize {
        self.table.len()
    }

    /// The table, `[M][256]`.
    pub fn table(&self) -> &[[f32; KSUB]] {
        &self.table
    }

    /// L2 norm of the query.
    pub fn query_norm(&self) -> f32 {
        self.query_norm
    }

    /// Inner product of the query with the decoded vector of `codes` (M codes): the sum of
    /// the M table entries, added in subspace order in f32.
    ///
    /// # Panics
    /// If `codes.len() != M`.
    pub fn inner_product(&self, codes: &[u8]) -> f32 {
        assert_eq!(codes.len(), self.table.len(), "code length");
        self.table
            .iter()
            .zip(codes)
            .fold(0.0f32, |acc, (t, &c)| acc + t[c as usize])
    }

    /// Cosine of the query with a decoded vector of norm `norm`: `0` where `norm` is 0.
    pub fn cosine(&self, codes: &[u8], norm: f32) -> f32 {
        cosine_of(self.inner_product(codes), self.query_norm, norm)
    }

    /// Inner products of consecutive codes `[n, M]` into `out` (n values); each equals
    /// [`LookupTable::inner_product`] bit for bit (see `sum_batch`).
    ///
    /// # Panics
    /// If `codes.len() != out.len() * M`.
    pub fn inner_products(&self, codes: &[u8], out: &mut [f32]) {
        let m = self.table.len();
        assert_eq!(codes.len(), out.len() * m, "codes length");
        let mut rows: Vec<&[u8]> = Vec::with_capacity(BATCH);
        for (batch, o) in codes.chunks(BATCH * m).zip(out.chunks_mut(BATCH)) {
            rows.clear();
            rows.extend(batch.chunks_exact(m));
            self.sum_batch(&rows, o);
        }
    }

    /// Inner products of the vectors `ids` of `codes` (`[N, M]`) into `out`, each equal
    /// to [`LookupTable::inner_product`] bit for bit (four codes side by side, like
    /// [`LookupTable::inner_products`]).
    ///
    /// # Panics
    /// If `ids.len() != out.len()` or an id is out of range.
    pub fn inner_products_of(&self, codes: &[u8], ids: &[u32], out: &mut [f32]) {
        let m = self.table.len();
        assert_eq!(ids.len(), out.len(), "one output per id");
        let row = |id: u32| &codes[id as usize * m..(id as usize + 1) * m];
        let mut rows: Vec<&[u8]> = Vec::with_capacity(BATCH);
        for (j, (batch, o)) in ids.chunks(BATCH).zip(out.chunks_mut(BATCH)).enumerate() {
            // The rows are scattered: ask for those a few batches ahead now.
            for &id in ids.iter().skip((j + PREFETCH_BATCHES) * BATCH).take(BATCH) {
                prefetch(row(id));
            }
            rows.clear();
            rows.extend(batch.iter().map(|&id| row(id)));
            self.sum_batch(&rows, o);
        }
    }

    /// The inner products of a batch of scattered codes, [`SPAN`] subspaces at a time
    /// for the whole batch: those subspaces' tables (16 KiB) stay in L1 while every code
    /// of the batch reads them (code by code, the 128 KiB table of M = 128 came from L2,
    /// a line per lookup). Four codes go side by side, and each code's sum still adds its
    /// entries in subspace order (carried between spans in f32), so it equals
    /// [`LookupTable::inner_product`] bit for bit.
    fn sum_batch(&self, rows: &[&[u8]], out: &mut [f32]) {
        out.fill(0.0);
        let m = self.table.len();
        for first in (0..m).step_by(SPAN) {
            let span = first..(first + SPAN).min(m);
            let mut groups = rows.chunks_exact(LANES);
            let mut outs = out.chunks_exact_mut(LANES);
            for (g, o) in (&mut groups).zip(&mut outs) {
                let mut acc: [f32; LANES] = std::array::from_fn(|i| o[i]);
                let codes: [&[u8]; LANES] = std::array::from_fn(|i| &g[i][span.clone()]);
                for (s, t) in self.table[span.clone()].iter().enumerate() {
                    for (a, c) in acc.iter_mut().zip(&codes) {
                        *a += t[c[s] as usize];
                    }
                }
                o.copy_from_slice(&acc);
            }
            for (r, o) in groups.remainder().iter().zip(outs.into_remainder()) {
                for (t, &c) in self.table[span.clone()].iter().zip(&r[span.clone()]) {
                    *o += t[c as usize];
                }
            }
        }
    }
}

/// Codes summed side by side in `sum_batch`.
const LANES: usize = 4;

/// Codes scored together by [`LookupTable::inner_products`] and
/// [`LookupTable::inner_products_of`].
const BATCH: usize = 64;

/// Subspaces `sum_batch` scores a whole batch on before the next
/// (16 KiB of table).
const SPAN: usize = 16;

/// How many batches ahead [`LookupTable::inner_products_of`] prefetches.
const PREFETCH_BATCHES: usize = 2;

/// Hints that `bytes` will be read soon (every cache line it touches); a no-op off
/// x86-64. The lines are counted from the one holding the first byte: codes inside a
/// mapped file start wherever the file puts them (a 128-byte row at offset 56 of a line
/// touches three lines, and stepping 64 bytes from its start would miss the third).
#[allow(unsafe_code)]
fn prefetch(bytes: &[u8]) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let start = bytes.as_ptr();
        let misalign = start as usize % 64;
        for offset in (0..misalign + bytes.len()).step_by(64) {
            let line = start.wrapping_sub(misalign).wrapping_add(offset);
            // SAFETY: SSE is part of every x86-64 CPU, and a prefetch never faults or
            // reads into the program: the address only has to be computed.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(line.cast()) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = bytes;
}

pub(crate) fn cosine_of(ip: f32, query_norm: f32, norm: f32) -> f32 {
    if norm > 0.0 {
        ip / (query_norm * norm)
    } else {
        0.0
    }
}

/// ADC cosine score of every vector: `<q, decoded_n> / (|q| * norms[n])`; 0 where invalid.
pub fn adc_scores(pq: &Pq, query: &[f32]) -> Result<Vec<f32>, PqError> {
    let lut = LookupTable::new(pq, query)?;
    let m = pq.m;
    let mut scores = vec![0f32; pq.len()];
    scores
        .par_chunks_mut(SCAN_CHUNK)
        .enumerate()
        .for_each(|(chunk, out)| {
            let start = chunk * SCAN_CHUNK;
            lut.inner_products(&pq.codes[start * m..(start + out.len()) * m], out);
            for (i, s) in out.iter_mut().enumerate() {
                let n = start + i;
                *s = if pq.valid[n] == 1 {
                    cosine_of(*s, lut.query_norm, pq.norms[n])
                } else {
                    0.0
                };
            }
        });
    Ok(scores)
}

/// Top-`k` valid vectors by exact cosine with their decoded vectors (computed in f64),
/// after an ADC shortlist of the `shortlist` best ADC scores (at least `k`). Sorted by
/// score descending, ties by ascending id. Invalid vectors are never returned.
pub fn search(
    pq: &Pq,
    query: &[f32],
    shortlist: usize,
    k: usize,
) -> Result<Vec<(u32, f32)>, PqError> {
    let candidates = adc_shortlist(pq, query, shortlist.max(k))?;
    let reranked: Vec<(u32, f32)> = candidates
        .par_iter()
        .map(|&(id, _)| (id, exact_cosine(pq, id as usize, query)))
        .collect();
    Ok(top_n(reranked, k))
}

/// The `shortlist` valid vectors with the best ADC cosine, sorted best first (ties by
/// id), with their ADC scores.
pub fn adc_shortlist(pq: &Pq, query: &[f32], shortlist: usize) -> Result<Vec<(u32, f32)>, PqError> {
    let lut = LookupTable::new(pq, query)?;
    let m = pq.m;
    let n = pq.len();
    if shortlist == 0 {
        return Ok(Vec::new());
    }
    let per_chunk: Vec<Vec<(u32, f32)>> = (0..n.div_ceil(SCAN_CHUNK))
        .into_par_iter()
        .map(|chunk| {
            let start = chunk * SCAN_CHUNK;
            let end = (start + SCAN_CHUNK).min(n);
            let mut scores = vec![0f32; end - start];
            lut.inner_products(&pq.codes[start * m..end * m], &mut scores);
            for (s, &norm) in scores.iter_mut().zip(&pq.norms[start..end]) {
                *s = cosine_of(*s, lut.query_norm, norm);
            }
            let mut best = Shortlist::new(shortlist);
            for (i, &s) in scores.iter().enumerate() {
                if pq.valid[start + i] == 1 {
                    best.offer((start + i) as u32, s);
                }
            }
            best.into_sorted()
        })
        .collect();
    Ok(top_n(per_chunk.concat(), shortlist))
}

/// The best `cap` (id, score) pairs seen so far in [`rank_order`]: a heap whose top is
/// the worst kept pair, so that most offers cost one comparison.
struct Shortlist {
    cap: usize,
    heap: BinaryHeap<Worst>,
}

/// Heap entry ordered so that the worse pair (lower score, then higher id) is greater.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Worst(u32, f32);

impl Eq for Worst {}

impl Ord for Worst {
    fn cmp(&self, other: &Self) -> Ordering {
        rank_order(&(self.0, self.1), &(other.0, other.1))
    }
}

impl PartialOrd for Worst {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

impl Shortlist {
    fn new(cap: usize) -> Self {
        Shortlist {
            cap,
            heap: BinaryHeap::with_capacity(cap + 1),
        }
    }

    fn offer(&mut self, id: u32, score: f32) {
        if self.heap.len() < self.cap {
            self.heap.push(Worst(id, score));
        } else if let Some(mut worst) = self.heap.peek_mut() {
            if rank_order(&(id, score), &(worst.0, worst.1)) == Ordering::Less {
                *worst = Worst(id, score);
            }
        }
    }

    fn into_sorted(self) -> Vec<(u32, f32)> {
        self.heap
            .into_sorted_vec()
            .into_iter()
            .map(|w| (w.0, w.1))
            .collect()
    }
}

/// Exact cosine of `query` with the decoded vector `n` (f64 arithmetic; 0 where the
/// vector is invalid or decodes to zero).
///
/// # Panics
/// If `n >= pq.len()` or `query.len() != pq.dim()`.
pub fn exact_cosine(pq: &Pq, n: usize, query: &[f32]) -> f32 {
    assert_eq!(query.len(), pq.dim(), "query length");
    if pq.valid[n] != 1 {
        return 0.0;
    }
    let (m, dsub) = (pq.m, pq.dsub);
    let (mut dot, mut xx, mut qq) = (0f64, 0f64, 0f64);
    for (s, &c) in pq.codes[n * m..(n + 1) * m].iter().enumerate() {
        let start = (s * KSUB + c as usize) * dsub;
        let cent = &pq.centroids[start..start + dsub];
        let q = &query[s * dsub..(s + 1) * dsub];
        for (&a, &b) in q.iter().zip(cent) {
            let (a, b) = (f64::from(a), f64::from(b));
            dot += a * b;
            xx += b * b;
            qq += a * a;
        }
    }
    if xx > 0.0 && qq > 0.0 {
        (dot / (qq.sqrt() * xx.sqrt())) as f32
    } else {
        0.0
    }
}

/// Ranking order: higher score first, then lower id.
pub fn rank_order(a: &(u32, f32), b: &(u32, f32)) -> Ordering {
    b.1.total_cmp(&a.1).then(a.0.cmp(&b.0))
}

/// The best `n` of `v` in [`rank_order`], sorted.
pub fn top_n(mut v: Vec<(u32, f32)>, n: usize) -> Vec<(u32, f32)> {
    if n == 0 {
        return Vec::new();
    }
    if v.len() > n {
        v.select_nth_unstable_by(n - 1, rank_order);
        v.truncate(n);
    }
    v.sort_unstable_by(rank_order);
    v
}

fn dot_f64(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(&x, &y)| f64::from(x) * f64::from(y))
        .sum()
}

/// Checks that a (possibly hand-built) pq's tensors agree, so that scoring cannot index
/// out of bounds.
pub(crate) fn check_pq(pq: &Pq) -> Result<(), PqError> {
    let n = pq.len();
    if pq.m == 0 || pq.dsub == 0 {
        return Err(PqError::Inconsistent(format!(
            "m = {} and dsub = {} must both be >= 1",
            pq.m, pq.dsub
        )));
    }
    let sizes = [
        ("centroids", pq.centroids.len(), pq.m * KSUB * pq.dsub),
        ("codes", pq.codes.len(), n * pq.m),
        ("norms", pq.norms.len(), n),
    ];
    for (name, got, want) in sizes {
        if got != want {
            return Err(PqError::Inconsistent(format!(
                "`{name}` has {got} values, expected {want}"
            )));
        }
    }
    Ok(())
}

/// The query's L2 norm, after checking its length and that it is finite and non-zero.
fn check_query(query: &[f32], dim: usize) -> Result<f32, PqError> {
    if query.len() != dim {
        return Err(PqError::QueryDim {
            got: query.len(),
            expected: dim,
        });
    }
    let sq = dot_f64(query, query);
    if !sq.is_finite() || sq == 0.0 {
        return Err(PqError::DegenerateQuery);
    }
    Ok(sq.sqrt() as f32)
}

#[cfg(test)]
mod tests {
    use super::{LookupTable, BATCH, KSUB, LANES, SPAN};

    /// Batches, spans and groups of four (with remainders of each: M not a multiple of
    /// the span or of four, ids not a multiple of the batch, repeats, any order) add
    /// every code's entries in subspace order, as the one-code sum does.
    #[test]
    fn scattered_batches_equal_one_code_sums_bit_for_bit() {
        let m = 2 * SPAN + 5;
        let mut state = 7u64;
        let mut next = move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 33) as u32
        };
        let table: Vec<[f32; KSUB]> = (0..m)
            .map(|_| std::array::from_fn(|_| (next() % 20_001) as f32 / 7_919.0 - 1.26))
            .collect();
        let lut = LookupTable {
            table,
            query_norm: 1.0,
        };
        let n = 500;
        let codes: Vec<u8> = (0..n * m).map(|_| (next() % 256) as u8).collect();
        let count = 2 * BATCH + LANES + 3;
        let ids: Vec<u32> = (0..count).map(|_| next() % n as u32).collect();
        let mut got = vec![0f32; count];
        lut.inner_products_of(&codes, &ids, &mut got);
        for (&id, g) in ids.iter().zip(&got) {
            let row = &codes[id as usize * m..(id as usize + 1) * m];
            assert_eq!(g.to_bits(), lut.inner_product(row).to_bits(), "id {id}");
        }
    }
}

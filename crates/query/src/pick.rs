//! The selection pass of index mode: the Gaussians whose proposal row passes the
//! threshold, in increasing id order with their scores, without forming N scores.
//!
//! Two passes over the 2-byte indices. The first sets one bit per passing Gaussian and
//! counts them per task; the second writes each task's Gaussians (walking the set bits)
//! into its exact slice of the output. Nothing branches per Gaussian, nothing is pushed
//! or concatenated, and only the output's own pages are touched. (An AVX-512 version,
//! a gather from the row table and a compress per sixteen Gaussians, was measured
//! slower than these scalar loops on the Ice Lake VM: the gathers dominate.)

use rayon::prelude::*;

/// Gaussians per parallel task (a multiple of 64).
const CHUNK: usize = 1 << 15;

/// The tables the passes read: per row value, 1 when the row passes (a byte, over every
/// u16 value so that a U16 index needs no bounds check) and its score. Index values
/// past the rows (the "no proposal" value) never pass.
pub(crate) struct ScoreTable {
    passes: Box<[u8; 1 << 16]>,
    wide_passes: Vec<u8>,
    scores: Vec<f32>,
}

impl ScoreTable {
    /// `rows` are the row scores; a row passes when its score is finite and at least
    /// `threshold`.
    pub(crate) fn new(rows: &[f32], threshold: f32) -> ScoreTable {
        let wide_passes: Vec<u8> = rows
            .iter()
            .map(|s| u8::from(s.is_finite() && *s >= threshold))
            .collect();
        let mut passes = Box::new([0u8; 1 << 16]);
        for (p, &w) in passes.iter_mut().zip(&wide_passes) {
            *p = w;
        }
        ScoreTable {
            passes,
            wide_passes,
            scores: rows.to_vec(),
        }
    }
}

/// A U16 or U32 index as the passes read it.
pub(crate) trait Row: Copy + Sync {
    /// 1 when the row passes, else 0.
    fn passes(self, table: &ScoreTable) -> u64;
    /// The row's score (only asked of passing rows).
    fn score(self, table: &ScoreTable) -> f32;
}

impl Row for u16 {
    #[inline(always)]
    fn passes(self, table: &ScoreTable) -> u64 {
        u64::from(table.passes[usize::from(self)])
    }
    #[inline(always)]
    fn score(self, table: &ScoreTable) -> f32 {
        table.scores[usize::from(self)]
    }
}

impl Row for u32 {
    #[inline(always)]
    fn passes(self, table: &ScoreTable) -> u64 {
        table
            .wide_passes
            .get(self as usize)
            .map_or(0, |&p| u64::from(p))
    }
    #[inline(always)]
    fn score(self, table: &ScoreTable) -> f32 {
        table.scores[self as usize]
    }
}

/// Ids (increasing) and scores of the Gaussians whose row passes.
#[cfg(test)]
pub(crate) fn pick<T: Row>(index: &[T], table: &ScoreTable) -> (Vec<u32>, Vec<f32>) {
    let (mut ids, mut scores) = (Vec::new(), Vec::new());
    pick_into(index, table, &mut Vec::new(), &mut ids, &mut scores);
    (ids, scores)
}

/// [`pick`] into `ids` and `scores` (replacing their contents, reusing their memory),
/// with `bits` as working memory.
pub(crate) fn pick_into<T: Row>(
    index: &[T],
    table: &ScoreTable,
    bits: &mut Vec<u64>,
    ids: &mut Vec<u32>,
    scores: &mut Vec<f32>,
) {
    bits.clear();
    bits.resize(index.len().div_ceil(64), 0);
    let counts: Vec<usize> = bits
        .par_chunks_mut(CHUNK / 64)
        .zip(index.par_chunks(CHUNK))
        .map(|(words, chunk)| mark(chunk, words, table))
        .collect();
    let total = counts.iter().sum();
    ids.clear();
    ids.resize(total, 0);
    scores.clear();
    scores.resize(total, 0.0);
    let mut slices = Vec::with_capacity(counts.len());
    let (mut rest_ids, mut rest_scores) = (ids.as_mut_slice(), scores.as_mut_slice());
    for &c in &counts {
        let (a, b) = std::mem::take(&mut rest_ids).split_at_mut(c);
        let (x, y) = std::mem::take(&mut rest_scores).split_at_mut(c);
        slices.push((a, x));
        (rest_ids, rest_scores) = (b, y);
    }
    slices
        .into_par_iter()
        .zip(bits.par_chunks(CHUNK / 64))
        .zip(index.par_chunks(CHUNK))
        .enumerate()
        .for_each(|(task, (((ids, scores), words), chunk))| {
            write(task * CHUNK, chunk, words, table, ids, scores);
        });
}

/// Pass 1 over one task's Gaussians: its bit words, and how many bits are set.
fn mark<T: Row>(chunk: &[T], words: &mut [u64], table: &ScoreTable) -> usize {
    let (whole, rest) = chunk.as_chunks::<64>();
    let mut count = 0;
    for (word, gaussians) in words.iter_mut().zip(whole) {
        *word = mark_64(gaussians, table);
        count += word.count_ones() as usize;
    }
    if let Some(word) = words.get_mut(whole.len()) {
        *word = 0;
        for (i, &r) in rest.iter().enumerate() {
            *word |= r.passes(table) << i;
        }
        count += word.count_ones() as usize;
    }
    count
}

/// Bit i set iff Gaussian i passes: a fixed 64-step loop (shifts by constants) with
/// four independent OR chains, bound by the loads rather than one chain's latency.
#[inline(always)]
fn mark_64<T: Row>(gaussians: &[T; 64], table: &ScoreTable) -> u64 {
    let mut w = [0u64; 4];
    for j in 0..16 {
        for l in 0..4 {
            w[l] |= gaussians[4 * j + l].passes(table) << (4 * j + l);
        }
    }
    (w[0] | w[1]) | (w[2] | w[3])
}

/// Pass 2 over one task's Gaussians (the first is `start`): their ids and scores into
/// `ids`/`scores`, which hold exactly as many slots as the words have bits.
fn write<T: Row>(
    start: usize,
    chunk: &[T],
    words: &[u64],
    table: &ScoreTable,
    ids: &mut [u32],
    scores: &mut [f32],
) {
    let mut k = 0;
    for (wi, (&word, gaussians)) in words.iter().zip(chunk.chunks(64)).enumerate() {
        let base = start + wi * 64;
        let mut w = word;
        while w != 0 {
            let i = w.trailing_zeros() as usize;
            ids[k] = (base + i) as u32;
            scores[k] = gaussians[i].score(table);
            k += 1;
            w &= w - 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A brute-force reference: every Gaussian in order, kept when its row passes.
    fn reference<T: Copy + Into<u32>>(index: &[T], rows: &[f32], t: f32) -> (Vec<u32>, Vec<f32>) {
        let mut out = (Vec::new(), Vec::new());
        for (g, &r) in index.iter().enumerate() {
            if let Some(&s) = rows.get(r.into() as usize) {
                if s.is_finite() && s >= t {
                    out.0.push(g as u32);
                    out.1.push(s);
                }
            }
        }
        out
    }

    fn lcg(seed: &mut u64) -> u64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        *seed >> 33
    }

    #[test]
    fn the_pick_equals_the_brute_force_pick_at_every_length_and_density() {
        let mut seed = 7u64;
        for &n in &[
            0usize,
            1,
            15,
            16,
            17,
            63,
            64,
            65,
            1000,
            CHUNK - 1,
            CHUNK + 77,
            3 * CHUNK,
        ] {
            for &p in &[1usize, 3, 1000] {
                let rows: Vec<f32> = (0..p)
                    .map(|r| match r % 17 {
                        0 => f32::NAN,
                        1 => f32::NEG_INFINITY,
                        _ => (lcg(&mut seed) % 1000) as f32 / 1000.0,
                    })
                    .collect();
                // Some "no proposal" values (u16::MAX) among the rows.
                let index: Vec<u16> = (0..n)
                    .map(|_| match lcg(&mut seed) % 10 {
                        0 => u16::MAX,
                        _ => (lcg(&mut seed) % p as u64) as u16,
                    })
                    .collect();
                for t in [0.0f32, 0.25, 0.9, 2.0] {
                    let table = ScoreTable::new(&rows, t);
                    let want = reference(&index, &rows, t);
                    assert_eq!(pick(&index, &table), want, "n {n} p {p} t {t}");
                    let wide: Vec<u32> = index
                        .iter()
                        .map(|&r| {
                            if r == u16::MAX {
                                u32::MAX
                            } else {
                                u32::from(r)
                            }
                        })
                        .collect();
                    assert_eq!(pick(&wide, &table), want, "u32: n {n} p {p} t {t}");
                }
            }
        }
    }

    #[test]
    fn rows_past_the_u16_range_are_picked_from_a_u32_index() {
        let p = 70_000;
        let rows: Vec<f32> = (0..p)
            .map(|r| if r >= 65_536 { 0.9 } else { 0.1 })
            .collect();
        let index: Vec<u32> = (0..500u32)
            .map(|g| g * 139 % p as u32)
            .chain([u32::MAX])
            .collect();
        let table = ScoreTable::new(&rows, 0.5);
        let want = reference(&index, &rows, 0.5);
        assert!(!want.0.is_empty());
        assert_eq!(pick(&index, &table), want);
    }
}

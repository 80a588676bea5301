//! Compact semantics (issue 24): per Gaussian the descriptor-table row it registered most
//! weight to, and that row's share of its weight, beside the table itself
//! (`profuse.semantic_index`, SPEC.md §4.17). A query then scores P rows, not N Gaussians.
//!
//! The dominant row comes from the same sparse rows of W that [`crate::finish`] multiplies
//! (a running best and total per Gaussian over its few nonzero entries): no Gaussian x
//! proposal matrix is formed, and the extra memory is the output (3 bytes a Gaussian, 2
//! with `min_share` 0, which omits the share).

use half::slice::HalfFloatSliceExt;
use profuse_formats::{f16, quantise_share, Floats, SemanticIndex};
use rayon::prelude::*;

use crate::accumulate::dequantise;
use crate::finish::{descriptor_table, run_metadata, Columns, Precision};
use crate::partial::PartialSums;

/// Default `min_share`: a Gaussian has a dominant proposal when that proposal holds at
/// least half of its weight (a strict majority up to the 1/255 quantisation).
pub const DEFAULT_MIN_SHARE: f64 = 0.5;

/// The semantic index of a registration: the descriptor table of [`crate::finish`] (its
/// rows stored in `precision`, as the features are) and per Gaussian its dominant row
/// (largest exact fixed-point weight, ties to the lower row) with that row's share of the
/// Gaussian's weight; `min_share` in [0, 1] is quantised like the shares. Gaussians are
/// independent, so the bytes do not depend on the thread count.
pub fn semantic_index(p: &PartialSums, precision: Precision, min_share: f64) -> SemanticIndex {
    let d = p.dim();
    let table = descriptor_table(p);
    let rows = table.rows.len() / d.max(1);
    let n = p.num_gaussians();
    let mut best = vec![None; n];
    let mut share = vec![0u8; n];
    const CHUNK: usize = 4096;
    best.par_chunks_mut(CHUNK)
        .zip(share.par_chunks_mut(CHUNK))
        .enumerate()
        .for_each(|(c, (best, share))| {
            let mut columns = Columns::default();
            for (i, (b, s)) in best.iter_mut().zip(share.iter_mut()).enumerate() {
                let (groups, qs) = p.weights().row(c * CHUNK + i);
                let (rows, qs) = match &table.column {
                    None => (groups, qs),
                    Some(column) => columns.gather(column, groups, qs),
                };
                if let Some((row, fraction)) = dominant(rows, qs) {
                    *b = Some(row);
                    *s = quantise_share(fraction);
                }
            }
        });
    SemanticIndex {
        descriptors: stored_table(&table.rows, precision),
        dim: d,
        index: SemanticIndex::index_of(rows, &best),
        // With min_share 0 every Gaussian with a row is dominant: the share carries
        // nothing a reader uses, and the index alone is 2 bytes a Gaussian.
        share: (quantise_share(min_share) > 0).then(|| share.into()),
        min_share: quantise_share(min_share),
        extra: run_metadata(p),
    }
}

/// The row with the largest weight (the first of equals: rows ascend) and its share of
/// the row total; `None` for a Gaussian without weight.
fn dominant(rows: &[u32], qs: &[u128]) -> Option<(u32, f64)> {
    let mut best: Option<(u32, u128)> = None;
    let mut total = 0u128;
    for (row, q) in rows.iter().zip(qs) {
        total += *q;
        if best.is_none_or(|(_, b)| *q > b) {
            best = Some((*row, *q));
        }
    }
    let (row, q) = best?;
    (total > 0).then(|| (row, dequantise(q) / dequantise(total)))
}

/// The table rows in the features' precision, rounded exactly as [`crate::finish`] rounds
/// a single-proposal Gaussian's row (f64 -> f32 -> f16), so such a Gaussian's features
/// row and its table row are the same numbers.
fn stored_table(rows: &[f64], precision: Precision) -> Floats {
    let f32s: Vec<f32> = rows.iter().map(|x| *x as f32).collect();
    match precision {
        Precision::F32 => Floats::F32(f32s.into()),
        Precision::F16 => {
            let mut out = vec![f16::ZERO; f32s.len()];
            out.convert_from_f32_slice(&f32s);
            Floats::F16(out.into())
        }
    }
}

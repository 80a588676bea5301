//! Queries over a semantic index (issue 24, `profuse.semantic_index`): a prompt is scored
//! against the P proposal descriptors once, and every Gaussian takes the score of its
//! dominant proposal; Gaussians without one take the score of their PQ code when a pq
//! file is given (else their largest proposal's, the best the index knows).
//!
//! A Gaussian's score is a function of its cosines to the query and the negatives only,
//! so scoring a row and handing it to every Gaussian of the row gives the same bits as
//! scoring each Gaussian with that row as its descriptor.

use profuse_formats::{Labels, Pq, SemanticIndex};
use profuse_pq::LookupTable;
use rayon::prelude::*;

use crate::error::{QueryError, Result};
use crate::pick::ScoreTable;
use crate::score::INVALID_SCORE;
use crate::select::{select, ActiveSet, Rule};

/// Gaussians per parallel task of the gathers.
const GATHER_CHUNK: usize = 1 << 16;

/// A semantic index with the PQ codes its flagged Gaussians fall back to, if any.
#[derive(Debug, Clone, Copy)]
pub struct Indexed<'a> {
    /// The index and its descriptor table.
    pub index: &'a SemanticIndex,
    /// PQ codes of the same Gaussians (`--semantics both`).
    pub fallback: Option<&'a Pq>,
}

impl Indexed<'_> {
    /// Gaussians N.
    pub fn len(&self) -> usize {
        self.index.num_gaussians()
    }

    /// Whether there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Whether Gaussian `g` is scored through its PQ code.
    pub fn falls_back(&self, g: usize) -> bool {
        self.fallback.is_some() && !self.index.is_dominant(g)
    }

    /// Whether Gaussian `g` has a descriptor: its PQ code's where it falls back, else
    /// whether it has a proposal at all.
    pub fn is_valid(&self, g: usize) -> bool {
        match self.fallback {
            Some(pq) if !self.index.is_dominant(g) => pq.valid.get(g) == Some(&1),
            _ => self.index.proposal(g).is_some(),
        }
    }

    /// Per unit vector, the cosine of every table row ([`INVALID_SCORE`] for a zero row).
    pub fn row_cosines(&self, units: &[Vec<f32>]) -> Vec<Vec<f32>> {
        IndexTable::new(self.index).cosines(units)
    }

    /// Per unit vector, the cosine of every Gaussian: its row's, or its PQ code's where it
    /// falls back; [`INVALID_SCORE`] without a descriptor.
    pub fn cosines(&self, units: &[Vec<f32>]) -> Result<Vec<Vec<f32>>> {
        let rows = self.row_cosines(units);
        let luts = self.lookup_tables(units)?;
        Ok(rows
            .iter()
            .zip(&luts)
            .map(|(row, lut)| self.gather(row, lut.as_ref()))
            .collect())
    }

    fn lookup_tables(&self, units: &[Vec<f32>]) -> Result<Vec<Option<LookupTable>>> {
        units
            .iter()
            .map(|u| match self.fallback {
                None => Ok(None),
                Some(pq) => LookupTable::new(pq, u)
                    .map(Some)
                    .map_err(|e| QueryError::Pq {
                        path: "pq".into(),
                        reason: e.to_string(),
                    }),
            })
            .collect()
    }

    /// Every Gaussian's value: `row[index]`, or the fallback's cosine.
    fn gather(&self, row: &[f32], lut: Option<&LookupTable>) -> Vec<f32> {
        let mut out = vec![INVALID_SCORE; self.len()];
        out.par_chunks_mut(GATHER_CHUNK)
            .enumerate()
            .for_each(|(c, chunk)| {
                for (i, s) in chunk.iter_mut().enumerate() {
                    *s = self.value(c * GATHER_CHUNK + i, row, lut);
                }
            });
        out
    }

    fn value(&self, g: usize, row: &[f32], lut: Option<&LookupTable>) -> f32 {
        match (lut, self.fallback) {
            (Some(lut), Some(pq)) if !self.index.is_dominant(g) => pq_cosine(pq, lut, g),
            _ => self
                .index
                .proposal(g)
                .map_or(INVALID_SCORE, |r| row[r as usize]),
        }
    }
}

/// Rows of the table scored per parallel task.
const TABLE_ROWS_PER_TASK: usize = 128;

/// A semantic index's descriptor table prepared for scoring: its rows as f32 and their
/// norms, computed once per index (when it is loaded), so that a query costs a few
/// products per row. Scores have exactly the bits of the features path
/// ([`crate::score_prompts`] over `profuse.features` rows equal to the table's): the same
/// conversion, the same [`crate::dot`] for the norm and the cosines.
#[derive(Debug, Clone)]
pub struct IndexTable {
    dim: usize,
    rows: Vec<f32>,
    norms: Vec<f32>,
}

impl IndexTable {
    /// Converts the table (F16 rows through F16C where the CPU has it) and takes the norms.
    pub fn new(index: &SemanticIndex) -> IndexTable {
        let (d, p) = (index.dim, index.num_proposals());
        let mut rows = vec![0f32; p * d];
        let mut norms = vec![0f32; p];
        if d > 0 {
            rows.par_chunks_mut(d)
                .zip(norms.par_iter_mut())
                .enumerate()
                .with_min_len(TABLE_ROWS_PER_TASK)
                .for_each(|(r, (row, norm))| {
                    crate::score::read_row(&index.descriptors, r * d, row);
                    *norm = crate::dot(row, row).sqrt();
                });
        }
        IndexTable {
            dim: d,
            rows,
            norms,
        }
    }

    /// Rows P.
    pub fn len(&self) -> usize {
        self.norms.len()
    }

    /// Whether the table has no rows.
    pub fn is_empty(&self) -> bool {
        self.norms.is_empty()
    }

    /// Per unit vector, the cosine of every row; [`INVALID_SCORE`] for a row without a
    /// direction (zero or not finite).
    pub fn cosines(&self, units: &[Vec<f32>]) -> Vec<Vec<f32>> {
        let (p, q, d) = (self.len(), units.len(), self.dim);
        if q == 0 {
            return Vec::new();
        }
        let mut interleaved = vec![INVALID_SCORE; p * q];
        interleaved
            .par_chunks_mut(q)
            .enumerate()
            .with_min_len(TABLE_ROWS_PER_TASK)
            .for_each_init(
                || units.iter().map(Vec::as_slice).collect::<Vec<&[f32]>>(),
                |vectors, (r, out)| {
                    let norm = self.norms[r];
                    if !(norm > 0.0 && norm.is_finite()) {
                        return;
                    }
                    let row = &self.rows[r * d..(r + 1) * d];
                    profuse_pq::dots(row, vectors, out);
                    for c in out.iter_mut() {
                        *c /= norm;
                    }
                },
            );
        (0..q)
            .map(|j| interleaved.iter().skip(j).step_by(q).copied().collect())
            .collect()
    }
}

/// The cosine of a PQ code as the pq path computes it ([`INVALID_SCORE`] when invalid).
fn pq_cosine(pq: &Pq, lut: &LookupTable, g: usize) -> f32 {
    let norm = pq.norms[g];
    if pq.valid[g] != 1 || norm.is_nan() || norm <= 0.0 {
        return INVALID_SCORE;
    }
    let m = pq.m;
    lut.cosine(&pq.codes[g * m..(g + 1) * m], norm)
}

/// Applies a threshold to per-row scores without forming N scores: a Gaussian of a
/// dominant row is selected iff its row passes, so one pass over the 2-byte indices
/// picks them; flagged Gaussians (with a fallback) take `fallback_score(g)`. Equals
/// [`select`] over the gathered scores; other rules gather first.
pub fn select_indexed(
    indexed: &Indexed<'_>,
    row_scores: &[f32],
    fallback_score: &(dyn Fn(usize) -> f32 + Sync),
    rule: Rule,
) -> Result<ActiveSet> {
    let mut out = ActiveSet::default();
    select_indexed_into(
        indexed,
        row_scores,
        fallback_score,
        rule,
        &mut SelectBuffers::default(),
        &mut out,
    )?;
    Ok(out)
}

/// Working memory of [`select_indexed_into`], kept between queries by a caller that
/// answers many (a server, a viewer, a benchmark): a selection then reuses memory
/// whose pages are already mapped instead of mapping (and unmapping) megabytes per query.
#[derive(Debug, Default)]
pub struct SelectBuffers {
    bits: Vec<u64>,
}

/// [`select_indexed`] into `out`, reusing its vectors' memory and `buffers`.
pub fn select_indexed_into(
    indexed: &Indexed<'_>,
    row_scores: &[f32],
    fallback_score: &(dyn Fn(usize) -> f32 + Sync),
    rule: Rule,
    buffers: &mut SelectBuffers,
    out: &mut ActiveSet,
) -> Result<()> {
    let Rule::Threshold(t) = rule else {
        let n = indexed.len();
        let scores: Vec<f32> = (0..n)
            .into_par_iter()
            .map(|g| score_of(indexed, row_scores, fallback_score, g))
            .collect();
        *out = select(&scores, rule)?;
        return Ok(());
    };
    rule.validate()?;
    out.threshold = t;
    if indexed.fallback.is_none() {
        let table = ScoreTable::new(row_scores, t);
        let (bits, ids, scores) = (&mut buffers.bits, &mut out.ids, &mut out.scores);
        match &indexed.index.index {
            Labels::U16(b) => crate::pick::pick_into(b, &table, bits, ids, scores),
            Labels::U32(b) => crate::pick::pick_into(b, &table, bits, ids, scores),
        }
        return Ok(());
    }
    let passes: Vec<bool> = row_scores
        .iter()
        .map(|s| s.is_finite() && *s >= t)
        .collect();
    let pick = Pick {
        passes: &passes,
        rows: row_scores,
        share: indexed.index.share.as_deref(),
        min_share: indexed.index.min_share,
        fallback: Some(fallback_score),
        threshold: t,
    };
    (out.ids, out.scores) = match &indexed.index.index {
        Labels::U16(b) => pick.run(b, u32::from(u16::MAX)),
        Labels::U32(b) => pick.run(b, u32::MAX),
    };
    Ok(())
}

/// What [`select_indexed`] needs per Gaussian, borrowed as plain slices so that the pass
/// over the 2-byte indices is a tight loop.
struct Pick<'a> {
    passes: &'a [bool],
    rows: &'a [f32],
    /// Absent only with `min_share` 0, where every Gaussian with a row is dominant.
    share: Option<&'a [u8]>,
    min_share: u8,
    fallback: Option<&'a (dyn Fn(usize) -> f32 + Sync)>,
    threshold: f32,
}

impl Pick<'_> {
    fn run<T: Copy + Into<u32> + Sync>(&self, index: &[T], none: u32) -> (Vec<u32>, Vec<f32>) {
        let parts: Vec<(Vec<u32>, Vec<f32>)> = index
            .par_chunks(GATHER_CHUNK)
            .enumerate()
            .map(|(c, chunk)| self.chunk(c * GATHER_CHUNK, chunk, none))
            .collect();
        let total = parts.iter().map(|p| p.0.len()).sum();
        let (mut ids, mut scores) = (Vec::with_capacity(total), Vec::with_capacity(total));
        for (i, s) in parts {
            ids.extend(i);
            scores.extend(s);
        }
        (ids, scores)
    }

    fn chunk<T: Copy + Into<u32>>(
        &self,
        start: usize,
        chunk: &[T],
        none: u32,
    ) -> (Vec<u32>, Vec<f32>) {
        let (mut ids, mut scores) = (Vec::new(), Vec::new());
        for (i, r) in chunk.iter().enumerate() {
            let (g, r) = (start + i, (*r).into());
            let score = match self.fallback {
                Some(f) if r == none || self.share.is_some_and(|s| s[g] < self.min_share) => f(g),
                _ if r != none && self.passes[r as usize] => self.rows[r as usize],
                _ => continue,
            };
            if score.is_finite() && score >= self.threshold {
                ids.push(g as u32);
                scores.push(score);
            }
        }
        (ids, scores)
    }
}

fn score_of(
    indexed: &Indexed<'_>,
    row_scores: &[f32],
    fallback_score: &(dyn Fn(usize) -> f32 + Sync),
    g: usize,
) -> f32 {
    if indexed.falls_back(g) {
        fallback_score(g)
    } else {
        indexed
            .index
            .proposal(g)
            .map_or(INVALID_SCORE, |r| row_scores[r as usize])
    }
}

/// One prompt scored over a semantic index: the score of every table row and, for the
/// Gaussians that fall back, the lookup tables of the query and its negatives.
#[derive(Debug, Clone)]
pub struct IndexQuery {
    /// Score of every table row ([`INVALID_SCORE`] for a zero row).
    pub rows: Vec<f32>,
    kind: crate::ScoreKind,
    /// Query first, then the negatives (relevancy only); empty without a fallback.
    luts: Vec<LookupTable>,
}

impl IndexQuery {
    /// Scores prompt `query` of `prompts` on the table (P rows, not N Gaussians), and
    /// prepares the fallback's lookup tables.
    pub fn new(
        indexed: &Indexed<'_>,
        prompts: &profuse_formats::Prompts,
        query: usize,
        kind: crate::ScoreKind,
    ) -> Result<IndexQuery> {
        IndexQuery::with_table(
            indexed,
            &IndexTable::new(indexed.index),
            prompts,
            query,
            kind,
        )
    }

    /// [`IndexQuery::new`] with the index's table prepared once ([`IndexTable::new`]),
    /// for many queries over one index.
    pub fn with_table(
        indexed: &Indexed<'_>,
        table: &IndexTable,
        prompts: &profuse_formats::Prompts,
        query: usize,
        kind: crate::ScoreKind,
    ) -> Result<IndexQuery> {
        let mut rows =
            crate::score::score_prompts_with(table.dim, prompts, &[query], kind, |units| {
                Ok(table.cosines(units))
            })?;
        let luts = match indexed.fallback {
            None => Vec::new(),
            Some(_) => {
                let mut which = vec![query];
                if kind == crate::ScoreKind::Relevancy {
                    which.extend(crate::negatives_for(prompts, query));
                }
                let units = which
                    .iter()
                    .map(|&r| {
                        crate::unit_vector(prompts.embedding(r)).ok_or_else(|| {
                            QueryError::BadEmbedding {
                                path: "prompts".into(),
                                name: prompts.names.get(r).cloned().unwrap_or_default(),
                            }
                        })
                    })
                    .collect::<Result<Vec<_>>>()?;
                indexed
                    .lookup_tables(&units)?
                    .into_iter()
                    .flatten()
                    .collect()
            }
        };
        Ok(IndexQuery {
            rows: rows.pop().unwrap_or_default(),
            kind,
            luts,
        })
    }

    /// The score of a Gaussian that falls back to its PQ code (as the pq path scores it).
    pub fn fallback_score(&self, pq: &Pq, g: usize) -> f32 {
        let Some((q, negatives)) = self.luts.split_first() else {
            return INVALID_SCORE;
        };
        let c_q = pq_cosine(pq, q, g);
        match self.kind {
            crate::ScoreKind::Cosine => c_q,
            crate::ScoreKind::Relevancy => {
                let nearest = negatives
                    .iter()
                    .map(|n| pq_cosine(pq, n, g))
                    .fold(f32::NEG_INFINITY, f32::max);
                crate::relevancy(c_q, nearest)
            }
        }
    }

    /// The prompt's active set under `rule` ([`select_indexed`]).
    pub fn select(&self, indexed: &Indexed<'_>, rule: Rule) -> Result<ActiveSet> {
        let mut out = ActiveSet::default();
        self.select_into(indexed, rule, &mut SelectBuffers::default(), &mut out)?;
        Ok(out)
    }

    /// [`IndexQuery::select`] into `out`, reusing its memory and `buffers`
    /// ([`select_indexed_into`]).
    pub fn select_into(
        &self,
        indexed: &Indexed<'_>,
        rule: Rule,
        buffers: &mut SelectBuffers,
        out: &mut ActiveSet,
    ) -> Result<()> {
        let fallback = |g: usize| match indexed.fallback {
            Some(pq) => self.fallback_score(pq, g),
            None => INVALID_SCORE,
        };
        select_indexed_into(indexed, &self.rows, &fallback, rule, buffers, out)
    }
}

/// Which per-Gaussian semantics a query reads (`profuse run --semantics`, config
/// `query.semantics`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Semantics {
    /// PQ codes of every Gaussian (the paper's storage).
    #[default]
    Pq,
    /// The semantic index alone: every Gaussian scored through its largest proposal.
    Index,
    /// The semantic index, with PQ codes for the Gaussians without a dominant proposal.
    Both,
}

impl Semantics {
    /// `pq`, `index` or `both`.
    pub fn name(self) -> &'static str {
        match self {
            Semantics::Pq => "pq",
            Semantics::Index => "index",
            Semantics::Both => "both",
        }
    }

    /// Whether fuse must write a semantic index.
    pub fn needs_index(self) -> bool {
        self != Semantics::Pq
    }

    /// Whether the PQ codes are read.
    pub fn needs_pq(self) -> bool {
        self != Semantics::Index
    }
}

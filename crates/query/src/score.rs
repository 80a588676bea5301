//! Per-Gaussian scores of text prompts: cosine similarity and the LERF relevancy.

use profuse_formats::{Features, Floats, Pq, Prompts};
use rayon::prelude::*;

use crate::error::{QueryError, Result};
use crate::semantic::Indexed;

/// The descriptor dot product (f32, fixed summation order), shared with vertex-transfer.
pub use profuse_pq::dot;

/// Names of the canonical negatives of the LERF relevancy score (SPEC.md §4.9), defined
/// with the label spaces in `profuse-formats`.
pub use profuse_formats::label_space::CANONICAL_NEGATIVES;

/// Temperature of the relevancy softmax (LERF, LangSplat, Dr. Splat use 10).
pub const RELEVANCY_TEMPERATURE: f32 = 10.0;

/// Score of a Gaussian without a descriptor: below every threshold, never selected.
pub const INVALID_SCORE: f32 = f32::NEG_INFINITY;

/// Rows scored per parallel task.
const ROWS_PER_TASK: usize = 1024;

/// Which score selects Gaussians.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum ScoreKind {
    /// s_g = ⟨q̂, f̂_g⟩ (paper §3.4).
    #[default]
    Cosine,
    /// min over canonical negatives n of softmax(10·[cos(q, f), cos(n, f)])₀ (LERF).
    Relevancy,
}

impl ScoreKind {
    /// `cosine` or `relevancy`.
    pub fn name(self) -> &'static str {
        match self {
            ScoreKind::Cosine => "cosine",
            ScoreKind::Relevancy => "relevancy",
        }
    }
}

/// Per-Gaussian language descriptors: exact (`profuse.features`) or product-quantised
/// (`profuse.pq`, scored by asymmetric distance against the decoded vectors).
#[derive(Debug, Clone, Copy)]
pub enum Descriptors<'a> {
    /// Full-precision descriptors.
    Features(&'a Features),
    /// PQ codes.
    Pq(&'a Pq),
    /// A semantic index: each Gaussian scored through its dominant proposal's descriptor
    /// (or its PQ code where it has none and codes are given).
    Indexed(Indexed<'a>),
}

impl Descriptors<'_> {
    /// Number of Gaussians N.
    pub fn len(&self) -> usize {
        match self {
            Descriptors::Features(f) => f.len(),
            Descriptors::Pq(p) => p.len(),
            Descriptors::Indexed(x) => x.len(),
        }
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Descriptor dimension D.
    pub fn dim(&self) -> usize {
        match self {
            Descriptors::Features(f) => f.dim,
            Descriptors::Pq(p) => p.dim(),
            Descriptors::Indexed(x) => x.index.dim,
        }
    }

    /// Whether Gaussian `i` has a descriptor.
    pub fn is_valid(&self, i: usize) -> bool {
        match self {
            Descriptors::Features(f) => f.valid.get(i) == Some(&1),
            Descriptors::Pq(p) => p.valid.get(i) == Some(&1),
            Descriptors::Indexed(x) => i < x.len() && x.is_valid(i),
        }
    }

    /// Number of Gaussians with a descriptor.
    pub fn valid_count(&self) -> usize {
        let valid = match self {
            Descriptors::Features(f) => &f.valid,
            Descriptors::Pq(p) => &p.valid,
            Descriptors::Indexed(x) => return (0..x.len()).filter(|&g| x.is_valid(g)).count(),
        };
        valid.iter().filter(|v| **v == 1).count()
    }

    /// The cosine of every descriptor with each of the unit vectors `units` (one `Vec`
    /// of N scores per unit vector), [`INVALID_SCORE`] where a Gaussian has no
    /// descriptor. Each descriptor is read once for all vectors.
    pub fn cosines(&self, units: &[Vec<f32>]) -> Result<Vec<Vec<f32>>> {
        let d = self.dim();
        if let Some(u) = units.iter().find(|u| u.len() != d) {
            return Err(QueryError::DimMismatch {
                prompts: "prompts".into(),
                prompt_dim: u.len(),
                descriptors: "descriptors".into(),
                descriptor_dim: d,
            });
        }
        match self {
            Descriptors::Features(f) => Ok(exact_cosines(f, units)),
            Descriptors::Pq(p) => pq_cosines(p, units),
            Descriptors::Indexed(x) => x.cosines(units),
        }
    }
}

/// Exact cosines: the descriptor is divided by its own norm, so F16 rounding of a
/// stored unit vector does not bias the score.
pub(crate) fn exact_cosines(f: &Features, units: &[Vec<f32>]) -> Vec<Vec<f32>> {
    let (n, d, q) = (f.len(), f.dim, units.len());
    if q == 0 {
        return Vec::new();
    }
    // Interleaved [N, Q] so that each descriptor row is read once for every vector.
    let mut table = vec![INVALID_SCORE; n * q];
    // Small inputs (a semantic index's proposal table) still use every thread; the
    // partition does not change a single bit.
    let rows_per_task = (n / (4 * rayon::current_num_threads())).clamp(16, ROWS_PER_TASK);
    table
        .par_chunks_mut(rows_per_task * q)
        .enumerate()
        .for_each(|(task, out)| {
            let mut row = vec![0.0f32; d];
            let mut dots = vec![0.0f32; q];
            let vectors: Vec<&[f32]> = units.iter().map(Vec::as_slice).collect();
            for (r, scores) in out.chunks_exact_mut(q).enumerate() {
                let g = task * rows_per_task + r;
                if f.valid[g] != 1 {
                    continue;
                }
                read_row(&f.features, g * d, &mut row);
                let norm = dot(&row, &row).sqrt();
                if !(norm > 0.0 && norm.is_finite()) {
                    continue;
                }
                // The same bits as `dot(u, row)` per unit; the product commutes exactly.
                profuse_pq::dots(&row, &vectors, &mut dots);
                for (s, c) in scores.iter_mut().zip(&dots) {
                    *s = c / norm;
                }
            }
        });
    (0..q)
        .map(|j| table.iter().skip(j).step_by(q).copied().collect())
        .collect()
}

/// One descriptor row as f32; F16 rows go through `half`'s slice conversion, which uses
/// the CPU's F16C instructions when present (4x faster than element-wise conversion).
pub(crate) fn read_row(features: &Floats, start: usize, row: &mut [f32]) {
    match features {
        Floats::F16(b) => {
            use half::slice::HalfFloatSliceExt;
            b[start..start + row.len()].convert_to_f32_slice(row);
        }
        Floats::F32(b) => row.copy_from_slice(&b[start..start + row.len()]),
    }
}

/// Cosines against the decoded PQ vectors by asymmetric distance computation
/// (`profuse_pq::adc_scores`: ⟨q, x̂⟩ / (‖q‖ ‖x̂‖) from per-subspace lookup tables, equal
/// to the cosine with the decoded vector up to f32 rounding).
fn pq_cosines(pq: &Pq, units: &[Vec<f32>]) -> Result<Vec<Vec<f32>>> {
    units
        .iter()
        .map(|u| {
            let mut scores = profuse_pq::adc_scores(pq, u).map_err(|e| QueryError::Pq {
                path: "pq".into(),
                reason: e.to_string(),
            })?;
            for (s, (&v, &norm)) in scores.iter_mut().zip(pq.valid.iter().zip(pq.norms.iter())) {
                // A code that decodes to zero has no direction: as good as no descriptor.
                if v != 1 || norm.is_nan() || norm <= 0.0 {
                    *s = INVALID_SCORE;
                }
            }
            Ok(scores)
        })
        .collect()
}

/// `v / ‖v‖₂`, or `None` when `v` is zero or not finite.
pub fn unit_vector(v: &[f32]) -> Option<Vec<f32>> {
    let norm = v
        .iter()
        .map(|x| f64::from(*x) * f64::from(*x))
        .sum::<f64>()
        .sqrt();
    (norm > 0.0 && norm.is_finite())
        .then(|| v.iter().map(|x| (f64::from(*x) / norm) as f32).collect())
}

/// The LERF two-way softmax `exp(10 c_q) / (exp(10 c_q) + exp(10 c_n))` of a query cosine
/// `c_q` against a negative's cosine `c_n`, computed as the logistic function of
/// `10 (c_q − c_n)` with the exponent never positive, so it neither overflows nor loses
/// the small side for any finite inputs. [`INVALID_SCORE`] in gives [`INVALID_SCORE`] out.
pub fn relevancy(c_q: f32, c_n: f32) -> f32 {
    if c_q == INVALID_SCORE {
        return INVALID_SCORE;
    }
    let z = f64::from(RELEVANCY_TEMPERATURE) * (f64::from(c_q) - f64::from(c_n));
    let p = if z >= 0.0 {
        1.0 / (1.0 + (-z).exp())
    } else {
        let e = z.exp();
        e / (1.0 + e)
    };
    p as f32
}

/// Indices of the canonical negatives present in `prompts`, excluding `query` itself
/// (a negative is not scored against itself), in the file's order.
pub fn negatives_for(prompts: &Prompts, query: usize) -> Vec<usize> {
    prompts
        .names
        .iter()
        .enumerate()
        .filter(|(i, n)| *i != query && CANONICAL_NEGATIVES.contains(&n.as_str()))
        .map(|(i, _)| i)
        .collect()
}

/// Scores every Gaussian for each prompt of `which` (indices into `prompts`): one `Vec`
/// of N scores per prompt, [`INVALID_SCORE`] where a Gaussian has no descriptor.
/// Embeddings are normalised here. For [`ScoreKind::Relevancy`] the cosines to the
/// negatives are computed once and shared by all prompts.
pub fn score_prompts(
    descriptors: Descriptors<'_>,
    prompts: &Prompts,
    which: &[usize],
    kind: ScoreKind,
) -> Result<Vec<Vec<f32>>> {
    score_prompts_with(descriptors.dim(), prompts, which, kind, |units| {
        descriptors.cosines(units)
    })
}

/// [`score_prompts`] over descriptors of dimension `dim` whose cosines with unit
/// vectors `cosines` computes (one `Vec` per unit vector, [`INVALID_SCORE`] where there
/// is no descriptor).
pub(crate) fn score_prompts_with(
    dim: usize,
    prompts: &Prompts,
    which: &[usize],
    kind: ScoreKind,
    cosines: impl FnOnce(&[Vec<f32>]) -> Result<Vec<Vec<f32>>>,
) -> Result<Vec<Vec<f32>>> {
    if prompts.dim != dim {
        return Err(QueryError::DimMismatch {
            prompts: "prompts".into(),
            prompt_dim: prompts.dim,
            descriptors: "descriptors".into(),
            descriptor_dim: dim,
        });
    }
    // Every prompt row needed (queries, then negatives), each scored once.
    let mut rows: Vec<usize> = which.to_vec();
    if kind == ScoreKind::Relevancy {
        for &q in which {
            let negatives = negatives_for(prompts, q);
            if negatives.is_empty() {
                return Err(QueryError::NoNegatives {
                    path: "prompts".into(),
                    name: prompt_name(prompts, q),
                });
            }
            rows.extend(negatives);
        }
    }
    rows.sort_unstable();
    rows.dedup();
    let units = rows
        .iter()
        .map(|&r| {
            if r >= prompts.len() {
                return Err(QueryError::UnknownPrompt {
                    path: "prompts".into(),
                    name: format!("#{r}"),
                    available: prompts.names.join(", "),
                });
            }
            unit_vector(prompts.embedding(r)).ok_or_else(|| QueryError::BadEmbedding {
                path: "prompts".into(),
                name: prompt_name(prompts, r),
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let cosines = cosines(&units)?;
    let of_row = |r: usize| -> &[f32] {
        // `rows` is sorted and holds every index looked up here.
        let at = rows.binary_search(&r).unwrap_or(0);
        &cosines[at]
    };
    Ok(which
        .iter()
        .map(|&q| match kind {
            ScoreKind::Cosine => of_row(q).to_vec(),
            ScoreKind::Relevancy => {
                let negatives: Vec<&[f32]> =
                    negatives_for(prompts, q).into_iter().map(of_row).collect();
                min_relevancy(of_row(q), &negatives)
            }
        })
        .collect())
}

/// Per Gaussian, the minimum over the negatives of [`relevancy`]. The logistic function
/// is increasing, so the minimum is the relevancy against the most similar negative: one
/// `exp` per Gaussian, whatever the number of negatives.
fn min_relevancy(query: &[f32], negatives: &[&[f32]]) -> Vec<f32> {
    let mut out = vec![0.0f32; query.len()];
    out.par_chunks_mut(ROWS_PER_TASK)
        .enumerate()
        .for_each(|(task, chunk)| {
            for (r, s) in chunk.iter_mut().enumerate() {
                let g = task * ROWS_PER_TASK + r;
                let nearest = negatives
                    .iter()
                    .map(|n| n[g])
                    .fold(f32::NEG_INFINITY, f32::max);
                *s = relevancy(query[g], nearest);
            }
        });
    out
}

fn prompt_name(prompts: &Prompts, i: usize) -> String {
    prompts
        .names
        .get(i)
        .cloned()
        .unwrap_or_else(|| format!("#{i}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unit_vector_rejects_zero_and_non_finite() {
        assert_eq!(unit_vector(&[3.0, 4.0]), Some(vec![0.6, 0.8]));
        assert_eq!(unit_vector(&[0.0, 0.0]), None);
        assert_eq!(unit_vector(&[f32::NAN, 1.0]), None);
        assert_eq!(unit_vector(&[]), None);
    }
}

//! Per-prompt score statistics and best Gaussians (`query scores`), and the
//! every-valid-Gaussian selection file that lets a user pick a threshold afterwards.

use profuse_formats::Selection;
use serde::Serialize;

use crate::pipeline::{DescriptorSet, ScoreInputs};
use crate::{select, QueryError, Result, Rule, ScoreKind};

/// The distribution of one prompt's scores over the Gaussians with a descriptor, and its
/// best Gaussians.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PromptScores {
    /// The prompt.
    pub prompt: String,
    /// Gaussians with a finite score.
    pub valid: usize,
    /// Smallest score.
    pub min: Option<f32>,
    /// Median (nearest rank).
    pub p50: Option<f32>,
    /// 90th percentile.
    pub p90: Option<f32>,
    /// 99th percentile.
    pub p99: Option<f32>,
    /// 99.9th percentile.
    pub p999: Option<f32>,
    /// Largest score.
    pub max: Option<f32>,
    /// Mean score.
    pub mean: Option<f64>,
    /// The best Gaussians, `[id, score]`, best first (ties by id).
    pub top: Vec<(u32, f32)>,
}

/// The statistics of prompt `q`'s `scores` (NaN = no descriptor) and its `n` best
/// Gaussians: for PQ cosine the paper's ADC shortlist (`shortlist` long) re-ranked by the
/// decoded descriptors, otherwise from the full scores.
pub fn prompt_scores(
    inputs: &ScoreInputs,
    q: usize,
    scores: &[f32],
    kind: ScoreKind,
    n: usize,
    shortlist: usize,
) -> Result<PromptScores> {
    let mut finite: Vec<f32> = scores.iter().copied().filter(|v| v.is_finite()).collect();
    finite.sort_by(|x, y| x.total_cmp(y));
    let quantile = |p: f64| {
        (!finite.is_empty()).then(|| finite[((finite.len() - 1) as f64 * p).round() as usize])
    };
    Ok(PromptScores {
        prompt: inputs.prompts.names[q].clone(),
        valid: finite.len(),
        min: finite.first().copied(),
        p50: quantile(0.5),
        p90: quantile(0.9),
        p99: quantile(0.99),
        p999: quantile(0.999),
        max: finite.last().copied(),
        mean: (!finite.is_empty())
            .then(|| finite.iter().map(|v| f64::from(*v)).sum::<f64>() / finite.len() as f64),
        top: best(inputs, q, scores, kind, n, shortlist)?,
    })
}

fn best(
    inputs: &ScoreInputs,
    q: usize,
    scores: &[f32],
    kind: ScoreKind,
    n: usize,
    shortlist: usize,
) -> Result<Vec<(u32, f32)>> {
    if let (DescriptorSet::Pq(pq), ScoreKind::Cosine) = (&inputs.descriptors, kind) {
        return profuse_pq::search(pq, inputs.prompts.embedding(q), shortlist, n).map_err(|e| {
            QueryError::Pq {
                path: inputs.descriptors_path.clone(),
                reason: e.to_string(),
            }
        });
    }
    let mut ranked: Vec<(u32, f32)> = scores
        .iter()
        .enumerate()
        .filter(|(_, v)| v.is_finite())
        .map(|(g, v)| (g as u32, *v))
        .collect();
    ranked.sort_by(|x, y| y.1.total_cmp(&x.1).then(x.0.cmp(&y.0)));
    ranked.truncate(n);
    Ok(ranked)
}

/// A selection of every Gaussian with a descriptor and its score (threshold `-inf`), so
/// that a threshold can be chosen afterwards.
pub fn every_valid_selection(prompt: &str, kind: ScoreKind, scores: &[f32]) -> Result<Selection> {
    let all = select(scores, Rule::Threshold(f32::MIN))?;
    Ok(Selection {
        prompt: prompt.to_string(),
        num_gaussians: scores.len(),
        gaussian_ids: all.ids.into(),
        scores: all.scores.into(),
        extra: [
            ("score".to_string(), kind.name().to_string()),
            ("threshold".to_string(), "-inf".to_string()),
            ("rule".to_string(), "every valid Gaussian".to_string()),
        ]
        .into_iter()
        .collect(),
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use profuse_formats::{Features, Floats, Prompts};

    fn inputs() -> ScoreInputs {
        ScoreInputs {
            descriptors: DescriptorSet::Features(Features {
                features: Floats::F32(vec![1.0, 0.0, 0.0, 1.0, 0.6, 0.8].into()),
                dim: 2,
                valid: vec![1u8, 1, 1].into(),
                weight_sum: None,
                extra: Default::default(),
            }),
            prompts: Prompts {
                names: vec!["x".into()],
                dim: 2,
                embeddings: vec![1.0, 0.0].into(),
                ..Default::default()
            },
            descriptors_path: "f".into(),
            prompts_path: "p".into(),
        }
    }

    #[test]
    fn statistics_and_ranking_of_a_hand_case() {
        let scores = [1.0, 0.0, f32::NAN, 0.6];
        let s = prompt_scores(&inputs(), 0, &scores, ScoreKind::Cosine, 2, 10).unwrap();
        assert_eq!(s.valid, 3);
        assert_eq!((s.min, s.max, s.p50), (Some(0.0), Some(1.0), Some(0.6)));
        assert!((s.mean.unwrap() - 1.6 / 3.0).abs() < 1e-7);
        assert_eq!(s.top, vec![(0, 1.0), (3, 0.6)]);
        let sel = every_valid_selection("x", ScoreKind::Cosine, &scores).unwrap();
        assert_eq!(sel.gaussian_ids.len(), 3);
        assert_eq!(sel.num_gaussians, 4);
    }
}

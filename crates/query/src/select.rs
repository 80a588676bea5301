//! Active sets: the Gaussians a prompt selects in 3D, by threshold or by top fraction.

use std::cmp::Ordering;

use crate::error::{QueryError, Result};

/// How the active set is chosen from the scores.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rule {
    /// Every Gaussian with score >= τ (paper: 𝒢_τ = {g | ⟨f̂_g, q̂⟩ >= τ}); τ finite.
    Threshold(f32),
    /// The ⌈f·V⌉ highest-scoring of the V Gaussians with a descriptor, f in [0, 1]; ties
    /// in score go to the lower id. (⌈·⌉ with a 1e-9 tolerance, so 0.1 × 30 is 3.)
    TopFraction(f64),
}

impl Rule {
    /// Checks the parameter's range.
    pub fn validate(&self) -> Result<()> {
        match *self {
            Rule::Threshold(t) if !t.is_finite() => Err(QueryError::BadParameter {
                name: "threshold",
                value: t.to_string(),
                expected: "a finite number",
            }),
            Rule::TopFraction(f) if !(0.0..=1.0).contains(&f) => Err(QueryError::BadParameter {
                name: "top_frac",
                value: f.to_string(),
                expected: "a fraction in [0, 1]",
            }),
            _ => Ok(()),
        }
    }
}

/// The Gaussians a prompt selected.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ActiveSet {
    /// Selected Gaussian ids, strictly increasing.
    pub ids: Vec<u32>,
    /// Their scores.
    pub scores: Vec<f32>,
    /// The effective threshold: τ for [`Rule::Threshold`], the lowest selected score for
    /// [`Rule::TopFraction`] (+∞ when nothing is selected).
    pub threshold: f32,
}

impl ActiveSet {
    /// Number of selected Gaussians.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// Whether nothing is selected.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }
}

/// Applies `rule` to the per-Gaussian `scores` (finite, or −∞ for Gaussians without a
/// descriptor, which are never selected).
pub fn select(scores: &[f32], rule: Rule) -> Result<ActiveSet> {
    rule.validate()?;
    let ids: Vec<u32> = match rule {
        Rule::Threshold(t) => (0..scores.len())
            .filter(|&g| scores[g].is_finite() && scores[g] >= t)
            .map(|g| g as u32)
            .collect(),
        Rule::TopFraction(f) => {
            let mut ranked: Vec<u32> = (0..scores.len())
                .filter(|&g| scores[g].is_finite())
                .map(|g| g as u32)
                .collect();
            let count = ((f * ranked.len() as f64) - 1e-9).ceil().max(0.0) as usize;
            let by_rank = |a: &u32, b: &u32| {
                descending(scores[*a as usize], scores[*b as usize]).then(a.cmp(b))
            };
            if count < ranked.len() {
                ranked.select_nth_unstable_by(count, by_rank);
                ranked.truncate(count);
            }
            ranked.sort_unstable();
            ranked
        }
    };
    let picked: Vec<f32> = ids.iter().map(|&g| scores[g as usize]).collect();
    let threshold = match rule {
        Rule::Threshold(t) => t,
        Rule::TopFraction(_) => picked.iter().copied().fold(f32::INFINITY, f32::min),
    };
    Ok(ActiveSet {
        ids,
        scores: picked,
        threshold,
    })
}

fn descending(a: f32, b: f32) -> Ordering {
    b.total_cmp(&a)
}

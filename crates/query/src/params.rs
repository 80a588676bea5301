//! The query stage's parameters as a pipeline runs it (the pipeline's `[query]` section).

use serde::{Deserialize, Serialize};

use crate::{ScoreKind, Semantics, DEFAULT_GAMMA, DEFAULT_RELEVANCY_THRESHOLD, DEFAULT_TOP_K};

/// What a pipeline's query stage selects with. The defaults are the LERF-style evaluation's:
/// relevancy against the canonical negatives, selected where the prompt beats every
/// negative (τ = 0.5).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Params {
    /// `relevancy` (LERF, with the canonical negatives) or `cosine` (the paper's score).
    pub score: ScoreKind,
    /// Selection threshold τ on the score.
    pub threshold: f32,
    /// Silhouette threshold γ of the per-view masks.
    pub gamma: f32,
    /// Top-K contributors per pixel for the masks.
    pub k: usize,
    /// Prompts to query; empty = the categories of the LERF label files when the scene has
    /// them, else every class prompt.
    pub prompts: Vec<String>,
    /// Also write overlays of the selections on the rendered views.
    pub overlay: bool,
    /// Per-Gaussian semantics the query and vertex-transfer stages read: `pq` (codes of
    /// every Gaussian), `index` (fuse's semantic index: dominant proposal per Gaussian) or
    /// `both` (the index, with PQ codes for Gaussians without a dominant proposal).
    pub semantics: Semantics,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            score: ScoreKind::Relevancy,
            threshold: DEFAULT_RELEVANCY_THRESHOLD,
            gamma: DEFAULT_GAMMA,
            k: DEFAULT_TOP_K,
            prompts: Vec::new(),
            overlay: true,
            semantics: Semantics::Pq,
        }
    }
}

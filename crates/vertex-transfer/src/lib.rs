//! Mesh-vertex labels from language Gaussians (paper §4.3, "Open-Vocabulary Point Cloud
//! Understanding"): every vertex of a mesh gets the class its nearby Gaussians vote for,
//! with a kernel that respects each Gaussian's full ellipsoid. No rendering is involved.
//!
//! # The rule
//!
//! For a vertex x:
//!
//! 1. **Shortlist**: the K (= 64) nearest *valid* Gaussian centres by Euclidean distance,
//!    from a kiddo [`ImmutableKdTree`](kiddo::immutable::float::kdtree::ImmutableKdTree)
//!    built over the Gaussians whose descriptor is valid (`features.valid = 1`), so
//!    invalid Gaussians never take shortlist slots. The search is bounded by the radius
//!    σ · (largest standard deviation of any valid Gaussian), beyond which no Gaussian can
//!    pass the gate (d >= |x − μ| / s_max): the gated candidates are exactly those of the
//!    unbounded K nearest, found 3–6x faster on ScanNet (unbounded when a scale is huge).
//! 2. **Gate**: keep a shortlisted Gaussian when its Mahalanobis distance d <= σ (= 3),
//!    d² = (x − μ)ᵀ Σ⁻¹ (x − μ) with Σ = R S Sᵀ Rᵀ (SPEC.md §4.2: S = diag(exp(log_scales)),
//!    R from the normalised quaternion (w, x, y, z)). It is evaluated as |S⁻¹ Rᵀ (x − μ)|²,
//!    never inverting Σ; each standard deviation is clamped to at least
//!    [`Params::min_scale`] (default 1e-4 scene units = 0.1 mm in metric scenes), so flat
//!    Gaussians (one log-scale near −∞) stay invertible and gate a thin slab instead of
//!    producing inf/NaN.
//! 3. **Weight**: w = exp(−d²/2) · sigmoid(opacity logit).
//! 4. **Class probabilities** per Gaussian: softmax over the class prompts of
//!    cos(f_g, e_q) / T, summed per class when several prompts name one class. T defaults
//!    to 0.1 (the paper gives no value): at CLIP's own logit scale (T = 0.01) every
//!    Gaussian votes nearly one-hot, and Gaussians of classes outside the evaluated set,
//!    or with noisy features, then vote hard for a wrong class; softer votes average them
//!    out (measured on the ScanNet oracle: see the README). Descriptors are normalised on
//!    use (decoded PQ codes are not unit length). Computed once per Gaussian, not per
//!    (vertex, candidate).
//! 5. **Vote**: score_c = Σ_candidates w · p_c (f64, in ascending Gaussian index);
//!    label = argmax_c (ties to the smaller class index = the smaller label);
//!    confidence = max_c score_c / Σ w ∈ [0, 1]. A vertex with no candidate (or only
//!    zero weights) gets label −1 and confidence 0.
//!
//! # Design decisions
//!
//! * **Classes** ([`ClassSet`]) come from a prompts file: every row with `class_ids >= 0`
//!   (the label written is the class id), or an explicit list of prompt names (label =
//!   class id when the file has `class_ids`, else the name's position in the list).
//! * **Exactness of the shortlist**: candidates are summed in Gaussian-index order, so the
//!   tree result equals the brute force over all Gaussians
//!   ([`GaussianField::label_vertices_brute_force`]) bit for bit wherever the K nearest
//!   centres contain every gated Gaussian; [`Stats::saturated`] counts vertices where they
//!   might not (all K passed the gate).
//! * **Determinism**: vertices are labelled in parallel chunks (rayon) that write disjoint
//!   output slices; each vertex's sum runs in a fixed order, and the counters are integer
//!   sums — the output bytes do not depend on the thread count.
//! * **Memory**: per valid Gaussian a 52-byte kernel (mean, whitening matrix, opacity) and
//!   C class probabilities; the descriptors themselves are read once and not kept.
//!
//! # Example
//!
//! ```
//! use profuse_formats::{Features, Gaussians, Prompts};
//! use vertex_transfer::{ClassSet, Descriptors, GaussianField, Params, Source};
//!
//! // Two Gaussians, one "chair" (class 5) at the origin, one "table" (7) at x = 1.
//! let gaussians = Gaussians {
//!     means: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]].into(),
//!     log_scales: vec![[0.1f32.ln(); 3]; 2].into(),
//!     rotations: vec![[1.0, 0.0, 0.0, 0.0]; 2].into(),
//!     opacity_logits: vec![3.0; 2].into(),
//!     sh_dc: vec![[0.0; 3]; 2].into(),
//!     ..Default::default()
//! };
//! let features = Features {
//!     features: vec![1.0f32, 0.0, 0.0, 1.0].into(),
//!     dim: 2,
//!     valid: vec![1u8, 1].into(),
//!     weight_sum: None,
//!     extra: Default::default(),
//! };
//! let prompts = Prompts {
//!     names: vec!["chair".into(), "table".into(), "object".into()],
//!     dim: 2,
//!     embeddings: vec![1.0, 0.0, 0.0, 1.0, 1.0, 1.0].into(),
//!     class_ids: Some(vec![5, 7, -1].into()),
//!     ..Default::default()
//! };
//! let classes = ClassSet::from_prompts(Source::new("prompts", &prompts))?;
//! let field = GaussianField::new(
//!     Source::new("gaussians", &gaussians),
//!     Descriptors::Features(Source::new("features", &features)),
//!     &classes,
//!     &Params::default(),
//! )?;
//! // Near the first Gaussian, near the second, and far from both (d > 3 for both).
//! let out = field.label_vertices(&[[0.05, 0.0, 0.0], [0.9, 0.1, 0.0], [0.5, 2.0, 0.0]]);
//! assert_eq!(out.labels, vec![5, 7, -1]);
//! assert!(out.confidence[0] > 0.99 && out.confidence[2] == 0.0);
//! # Ok::<(), vertex_transfer::TransferError>(())
//! ```

mod classes;
mod error;
mod field;
mod job;
pub mod kernel;
#[cfg(feature = "oracle")]
pub mod oracle;

pub use classes::ClassSet;
pub use error::{Result, TransferError};
pub use field::{
    Candidate, Descriptors, GaussianField, Labelling, Params, Stats, DEFAULT_K, DEFAULT_MIN_SCALE,
    DEFAULT_SIGMA, DEFAULT_TEMPERATURE,
};
pub use job::{run_job, run_job_with_progress, DescriptorFile, Job, JobReport, JobStage};
pub use kernel::Kernel;

/// An in-memory input with the name its errors report (usually its file path).
#[derive(Debug)]
pub struct Source<'a, T> {
    /// The name errors report.
    pub file: &'a str,
    /// The data.
    pub data: &'a T,
}

impl<'a, T> Source<'a, T> {
    /// Pairs data with the name its errors report.
    pub fn new(file: &'a str, data: &'a T) -> Self {
        Source { file, data }
    }
}

impl<T> Clone for Source<'_, T> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<T> Copy for Source<'_, T> {}

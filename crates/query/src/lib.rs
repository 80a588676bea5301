//! Open-vocabulary 3D selection (paper §3.4 "Inference Procedure" and §4.2): score every
//! Gaussian's language descriptor against a text embedding, select the active Gaussians
//! directly in 3D, and show the selection in any view as an activation mask built from
//! the rasterizer's per-pixel top-K contributors.
//!
//! # What it computes
//!
//! * **Scores** ([`score_prompts`]). With q̂ = q/‖q‖ the prompt embedding and f̂_g the
//!   descriptor of Gaussian g (divided by its own norm, so F16 storage does not bias it):
//!   - cosine: s_g = ⟨q̂, f̂_g⟩ (the paper's score);
//!   - LERF relevancy (LangSplat, Dr. Splat): s_g = min over the canonical negatives n
//!     (`object`, `things`, `stuff`, `texture`, those present in the prompts file, the
//!     prompt itself excluded) of softmax(10·[⟨q̂, f̂_g⟩, ⟨n̂, f̂_g⟩])₀
//!     = 1 / (1 + exp(10(c_n − c_q))), evaluated with a non-positive exponent
//!     ([`relevancy`]) so it is exact for any finite cosines. Relevancy >= 0.5 exactly when
//!     the prompt beats every negative, hence the default threshold 0.5.
//!
//!   Gaussians without a descriptor score [`INVALID_SCORE`] (−∞) and are never selected.
//!   Descriptors come from a `profuse.features` file (exact) or a `profuse.pq` file
//!   (asymmetric distance against the decoded vectors, `profuse_pq::adc_scores`, which
//!   equals the cosine with the decoded descriptor up to f32 rounding). Each descriptor
//!   row is read once for all prompts, and the negatives' cosines are shared by all
//!   prompts.
//! * **Active sets** ([`select`]): score >= τ ([`Rule::Threshold`]), or the ⌈f·V⌉ best of
//!   the V Gaussians with a descriptor ([`Rule::TopFraction`], ties to the lower id).
//! * **Activation masks** ([`activation`]): for view i and pixel p with top-K contributors
//!   (g_t, ω_t), A_i(p) = Σ_t ω_t·1[g_t active], summed in slot order; the mask is
//!   A_i(p) >= γ (γ = 0.5 by default: the active Gaussians carry at least half of the
//!   pixel's top-K weight; K = 10).
//!
//! # Design decisions
//!
//! * **One render pass for every prompt.** The per-view top-K buffer (8K bytes a pixel) is
//!   the expensive part, so [`Plan::run`] renders each view once with
//!   `splat_raster::Rasterizer::for_each_view` (one view's buffers alive at a time) and a
//!   [`Membership`] bitset (one bit per prompt per Gaussian, ⌈Q/8⌉ bytes) turns the
//!   buffer into every prompt's activation in one pass; masks are identical to separate
//!   runs.
//! * **Validate, then write.** [`Inputs::plan`] reads and cross-checks every file (counts,
//!   dimensions, prompt names, views, parameters) and computes every active set before
//!   [`Plan::run`] creates a directory, so bad input writes nothing. PNGs are written to
//!   a temporary file and renamed; selection files go through `profuse_formats`.
//! * **Determinism.** Scores are per-Gaussian computations with a fixed summation order,
//!   activations are per-pixel sums in slot order, and the renderer is bit-identical for
//!   any thread count, so the output bytes do not depend on the thread count.
//!
//! # Query by click ([`click`])
//!
//! A click (view, x = column, y = row in image pixels) picks the mask under it in the
//! masks file; its query vector is the pooled descriptor of that mask's 3D Context
//! Proposal (eq. proposal-desc, computed by `profuse_fuse::pooled_descriptor`, the
//! registration's own code, rendering only the proposal's views) or, with
//! [`ClickBy::Mask`], the mask's own feature. [`ClickTarget::prompts`] makes it a one-row
//! prompts table (plus the canonical negatives of a prompts file, for relevancy), so
//! scoring, the selection rule and every output are those of a text query.
//! [`selected_gaussians`] cuts the selected Gaussians out as a Gaussian set of their own
//! (the query tool writes it as an INRIA PLY with scene-io's writer).
//!
//! # Outputs ([`Layout`])
//!
//! ```text
//! --layout prompt (default)                  --layout lerf (what the LERF-OVS metric reads)
//! OUT/<prompt>/selection.safetensors         OUT/<stem>/<prompt>.png
//! OUT/<prompt>/masks/<stem>.png              OUT/selection/<prompt>.safetensors
//! OUT/<prompt>/overlay/<stem>.png            OUT/overlay/<stem>/<prompt>.png
//! ```
//!
//! `<stem>` is the file stem of the view's image name; masks are 8-bit grey PNGs (0 or
//! 255); overlays are the rendered colour with selected pixels tinted red.
//!
//! # Example
//!
//! ```
//! use profuse_formats::{Features, Gaussians, Prompts};
//! use profuse_query::{activation, score_prompts, select, Descriptors, Membership, Rule, ScoreKind};
//! use splat_raster::{camera, Rasterizer, RenderOptions};
//!
//! // Two Gaussians on the optical axis: a "chair" in front of a "table".
//! let g = Gaussians {
//!     means: vec![[0.0, 0.0, 3.0], [0.0, 0.0, 5.0]].into(),
//!     log_scales: vec![[-1.0; 3]; 2].into(),
//!     rotations: vec![[1.0, 0.0, 0.0, 0.0]; 2].into(),
//!     opacity_logits: vec![4.0, 4.0].into(),
//!     sh_dc: vec![[0.0; 3]; 2].into(),
//!     ..Default::default()
//! };
//! let features = Features {
//!     features: profuse_formats::Floats::F32(vec![1.0, 0.0, 0.0, 1.0].into()),
//!     dim: 2,
//!     valid: vec![1, 1].into(),
//!     weight_sum: None,
//!     extra: Default::default(),
//! };
//! let prompts = Prompts {
//!     names: vec!["chair".into(), "table".into()],
//!     dim: 2,
//!     embeddings: vec![2.0, 0.2, 0.1, 1.0].into(),
//!     ..Default::default()
//! };
//! let scores = score_prompts(Descriptors::Features(&features), &prompts, &[0], ScoreKind::Cosine)?;
//! assert!((scores[0][0] - 0.995).abs() < 1e-3 && (scores[0][1] - 0.0995).abs() < 1e-3);
//! let chair = select(&scores[0], Rule::Threshold(0.5))?;
//! assert_eq!(chair.ids, vec![0]);
//!
//! // Render the view's top-K once and turn it into the activation of every prompt.
//! let pose = camera::look_at([0.0; 3], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]).unwrap();
//! let cams = camera::cameras_from_poses(&[pose], 33, 31, camera::pinhole_intrinsics(33, 31, 60.0));
//! let opts = RenderOptions { color: false, top_k: Some(10), ..Default::default() };
//! let view = Rasterizer::new(&g)?.render_view(&cams, 0, &opts)?;
//! let act = activation(
//!     view.topk_ids().unwrap(),
//!     view.topk_weights().unwrap(),
//!     view.width(),
//!     view.height(),
//!     10,
//!     &Membership::new(g.len(), &[&chair]),
//! )?;
//! // The centre pixel is dominated by the chair in front (opacity 0.98).
//! assert!(act.get(0, 16, 15) > 0.9);
//! assert_eq!(act.mask(0, 0.5)[15 * 33 + 16], 255);
//! assert_eq!(act.mask(0, 0.5)[0], 0); // a corner sees nothing
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

mod activation;
pub mod click;
mod error;
mod export;
mod output;
mod params;
mod pick;
mod pipeline;
mod score;
mod select;
mod semantic;
pub mod stats;

pub use activation::{activation, Activation, Membership};
pub use click::{resolve_click, Click, ClickBy, ClickSource, ClickTarget};
pub use error::{QueryError, Result};
pub use export::selected_gaussians;
pub use output::{overlay, OVERLAY_MIX, OVERLAY_TINT};
pub use params::Params;
pub use pipeline::{
    file_name_of, image_stem, is_query_output, rule_text, scale_cameras, DescriptorPath,
    DescriptorSet, Inputs, Layout, Plan, PlannedPrompt, PlannedView, PromptReport, PromptSelection,
    QueryOptions, Report, ScoreInputs, ViewSelection, DEFAULT_GAMMA, DEFAULT_RELEVANCY_THRESHOLD,
    DEFAULT_TOP_K,
};
pub use score::{
    dot, negatives_for, relevancy, score_prompts, unit_vector, Descriptors, ScoreKind,
    CANONICAL_NEGATIVES, INVALID_SCORE, RELEVANCY_TEMPERATURE,
};
pub use select::{select, ActiveSet, Rule};
pub use semantic::{
    select_indexed, select_indexed_into, IndexQuery, IndexTable, Indexed, SelectBuffers, Semantics,
};

//! Typed errors of the vertex label transfer.

use profuse_formats::FormatError;

/// Why a transfer could not run. Every variant about input names the file (or the label
/// the caller gave an in-memory input, see [`crate::Source`]) and what was expected.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum TransferError {
    /// A file could not be read or written, or an input violates SPEC.md.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// The descriptors (features or PQ codes) do not have one row per Gaussian.
    #[error(
        "{file}: `{tensor}` has {found} rows, expected one per Gaussian of {gaussians_file} ({expected})"
    )]
    CountMismatch {
        /// The descriptor file.
        file: String,
        /// The tensor whose row count is wrong.
        tensor: &'static str,
        /// Its number of rows.
        found: usize,
        /// The gaussians file.
        gaussians_file: String,
        /// The number of Gaussians.
        expected: usize,
    },
    /// Descriptors and class prompt embeddings live in spaces of different dimension.
    #[error(
        "{file}: descriptors have dimension {found}, but the prompt embeddings of {prompts_file} have dimension {expected}"
    )]
    DimMismatch {
        /// The descriptor file.
        file: String,
        /// The descriptor dimension.
        found: usize,
        /// The prompts file.
        prompts_file: String,
        /// The embedding dimension of the prompts.
        expected: usize,
    },
    /// No prompt qualifies as a class.
    #[error("{file}: no class prompts: {detail}")]
    NoClassPrompts {
        /// The prompts file.
        file: String,
        /// Why (no `class_ids`, every class id −1, an empty `--classes` list).
        detail: String,
    },
    /// A prompt named as a class is absent, repeated, or not a class.
    #[error("{file}: metadata `names`: {detail}")]
    BadClassPrompt {
        /// The prompts file.
        file: String,
        /// Which name and why.
        detail: String,
    },
    /// The mesh has no ground-truth labels where they are needed (the oracle fixture).
    #[error("{file}: missing tensor `labels` (the per-vertex classes the fixture places Gaussians with)")]
    MissingMeshLabels {
        /// The mesh file.
        file: String,
    },
    /// A transfer parameter is out of its domain.
    #[error("parameter `{name}` is {value}, expected {expected}")]
    Parameter {
        /// The parameter.
        name: &'static str,
        /// Its value, printed.
        value: String,
        /// Its domain.
        expected: &'static str,
    },
}

/// Result alias of this crate.
pub type Result<T, E = TransferError> = std::result::Result<T, E>;

//! The one error type of the format crate.
//!
//! Every variant names the file; every variant about content names the tensor or
//! metadata key and what was expected, so a user can fix the file without reading code.
//! [`FormatError::code`] is a stable machine-readable name shared with the Python reader.

use std::io;

/// Why a file could not be read, validated or written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FormatError {
    /// The file could not be opened, mapped, written or renamed.
    #[error("{path}: {action}: {source}")]
    Io {
        path: String,
        action: &'static str,
        #[source]
        source: io::Error,
    },
    /// The file ends before the header or the tensor data it announces.
    #[error("{path}: truncated: {detail}")]
    Truncated { path: String, detail: String },
    /// The safetensors header is malformed or lies about the data (bad JSON,
    /// offsets that overlap or leave gaps, byte sizes that disagree with shapes).
    #[error("{path}: invalid safetensors header: {detail}")]
    Header { path: String, detail: String },
    /// `__metadata__.format` names another file kind (or is absent).
    #[error("{path}: metadata `format` is {found}, expected \"{expected}\"")]
    WrongKind {
        path: String,
        expected: String,
        found: String,
    },
    /// `__metadata__.format_version` has a major version this reader does not know.
    #[error("{path}: metadata `format_version` is {found}, expected \"{supported}.<minor>\"")]
    WrongVersion {
        path: String,
        found: String,
        supported: u32,
    },
    /// A metadata key is missing or its value does not parse or is inconsistent.
    #[error("{path}: metadata `{key}`: expected {expected}")]
    Metadata {
        path: String,
        key: String,
        expected: String,
    },
    /// A required tensor is absent.
    #[error("{path}: missing tensor `{tensor}` (expected {expected})")]
    MissingTensor {
        path: String,
        tensor: String,
        expected: String,
    },
    /// A tensor has a dtype the spec does not allow for it.
    #[error("{path}: tensor `{tensor}` has dtype {found}, expected {expected}")]
    Dtype {
        path: String,
        tensor: String,
        found: String,
        expected: String,
    },
    /// A tensor's shape disagrees with the spec or with another tensor.
    #[error("{path}: tensor `{tensor}` has shape {found:?}, expected {expected}")]
    Shape {
        path: String,
        tensor: String,
        found: Vec<usize>,
        expected: String,
    },
    /// An index or value lies outside its allowed range (an id pointing outside its table,
    /// a certainty outside [0, 1], offsets that decrease, ...).
    #[error("{path}: tensor `{tensor}` element {index} is {value}, expected {expected}")]
    OutOfRange {
        path: String,
        tensor: String,
        index: usize,
        value: String,
        expected: String,
    },
    /// A NaN or infinity where the spec requires finite values.
    #[error("{path}: tensor `{tensor}` element {index} is {value}, expected a finite value")]
    NonFinite {
        path: String,
        tensor: String,
        index: usize,
        value: String,
    },
    /// A semantic rule that is not a simple range (a rotation that is not orthonormal,
    /// a feature row that is not unit length, duplicate names, ...).
    #[error("{path}: tensor `{tensor}`: {detail}")]
    Invalid {
        path: String,
        tensor: String,
        detail: String,
    },
}

impl FormatError {
    /// Stable machine-readable name of the error class (SPEC.md "Errors").
    pub fn code(&self) -> &'static str {
        match self {
            FormatError::Io { .. } => "io",
            FormatError::Truncated { .. } => "truncated",
            FormatError::Header { .. } => "header",
            FormatError::WrongKind { .. } => "wrong_kind",
            FormatError::WrongVersion { .. } => "wrong_version",
            FormatError::Metadata { .. } => "metadata",
            FormatError::MissingTensor { .. } => "missing_tensor",
            FormatError::Dtype { .. } => "dtype",
            FormatError::Shape { .. } => "shape",
            FormatError::OutOfRange { .. } => "out_of_range",
            FormatError::NonFinite { .. } => "non_finite",
            FormatError::Invalid { .. } => "invalid",
        }
    }

    /// The tensor or metadata key the error is about, if any.
    pub fn field(&self) -> Option<&str> {
        match self {
            FormatError::Io { .. } | FormatError::Truncated { .. } | FormatError::Header { .. } => {
                None
            }
            FormatError::WrongKind { .. } => Some("format"),
            FormatError::WrongVersion { .. } => Some("format_version"),
            FormatError::Metadata { key, .. } => Some(key),
            FormatError::MissingTensor { tensor, .. }
            | FormatError::Dtype { tensor, .. }
            | FormatError::Shape { tensor, .. }
            | FormatError::OutOfRange { tensor, .. }
            | FormatError::NonFinite { tensor, .. }
            | FormatError::Invalid { tensor, .. } => Some(tensor),
        }
    }

    /// The file the error is about.
    pub fn path(&self) -> &str {
        match self {
            FormatError::Io { path, .. }
            | FormatError::Truncated { path, .. }
            | FormatError::Header { path, .. }
            | FormatError::WrongKind { path, .. }
            | FormatError::WrongVersion { path, .. }
            | FormatError::Metadata { path, .. }
            | FormatError::MissingTensor { path, .. }
            | FormatError::Dtype { path, .. }
            | FormatError::Shape { path, .. }
            | FormatError::OutOfRange { path, .. }
            | FormatError::NonFinite { path, .. }
            | FormatError::Invalid { path, .. } => path,
        }
    }
}

/// Result alias of the format crate.
pub type Result<T, E = FormatError> = std::result::Result<T, E>;

//! The crate's typed error.

use std::io;

/// Everything that can go wrong while evaluating; each variant names the offending input
/// (file, field) and what was expected.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum MetricsError {
    /// Two per-item arrays that must align have different lengths.
    #[error("{what}: {left_name} has {left} entries but {right_name} has {right}")]
    LengthMismatch {
        /// What was being evaluated.
        what: &'static str,
        /// Name of the first array.
        left_name: &'static str,
        /// Its length.
        left: usize,
        /// Name of the second array.
        right_name: &'static str,
        /// Its length.
        right: usize,
    },
    /// A file or directory could not be read or listed.
    #[error("{path}: {action}: {source}")]
    Io {
        /// The path.
        path: String,
        /// What was attempted.
        action: &'static str,
        /// The OS error.
        #[source]
        source: io::Error,
    },
    /// A JSON file does not parse or does not have the expected structure.
    #[error("{path}: not a valid {expected}: {source}")]
    Json {
        /// The path.
        path: String,
        /// The schema expected.
        expected: &'static str,
        /// The parser's error (with line and column).
        #[source]
        source: serde_json::Error,
    },
    /// A field of an input parses but its value is not allowed.
    #[error("{path}: `{field}`: {detail}")]
    Invalid {
        /// The file (or `<memory>`).
        path: String,
        /// The field, e.g. `objects[3].segmentation` or `masks[12].id`.
        field: String,
        /// What is wrong and what was expected.
        detail: String,
    },
    /// A PNG mask could not be decoded.
    #[error("{path}: cannot decode image: {source}")]
    Image {
        /// The path.
        path: String,
        /// The decoder's error.
        #[source]
        source: image::ImageError,
    },
    /// A predicted mask does not have the size of the ground truth it is compared with.
    #[error("{path}: mask is {found_width}x{found_height}, expected {width}x{height} (the size in the label file)")]
    MaskSize {
        /// The predicted mask.
        path: String,
        /// Width of the ground truth.
        width: u32,
        /// Height of the ground truth.
        height: u32,
        /// Width found.
        found_width: u32,
        /// Height found.
        found_height: u32,
    },
    /// A pipeline file could not be read or failed validation.
    #[error(transparent)]
    Format(#[from] profuse_formats::FormatError),
    /// A ground-truth file (`gt/scene.json`, `gt/mask_objects.json`) could not be read or
    /// failed validation.
    #[error(transparent)]
    GroundTruth(#[from] profuse_formats::ground_truth::GtError),
}

/// Result alias of this crate.
pub type Result<T, E = MetricsError> = std::result::Result<T, E>;

/// Builds the closure for `map_err` of an I/O call on `path`.
pub(crate) fn io_err<'a>(
    path: &'a std::path::Path,
    action: &'static str,
) -> impl FnOnce(io::Error) -> MetricsError + 'a {
    move |source| MetricsError::Io {
        path: path.display().to_string(),
        action,
        source,
    }
}

/// An [`MetricsError::Invalid`].
pub(crate) fn invalid(
    path: impl std::fmt::Display,
    field: impl Into<String>,
    detail: impl Into<String>,
) -> MetricsError {
    MetricsError::Invalid {
        path: path.to_string(),
        field: field.into(),
        detail: detail.into(),
    }
}

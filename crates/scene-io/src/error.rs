//! The one error type of the crate.
//!
//! Every variant names the file; every variant about content names the field (PLY
//! property, JSON key, COLMAP line, NumPy header key, ...) and what was expected, so a
//! user can fix the input without reading code. [`SceneError::code`] is a stable
//! machine-readable class name.

use std::io;

use profuse_formats::FormatError;

/// Why a scene could not be imported or exported.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SceneError {
    /// A file or directory could not be opened, listed, read, written or renamed.
    #[error("{path}: {action}: {source}")]
    Io {
        path: String,
        action: &'static str,
        #[source]
        source: io::Error,
    },
    /// The file ends before the data its header announces.
    #[error("{path}: truncated: {detail}")]
    Truncated { path: String, detail: String },
    /// A malformed header (PLY header line, NumPy header dictionary, magic bytes).
    #[error("{path}: malformed header: {detail}")]
    Header { path: String, detail: String },
    /// A well-formed input using a feature this crate does not read (big-endian data,
    /// a fisheye camera model, a Fortran-ordered array, an unknown dtype, ...).
    #[error("{path}: unsupported {what}: {detail}")]
    Unsupported {
        path: String,
        what: String,
        detail: String,
    },
    /// A required field (PLY property, JSON key, file of a model) is absent.
    #[error("{path}: missing {field} (expected {expected})")]
    Missing {
        path: String,
        field: String,
        expected: String,
    },
    /// A value that does not parse, at a line of a text file.
    #[error("{path}:{line}: {field}: expected {expected}, found {found:?}")]
    Parse {
        path: String,
        line: usize,
        field: String,
        expected: String,
        found: String,
    },
    /// NaN or infinity where a finite value is required.
    #[error("{path}: {field} of element {index} is {value}, expected a finite number")]
    NonFinite {
        path: String,
        field: String,
        index: usize,
        value: String,
    },
    /// Any other semantic rule (counts that disagree, an index out of range, a rotation
    /// that is not one, a zero feature row, ...).
    #[error("{path}: {field}: {detail}")]
    Invalid {
        path: String,
        field: String,
        detail: String,
    },
    /// A JSON file that does not parse.
    #[error("{path}: invalid JSON: {source}")]
    Json {
        path: String,
        #[source]
        source: serde_json::Error,
    },
    /// A zip archive (`.npz`) that cannot be read.
    #[error("{path}: invalid zip archive: {source}")]
    Zip {
        path: String,
        #[source]
        source: zip::result::ZipError,
    },
    /// An image whose header cannot be read (only its size is ever needed).
    #[error("{path}: cannot read the image size: {source}")]
    Image {
        path: String,
        #[source]
        source: image::ImageError,
    },
    /// The converted data failed the ProFuse file validation, or writing it failed.
    #[error(transparent)]
    Format(#[from] FormatError),
}

impl SceneError {
    /// Stable machine-readable name of the error class.
    pub fn code(&self) -> &'static str {
        match self {
            SceneError::Io { .. } => "io",
            SceneError::Truncated { .. } => "truncated",
            SceneError::Header { .. } => "header",
            SceneError::Unsupported { .. } => "unsupported",
            SceneError::Missing { .. } => "missing",
            SceneError::Parse { .. } => "parse",
            SceneError::NonFinite { .. } => "non_finite",
            SceneError::Invalid { .. } => "invalid",
            SceneError::Json { .. } => "json",
            SceneError::Zip { .. } => "zip",
            SceneError::Image { .. } => "image",
            SceneError::Format(e) => e.code(),
        }
    }
}

/// Result alias of the crate.
pub type Result<T, E = SceneError> = std::result::Result<T, E>;

/// Shorthand constructors used across modules, so that call sites stay one line.
pub(crate) fn io_err(path: &str, action: &'static str, source: io::Error) -> SceneError {
    SceneError::Io {
        path: path.to_string(),
        action,
        source,
    }
}

pub(crate) fn invalid(
    path: &str,
    field: impl Into<String>,
    detail: impl Into<String>,
) -> SceneError {
    SceneError::Invalid {
        path: path.to_string(),
        field: field.into(),
        detail: detail.into(),
    }
}

pub(crate) fn missing(
    path: &str,
    field: impl Into<String>,
    expected: impl Into<String>,
) -> SceneError {
    SceneError::Missing {
        path: path.to_string(),
        field: field.into(),
        expected: expected.into(),
    }
}

pub(crate) fn unsupported(
    path: &str,
    what: impl Into<String>,
    detail: impl Into<String>,
) -> SceneError {
    SceneError::Unsupported {
        path: path.to_string(),
        what: what.into(),
        detail: detail.into(),
    }
}

pub(crate) fn truncated(path: &str, detail: impl Into<String>) -> SceneError {
    SceneError::Truncated {
        path: path.to_string(),
        detail: detail.into(),
    }
}

pub(crate) fn header_err(path: &str, detail: impl Into<String>) -> SceneError {
    SceneError::Header {
        path: path.to_string(),
        detail: detail.into(),
    }
}

pub(crate) fn parse_err(
    path: &str,
    line: usize,
    field: impl Into<String>,
    expected: impl Into<String>,
    found: impl Into<String>,
) -> SceneError {
    SceneError::Parse {
        path: path.to_string(),
        line,
        field: field.into(),
        expected: expected.into(),
        found: found.into(),
    }
}

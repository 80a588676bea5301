//! The one error type of the crate.

use std::io;

use profuse_formats::FormatError;

/// Why a scene could not be generated, written or rebuilt.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SynthError {
    /// A configuration parameter is outside its allowed range.
    #[error("parameter `{name}` is {value}, expected {expected}")]
    Parameter {
        /// The parameter (the `Config` / `FaultModel` field, also the CLI flag name).
        name: &'static str,
        /// The value given.
        value: String,
        /// What is allowed.
        expected: String,
    },
    /// An unknown preset name.
    #[error("unknown preset {0:?}, expected one of: tiny, demo, scale")]
    Preset(String),
    /// An unknown fault-set name.
    #[error("unknown fault set {0:?}, expected one of: default, noisy-features, harsh-segmentation, sparse-views")]
    FaultSet(String),
    /// A file or directory could not be created, written, renamed or read.
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
    /// An output rule refused the output directory (see `profuse_formats::output`).
    #[error(transparent)]
    Output(#[from] profuse_formats::output::OutputError),
    /// A safetensors file of the pipeline could not be written (validation or I/O).
    #[error(transparent)]
    Format(#[from] FormatError),
    /// A PNG image could not be encoded.
    #[error("{path}: cannot encode PNG: {source}")]
    Image {
        /// The image path.
        path: String,
        /// The encoder's error.
        #[source]
        source: image::ImageError,
    },
    /// A JSON file could not be serialised or parsed.
    #[error("{path}: JSON: {source}")]
    Json {
        /// The JSON path.
        path: String,
        /// The serde error.
        #[source]
        source: serde_json::Error,
    },
    /// A `gt/scene.json` describes a scene that cannot be built (bad dimensions, ...).
    #[error("{path}: invalid scene description: {detail}")]
    Scene {
        /// The scene description's path (or `<memory>`).
        path: String,
        /// What is wrong.
        detail: String,
    },
}

/// Result alias of the crate.
pub type Result<T, E = SynthError> = std::result::Result<T, E>;

pub(crate) fn io_err<'a>(
    path: &'a std::path::Path,
    action: &'static str,
) -> impl FnOnce(io::Error) -> SynthError + 'a {
    move |source| SynthError::Io {
        path: path.display().to_string(),
        action,
        source,
    }
}

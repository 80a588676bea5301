//! The one error type of the viewer crate.

use std::path::PathBuf;

/// Why the viewer could not start or answer a request.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ViewError {
    /// The directory lacks a file every pipeline output has.
    #[error(
        "{dir}: not a pipeline output: missing {missing} (give the scene directory that \
         `profuse run`/`profuse demo` wrote, or its `out/` directory)"
    )]
    NotPipelineOutput {
        /// The directory given.
        dir: PathBuf,
        /// The first missing file.
        missing: PathBuf,
    },
    /// Another process listens on the port.
    #[error("cannot listen on {addr}: the port is already in use (choose another with --port)")]
    PortInUse {
        /// host:port.
        addr: String,
    },
    /// Binding failed for another reason.
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        /// host:port.
        addr: String,
        /// The system's reason.
        source: std::io::Error,
    },
    /// A file was unreadable or invalid.
    #[error(transparent)]
    Format(#[from] profuse_formats::FormatError),
    /// Scoring, selection or click resolution failed.
    #[error(transparent)]
    Query(#[from] profuse_query::QueryError),
    /// The selected Gaussians could not be written as an INRIA PLY.
    #[error(transparent)]
    Export(#[from] scene_io::SceneError),
    /// The files disagree with each other.
    #[error("{file}: {reason}")]
    Mismatch {
        /// The file that disagrees.
        file: PathBuf,
        /// How.
        reason: String,
    },
    /// A request carried a bad parameter (answered with HTTP 400).
    #[error("bad request: parameter {name:?}: {reason}")]
    BadRequest {
        /// The parameter.
        name: String,
        /// What was expected.
        reason: String,
    },
}

/// Result with [`ViewError`].
pub type Result<T> = std::result::Result<T, ViewError>;

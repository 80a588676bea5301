//! The pipeline's error: which stage failed, and the stage crate's own error (which names
//! the file and field).

/// Why a run failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PipelineError {
    /// A configuration key or value is wrong.
    #[error("configuration {key}: {detail}")]
    Config {
        /// The key (or the config file).
        key: String,
        /// What is wrong.
        detail: String,
    },
    /// A required input of the scene directory is missing.
    #[error("stage {stage}: missing input {path} ({expected})")]
    MissingInput {
        /// The stage that needs it.
        stage: &'static str,
        /// The path.
        path: String,
        /// What the file should be.
        expected: &'static str,
    },
    /// A stage failed.
    #[error("stage {stage} failed")]
    Stage {
        /// The stage.
        stage: &'static str,
        /// The stage crate's error.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync + 'static>,
    },
    /// An output rule refused the output directory (another run holds its lock, it is
    /// not a directory, ...; see `profuse_formats::output`).
    #[error(transparent)]
    Output(#[from] profuse_formats::output::OutputError),
    /// A file or directory of the output could not be written.
    #[error("{path}: {action}: {source}")]
    Io {
        /// The path.
        path: String,
        /// What was attempted.
        action: &'static str,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
}

/// Result of this crate.
pub type Result<T, E = PipelineError> = std::result::Result<T, E>;

/// Wraps a stage crate's error.
pub fn stage_err<E>(stage: &'static str) -> impl FnOnce(E) -> PipelineError
where
    E: std::error::Error + Send + Sync + 'static,
{
    move |e| PipelineError::Stage {
        stage,
        source: Box::new(e),
    }
}

/// Wraps an I/O error with its path.
pub fn io_err<'a>(
    path: &'a std::path::Path,
    action: &'static str,
) -> impl FnOnce(std::io::Error) -> PipelineError + 'a {
    move |source| PipelineError::Io {
        path: path.display().to_string(),
        action,
        source,
    }
}

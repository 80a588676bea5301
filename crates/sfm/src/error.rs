//! The one error type of the crate.

use std::path::PathBuf;

use crate::SfmStep;

/// Everything that can go wrong while finding or running COLMAP.
#[derive(Debug, thiserror::Error)]
pub enum SfmError {
    /// Neither backend could be started. The message is one line that names the install
    /// commands and what was tried.
    #[error(
        "no COLMAP found: install it with `apt-get install colmap` or `pip install pycolmap` \
         (tried: {})",
        tried.join("; ")
    )]
    NoBackend {
        /// One entry per backend tried: the program and why it was not usable.
        tried: Vec<String>,
    },
    /// The images folder could not be listed.
    #[error("cannot read the images folder {}: {source}", path.display())]
    ImagesDir {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The images folder holds no image file COLMAP reads.
    #[error(
        "no images in {} (looked for {} files, subfolders included)",
        path.display(),
        crate::images::EXTENSIONS.join("/")
    )]
    NoImages { path: PathBuf },
    /// A file or folder under the work folder could not be created, read or moved.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// An option is out of range (say which and why).
    #[error("invalid SfM option {option}: {why}")]
    InvalidOption { option: &'static str, why: String },
    /// The step's program could not be started at all.
    #[error("cannot start COLMAP {step} ({}): {source}", program.display())]
    Spawn {
        step: SfmStep,
        program: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The step's program ran and failed.
    #[error(
        "COLMAP {step} failed ({status}); full output in {}; last lines:\n{tail}",
        log.display()
    )]
    StepFailed {
        step: SfmStep,
        /// The exit status as the OS reports it (`exit status: 1`, `signal: 9 (SIGKILL)`).
        status: String,
        /// The last lines of its standard error (of its standard output when it wrote
        /// nothing to standard error).
        tail: String,
        /// The step's full output.
        log: PathBuf,
    },
    /// The mapper finished without writing any model.
    #[error(
        "COLMAP mapper produced no model from {images} images (too few matches between \
         them?); full output in {}",
        log.display()
    )]
    NoModel { images: usize, log: PathBuf },
    /// The largest model has fewer than two registered images: there are no poses.
    #[error(
        "COLMAP registered only {registered} of {images} images (at least 2 are needed); \
         model in {}",
        model_dir.display()
    )]
    TooFewRegistered {
        registered: usize,
        images: usize,
        model_dir: PathBuf,
    },
    /// A model file the mapper wrote could not be parsed.
    #[error("malformed COLMAP model file {}: {why}", path.display())]
    Model { path: PathBuf, why: String },
}

impl SfmError {
    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> SfmError {
        SfmError::Io {
            path: path.into(),
            source,
        }
    }
}

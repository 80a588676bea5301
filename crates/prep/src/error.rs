//! The crate's one error type: every variant names the file or input and the expectation.

use std::path::PathBuf;

/// Errors of the preprocessing stage.
#[derive(Debug, thiserror::Error)]
pub enum PrepError {
    /// No ONNX Runtime shared library was found.
    #[error(
        "no ONNX Runtime library found (tried: {tried}); pass --ort-lib PATH to \
         libonnxruntime.so, set ORT_DYLIB_PATH, or `pip install onnxruntime==1.32.0`"
    )]
    RuntimeNotFound {
        /// What was tried, in order.
        tried: String,
    },
    /// The ONNX Runtime library exists but cannot be loaded (wrong file, too old).
    #[error("cannot load the ONNX Runtime library {path}: {message}")]
    RuntimeLoad {
        /// The library file.
        path: PathBuf,
        /// The loader's message.
        message: String,
    },
    /// ONNX Runtime refused a model file or failed running it.
    #[error("{model}: {action}: {message}")]
    Onnx {
        /// The model file.
        model: PathBuf,
        /// What was being done.
        action: &'static str,
        /// ONNX Runtime's message.
        message: String,
    },
    /// A model's inputs or outputs are not what this stage drives.
    #[error("{model}: {message}")]
    ModelInterface {
        /// The model file.
        model: PathBuf,
        /// Which name or shape is wrong, and what was expected.
        message: String,
    },
    /// An image could not be read or decoded.
    #[error("cannot read image {path}: {message}")]
    Image {
        /// The image file.
        path: PathBuf,
        /// The decoder's message.
        message: String,
    },
    /// Inputs that do not fit together (sizes, counts, options).
    #[error("{what}: {message}")]
    Input {
        /// The input or option.
        what: String,
        /// The expectation that failed.
        message: String,
    },
    /// A file of the formats crate could not be read or written.
    #[error(transparent)]
    Format(#[from] profuse_formats::FormatError),
}

/// Result of this crate.
pub type Result<T, E = PrepError> = std::result::Result<T, E>;

/// An input error.
pub(crate) fn input(what: impl Into<String>, message: impl Into<String>) -> PrepError {
    PrepError::Input {
        what: what.into(),
        message: message.into(),
    }
}

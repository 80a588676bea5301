//! Errors of the refinement.

use profuse_formats::FormatError;
use splat_raster::RasterError;

/// Everything that can go wrong in a refinement.
#[derive(Debug, thiserror::Error)]
pub enum RefineError {
    /// A file could not be read, failed validation, or could not be written.
    #[error(transparent)]
    Format(#[from] FormatError),
    /// The Gaussians or a camera failed the rasterizer's checks.
    #[error(transparent)]
    Raster(#[from] RasterError),
    /// A Gaussians tensor has the wrong length.
    #[error("gaussians: `{field}` has {got} entries, expected {expected}")]
    Inconsistent {
        /// The tensor.
        field: &'static str,
        /// Its length.
        got: usize,
        /// The length the means imply.
        expected: usize,
    },
    /// The image of a view could not be read.
    #[error("{path}: cannot read the image of view {view}: {reason}")]
    Image {
        /// The image file.
        path: String,
        /// The view.
        view: usize,
        /// What failed.
        reason: String,
    },
    /// An image's size is not the camera's.
    #[error(
        "{path}: image is {got:?} pixels but the cameras file says {expected:?} for view {view}"
    )]
    ImageSize {
        /// The image file.
        path: String,
        /// The view.
        view: usize,
        /// Its size.
        got: [u32; 2],
        /// The camera's size.
        expected: [u32; 2],
    },
    /// A configuration value is out of range.
    #[error("invalid setting `{name}` = {value}: {expected}")]
    Config {
        /// The setting.
        name: &'static str,
        /// Its value.
        value: String,
        /// What it must be.
        expected: &'static str,
    },
    /// The folder of the output file cannot be created.
    #[error("{path}: cannot create the output folder")]
    OutputFolder {
        /// The folder.
        path: String,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// No view is left to train on.
    #[error("no training view: {reason}")]
    NoViews {
        /// Why.
        reason: String,
    },
}

/// Result with [`RefineError`].
pub type Result<T, E = RefineError> = std::result::Result<T, E>;

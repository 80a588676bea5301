//! The error type of the crate: every variant says which input (masks, matches, cameras,
//! Gaussians, parameters) is wrong, where, and what was expected.

use splat_raster::RasterError;

/// Result alias of this crate.
pub type Result<T, E = WarpGraphError> = std::result::Result<T, E>;

/// Why proposals could not be built. Inputs are checked before any work is done, so an
/// error never leaves partial output behind.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum WarpGraphError {
    /// The masks and matches describe different numbers of views.
    #[error(
        "masks have {masks} views (metadata `view_names`) but matches metadata `num_views` is {matches}; both must describe the same cameras"
    )]
    ViewCountMismatch {
        /// Views of the masks.
        masks: usize,
        /// `num_views` of the matches.
        matches: usize,
    },
    /// The cameras describe a different number of views than the masks.
    #[error("cameras have {cameras} views (metadata `image_names`) but masks have {masks}")]
    CameraCountMismatch {
        /// Views of the cameras.
        cameras: usize,
        /// Views of the masks.
        masks: usize,
    },
    /// A matches pair names a view that does not exist.
    #[error(
        "matches tensor `pairs` row {row} names view {view}, expected a view index < {views} (the masks' view count)"
    )]
    PairOutOfRange {
        /// Row of `pairs`.
        row: usize,
        /// The offending view id.
        view: u32,
        /// Number of views.
        views: usize,
    },
    /// A matches pair is (v, v) or repeats an earlier ordered pair.
    #[error("matches tensor `pairs` row {row} ({i}, {j}): {reason}")]
    BadPair {
        /// Row of `pairs`.
        row: usize,
        /// Source view.
        i: u32,
        /// Target view.
        j: u32,
        /// What is wrong.
        reason: &'static str,
    },
    /// A tensor's length disagrees with the shapes declared by its file.
    #[error("{input} tensor `{tensor}` has {found} values, expected {expected}")]
    Shape {
        /// `masks`, `matches` or `cameras`.
        input: &'static str,
        /// The tensor.
        tensor: &'static str,
        /// Values found.
        found: usize,
        /// What was expected.
        expected: String,
    },
    /// A label of a view is neither one of that view's masks nor "no mask".
    #[error(
        "masks tensor `labels`: view {view} pixel {pixel} has label {label}, expected a view-local mask index < {count} or the reserved no-mask value"
    )]
    LabelOutOfRange {
        /// View.
        view: usize,
        /// Flat pixel index inside the view.
        pixel: usize,
        /// The label.
        label: u32,
        /// Masks of the view.
        count: usize,
    },
    /// `mask_offsets` decreases or does not start at 0.
    #[error("masks tensor `mask_offsets` element {index} is {value}, expected a non-decreasing sequence starting at 0")]
    BadOffsets {
        /// Element index.
        index: usize,
        /// Its value.
        value: u32,
    },
    /// A camera cannot be used (empty image).
    #[error("cameras view {view}: {reason}")]
    BadCamera {
        /// The view.
        view: usize,
        /// What is wrong.
        reason: String,
    },
    /// Cameras are needed but were not given.
    #[error("{what} needs a cameras file (--cameras)")]
    MissingCameras {
        /// What needs them.
        what: &'static str,
    },
    /// Gaussians are needed but were not given.
    #[error("{what} needs a gaussians file (--gaussians) and a cameras file (--cameras)")]
    MissingGaussians {
        /// What needs them.
        what: &'static str,
    },
    /// A parameter is outside its domain.
    #[error("parameter `{name}` is {value}, expected {expected}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// Its value.
        value: String,
        /// The allowed domain.
        expected: &'static str,
    },
    /// The rasterizer rejected the Gaussians or a camera while rendering depth.
    #[error("{context}")]
    Raster {
        /// What was being rendered.
        context: String,
        /// The rasterizer's error.
        #[source]
        source: RasterError,
    },
    /// Writing the proposals failed their own validation (a bug, reported rather than hidden).
    #[error("the proposals failed validation")]
    Format(#[from] profuse_formats::FormatError),
}

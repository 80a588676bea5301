//! The one error type of the crate.

use profuse_formats::FormatError;
use splat_raster::RasterError;

/// Why a registration, a partial-sums file or a merge failed. Every variant names the
/// file (or the input's label, see [`crate::Names`]) and what was expected.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FuseError {
    /// The semantic index's `min_share` is not a share in [0, 1].
    #[error("fuse min_share = {0}: expected a share in [0, 1]")]
    MinShare(f64),
    /// The exponent of the members' pixel weights is negative or not finite.
    #[error("fuse pixel_share_power = {0}: expected a finite number >= 0")]
    PixelSharePower(f64),
    /// A file could not be read or written, or breaks a rule of its kind (SPEC.md), or a
    /// partial-sums file breaks a rule of its layout (see [`crate::PartialSums`]).
    #[error(transparent)]
    Format(#[from] FormatError),
    /// The rasterizer rejected the Gaussians (non-finite parameters, zero rotations, ...).
    #[error("{gaussians}: {source}")]
    Gaussians {
        /// The Gaussians' file or label.
        gaussians: String,
        #[source]
        source: RasterError,
    },
    /// A view could not be rendered (unusable camera, K out of range, image too large).
    #[error("{cameras}: {source}")]
    Render {
        /// The cameras' file or label.
        cameras: String,
        #[source]
        source: RasterError,
    },
    /// The masks do not belong to the cameras (view count or view names differ).
    #[error("{masks} does not match {cameras}: {detail}")]
    ViewMismatch {
        /// The masks' file or label.
        masks: String,
        /// The cameras' file or label.
        cameras: String,
        /// What differs.
        detail: String,
    },
    /// The masks' tensors disagree with each other (only possible for masks built in
    /// memory: reading a masks file rejects them).
    #[error("{masks}: {detail}")]
    BadMasks {
        /// The masks' file or label.
        masks: String,
        /// What is wrong.
        detail: String,
    },
    /// The mask-to-group mapping does not fit the masks (only possible for groupings built
    /// in memory: [`crate::Groups::from_proposals`] checks the proposals file).
    #[error("grouping for {masks}: {detail}")]
    BadGrouping {
        /// The masks' file or label.
        masks: String,
        /// What is wrong.
        detail: String,
    },
    /// The requested view range is empty or beyond the views.
    #[error("view range {start}..{end} is not a non-empty range inside 0..{views}")]
    ViewRange {
        /// First view.
        start: usize,
        /// One past the last view.
        end: usize,
        /// Number of views.
        views: usize,
    },
    /// Partial sums to merge were computed for different inputs or parameters.
    #[error("{path}: `{field}` is {found}, but the first partial file has {expected}")]
    PartialMismatch {
        /// The partial file that differs.
        path: String,
        /// The metadata key or tensor that differs.
        field: &'static str,
        /// The first file's value.
        expected: String,
        /// This file's value.
        found: String,
    },
    /// Partial sums given to finish a job were computed for other inputs or parameters
    /// than the job's own (e.g. a shard left over from before the proposals changed).
    #[error("partial sums {shards}: `{field}` is {found}, but this job's inputs and parameters give {expected}")]
    ShardOfOtherInputs {
        /// The partial files.
        shards: String,
        /// The metadata key or tensor that differs.
        field: &'static str,
        /// The job's value.
        expected: String,
        /// The shards' value.
        found: String,
    },
    /// Two partial files both contain a view, so merging them would count it twice.
    #[error("view {view} is in both {first} and {second}")]
    ViewOverlap {
        /// The view.
        view: u32,
        /// The first file that contains it.
        first: String,
        /// The second file that contains it.
        second: String,
    },
    /// The merged partial sums do not cover every view.
    #[error("the partial files do not cover views {missing} (of 0..{views})")]
    MissingViews {
        /// The uncovered views, as ranges.
        missing: String,
        /// Number of views.
        views: usize,
    },
    /// `merge` was given no partial sums.
    #[error("nothing to merge: no partial files")]
    NothingToMerge,
    /// More (Gaussian, proposal) pairs than a u32 index can address.
    #[error("more than {max} nonzero (Gaussian, proposal) pairs")]
    TooManyPairs {
        /// The limit.
        max: usize,
    },
}

/// Result alias of this crate.
pub type Result<T, E = FuseError> = std::result::Result<T, E>;

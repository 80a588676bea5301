//! Typed errors of the rasterizer.

/// Everything that can go wrong when preparing or rendering Gaussians.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RasterError {
    /// The requested view does not exist in the cameras.
    #[error("view {view} is out of range: the cameras have {views} views")]
    ViewOutOfRange {
        /// The requested view.
        view: usize,
        /// Number of views in the cameras.
        views: usize,
    },
    /// `top_k: Some(0)` was asked for (use `None` to disable the top-K output).
    #[error("top-K must be at least 1 (use `top_k: None` to switch the top-K output off)")]
    TopKZero,
    /// `top_k` above [`crate::MAX_TOP_K`].
    #[error("top-K {k} is larger than the maximum {max}")]
    TopKTooLarge {
        /// The requested K.
        k: usize,
        /// The largest supported K.
        max: usize,
    },
    /// The image is larger than the rasterizer supports.
    #[error(
        "image {width}x{height} is too large (at most {max_side} pixels per side and {max_pixels} pixels)"
    )]
    ImageTooLarge {
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
        /// Largest width or height.
        max_side: u32,
        /// Largest pixel count.
        max_pixels: u64,
    },
    /// A Gaussian parameter is NaN or infinite (opacity logits may be ±inf, not NaN).
    #[error("Gaussian {index}: `{field}` is not finite ({value})")]
    NonFiniteGaussian {
        /// The Gaussian's index.
        index: usize,
        /// The tensor (`means`, `log_scales`, `rotations`, `opacity_logits`, `sh_dc`, `sh_rest`).
        field: &'static str,
        /// The offending value, printed.
        value: String,
    },
    /// A Gaussian's rotation quaternion is all zero and cannot be normalised.
    #[error("Gaussian {index}: `rotations` is the zero quaternion")]
    ZeroRotation {
        /// The Gaussian's index.
        index: usize,
    },
    /// The tensors of a Gaussian set disagree in length.
    #[error("Gaussians: `{field}` has {got} values, expected {expected}")]
    InconsistentGaussians {
        /// The tensor.
        field: &'static str,
        /// Its number of values.
        got: usize,
        /// The number implied by `means` (and `sh_degree` for `sh_rest`).
        expected: usize,
    },
    /// A camera cannot be used (missing rows, non-finite or non-positive intrinsics, ...).
    #[error("this CPU cannot run the {simd} SIMD blend")]
    SimdUnsupported {
        /// The SIMD width asked for.
        simd: &'static str,
    },
    #[error("camera of view {view}: {reason}")]
    BadCamera {
        /// The view.
        view: usize,
        /// What is wrong.
        reason: String,
    },
}

/// Result alias of this crate.
pub type Result<T, E = RasterError> = std::result::Result<T, E>;

//! Photometric refinement of 3D Gaussians on the CPU (issue 18): a short 3DGS optimisation
//! of the correspondence-initialised Gaussians. EDGS argues that a dense initialisation
//! makes densification unnecessary, and it is off by default; but where no
//! correspondences were found (plain walls, fur) the fixed set underfits even the training
//! views, so 3DGS's clone/split densification ([`densify`]) and a raise of the SH degree
//! ([`Params::raise_sh_degree`]) are available.
//!
//! # Design
//!
//! * **Forward = splat-raster's.** [`raster::forward`] renders colour with exactly
//!   `splat_raster`'s semantics: the projection ([`project`]) repeats its `f64` operations
//!   (near cull z <= 0.2, Σ = R S Sᵀ Rᵀ, the Jacobian with the 1.3 × half-FOV clamp about
//!   the tangent range's middle, +0.3 low-pass, 3-sigma tiles, SH degrees 0..3 with
//!   `max(0, · + 0.5)`), and the per-pixel blend its single-precision operations in the same
//!   order (power, `splat_raster::math::exp`, α = min(0.99, o·G), skip power > 0 or
//!   α < 1/255, stop before a Gaussian taking T below 1e-4, background × T_final). The
//!   integration tests check the image against `Rasterizer::render_view`. It is a separate
//!   implementation rather than a call into splat-raster because the backward pass needs
//!   what splat-raster does not keep: per pixel the final T and how far down its tile's
//!   list it blended, and the tile lists themselves.
//! * **Backward.** Per pixel, back to front over its tile's list up to its last
//!   contributor (INRIA's `renderCUDA` backward: T recovered by division by 1 − α, the
//!   colour behind each contributor accumulated), into one gradient slot per (tile, Gaussian)
//!   list entry; the α clamp at 0.99 passes no gradient, nor does the colour clamp at 0.
//!   Then each Gaussian's slots are summed in list order, and [`project::backward`] pulls
//!   the screen gradient (centre, conic, opacity, colour) back through the conic inverse,
//!   T Σ Tᵀ, the Jacobian (clamped tangents pass gradient to z only), R S Sᵀ Rᵀ, the
//!   quaternion normalisation, the sigmoid and the SH basis (including its dependence on the
//!   view direction) in `f64`.
//! * **Determinism.** Tile rows run in parallel but own their slots; the reduction is
//!   sequential in a fixed order; the loss is a fixed-order sum. Same seed, same bytes,
//!   whatever the thread count (tested).
//! * **Loss and optimiser.** [`loss`]: 0.8 L1 + 0.2 (1 − SSIM), 11 × 11 Gaussian window,
//!   σ = 1.5, zero padding. [`train`]: one view per iteration from a seeded shuffle per
//!   epoch, Adam (β 0.9/0.999, ε 1e-15) with the 3DGS learning rates, position rate ×
//!   scene extent decaying exponentially over the run; optional opacity pruning.
//! * **Densification** ([`densify`]): 3DGS's rule on the mean NDC norm of each Gaussian's
//!   screen-centre gradient over the views that drew it; small Gaussians cloned, large ones
//!   split in two samples of their own distribution (seeded, drawn in index order, so the
//!   bytes stay independent of the thread count), new Gaussians with fresh Adam moments.

pub mod densify;
pub mod error;
pub mod images;
pub mod job;
pub mod loss;
pub mod params;
pub mod project;
pub mod raster;
pub mod train;
pub mod views;

pub use densify::DensifyConfig;
pub use error::{RefineError, Result};
pub use params::{Grads, Params};
pub use raster::{backward, forward, ViewState};
pub use train::{Config, LearningRates, StepStats, Trainer};

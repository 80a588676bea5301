//! Training-free registration of language descriptors onto 3D Gaussians (ProFuse paper
//! §3.3): every Gaussian gets the visibility-weighted average of the descriptors of the 3D
//! Context Proposals whose pixels it is rendered into, from the rasterizer's per-pixel
//! top-K weights ω = T·α alone — no gradient, no render supervision.
//!
//! # What it computes
//!
//! For view i, pixel p and its top-K hits (g, ω) (from `splat-raster`):
//!
//! * mask mass μ(M) = Σ_{p ∈ M} Σ_t ω (eq. mask-mass);
//! * proposal descriptor f̄_P = normalise(Σ_{M ∈ P} μ(M) f_M) over the member masks of
//!   every view (eq. proposal-desc) — or, with [`Grouping::Blend`], per mask a blend of
//!   f̄_P with the mask's own feature (below);
//! * A\[g\] += ω f̄_{L(p)}, S\[g\] += ω for every pixel whose mask has a proposal and every
//!   top-K hit (eq. accumulate); f_g = normalise(A / max(S, ε)) (eq. gaussian-feature);
//!   a Gaussian with S = 0 is invalid (zero row, `valid` 0).
//!
//! # Design decisions
//!
//! * **One pass, D-dimensional work per pair, not per hit.** Grouping the hits of
//!   eq. accumulate by proposal, A\[g\] = Σ_P W\[g, P\] f̄_P with W\[g, P\] = Σ ω over the hits of
//!   g in P's pixels. W does not depend on the descriptors, so the mask masses and W come
//!   from the *same* rendering pass over the views; the descriptors are formed after the
//!   pass, and A is one sparse-dense product W F. The per-hit work is one scalar add into
//!   a sparse Gaussian x proposal matrix (a handful of proposals per Gaussian); the
//!   D-dimensional work is per nonzero (Gaussian, proposal) pair. Dr. Splat's dense
//!   [Gaussians x masks] matrix is what this avoids.
//! * **Exact sums.** Weights are added as integers in units of 2^-62 ([`WEIGHT_SCALE`]);
//!   every weight the rasterizer produces (>= 1/255 · 1e-4) converts exactly, so W and μ are
//!   the exact sums of the rendered f32 weights whatever the order of views, pixels or
//!   threads. That is what makes view sharding free: partial sums of any view split, added
//!   in any order ([`merge`]), give the same integers as one pass, and [`finish`] the same
//!   bytes. After the pass everything is f64, each row summed in ascending proposal order.
//! * **Streaming, memory independent of the number of views.** Views are rendered one at
//!   a time, tile by tile ([`splat_raster::Rasterizer::render_tiles`]): each 16x16 tile's
//!   top-K lists are summed as soon as they are rendered, while they are in cache, so no
//!   image-sized list buffer exists. The accumulator holds 4 bytes per Gaussian, 24 per
//!   nonzero (Gaussian, proposal) pair and 16 per mask, plus one view's scratch (its
//!   tiles' records); nothing per view or per pixel accumulates.
//! * **Cache-friendly scatter.** Gaussian ids are arbitrary with respect to the screen, so
//!   adding hits straight into W would miss the cache on nearly every Gaussian's first touch
//!   in a view. Instead each 16x16 tile first sums its hits per (Gaussian, proposal) in a
//!   small table (neighbouring pixels share most of their top-K), the tile records are
//!   counting-sorted by block of 4096 Gaussians, and each block of W adds its records while
//!   its entries sit in cache. Tiles and blocks run in parallel; no locks.
//! * **Mask grid.** Views are rendered at the masks' grid (SPEC.md §4.3): when it differs
//!   from the image size the intrinsics are scaled by (W / image_w, H / image_h), so grid
//!   pixel (x, y) samples the ray through the centre of the image region it covers.
//!   Weights are then per grid cell; when all views share an image size that is a uniform
//!   factor that cancels in every normalisation.
//! * **Orphan masks** (no proposal, e.g. filtered by `s_min` / `v_min`) register nothing
//!   by default, as in the paper; [`Orphans::Singleton`] makes each its own proposal.
//! * **Baseline.** [`Groups::per_mask`] registers every mask's own feature (Dr. Splat
//!   style, no proposals, no mass weighting), so the paper's claim can be measured.
//! * **Blend (a switchable deviation from the paper, [`Groups::blend`]).** The paper gives
//!   every pixel of a proposal f̄_P, so when a proposal wrongly joins two objects the
//!   minority object's pixels get the majority's descriptor with no way back. The blend
//!   registers per mask d_m = normalise(α_m f̄_P + (1 − α_m) f̂_m), with
//!   a_m = cos(f_m, f̄_P), c_P = Σ_{k∈P} μ_k a_k / Σ_{k∈P} μ_k and
//!   α_m = clamp(a_m / c_P, 0, 1): a mask as coherent with its proposal as the average
//!   member keeps f̄_P, one with half the typical agreement gets an even mix, one
//!   orthogonal to it keeps its own feature. The ratio makes it scale-free (in CLIP's
//!   anisotropic space, where every cosine is ~0.8, α ≈ 1 everywhere). d_m is per mask,
//!   so W's groups are the masks (the baseline's W size and cost); masks with α = 1 share
//!   their proposal's descriptor row, so where every mask is that coherent the result has
//!   the paper's bytes. The masses (hence d_m) are final only after the last view, so the
//!   blend is formed in [`finish`], and partial files keep the masks' proposals.
//! * **Member pixels weighed by their share (a deviation from the paper,
//!   [`Groups::with_pixel_shares`], default exponent [`DEFAULT_PIXEL_SHARE_POWER`]).** A
//!   member mask that runs onto a neighbouring object would register its proposal's pooled
//!   descriptor there, which answers its class far more sharply than the neighbour's own
//!   evidence and so wins every contact. Each hit of member m adds ω · s_m^e instead of ω,
//!   s_m the proposals' `mask_share`: a mask the other views find partly off its object
//!   counts less wherever others also see the Gaussian (alone, its weight cancels in
//!   A / S). The factor is an integer in units of 2^-16 and each fixed-point hit is
//!   floored after the product, so sums stay exact and order-free.
//! * **Views without masks** are not rendered (they cannot contribute).
//!
//! # Example
//!
//! ```
//! use profuse_formats::{Cameras, FileKind, Gaussians, Masks};
//! use profuse_fuse::{
//!     accumulate, finish, fuse, merge, FuseOptions, Groups, MemberWeight, Orphans, Scene,
//! };
//!
//! // A tiny synthetic scene with ground-truth Gaussians; proposals from its ground truth
//! // (in the pipeline they come from warp-graph).
//! let dir = tempfile::tempdir()?;
//! let mut config = synth::Config::preset(synth::Preset::Tiny, 1);
//! config.gaussians = 2000;
//! synth::generate(&config, dir.path())?;
//! let gaussians = Gaussians::read(dir.path().join("gt/gaussians.safetensors"))?;
//! let cameras = Cameras::read(dir.path().join("cameras.safetensors"))?;
//! let masks = Masks::read(dir.path().join("masks.safetensors"))?;
//! let proposals = profuse_fuse::testing::proposals_from_mask_objects(
//!     dir.path().join("gt/mask_objects.json"), &masks, 1)?;
//! let groups =
//!     Groups::from_proposals(&masks, &proposals, Orphans::Ignore, MemberWeight::Share, "proposals")?;
//!
//! let scene = Scene::new(&gaussians, &cameras, &masks);
//! let registration = fuse(&scene, &groups, &FuseOptions::default())?;
//! assert!(registration.summary.valid > 1000);
//! assert_eq!(registration.features.len(), gaussians.len());
//!
//! // Two view shards, merged: the same bytes as the single pass.
//! let a = accumulate(&scene, &groups, 10, 0..2, &mut |_| {})?;
//! let b = accumulate(&scene, &groups, 10, 2..4, &mut |_| {})?;
//! let merged = merge(&[b, a], &[])?;
//! let precision = profuse_fuse::Precision::of(&masks.features);
//! assert_eq!(finish(&merged, precision).features, registration.features);
//! # Ok::<(), Box<dyn std::error::Error + Send + Sync>>(())
//! ```

mod accumulate;
mod error;
mod finish;
mod groups;
pub mod job;
mod partial;
mod semantic;
#[doc(hidden)]
pub mod testing;

use profuse_formats::{Cameras, Gaussians, Masks};
use splat_raster::{RenderStats, ViewCamera};

pub use accumulate::{accumulate, dequantise, quantise, HitCounts, WeightMatrix, WEIGHT_SCALE};
pub use error::{FuseError, Result};
pub use finish::{
    finish, group_descriptors, registered_mask_descriptors, Precision, Registration, Summary, EPS,
};
pub use groups::{Grouping, Groups, MemberWeight, Orphans, NO_GROUP, PIXEL_WEIGHT_ONE};
pub use partial::{merge, PartialSums, Timings, PARTIAL_FORMAT, PARTIAL_VERSION};
pub use semantic::{semantic_index, DEFAULT_MIN_SHARE};

/// Top-K of the paper (K = 10 saturates with proposals, Table topk_miou).
pub const DEFAULT_K: usize = 10;

/// Default exponent e of the members' pixel weights s_m^e in W ([`Groups::with_pixel_shares`];
/// 0 is the paper). Measured over unseen seeds in crates/fuse/README.md ("Member pixels
/// weighed by their share"): on `default` seeds 16-31 the ScanNet mIoU19 gap to the
/// per-mask baseline went -1.05 (e = 0), -0.66 (1), -0.39 (2), +0.02 (4) in the
/// exploratory build (f64 factors; the committed integer factors give +0.03), and on the
/// seeds 32-47 measured afterwards -0.23 (0) and +0.30 (4).
pub const DEFAULT_PIXEL_SHARE_POWER: f64 = 4.0;

/// How the inputs are named in errors (file paths in the tools).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Names {
    /// The Gaussians.
    pub gaussians: String,
    /// The cameras.
    pub cameras: String,
    /// The masks.
    pub masks: String,
}

impl Default for Names {
    fn default() -> Self {
        Names {
            gaussians: "gaussians".into(),
            cameras: "cameras".into(),
            masks: "masks".into(),
        }
    }
}

/// The inputs of a registration: Gaussians, the cameras of the views and the masks of
/// the same views (view v of the masks is view v of the cameras).
#[derive(Debug, Clone)]
pub struct Scene<'a> {
    /// The Gaussians to register descriptors onto.
    pub gaussians: &'a Gaussians,
    /// The posed views.
    pub cameras: &'a Cameras,
    /// Per-view masks and their features.
    pub masks: &'a Masks,
    /// Labels for errors.
    pub names: Names,
}

impl<'a> Scene<'a> {
    /// A scene with the default names.
    pub fn new(gaussians: &'a Gaussians, cameras: &'a Cameras, masks: &'a Masks) -> Self {
        Scene {
            gaussians,
            cameras,
            masks,
            names: Names::default(),
        }
    }

    /// The same scene with other names in errors.
    pub fn named(self, names: Names) -> Self {
        Scene { names, ..self }
    }

    /// The masks belong to the cameras (same number and names of views) and their
    /// tensors agree in size.
    pub fn check(&self) -> Result<()> {
        let (m, c) = (self.masks, self.cameras);
        let mismatch = |detail: String| FuseError::ViewMismatch {
            masks: self.names.masks.clone(),
            cameras: self.names.cameras.clone(),
            detail,
        };
        if m.num_views() != c.len() {
            return Err(mismatch(format!(
                "{} views in the masks, {} in the cameras",
                m.num_views(),
                c.len()
            )));
        }
        if let Some(v) = (0..c.len()).find(|v| m.view_names[*v] != c.image_names[*v]) {
            return Err(mismatch(format!(
                "view {v} is {:?} in the masks but {:?} in the cameras",
                m.view_names[v], c.image_names[v]
            )));
        }
        let bad = |detail: String| FuseError::BadMasks {
            masks: self.names.masks.clone(),
            detail,
        };
        let v = m.num_views();
        if m.labels.len() != v * m.width * m.height || m.mask_offsets.len() != v + 1 {
            return Err(bad(format!(
                "labels hold {} values and mask_offsets {}, expected {} (V x H x W) and {}",
                m.labels.len(),
                m.mask_offsets.len(),
                v * m.width * m.height,
                v + 1
            )));
        }
        if m.dim == 0
            || m.features.len() != m.num_masks() * m.dim
            || m.mask_offsets.windows(2).any(|w| w[1] < w[0])
        {
            return Err(bad(format!(
                "features hold {} values for {} masks of dimension {}, or mask_offsets decrease",
                m.features.len(),
                m.num_masks(),
                m.dim
            )));
        }
        if u32::try_from(m.width).is_err() || u32::try_from(m.height).is_err() {
            return Err(bad(format!(
                "mask grid {}x{} is too large",
                m.width, m.height
            )));
        }
        Ok(())
    }
}

/// Options of [`fuse`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FuseOptions {
    /// Top-K contributors per pixel (1..=256).
    pub k: usize,
    /// Storage precision of the descriptors; `None` = that of the mask features.
    pub precision: Option<Precision>,
}

impl Default for FuseOptions {
    fn default() -> Self {
        FuseOptions {
            k: DEFAULT_K,
            precision: None,
        }
    }
}

/// What one view contributed, reported after it was accumulated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewReport {
    /// The view.
    pub view: usize,
    /// Whether it was rendered (views without any mask pixel are skipped).
    pub rendered: bool,
    /// Seconds spent rendering its top-K.
    pub raster_s: f64,
    /// Seconds spent scattering its hits.
    pub accumulate_s: f64,
    /// Its grouped pixels and their hits.
    pub counts: HitCounts,
    /// Nonzero W entries after this view.
    pub nnz: usize,
    /// Bytes held by the accumulator after this view.
    pub accumulator_bytes: usize,
    /// Bytes of the per-view buffers (top-K outputs and the accumulator's scratch), which
    /// are reused from view to view.
    pub view_buffer_bytes: usize,
    /// The rasterizer's counters (visible Gaussians, tile pairs) of this view.
    pub render: RenderStats,
}

/// Registers descriptors from every view in one pass: [`accumulate`] over all views, then
/// [`finish`].
pub fn fuse(scene: &Scene<'_>, groups: &Groups, opts: &FuseOptions) -> Result<Registration> {
    let partial = accumulate(scene, groups, opts.k, 0..scene.cameras.len(), &mut |_| {})?;
    let precision = opts
        .precision
        .unwrap_or_else(|| Precision::of(&scene.masks.features));
    Ok(finish(&partial, precision))
}

/// The camera of `view` rendered at a `width` x `height` grid over its image: intrinsics
/// scaled by (width / image_w, height / image_h), so grid pixel (x, y) is the ray through
/// the centre of the image region it covers (unchanged when the sizes agree).
pub fn grid_camera(
    cameras: &Cameras,
    view: usize,
    width: u32,
    height: u32,
) -> splat_raster::Result<ViewCamera> {
    Ok(ViewCamera::from_cameras(cameras, view)?.at_grid(width, height))
}

/// That the groups cover the scene's masks ([`Groups::check`]), as a typed error naming
/// the masks file.
fn check_groups(scene: &Scene<'_>, groups: &Groups) -> Result<()> {
    groups
        .check(scene.masks.num_masks())
        .map_err(|detail| FuseError::BadGrouping {
            masks: scene.names.masks.clone(),
            detail,
        })
}

/// The pooled descriptor of one set of masks, as eq. proposal-desc forms a proposal's:
/// normalise(Σ_{m ∈ members} μ(m) f_m), with the masses μ from the same top-K rendering
/// as [`accumulate`] (the same routine: the members are one group, every other mask none,
/// and [`group_descriptors`] pools them), so the result equals the proposal's row of a
/// full registration. Only the views that hold a member are rendered, one at a time.
/// With `shares` (a proposals file's `mask_share`, one per mask) each μ(m) is weighed by
/// its share, as [`MemberWeight::Share`] registers. `None` when the pool is zero (no
/// member is hit by any Gaussian, or `members` is empty). A member id `>= M`, or shares
/// not one per mask, is a [`FuseError::BadGrouping`].
pub fn pooled_descriptor(
    scene: &Scene<'_>,
    members: &[u32],
    shares: Option<&[f32]>,
    k: usize,
) -> Result<Option<Vec<f32>>> {
    let masks = scene.masks;
    let num_masks = masks.num_masks();
    let mut mask_group = vec![NO_GROUP; num_masks];
    for &m in members {
        let slot = mask_group
            .get_mut(m as usize)
            .ok_or_else(|| FuseError::BadGrouping {
                masks: scene.names.masks.clone(),
                detail: format!("member mask {m} of {num_masks}"),
            })?;
        *slot = 0;
    }
    let groups = Groups {
        grouping: Grouping::Proposals {
            orphans: Orphans::Ignore,
        },
        mask_group,
        num_groups: 1,
        mask_proposal: Vec::new(),
        mask_share: shares.map(<[f32]>::to_vec).unwrap_or_default(),
        pixel_weight: Vec::new(),
        pixel_share_power: 0.0,
    };
    // The check every registration runs (shares one per mask), here also when no view is
    // rendered (no members).
    check_groups(scene, &groups)?;
    scene.check()?;
    let mut views: Vec<usize> = members.iter().map(|&m| masks.view_of(m as usize)).collect();
    views.sort_unstable();
    views.dedup();
    let parts = views
        .iter()
        .map(|&v| accumulate(scene, &groups, k, v..v + 1, &mut |_| {}))
        .collect::<Result<Vec<_>>>()?;
    if parts.is_empty() {
        return Ok(None);
    }
    let pooled = group_descriptors(&merge(&parts, &[])?);
    Ok(pooled
        .iter()
        .any(|x| *x != 0.0)
        .then(|| pooled.iter().map(|x| *x as f32).collect()))
}

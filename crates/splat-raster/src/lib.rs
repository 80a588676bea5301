//! CPU tile rasterizer for 3D Gaussians (the 3DGS forward pass) with per-pixel top-K
//! contributors, as used by ProFuse's feature registration (paper §3.3, eq. ray-weights:
//! ω = T·α, T = Π_{s<t}(1 − α_s)).
//!
//! # What it computes
//!
//! The INRIA `diff-gaussian-rasterization` forward pass, on the CPU:
//!
//! * **Per Gaussian** ([`Rasterizer::project`]): mean to camera; culled when z <= 0.2;
//!   Σ = R S Sᵀ Rᵀ from the normalised quaternion and exp(log-scales); EWA projection
//!   Σ' = J W Σ Wᵀ Jᵀ with the perspective Jacobian J evaluated at the mean with x/z, y/z
//!   clamped to 1.3 × the half field of view; + 0.3 on the diagonal (low-pass); culled when
//!   det Σ' <= 0; radius r = ceil(3 sqrt(λ_max)) with INRIA's `max(0.1, mid² − det)`;
//!   colour from SH degrees 0..3 (INRIA constants, direction from the camera centre to the
//!   mean, `max(0, · + 0.5)`); depth = camera z. The projection runs in `f64`; the
//!   per-pixel blend in `f32`, like INRIA's kernel. A view projects its Gaussians 8 at a
//!   time, lane by lane without branches (8 f64 lanes with AVX-512, 2 with SSE2): the same
//!   IEEE operations as the one-Gaussian formula, so the same bits.
//! * **Per pixel**, over the Gaussians of its tile in front-to-back order:
//!   power = −½(a dx² + c dy²) − b dx dy (skip if > 0); α = min(0.99, o·exp(power)); skip
//!   α < 1/255; if T(1 − α) < 1e-4 stop *before* this Gaussian (it is not recorded);
//!   ω = T·α; colour += ω c, depth += ω z; T ← T(1 − α). Outputs ([`RenderOptions`]):
//!   colour, depth (Σωz or Σωz/Σω), accumulated alpha 1 − T, final T, and the top-K.
//!
//! # Design decisions
//!
//! * **Pixel centres.** SPEC.md §3.3 puts pixel (px, py)'s centre at (px + 0.5, py + 0.5)
//!   with u = fx X/Z + cx. INRIA's kernel places centres at integers and its projection at
//!   u − 0.5 (its `ndc2Pix`), which is the same geometry for a centred principal point; here
//!   dx = u − (px + 0.5) directly, so a Gaussian whose mean projects onto a pixel centre
//!   peaks at that pixel for any cx, cy. The Jacobian's 1.3 × half-FOV clamp is taken about
//!   the middle of the image's tangent range, which is INRIA's ±1.3·tan(fov/2) when the
//!   principal point is centred.
//! * **Tile binning.** 16×16 tiles. A Gaussian belongs to every tile overlapped by its
//!   3-sigma square [u − r, u + r] × [v − r, v + r], where the tile of a coordinate x is
//!   floor(x / 16) (INRIA's `getRect` uses an exclusive bound that drops a tile the square
//!   only just reaches; we use the plain inclusive rule). As in INRIA, a Gaussian is tested at
//!   every pixel of its tiles, so a reference renderer must use the same tile-granular pixel
//!   set (the integration tests do). Without changing any result, work is skipped where
//!   α < 1/255 is certain: a Gaussian with opacity < 1/255 is dropped, it is binned only into
//!   the tiles of its α >= 1/255 footprint (the ellipse ½ dᵀΣ'⁻¹d <= ln(255·o), with a margin
//!   of 0.05 in the exponent), and in each pixel row only the span of that ellipse (solved
//!   per row, widened by 1/64 pixel) is visited.
//! * **Order and determinism.** Survivors are sorted once by (camera depth as `f32`,
//!   Gaussian id) and bucketed into tile rows, then into tiles, keeping that order, so every
//!   tile's list is front to back with ties broken by id. The projected splats themselves
//!   are never moved: they stay in *slot* order, the Morton order of the Gaussians' means
//!   (computed once in [`Rasterizer::new`]), so that a tile's splats lie in a few runs of
//!   memory whatever order the file has; only the ties of the depth sort look at ids. Tiles
//!   are independent and each is blended by one thread, with no floating-point reduction
//!   across threads: outputs are bit-identical for any thread count. Rayon runs the tile rows in parallel; a view's
//!   projection and sort are parallel too.
//! * **SIMD.** The per-pixel step runs on units of adjacent pixels of a tile, branch-free with
//!   lane masks, and with [`math::exp`], a polynomial `expf` accurate to ~2 ulp (the class
//!   of CUDA's `expf`) that vectorises. Two widths share one generic kernel: 4 lanes of
//!   `wide::f32x4` (SSE2 on x86-64, NEON on aarch64; no `unsafe`) everywhere, and 16 lanes
//!   (a 4 x 4 pixel block) with AVX-512 F + DQ, chosen at run time when the CPU has them (a
//!   small `unsafe` wrapper of the intrinsics, entered only after `is_x86_feature_detected`).
//!   Every lane performs the same IEEE operations as the scalar formula, so both widths
//!   give the same bytes as a scalar per-pixel loop ([`Simd`] and
//!   [`Rasterizer::set_simd`] exist to compare their speed; the tests render with both).
//! * **Blend loop.** A tile is cut into units of N pixels: 4 adjacent pixels of one row
//!   with 4 lanes, a 4 x 4 block with 16 (most splats of a dense scene cover a few pixels:
//!   a block wastes fewer lanes on them than a 16-pixel row, e.g. a 3 x 3 splat is one
//!   block entry instead of three mostly empty rows). A 4 x 4 unit selects the tile's
//!   depth-ordered splats whose rectangles reach it just before its walk (one integer bit
//!   test per 16 entries, the positions packed by a compress: no branch per entry and no
//!   per-unit list kept for the tile); with 4 lanes each splat is first appended to the
//!   lists of the units its ellipse's span reaches in each row. Each unit then walks its
//!   splats with its whole state (T, the sums, stopped lanes, the K-th weight) in
//!   registers and stops once all its pixels have, so
//!   nothing but T's few operations chains one splat to the next. The α of a batch of 8
//!   entries is computed before they are composited, so their exp chains overlap. Powers
//!   are clamped to [−40, 0] before exp, which changes no result: below −40 no α reaches
//!   1/255 (opacity <= 1), above 0 nothing is drawn, and without the floor o·e^power of a
//!   thin splat's far rectangle corners lands in the subnormal range, where every product
//!   costs a microcode assist on x86 (that alone made colour renders ~1.35× slower).
//! * **Exact top-K.** While a tile is blended each pixel's list lives in the worker's tile
//!   scratch, rank-major per lane group (rank r of all the group's pixels is one SIMD
//!   vector), so a new contributor is inserted into every lane that wants it with one pass
//!   of compares and blends over every rank, from the first down, with no branch on the
//!   data (stopping at the first rank no lane shifts into cost a mispredicted exit per
//!   insertion, which was more). The lists of an image render carry Gaussian ids (one
//!   lookup per insertion), so writing them out is a plain transposition.
//!   A SIMD compare against each pixel's K-th weight first skips most contributors. A
//!   newcomer goes after every entry with a weight >= its own and is dropped when the list
//!   is full and its weight is <= the K-th: the result is the K largest weights of the full
//!   contributor list, in descending order, ties in depth order (nearer first). Pixels with
//!   fewer hits are padded with id [`NO_GAUSSIAN`] and weight 0 (the scratch lists are not
//!   cleared between tiles: ranks past a group's longest list are read and written out as
//!   padding). A finished tile's lists
//!   are transposed into the view's output, K × 8 bytes per pixel (design.md: a true top-K,
//!   not the first K hits), or handed to a consumer by [`Rasterizer::render_tiles`]. A
//!   lists-only render (no colour, depth, alpha or T) stops a pixel as soon as T <= its
//!   K-th weight: no later ω = T·α < T can enter, so the lists are the same.
//! * **Streaming.** [`Rasterizer::new`] does the view-independent work once;
//!   [`Rasterizer::render_view_into`] and [`Rasterizer::for_each_view`] render one view at a
//!   time into one reused [`ViewRender`] (outputs, binning buffers and tile scratch), so
//!   consumers never hold more than one view's top-K buffers; [`Rasterizer::render_tiles`]
//!   holds no image-sized buffer at all (fuse sums each tile's lists while they are in
//!   cache).
//! * **Degenerate input.** Non-finite means, scales, rotations, SH or NaN opacity logits are
//!   a typed error naming the Gaussian ([`RasterError::NonFiniteGaussian`]); ±inf opacity
//!   logits are accepted (opacity 1 or 0). Scales that underflow give a point Gaussian kept
//!   invertible by the low-pass; a 2D covariance that overflows even `f64` is culled.
//!   Empty sets and views with everything behind the camera give T = 1 and no hits.
//!
//! # Example
//!
//! ```
//! use profuse_formats::Gaussians;
//! use splat_raster::{camera, Rasterizer, RenderOptions, NO_GAUSSIAN};
//!
//! // Two Gaussians on the optical axis: a red one in front of a green one.
//! let g = Gaussians {
//!     means: vec![[0.0, 0.0, 3.0], [0.0, 0.0, 5.0]].into(),
//!     log_scales: vec![[-1.0; 3]; 2].into(),
//!     rotations: vec![[1.0, 0.0, 0.0, 0.0]; 2].into(),
//!     opacity_logits: vec![0.0, 4.0].into(), // opacities 0.5 and ~0.98
//!     sh_dc: vec![[1.5, -1.8, -1.8], [-1.8, 1.5, -1.8]].into(),
//!     ..Default::default()
//! };
//! let pose = camera::look_at([0.0; 3], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]).unwrap();
//! let cams = camera::cameras_from_poses(&[pose], 33, 31, camera::pinhole_intrinsics(33, 31, 60.0));
//!
//! let raster = Rasterizer::new(&g)?;
//! let out = raster.render_view(&cams, 0, &RenderOptions::all(4))?;
//! // The centre pixel: the red Gaussian first (ω = 0.5), then the green one (ω ≈ 0.49).
//! let (ids, weights) = out.topk(16, 15).unwrap();
//! assert_eq!(&ids[..3], &[0, 1, NO_GAUSSIAN]);
//! assert!((weights[0] - 0.5).abs() < 1e-6 && weights[1] > 0.48 && weights[2] == 0.0);
//! let rgb = &out.color().unwrap()[(15 * 33 + 16) * 3..][..3];
//! assert!(rgb[0] > rgb[2] && rgb[1] > rgb[2]);
//! // Σ ω + T = 1.
//! let t = out.transmittance().unwrap()[15 * 33 + 16];
//! assert!((weights.iter().sum::<f32>() + t - 1.0).abs() < 1e-5);
//! # Ok::<(), splat_raster::RasterError>(())
//! ```

pub mod camera;
mod error;
pub mod math;
mod project;
mod raster;
pub mod sh;
mod simd;

pub use camera::ViewCamera;
pub use error::{RasterError, Result};
pub use project::{
    check_gaussians, covariance_3d, ewa_jacobian, footprint, screen_tiles, tangent_range,
    EwaJacobian, Footprint, Projected,
};
pub use raster::{
    BlendCounts, DepthMode, ListScratch, Phases, Rasterizer, RenderOptions, RenderStats, Simd,
    TileLists, ViewRender,
};
/// Re-exported so callers can size the thread pool (`rayon::ThreadPoolBuilder`) with the
/// rayon this crate renders on.
pub use rayon;

/// Tile side in pixels.
pub const TILE: usize = 16;
/// Largest supported K of the top-K output.
pub const MAX_TOP_K: usize = 256;
/// Id written into unused top-K slots (the `profuse.topk` padding id).
pub const NO_GAUSSIAN: u32 = profuse_formats::NO_GAUSSIAN;
/// Gaussians with camera z <= this are culled.
pub const NEAR_PLANE: f64 = 0.2;
/// Added to the diagonal of every 2D covariance (pixels²).
pub const LOW_PASS: f64 = 0.3;
/// x/z and y/z are clamped to this multiple of the half field of view in the Jacobian.
pub const FRUSTUM_CLAMP: f64 = 1.3;
/// Screen extent in standard deviations.
pub const SIGMA_EXTENT: f64 = 3.0;
/// Contributions with alpha below this are skipped.
pub const ALPHA_MIN: f32 = 1.0 / 255.0;
/// Alpha is clamped to this.
pub const ALPHA_MAX: f32 = 0.99;
/// A pixel stops before a Gaussian that would take its transmittance below this.
pub const T_MIN: f32 = 1e-4;
/// Largest image width or height.
pub const MAX_SIDE: u32 = 1 << 15;
/// Largest image pixel count.
pub const MAX_PIXELS: u64 = 1 << 28;

//! Triangulated 3D Gaussian initialisation from dense or sparse matches (ProFuse paper
//! §3.1, "Gaussian Initialization", following EDGS).
//!
//! # What it does
//!
//! 1. **References.** With dense matches, up to [`Params::references`] (180) reference views
//!    are chosen by seeded k-means over camera poses ([`select`]: a pose is the camera
//!    centre scaled by the spread of all centres, plus the unit optical axis), taking the
//!    view nearest each centroid. Each reference is triangulated against its
//!    [`Params::neighbours`] (3) nearest views by pose distance, among the views `j` for
//!    which the matches file has the ordered pair (reference, `j`). With sparse matches
//!    every listed pair is used: each view with outgoing pairs is a reference, and each
//!    match is triangulated between its two views.
//! 2. **Sampling.** A match is confident when its certainty is above
//!    [`Params::certainty_threshold`] (0.05); a dense grid cell is confident when it is so
//!    in at least one neighbour. Up to [`Params::budget`] (15,000) confident matches per
//!    reference are drawn uniformly without replacement from a SplitMix64 stream keyed by
//!    (seed, reference), so the draw does not depend on threads or on a third-party RNG.
//!    A dense cell (x, y) of an H x W grid stands for the reference pixel position
//!    ((x + 0.5) · image_w / W, (y + 0.5) · image_h / H) (SPEC.md §4.4); warp targets in
//!    `normalized` coordinates become pixels by `(t + 1) / 2 · size`.
//! 3. **Triangulation** ([`geometry`]): linear DLT in undistorted normalised coordinates
//!    (OpenCV distortion, where the cameras have it, is removed first), with the unknown
//!    point expressed relative to the reference centre in baseline units so the 4x4 system
//!    is well conditioned in any world frame; the null vector comes from an SVD. A dense
//!    sample is triangulated against every neighbour where it is confident, and one
//!    triangulation is kept: among those that pass the gates, the one that most of the
//!    other neighbours' warps agree with (the point projects within the reprojection
//!    tolerance of their target), then the smallest reprojection error (the larger of its
//!    two views), as in EDGS. The agreement count only matters when neighbours disagree: a
//!    wrong warp that happens to lie near its epipolar line can have a smaller two-view
//!    error than the right one, but the other neighbours do not confirm it.
//! 4. **Rejection.** Gates in order, the first failure is the reason counted in the
//!    [`Report`]: not finite / at infinity, camera z <= [`Params::near`] in either view,
//!    reprojection error above [`Params::max_reproj_px`] (2 px) in either view, angle
//!    between the two rays below [`Params::min_angle_deg`] (2°). When no neighbour passes,
//!    the reason of the one with the smallest reprojection error is counted. A wrong match
//!    is only detectable when it leaves the epipolar line: a random target passes the
//!    reprojection gate with probability about (band width × line length) / image area.
//! 5. **Gaussians**: mean = the point; colour = the reference image bilinearly sampled at
//!    the reference pixel, SH DC = (rgb − 0.5) / 0.28209479; identity rotation; opacity
//!    0.5 (logit 0); isotropic scale by [`Scale`]: by default one reference pixel at the
//!    point's depth (σ = z / f, EDGS's "proportional to depth" rule with the factor tied to
//!    the focal length: EDGS's 0.0005 × distance is one pixel at f = 2000 px), or
//!    [`Scale::Distance`] (EDGS literally), or [`Scale::Knn`] (the 3DGS rule: root mean
//!    squared distance to the 3 nearest points, kiddo k-d tree). SH degree 0.
//!
//! # Determinism and memory
//!
//! References are processed in parallel (rayon) and so are the samples inside each; every
//! result is collected in order and reductions run sequentially in reference order, so the
//! output file is byte-identical for any thread count. Matches are read through the
//! memory-mapped file; only the images of the references being processed are decoded, and
//! images are checked (size against the cameras) before any work starts, by their headers.
//!
//! # Example
//!
//! ```
//! use gs_init::{initialise_sparse, Params, ViewImage};
//! use profuse_formats::{Cameras, SparseMatches};
//!
//! // Two cameras 1 m apart looking down +z, and one match: the point (0.2, -0.1, 4).
//! let pose = |x: f64| [1.0, 0.0, 0.0, -x, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];
//! let cameras = Cameras {
//!     image_names: vec!["a.png".into(), "b.png".into()],
//!     image_size: vec![[64, 48]; 2].into(),
//!     intrinsics: vec![[50.0, 50.0, 32.0, 24.0]; 2].into(),
//!     world_to_camera: vec![pose(0.0), pose(1.0)].into(),
//!     ..Default::default()
//! };
//! let project = |v: usize, p: [f64; 3]| {
//!     let q = cameras.project(v, p);
//!     [q[0] as f32, q[1] as f32]
//! };
//! let truth = [0.2, -0.1, 4.0];
//! let matches = SparseMatches {
//!     num_views: 2,
//!     pairs: vec![[0, 1]].into(),
//!     pair_offsets: vec![0, 1].into(),
//!     points_i: vec![project(0, truth)].into(),
//!     points_j: vec![project(1, truth)].into(),
//!     certainty: vec![1.0].into(),
//!     ..Default::default()
//! };
//! let images = vec![ViewImage::filled(64, 48, [255, 128, 0]); 2];
//! let (gaussians, report) = initialise_sparse(&cameras, &images, &matches, &Params::default())?;
//! assert_eq!((report.sampled, report.kept), (1, 1));
//! let m = gaussians.means[0];
//! assert!((m[0] - 0.2).abs() < 1e-5 && (m[1] + 0.1).abs() < 1e-5 && (m[2] - 4.0).abs() < 1e-5);
//! // Colour from the reference pixel: SH DC = (rgb − 0.5) / C0.
//! assert!((gaussians.sh_dc[0][0] * 0.28209479 + 0.5 - 1.0).abs() < 1e-6);
//! // Scale: one reference pixel at depth 4 with f = 50.
//! assert!((gaussians.log_scales[0][0] - (4.0f32 / 50.0).ln()).abs() < 1e-5);
//! # Ok::<(), gs_init::InitError>(())
//! ```

mod error;
mod flat;
pub mod geometry;
mod images;
mod init;
pub mod job;
mod params;
mod report;
mod rng;
pub mod select;

use std::path::{Path, PathBuf};

use profuse_formats::{Cameras, FileKind, Gaussians, Matches, SparseMatches};

pub use error::{InitError, Result};
pub use flat::FlatParams;
pub use geometry::{triangulate, Gates, Reason, Triangulation, View};
pub use images::{ImageDir, ImageSource, ViewImage};
pub use init::{knn_scales, warp_to_pixels, MIN_KNN_DIST2, SH_C0};
pub use params::{Params, Scale};
pub use report::{ReferenceReport, Rejected, Report};

use init::{initialise, Input, Labels};

/// Re-exported so callers can size the thread pool (`rayon::ThreadPoolBuilder`) with the
/// rayon this crate runs on.
pub use rayon;

/// Initialises Gaussians from dense matches (`profuse.matches`). Errors name the inputs
/// `cameras` and `matches`; [`initialise_files`] names the files.
pub fn initialise_dense(
    cameras: &Cameras,
    images: &dyn ImageSource,
    matches: &Matches,
    params: &Params,
) -> Result<(Gaussians, Report)> {
    initialise(
        cameras,
        images,
        Input::Dense(matches),
        params,
        MEMORY_LABELS,
        &|_, _| {},
    )
}

/// Initialises Gaussians from sparse matches (`profuse.sparse_matches`).
pub fn initialise_sparse(
    cameras: &Cameras,
    images: &dyn ImageSource,
    matches: &SparseMatches,
    params: &Params,
) -> Result<(Gaussians, Report)> {
    initialise(
        cameras,
        images,
        Input::Sparse(matches),
        params,
        MEMORY_LABELS,
        &|_, _| {},
    )
}

const MEMORY_LABELS: Labels<'static> = Labels {
    cameras: "cameras",
    matches: "matches",
};

/// A matches file of either kind.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MatchFile {
    /// A `profuse.matches` file.
    Dense(PathBuf),
    /// A `profuse.sparse_matches` file.
    Sparse(PathBuf),
}

/// The input files of an initialisation.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Inputs {
    /// The cameras file.
    pub cameras: PathBuf,
    /// The folder `cameras.image_names` are relative to (see [`ImageDir`]).
    pub images: PathBuf,
    /// The matches.
    pub matches: MatchFile,
}

impl Inputs {
    /// The inputs of a scene directory (SPEC.md §6): `cameras.safetensors`, images under
    /// the directory, and `matches.safetensors`, or `sparse_matches.safetensors` when there
    /// are no dense matches.
    pub fn scene(dir: &Path) -> Result<Inputs> {
        let dense = dir.join("matches.safetensors");
        let sparse = dir.join("sparse_matches.safetensors");
        let matches = if dense.is_file() {
            MatchFile::Dense(dense)
        } else if sparse.is_file() {
            MatchFile::Sparse(sparse)
        } else {
            return Err(InitError::NoMatches {
                dir: dir.display().to_string(),
            });
        };
        Ok(Inputs {
            cameras: dir.join("cameras.safetensors"),
            images: dir.to_path_buf(),
            matches,
        })
    }
}

/// Reads the input files and initialises; errors name the file they are about.
/// `progress(done, total)` is called after each reference view.
pub fn initialise_files(
    inputs: &Inputs,
    params: &Params,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<(Gaussians, Report)> {
    params.validate()?;
    let cameras = Cameras::read(&inputs.cameras)?;
    let images = ImageDir::new(&inputs.images, &cameras.image_names);
    let cameras_label = inputs.cameras.display().to_string();
    match &inputs.matches {
        MatchFile::Dense(path) => {
            let m = Matches::read(path)?;
            let label = path.display().to_string();
            let labels = Labels {
                cameras: &cameras_label,
                matches: &label,
            };
            initialise(
                &cameras,
                &images,
                Input::Dense(&m),
                params,
                labels,
                progress,
            )
        }
        MatchFile::Sparse(path) => {
            let m = SparseMatches::read(path)?;
            let label = path.display().to_string();
            let labels = Labels {
                cameras: &cameras_label,
                matches: &label,
            };
            initialise(
                &cameras,
                &images,
                Input::Sparse(&m),
                params,
                labels,
                progress,
            )
        }
    }
}

/// Initialises from a scene directory ([`Inputs::scene`]); the caller writes the result
/// (conventionally to `SCENE/out/gaussians.safetensors`).
pub fn initialise_scene(dir: &Path, params: &Params) -> Result<(Gaussians, Report)> {
    initialise_files(&Inputs::scene(dir)?, params, &|_, _| {})
}

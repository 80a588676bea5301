//! Importers and exporters between ProFuse files (`profuse_formats`) and the formats
//! scenes arrive in: INRIA 3DGS PLY (import and export), instant-ngp/NeRF
//! `transforms.json`, COLMAP sparse models (text and binary), LLFF `poses_bounds.npy`
//! scenes, ScanNet exports and `*_vh_clean_2.labels.ply`, NumPy `.npy`/`.npz`, and
//! LangSplat `language_features/`.
//!
//! # Design
//!
//! * **One convention inside.** Everything is converted on the way in to SPEC.md's
//!   conventions: OpenCV camera axes (x right, y down, z forward), world-to-camera
//!   `[R | t]`, pixel centres at integer + 0.5 (origin at the top-left *corner*), SH
//!   coefficients indexed `[n, k, channel]`. Each importer states its conversion:
//!   - [`transforms`]: OpenGL camera-to-world → `c2w · diag(1, −1, −1, 1)`, inverted;
//!     `cx, cy` copied (instant-ngp already uses the corner origin).
//!   - [`colmap`]: quaternion (w, x, y, z) → R, `tvec` → t; `cx, cy` copied (COLMAP puts
//!     pixel centres at +0.5 too).
//!   - [`llff`]: camera-to-world columns [down, right, back] → [right, down, forward],
//!     inverted; principal point at the image centre, focal scaled by the downscale.
//!   - [`scannet`]: camera-to-world inverted after the axis alignment `A · c2w`;
//!     `cx, cy` + 0.5 (ScanNet's calibration puts pixel centres at integers).
//!   - [`ply`]: INRIA's channel-major `f_rest_{c·R + k}` ↔ our `sh_rest[n, k, c]`.
//! * **Rotations from text** (transforms.json, ScanNet poses) are snapped to the nearest
//!   rotation (SVD polar factor) when within
//!   [`geometry::REORTHONORMALIZE_TOLERANCE`] = 1e-3 of orthonormal, and rejected beyond
//!   that, so a file with a scaled or sheared matrix fails loudly instead of producing
//!   a camera that the format crate would reject later with a less helpful message.
//! * **Clamping.** Trained 3DGS scenes sometimes store `+inf` opacity logits (opacity
//!   exactly 1). These, and NaN/−inf, are clamped to ±[`ply::OPACITY_LOGIT_CLAMP`] (20)
//!   and counted in [`ply::PlyReport::clamped_opacity`]; every other non-finite value is
//!   an error naming the property and vertex. Finite values round-trip bit for bit.
//! * **Errors, not panics.** Parsers never index with values read from a file; every
//!   failure is a [`SceneError`] naming the file, the field (PLY property, JSON key,
//!   line, NumPy header key) and what was expected. Counts in headers never reserve more
//!   memory than the file's remaining bytes could fill.
//!   - [`keypoints`]: keypoint-pair `.npz` files (XFeat, LightGlue, LoFTR) → `+0.5`
//!     (OpenCV puts pixel centres at integers), undistorted with [`undistort`] when the
//!     cameras carry OpenCV k1 k2 p1 p2, so that every later stage is pinhole.
//!   - [`colmap::track_matches`]: a COLMAP model's own tracks → sparse matches (no
//!     learned matcher), one match per 3D point on its widest-angle view pair, undistorted
//!     the same way as keypoint pairs.
//! * **Bounded reads.** Files are opened only when they are regular files (a FIFO would
//!   block, `/dev/zero` never ends); text inputs are capped ([`MAX_SMALL_TEXT_BYTES`],
//!   [`MAX_JSON_BYTES`], [`ColmapOptions::max_text_bytes`]); `.npy` headers are capped at
//!   NumPy's 10,000 bytes and 16 nesting levels; `.npz` members are inflated only up to
//!   the size their `.npy` header fixes ([`npy::read_npz_capped`]).
//! * **One rule for image paths** read from inputs ([`scene_relative_parts`]): relative,
//!   inside the scene folder (no `..`), not absolute. An import with nothing to import
//!   (no view, no pair) is an error, never an empty file.
//! * **No printing.** Warnings (skipped frames, missing optional files) are returned in
//!   each importer's report; the `scene-io` tool prints them.
//! * **Atomic writes.** Exports go to a temporary file next to the target, then are
//!   renamed into place, like the format crate's writers.
//!
//! # Example: a PLY round trip
//!
//! ```
//! use profuse_formats::Gaussians;
//! use scene_io::ply::{read_inria_ply, write_inria_ply};
//!
//! let dir = tempfile::tempdir()?;
//! let path = dir.path().join("scene.ply");
//! let gaussians = Gaussians {
//!     means: vec![[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]].into(),
//!     log_scales: vec![[-2.0; 3], [-3.0; 3]].into(),
//!     rotations: vec![[1.0, 0.0, 0.0, 0.0], [0.5, 0.5, 0.5, 0.5]].into(),
//!     opacity_logits: vec![0.25, -1.5].into(),
//!     sh_dc: vec![[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]].into(),
//!     sh_degree: 1,
//!     // [n, k, channel]: 2 Gaussians x 3 coefficients x RGB
//!     sh_rest: Some((0..18).map(|i| i as f32 / 100.0).collect::<Vec<_>>().into()),
//!     ..Default::default()
//! };
//! write_inria_ply(&path, &gaussians)?;
//!
//! let (back, report) = read_inria_ply(&path)?;
//! assert_eq!(report.gaussians, 2);
//! assert_eq!(report.sh_degree, 1);
//! assert_eq!(report.clamped_opacity, 0);
//! assert_eq!(back.means, gaussians.means);
//! assert_eq!(back.sh_rest, gaussians.sh_rest);
//! assert_eq!(back.rotations, gaussians.rotations);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

pub mod colmap;
mod error;
mod fsutil;
pub mod geometry;
pub mod keypoints;
pub mod langsplat;
pub mod llff;
pub mod npy;
pub mod photo;
pub mod ply;
pub mod scannet;
pub mod transforms;
pub mod undistort;

pub use colmap::{import_colmap, ColmapImport, ColmapOptions, ColmapReport};
pub use error::{Result, SceneError};
pub use fsutil::{image_dimensions, scene_relative_parts, MAX_JSON_BYTES, MAX_SMALL_TEXT_BYTES};
pub use langsplat::{import_langsplat, LangSplatOptions, LangSplatReport};
pub use llff::{import_llff, LlffOptions, LlffReport};
pub use ply::{read_inria_ply, write_inria_ply, PlyReport, OPACITY_LOGIT_CLAMP};
pub use scannet::{
    import_scannet_folder, read_scannet_labels_ply, read_scannet_npy, AxisAlignment, MeshReport,
    ScannetOptions, ScannetReport,
};
pub use transforms::{read_transforms, TransformsReport};

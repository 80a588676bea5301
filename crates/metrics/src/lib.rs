//! Evaluation protocols of the ProFuse paper and of the pipeline's intermediate stages:
//!
//! * [`lerf`]: LERF-OVS open-vocabulary 3D object selection (paper §4.2): LangSplat label
//!   polygons rasterised as the reference code does (int32 truncation + `cv2.fillPoly`,
//!   [`mask`]), IoU per (frame, query), mIoU and
//!   Acc@0.25 per scene and over scenes, and a grid search of the selection threshold.
//! * [`scannet`]: ScanNet point-cloud understanding (paper §4.3): per-vertex NYU40
//!   predictions against mesh labels, mIoU and mAcc over the 19/15/10-class sets.
//! * [`cluster`]: adjusted Rand index, purity and completeness of a clustering (3D
//!   Context Proposals against synth's per-mask ground-truth objects).
//! * [`surface`]: distances of reconstructed points to an exact surface (a distance
//!   function the caller supplies, e.g. a synth scene's).
//! * [`wrong_class`]: the share of mask pixels whose registered descriptor's best class
//!   prompt is not their ground-truth object's class (proposals against the baseline).
//!
//! # Design
//!
//! Every metric is a pure function of in-memory arrays (exact integer counts first, one
//! division at the end), so it can be tested against hand-computed cases and brute force;
//! readers of the on-disk inputs are thin and separate (`read_*`), and reuse the typed
//! readers of `profuse-formats` (ground truth under `gt/` included) instead of parsing
//! those files again. The crate depends on no scene generator or importer (ARCHITECTURE.md):
//! a ScanNet mesh is read by the caller (`scene_io::scannet::read_labelled_mesh`) and an
//! exact surface is a closure.
//! Conventions the papers leave implicit are fixed and documented in each module, following
//! the reference code where there is one: OpenCV's polygon fill on int32 vertices, strict
//! `IoU > 0.25`, classes averaged
//! over those present in the ground truth, unassigned items as singleton clusters.
//! Percentages are used where the paper reports percentages (mIoU, mAcc, Acc@0.25);
//! per-pair IoUs and clustering scores are fractions. Work that is parallel (frames,
//! points) writes disjoint outputs and reduces in a fixed order, so results do not depend
//! on the thread count.
//!
//! # Example
//!
//! ```
//! use profuse_metrics::lerf::{evaluate_scene, parse_label_json, LabelScene};
//! use profuse_metrics::mask::{rasterize_polygon, Mask};
//!
//! // One 8x8 frame with a "mug" traced at [2, 6] x [2, 6]: the outline is included, so
//! // the mug covers pixels 2..=6 x 2..=6 (25 pixels).
//! let label = r#"{"info": {"name": "f.png", "width": 8, "height": 8},
//!   "objects": [{"category": "mug", "segmentation": [[2,2],[6,2],[6,6],[2,6]], "bbox": [2,2,6,6]}]}"#;
//! let scene = LabelScene {
//!     name: "toy".into(),
//!     frames: vec![parse_label_json(label, "frame_00000".into(), "<memory>")?],
//! };
//! // The prediction covers pixels 0..=4 x 2..=6: 15 of the mug's pixels and 10 others,
//! // IoU 15/35.
//! let predict = |_: &_, _: &str| -> profuse_metrics::Result<Option<Mask>> {
//!     Ok(Some(rasterize_polygon(&[[0.0, 2.0], [4.0, 2.0], [4.0, 6.0], [0.0, 6.0]], 8, 8)))
//! };
//! let s = evaluate_scene(&scene, &predict, None)?;
//! assert_eq!((s.pairs, s.rows[0].intersection), (1, 15));
//! assert!((s.miou - 100.0 * 15.0 / 35.0).abs() < 1e-9 && s.acc25 == 100.0);
//! # Ok::<(), profuse_metrics::MetricsError>(())
//! ```

pub mod cluster;
mod error;
pub mod lerf;
pub mod mask;
pub mod photo;
pub mod scannet;
pub mod surface;
pub mod wrong_class;

pub(crate) use error::invalid;
pub use error::{MetricsError, Result};

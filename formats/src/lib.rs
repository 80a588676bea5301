//! Typed, validated readers and atomic writers for every file kind the ProFuse
//! pipeline exchanges. `SPEC.md` at the repository root is the normative contract;
//! this crate is its reference implementation and the Python package `formats/python`
//! its mirror.
//!
//! # Design
//!
//! Every file is a [safetensors](https://github.com/huggingface/safetensors) container:
//! an 8-byte little-endian header length, a JSON header (tensor dtypes, shapes, byte
//! offsets and a `__metadata__` string map naming the `format` and `format_version`),
//! then the raw little-endian tensor bytes. Readers memory-map the file and hand out
//! [`Buffer`]s that borrow the mapped bytes when they are aligned (the writer makes sure
//! they are), so opening a multi-gigabyte warp file costs a header parse.
//!
//! Reading validates everything the file alone can show: the container structure
//! (truncation, a header that lies about offsets or sizes), the kind and major version,
//! required tensors, dtypes, shapes that agree with each other through named dimensions,
//! index ranges, finiteness and unit norms. Writing runs the same validation first, then
//! writes a temporary file next to the target and renames it into place. Errors are one
//! enum, [`FormatError`], whose variants name file, tensor and expectation; its
//! [`FormatError::code`] is shared with the Python reader.
//!
//! [`output`] holds the rules every ProFuse output follows (issue 20): only regular files
//! are replaced, names from data must be plain path components, temporary names are unique
//! (`.profuse-tmp-*`) and locked while written, leftovers of killed runs are cleaned,
//! multi-file outputs are built next to their target and swapped in whole
//! ([`output::StagedDir`]), output directories can be locked ([`output::lock_dir`]), and
//! report paths serialise lossily ([`output::lossy_path`]).
//!
//! Two small modules hold the math every stage shares, so that it exists once: [`camera`]
//! (SPEC.md §3.3's poses, projection, pixel centres, grid intrinsics and lens model, and
//! the SH DC colour rule of §4.2) and [`rng`] (the workspace's seeded SplitMix64).
//!
//! # Example: a round trip
//!
//! ```
//! use profuse_formats::{FileKind, Prompts};
//!
//! let dir = tempfile::tempdir()?;
//! let path = dir.path().join("prompts.safetensors");
//! let prompts = Prompts {
//!     names: vec!["chair".into(), "table".into()],
//!     dim: 3,
//!     embeddings: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0].into(),
//!     ..Default::default()
//! };
//! prompts.write(&path)?;
//! let back = Prompts::read(&path)?;
//! assert_eq!(back, prompts);
//! assert_eq!(back.embedding(1), &[0.0, 1.0, 0.0]);
//!
//! // A bad file is a typed error naming the file and the problem.
//! std::fs::write(&path, b"not a safetensors file")?;
//! let err = Prompts::read(&path).unwrap_err();
//! assert_eq!(err.code(), "header");
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

pub mod camera;
mod cameras;
mod check;
mod container;
mod error;
mod features;
mod fuse_partial;
mod gaussians;
pub mod ground_truth;
mod inspect;
mod kind;
pub mod label_space;
mod masks;
mod matches;
mod mesh;
pub mod output;
#[cfg(feature = "png")]
pub mod png;
mod pq;
mod prompts;
mod proposals;
pub mod rng;
pub mod samples;
mod selection;
mod semantic_index;
mod topk;
mod vertex_labels;
mod view_maps;
mod warp_partial;
mod writer;

pub use cameras::{Cameras, Pose, ROTATION_TOLERANCE};
pub use check::{format_float, Floats, Labels};
pub use container::{
    read_files_into_memory, Buffer, Container, Dtype, Element, Scalar, TensorInfo, MAX_HEADER_BYTES,
};
pub use error::{FormatError, Result};
pub use features::Features;
pub use fuse_partial::{
    fixed_point, fixed_point_words, FuseGrouping, FuseOrphans, FusePartial, NO_GROUP,
};
pub use gaussians::{Gaussians, SH_REST_COEFFS};
pub use inspect::{inspect, validate_any, Report};
pub use kind::{check_version, FileKind, Kind, MAJOR_VERSION};
pub use masks::Masks;
pub use matches::{Matches, SparseMatches, WarpCoords};
pub use mesh::Mesh;
pub use pq::{Pq, KSUB};
pub use prompts::Prompts;
pub use proposals::{Proposals, NO_PROPOSAL};
pub use selection::Selection;
pub use semantic_index::{
    index_dtype, quantise_share, SemanticIndex, MAX_U16_PROPOSALS, SHARE_SCALE,
};
pub use topk::{TopK, NO_GAUSSIAN, WEIGHT_SUM_TOLERANCE};
pub use vertex_labels::VertexLabels;
pub use view_maps::{ViewMaps, NO_OBJECT};
pub use warp_partial::{WarpPartial, WARP_COUNTERS, WARP_INPUTS};
pub use writer::{write_atomically, FileWriter};

/// Re-exported so users can build F16 tensors without naming the `half` crate.
pub use half::f16;

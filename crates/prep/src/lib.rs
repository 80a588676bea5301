//! Front-end preprocessing from real models: the files the semantic half reads (masks and
//! mask features, text prompts) made from a user's photos with SAM and CLIP ONNX exports.
//!
//! # Design
//!
//! Models run through ONNX Runtime (`ort`, `load-dynamic`): the shared library is opened
//! at run time ([`runtime`]) from an explicit path, `ORT_DYLIB_PATH`, or the `onnxruntime`
//! Python wheel, so nothing is downloaded or linked at build time and the same library
//! gives bit-identical results to the Python reference. Images are decoded by the caller or
//! [`image::load_rgb`]; every model input is made here ([`sam::preprocess`],
//! [`clip::image_input`]) with one bilinear resampler.
//!
//! [`amg`] is SAM's automatic mask generator (point grid, predicted-IoU and stability
//! filters, box NMS, small-region removal) on one view; [`amg::label_map`] flattens its
//! overlapping masks into the non-overlapping label map the masks file stores (larger
//! masks first, smaller on top). [`masks::run_masks`] streams the views: one image and one
//! embedding in memory at a time, the encoder once per view. Mask descriptors come from
//! the SAM embedding ([`pool`]) or a CLIP image encoder ([`clip`]); prompts from a CLIP
//! text encoder with CLIP's BPE tokeniser.
//!
//! [`xfeat`] makes keypoint matches between view pairs for the geometry: XFeat* semi-dense
//! matching with the package's own weights (exported to ONNX, embedded), pairs chosen by
//! camera neighbourhood.
//!
//! The stage is built so that more front-end steps (e.g. dense warps from geometry) can
//! be added as modules next to these, behind the same `prep` tool.

pub mod amg;
pub mod clip;
mod error;
pub mod features;
pub mod image;
pub mod masks;
pub mod pool;
pub mod preview;
pub mod rle;
pub mod runtime;
pub mod sam;
pub mod shard;
pub mod xfeat;

pub use error::{PrepError, Result};

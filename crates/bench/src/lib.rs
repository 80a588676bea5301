//! Benchmarks of the ProFuse stages on synthetic scenes: what the tools' `bench`
//! subcommands run. They print throughput, CPU seconds and peak memory as one JSON object.
//!
//! # Design
//!
//! Benchmarks live in their own crate, in the tools layer, because they need the synthetic
//! scene generator (`synth`) and the stage crates must not depend on it (ARCHITECTURE.md).
//! A benchmark's scene is generated in a child process (the calling tool re-run with a
//! hidden subcommand, [`common::generate_in_child`]), so that the generator's memory does
//! not count in the benchmark's peak RSS; a scene kept with `--scene-dir` is reused when it
//! was generated with the same parameters ([`common::scene_matches`]).

pub mod common;
pub mod fuse;
pub mod gs_init;
pub mod gs_refine;
pub mod metrics;
pub mod pq;
pub mod query;
pub mod raster;
pub mod semantics;
pub mod vertex_transfer;
pub mod warp_graph;

/// Boxed error of a benchmark.
pub type BoxError = Box<dyn std::error::Error + Send + Sync + 'static>;

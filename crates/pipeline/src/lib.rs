//! The ProFuse pipeline as one library call, behind `profuse run` and `profuse prepare`:
//! [`run`] runs the stages on a scene directory, [`prepare`] makes that scene directory from
//! a capture (photos, a COLMAP project, a transforms.json, a trained splat). The synthetic
//! experiments (`profuse demo`, `profuse sweep`) and their ground-truth scoring live in
//! `profuse-experiments`, so that this crate links no scene generator.
//!
//! # Design
//!
//! * **Stages are the crates' library calls**, in the paper's order: `gs-init` (geometry),
//!   `warp-graph` and `fuse` (semantics), `pq` (indexing), then `query` and
//!   `vertex-transfer` (evaluation outputs). The per-crate tools make the same calls, so a
//!   shell script composing the tools produces the same bytes (`tools/pipeline.sh`, checked
//!   by a test).
//! * **Up-to-date checks without trusting partial work.** Each stage writes a completion
//!   record after its outputs are in place; a stage is skipped only when that record
//!   holds the same parameters, the same code identity and the fingerprints its inputs
//!   and outputs still have ([`stage`]). Outputs are written atomically, multi-file
//!   outputs through a temporary directory, so a run killed midway is redone from the
//!   interrupted stage.
//! * **One configuration** ([`config::Config`]): every parameter of every stage with the
//!   paper's values as defaults, from TOML and `section.key=value` overrides; the
//!   effective configuration is written as `out/config.toml`.
//! * **What experiments need is public** ([`support`], [`Summary::registered`]): the
//!   registration the fuse stage keeps in memory, the fuse job of a configuration, the
//!   scene's image list, so that `profuse-experiments` scores a run without re-reading or
//!   re-implementing any stage.
//!
//! # Example
//!
//! ```no_run
//! use profuse_pipeline::{config::Config, run, RunOptions};
//!
//! let scene = std::path::Path::new("/tmp/profuse-demo");
//! let summary = run(scene, &Config::default(), &RunOptions::default(), &|_| {})?;
//! println!("total {:.1} s", summary.timing_s["total"]);
//! # Ok::<(), profuse_pipeline::PipelineError>(())
//! ```

pub mod cli;
pub mod config;
mod error;
pub mod fnv;
#[cfg(test)]
mod identity;
pub mod prepare;
mod run;
pub mod stage;

/// Helpers shared with the crates built on the pipeline (`profuse-experiments`): the same
/// error wrapping, atomic writes and stage jobs the pipeline uses itself.
pub mod support {
    pub use crate::error::{io_err, stage_err};
    pub use crate::run::{fuse_job, image_paths, write_text};
}

pub use error::{PipelineError, Result};
pub use run::{
    fuse_shard, run, warp_shard, Event, Paths, RegisteredMasks, RunOptions, StageLine, StageName,
    Summary, SCANNET_SETS,
};

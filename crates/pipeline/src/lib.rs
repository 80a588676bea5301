//! The ProFuse pipeline as one library call, behind `profuse run` and `profuse demo`.
//!
//! # Design
//!
//! * **Stages are the crates' library calls**, in the paper's order: `gs-init` (geometry),
//!   `warp-graph` and `fuse` (semantics), `pq` (indexing), then `query` and
//!   `vertex-transfer` (evaluation outputs). The per-crate tools make the same calls, so a
//!   shell script composing the tools produces the same bytes (`tools/pipeline.sh`, checked
//!   by a test).
//! * **Up-to-date checks without trusting partial work.** Each stage writes a completion
//!   record after its outputs are in place; a stage is skipped only when that record is
//!   newer than every input and records the same parameters ([`stage`]). Outputs are
//!   written atomically, multi-file outputs through a temporary directory, so a run killed
//!   midway is redone from the interrupted stage.
//! * **One configuration** ([`config::Config`]): every parameter of every stage with the
//!   paper's values as defaults, from TOML and `section.key=value` overrides; the
//!   effective configuration is written as `out/config.toml`.
//! * **Ground truth when present** ([`evaluate`]): synthetic scenes carry `gt/`, from which
//!   the run is scored (surface distance of the initial Gaussians, proposal ARI, LERF mIoU
//!   and Acc@0.25, ScanNet-style mIoU).
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

pub mod config;
mod error;
pub mod evaluate;
mod run;
pub mod stage;

pub use error::{PipelineError, Result};
pub use run::{run, Event, Paths, RunOptions, StageLine, Summary, SCANNET_SETS};

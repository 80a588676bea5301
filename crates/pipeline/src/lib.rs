//! The ProFuse pipeline as one library call, behind `profuse run`, `profuse demo` and
//! `profuse sweep`: [`run`] runs the stages, [`evaluate`] scores a run against a synthetic
//! scene's ground truth, [`demo`] is the paper's central experiment (ProFuse against the
//! `--no-proposals` baseline on a synth scene) and [`sweep`] repeats it over seeds and
//! fault sets (the accuracy harness).
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
//! * **Ground truth when present** ([`evaluate`]): synthetic scenes carry `gt/`, from which
//!   the run is scored (surface distance of the run's Gaussians, proposal ARI, LERF mIoU
//!   and Acc@0.25, ScanNet-style mIoU) and, with [`evaluate::evaluate_run`], the share of
//!   mask pixels whose registered descriptor names the wrong class, from the registration
//!   the fuse stage keeps in memory ([`Summary::registered`]) or recomputes; nothing extra
//!   is written to the output directory.
//! * **Experiments are library calls too** ([`demo::run_experiment`], [`sweep::sweep`]):
//!   the tools only parse arguments and display progress. Sweep rows run one after the
//!   other (each run is parallel inside) in the fixed order fault set, then seed, and each
//!   equals the `profuse demo` of the same seed, fault set and options.
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
pub mod demo;
mod error;
pub mod evaluate;
mod fnv;
#[cfg(test)]
mod identity;
pub mod prepare;
mod run;
pub mod stage;
pub mod sweep;

pub use error::{PipelineError, Result};
pub use run::{
    fuse_shard, run, warp_shard, Event, Paths, RegisteredMasks, RunOptions, StageLine, StageName,
    Summary, SCANNET_SETS,
};

//! The paper's central experiment on synthetic scenes, behind `profuse demo` and
//! `profuse sweep`: [`demo`] generates a synth scene, runs the pipeline with 3D Context
//! Proposals and the `--no-proposals` baseline (every mask registers its own feature,
//! Dr. Splat style), and scores both against the scene's exact ground truth
//! ([`evaluate`]); [`sweep`] repeats it over seeds and fault sets.
//!
//! # Design
//!
//! * **Apart from the pipeline.** The experiments need the scene generator (synth, and
//!   through it parry3d); a user running `profuse run` on their photos does not. So they
//!   live here, on top of `profuse-pipeline`'s library calls, and the pipeline links no
//!   generator (`.ci/check-layers` checks it).
//! * **Ground truth when present** ([`evaluate`]): synthetic scenes carry `gt/`, from which
//!   the run is scored (surface distance of the run's Gaussians, proposal ARI, LERF mIoU
//!   and Acc@0.25, ScanNet-style mIoU) and, with [`evaluate::evaluate_run`], the share of
//!   mask pixels whose registered descriptor names the wrong class, from the registration
//!   the fuse stage keeps in memory (`Summary::registered`) or recomputes; nothing extra
//!   is written to the output directory.
//! * **Experiments are library calls** ([`demo::run_experiment`], [`sweep::sweep`]): the
//!   tools only parse arguments and display progress. Sweep rows run one after the other
//!   (each run is parallel inside) in the fixed order fault set, then seed, and each equals
//!   the `profuse demo` of the same seed, fault set and options.
//!
//! # Example
//!
//! ```no_run
//! use profuse_experiments::demo::{run_demo, DemoOptions};
//!
//! let mut opts = DemoOptions::new(0)?;
//! opts.scene = Some(std::env::temp_dir().join("profuse-demo"));
//! let report = run_demo(&opts, &|_| {}, &|msg| eprintln!("{msg}"))?;
//! println!("LERF mIoU {}", report["metrics"]["lerf_miou"]);
//! # Ok::<(), profuse_pipeline::PipelineError>(())
//! ```

pub mod demo;
pub mod evaluate;
pub mod record;
pub mod sweep;

mod generated {
    include!(concat!(env!("OUT_DIR"), "/code_identity.rs"));
}

/// The code identity of a workspace crate the experiments run (see `build.rs`); `None`
/// for any other crate.
fn crate_code(krate: &str) -> Option<&'static str> {
    generated::CRATE_CODE
        .iter()
        .find(|(name, _)| *name == krate)
        .map(|(_, id)| *id)
}

//! `vertex-transfer`: label the vertices of a mesh from language Gaussians (paper §4.3),
//! and benchmark the transfer on the real ScanNet scene0000_00.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error goes to stderr, the exit code is 1 and nothing is written.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::{Args, Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use profuse_bench::vertex_transfer as bench;
use profuse_metrics::scannet::ClassSet as ScannetSet;
use profuse_tools::{chatty, init_threads, run, Bars, BoxError};
use serde_json::{json, Value};
use vertex_transfer::{run_job_with_progress, DescriptorFile, Job, JobStage, Params};

#[derive(Debug, Parser)]
#[command(
    name = "vertex-transfer",
    version,
    about = "Label mesh vertices from language Gaussians (KD-tree shortlist, Mahalanobis gate)",
    long_about = "Labels every vertex of a mesh with the class its nearby Gaussians vote for \
                  (ProFuse paper §4.3): the K nearest valid Gaussian centres, kept when the \
                  Mahalanobis distance under the Gaussian's own covariance is <= sigma, \
                  weighted by exp(-d²/2) · opacity; each Gaussian's class probabilities are \
                  the softmax of cos(descriptor, class prompt) / temperature; the label is \
                  the argmax of the weighted sum (ties to the smaller label), -1 where no \
                  Gaussian passes the gate. Prints one JSON report on stdout."
)]
struct Cli {
    /// Do not print progress on stderr.
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Transfer labels onto a mesh and write a `vertex_labels` file (SPEC.md §4.11):
    /// `labels` I32 (the class id, or the position in --classes when the prompts have no
    /// class_ids; -1 = no candidate) and `confidence` F32 (max score / sum of weights).
    Run {
        /// Gaussians file (profuse.gaussians).
        #[arg(long)]
        gaussians: PathBuf,
        #[command(flatten)]
        descriptors: DescriptorArgs,
        /// Prompts file (profuse.prompts); every prompt with class_ids >= 0 is a class
        /// unless --classes names them.
        #[arg(long)]
        prompts: PathBuf,
        /// Class prompt names (comma-separated or repeated) instead of the class_ids rows.
        #[arg(long, value_delimiter = ',', num_args = 1..)]
        classes: Option<Vec<String>>,
        /// Restrict the vocabulary to one NYU40 class set of the ScanNet protocol
        /// (OpenGaussian's): only the prompts of classes in the set compete, each vertex
        /// takes the argmax over them. `all` keeps every class.
        #[arg(long, value_enum, default_value = "all")]
        class_set: ClassSetArg,
        /// Mesh file (profuse.mesh) whose vertices are labelled.
        #[arg(long)]
        mesh: PathBuf,
        /// The vertex_labels file to write.
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        params: Params,
    },
    /// Benchmark on ScanNet scene0000_00 with the oracle fixture (Gaussians on the mesh
    /// vertices with synthetic class features; see the crate README): mIoU / mAcc for the
    /// 19/15/10-class sets with exact features on every vertex and with CLIP-like noisy
    /// features on 20% of the vertices, labelling throughput at K = 64, peak memory.
    Bench {
        #[command(flatten)]
        params: bench::BenchParams,
        /// Worker threads (default: rayon's, i.e. RAYON_NUM_THREADS or the core count).
        #[arg(long)]
        threads: Option<usize>,
    },
}

/// `--class-set`: a class set of the ScanNet protocol, or every class.
#[derive(Debug, Clone, Copy, ValueEnum)]
enum ClassSetArg {
    /// The 19 NYU40 classes of OpenGaussian's protocol.
    Nyu19,
    /// The 15-class subset.
    Nyu15,
    /// The 10-class subset.
    Nyu10,
    /// Every class of the prompts (no restriction).
    All,
}

impl ClassSetArg {
    /// The NYU40 ids to restrict to; `None` for `all`.
    fn filter(self) -> Option<Vec<i32>> {
        let set = match self {
            ClassSetArg::Nyu19 => ScannetSet::Nyu19,
            ClassSetArg::Nyu15 => ScannetSet::Nyu15,
            ClassSetArg::Nyu10 => ScannetSet::Nyu10,
            ClassSetArg::All => return None,
        };
        // NYU40 ids are 1..=40: they fit i32.
        Some(set.ids().iter().map(|&id| id as i32).collect())
    }
}

#[derive(Debug, Args)]
#[group(required = true, multiple = false)]
struct DescriptorArgs {
    /// Decoded descriptors (profuse.features), one row per Gaussian.
    #[arg(long)]
    features: Option<PathBuf>,
    /// Product-quantised descriptors (profuse.pq), one code per Gaussian.
    #[arg(long)]
    pq: Option<PathBuf>,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| execute(cli.command, quiet))
}

fn execute(command: Command, quiet: bool) -> Result<Value, BoxError> {
    match command {
        Command::Run {
            gaussians,
            descriptors,
            prompts,
            classes,
            class_set,
            mesh,
            out,
            params,
        } => {
            let descriptors = match (descriptors.features, descriptors.pq) {
                (Some(f), _) => DescriptorFile::Features(f),
                (None, Some(p)) => DescriptorFile::Pq(p),
                (None, None) => return Err("one of --features or --pq is required".into()),
            };
            profuse_tools::check_outputs([out.as_path()])?;
            let job = Job {
                gaussians,
                descriptors,
                prompts,
                classes,
                class_filter: class_set.filter(),
                mesh,
                out,
                generator: Some(format!("vertex-transfer {} run", env!("CARGO_PKG_VERSION"))),
            };
            transfer(&job, &params, quiet)
        }
        Command::Bench { params, threads } => {
            init_threads(threads)?;
            bench::run(&params, &Bars::new(chatty(quiet)))
        }
    }
}

fn transfer(job: &Job, params: &Params, quiet: bool) -> Result<Value, BoxError> {
    let show = chatty(quiet);
    let t = Instant::now();
    let bar = ProgressBar::hidden();
    let stage = |s: JobStage| {
        if !show {
            return;
        }
        match s {
            JobStage::Read => eprintln!("reading inputs"),
            JobStage::Build => eprintln!("preparing Gaussians and the KD-tree"),
            JobStage::Label { vertices } => {
                bar.set_draw_target(indicatif::ProgressDrawTarget::stderr());
                bar.set_length(vertices);
                if let Ok(style) =
                    ProgressStyle::with_template("labelling {bar:40} {pos}/{len} [{elapsed}]")
                {
                    bar.set_style(style);
                }
            }
            JobStage::Write => {
                bar.finish_and_clear();
                eprintln!("writing {}", job.out.display());
            }
        }
    };
    let report = run_job_with_progress(job, params, &stage, &|n| bar.inc(n))?;
    let mut value = serde_json::to_value(&report)?;
    if let Value::Object(map) = &mut value {
        map.insert("out".to_string(), json!(job.out.display().to_string()));
        map.insert("seconds".to_string(), json!(t.elapsed().as_secs_f64()));
    }
    Ok(value)
}

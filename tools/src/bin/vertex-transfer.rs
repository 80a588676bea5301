//! `vertex-transfer`: label the vertices of a mesh from language Gaussians (paper §4.3),
//! and benchmark the transfer on the real ScanNet scene0000_00.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error goes to stderr, the exit code is 1 and nothing is written.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{Args, Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use profuse_formats::Mesh;
use profuse_metrics::scannet::{evaluate, ClassSet as ScannetSet};
use profuse_tools::{chatty, peak_rss_mb, run, BoxError};
use serde_json::{json, Map, Value};
use vertex_transfer::oracle::{self, OracleConfig, OracleScene};
use vertex_transfer::{
    run_job_with_progress, ClassSet, DescriptorFile, Descriptors, GaussianField, Job, JobStage,
    Params, Source, DEFAULT_K, DEFAULT_MIN_SCALE, DEFAULT_SIGMA, DEFAULT_TEMPERATURE,
};

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
        params: ParamArgs,
    },
    /// Benchmark on ScanNet scene0000_00 with the oracle fixture (Gaussians on the mesh
    /// vertices with synthetic class features; see the crate README): mIoU / mAcc for the
    /// 19/15/10-class sets with exact features on every vertex and with CLIP-like noisy
    /// features on 20% of the vertices, labelling throughput at K = 64, peak memory.
    Bench {
        /// ScanNet NumPy export: a directory holding *_vert_all.npy and
        /// *_sem_label_all.npy, or their prefix.
        #[arg(long, default_value = "../shared/data/scannet/scene0000_00")]
        scannet: PathBuf,
        /// Worker threads (default: rayon's, i.e. RAYON_NUM_THREADS or the core count).
        #[arg(long)]
        threads: Option<usize>,
        /// Time the labelling this many times and keep the fastest.
        #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u64).range(1..))]
        repeat: u64,
        /// Seed of the fixture (subset, prototypes, noise).
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Noise norm of the noisy fixture: feature = normalize(prompt + noise · g),
        /// g ~ N(0, I/D).
        #[arg(long, default_value_t = 8.0)]
        noise: f64,
        /// Share of the vertices that carry a Gaussian in the noisy fixture.
        #[arg(long, default_value_t = 0.2)]
        fraction: f64,
        #[command(flatten)]
        params: ParamArgs,
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

#[derive(Debug, Args)]
struct ParamArgs {
    /// Shortlist: the K nearest valid Gaussian centres of each vertex.
    #[arg(long, default_value_t = DEFAULT_K)]
    k: usize,
    /// Mahalanobis gate: a Gaussian counts when d <= sigma.
    #[arg(long, default_value_t = DEFAULT_SIGMA)]
    sigma: f32,
    /// Softmax temperature of the class logits cos / T (0.01 = CLIP's own logit scale;
    /// lower values make every Gaussian vote nearly one-hot).
    #[arg(long, default_value_t = DEFAULT_TEMPERATURE)]
    temperature: f32,
    /// Smallest standard deviation of a Gaussian axis, in scene units.
    #[arg(long, default_value_t = DEFAULT_MIN_SCALE)]
    min_scale: f32,
}

impl ParamArgs {
    fn params(&self) -> Params {
        Params {
            k: self.k,
            sigma: self.sigma,
            temperature: self.temperature,
            min_scale: self.min_scale,
        }
    }
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
            transfer(&job, &params.params(), quiet)
        }
        Command::Bench {
            scannet,
            threads,
            repeat,
            seed,
            noise,
            fraction,
            params,
        } => {
            let params = params.params();
            let body = || bench(&scannet, &params, repeat, seed, noise, fraction, quiet);
            match threads {
                Some(n) => rayon_pool(n)?.install(body),
                None => body(),
            }
        }
    }
}

fn rayon_pool(threads: usize) -> Result<profuse_pq::rayon::ThreadPool, BoxError> {
    Ok(profuse_pq::rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?)
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

/// Scores and timing of one fixture under the three class sets.
struct FixtureRun {
    scores: Map<String, Value>,
    /// Fastest labelling time of the 19-class field.
    label_s: f64,
    build_s: f64,
    mean_candidates: f64,
    unlabelled: u64,
    saturated: u64,
}

fn bench(
    dir: &Path,
    params: &Params,
    repeat: u64,
    seed: u64,
    noise: f64,
    fraction: f64,
    quiet: bool,
) -> Result<Value, BoxError> {
    let show = chatty(quiet);
    let say = |m: &str| {
        if show {
            eprintln!("{m}");
        }
    };
    say("reading the ScanNet mesh");
    let (mesh, _) = scene_io::read_scannet_npy(dir)?;
    let file = dir.display().to_string();
    let truth_labelled = mesh
        .labels
        .as_ref()
        .map_or(0, |l| l.iter().filter(|x| **x != 0).count());

    let exact_cfg = OracleConfig {
        seed,
        ..OracleConfig::exact()
    };
    let sub_cfg = OracleConfig {
        fraction,
        scale_factor: OracleConfig::noisy().scale_factor,
        ..exact_cfg
    };
    let noisy_cfg = OracleConfig { noise, ..sub_cfg };

    say("exact features on every vertex");
    let exact = oracle::place_gaussians(Source::new(&file, &mesh), &exact_cfg)?;
    let exact_run = fixture(&mesh, &exact, &exact_cfg, params, repeat, "", show)?;
    drop(exact);
    say("exact features on a subset");
    let sub = oracle::place_gaussians(Source::new(&file, &mesh), &sub_cfg)?;
    let sub_run = fixture(&mesh, &sub, &sub_cfg, params, 1, "subsampled_", show)?;
    drop(sub);
    say("noisy features on a subset");
    let noisy = oracle::place_gaussians(Source::new(&file, &mesh), &noisy_cfg)?;
    let noisy_run = fixture(&mesh, &noisy, &noisy_cfg, params, repeat, "noisy_", show)?;

    let vertices = mesh.vertices.len();
    let mut out = Map::new();
    out.insert("scene".into(), json!(file));
    out.insert("vertices".into(), json!(vertices));
    out.insert("labelled_vertices".into(), json!(truth_labelled));
    out.insert("threads".into(), json!(rayon_threads()));
    out.insert("k".into(), json!(params.k));
    out.insert("sigma".into(), json!(shortest(params.sigma)));
    out.insert("temperature".into(), json!(shortest(params.temperature)));
    out.insert("exact_gaussians".into(), json!(vertices));
    out.insert("noisy_gaussians".into(), json!(noisy.gaussians.len()));
    out.insert("noisy_scale".into(), json!(noisy.scale));
    out.insert("noise".into(), json!(noise));
    out.insert("fraction".into(), json!(fraction));
    // Throughput at K: the noisy fixture, whose Gaussians overlap like a real scene's.
    out.insert(
        "vertices_per_s".into(),
        json!(vertices as f64 / noisy_run.label_s),
    );
    out.insert("label_s".into(), json!(noisy_run.label_s));
    out.insert("build_s".into(), json!(noisy_run.build_s));
    out.insert(
        "exact_vertices_per_s".into(),
        json!(vertices as f64 / exact_run.label_s),
    );
    out.insert("exact_build_s".into(), json!(exact_run.build_s));
    out.insert(
        "noisy_mean_candidates".into(),
        json!(noisy_run.mean_candidates),
    );
    out.insert("noisy_unlabelled".into(), json!(noisy_run.unlabelled));
    out.insert("noisy_saturated".into(), json!(noisy_run.saturated));
    out.insert(
        "exact_mean_candidates".into(),
        json!(exact_run.mean_candidates),
    );
    for run in [exact_run, sub_run, noisy_run] {
        out.extend(run.scores);
    }
    out.insert("peak_rss_mb".into(), json!(peak_rss_mb()));
    Ok(Value::Object(out))
}

fn fixture(
    mesh: &Mesh,
    scene: &OracleScene,
    config: &OracleConfig,
    params: &Params,
    repeat: u64,
    prefix: &str,
    show: bool,
) -> Result<FixtureRun, BoxError> {
    let truth = mesh
        .labels
        .as_ref()
        .ok_or("the ScanNet mesh has no labels")?;
    let mut scores = Map::new();
    let mut timing = None;
    for set in ScannetSet::PAPER {
        let prompts = oracle::nyu40_prompts(set.ids(), config.dim, config.seed);
        let classes = ClassSet::from_prompts(Source::new("nyu40 prototypes", &prompts))?;
        let t = Instant::now();
        let field = GaussianField::new(
            Source::new("oracle gaussians", &scene.gaussians),
            Descriptors::Features(Source::new("oracle features", &scene.features)),
            &classes,
            params,
        )?;
        let build_s = t.elapsed().as_secs_f64();
        let bar = progress(show, mesh.vertices.len() as u64, set.name());
        let mut best = f64::INFINITY;
        let mut labelling = None;
        let runs = if set == ScannetSet::Nyu19 { repeat } else { 1 };
        for _ in 0..runs {
            bar.set_position(0);
            let t = Instant::now();
            let out = field.label_vertices_with_progress(&mesh.vertices, &|n| bar.inc(n));
            best = best.min(t.elapsed().as_secs_f64());
            labelling = Some(out);
        }
        bar.finish_and_clear();
        let out = labelling.ok_or("no labelling run")?;
        let s = evaluate(&out.labels, truth, set)?;
        let name = set.name();
        scores.insert(format!("{prefix}miou{name}"), json!(s.miou));
        scores.insert(format!("{prefix}macc{name}"), json!(s.macc));
        if !prefix.is_empty() {
            scores.insert(
                format!("{prefix}descriptor_accuracy{name}"),
                json!(oracle::descriptor_accuracy(scene, &classes)),
            );
        }
        if set == ScannetSet::Nyu19 {
            timing = Some((best, build_s, out.stats));
        }
    }
    let (label_s, build_s, stats) = timing.ok_or("no 19-class run")?;
    Ok(FixtureRun {
        scores,
        label_s,
        build_s,
        mean_candidates: stats.candidates as f64 / stats.vertices.max(1) as f64,
        unlabelled: stats.vertices - stats.labelled,
        saturated: stats.saturated,
    })
}

fn progress(show: bool, len: u64, set: &str) -> ProgressBar {
    if !show {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new(len);
    if let Ok(style) = ProgressStyle::with_template("{msg} {bar:40} {pos}/{len} [{elapsed}]") {
        pb.set_style(style);
    }
    pb.set_message(format!("labelling ({set} classes)"));
    pb
}

/// An f32 parameter as the f64 of its shortest decimal form (0.01, not 0.009999999776).
fn shortest(x: f32) -> f64 {
    x.to_string().parse().unwrap_or(f64::from(x))
}

fn rayon_threads() -> usize {
    profuse_pq::rayon::current_num_threads()
}

//! `vertex-transfer bench`: the transfer on ScanNet scene0000_00 with the oracle fixture
//! (Gaussians on the mesh vertices with synthetic class features; see the vertex-transfer
//! README): mIoU / mAcc of the 19/15/10-class sets with exact features on every vertex and
//! with CLIP-like noisy features on a share of the vertices, labelling throughput, memory.

use std::path::PathBuf;
use std::time::Instant;

use profuse_formats::Mesh;
use profuse_metrics::scannet::{evaluate, ClassSet as ScannetSet};
use serde_json::{json, Map, Value};
use vertex_transfer::oracle::{self, OracleConfig, OracleScene};
use vertex_transfer::{ClassSet, Descriptors, GaussianField, Params, Source};

use crate::common::{self, Progress};
use crate::BoxError;

/// The benchmark's parameters (the `vertex-transfer bench` arguments).
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct BenchParams {
    /// ScanNet NumPy export: a directory holding *_vert_all.npy and *_sem_label_all.npy,
    /// or their prefix.
    #[arg(long, default_value = "../shared/data/scannet/scene0000_00")]
    pub scannet: PathBuf,
    /// Time the labelling this many times and keep the fastest.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u64).range(1..))]
    pub repeat: u64,
    /// Seed of the fixture (subset, prototypes, noise).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Noise norm of the noisy fixture: feature = normalize(prompt + noise · g),
    /// g ~ N(0, I/D).
    #[arg(long, default_value_t = 8.0)]
    pub noise: f64,
    /// Share of the vertices that carry a Gaussian in the noisy fixture.
    #[arg(long, default_value_t = 0.2)]
    pub fraction: f64,
    #[command(flatten)]
    pub params: Params,
}

/// One fixture's scores and timings.
struct FixtureRun {
    scores: Map<String, Value>,
    /// Fastest labelling time of the 19-class field.
    label_s: f64,
    build_s: f64,
    mean_candidates: f64,
    unlabelled: u64,
    saturated: u64,
}

/// Runs the benchmark.
pub fn run(b: &BenchParams, progress: &dyn Progress) -> Result<Value, BoxError> {
    let (dir, params, repeat, seed, noise, fraction) =
        (&b.scannet, &b.params, b.repeat, b.seed, b.noise, b.fraction);
    let say = |m: &str| progress.note(m);
    say("reading the ScanNet mesh");
    let (mesh, _) = scene_io::scannet::read_scannet_npy(dir)?;
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
    let exact_run = fixture(&mesh, &exact, &exact_cfg, params, repeat, "", progress)?;
    drop(exact);
    say("exact features on a subset");
    let sub = oracle::place_gaussians(Source::new(&file, &mesh), &sub_cfg)?;
    let sub_run = fixture(&mesh, &sub, &sub_cfg, params, 1, "subsampled_", progress)?;
    drop(sub);
    say("noisy features on a subset");
    let noisy = oracle::place_gaussians(Source::new(&file, &mesh), &noisy_cfg)?;
    let noisy_run = fixture(
        &mesh, &noisy, &noisy_cfg, params, repeat, "noisy_", progress,
    )?;

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
    out.insert("peak_rss_mb".into(), json!(common::peak_rss_mb()));
    Ok(Value::Object(out))
}

fn fixture(
    mesh: &Mesh,
    scene: &OracleScene,
    config: &OracleConfig,
    params: &Params,
    repeat: u64,
    prefix: &str,
    progress: &dyn Progress,
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
        let mut best = f64::INFINITY;
        let mut labelling = None;
        let runs = if set == ScannetSet::Nyu19 { repeat } else { 1 };
        let phase = format!("labelling ({} classes)", set.name());
        for _ in 0..runs {
            progress.start(&phase, mesh.vertices.len() as u64);
            let t = Instant::now();
            let out = field.label_vertices_with_progress(&mesh.vertices, &|n| progress.inc(n));
            best = best.min(t.elapsed().as_secs_f64());
            progress.finish();
            labelling = Some(out);
        }
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

/// An f32 parameter as the f64 of its shortest decimal form (0.01, not 0.009999999776).
fn shortest(x: f32) -> f64 {
    x.to_string().parse().unwrap_or(f64::from(x))
}

fn rayon_threads() -> usize {
    profuse_pq::rayon::current_num_threads()
}

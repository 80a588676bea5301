//! `profuse demo`: the paper's central experiment on a synthetic scene. Generates the
//! scene (synth preset + [`synth::FaultSet`]), runs the pipeline with 3D Context
//! Proposals and the `--no-proposals` baseline (Dr. Splat style: every mask registers its
//! own feature) with the same settings, and scores both against the ground truth.
//! [`crate::sweep`] repeats [`run_experiment`] over seeds and fault sets.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde_json::{json, Map, Value};

use profuse_pipeline::config::Config;
use profuse_pipeline::support::{io_err, stage_err, write_text};
use profuse_pipeline::{run, Event, Paths, Result, RunOptions, Summary};

use crate::evaluate::evaluate_run;

/// The demo's departures from `profuse run`'s defaults, so that it runs in about a minute
/// on two cores: gs-init samples 3,000 matches per reference view (the paper's 15,000 are
/// for ~1000x730 photos, 2% of their pixels; 3,000 is 4% of a 320x240 view); gs-refine runs
/// 500 iterations at half resolution (the paper refines its correspondence-initialised
/// Gaussians before registration; `run` leaves the stage off because on real photos it
/// takes minutes. On the demo scene the held-out PSNR rises 17.9 → 21.9 dB and the alpha
/// coverage 0.86 → 0.95: the triangulated Gaussians leave gaps on plain surfaces, through
/// which the top-1 renders of the grouping's votes see what lies behind); and PQ trains on
/// 16,384 vectors (64 per centroid) for 10 iterations instead of faiss's 65,536 for 25.
pub const DEMO_SETTINGS: [&str; 4] = [
    "gs_init.budget=3000",
    "gs_refine.iterations=500",
    "pq.sample=16384",
    "pq.iters=10",
];

/// The demo's configuration: the paper's defaults with [`DEMO_SETTINGS`], then the keys
/// of an optional TOML text (`(text, label)`, [`Config::with_toml`]), then `section.key=value`
/// assignments.
pub fn demo_config(toml: Option<(&str, &str)>, set: &[String]) -> Result<Config> {
    let mut config = Config::default().with_overrides(&DEMO_SETTINGS.map(String::from))?;
    if let Some((text, label)) = toml {
        config = config.with_toml(text, label)?;
    }
    config.with_overrides(set)
}

/// The outcome of one experiment: both runs and their scores.
#[derive(Debug, Clone)]
pub struct Experiment {
    /// The scene directory.
    pub scene: PathBuf,
    /// Seconds spent generating the scene (0 when it was reused).
    pub generate_s: f64,
    /// The run with 3D Context Proposals.
    pub full: Summary,
    /// The `--no-proposals` baseline run.
    pub baseline: Summary,
    /// [`evaluate_run`] of the full run.
    pub scores: BTreeMap<String, Value>,
    /// [`evaluate_run`] of the baseline.
    pub baseline_scores: BTreeMap<String, Value>,
    /// Wall-clock seconds of the experiment, generation included.
    pub wall_s: f64,
}

/// Runs the experiment on a scene directory: generates it first from `generate` when
/// given, then the pipeline with `config` and again with `fuse.no_proposals` (the same
/// other settings, sharing the geometry stage), and [`evaluate_run`] of both.
pub fn run_experiment(
    scene: &Path,
    generate: Option<&synth::Config>,
    config: &Config,
    opts: &RunOptions,
    events: &(dyn Fn(Event<'_>) + Sync),
) -> Result<Experiment> {
    let t0 = Instant::now();
    if let Some(g) = generate {
        synth::generate(g, scene).map_err(stage_err("synth"))?;
    }
    let generate_s = if generate.is_some() {
        t0.elapsed().as_secs_f64()
    } else {
        0.0
    };
    let full = run(scene, config, opts, events)?;
    let mut baseline_config = config.clone();
    baseline_config.fuse.no_proposals = true;
    let baseline = run(scene, &baseline_config, opts, events)?;
    let scores = evaluate_run(&Paths::new(scene, &full.out, false), config, &full)?;
    let baseline_scores = evaluate_run(
        &Paths::new(scene, &baseline.out, true),
        &baseline_config,
        &baseline,
    )?;
    Ok(Experiment {
        scene: scene.to_path_buf(),
        generate_s,
        full,
        baseline,
        scores,
        baseline_scores,
        wall_s: t0.elapsed().as_secs_f64(),
    })
}

/// What `profuse demo` runs.
#[derive(Debug, Clone)]
pub struct DemoOptions {
    /// Scene directory (default `<temp dir>/profuse-demo`).
    pub scene: Option<PathBuf>,
    /// Seed of the synthetic scene.
    pub seed: u64,
    /// The synth preset (the demo's is [`synth::Preset::Demo`]).
    pub preset: synth::Preset,
    /// The fault set applied on top of the preset (the demo's is
    /// [`synth::FaultSet::Default`]).
    pub faults: synth::FaultSet,
    /// The pipeline configuration (see [`demo_config`]).
    pub config: Config,
    /// Output directory and `--force` (which also regenerates the scene).
    pub run: RunOptions,
}

impl DemoOptions {
    /// The demo's defaults: seed 0, the `demo` preset, the `default` fault set, the
    /// [`DEMO_SETTINGS`].
    pub fn new(seed: u64) -> Result<DemoOptions> {
        Ok(DemoOptions {
            scene: None,
            seed,
            preset: synth::Preset::Demo,
            faults: synth::FaultSet::Default,
            config: demo_config(None, &[])?,
            run: RunOptions::default(),
        })
    }
}

/// The value of a score key (`null` when absent).
fn pick(m: &BTreeMap<String, Value>, k: &str) -> Value {
    m.get(k).cloned().unwrap_or(Value::Null)
}

/// Runs the demo and returns the JSON object `profuse demo --json` prints (also written
/// as `OUT/demo.json`). The scene is regenerated unless the same seed (and preset and
/// fault set) is already there, or with `force`. `log` gets informational messages.
pub fn run_demo(
    opts: &DemoOptions,
    events: &(dyn Fn(Event<'_>) + Sync),
    log: &dyn Fn(&str),
) -> Result<Value> {
    let scene = opts
        .scene
        .clone()
        .unwrap_or_else(|| std::env::temp_dir().join("profuse-demo"));
    let t0 = Instant::now();
    let synth_config = opts.faults.config(opts.preset, opts.seed);
    // Regenerate unless the same preset, faults and seed, made by the same synth code, are
    // already there (a rerun is then fast).
    let stamp_text = format!(
        "{} {} {} synth@{}",
        opts.seed,
        opts.preset.name(),
        opts.faults.name(),
        crate::crate_code("synth").unwrap_or("unknown")
    );
    let stamp = scene.join(".demo-seed");
    let fresh = std::fs::read_to_string(&stamp).ok().as_deref() == Some(stamp_text.as_str());
    let present = scene.join("cameras.safetensors").is_file()
        && scene.join("gt").join("scene.json").is_file();
    let generate = if opts.run.force || !fresh || !present {
        log(&format!(
            "generating the synthetic demo scene into {}",
            scene.display()
        ));
        // Stale until the scene is complete.
        match std::fs::remove_file(&stamp) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(io_err(&stamp, "cannot remove the scene stamp")(e))
            }
            _ => {}
        }
        Some(&synth_config)
    } else {
        None
    };
    let x = run_experiment(&scene, generate, &opts.config, &opts.run, events)?;
    if generate.is_some() {
        write_text(&stamp, &stamp_text)?;
    }
    let generate_s = x.generate_s;

    let (scores, base) = (&x.scores, &x.baseline_scores);
    let mut timing = Map::new();
    timing.insert("generate".into(), json!(generate_s));
    for (k, v) in &x.full.timing_s {
        timing.insert(k.clone(), json!(v));
    }
    for l in &x.baseline.stages {
        if l.stage.ends_with("_baseline") {
            timing.insert(l.stage.clone(), json!(l.seconds));
        }
    }
    timing.insert("wall".into(), json!(t0.elapsed().as_secs_f64()));
    let proposals = scores.get("proposals");
    let cluster = |k: &str| proposals.map_or(Value::Null, |p| p[k].clone());
    let overlays = x.full.out.join("query").join("overlay");
    let value = json!({
        "scene": scene,
        "out": x.full.out,
        "seed": opts.seed,
        "preset": opts.preset.name(),
        "faults": opts.faults.name(),
        "lerf_miou": pick(scores, "lerf_miou"),
        "lerf_acc25": pick(scores, "lerf_acc25"),
        "baseline_lerf_miou": pick(base, "lerf_miou"),
        "baseline_lerf_acc25": pick(base, "lerf_acc25"),
        "scannet_miou19": pick(scores, "scannet_miou19"),
        "scannet_miou15": pick(scores, "scannet_miou15"),
        "scannet_miou10": pick(scores, "scannet_miou10"),
        "baseline_scannet_miou19": pick(base, "scannet_miou19"),
        "proposals_ari": pick(scores, "proposals_ari"),
        "ari": cluster("ari"),
        "member_ari": scores
            .get("proposal_members")
            .map_or(Value::Null, |p| p["ari"].clone()),
        "purity": cluster("purity"),
        "completeness": cluster("completeness"),
        "wrong_class_pixel_share": pick(scores, "wrong_class_pixel_share"),
        "baseline_wrong_class_pixel_share": pick(base, "wrong_class_pixel_share"),
        "init_median_surface_dist_rel": pick(scores, "init_median_surface_dist_rel"),
        "timing_s": Value::Object(timing),
        "overlays": overlays,
        "metrics": scores,
        "baseline_metrics": base,
    });
    let path = x.full.out.join("demo.json");
    let bytes = serde_json::to_vec_pretty(&value).unwrap_or_default();
    profuse_formats::write_atomically(&path, |mut f| std::io::Write::write_all(&mut f, &bytes))
        .map_err(|(action, e)| io_err(&path, action)(e))?;
    Ok(value)
}

/// The demo's text report (from [`run_demo`]'s JSON).
pub fn demo_text(v: &Value) -> String {
    let num = |k: &str| {
        v[k].as_f64()
            .map_or("n/a".to_string(), |x| format!("{x:.2}"))
    };
    let pct = |k: &str| {
        v[k].as_f64()
            .map_or("n/a".to_string(), |x| format!("{:.1}%", 100.0 * x))
    };
    let t = |k: &str| {
        v["timing_s"][k]
            .as_f64()
            .map_or("n/a".to_string(), |x| format!("{x:.2} s"))
    };
    format!(
        "ProFuse demo on the synthetic scene {scene}\n\
         \n\
         3D object selection (LERF-OVS protocol, eval frames x class prompts)\n\
         \x20 ProFuse (3D Context Proposals)   mIoU {m}  Acc@0.25 {a}\n\
         \x20 --no-proposals baseline           mIoU {bm}  Acc@0.25 {ba}\n\
         Point-cloud understanding (ScanNet protocol on the labelled mesh)\n\
         \x20 mIoU 19 classes {s19}  15 classes {s15}  10 classes {s10}\n\
         Pre-registration\n\
         \x20 proposals ARI {ari}  purity {pur}  completeness {com}   Gaussians' median distance to the surface {d} of the scene extent\n\
         \x20 mask pixels registering the wrong class: ProFuse {w}, baseline {bw}\n\
         Time: geometry {tg}, semantics {ts}, indexing {ti}, total {tt} (wall {tw})\n\
         Selections over the rendered views: {ov}/<frame>/<prompt>.png",
        scene = v["scene"].as_str().unwrap_or(""),
        m = num("lerf_miou"),
        a = num("lerf_acc25"),
        bm = num("baseline_lerf_miou"),
        ba = num("baseline_lerf_acc25"),
        s19 = num("scannet_miou19"),
        s15 = num("scannet_miou15"),
        s10 = num("scannet_miou10"),
        ari = num("proposals_ari"),
        pur = num("purity"),
        com = num("completeness"),
        w = pct("wrong_class_pixel_share"),
        bw = pct("baseline_wrong_class_pixel_share"),
        d = v["init_median_surface_dist_rel"]
            .as_f64()
            .map_or("n/a".into(), |x| format!("{:.2e}", x)),
        tg = t("geometry"),
        ts = t("semantics"),
        ti = t("indexing"),
        tt = t("total"),
        tw = t("wall"),
        ov = v["overlays"].as_str().unwrap_or(""),
    )
}

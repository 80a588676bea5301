//! `profuse run`: every stage in order, each skipped when its completion record proves
//! it up to date (see [`crate::stage`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use profuse_formats::{Cameras, FileKind, Gaussians, Masks, Proposals};
use profuse_metrics::scannet::ClassSet;
use serde::Serialize;
use serde_json::{json, Value};

use crate::config::Config;
use crate::error::{io_err, stage_err, PipelineError, Result};
use crate::stage::{
    clear_stamp, code_identity, fingerprints, needs_run, write_stamp, Stamp, STAMP_VERSION,
};

/// The class sets of the ScanNet protocol the pipeline labels the mesh for, one
/// vertex-labels file each (the paper's 19, 15 and 10 NYU40 classes).
pub const SCANNET_SETS: [ClassSet; 3] = ClassSet::PAPER;

/// How to run.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// Output directory (default `SCENE/out`).
    pub out: Option<PathBuf>,
    /// Redo every stage even when up to date.
    pub force: bool,
    /// Use this proposals file (e.g. another grouping's, or the ground truth's) instead
    /// of running warp-graph: the `proposals` stage validates it against the masks and
    /// copies it to `out/proposals.safetensors`.
    pub proposals: Option<PathBuf>,
    /// Use this Gaussians file (e.g. a trained splat, or the geometry of another run of
    /// the same photos) instead of running gs-init and gs-refine: the `gaussians` stage
    /// validates it and copies its bytes to `out/gaussians.safetensors`.
    pub gaussians: Option<PathBuf>,
    /// When another run holds the output directory's lock, wait for it instead of
    /// failing with [`PipelineError::Output`] (`OutputError::Locked`).
    pub wait: bool,
    /// Stop after this stage (the later ones neither run nor are checked); `None` runs
    /// every stage. A run that stops early is not scored.
    pub until: Option<StageName>,
    /// Finish the fuse stage from these partial sums of disjoint view shards (written by
    /// [`fuse_shard`], e.g. on other machines) instead of rendering every view: the
    /// features are byte-identical to an unsharded fuse
    /// ([`profuse_fuse::job::run_merged`], which refuses shards of other inputs).
    pub fuse_partials: Vec<PathBuf>,
    /// Finish the warp-graph stage from the evidence of disjoint view-pair shards
    /// (written by [`warp_shard`]) instead of computing every view pair: the proposals
    /// are byte-identical to an unsharded warp-graph ([`warp_graph::job::run_merged`],
    /// which refuses shards of other inputs or parameters).
    pub warp_partials: Vec<PathBuf>,
}

/// Why the query stage did not run on a scene without `prompts.safetensors`.
pub const NO_PROMPTS: &str = "skipped: the scene has no prompts.safetensors, so it answers \
     clicks and example masks only (`query run --click`); `prep prompts` with a CLIP text \
     encoder adds text prompts";

/// The stages of [`run`], in order, for [`RunOptions::until`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum StageName {
    /// Triangulated Gaussians.
    GsInit,
    /// Photometric refinement (when `gs_refine.iterations` > 0).
    GsRefine,
    /// The proposals (warp-graph, or a given file).
    WarpGraph,
    /// Registration.
    Fuse,
    /// Product quantisation.
    Pq,
    /// The text queries.
    Query,
    /// The labelled mesh (when the scene has one).
    VertexTransfer,
}

impl StageName {
    /// Every stage with its command-line name.
    pub const ALL: [(StageName, &'static str); 7] = [
        (StageName::GsInit, "gs-init"),
        (StageName::GsRefine, "gs-refine"),
        (StageName::WarpGraph, "warp-graph"),
        (StageName::Fuse, "fuse"),
        (StageName::Pq, "pq"),
        (StageName::Query, "query"),
        (StageName::VertexTransfer, "vertex-transfer"),
    ];

    /// The command-line name.
    pub fn name(self) -> &'static str {
        Self::ALL
            .iter()
            .find(|(s, _)| *s == self)
            .map_or("?", |(_, n)| n)
    }
}

impl std::str::FromStr for StageName {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        Self::ALL
            .iter()
            .find(|(_, n)| *n == s)
            .map(|(stage, _)| *stage)
            .ok_or_else(|| {
                let names: Vec<&str> = Self::ALL.iter().map(|(_, n)| *n).collect();
                format!("unknown stage {s:?}; stages: {}", names.join(", "))
            })
    }
}

/// Progress of a run, for a front end to display.
#[derive(Debug, Clone)]
pub enum Event<'a> {
    /// A stage starts, and why it must run.
    Start {
        /// The stage.
        stage: &'a str,
        /// Why it runs.
        reason: &'a str,
    },
    /// Work inside the running stage: `done` of `total` units.
    Progress {
        /// Units done.
        done: u64,
        /// Units in all.
        total: u64,
    },
    /// A stage finished (ran or was up to date).
    Done {
        /// The stage.
        stage: &'a str,
        /// Whether it ran.
        ran: bool,
        /// Seconds it took (0 when up to date).
        seconds: f64,
    },
}

/// The paths of a scene directory (SPEC.md §6) and of one run's outputs.
#[derive(Debug, Clone)]
pub struct Paths {
    /// The scene directory.
    pub scene: PathBuf,
    /// The output directory.
    pub out: PathBuf,
    /// `cameras.safetensors`.
    pub cameras: PathBuf,
    /// Dense `matches.safetensors`, or sparse `sparse_matches.safetensors` when only that exists.
    pub matches: PathBuf,
    /// Whether `matches` is the sparse kind.
    pub sparse: bool,
    /// `masks.safetensors`.
    pub masks: PathBuf,
    /// `prompts.safetensors`.
    pub prompts: PathBuf,
    /// `out/gaussians.safetensors`: the Gaussians every later stage reads.
    pub gaussians: PathBuf,
    /// What gs-init writes: `gaussians` itself, or `out/gaussians_init.safetensors` when
    /// the gs-refine stage runs ([`Paths::with_refinement`]) and writes `gaussians`.
    pub gaussians_init: PathBuf,
    /// `out/proposals.safetensors`.
    pub proposals: PathBuf,
    /// `out/features[_baseline].safetensors`.
    pub features: PathBuf,
    /// `out/pq[_baseline].safetensors`.
    pub pq: PathBuf,
    /// `out/semantic_index[_baseline].safetensors` (written with `query.semantics` index
    /// or both).
    pub semantic_index: PathBuf,
    /// `out/query[_baseline]/`.
    pub query: PathBuf,
    /// Per class set of the ScanNet protocol ([`SCANNET_SETS`]), the labelling with that
    /// set's vocabulary: `out/vertex_labels_nyu<19|15|10>[_baseline].safetensors`.
    pub vertex_labels: Vec<(ClassSet, PathBuf)>,
    /// `gt/` (synthetic scenes).
    pub gt: PathBuf,
    /// Suffix of the variant's outputs (`_baseline` for `fuse.no_proposals`).
    pub suffix: &'static str,
}

impl Paths {
    /// With the gs-refine stage on, gs-init writes `out/gaussians_init.safetensors` and
    /// gs-refine writes the refined `out/gaussians.safetensors`.
    pub fn with_refinement(mut self, on: bool) -> Paths {
        if on {
            self.gaussians_init = self.out.join("gaussians_init.safetensors");
        }
        self
    }

    /// The paths for a scene, an output directory and a variant.
    pub fn new(scene: &Path, out: &Path, baseline: bool) -> Paths {
        let suffix = if baseline { "_baseline" } else { "" };
        let dense = scene.join("matches.safetensors");
        let sparse_path = scene.join("sparse_matches.safetensors");
        let sparse = !dense.is_file() && sparse_path.is_file();
        Paths {
            scene: scene.to_path_buf(),
            out: out.to_path_buf(),
            cameras: scene.join("cameras.safetensors"),
            matches: if sparse { sparse_path } else { dense },
            sparse,
            masks: scene.join("masks.safetensors"),
            prompts: scene.join("prompts.safetensors"),
            gaussians: out.join("gaussians.safetensors"),
            gaussians_init: out.join("gaussians.safetensors"),
            proposals: out.join("proposals.safetensors"),
            features: out.join(format!("features{suffix}.safetensors")),
            pq: out.join(format!("pq{suffix}.safetensors")),
            semantic_index: out.join(format!("semantic_index{suffix}.safetensors")),
            query: out.join(format!("query{suffix}")),
            vertex_labels: SCANNET_SETS
                .iter()
                .map(|&set| {
                    let name = format!("vertex_labels_nyu{}{suffix}.safetensors", set.name());
                    (set, out.join(name))
                })
                .collect(),
            gt: scene.join("gt"),
            suffix,
        }
    }

    /// `SCENE/gaussians.safetensors`, when the scene brings its geometry (`profuse
    /// prepare` writes it: refined Gaussians or the user's own splat): the run then uses
    /// it as [`RunOptions::gaussians`] instead of running gs-init and gs-refine.
    pub fn prepared_gaussians(&self) -> Option<PathBuf> {
        let p = self.scene.join("gaussians.safetensors");
        p.is_file().then_some(p)
    }

    /// LERF-style label files (`gt/label/`), when the scene has them.
    pub fn labels(&self) -> Option<PathBuf> {
        let p = self.gt.join("label");
        p.is_dir().then_some(p)
    }

    /// The labelled mesh (`gt/mesh.safetensors`), when the scene has one.
    pub fn mesh(&self) -> Option<PathBuf> {
        let p = self.gt.join("mesh.safetensors");
        p.is_file().then_some(p)
    }
}

/// One stage's line of the summary.
#[derive(Debug, Clone, Serialize)]
pub struct StageLine {
    /// The stage.
    pub stage: String,
    /// Whether it ran in this invocation.
    pub ran: bool,
    /// Why it ran, or `up to date`.
    pub reason: String,
    /// Seconds it took in this invocation, or when it last ran (up to date).
    pub seconds: f64,
    /// The stage's report (counts), when it ran.
    pub report: Value,
}

/// What a run did.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    /// The scene directory.
    #[serde(serialize_with = "profuse_formats::output::lossy_path::one")]
    pub scene: PathBuf,
    /// The output directory.
    #[serde(serialize_with = "profuse_formats::output::lossy_path::one")]
    pub out: PathBuf,
    /// Each stage in order.
    pub stages: Vec<StageLine>,
    /// The paper's Table 4 grouping: geometry (gs-init), semantics (warp-graph + fuse),
    /// indexing (pq), total (the three), plus evaluation (query, vertex-transfer) and the
    /// per-stage seconds.
    pub timing_s: BTreeMap<String, f64>,
    /// What every mask registered in this invocation's fuse stage
    /// ([`profuse_fuse::registered_mask_descriptors`]), for the wrong-class share of
    /// `profuse_experiments::evaluate::evaluate_run`; `None` when the fuse stage was up to date (then
    /// it is recomputed from the files). Not serialised.
    #[serde(skip)]
    pub registered: Option<RegisteredMasks>,
}

/// The descriptor each global mask's pixels register (`None`: nothing), shared cheaply.
#[derive(Clone)]
pub struct RegisteredMasks(pub std::sync::Arc<Vec<Option<Vec<f32>>>>);

impl std::fmt::Debug for RegisteredMasks {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let some = self.0.iter().filter(|m| m.is_some()).count();
        write!(
            f,
            "RegisteredMasks({} masks, {some} registered)",
            self.0.len()
        )
    }
}

fn check_input(stage: &'static str, path: &Path, expected: &'static str) -> Result<()> {
    if path.is_file() {
        Ok(())
    } else {
        Err(PipelineError::MissingInput {
            stage,
            path: path.display().to_string(),
            expected,
        })
    }
}

/// Where and how stages run: `out` holds the completion records (`out/.stamps/`).
pub(crate) struct Runner<'a> {
    pub(crate) out: &'a Path,
    pub(crate) force: bool,
    pub(crate) events: &'a (dyn Fn(Event<'_>) + Sync),
}

/// The workspace crate whose code a stage runs (its completion record holds that crate's
/// [`code_identity`]); `None` for a name no stage has.
pub(crate) fn stage_crate(stage: &str) -> Option<&'static str> {
    Some(match stage.strip_suffix("_baseline").unwrap_or(stage) {
        "gs-init" => "gs-init",
        "gs-refine" => "gs-refine",
        "warp-graph" => "warp-graph",
        "proposals" | "gaussians" => "profuse-formats",
        "fuse" => "profuse-fuse",
        "pq" => "profuse-pq",
        "query" => "profuse-query",
        "vertex-transfer" => "vertex-transfer",
        // `profuse prepare`'s own stages.
        "poses" | "correspondences" => "scene-io",
        "sfm" => "profuse-sfm",
        "masks" | "features" | "prompts" => "profuse-prep",
        "warps" => "warp-graph",
        _ => return None,
    })
}

/// Runs one stage unless up to date: clears its record, runs `body`, writes the record.
pub(crate) fn stage(
    r: &Runner<'_>,
    name: &str,
    params: Value,
    inputs: Vec<PathBuf>,
    outputs: Vec<PathBuf>,
    body: impl FnOnce() -> Result<Value>,
) -> Result<StageLine> {
    let (out, force, events) = (r.out, r.force, r.events);
    // A name without a crate gets the whole pipeline's identity (every crate it runs).
    let code = code_identity(stage_crate(name).unwrap_or("profuse-pipeline"));
    let reason = if force {
        Some("--force".to_string())
    } else {
        needs_run(out, name, &code, &params, &inputs, &outputs)
    };
    let Some(reason) = reason else {
        let seconds = std::fs::read(crate::stage::stamp_path(out, name))
            .ok()
            .and_then(|b| serde_json::from_slice::<Stamp>(&b).ok())
            .map_or(0.0, |s| s.seconds);
        events(Event::Done {
            stage: name,
            ran: false,
            seconds: 0.0,
        });
        return Ok(StageLine {
            stage: name.into(),
            ran: false,
            reason: "up to date".into(),
            seconds,
            report: Value::Null,
        });
    };
    clear_stamp(out, name).map_err(io_err(out, "cannot remove a completion record"))?;
    events(Event::Start {
        stage: name,
        reason: &reason,
    });
    let fingerprint_err = |(path, e): (PathBuf, std::io::Error)| PipelineError::Io {
        path: path.display().to_string(),
        action: "cannot read the file's status for the completion record",
        source: e,
    };
    // Inputs as they are before the stage reads them: a change during the run shows as a
    // difference next time.
    let inputs = fingerprints(&inputs).map_err(fingerprint_err)?;
    let t0 = Instant::now();
    let report = body()?;
    let seconds = t0.elapsed().as_secs_f64();
    let stamp = Stamp {
        version: STAMP_VERSION,
        stage: name.into(),
        params,
        code,
        inputs,
        outputs: fingerprints(&outputs).map_err(fingerprint_err)?,
        seconds,
    };
    write_stamp(out, &stamp).map_err(io_err(out, "cannot write a completion record"))?;
    events(Event::Done {
        stage: name,
        ran: true,
        seconds,
    });
    Ok(StageLine {
        stage: name.into(),
        ran: true,
        reason,
        seconds,
        report,
    })
}

pub(crate) fn to_json(v: &impl Serialize) -> Value {
    serde_json::to_value(v).unwrap_or(Value::Null)
}

/// Runs the pipeline on a scene directory: gs-init, warp-graph (skipped for the
/// `fuse.no_proposals` baseline), fuse, pq, query and, when the scene has a labelled mesh,
/// vertex-transfer. Writes `config.toml` (the effective configuration) into the output
/// directory first. The run holds the output directory's lock
/// ([`profuse_formats::output::lock_dir`]; a second run on it fails, or waits with
/// [`RunOptions::wait`]) and first removes what killed runs left there
/// ([`clean_leftovers`]).
pub fn run(
    scene: &Path,
    config: &Config,
    opts: &RunOptions,
    events: &(dyn Fn(Event<'_>) + Sync),
) -> Result<Summary> {
    config.validate()?;
    let out = opts.out.clone().unwrap_or_else(|| scene.join("out"));
    let p = Paths::new(scene, &out, config.fuse.no_proposals)
        .with_refinement(config.gs_refine.iterations > 0);
    check_input("gs-init", &p.cameras, "cameras file")?;
    let given_gaussians = opts.gaussians.clone().or_else(|| p.prepared_gaussians());
    if given_gaussians.is_none() {
        check_input(
            "gs-init",
            &p.matches,
            "matches.safetensors or sparse_matches.safetensors",
        )?;
    }
    check_input("warp-graph", &p.masks, "masks file")?;
    profuse_formats::output::check_output_dir(&out)?;
    std::fs::create_dir_all(&out).map_err(io_err(&out, "cannot create the output directory"))?;
    let _lock = profuse_formats::output::lock_dir(&out, opts.wait)?;
    clean_leftovers(&out);
    write_text(
        &out.join(format!("config{}.toml", p.suffix)),
        &config.to_toml(),
    )?;

    let runner = Runner {
        out: &out,
        force: opts.force,
        events,
    };
    let mut lines = Vec::new();
    let opts = RunOptions {
        gaussians: given_gaussians,
        ..opts.clone()
    };
    let registered = run_stages(&runner, config, &opts, &p, &mut lines)?;
    let timing_s = timing(&lines);
    Ok(Summary {
        scene: scene.to_path_buf(),
        out,
        stages: lines,
        timing_s,
        registered,
    })
}

/// The stages in order, up to [`RunOptions::until`]; returns what fuse registered when it
/// ran.
fn run_stages(
    runner: &Runner<'_>,
    config: &Config,
    opts: &RunOptions,
    p: &Paths,
    lines: &mut Vec<StageLine>,
) -> Result<Option<RegisteredMasks>> {
    let stop_after = |stage: StageName| opts.until.is_some_and(|u| u <= stage);
    if let Some(given) = &opts.gaussians {
        lines.push(given_gaussians_stage(runner, p, given)?);
    } else {
        lines.push(gs_init_stage(runner, config, p)?);
        if stop_after(StageName::GsInit) {
            return Ok(None);
        }
        if config.gs_refine.iterations > 0 {
            lines.push(gs_refine_stage(runner, config, p)?);
        }
    }
    if stop_after(StageName::GsRefine) {
        return Ok(None);
    }
    if !config.fuse.no_proposals {
        lines.push(match &opts.proposals {
            Some(given) => given_proposals_stage(runner, p, given)?,
            None => warp_graph_stage(runner, config, p, &opts.warp_partials)?,
        });
    }
    if stop_after(StageName::WarpGraph) {
        return Ok(None);
    }
    let (fuse_line, registered) = fuse_stage(runner, config, p, &opts.fuse_partials)?;
    lines.push(fuse_line);
    if stop_after(StageName::Fuse) {
        return Ok(registered);
    }
    lines.push(pq_stage(runner, config, p)?);
    if stop_after(StageName::Pq) {
        return Ok(registered);
    }
    if !p.prompts.is_file() {
        // A scene prepared without a text encoder answers clicks and example masks
        // (`query run --click`) from the pq codes; text queries need prompts.
        lines.push(StageLine {
            stage: "query".into(),
            ran: false,
            reason: NO_PROMPTS.into(),
            seconds: 0.0,
            report: Value::Null,
        });
        return Ok(registered);
    }
    lines.push(query_stage(runner, config, p)?);
    if stop_after(StageName::Query) {
        return Ok(registered);
    }
    if let Some(mesh) = p.mesh() {
        lines.push(vertex_transfer_stage(runner, config, p, &mesh)?);
    }
    Ok(registered)
}

/// One view shard of the fuse stage of a run: renders views `views` of the scene into the
/// run's Gaussians and proposals (`out_dir`, written by a run that reached warp-graph)
/// with the run's configuration, and writes the exact partial sums to `partial_out`
/// (atomically) for [`RunOptions::fuse_partials`]. Takes no lock: it reads the output
/// directory and writes only `partial_out`, so shards run in parallel, anywhere the files
/// are visible.
pub fn fuse_shard(
    scene: &Path,
    out_dir: &Path,
    config: &Config,
    views: std::ops::Range<usize>,
    partial_out: &Path,
    on_view: &mut dyn FnMut(usize),
) -> Result<profuse_fuse::job::Report> {
    config.validate()?;
    let p = Paths::new(scene, out_dir, config.fuse.no_proposals);
    check_input(
        "fuse",
        &p.gaussians,
        "gaussians of a run that reached gs-init",
    )?;
    if !config.fuse.no_proposals {
        check_input(
            "fuse",
            &p.proposals,
            "proposals of a run that reached warp-graph",
        )?;
    }
    profuse_formats::output::check_output_file(partial_out)?;
    let mut job = fuse_job(config, &p);
    job.views = Some(views);
    job.partial_out = Some(partial_out.to_path_buf());
    let run = profuse_fuse::job::run(&job, &config.fuse, &mut |v| on_view(v.view))
        .map_err(stage_err("fuse"))?;
    Ok(run.report)
}

impl Runner<'_> {
    /// Progress of the running stage: `done` of `total` units.
    pub(crate) fn progress(&self, done: usize, total: usize) {
        (self.events)(Event::Progress {
            done: done as u64,
            total: total as u64,
        })
    }
}

/// gs-init: cameras + images + matches -> gaussians.
fn gs_init_stage(r: &Runner<'_>, config: &Config, p: &Paths) -> Result<StageLine> {
    let images = image_paths(p)?;
    let mut inputs = vec![p.cameras.clone(), p.matches.clone()];
    inputs.extend(images);
    stage(
        r,
        "gs-init",
        to_json(&config.gs_init),
        inputs,
        vec![p.gaussians_init.clone()],
        || {
            let params = gs_init::Params::from(config.gs_init);
            let match_file = if p.sparse {
                gs_init::MatchFile::Sparse(p.matches.clone())
            } else {
                gs_init::MatchFile::Dense(p.matches.clone())
            };
            let job = gs_init::job::Job {
                inputs: gs_init::Inputs {
                    cameras: p.cameras.clone(),
                    images: p.scene.clone(),
                    matches: match_file,
                },
                out: p.gaussians_init.clone(),
            };
            let report = gs_init::job::run(&job, &params, &|d, t| r.progress(d, t))
                .map_err(stage_err("gs-init"))?;
            Ok(to_json(&report))
        },
    )
}

/// gs-refine: gs-init's Gaussians + cameras + photos -> refined gaussians.
fn gs_refine_stage(r: &Runner<'_>, config: &Config, p: &Paths) -> Result<StageLine> {
    let mut inputs = vec![p.gaussians_init.clone(), p.cameras.clone()];
    inputs.extend(image_paths(p)?);
    stage(
        r,
        "gs-refine",
        to_json(&config.gs_refine),
        inputs,
        vec![p.gaussians.clone()],
        || {
            let job = gs_refine::job::Job {
                gaussians: p.gaussians_init.clone(),
                cameras: p.cameras.clone(),
                images: p.scene.clone(),
                out: p.gaussians.clone(),
                exclude: Vec::new(),
                save_every: 0,
            };
            let total = config.gs_refine.iterations;
            let report = gs_refine::job::run(&job, &config.gs_refine, &mut |it, _, _| {
                r.progress(it, total)
            })
            .map_err(stage_err("gs-refine"))?;
            Ok(to_json(&report))
        },
    )
}

/// gaussians: a given Gaussians file (instead of gs-init and gs-refine) ->
/// out/gaussians, its bytes unchanged once it reads as a valid Gaussians file. Running it
/// removes the records of gs-init and gs-refine, whose output it replaces, so that they run
/// again when they are next asked for.
fn given_gaussians_stage(r: &Runner<'_>, p: &Paths, given: &Path) -> Result<StageLine> {
    stage(
        r,
        "gaussians",
        json!({ "from": given }),
        vec![given.to_path_buf()],
        vec![p.gaussians.clone()],
        || {
            for replaced in ["gs-init", "gs-refine"] {
                clear_stamp(r.out, replaced)
                    .map_err(io_err(r.out, "cannot remove a completion record"))?;
            }
            let g = Gaussians::read(given).map_err(stage_err("gaussians"))?;
            let mut src = std::fs::File::open(given)
                .map_err(io_err(given, "cannot open the given Gaussians"))?;
            profuse_formats::write_atomically(&p.gaussians, |mut f| {
                std::io::copy(&mut src, &mut f).map(|_| ())
            })
            .map_err(|(action, e)| io_err(&p.gaussians, action)(e))?;
            Ok(json!({ "from": given, "gaussians": g.len() }))
        },
    )
}

/// warp-graph: masks + matches (+ cameras, gaussians for visibility) -> proposals.
fn warp_graph_stage(
    r: &Runner<'_>,
    config: &Config,
    p: &Paths,
    partials: &[PathBuf],
) -> Result<StageLine> {
    if p.sparse {
        return Err(PipelineError::MissingInput {
            stage: "warp-graph",
            path: p.scene.join("matches.safetensors").display().to_string(),
            expected: "dense matches (warp-graph warps mask label maps; sparse matches cannot)",
        });
    }
    stage(
        r,
        "warp-graph",
        to_json(&config.warp_graph),
        vec![
            p.masks.clone(),
            p.matches.clone(),
            p.cameras.clone(),
            p.gaussians.clone(),
        ],
        vec![p.proposals.clone()],
        || {
            let job = warp_graph_job(p);
            let report = if partials.is_empty() {
                warp_graph::job::run(&job, &config.warp_graph, &|d, t| r.progress(d, t))
            } else {
                warp_graph::job::run_merged(&job, &config.warp_graph, partials)
            }
            .map_err(stage_err("warp-graph"))?;
            Ok(to_json(&report))
        },
    )
}

/// The warp-graph job of a run: its masks, matches, cameras and Gaussians.
fn warp_graph_job(p: &Paths) -> warp_graph::job::Job {
    warp_graph::job::Job {
        masks: p.masks.clone(),
        matches: p.matches.clone(),
        cameras: Some(p.cameras.clone()),
        gaussians: Some(p.gaussians.clone()),
        out: p.proposals.clone(),
    }
}

/// One view-pair shard of the warp-graph stage of a run: computes the mask-pair evidence
/// of view pairs `pairs` (of the run's list, ascending (i, j)) from the scene and the
/// run's Gaussians (`out_dir`, written by a run that reached gs-init, or gs-refine when
/// it is on) with the run's configuration, and writes it to `partial_out` (atomically)
/// for [`RunOptions::warp_partials`]. Takes no lock: shards run in parallel, anywhere the
/// files are visible. The report's `view_pairs` is the run's T.
pub fn warp_shard(
    scene: &Path,
    out_dir: &Path,
    config: &Config,
    pairs: std::ops::Range<usize>,
    partial_out: &Path,
    on_pair: &(dyn Fn(usize, usize) + Sync),
) -> Result<warp_graph::job::ShardReport> {
    config.validate()?;
    if config.fuse.no_proposals {
        return Err(PipelineError::Stage {
            stage: "warp-graph",
            source: "the configuration sets fuse.no_proposals, so a run has no warp-graph \
                     stage to shard"
                .into(),
        });
    }
    let p = Paths::new(scene, out_dir, false).with_refinement(config.gs_refine.iterations > 0);
    check_input("warp-graph", &p.masks, "masks file")?;
    check_input(
        "warp-graph",
        &p.gaussians,
        "gaussians of a run that reached gs-init (gs-refine when it is on)",
    )?;
    profuse_formats::output::check_output_file(partial_out)?;
    warp_graph::job::run_shard(
        &warp_graph_job(&p),
        &config.warp_graph,
        pairs,
        partial_out,
        on_pair,
    )
    .map_err(stage_err("warp-graph"))
}

/// proposals: a given proposals file (instead of warp-graph) -> out/proposals, after
/// checking that it has one entry per mask. Running it removes warp-graph's completion
/// record, whose output it replaces, so that warp-graph runs again when it is next asked
/// for.
fn given_proposals_stage(r: &Runner<'_>, p: &Paths, given: &Path) -> Result<StageLine> {
    stage(
        r,
        "proposals",
        json!({ "from": given }),
        vec![given.to_path_buf(), p.masks.clone()],
        vec![p.proposals.clone()],
        || {
            clear_stamp(r.out, "warp-graph")
                .map_err(io_err(r.out, "cannot remove a completion record"))?;
            let props = Proposals::read(given).map_err(stage_err("proposals"))?;
            let masks = Masks::read(&p.masks).map_err(stage_err("proposals"))?;
            if props.mask_proposal.len() != masks.num_masks() {
                return Err(PipelineError::Stage {
                    stage: "proposals",
                    source: format!(
                        "{}: mask_proposal has {} entries, expected one per mask of {} ({})",
                        given.display(),
                        props.mask_proposal.len(),
                        p.masks.display(),
                        masks.num_masks()
                    )
                    .into(),
                });
            }
            props.write(&p.proposals).map_err(stage_err("proposals"))?;
            Ok(json!({
                "from": given,
                "proposals": props.len(),
                "masks": masks.num_masks(),
            }))
        },
    )
}

/// fuse: gaussians + cameras + masks (+ proposals) -> features, and what every mask
/// registered (for the wrong-class share).
fn fuse_stage(
    r: &Runner<'_>,
    config: &Config,
    p: &Paths,
    partials: &[PathBuf],
) -> Result<(StageLine, Option<RegisteredMasks>)> {
    let fuse_name = if config.fuse.no_proposals {
        "fuse_baseline"
    } else {
        "fuse"
    };
    let mut registered = None;
    let mut fuse_inputs = vec![p.gaussians.clone(), p.cameras.clone(), p.masks.clone()];
    if !config.fuse.no_proposals {
        fuse_inputs.push(p.proposals.clone());
    }
    let line = stage(
        r,
        fuse_name,
        to_json(&config.fuse),
        fuse_inputs,
        fuse_outputs(config, p),
        || {
            let mut job = fuse_job(config, p).with_out(&p.features);
            if config.query.semantics.needs_index() {
                job.semantic_index = Some(p.semantic_index.clone());
            }
            let run = if partials.is_empty() {
                let views = Cameras::read(&p.cameras).map_or(0, |c| c.len());
                let mut done = 0;
                profuse_fuse::job::run(&job, &config.fuse, &mut |_| {
                    done += 1;
                    r.progress(done, views)
                })
            } else {
                profuse_fuse::job::run_merged(&job, &config.fuse, partials)
            }
            .map_err(stage_err("fuse"))?;
            registered = Some(RegisteredMasks(std::sync::Arc::new(
                profuse_fuse::registered_mask_descriptors(&run.partial),
            )));
            Ok(to_json(&run.report))
        },
    )?;
    Ok((line, registered))
}

/// The fuse stage's files: the features, and the semantic index when the query reads one.
fn fuse_outputs(config: &Config, p: &Paths) -> Vec<PathBuf> {
    let mut out = vec![p.features.clone()];
    if config.query.semantics.needs_index() {
        out.push(p.semantic_index.clone());
    }
    out
}

/// The per-Gaussian semantics files the query and vertex-transfer stages read.
fn semantics_files(config: &Config, p: &Paths) -> Vec<PathBuf> {
    let s = config.query.semantics;
    let mut files = Vec::new();
    if s.needs_index() {
        files.push(p.semantic_index.clone());
    }
    if s.needs_pq() {
        files.push(p.pq.clone());
    }
    files
}

/// The query's descriptors under `query.semantics`.
fn query_descriptors(config: &Config, p: &Paths) -> profuse_query::DescriptorPath {
    use profuse_query::{DescriptorPath, Semantics};
    match config.query.semantics {
        Semantics::Pq => DescriptorPath::Pq(p.pq.clone()),
        Semantics::Index => DescriptorPath::Indexed {
            index: p.semantic_index.clone(),
            fallback: None,
        },
        Semantics::Both => DescriptorPath::Indexed {
            index: p.semantic_index.clone(),
            fallback: Some(p.pq.clone()),
        },
    }
}

/// vertex-transfer's descriptors under `query.semantics`.
fn transfer_descriptors(config: &Config, p: &Paths) -> vertex_transfer::DescriptorFile {
    use vertex_transfer::DescriptorFile;
    match query_descriptors(config, p) {
        profuse_query::DescriptorPath::Indexed { index, fallback } => {
            DescriptorFile::Indexed { index, fallback }
        }
        _ => DescriptorFile::Pq(p.pq.clone()),
    }
}

/// pq: features -> pq.
fn pq_stage(r: &Runner<'_>, config: &Config, p: &Paths) -> Result<StageLine> {
    stage(
        r,
        &format!("pq{}", p.suffix),
        to_json(&config.pq),
        vec![p.features.clone()],
        vec![p.pq.clone()],
        || {
            let report = profuse_pq::job::train_file(&p.features, &p.pq, &config.pq)
                .map_err(stage_err("pq"))?;
            Ok(to_json(&report))
        },
    )
}

/// query: gaussians + cameras + pq + prompts -> masks per (view, prompt) + selections.
fn query_stage(r: &Runner<'_>, config: &Config, p: &Paths) -> Result<StageLine> {
    let prompts = query_prompts(config, p)?;
    let mut query_inputs = vec![p.gaussians.clone(), p.cameras.clone()];
    query_inputs.extend(semantics_files(config, p));
    query_inputs.push(p.prompts.clone());
    if let Some(l) = p.labels() {
        query_inputs.push(l);
    }
    stage(
        r,
        &format!("query{}", p.suffix),
        json!({ "query": to_json(&config.query), "prompts": prompts }),
        query_inputs,
        vec![p.query.clone()],
        || run_query(config, p, &prompts, &|d, t| r.progress(d, t)),
    )
}

/// vertex-transfer, when the scene has a labelled mesh (synthetic ground truth): one
/// labelling per class set of the ScanNet protocol (OpenGaussian's); the vocabulary is the
/// set's own class prompts, so each vertex takes the argmax over that set only.
fn vertex_transfer_stage(
    r: &Runner<'_>,
    config: &Config,
    p: &Paths,
    mesh: &Path,
) -> Result<StageLine> {
    let sets: Vec<&str> = p.vertex_labels.iter().map(|(s, _)| s.name()).collect();
    stage(
        r,
        &format!("vertex-transfer{}", p.suffix),
        json!({ "vertex_transfer": to_json(&config.vertex_transfer), "class_sets": sets }),
        [p.gaussians.clone()]
            .into_iter()
            .chain(semantics_files(config, p))
            .chain([p.prompts.clone(), mesh.to_path_buf()])
            .collect(),
        p.vertex_labels.iter().map(|(_, f)| f.clone()).collect(),
        || {
            let mut reports = serde_json::Map::new();
            for (set, out) in &p.vertex_labels {
                let job = vertex_transfer::Job {
                    gaussians: p.gaussians.clone(),
                    descriptors: transfer_descriptors(config, p),
                    prompts: p.prompts.clone(),
                    classes: None,
                    // NYU40 ids are 1..=40: they fit i32.
                    class_filter: Some(set.ids().iter().map(|&id| id as i32).collect()),
                    mesh: mesh.to_path_buf(),
                    out: out.clone(),
                    // The same stamp as the vertex-transfer tool, so the bytes agree.
                    generator: Some(format!("vertex-transfer {} run", env!("CARGO_PKG_VERSION"))),
                };
                let report = vertex_transfer::run_job(&job, &config.vertex_transfer)
                    .map_err(stage_err("vertex-transfer"))?;
                reports.insert(format!("nyu{}", set.name()), to_json(&report));
            }
            Ok(Value::Object(reports))
        },
    )
}

/// The fuse stage's job over every view: the proposals under the configured
/// registration, or one group per mask for `fuse.no_proposals`; it writes nothing.
pub fn fuse_job(config: &Config, p: &Paths) -> profuse_fuse::job::Job {
    let job = profuse_fuse::job::Job::new(&p.gaussians, &p.cameras, &p.masks);
    if config.fuse.no_proposals {
        job.baseline()
    } else {
        job.with_proposals(&p.proposals)
    }
}

/// The paper's Table 4 grouping of stage seconds.
fn timing(lines: &[StageLine]) -> BTreeMap<String, f64> {
    let sec = |names: &[&str]| -> f64 {
        lines
            .iter()
            .filter(|l| {
                names
                    .iter()
                    .any(|n| l.stage == *n || l.stage == format!("{n}_baseline"))
            })
            .map(|l| l.seconds)
            .sum()
    };
    let geometry = sec(&["gs-init", "gs-refine"]);
    let semantics = sec(&["warp-graph", "fuse"]);
    let indexing = sec(&["pq"]);
    let mut t = BTreeMap::new();
    t.insert("geometry".into(), geometry);
    t.insert("semantics".into(), semantics);
    t.insert("indexing".into(), indexing);
    t.insert("total".into(), geometry + semantics + indexing);
    t.insert("evaluation".into(), sec(&["query", "vertex-transfer"]));
    for l in lines {
        t.insert(l.stage.clone(), l.seconds);
    }
    t
}

/// Every image of the cameras file (gs-init reads reference views' images).
pub fn image_paths(p: &Paths) -> Result<Vec<PathBuf>> {
    let cams = Cameras::read(&p.cameras).map_err(stage_err("gs-init"))?;
    Ok(cams.image_names.iter().map(|n| p.scene.join(n)).collect())
}

/// The prompts to query: the configured ones, else the categories of the LERF label files
/// that the prompts file has, else every class prompt.
fn query_prompts(config: &Config, p: &Paths) -> Result<Vec<String>> {
    if !config.query.prompts.is_empty() {
        return Ok(config.query.prompts.clone());
    }
    let prompts = profuse_formats::Prompts::read(&p.prompts).map_err(stage_err("query"))?;
    if let Some(dir) = p.labels() {
        let scene = profuse_metrics::lerf::read_label_dir(&dir).map_err(stage_err("query"))?;
        let mut cats: Vec<String> = scene
            .frames
            .iter()
            .flat_map(|f| f.objects.iter().map(|o| o.category.clone()))
            .filter(|c| prompts.names.contains(c))
            .collect();
        cats.sort();
        cats.dedup();
        return Ok(cats);
    }
    Ok(match &prompts.class_ids {
        Some(ids) => prompts
            .names
            .iter()
            .zip(ids.iter())
            .filter(|(_, id)| **id >= 0)
            .map(|(n, _)| n.clone())
            .collect(),
        None => prompts
            .names
            .iter()
            .filter(|n| !profuse_formats::label_space::CANONICAL_NEGATIVES.contains(&n.as_str()))
            .cloned()
            .collect(),
    })
}

/// The query stage: the LERF layout over the labelled frames when the scene has labels,
/// else the per-prompt layout over every view; written to a uniquely named temporary
/// directory swapped into place at the end (`Plan::run_replacing`), so an interrupted
/// query leaves no partial folder behind.
fn run_query(
    config: &Config,
    p: &Paths,
    prompts: &[String],
    progress: &dyn Fn(usize, usize),
) -> Result<Value> {
    let q = &config.query;
    let inputs = profuse_query::Inputs::load(
        &p.gaussians,
        &p.cameras,
        &query_descriptors(config, p),
        &p.prompts,
    )
    .map_err(stage_err("query"))?;
    let score = q.score;
    let (views, layout) = match p.labels() {
        Some(dir) => (
            profuse_query::ViewSelection::FromLabels(dir),
            profuse_query::Layout::Lerf,
        ),
        None => (
            profuse_query::ViewSelection::All,
            profuse_query::Layout::Prompt,
        ),
    };
    let options = profuse_query::QueryOptions {
        prompts: profuse_query::PromptSelection::Names(prompts.to_vec()),
        score,
        rule: Some(profuse_query::Rule::Threshold(q.threshold)),
        gamma: q.gamma,
        k: q.k,
        scale: None,
        views,
        layout,
        overlay: q.overlay,
    };
    let plan = inputs.plan(&options).map_err(stage_err("query"))?;
    let report = plan
        .run_replacing(&inputs.gaussians, &p.query, &mut |d, t| progress(d, t))
        .map_err(stage_err("query"))?;
    Ok(to_json(&report))
}

/// Removes what killed runs left in the output directory (the caller holds its lock, so
/// every unclaimed `.profuse-tmp-*` there is a leftover): temporary files and
/// directories in `out/` and `out/.stamps/`, and the fixed temporary names of earlier
/// versions (`.query.tmp`, `.query_baseline.tmp`, `.stamps/.<stage>.tmp`).
fn clean_leftovers(out: &Path) {
    use profuse_formats::output::clean_leftovers as clean;
    let stamps = out.join(".stamps");
    clean(out, std::time::Duration::ZERO);
    clean(&stamps, std::time::Duration::ZERO);
    for legacy in [".query.tmp", ".query_baseline.tmp"] {
        let _ = std::fs::remove_dir_all(out.join(legacy));
    }
    for entry in std::fs::read_dir(&stamps).into_iter().flatten().flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') && name.ends_with(".tmp") {
            let _ = std::fs::remove_file(entry.path());
        }
    }
}

/// Writes a text file atomically.
pub fn write_text(path: &Path, text: &str) -> Result<()> {
    use std::io::Write;
    profuse_formats::write_atomically(path, |mut f| f.write_all(text.as_bytes()))
        .map_err(|(action, e)| io_err(path, action)(e))
}

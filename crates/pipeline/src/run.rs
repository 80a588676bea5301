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

mod paths;
mod stages;

pub use paths::Paths;
use stages::*;
pub use stages::{fuse_job, warp_shard};

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

/// What would fail only at the pq or query stage, checked before any stage runs: PQ's
/// sub-quantisers must divide the masks' descriptor dimension, and the prompts (when the
/// scene has them) must live in the same space as the masks' descriptors.
fn check_dimensions(p: &Paths, config: &Config) -> Result<()> {
    use profuse_formats::{FileKind, Masks, Prompts};
    let masks = Masks::read(&p.masks).map_err(stage_err("warp-graph"))?;
    let m = config.pq.m;
    if !masks.dim.is_multiple_of(m) {
        return Err(PipelineError::Config {
            key: "pq.m".into(),
            detail: format!(
                "{m} does not divide the dimension {} of the descriptors in {} (choose a \
                 divisor, e.g. --set pq.m={})",
                masks.dim,
                p.masks.display(),
                largest_divisor_up_to(masks.dim, m)
            ),
        });
    }
    if p.prompts.is_file() {
        let prompts = Prompts::read(&p.prompts).map_err(stage_err("query"))?;
        if prompts.dim != masks.dim {
            return Err(PipelineError::Config {
                key: "prompts".into(),
                detail: format!(
                    "{} holds {}-d embeddings but the descriptors of {} are {}-d: the prompts \
                     of another encoder or scene?",
                    p.prompts.display(),
                    prompts.dim,
                    p.masks.display(),
                    masks.dim
                ),
            });
        }
    }
    Ok(())
}

/// The largest divisor of `n` that is at most `cap` (at least 1).
fn largest_divisor_up_to(n: usize, cap: usize) -> usize {
    (1..=cap.min(n).max(1))
        .rev()
        .find(|d| n.is_multiple_of(*d))
        .unwrap_or(1)
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
    check_dimensions(&p, config)?;
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

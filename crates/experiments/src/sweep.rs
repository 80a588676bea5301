//! `profuse sweep`: the accuracy harness of the paper's central claim — 3D Context
//! Proposals against the `--no-proposals` baseline (every mask registers its own feature,
//! Dr. Splat style) — over many synthetic seeds and fault models ([`synth::FaultSet`]).
//!
//! For every (fault set, seed), fault set outer and seed inner, [`sweep`] generates the
//! synth scene into its own directory, runs [`crate::demo::run_experiment`] (both
//! variants with the same configuration, by default the demo's), and collects one
//! [`SweepRow`]; rows run one after the other (each run is parallel inside), so a row's
//! numbers equal `profuse demo --seed S --faults F --json` for the same settings. The
//! [`SweepSummary`] averages the rows, overall and per fault set.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;
use serde_json::Value;

use profuse_formats::{FileKind, Masks};
use profuse_pipeline::config::Config;
use profuse_pipeline::fnv::Fnv;
use profuse_pipeline::support::{image_paths, io_err, stage_err};
use profuse_pipeline::{run, Paths, PipelineError, Result, RunOptions};

use crate::demo::{run_experiment, Experiment};
use crate::evaluate::evaluate_run;

/// What to sweep.
#[derive(Debug, Clone)]
pub struct SweepOptions {
    /// Seeds, in order.
    pub seeds: Vec<u64>,
    /// Fault sets, in order (the outer loop).
    pub faults: Vec<synth::FaultSet>,
    /// The synth preset of every scene.
    pub preset: synth::Preset,
    /// Parent of the scene directories `<faults>-seed<S>` (default: a fresh
    /// `<temp dir>/profuse-sweep-<pid>`, removed at the end unless `keep`).
    pub out: Option<PathBuf>,
    /// Keep every scene directory (with its `out/`) instead of removing it after its row.
    pub keep: bool,
    /// The pipeline configuration of both variants (`fuse.no_proposals` is set for the
    /// baseline).
    pub config: Config,
    /// Also run every row with the ground-truth proposals ([`run_oracle`]): the ceiling
    /// of proposal pooling, which no grouping can beat with the same registration.
    pub oracle: bool,
}

/// One (seed, fault set): scores of ProFuse and of the baseline. Scores in percent where
/// the paper uses percent (LERF, ScanNet), fractions otherwise.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SweepRow {
    /// The seed.
    pub seed: u64,
    /// The fault set's name.
    pub faults: String,
    /// LERF-OVS selection mIoU with proposals.
    pub lerf_miou: f64,
    /// The same for the baseline.
    pub baseline_lerf_miou: f64,
    /// LERF-OVS Acc@0.25 with proposals.
    pub lerf_acc25: f64,
    /// The same for the baseline.
    pub baseline_lerf_acc25: f64,
    /// ScanNet-protocol mIoU over the 19 classes with proposals.
    pub scannet_miou19: f64,
    /// The same for the baseline.
    pub baseline_scannet_miou19: f64,
    /// Adjusted Rand index of the proposals' object instances (members and attached
    /// masks) against the masks' objects.
    pub ari: f64,
    /// The same for the members alone (the masks pooled into each proposal).
    pub member_ari: f64,
    /// Purity of the proposals.
    pub purity: f64,
    /// Completeness of the proposals.
    pub completeness: f64,
    /// Share of mask pixels whose registered descriptor names the wrong class
    /// ([`profuse_metrics::wrong_class`]), with proposals.
    pub wrong_class_pixel_share: f64,
    /// The same for the baseline.
    pub baseline_wrong_class_pixel_share: f64,
    /// LERF mIoU with the ground-truth proposals (`--oracle` only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub oracle_lerf_miou: Option<f64>,
    /// ScanNet mIoU19 with the ground-truth proposals (`--oracle` only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub oracle_scannet_miou19: Option<f64>,
    /// Whether the row's Gaussians were an earlier row's (the same photos, cameras and
    /// matches under the same gs-init and gs-refine settings: [`GeometryCache`]) instead of
    /// being computed again.
    pub geometry_reused: bool,
    /// Wall-clock seconds of the row (generation, both runs, evaluation, and the
    /// ground-truth proposals' run with `--oracle`).
    pub seconds: f64,
}

impl SweepRow {
    /// ProFuse's LERF mIoU minus the baseline's.
    pub fn delta_lerf_miou(&self) -> f64 {
        self.lerf_miou - self.baseline_lerf_miou
    }

    /// ProFuse's ScanNet mIoU (19 classes) minus the baseline's.
    pub fn delta_scannet_miou19(&self) -> f64 {
        self.scannet_miou19 - self.baseline_scannet_miou19
    }

    /// The row of an experiment; every score must be present (synthetic scenes have the
    /// ground truth of each).
    pub fn from_experiment(seed: u64, faults: &str, x: &Experiment) -> Result<SweepRow> {
        let get = |m: &BTreeMap<String, Value>, key: &'static str, variant: &str| {
            score(m, key, &x.scene, variant)
        };
        let (s, b) = (&x.scores, &x.baseline_scores);
        let cluster = |key: &'static str| {
            s.get("proposals")
                .and_then(|p| p.get(key))
                .and_then(Value::as_f64)
                .ok_or_else(|| missing(&x.scene, "proposals", key))
        };
        Ok(SweepRow {
            seed,
            faults: faults.to_string(),
            lerf_miou: get(s, "lerf_miou", "proposals")?,
            baseline_lerf_miou: get(b, "lerf_miou", "baseline")?,
            lerf_acc25: get(s, "lerf_acc25", "proposals")?,
            baseline_lerf_acc25: get(b, "lerf_acc25", "baseline")?,
            scannet_miou19: get(s, "scannet_miou19", "proposals")?,
            baseline_scannet_miou19: get(b, "scannet_miou19", "baseline")?,
            ari: cluster("ari")?,
            member_ari: s
                .get("proposal_members")
                .and_then(|p| p.get("ari"))
                .and_then(Value::as_f64)
                .ok_or_else(|| missing(&x.scene, "proposal_members", "ari"))?,
            purity: cluster("purity")?,
            completeness: cluster("completeness")?,
            wrong_class_pixel_share: get(s, "wrong_class_pixel_share", "proposals")?,
            baseline_wrong_class_pixel_share: get(b, "wrong_class_pixel_share", "baseline")?,
            oracle_lerf_miou: None,
            oracle_scannet_miou19: None,
            geometry_reused: false,
            seconds: x.wall_s,
        })
    }

    /// Adds the scores of the ground-truth proposals' run ([`run_oracle`]).
    pub fn with_oracle(
        mut self,
        scene: &Path,
        scores: &BTreeMap<String, Value>,
    ) -> Result<SweepRow> {
        let get = |key: &'static str| score(scores, key, scene, "ground-truth proposals");
        self.oracle_lerf_miou = Some(get("lerf_miou")?);
        self.oracle_scannet_miou19 = Some(get("scannet_miou19")?);
        Ok(self)
    }

    /// LERF mIoU of the ground-truth proposals minus the baseline's.
    pub fn delta_oracle_lerf_miou(&self) -> Option<f64> {
        self.oracle_lerf_miou.map(|m| m - self.baseline_lerf_miou)
    }

    /// ScanNet mIoU19 of the ground-truth proposals minus the baseline's.
    pub fn delta_oracle_scannet_miou19(&self) -> Option<f64> {
        self.oracle_scannet_miou19
            .map(|m| m - self.baseline_scannet_miou19)
    }
}

/// Runs the pipeline on a generated scene with its ground-truth proposals
/// ([`profuse_metrics::cluster::oracle_proposals`] of `gt/mask_objects.json`) given to the
/// `proposals` stage instead of warp-graph, into `SCENE/out_oracle`, and scores it. With
/// `gaussians` (e.g. the row's own run's), that file is the run's geometry instead of a
/// second gs-init and gs-refine.
pub fn run_oracle(
    scene: &Path,
    config: &Config,
    gaussians: Option<&Path>,
) -> Result<BTreeMap<String, Value>> {
    let out = scene.join("out_oracle");
    std::fs::create_dir_all(&out).map_err(io_err(&out, "cannot create the output directory"))?;
    let truth = profuse_metrics::cluster::read_mask_objects(scene.join("gt/mask_objects.json"))
        .map_err(stage_err("oracle"))?;
    let masks = Masks::read(scene.join("masks.safetensors")).map_err(stage_err("oracle"))?;
    let views: Vec<u32> = (0..masks.num_masks())
        .map(|m| masks.view_of(m) as u32)
        .collect();
    let given = out.join("ground_truth_proposals.safetensors");
    profuse_metrics::cluster::oracle_proposals(&truth, &views)
        .map_err(stage_err("oracle"))?
        .write(&given)
        .map_err(stage_err("oracle"))?;
    let opts = RunOptions {
        out: Some(out),
        force: false,
        proposals: Some(given),
        gaussians: gaussians.map(Path::to_path_buf),
        ..RunOptions::default()
    };
    let summary = run(scene, config, &opts, &|_| {})?;
    evaluate_run(&Paths::new(scene, &summary.out, false), config, &summary)
}

/// Score `key` of a variant's scores; its absence is an error naming the scene.
fn score(scores: &BTreeMap<String, Value>, key: &str, scene: &Path, variant: &str) -> Result<f64> {
    scores
        .get(key)
        .and_then(Value::as_f64)
        .ok_or_else(|| missing(scene, variant, key))
}

fn missing(scene: &Path, variant: &str, key: &str) -> PipelineError {
    PipelineError::Stage {
        stage: "sweep",
        source: format!(
            "{}: no `{key}` score for the {variant} run (the scene lacks that ground truth)",
            scene.display()
        )
        .into(),
    }
}

/// Means over a set of rows.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SweepMeans {
    /// Mean of ProFuse's LERF mIoU minus the baseline's.
    pub mean_delta_lerf_miou: f64,
    /// Smallest such difference (the worst row for ProFuse).
    pub min_delta_lerf_miou: f64,
    /// Rows where ProFuse's LERF mIoU beats the baseline's.
    pub rows_ahead_lerf_miou: usize,
    /// Mean of ProFuse's ScanNet mIoU (19 classes) minus the baseline's.
    pub mean_delta_scannet_miou19: f64,
    /// Mean proposal ARI (object instances).
    pub mean_ari: f64,
    /// Mean ARI of the proposals' members alone.
    pub mean_member_ari: f64,
    /// Mean proposal purity.
    pub mean_purity: f64,
    /// Mean proposal completeness.
    pub mean_completeness: f64,
    /// Mean wrong-class pixel share with proposals.
    pub mean_wrong_class_pixel_share: f64,
    /// Mean wrong-class pixel share of the baseline.
    pub mean_baseline_wrong_class_pixel_share: f64,
    /// Mean LERF mIoU of the ground-truth proposals minus the baseline's (`--oracle`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mean_delta_oracle_lerf_miou: Option<f64>,
    /// Mean ScanNet mIoU19 of the ground-truth proposals minus the baseline's (`--oracle`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mean_delta_oracle_scannet_miou19: Option<f64>,
    /// Rows averaged.
    pub rows: usize,
}

impl SweepMeans {
    /// The means of `rows` (arithmetic, in row order; NaN fields of an empty set are 0).
    pub fn of<'a>(rows: impl IntoIterator<Item = &'a SweepRow>) -> SweepMeans {
        let rows: Vec<&SweepRow> = rows.into_iter().collect();
        let mean = |f: &dyn Fn(&SweepRow) -> f64| {
            if rows.is_empty() {
                0.0
            } else {
                rows.iter().map(|r| f(r)).sum::<f64>() / rows.len() as f64
            }
        };
        SweepMeans {
            mean_delta_lerf_miou: mean(&SweepRow::delta_lerf_miou),
            min_delta_lerf_miou: rows
                .iter()
                .map(|r| r.delta_lerf_miou())
                .reduce(f64::min)
                .unwrap_or(0.0),
            rows_ahead_lerf_miou: rows.iter().filter(|r| r.delta_lerf_miou() > 0.0).count(),
            mean_delta_scannet_miou19: mean(&SweepRow::delta_scannet_miou19),
            mean_ari: mean(&|r| r.ari),
            mean_member_ari: mean(&|r| r.member_ari),
            mean_purity: mean(&|r| r.purity),
            mean_completeness: mean(&|r| r.completeness),
            mean_wrong_class_pixel_share: mean(&|r| r.wrong_class_pixel_share),
            mean_baseline_wrong_class_pixel_share: mean(&|r| r.baseline_wrong_class_pixel_share),
            mean_delta_oracle_lerf_miou: mean_of_all(&rows, SweepRow::delta_oracle_lerf_miou),
            mean_delta_oracle_scannet_miou19: mean_of_all(
                &rows,
                SweepRow::delta_oracle_scannet_miou19,
            ),
            rows: rows.len(),
        }
    }
}

/// The mean of `f` over `rows` when every row has it (and there is a row).
fn mean_of_all(rows: &[&SweepRow], f: impl Fn(&SweepRow) -> Option<f64>) -> Option<f64> {
    let values: Option<Vec<f64>> = rows.iter().map(|r| f(r)).collect();
    values
        .filter(|v| !v.is_empty())
        .map(|v| v.iter().sum::<f64>() / v.len() as f64)
}

/// The summary of a sweep: the means over every row, the same per fault set, and the
/// total wall-clock seconds.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SweepSummary {
    /// Means over every row.
    #[serde(flatten)]
    pub all: SweepMeans,
    /// Means per fault set (by name).
    pub by_faults: BTreeMap<String, SweepMeans>,
    /// Wall-clock seconds of the whole sweep.
    pub seconds: f64,
}

/// What `profuse sweep --json` prints.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SweepReport {
    /// One row per (fault set, seed), fault set outer.
    pub rows: Vec<SweepRow>,
    /// Means.
    pub summary: SweepSummary,
}

impl SweepReport {
    /// The report of `rows` that took `seconds`.
    pub fn new(rows: Vec<SweepRow>, seconds: f64) -> SweepReport {
        let mut names: Vec<&str> = rows.iter().map(|r| r.faults.as_str()).collect();
        names.sort_unstable();
        names.dedup();
        let by_faults = names
            .iter()
            .map(|n| {
                (
                    n.to_string(),
                    SweepMeans::of(rows.iter().filter(|r| r.faults == *n)),
                )
            })
            .collect();
        SweepReport {
            summary: SweepSummary {
                all: SweepMeans::of(&rows),
                by_faults,
                seconds,
            },
            rows,
        }
    }
}

/// Progress of a sweep.
#[derive(Debug, Clone)]
pub enum SweepEvent<'a> {
    /// Row `index` (1-based) of `total` starts.
    RowStart {
        /// 1-based row number.
        index: usize,
        /// Rows in all.
        total: usize,
        /// Its seed.
        seed: u64,
        /// Its fault set.
        faults: &'a str,
        /// Seconds since the sweep started.
        elapsed: f64,
    },
    /// Row `index` is done.
    RowDone {
        /// 1-based row number.
        index: usize,
        /// Rows in all.
        total: usize,
        /// The row.
        row: &'a SweepRow,
        /// Seconds since the sweep started.
        elapsed: f64,
    },
}

impl SweepEvent<'_> {
    /// The progress line of the event.
    pub fn line(&self) -> String {
        match self {
            SweepEvent::RowStart {
                index,
                total,
                seed,
                faults,
                elapsed,
            } => format!("row {index}/{total}: seed {seed}, faults {faults} ({elapsed:.0} s elapsed)"),
            SweepEvent::RowDone {
                index,
                total,
                row,
                elapsed,
            } => format!(
                "row {index}/{total} done in {:.1} s: LERF mIoU {:.2} vs {:.2} ({elapsed:.0} s elapsed)",
                row.seconds, row.lerf_miou, row.baseline_lerf_miou
            ),
        }
    }
}

fn list_err(list: &str, detail: String) -> PipelineError {
    PipelineError::Config {
        key: format!("list {list:?}"),
        detail,
    }
}

/// Parses a seed list: comma-separated seeds and inclusive ranges, e.g. `0-15`, `0,3,7`,
/// `0-3,9`. Seeds must be distinct.
pub fn parse_seeds(list: &str) -> Result<Vec<u64>> {
    let mut seeds = Vec::new();
    for part in list.split(',').map(str::trim) {
        let number = |s: &str| {
            s.trim()
                .parse::<u64>()
                .map_err(|e| list_err(list, format!("{s:?} is not a seed: {e}")))
        };
        match part.split_once('-') {
            Some((a, b)) => {
                let (a, b) = (number(a)?, number(b)?);
                if a > b {
                    return Err(list_err(list, format!("range {part:?} is empty")));
                }
                if b - a >= 1_000_000 {
                    return Err(list_err(list, format!("range {part:?} is too long")));
                }
                seeds.extend(a..=b);
            }
            None => seeds.push(number(part)?),
        }
    }
    let mut sorted = seeds.clone();
    sorted.sort_unstable();
    if let Some(w) = sorted.windows(2).find(|w| w[0] == w[1]) {
        return Err(list_err(list, format!("seed {} appears twice", w[0])));
    }
    Ok(seeds)
}

/// Parses a comma-separated list of fault-set names ([`synth::FaultSet::NAMES`]),
/// distinct.
pub fn parse_fault_sets(list: &str) -> Result<Vec<synth::FaultSet>> {
    let mut sets = Vec::new();
    for name in list.split(',').map(str::trim) {
        let set = synth::FaultSet::parse(name).map_err(|e| list_err(list, e.to_string()))?;
        if sets.contains(&set) {
            return Err(list_err(list, format!("{name} appears twice")));
        }
        sets.push(set);
    }
    Ok(sets)
}

fn remove_dir(dir: &Path) -> Result<()> {
    match std::fs::remove_dir_all(dir) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            Err(io_err(dir, "cannot remove a scene directory")(e))
        }
        _ => Ok(()),
    }
}

/// The Gaussians of the rows run so far, by what determines them: rows of one seed whose
/// fault sets change only masks and features (`default`, `noisy-features`,
/// `harsh-segmentation`) have byte-identical photos, cameras and matches, so gs-init and
/// gs-refine would compute byte-identical Gaussians again; the later rows take the first
/// one's through [`RunOptions::gaussians`] instead (the stages being deterministic, their
/// rows do not change by a bit). Files live in `DIR/.geometry/` and go with the sweep.
#[derive(Debug)]
pub struct GeometryCache {
    dir: PathBuf,
    known: BTreeMap<u64, PathBuf>,
}

impl GeometryCache {
    /// An empty cache whose files go under `parent/.geometry`.
    pub fn new(parent: &Path) -> GeometryCache {
        GeometryCache {
            dir: parent.join(".geometry"),
            known: BTreeMap::new(),
        }
    }

    /// The key of a scene's geometry: FNV-1a over the gs-init and gs-refine settings and
    /// the bytes of the cameras, the matches and every photo the cameras name.
    pub fn key(scene: &Path, config: &Config) -> Result<u64> {
        let p = Paths::new(scene, &scene.join("out"), false);
        let settings = format!(
            "{}\0{}\0",
            serde_json::to_string(&config.gs_init).unwrap_or_default(),
            serde_json::to_string(&config.gs_refine).unwrap_or_default()
        );
        let mut hash = Fnv::new().bytes(settings.as_bytes());
        let mut files = vec![p.cameras.clone(), p.matches.clone()];
        files.extend(image_paths(&p)?);
        for f in files {
            let bytes = std::fs::read(&f).map_err(io_err(&f, "cannot read a geometry input"))?;
            hash = hash
                .bytes(
                    f.strip_prefix(scene)
                        .unwrap_or(&f)
                        .as_os_str()
                        .as_encoded_bytes(),
                )
                .bytes(&(bytes.len() as u64).to_le_bytes())
                .bytes(&bytes);
        }
        Ok(hash.0)
    }

    /// The Gaussians stored under `key`, if any.
    pub fn get(&self, key: u64) -> Option<&Path> {
        self.known.get(&key).map(PathBuf::as_path)
    }

    /// Stores a copy of `gaussians` under `key`.
    pub fn insert(&mut self, key: u64, gaussians: &Path) -> Result<()> {
        std::fs::create_dir_all(&self.dir)
            .map_err(io_err(&self.dir, "cannot create the geometry cache"))?;
        let kept = self.dir.join(format!("{key:016x}.safetensors"));
        std::fs::copy(gaussians, &kept).map_err(io_err(&kept, "cannot keep a row's Gaussians"))?;
        self.known.insert(key, kept);
        Ok(())
    }

    /// Removes the stored files.
    pub fn remove(self) -> Result<()> {
        remove_dir(&self.dir)
    }
}

/// The directory of one row's scene under the sweep's parent directory.
pub fn row_dir(parent: &Path, faults: synth::FaultSet, seed: u64) -> PathBuf {
    parent.join(format!("{}-seed{seed}", faults.name()))
}

/// The sweep's parent directory: `opts.out`, or `<temp dir>/profuse-sweep-<pid>`.
pub fn parent_dir(opts: &SweepOptions) -> PathBuf {
    opts.out.clone().unwrap_or_else(|| {
        std::env::temp_dir().join(format!("profuse-sweep-{}", std::process::id()))
    })
}

/// Runs the sweep (see the module documentation). A row's directory is emptied before its
/// scene is generated and removed after its row unless `keep`; the default temporary
/// parent is removed at the end unless `keep`. With `out`, the report is also written to
/// `OUT/sweep.json`.
pub fn sweep(opts: &SweepOptions, events: &dyn Fn(SweepEvent<'_>)) -> Result<SweepReport> {
    if opts.seeds.is_empty() || opts.faults.is_empty() {
        return Err(PipelineError::Config {
            key: "sweep".into(),
            detail: "no seeds or no fault sets".into(),
        });
    }
    opts.config.validate()?;
    let t0 = Instant::now();
    let parent = parent_dir(opts);
    std::fs::create_dir_all(&parent)
        .map_err(io_err(&parent, "cannot create the sweep directory"))?;
    let total = opts.seeds.len() * opts.faults.len();
    let mut rows = Vec::with_capacity(total);
    let mut geometry = GeometryCache::new(&parent);
    let result: Result<()> = (|| {
        for &faults in &opts.faults {
            for &seed in &opts.seeds {
                let index = rows.len() + 1;
                events(SweepEvent::RowStart {
                    index,
                    total,
                    seed,
                    faults: faults.name(),
                    elapsed: t0.elapsed().as_secs_f64(),
                });
                let dir = row_dir(&parent, faults, seed);
                remove_dir(&dir)?;
                let synth_config = faults.config(opts.preset, seed);
                let t_row = Instant::now();
                synth::generate(&synth_config, &dir).map_err(stage_err("synth"))?;
                let key = GeometryCache::key(&dir, &opts.config)?;
                let run_opts = RunOptions {
                    gaussians: geometry.get(key).map(Path::to_path_buf),
                    ..RunOptions::default()
                };
                let x = run_experiment(&dir, None, &opts.config, &run_opts, &|_| {})?;
                let gaussians = x.full.out.join("gaussians.safetensors");
                if run_opts.gaussians.is_none() {
                    geometry.insert(key, &gaussians)?;
                }
                let mut row = SweepRow::from_experiment(seed, faults.name(), &x)?;
                row.geometry_reused = run_opts.gaussians.is_some();
                if opts.oracle {
                    let oracle = run_oracle(&dir, &opts.config, Some(&gaussians))?;
                    row = row.with_oracle(&dir, &oracle)?;
                }
                row.seconds = t_row.elapsed().as_secs_f64();
                if !opts.keep {
                    remove_dir(&dir)?;
                }
                events(SweepEvent::RowDone {
                    index,
                    total,
                    row: &row,
                    elapsed: t0.elapsed().as_secs_f64(),
                });
                rows.push(row);
            }
        }
        Ok(())
    })();
    let removed = geometry.remove();
    if opts.out.is_none() && !opts.keep {
        remove_dir(&parent)?;
    }
    result?;
    removed?;
    let report = SweepReport::new(rows, t0.elapsed().as_secs_f64());
    if let Some(out) = &opts.out {
        let path = out.join("sweep.json");
        let bytes = serde_json::to_vec_pretty(&report).unwrap_or_default();
        profuse_formats::write_atomically(&path, |mut f| std::io::Write::write_all(&mut f, &bytes))
            .map_err(|(action, e)| io_err(&path, action)(e))?;
    }
    Ok(report)
}

/// The text table of a report: one line per row, then the means overall and per fault
/// set. Δ = ProFuse − baseline; "wrong px" is the wrong-class pixel share in percent.
pub fn text_table(r: &SweepReport) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{:>5} {:<19} {:>21} {:>6} {:>13} {:>13} {:>5} {:>6} {:>6} {:>13}",
        "seed",
        "faults",
        "LERF mIoU PF / base",
        "Δ",
        "Acc@.25 PF/b",
        "mIoU19 PF/b",
        "ARI",
        "purity",
        "compl.",
        "wrong px PF/b"
    );
    for row in &r.rows {
        let _ = writeln!(
            s,
            "{:>5} {:<19} {:>10.2} / {:>8.2} {:>+6.2} {:>6.1}/{:<6.1} {:>6.2}/{:<6.2} {:>5.3} {:>6.3} {:>6.3} {:>6.1}/{:.1}",
            row.seed,
            row.faults,
            row.lerf_miou,
            row.baseline_lerf_miou,
            row.delta_lerf_miou(),
            row.lerf_acc25,
            row.baseline_lerf_acc25,
            row.scannet_miou19,
            row.baseline_scannet_miou19,
            row.ari,
            row.purity,
            row.completeness,
            100.0 * row.wrong_class_pixel_share,
            100.0 * row.baseline_wrong_class_pixel_share,
        );
        if let (Some(l), Some(n)) = (
            row.delta_oracle_lerf_miou(),
            row.delta_oracle_scannet_miou19(),
        ) {
            let _ = writeln!(
                s,
                "{:>5} {:<19} ground-truth proposals: LERF mIoU {:.2} (Δ {l:+.2}), mIoU19 {:.2} (Δ {n:+.2})",
                "",
                "",
                row.oracle_lerf_miou.unwrap_or(f64::NAN),
                row.oracle_scannet_miou19.unwrap_or(f64::NAN),
            );
        }
    }
    let means = |s: &mut String, name: &str, m: &SweepMeans| {
        let _ = writeln!(
            s,
            "{name:<19} rows {:>3}: mean Δ LERF mIoU {:+.2} (min {:+.2}, ahead in {}/{}), mean Δ ScanNet mIoU19 {:+.2}, ARI {:.3} (members {:.3}), purity {:.3}, completeness {:.3}, wrong px {:.1}% vs {:.1}%",
            m.rows,
            m.mean_delta_lerf_miou,
            m.min_delta_lerf_miou,
            m.rows_ahead_lerf_miou,
            m.rows,
            m.mean_delta_scannet_miou19,
            m.mean_ari,
            m.mean_member_ari,
            m.mean_purity,
            m.mean_completeness,
            100.0 * m.mean_wrong_class_pixel_share,
            100.0 * m.mean_baseline_wrong_class_pixel_share,
        );
        if let (Some(l), Some(n)) = (
            m.mean_delta_oracle_lerf_miou,
            m.mean_delta_oracle_scannet_miou19,
        ) {
            let _ = writeln!(
                s,
                "{:<19}           ground-truth proposals: mean Δ LERF mIoU {l:+.2}, mean Δ ScanNet mIoU19 {n:+.2}",
                ""
            );
        }
    };
    let _ = writeln!(s);
    means(&mut s, "all", &r.summary.all);
    for (name, m) in &r.summary.by_faults {
        means(&mut s, name, m);
    }
    let _ = write!(s, "wall {:.1} s", r.summary.seconds);
    s
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn seed_lists_take_ranges_and_single_seeds() {
        assert_eq!(parse_seeds("0-3").unwrap(), vec![0, 1, 2, 3]);
        assert_eq!(parse_seeds("0,3,7").unwrap(), vec![0, 3, 7]);
        assert_eq!(parse_seeds("0-2,9, 5").unwrap(), vec![0, 1, 2, 9, 5]);
        for bad in ["", "a", "3-1", "1,1", "0-2,2", "-1", "1-"] {
            assert!(parse_seeds(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn fault_lists_are_names() {
        assert_eq!(
            parse_fault_sets("default,sparse-views").unwrap(),
            vec![synth::FaultSet::Default, synth::FaultSet::SparseViews]
        );
        let e = parse_fault_sets("default,noisy").unwrap_err().to_string();
        assert!(
            e.contains("noisy") && e.contains("harsh-segmentation"),
            "{e}"
        );
        assert!(parse_fault_sets("default,default").is_err());
    }

    fn row(faults: &str, miou: f64, base: f64) -> SweepRow {
        SweepRow {
            seed: 0,
            faults: faults.into(),
            lerf_miou: miou,
            baseline_lerf_miou: base,
            lerf_acc25: 0.0,
            baseline_lerf_acc25: 0.0,
            scannet_miou19: 2.0,
            baseline_scannet_miou19: 1.0,
            ari: 0.5,
            member_ari: 0.5,
            purity: 1.0,
            completeness: 0.25,
            wrong_class_pixel_share: 0.1,
            baseline_wrong_class_pixel_share: 0.2,
            oracle_lerf_miou: None,
            oracle_scannet_miou19: None,
            geometry_reused: false,
            seconds: 1.0,
        }
    }

    #[test]
    fn oracle_means_need_every_row_and_stay_out_of_the_json_otherwise() {
        let plain = SweepReport::new(vec![row("a", 50.0, 40.0)], 1.0);
        let j = serde_json::to_value(&plain).unwrap();
        assert!(j["summary"].get("mean_delta_oracle_lerf_miou").is_none());
        assert!(j["rows"][0].get("oracle_lerf_miou").is_none());

        let with = |miou: f64, sn: f64| SweepRow {
            oracle_lerf_miou: Some(miou),
            oracle_scannet_miou19: Some(sn),
            ..row("a", 50.0, 40.0)
        };
        let r = SweepReport::new(vec![with(44.0, 3.0), with(47.0, 0.0)], 1.0);
        assert_eq!(r.summary.all.mean_delta_oracle_lerf_miou, Some(5.5));
        assert_eq!(r.summary.all.mean_delta_oracle_scannet_miou19, Some(0.5));
        let j = serde_json::to_value(&r).unwrap();
        assert_eq!(j["rows"][1]["oracle_lerf_miou"], 47.0);
        let text = text_table(&r);
        assert!(
            text.contains("ground-truth proposals: mean Δ LERF mIoU +5.50"),
            "{text}"
        );

        let mixed = SweepReport::new(vec![with(44.0, 3.0), row("a", 50.0, 40.0)], 1.0);
        assert_eq!(mixed.summary.all.mean_delta_oracle_lerf_miou, None);
    }

    #[test]
    fn summary_means_are_over_all_rows_and_per_fault_set() {
        let r = SweepReport::new(
            vec![
                row("a", 50.0, 40.0),
                row("a", 30.0, 35.0),
                row("b", 60.0, 60.0),
            ],
            3.0,
        );
        assert_eq!(r.summary.all.rows, 3);
        assert!((r.summary.all.mean_delta_lerf_miou - 5.0 / 3.0).abs() < 1e-12);
        assert_eq!(r.summary.all.min_delta_lerf_miou, -5.0);
        assert_eq!(r.summary.all.rows_ahead_lerf_miou, 1);
        assert_eq!(r.summary.by_faults["a"].mean_delta_lerf_miou, 2.5);
        assert_eq!(r.summary.by_faults["b"].min_delta_lerf_miou, 0.0);
        assert_eq!(r.summary.all.mean_delta_scannet_miou19, 1.0);
        let j = serde_json::to_value(&r).unwrap();
        assert_eq!(j["summary"]["rows"], 3);
        assert_eq!(j["summary"]["by_faults"]["a"]["rows"], 2);
        assert!(j["summary"]["mean_ari"].is_number());
        let text = text_table(&r);
        assert_eq!(text.lines().count(), 1 + 3 + 1 + 3 + 1, "{text}");
    }
}

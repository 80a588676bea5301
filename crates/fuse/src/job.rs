//! The fuse stage as a file-level job: read the inputs, register, write the features
//! and/or the partial sums, and report. The `fuse` tool and the pipeline both run this, so
//! they write the same bytes and print the same report; [`Params`] is the `[fuse]` section
//! of the pipeline's configuration as it is.
//!
//! ```
//! use profuse_fuse::job::{self, Job, Params};
//!
//! let dir = tempfile::tempdir()?;
//! let mut config = synth::Config::preset(synth::Preset::Tiny, 1);
//! config.gaussians = 2000; // ground-truth Gaussians, which the tiny preset leaves out
//! synth::generate(&config, dir.path())?;
//! let file = |name: &str| dir.path().join(name);
//! let job = Job::new(
//!     &file("gt/gaussians.safetensors"),
//!     &file("cameras.safetensors"),
//!     &file("masks.safetensors"),
//! )
//! .baseline()
//! .with_out(&file("features.safetensors"));
//! let run = job::run(&job, &Params::default(), &mut |_| {})?;
//! assert!(run.report.valid.unwrap_or(0) > 0);
//! assert_eq!(run.report.grouping, "masks");
//! assert!(file("features.safetensors").is_file());
//! # Ok::<(), Box<dyn std::error::Error + Send + Sync>>(())
//! ```

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::time::Instant;

use profuse_formats::{Cameras, FileKind, Gaussians, Masks, Proposals};
use serde::{Deserialize, Serialize};

use crate::{
    accumulate, finish, Groups, MemberWeight, Names, Orphans, PartialSums, Precision, Registration,
    Result, ViewReport, DEFAULT_K,
};

/// What a mask's pixels register.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Register {
    /// The proposal's descriptor (the paper).
    #[default]
    Proposals,
    /// The proposal's descriptor blended with the mask's own feature by how well they
    /// agree ([`Groups::blend`]).
    Blend,
}

/// The stage's parameters (the pipeline's `[fuse]` section).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Params {
    /// Top-K contributors per pixel (paper: 10).
    pub k: usize,
    /// Masks without a proposal: `ignore` (paper) or `singleton`.
    pub orphans: Orphans,
    /// The Dr. Splat-style baseline: every mask registers its own feature.
    pub no_proposals: bool,
    /// `proposals` (paper) or `blend`; ignored with `no_proposals`.
    pub registration: Register,
    /// What a member mask weighs in its proposal's descriptor: `share` (its mass times
    /// the proposals file's `mask_share`, where the file has one) or `mass` (the paper).
    pub member_weight: MemberWeight,
    /// The exponent e of a member mask's pixel weights in W: every hit of a pixel of
    /// member m weighs ω · s_m^e, s_m the proposals file's `mask_share` (orphans weigh ω);
    /// 0 is the paper (ω alone). Finite, >= 0.
    pub pixel_share_power: f64,
    /// Semantic index: the smallest share of a Gaussian's weight its largest proposal
    /// must hold to be its dominant proposal (in [0, 1]; stored in units of 1/255).
    pub min_share: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            k: DEFAULT_K,
            orphans: Orphans::default(),
            no_proposals: false,
            registration: Register::default(),
            member_weight: MemberWeight::default(),
            pixel_share_power: crate::DEFAULT_PIXEL_SHARE_POWER,
            min_share: crate::DEFAULT_MIN_SHARE,
        }
    }
}

/// The files of one run and the options that are not parameters of the method.
#[derive(Debug, Clone, PartialEq)]
pub struct Job {
    /// Gaussians (profuse.gaussians).
    pub gaussians: PathBuf,
    /// Cameras (profuse.cameras).
    pub cameras: PathBuf,
    /// Masks with their features (profuse.masks).
    pub masks: PathBuf,
    /// Proposals (profuse.proposals); `None` registers every mask's own feature, as
    /// [`Params::no_proposals`] does.
    pub proposals: Option<PathBuf>,
    /// The features file to write.
    pub out: Option<PathBuf>,
    /// The partial-sums file to write (profuse.fuse_partial), for [`crate::merge`].
    pub partial_out: Option<PathBuf>,
    /// Only these views (a shard); `None` = every view.
    pub views: Option<Range<usize>>,
    /// Storage precision of the descriptors; `None` = that of the mask features.
    pub precision: Option<Precision>,
    /// The semantic index to write beside the features (profuse.semantic_index).
    pub semantic_index: Option<PathBuf>,
}

impl Job {
    /// A job over these inputs that writes nothing yet and reads no proposals.
    pub fn new(gaussians: &Path, cameras: &Path, masks: &Path) -> Job {
        Job {
            gaussians: gaussians.to_path_buf(),
            cameras: cameras.to_path_buf(),
            masks: masks.to_path_buf(),
            proposals: None,
            out: None,
            partial_out: None,
            views: None,
            precision: None,
            semantic_index: None,
        }
    }

    /// Registers the proposals of this file.
    pub fn with_proposals(mut self, path: &Path) -> Job {
        self.proposals = Some(path.to_path_buf());
        self
    }

    /// Every mask registers its own feature (no proposals).
    pub fn baseline(mut self) -> Job {
        self.proposals = None;
        self
    }

    /// Writes the features here.
    pub fn with_out(mut self, path: &Path) -> Job {
        self.out = Some(path.to_path_buf());
        self
    }
}

/// Per-mask-mass statistics of a registration.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MaskMass {
    /// Masks with μ > 0.
    pub masks_with_mass: usize,
    /// Σ μ.
    pub total: f64,
    /// Smallest μ > 0.
    pub min: f64,
    /// Median μ > 0.
    pub median: f64,
    /// Largest μ.
    pub max: f64,
}

/// What a run did: the same object from the tool (stdout) and the pipeline (its summary).
/// The registration fields are present when features were written.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    /// Gaussians N.
    pub gaussians: usize,
    /// The views summed, `[a, b)`.
    pub views: [usize; 2],
    /// Top-K.
    pub k: usize,
    /// `proposals`, `blend` or `masks` (the baseline).
    pub grouping: String,
    /// The orphan policy (`ignore`, `singleton`, or `none` without proposals).
    pub orphans: String,
    /// Nonzero (Gaussian, group) pairs of W.
    pub nnz: usize,
    /// Grouped mask-grid pixels.
    pub pixels: u64,
    /// Their top-K hits.
    pub hits: u64,
    /// Gaussians with a descriptor.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub valid: Option<usize>,
    /// Groups G.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub groups: Option<usize>,
    /// Groups with a nonzero descriptor.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub groups_with_descriptor: Option<usize>,
    /// Masks M.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub masks: Option<usize>,
    /// Masks that register into a group.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub assigned_masks: Option<usize>,
    /// Mask masses.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mask_mass: Option<MaskMass>,
    /// Descriptor dimension D.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub feature_dim: Option<usize>,
    /// `f16` or `f32`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub precision: Option<&'static str>,
    /// The features file written (non-UTF-8 bytes shown as U+FFFD in JSON).
    #[serde(
        skip_serializing_if = "Option::is_none",
        serialize_with = "profuse_formats::output::lossy_path::option"
    )]
    pub out: Option<PathBuf>,
    /// The partial-sums file written.
    #[serde(
        skip_serializing_if = "Option::is_none",
        serialize_with = "profuse_formats::output::lossy_path::option"
    )]
    pub partial_out: Option<PathBuf>,
    /// The semantic index written (profuse.semantic_index).
    #[serde(
        skip_serializing_if = "Option::is_none",
        serialize_with = "profuse_formats::output::lossy_path::option"
    )]
    pub semantic_index: Option<PathBuf>,
    /// Gaussians with a dominant proposal in the semantic index.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dominant: Option<usize>,
    /// Reading the inputs.
    pub load_s: f64,
    /// Rendering the top-K buffers.
    pub raster_s: f64,
    /// Scattering the hits.
    pub accumulate_s: f64,
    /// Compacting the tile records.
    pub compact_s: f64,
    /// Forming the descriptors ([`finish`]); 0 without features.
    pub finish_s: f64,
    /// Accumulation and finish, wall clock.
    pub seconds: f64,
}

/// A finished run: its report and the partial sums it accumulated (what every mask
/// registered can be read from them, [`crate::registered_mask_descriptors`]).
#[derive(Debug)]
pub struct Run {
    /// The report.
    pub report: Report,
    /// The exact sums over the job's views.
    pub partial: PartialSums,
}

fn name(p: &Path) -> String {
    p.display().to_string()
}

/// Runs a job: reads the inputs, accumulates over the views (calling `on_view` after
/// each), writes the partial sums and/or the features (atomically), and reports.
pub fn run(job: &Job, params: &Params, on_view: &mut dyn FnMut(&ViewReport)) -> Result<Run> {
    check_params(params)?;
    let t0 = Instant::now();
    let gaussians = Gaussians::read(&job.gaussians)?;
    let cameras = Cameras::read(&job.cameras)?;
    let masks = Masks::read(&job.masks)?;
    let groups = job_groups(job, params, &masks)?;
    let scene = crate::Scene::new(&gaussians, &cameras, &masks).named(Names {
        gaussians: name(&job.gaussians),
        cameras: name(&job.cameras),
        masks: name(&job.masks),
    });
    let load_s = t0.elapsed().as_secs_f64();
    let views = job.views.clone().unwrap_or(0..cameras.len());
    let t1 = Instant::now();
    let partial = accumulate(&scene, &groups, params.k, views.clone(), on_view)?;
    if let Some(path) = &job.partial_out {
        partial.write(path)?;
    }
    let mut report = base_report(&partial, [views.start, views.end], load_s);
    report.partial_out = job.partial_out.clone();
    if let Some(out) = &job.out {
        let precision = job
            .precision
            .unwrap_or_else(|| Precision::of(&masks.features));
        write_features(&partial, precision, out, &mut report)?;
        write_semantic_index(job, params, &partial, precision, &mut report)?;
    }
    report.seconds = t1.elapsed().as_secs_f64();
    Ok(Run { report, partial })
}

/// The finishing step of a sharded run: adds up the partial sums that runs of this same
/// job over disjoint view shards wrote (`views` + `partial_out`), and writes `job.out`,
/// byte-identical to an unsharded [`run`]. Unlike [`merge_files`], every shard is checked
/// against the job's own inputs and parameters (Gaussian and view counts, K, the grouping
/// of the masks, the mask features), so a shard left over from other inputs is refused
/// ([`crate::FuseError::ShardOfOtherInputs`]) instead of being summed.
pub fn run_merged(job: &Job, params: &Params, partials: &[PathBuf]) -> Result<Run> {
    check_params(params)?;
    let t0 = Instant::now();
    let gaussians = Gaussians::read(&job.gaussians)?;
    let cameras = Cameras::read(&job.cameras)?;
    let masks = Masks::read(&job.masks)?;
    let groups = job_groups(job, params, &masks)?;
    let (merged, names) = read_and_merge(partials)?;
    let expected = crate::partial::JobFacts {
        num_gaussians: gaussians.len(),
        num_views: cameras.len(),
        k: params.k,
        groups: &groups,
        mask_features: &masks.features,
        num_masks: masks.num_masks(),
        dim: masks.dim,
    };
    crate::partial::compare_facts(&expected, &merged.facts()).map_err(
        |(field, expected, found)| crate::FuseError::ShardOfOtherInputs {
            shards: names.join(", "),
            field,
            expected,
            found,
        },
    )?;
    require_every_view(&merged)?;
    let load_s = t0.elapsed().as_secs_f64();
    let mut report = base_report(&merged, [0, merged.num_views()], load_s);
    if let Some(out) = &job.out {
        let precision = job
            .precision
            .unwrap_or_else(|| Precision::of(&masks.features));
        write_features(&merged, precision, out, &mut report)?;
        write_semantic_index(job, params, &merged, precision, &mut report)?;
    }
    report.seconds = t0.elapsed().as_secs_f64();
    Ok(Run {
        report,
        partial: merged,
    })
}

/// Adds up partial-sums files of disjoint shards that cover every view and writes the
/// features: byte-identical to an unsharded [`run`].
pub fn merge_files(
    partials: &[PathBuf],
    out: &Path,
    precision: Option<Precision>,
) -> Result<Report> {
    let t0 = Instant::now();
    let (merged, _) = read_and_merge(partials)?;
    require_every_view(&merged)?;
    let precision = precision.unwrap_or_else(|| Precision::of(merged.mask_features()));
    let mut report = base_report(&merged, [0, merged.num_views()], 0.0);
    write_features(&merged, precision, out, &mut report)?;
    report.seconds = t0.elapsed().as_secs_f64();
    Ok(report)
}

/// Reads partial-sums files and adds them up (checking them against each other); returns
/// the sums and the files' names for messages.
fn read_and_merge(partials: &[PathBuf]) -> Result<(PartialSums, Vec<String>)> {
    let parts = partials
        .iter()
        .map(PartialSums::read)
        .collect::<Result<Vec<_>>>()?;
    let names: Vec<String> = partials.iter().map(|p| name(p)).collect();
    let merged = crate::merge(&parts, &names)?;
    Ok((merged, names))
}

/// Merged shards must cover every view before they are finished.
fn require_every_view(merged: &PartialSums) -> Result<()> {
    if merged.is_complete() {
        return Ok(());
    }
    Err(crate::FuseError::MissingViews {
        missing: merged.missing_views(),
        views: merged.num_views(),
    })
}

/// Finishes the sums into descriptors, writes them to `out` (atomically) and adds the
/// registration's figures to `report`.
fn write_features(
    partial: &PartialSums,
    precision: Precision,
    out: &Path,
    report: &mut Report,
) -> Result<()> {
    let reg = finish(partial, precision);
    reg.features.write(out)?;
    add_registration(report, &reg, partial, precision);
    report.out = Some(out.to_path_buf());
    Ok(())
}

/// `min_share` must be a share and `pixel_share_power` a finite number >= 0, checked
/// before anything is read or written.
fn check_params(params: &Params) -> Result<()> {
    if !(0.0..=1.0).contains(&params.min_share) {
        return Err(crate::FuseError::MinShare(params.min_share));
    }
    crate::groups::check_pixel_share_power(params.pixel_share_power)
}

/// Writes the job's semantic index (if it names one) from the same sums as its features.
fn write_semantic_index(
    job: &Job,
    params: &Params,
    partial: &PartialSums,
    precision: Precision,
    report: &mut Report,
) -> Result<()> {
    let Some(path) = &job.semantic_index else {
        return Ok(());
    };
    let index = crate::semantic_index(partial, precision, params.min_share);
    index.write(path)?;
    report.semantic_index = Some(path.clone());
    report.dominant = index.counts().get("dominant").map(|d| *d as usize);
    Ok(())
}

/// The groups the job registers: its proposals under the parameters, or one per mask.
fn job_groups(job: &Job, params: &Params, masks: &Masks) -> Result<Groups> {
    match &job.proposals {
        Some(path) if !params.no_proposals => {
            let proposals = Proposals::read(path)?;
            let build = match params.registration {
                Register::Proposals => Groups::from_proposals,
                Register::Blend => Groups::blend,
            };
            build(
                masks,
                &proposals,
                params.orphans,
                params.member_weight,
                &name(path),
            )?
            .with_pixel_shares(&proposals, params.pixel_share_power)
        }
        _ => Ok(Groups::per_mask(masks)),
    }
}

fn base_report(p: &PartialSums, views: [usize; 2], load_s: f64) -> Report {
    let t = p.timings();
    Report {
        gaussians: p.num_gaussians(),
        views,
        k: p.k(),
        grouping: p.groups().grouping.name().into(),
        orphans: p.groups().grouping.orphans_name().into(),
        nnz: p.weights().nnz(),
        pixels: p.counts().pixels,
        hits: p.counts().hits,
        valid: None,
        groups: None,
        groups_with_descriptor: None,
        masks: None,
        assigned_masks: None,
        mask_mass: None,
        feature_dim: None,
        precision: None,
        out: None,
        partial_out: None,
        semantic_index: None,
        dominant: None,
        load_s,
        raster_s: t.raster_s,
        accumulate_s: t.accumulate_s,
        compact_s: t.compact_s,
        finish_s: 0.0,
        seconds: 0.0,
    }
}

fn add_registration(r: &mut Report, reg: &Registration, p: &PartialSums, precision: Precision) {
    let s = &reg.summary;
    r.valid = Some(s.valid);
    r.nnz = s.nnz;
    r.groups = Some(s.groups);
    r.groups_with_descriptor = Some(s.groups_with_descriptor);
    r.masks = Some(s.masks);
    r.assigned_masks = Some(s.assigned_masks);
    r.mask_mass = Some(MaskMass {
        masks_with_mass: s.masks_with_mass,
        total: s.mass_total,
        min: s.mass_min,
        median: s.mass_median,
        max: s.mass_max,
    });
    r.pixels = s.pixels;
    r.hits = s.hits;
    r.feature_dim = Some(p.dim());
    r.precision = Some(precision.name());
    r.finish_s = s.finish_s;
}

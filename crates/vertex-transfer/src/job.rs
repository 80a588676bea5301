//! The file-level transfer the `vertex-transfer run` tool performs: read, validate,
//! transfer, write atomically (nothing is written when any step fails).

use std::path::PathBuf;
use std::time::Instant;

use profuse_formats::{Features, FileKind, Gaussians, Mesh, Pq, Prompts, SemanticIndex};
use serde::Serialize;

use crate::classes::ClassSet;
use crate::error::Result;
use crate::field::{Descriptors, GaussianField, Params, Stats};
use crate::Source;

/// The descriptor input of a [`Job`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum DescriptorFile {
    /// A `features` file (decoded descriptors).
    Features(PathBuf),
    /// A `pq` file (product-quantised descriptors).
    Pq(PathBuf),
    /// A `semantic_index` file, with the `pq` file of its Gaussians without a dominant
    /// proposal (`--semantics both`).
    Indexed {
        /// The semantic index.
        index: PathBuf,
        /// The PQ codes of the same Gaussians.
        fallback: Option<PathBuf>,
    },
}

/// A read descriptor file.
enum Loaded {
    Features(Features),
    Pq(Pq),
    Indexed(SemanticIndex, Option<(String, Pq)>),
}

/// Every path of one transfer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Job {
    /// The `gaussians` file.
    pub gaussians: PathBuf,
    /// The descriptors, one row per Gaussian.
    pub descriptors: DescriptorFile,
    /// The `prompts` file.
    pub prompts: PathBuf,
    /// Class prompt names; `None` = every prompt with `class_ids >= 0`.
    pub classes: Option<Vec<String>>,
    /// Restrict the classes to those whose label is listed ([`ClassSet::restrict`]): the
    /// vocabulary of one evaluated class set, e.g. the 19 NYU40 ids; `None` = all classes.
    pub class_filter: Option<Vec<i32>>,
    /// The `mesh` file whose vertices are labelled.
    pub mesh: PathBuf,
    /// The `vertex_labels` file to write.
    pub out: PathBuf,
    /// Value of the output's `generator` metadata, if any.
    pub generator: Option<String>,
}

/// A stage of [`run_job_with_progress`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JobStage {
    /// Reading and validating the four inputs.
    Read,
    /// Preparing kernels, class probabilities and the KD-tree.
    Build,
    /// Labelling this many vertices.
    Label {
        /// Mesh vertices.
        vertices: u64,
    },
    /// Writing the output.
    Write,
}

/// What [`run_job`] did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct JobReport {
    /// Mesh vertices.
    pub vertices: u64,
    /// Vertices that received a label.
    pub labelled: u64,
    /// Classes chosen from.
    pub classes: usize,
    /// Labels of the classes, ascending.
    pub class_labels: Vec<i32>,
    /// Label space written to the output.
    pub label_space: String,
    /// Gaussians in the gaussians file.
    pub gaussians: usize,
    /// Gaussians with a valid descriptor (the candidate pool).
    pub valid_gaussians: usize,
    /// Mean gated candidates per vertex.
    pub mean_candidates: f64,
    /// Vertices whose whole K-shortlist passed the gate (see [`Stats::saturated`]).
    pub saturated: u64,
    /// Seconds reading and validating the inputs.
    pub read_s: f64,
    /// Seconds preparing kernels, class probabilities and the KD-tree.
    pub build_s: f64,
    /// Seconds labelling the vertices.
    pub label_s: f64,
    /// Seconds writing the output.
    pub write_s: f64,
}

/// Reads the inputs, transfers labels, and writes `job.out` atomically.
pub fn run_job(job: &Job, params: &Params) -> Result<JobReport> {
    run_job_with_progress(job, params, &|_| {}, &|_| {})
}

/// [`run_job`] reporting progress: `stage(name)` when a stage starts (`read`, `build`,
/// `label`, `write`), then `vertices(n)` after each chunk of n labelled vertices.
pub fn run_job_with_progress(
    job: &Job,
    params: &Params,
    stage: &dyn Fn(JobStage),
    vertices: &(dyn Fn(u64) + Sync),
) -> Result<JobReport> {
    params.validate()?;
    stage(JobStage::Read);
    let t = Instant::now();
    let show = |p: &PathBuf| p.display().to_string();
    let (gaussians_file, prompts_file, mesh_file) =
        (show(&job.gaussians), show(&job.prompts), show(&job.mesh));
    let gaussians = Gaussians::read(&job.gaussians)?;
    let (descriptor_file, loaded) = match &job.descriptors {
        DescriptorFile::Features(p) => (show(p), Loaded::Features(Features::read(p)?)),
        DescriptorFile::Pq(p) => (show(p), Loaded::Pq(Pq::read(p)?)),
        DescriptorFile::Indexed { index, fallback } => {
            let pq = match fallback {
                Some(p) => Some((show(p), Pq::read(p)?)),
                None => None,
            };
            (
                show(index),
                Loaded::Indexed(SemanticIndex::read(index)?, pq),
            )
        }
    };
    let prompts = Prompts::read(&job.prompts)?;
    let mesh = Mesh::read(&job.mesh)?;
    let prompt_source = Source::new(&prompts_file, &prompts);
    let classes = match &job.classes {
        Some(names) => ClassSet::from_names(prompt_source, names)?,
        None => ClassSet::from_prompts(prompt_source)?,
    };
    let classes = match &job.class_filter {
        Some(labels) => classes.restrict(labels)?,
        None => classes,
    };
    let read_s = t.elapsed().as_secs_f64();

    stage(JobStage::Build);
    let t = Instant::now();
    let field = GaussianField::new(
        Source::new(&gaussians_file, &gaussians),
        match &loaded {
            Loaded::Features(f) => Descriptors::Features(Source::new(&descriptor_file, f)),
            Loaded::Pq(p) => Descriptors::Pq(Source::new(&descriptor_file, p)),
            Loaded::Indexed(index, fallback) => Descriptors::Indexed {
                index: Source::new(&descriptor_file, index),
                fallback: fallback.as_ref().map(|(file, pq)| Source::new(file, pq)),
            },
        },
        &classes,
        params,
    )?;
    let build_s = t.elapsed().as_secs_f64();

    stage(JobStage::Label {
        vertices: mesh.vertices.len() as u64,
    });
    let t = Instant::now();
    let labelling = field.label_vertices_with_progress(&mesh.vertices, vertices);
    let label_s = t.elapsed().as_secs_f64();

    stage(JobStage::Write);
    let t = Instant::now();
    let label_space = label_space(&classes, &mesh);
    let mut file = field.to_file(&labelling, &label_space);
    file.extra.insert("mesh".to_string(), mesh_file);
    if let Some(g) = &job.generator {
        file.extra.insert("generator".to_string(), g.clone());
    }
    file.write(&job.out)?;
    let write_s = t.elapsed().as_secs_f64();

    let Stats {
        vertices,
        labelled,
        candidates,
        saturated,
    } = labelling.stats;
    Ok(JobReport {
        vertices,
        labelled,
        classes: classes.len(),
        class_labels: classes.labels().to_vec(),
        label_space,
        gaussians: gaussians.len(),
        valid_gaussians: field.valid_gaussians(),
        mean_candidates: candidates as f64 / vertices.max(1) as f64,
        saturated,
        read_s,
        build_s,
        label_s,
        write_s,
    })
}

/// The prompts' label space, else (labels being class ids) the mesh's, else `class_ids`.
fn label_space(classes: &ClassSet, mesh: &Mesh) -> String {
    classes
        .label_space()
        .map(str::to_string)
        .or_else(|| mesh.extra.get("label_space").cloned())
        .unwrap_or_else(|| "class_ids".to_string())
}

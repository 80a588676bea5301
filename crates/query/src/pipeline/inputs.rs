//! What a query reads: the per-Gaussian descriptors (PQ codes, features or a semantic index),
//! the prompts and the prompt selection, the Gaussians and the cameras.

use super::*;

/// Where the per-Gaussian descriptors come from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum DescriptorPath {
    /// A `profuse.features` file (exact).
    Features(PathBuf),
    /// A `profuse.pq` file (scored by asymmetric distance).
    Pq(PathBuf),
    /// A `profuse.semantic_index` file, with the pq file its Gaussians without a dominant
    /// proposal fall back to (`--semantics both`).
    Indexed {
        /// The semantic index.
        index: PathBuf,
        /// The PQ codes of the same Gaussians.
        fallback: Option<PathBuf>,
    },
}

impl DescriptorPath {
    /// The file (the semantic index for [`DescriptorPath::Indexed`]).
    pub fn path(&self) -> &Path {
        match self {
            DescriptorPath::Features(p) | DescriptorPath::Pq(p) => p,
            DescriptorPath::Indexed { index, .. } => index,
        }
    }
}

/// Loaded descriptors.
#[derive(Debug, Clone)]
pub enum DescriptorSet {
    /// From a features file.
    Features(Features),
    /// From a pq file.
    Pq(Pq),
    /// From a semantic index, with its PQ fallback.
    Indexed(SemanticIndex, Option<Pq>),
}

impl DescriptorSet {
    /// Reads the descriptors file.
    pub fn read(path: &DescriptorPath) -> Result<DescriptorSet> {
        Ok(match path {
            DescriptorPath::Features(p) => DescriptorSet::Features(Features::read(p)?),
            DescriptorPath::Pq(p) => DescriptorSet::Pq(Pq::read(p)?),
            DescriptorPath::Indexed { index, fallback } => {
                let si = SemanticIndex::read(index)?;
                let pq = fallback.as_ref().map(Pq::read).transpose()?;
                if let (Some(pq), Some(pq_path)) = (&pq, fallback) {
                    if pq.len() != si.num_gaussians() {
                        return Err(QueryError::CountMismatch {
                            descriptors: pq_path.display().to_string(),
                            descriptor_count: pq.len(),
                            gaussians: index.display().to_string(),
                            gaussian_count: si.num_gaussians(),
                        });
                    }
                }
                DescriptorSet::Indexed(si, pq)
            }
        })
    }

    /// Borrowed view for scoring.
    pub fn as_descriptors(&self) -> Descriptors<'_> {
        match self {
            DescriptorSet::Features(f) => Descriptors::Features(f),
            DescriptorSet::Pq(p) => Descriptors::Pq(p),
            DescriptorSet::Indexed(index, fallback) => Descriptors::Indexed(Indexed {
                index,
                fallback: fallback.as_ref(),
            }),
        }
    }
}

/// Descriptors and prompts, read and checked against each other.
#[derive(Debug, Clone)]
pub struct ScoreInputs {
    /// The descriptors.
    pub descriptors: DescriptorSet,
    /// The prompts.
    pub prompts: Prompts,
    /// The descriptors file, for messages.
    pub descriptors_path: String,
    /// The prompts file, for messages.
    pub prompts_path: String,
}

/// Which prompts of the prompts file to query.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PromptSelection {
    /// These names, in this order.
    Names(Vec<String>),
    /// Every prompt with a class id >= 0 (the file must have `class_ids`).
    AllClasses,
    /// Every prompt except the canonical negatives.
    All,
}

impl ScoreInputs {
    /// Reads both files and checks that their dimensions agree.
    pub fn load(descriptors: &DescriptorPath, prompts: &Path) -> Result<ScoreInputs> {
        ScoreInputs::new(
            DescriptorSet::read(descriptors)?,
            Prompts::read(prompts)?,
            &descriptors.path().display().to_string(),
            &prompts.display().to_string(),
        )
    }

    /// Checks that the prompts and descriptors share one embedding dimension.
    pub fn new(
        descriptors: DescriptorSet,
        prompts: Prompts,
        descriptors_path: &str,
        prompts_path: &str,
    ) -> Result<ScoreInputs> {
        let d = descriptors.as_descriptors().dim();
        if prompts.dim != d {
            return Err(QueryError::DimMismatch {
                prompts: prompts_path.into(),
                prompt_dim: prompts.dim,
                descriptors: descriptors_path.into(),
                descriptor_dim: d,
            });
        }
        Ok(ScoreInputs {
            descriptors,
            prompts,
            descriptors_path: descriptors_path.into(),
            prompts_path: prompts_path.into(),
        })
    }

    /// The descriptors, borrowed.
    pub fn descriptors(&self) -> Descriptors<'_> {
        self.descriptors.as_descriptors()
    }

    /// Checks that the descriptors belong to a Gaussian set of `count` Gaussians.
    pub fn check_gaussian_count(&self, count: usize, gaussians_path: &str) -> Result<()> {
        let n = self.descriptors().len();
        if n != count {
            return Err(QueryError::CountMismatch {
                descriptors: self.descriptors_path.clone(),
                descriptor_count: n,
                gaussians: gaussians_path.into(),
                gaussian_count: count,
            });
        }
        Ok(())
    }

    /// Indices of the selected prompts, in request order, without repeats.
    pub fn resolve_prompts(&self, selection: &PromptSelection) -> Result<Vec<usize>> {
        let p = &self.prompts;
        let which: Vec<usize> = match selection {
            PromptSelection::Names(names) => {
                let mut out = Vec::new();
                for name in names {
                    let i = p.index_of(name).ok_or_else(|| QueryError::UnknownPrompt {
                        path: self.prompts_path.clone(),
                        name: name.clone(),
                        available: p.names.join(", "),
                    })?;
                    if !out.contains(&i) {
                        out.push(i);
                    }
                }
                out
            }
            PromptSelection::AllClasses => {
                let ids = p.class_ids.as_ref().ok_or_else(|| QueryError::NoPrompts {
                    path: self.prompts_path.clone(),
                    reason: "the file has no `class_ids`, so no prompt names a class".into(),
                })?;
                (0..p.len()).filter(|&i| ids[i] >= 0).collect()
            }
            PromptSelection::All => (0..p.len())
                .filter(|&i| !CANONICAL_NEGATIVES.contains(&p.names[i].as_str()))
                .collect(),
        };
        if which.is_empty() {
            return Err(QueryError::NoPrompts {
                path: self.prompts_path.clone(),
                reason: format!("no prompt matches {selection:?}"),
            });
        }
        Ok(which)
    }

    /// Scores every Gaussian for each prompt of `which` (see [`score_prompts`]); errors
    /// name the files.
    pub fn scores(&self, which: &[usize], kind: ScoreKind) -> Result<Vec<Vec<f32>>> {
        score_prompts(self.descriptors(), &self.prompts, which, kind)
            .map_err(|e| self.name_files(e))
    }

    pub(super) fn name_files(&self, e: QueryError) -> QueryError {
        let (pp, dp) = (self.prompts_path.clone(), self.descriptors_path.clone());
        match e {
            QueryError::DimMismatch {
                prompt_dim,
                descriptor_dim,
                ..
            } => QueryError::DimMismatch {
                prompts: pp,
                prompt_dim,
                descriptors: dp,
                descriptor_dim,
            },
            QueryError::BadEmbedding { name, .. } => QueryError::BadEmbedding { path: pp, name },
            QueryError::NoNegatives { name, .. } => QueryError::NoNegatives { path: pp, name },
            QueryError::UnknownPrompt {
                name, available, ..
            } => QueryError::UnknownPrompt {
                path: pp,
                name,
                available,
            },
            QueryError::Pq { reason, .. } => QueryError::Pq { path: dp, reason },
            other => other,
        }
    }
}

/// Every input of a query run.
#[derive(Debug, Clone)]
pub struct Inputs {
    /// Descriptors and prompts.
    pub scoring: ScoreInputs,
    /// The Gaussians the descriptors belong to.
    pub gaussians: Gaussians,
    /// The cameras of the views to render.
    pub cameras: Cameras,
    /// The gaussians file, for messages.
    pub gaussians_path: String,
    /// The cameras file, for messages.
    pub cameras_path: String,
}

impl Inputs {
    /// Reads every file and checks them against each other (descriptor count = Gaussian
    /// count, prompt dimension = descriptor dimension).
    pub fn load(
        gaussians: &Path,
        cameras: &Path,
        descriptors: &DescriptorPath,
        prompts: &Path,
    ) -> Result<Inputs> {
        let g = Gaussians::read(gaussians)?;
        let c = Cameras::read(cameras)?;
        let scoring = ScoreInputs::load(descriptors, prompts)?;
        Inputs::new(
            scoring,
            g,
            c,
            &gaussians.display().to_string(),
            &cameras.display().to_string(),
        )
    }

    /// Checks already loaded inputs against each other.
    pub fn new(
        scoring: ScoreInputs,
        gaussians: Gaussians,
        cameras: Cameras,
        gaussians_path: &str,
        cameras_path: &str,
    ) -> Result<Inputs> {
        scoring.check_gaussian_count(gaussians.len(), gaussians_path)?;
        Ok(Inputs {
            scoring,
            gaussians,
            cameras,
            gaussians_path: gaussians_path.into(),
            cameras_path: cameras_path.into(),
        })
    }
}

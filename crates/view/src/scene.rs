//! A pipeline output opened for viewing: the files found, read, cross-checked and scored
//! once at start-up, so that a selection request is a threshold over stored scores.

use std::path::{Path, PathBuf};

use profuse_formats::{Cameras, FileKind, Gaussians, Masks, Proposals};
use profuse_fuse::{Names, Scene};
use profuse_query::{
    resolve_click, score_prompts, select, Click, ClickBy, ClickTarget, DescriptorPath,
    DescriptorSet, Descriptors, PromptSelection, Rule, ScoreInputs, ScoreKind,
    DEFAULT_RELEVANCY_THRESHOLD, DEFAULT_TOP_K,
};

use crate::error::{Result, ViewError};
use crate::presets::{presets, Preset};
use crate::splat::splat_bytes;

/// Cosine threshold of a click in click-only mode (the slider's initial value): the one
/// `examples/fox-semantic.sh` gives `query run --click --score cosine --threshold`, chosen
/// for SAM-embedding descriptors, whose cosines are all high (crates/prep/README.md, the
/// fox example). The query crate has no cosine default (`query run --score cosine` needs
/// an explicit threshold).
pub const DEFAULT_CLICK_COSINE_THRESHOLD: f32 = 0.9;

/// How selections are scored, with the files that scoring reads.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ScoringPaths {
    /// Gaussians only (`--gaussians-only`): no selection.
    None,
    /// Text prompts and clicks, scored by LERF relevancy against the prompts file's
    /// canonical negatives.
    Relevancy {
        /// `SCENE/prompts.safetensors`.
        prompts: PathBuf,
        /// `OUT/pq.safetensors`.
        pq: PathBuf,
    },
    /// Click only (no prompts file, e.g. a `profuse prepare` scene without a CLIP text
    /// encoder, whose masks carry SAM-embedding descriptors): no text prompts; a click is
    /// scored by the cosine between the clicked mask's proposal descriptor and every
    /// Gaussian's PQ-decoded descriptor.
    ClickCosine {
        /// `OUT/pq.safetensors`.
        pq: PathBuf,
    },
}

impl ScoringPaths {
    /// `gaussians_only`, `prompts` or `click_only` (the `mode` of `/api/scene`).
    pub fn mode(&self) -> &'static str {
        match self {
            ScoringPaths::None => "gaussians_only",
            ScoringPaths::Relevancy { .. } => "prompts",
            ScoringPaths::ClickCosine { .. } => "click_only",
        }
    }
}

/// Where the files of a pipeline output are (SPEC.md §6).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OutputPaths {
    /// `SCENE/cameras.safetensors`.
    pub cameras: PathBuf,
    /// `OUT/gaussians.safetensors`.
    pub gaussians: PathBuf,
    /// The scoring mode and its files.
    pub scoring: ScoringPaths,
    /// `SCENE/masks.safetensors` and `OUT/proposals.safetensors` (query by click).
    pub click: Option<(PathBuf, PathBuf)>,
}

impl OutputPaths {
    /// Every file of the output in use.
    pub fn files(&self) -> Vec<&Path> {
        let mut v = vec![self.cameras.as_path(), self.gaussians.as_path()];
        match &self.scoring {
            ScoringPaths::None => {}
            ScoringPaths::Relevancy { prompts, pq } => v.extend([prompts.as_path(), pq.as_path()]),
            ScoringPaths::ClickCosine { pq } => v.push(pq.as_path()),
        }
        if let Some((m, p)) = &self.click {
            v.extend([m.as_path(), p.as_path()]);
        }
        v
    }

    /// The files of `dir`, which is a scene directory with an `out/` of pipeline outputs
    /// or that `out/` directory itself. Names the first required file that is missing.
    ///
    /// With `SCENE/prompts.safetensors` the scoring is [`ScoringPaths::Relevancy`]. Without
    /// it, an output with `OUT/pq.safetensors`, `SCENE/masks.safetensors` and
    /// `OUT/proposals.safetensors` is viewed click only ([`ScoringPaths::ClickCosine`]);
    /// any other output lacks the prompts file (view it with
    /// [`OutputPaths::find_gaussians_only`]).
    pub fn find(dir: &Path) -> Result<OutputPaths> {
        let (scene, out) = scene_and_out(dir)?;
        let cameras = scene.join("cameras.safetensors");
        let prompts = scene.join("prompts.safetensors");
        let pq = out.join("pq.safetensors");
        let click = Some((
            scene.join("masks.safetensors"),
            out.join("proposals.safetensors"),
        ))
        .filter(|(m, p)| m.is_file() && p.is_file());
        let scoring = if !prompts.is_file() && pq.is_file() && click.is_some() {
            ScoringPaths::ClickCosine { pq }
        } else {
            ScoringPaths::Relevancy { prompts, pq }
        };
        let mut required = vec![&cameras];
        match &scoring {
            ScoringPaths::Relevancy { prompts, pq } => required.extend([prompts, pq]),
            ScoringPaths::ClickCosine { pq } => required.push(pq),
            ScoringPaths::None => {}
        }
        if let Some(missing) = required.into_iter().find(|p| !p.is_file()) {
            return Err(ViewError::NotPipelineOutput {
                dir: dir.into(),
                missing: missing.clone(),
            });
        }
        Ok(OutputPaths {
            cameras,
            gaussians: out.join("gaussians.safetensors"),
            scoring,
            click,
        })
    }

    /// Gaussians and cameras only (no prompts, no selection): `gaussians.safetensors` in
    /// `dir` or `dir/out`, `cameras.safetensors` in `dir`, `dir/scene` (the layout of
    /// `examples/fox.sh`) or the parent of `dir`.
    pub fn find_gaussians_only(dir: &Path) -> Result<OutputPaths> {
        let (scene, out) = scene_and_out(dir)?;
        let candidates = [
            scene.join("cameras.safetensors"),
            out.join("scene").join("cameras.safetensors"),
            out.join("cameras.safetensors"),
        ];
        let cameras = candidates.iter().find(|p| p.is_file()).ok_or_else(|| {
            ViewError::NotPipelineOutput {
                dir: dir.into(),
                missing: candidates[0].clone(),
            }
        })?;
        Ok(OutputPaths {
            cameras: cameras.clone(),
            gaussians: out.join("gaussians.safetensors"),
            scoring: ScoringPaths::None,
            click: None,
        })
    }
}

/// (scene directory, output directory) of `dir`: `dir` and `dir/out` when `dir/out` holds
/// the Gaussians, else `dir`'s parent and `dir` when `dir` does.
fn scene_and_out(dir: &Path) -> Result<(PathBuf, PathBuf)> {
    if dir.join("out").join("gaussians.safetensors").is_file() {
        Ok((dir.to_path_buf(), dir.join("out")))
    } else if dir.join("gaussians.safetensors").is_file() {
        let parent = dir
            .parent()
            .map_or_else(|| dir.join(".."), Path::to_path_buf);
        Ok((parent, dir.to_path_buf()))
    } else {
        Err(ViewError::NotPipelineOutput {
            dir: dir.into(),
            missing: dir.join("out").join("gaussians.safetensors"),
        })
    }
}

/// What a click needs: the masks and the proposals of the same views.
#[derive(Debug)]
struct ClickInputs {
    masks: Masks,
    proposals: Proposals,
}

/// The descriptors selections are scored on, and how.
// One value per opened scene: the variants' sizes (a few hundred bytes of headers) do not
// matter.
#[allow(clippy::large_enum_variant)]
#[derive(Debug)]
enum Scoring {
    /// Prompts and PQ codes: LERF relevancy.
    Relevancy(PromptScores),
    /// PQ codes only: clicks scored by cosine.
    ClickCosine {
        /// The PQ codes.
        pq: DescriptorSet,
    },
}

impl Scoring {
    fn descriptors(&self) -> Descriptors<'_> {
        match self {
            Scoring::Relevancy(s) => s.inputs.descriptors(),
            Scoring::ClickCosine { pq } => pq.as_descriptors(),
        }
    }

    fn kind(&self) -> ScoreKind {
        match self {
            Scoring::Relevancy(_) => ScoreKind::Relevancy,
            Scoring::ClickCosine { .. } => ScoreKind::Cosine,
        }
    }
}

/// The prompts and their scores.
#[derive(Debug)]
struct PromptScores {
    inputs: ScoreInputs,
    /// The prompts offered (every prompt but the canonical negatives), as prompt-file rows.
    offered: Vec<usize>,
    /// LERF relevancy of every Gaussian for each offered prompt.
    relevancy: Vec<Vec<f32>>,
}

/// The opened output.
#[derive(Debug)]
pub struct ViewScene {
    paths: OutputPaths,
    gaussians: Gaussians,
    cameras: Cameras,
    scoring: Option<Scoring>,
    splat: Vec<u8>,
    click: Option<ClickInputs>,
}

/// The scene summary the page starts from (`/api/scene`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct SceneInfo {
    /// Number of Gaussians (rows of `/scene.splat`).
    pub gaussians: usize,
    /// `prompts` (text prompts and clicks), `click_only` (no prompts file: clicks only)
    /// or `gaussians_only` (no selection).
    pub mode: &'static str,
    /// The prompts offered, in prompts-file order (none when viewing Gaussians only or
    /// click only).
    pub prompts: Vec<String>,
    /// The score the threshold applies to: `relevancy` (LERF, with prompts) or `cosine`
    /// (click only).
    pub score: &'static str,
    /// The slider's initial threshold: [`DEFAULT_RELEVANCY_THRESHOLD`] for relevancy,
    /// [`DEFAULT_CLICK_COSINE_THRESHOLD`] for cosine.
    pub default_threshold: f32,
    /// One camera preset per view.
    pub views: Vec<Preset>,
    /// Whether clicks can be resolved (masks, proposals and PQ codes present).
    pub click: bool,
}

impl ViewScene {
    /// Finds, reads and checks the files of the pipeline output `dir` and scores every
    /// offered prompt.
    pub fn open(dir: &Path) -> Result<ViewScene> {
        ViewScene::open_paths(OutputPaths::find(dir)?)
    }

    /// Reads and checks the files of `paths` and scores every offered prompt.
    ///
    /// From this call on the process reads files into memory instead of mapping them
    /// ([`profuse_formats::read_files_into_memory`]): a viewer runs for hours, and a mapped
    /// input that someone copies over in place would kill it (SIGBUS) at its next request.
    pub fn open_paths(paths: OutputPaths) -> Result<ViewScene> {
        profuse_formats::read_files_into_memory();
        let gaussians = Gaussians::read(&paths.gaussians)?;
        let cameras = Cameras::read(&paths.cameras)?;
        let gaussians_name = paths.gaussians.display().to_string();
        let click = match &paths.click {
            Some((masks, proposals)) => {
                let inputs = ClickInputs {
                    masks: Masks::read(masks)?,
                    proposals: Proposals::read(proposals)?,
                };
                check_click_inputs(&inputs, &cameras, (masks, proposals), &paths.cameras)?;
                Some(inputs)
            }
            None => None,
        };
        let scoring = match &paths.scoring {
            ScoringPaths::None => None,
            ScoringPaths::Relevancy { prompts, pq } => Some(Scoring::Relevancy(score(
                prompts,
                pq,
                gaussians.len(),
                &gaussians_name,
            )?)),
            ScoringPaths::ClickCosine { pq } => {
                let inputs = click.as_ref().zip(paths.click.as_ref());
                let pq = click_only_descriptors(pq, inputs, &gaussians, &gaussians_name)?;
                Some(Scoring::ClickCosine { pq })
            }
        };
        let splat = splat_bytes(&gaussians);
        Ok(ViewScene {
            paths,
            gaussians,
            cameras,
            scoring,
            splat,
            click,
        })
    }

    /// The files in use.
    pub fn paths(&self) -> &OutputPaths {
        &self.paths
    }

    /// The scene in `.splat` rows.
    pub fn splat(&self) -> &[u8] {
        &self.splat
    }

    /// The summary for the page.
    pub fn info(&self) -> SceneInfo {
        let kind = self
            .scoring
            .as_ref()
            .map_or(ScoreKind::Relevancy, Scoring::kind);
        SceneInfo {
            gaussians: self.gaussians.len(),
            mode: self.paths.scoring.mode(),
            prompts: self.prompt_names(),
            score: kind.name(),
            default_threshold: match kind {
                ScoreKind::Relevancy => DEFAULT_RELEVANCY_THRESHOLD,
                ScoreKind::Cosine => DEFAULT_CLICK_COSINE_THRESHOLD,
            },
            views: presets(&self.cameras),
            click: self.click.is_some() && self.scoring.is_some(),
        }
    }

    /// Names of the offered prompts.
    pub fn prompt_names(&self) -> Vec<String> {
        match &self.scoring {
            Some(Scoring::Relevancy(s)) => {
                let names = &s.inputs.prompts.names;
                s.offered.iter().map(|&i| names[i].clone()).collect()
            }
            _ => Vec::new(),
        }
    }

    fn scoring(&self) -> Result<&Scoring> {
        self.scoring.as_ref().ok_or_else(|| ViewError::BadRequest {
            name: "prompt".into(),
            reason: "viewing Gaussians only: no prompts or PQ codes".into(),
        })
    }

    /// The Gaussians whose relevancy for the offered prompt `name` is >= `threshold`,
    /// ascending (the query library's selection rule). In click-only mode a
    /// [`ViewError::BadRequest`]: the scene has no text prompts.
    pub fn select_prompt(&self, name: &str, threshold: f32) -> Result<Vec<u32>> {
        let scoring = match self.scoring()? {
            Scoring::Relevancy(s) => s,
            Scoring::ClickCosine { .. } => {
                return Err(ViewError::BadRequest {
                    name: "prompt".into(),
                    reason: "the scene has no text prompts (no SCENE/prompts.safetensors): \
                             select by clicking"
                        .into(),
                })
            }
        };
        let names = &scoring.inputs.prompts.names;
        let k = scoring
            .offered
            .iter()
            .position(|&i| names[i] == name)
            .ok_or_else(|| ViewError::BadRequest {
                name: "prompt".into(),
                reason: format!("no offered prompt {name:?}"),
            })?;
        Ok(select(&scoring.relevancy[k], Rule::Threshold(threshold))?.ids)
    }

    /// The Gaussians `ids` (ascending, as a selection gives them) as an INRIA 3DGS PLY
    /// (the query crate's `selected_gaussians`, scene-io's writer): the export of a
    /// selection.
    pub fn export_ply(&self, ids: &[u32]) -> Result<Vec<u8>> {
        let subset = profuse_query::selected_gaussians(&self.gaussians, ids)?;
        Ok(scene_io::ply::inria_ply_bytes(&subset)?)
    }

    /// Query by click (the query crate's `resolve_click`: the clicked mask's proposal
    /// descriptor), scored by relevancy against the prompts file's canonical negatives
    /// (with prompts) or by cosine (click only, as `query run --click --score cosine`),
    /// and thresholded like a prompt.
    pub fn select_click(&self, click: Click, threshold: f32) -> Result<(ClickTarget, Vec<u32>)> {
        let scoring = self.scoring()?;
        let (inputs, (masks_path, proposals_path)) = self
            .click
            .as_ref()
            .zip(self.paths.click.as_ref())
            .ok_or_else(|| ViewError::BadRequest {
                name: "click".into(),
                reason: "query by click needs SCENE/masks.safetensors and \
                         OUT/proposals.safetensors"
                    .into(),
            })?;
        let names = Names {
            gaussians: self.paths.gaussians.display().to_string(),
            cameras: self.paths.cameras.display().to_string(),
            masks: masks_path.display().to_string(),
        };
        let scene = Scene::new(&self.gaussians, &self.cameras, &inputs.masks).named(names);
        let proposals_name = proposals_path.display().to_string();
        let target = resolve_click(
            &scene,
            Some((&inputs.proposals, proposals_name.as_str())),
            click,
            ClickBy::Proposal,
            DEFAULT_TOP_K,
        )?;
        // The click's query vector as a one-row prompts table (plus the canonical
        // negatives for relevancy), scored like a text prompt.
        let prompts = match scoring {
            Scoring::Relevancy(s) => {
                let prompts_name = s.inputs.prompts_path.as_str();
                target.prompts(Some((&s.inputs.prompts, prompts_name)))?
            }
            Scoring::ClickCosine { .. } => target.prompts(None)?,
        };
        let scores = score_prompts(scoring.descriptors(), &prompts, &[0], scoring.kind())?;
        let ids = select(&scores[0], Rule::Threshold(threshold))?.ids;
        Ok((target, ids))
    }
}

/// Reads the prompts and PQ codes, checks them against the Gaussians and scores every
/// prompt but the canonical negatives.
fn score(
    prompts: &Path,
    pq: &Path,
    gaussians: usize,
    gaussians_name: &str,
) -> Result<PromptScores> {
    let inputs = ScoreInputs::load(&DescriptorPath::Pq(pq.to_path_buf()), prompts)?;
    inputs.check_gaussian_count(gaussians, gaussians_name)?;
    let offered = inputs.resolve_prompts(&PromptSelection::All)?;
    let relevancy = inputs.scores(&offered, ScoreKind::Relevancy)?;
    Ok(PromptScores {
        inputs,
        offered,
        relevancy,
    })
}

/// Masks and proposals of another scene would be accepted at start and then refuse every
/// click: they are checked against the cameras (views, image sizes) and each other now.
fn check_click_inputs(
    inputs: &ClickInputs,
    cameras: &Cameras,
    (masks_path, proposals_path): (&PathBuf, &PathBuf),
    cameras_path: &Path,
) -> Result<()> {
    let m = &inputs.masks;
    if m.num_views() != cameras.len() {
        return Err(ViewError::Mismatch {
            file: masks_path.clone(),
            reason: format!(
                "{} views, but the cameras ({}) have {}: the masks of another scene?",
                m.num_views(),
                cameras_path.display(),
                cameras.len()
            ),
        });
    }
    inputs
        .proposals
        .check_against(m, &proposals_path.display().to_string())?;
    Ok(())
}

/// Reads the PQ codes of click-only mode and checks them against the Gaussians and against
/// the masks (with their path) whose proposals' descriptors a click scores with.
fn click_only_descriptors(
    pq: &Path,
    click: Option<(&ClickInputs, &(PathBuf, PathBuf))>,
    gaussians: &Gaussians,
    gaussians_name: &str,
) -> Result<DescriptorSet> {
    let Some((inputs, (masks_path, _))) = click else {
        return Err(ViewError::Mismatch {
            file: pq.to_path_buf(),
            reason: "click-only scoring needs SCENE/masks.safetensors and \
                     OUT/proposals.safetensors"
                .into(),
        });
    };
    let set = DescriptorSet::read(&DescriptorPath::Pq(pq.to_path_buf()))?;
    let (n, dim) = (set.as_descriptors().len(), set.as_descriptors().dim());
    if n != gaussians.len() {
        return Err(profuse_query::QueryError::CountMismatch {
            descriptors: pq.display().to_string(),
            descriptor_count: n,
            gaussians: gaussians_name.into(),
            gaussian_count: gaussians.len(),
        }
        .into());
    }
    if dim != inputs.masks.dim {
        return Err(ViewError::Mismatch {
            file: pq.to_path_buf(),
            reason: format!(
                "descriptors of dimension {dim}, but the masks' features ({}), whose \
                 proposals' descriptors a click is scored with, have dimension {}",
                masks_path.display(),
                inputs.masks.dim
            ),
        });
    }
    Ok(set)
}

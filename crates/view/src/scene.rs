//! A pipeline output opened for viewing: the files found, read, cross-checked and scored
//! once at start-up, so that a selection request is a threshold over stored scores.

use std::path::{Path, PathBuf};

use profuse_formats::{Cameras, FileKind, Gaussians, Masks, Proposals};
use profuse_fuse::{Names, Scene};
use profuse_query::{
    resolve_click, score_prompts, select, Click, ClickBy, ClickTarget, DescriptorPath,
    PromptSelection, Rule, ScoreInputs, ScoreKind, DEFAULT_RELEVANCY_THRESHOLD, DEFAULT_TOP_K,
};

use crate::error::{Result, ViewError};
use crate::presets::{presets, Preset};
use crate::splat::splat_bytes;

/// Where the files of a pipeline output are (SPEC.md §6).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OutputPaths {
    /// `SCENE/cameras.safetensors`.
    pub cameras: PathBuf,
    /// `OUT/gaussians.safetensors`.
    pub gaussians: PathBuf,
    /// `SCENE/prompts.safetensors` and `OUT/pq.safetensors`; absent when viewing
    /// Gaussians only.
    pub scoring: Option<(PathBuf, PathBuf)>,
    /// `SCENE/masks.safetensors` and `OUT/proposals.safetensors` (query by click).
    pub click: Option<(PathBuf, PathBuf)>,
}

impl OutputPaths {
    /// The files of `dir`, which is a scene directory with an `out/` of pipeline outputs
    /// or that `out/` directory itself. Names the first required file that is missing.
    pub fn find(dir: &Path) -> Result<OutputPaths> {
        let (scene, out) = scene_and_out(dir)?;
        let paths = OutputPaths {
            cameras: scene.join("cameras.safetensors"),
            gaussians: out.join("gaussians.safetensors"),
            scoring: Some((
                scene.join("prompts.safetensors"),
                out.join("pq.safetensors"),
            )),
            click: Some((
                scene.join("masks.safetensors"),
                out.join("proposals.safetensors"),
            ))
            .filter(|(m, p)| m.is_file() && p.is_file()),
        };
        let mut required = vec![&paths.cameras];
        if let Some((prompts, pq)) = &paths.scoring {
            required.extend([prompts, pq]);
        }
        for required in required {
            if !required.is_file() {
                return Err(ViewError::NotPipelineOutput {
                    dir: dir.into(),
                    missing: required.clone(),
                });
            }
        }
        Ok(paths)
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
            scoring: None,
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

/// The prompts and their scores.
#[derive(Debug)]
struct Scoring {
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
    /// The prompts offered, in prompts-file order (none when viewing Gaussians only).
    pub prompts: Vec<String>,
    /// The score: always LERF relevancy.
    pub score: &'static str,
    /// The slider's initial threshold.
    pub default_threshold: f32,
    /// One camera preset per view.
    pub views: Vec<Preset>,
    /// Whether clicks can be resolved (masks and proposals present).
    pub click: bool,
}

impl ViewScene {
    /// Finds, reads and checks the files of the pipeline output `dir` and scores every
    /// offered prompt.
    pub fn open(dir: &Path) -> Result<ViewScene> {
        ViewScene::open_paths(OutputPaths::find(dir)?)
    }

    /// Reads and checks the files of `paths` and scores every offered prompt.
    pub fn open_paths(paths: OutputPaths) -> Result<ViewScene> {
        let gaussians = Gaussians::read(&paths.gaussians)?;
        let cameras = Cameras::read(&paths.cameras)?;
        let gaussians_name = paths.gaussians.display().to_string();
        let scoring = match &paths.scoring {
            Some((prompts, pq)) => Some(score(prompts, pq, gaussians.len(), &gaussians_name)?),
            None => None,
        };
        let click = match &paths.click {
            Some((masks, proposals)) => Some(ClickInputs {
                masks: Masks::read(masks)?,
                proposals: Proposals::read(proposals)?,
            }),
            None => None,
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
        SceneInfo {
            gaussians: self.gaussians.len(),
            prompts: self.prompt_names(),
            score: "relevancy",
            default_threshold: DEFAULT_RELEVANCY_THRESHOLD,
            views: presets(&self.cameras),
            click: self.click.is_some() && self.scoring.is_some(),
        }
    }

    /// Names of the offered prompts.
    pub fn prompt_names(&self) -> Vec<String> {
        self.scoring.as_ref().map_or_else(Vec::new, |s| {
            let names = &s.inputs.prompts.names;
            s.offered.iter().map(|&i| names[i].clone()).collect()
        })
    }

    fn scoring(&self) -> Result<&Scoring> {
        self.scoring.as_ref().ok_or_else(|| ViewError::BadRequest {
            name: "prompt".into(),
            reason: "viewing Gaussians only: no prompts or PQ codes".into(),
        })
    }

    /// The Gaussians whose relevancy for the offered prompt `name` is >= `threshold`,
    /// ascending (the query library's selection rule).
    pub fn select_prompt(&self, name: &str, threshold: f32) -> Result<Vec<u32>> {
        let scoring = self.scoring()?;
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
    /// descriptor), scored by relevancy against the prompts file's canonical negatives and
    /// thresholded like a prompt.
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
        let prompts_name = scoring.inputs.prompts_path.clone();
        let prompts = target.prompts(Some((&scoring.inputs.prompts, prompts_name.as_str())))?;
        let scores = score_prompts(
            scoring.inputs.descriptors(),
            &prompts,
            &[0],
            ScoreKind::Relevancy,
        )?;
        let ids = select(&scores[0], Rule::Threshold(threshold))?.ids;
        Ok((target, ids))
    }
}

/// Reads the prompts and PQ codes, checks them against the Gaussians and scores every
/// prompt but the canonical negatives.
fn score(prompts: &Path, pq: &Path, gaussians: usize, gaussians_name: &str) -> Result<Scoring> {
    let inputs = ScoreInputs::load(&DescriptorPath::Pq(pq.to_path_buf()), prompts)?;
    inputs.check_gaussian_count(gaussians, gaussians_name)?;
    let offered = inputs.resolve_prompts(&PromptSelection::All)?;
    let relevancy = inputs.scores(&offered, ScoreKind::Relevancy)?;
    Ok(Scoring {
        inputs,
        offered,
        relevancy,
    })
}

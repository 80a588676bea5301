//! `query run --click`: reads the masks (and proposals), resolves the click to its query
//! vector with the library, and builds the query's inputs around it.

use profuse_formats::{Cameras, FileKind, Gaussians, Masks, Prompts, Proposals};
use profuse_fuse::{Names, Scene};
use profuse_query::{
    resolve_click, Click, ClickTarget, DescriptorPath, DescriptorSet, Inputs, ScoreInputs,
};
use profuse_tools::BoxError;

use crate::args::RunArgs;

/// The inputs of a click query: its one prompt is the click's query vector (plus the
/// canonical negatives of `--prompts`, when given).
pub(crate) fn inputs(
    a: &RunArgs,
    click: &[f64],
    source: &DescriptorPath,
) -> Result<(Inputs, ClickTarget), BoxError> {
    let &[view, x, y] = click else {
        return Err("--click takes three values: VIEW X Y".into());
    };
    if !(view >= 0.0 && view.fract() == 0.0 && view <= u32::MAX as f64) {
        return Err(format!("--click: VIEW must be a view index, got {view}").into());
    }
    let masks_path = a.click.masks.as_ref().ok_or("--click needs --masks FILE")?;
    let gaussians = Gaussians::read(&a.gaussians)?;
    let cameras = Cameras::read(&a.cameras)?;
    let masks = Masks::read(masks_path)?;
    let proposals = a
        .click
        .proposals
        .as_ref()
        .map(Proposals::read)
        .transpose()?;
    let names = Names {
        gaussians: a.gaussians.display().to_string(),
        cameras: a.cameras.display().to_string(),
        masks: masks_path.display().to_string(),
    };
    let proposals_name = a.click.proposals.as_ref().map(|p| p.display().to_string());
    let scene = Scene::new(&gaussians, &cameras, &masks).named(names);
    let (x, y) = match &a.click.click_on_photo {
        None => (x, y),
        Some(path) => {
            let source = Cameras::read(path)?;
            let p = scene_io::photo::photo_to_scene(&source, &cameras, view as usize, [x, y])?
                .ok_or_else(|| {
                    format!("--click-on-photo: photo pixel ({x}, {y}) lies outside the scene's cut")
                })?;
            (p[0], p[1])
        }
    };
    let click = Click {
        view: view as usize,
        x,
        y,
    };
    let target = resolve_click(
        &scene,
        proposals.as_ref().zip(proposals_name.as_deref()),
        click,
        a.click.click_by,
        usize::from(a.k),
    )?;
    let negatives = a
        .descriptors
        .prompts
        .as_ref()
        .map(Prompts::read)
        .transpose()?;
    let negatives_name = a
        .descriptors
        .prompts
        .as_ref()
        .map(|p| p.display().to_string());
    let prompts = target.prompts(negatives.as_ref().zip(negatives_name.as_deref()))?;
    let scoring = ScoreInputs::new(
        DescriptorSet::read(source)?,
        prompts,
        &source.path().display().to_string(),
        "the click's query vector",
    )?;
    let inputs = Inputs::new(
        scoring,
        gaussians,
        cameras,
        &a.gaussians.display().to_string(),
        &a.cameras.display().to_string(),
    )?;
    Ok((inputs, target))
}

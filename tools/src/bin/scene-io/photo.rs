//! `scene-io to-photo` and `scene-io photo-point`: between a prepared scene's pixels and
//! the user's original photos (`scene_io::photo`).

use std::path::{Path, PathBuf};

use profuse_formats::{Cameras, FileKind};
use profuse_tools::{write_png, BoxError};
use scene_io::photo::{photo_to_scene, scene_mask_to_photo};
use serde_json::{json, Value};

/// The cameras of a prepared scene: the scene's and the original photos'.
#[derive(Debug, clap::Args)]
pub struct SceneCameras {
    /// A scene directory made by `profuse prepare` (cameras.safetensors and
    /// source_cameras.safetensors).
    #[arg(long)]
    pub scene: PathBuf,
    /// The view (index into the scene's cameras).
    #[arg(long)]
    pub view: usize,
}

impl SceneCameras {
    fn read(&self) -> Result<(Cameras, Cameras), BoxError> {
        let scene = Cameras::read(self.scene.join("cameras.safetensors"))?;
        let source = Cameras::read(self.scene.join("source_cameras.safetensors"))?;
        Ok((source, scene))
    }
}

/// `scene-io to-photo`: a mask PNG in the scene's pixels -> the same mask on the photo.
pub fn to_photo(at: &SceneCameras, mask: &Path, out: &Path) -> Result<Value, BoxError> {
    profuse_tools::check_outputs([out])?;
    let (source, scene) = at.read()?;
    let img = image::open(mask)
        .map_err(|e| format!("{}: {e}", mask.display()))?
        .to_luma8();
    let on_photo = scene_mask_to_photo(img.as_raw(), &source, &scene, at.view)?;
    let [w, h] = source.image_size[at.view];
    write_png(out, &on_photo, w, h, image::ExtendedColorType::L8)?;
    let set = on_photo.iter().filter(|&&m| m > 0).count();
    Ok(json!({
        "view": at.view,
        "photo": source.image_names[at.view],
        "size": [w, h],
        "selected_pixels": set,
        "out": out.to_string_lossy(),
    }))
}

/// `scene-io photo-point`: a pixel position on the photo -> the scene's pixel position.
pub fn photo_point(at: &SceneCameras, x: f64, y: f64) -> Result<Value, BoxError> {
    let (source, scene) = at.read()?;
    let p = photo_to_scene(&source, &scene, at.view, [x, y])?.ok_or_else(|| {
        format!(
            "photo pixel ({x}, {y}) of view {} lies outside the scene's image (cut off by the \
             undistortion)",
            at.view
        )
    })?;
    Ok(json!({"view": at.view, "photo": [x, y], "scene": p}))
}

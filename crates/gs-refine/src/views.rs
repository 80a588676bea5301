//! Loading the training views: cameras rescaled to the training size and their photos
//! resampled to it.

use std::path::Path;

use profuse_formats::Cameras;
use rayon::prelude::*;
use splat_raster::ViewCamera;

use crate::error::{RefineError, Result};
use crate::images::{image_path, load_target, scaled_size, Target};

/// One training view: its id in the cameras file, its camera at the training size, and
/// its target image.
pub type View = (usize, ViewCamera, Target);

/// The views of `cameras` except `exclude`, at `scale` × their size (intrinsics rescaled
/// with `profuse_formats::camera::rescale_intrinsics`), with their photos from `images`
/// (gs-init's lookup: `images/name`, else `images/<file name>`) area-averaged to that size.
pub fn load_views(
    cameras: &Cameras,
    images: &Path,
    scale: f64,
    exclude: &[usize],
) -> Result<Vec<View>> {
    if !(scale > 0.0 && scale <= 1.0) {
        return Err(RefineError::Config {
            name: "scale",
            value: scale.to_string(),
            expected: "in (0, 1]",
        });
    }
    let ids: Vec<usize> = (0..cameras.len())
        .filter(|v| !exclude.contains(v))
        .collect();
    ids.par_iter()
        .map(|&v| {
            let cam = ViewCamera::from_cameras(cameras, v)?;
            let size = [cam.width, cam.height];
            let to = scaled_size(size, scale);
            let name = cameras.image_names.get(v).map_or("", |s| s.as_str());
            let target = load_target(&image_path(images, name), v, size, to)?;
            Ok((v, cam.at_grid(to[0], to[1]), target))
        })
        .collect()
}

/// A held-out check of one view: the render, its PSNR against the photo over every pixel
/// (render clamped to [0, 1]), and its coverage (fraction of pixels with accumulated alpha
/// 1 − T > 0.5, examples/fox.sh's definition).
#[derive(Debug, Clone, PartialEq)]
pub struct Eval {
    /// The view id.
    pub view: usize,
    /// PSNR in dB.
    pub psnr: f64,
    /// Covered fraction of the pixels.
    pub coverage: f64,
    /// The render `[H, W, 3]`, clamped to [0, 1].
    pub render: Vec<f32>,
}

/// Renders `view` from `p` over a black background and compares it with its target.
pub fn evaluate(p: &crate::Params, view: &View) -> Eval {
    let (v, cam, target) = view;
    let mut st = crate::ViewState::default();
    crate::forward(p, cam, [0.0; 3], &mut st);
    let render: Vec<f32> = st.color().iter().map(|c| c.clamp(0.0, 1.0)).collect();
    let mse = render
        .iter()
        .zip(&target.rgb)
        .map(|(a, b)| (f64::from(*a) - f64::from(*b)).powi(2))
        .sum::<f64>()
        / render.len().max(1) as f64;
    let t = st.transmittance();
    let covered = t.iter().filter(|t| 1.0 - **t > 0.5).count();
    Eval {
        view: *v,
        psnr: crate::loss::psnr(mse),
        coverage: covered as f64 / t.len().max(1) as f64,
        render,
    }
}

//! From the scene back to the user's photo: `profuse prepare` undistorts every photo and
//! cuts it to its valid area (SPEC.md §6), so a pixel of the scene is not the pixel of
//! the photo the user took. These functions map between the two through the original
//! camera (lens included) and the scene's pinhole camera of the same view: a click given
//! on the photo becomes a scene pixel, and a selection mask rendered in the scene's
//! pixels is laid onto the photo.
//!
//! ```
//! use profuse_formats::Cameras;
//! use scene_io::photo::{photo_to_scene, scene_mask_to_photo};
//!
//! // One 8 x 6 view without a lens whose scene image is its cut [2, 1, 8, 6].
//! let source = Cameras {
//!     image_names: vec!["a.jpg".into()],
//!     image_size: vec![[8, 6]].into(),
//!     intrinsics: vec![[10.0, 10.0, 4.0, 3.0]].into(),
//!     world_to_camera: vec![[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]].into(),
//!     ..Default::default()
//! };
//! let rect = [2, 1, 8, 6];
//! let scene = Cameras { image_names: vec!["images/a.png".into()],
//!     ..scene_io::undistort::cropped(&source, &[rect]) };
//! assert_eq!(photo_to_scene(&source, &scene, 0, [2.5, 1.5])?, Some([0.5, 0.5]));
//! let mask: Vec<u8> = (0..6 * 5).map(|i| if i == 0 { 255 } else { 0 }).collect();
//! let on_photo = scene_mask_to_photo(&mask, &source, &scene, 0)?;
//! assert_eq!(on_photo[1 * 8 + 2], 255); // photo pixel (2, 1) is scene pixel (0, 0)
//! assert_eq!(on_photo.iter().filter(|&&m| m == 255).count(), 1);
//! # Ok::<(), scene_io::SceneError>(())
//! ```

use std::path::Path;

use profuse_formats::camera::{pixel_centre, undistort_pixel};
use profuse_formats::Cameras;

use crate::error::{invalid, Result};

/// View `v` of a source camera and its scene camera: the source's intrinsics and lens,
/// the cut's origin in the uncut pinhole image, the scene image's size.
type ViewPair = ([f64; 4], [f64; 4], [f64; 2], [u32; 2]);

/// Checks that view `v` of both files is one photo seen through one focal length.
fn view_pair(source: &Cameras, scene: &Cameras, v: usize) -> Result<ViewPair> {
    let label = "source cameras";
    if source.len() != scene.len() {
        return Err(invalid(
            label,
            "views",
            format!(
                "{} views, but the scene's cameras have {}",
                source.len(),
                scene.len()
            ),
        ));
    }
    if v >= scene.len() {
        return Err(invalid(
            label,
            "view",
            format!("{v} is out of range: the scene has {} views", scene.len()),
        ));
    }
    let stem = |n: &str| Path::new(n).file_stem().map(|s| s.to_os_string());
    if stem(&source.image_names[v]) != stem(&scene.image_names[v]) {
        return Err(invalid(
            label,
            format!("image_names[{v}]"),
            format!(
                "{:?} is not the photo of the scene's view {v} ({:?})",
                source.image_names[v], scene.image_names[v]
            ),
        ));
    }
    let [fx, fy, cx, cy] = source.intrinsics[v];
    let [sfx, sfy, scx, scy] = scene.intrinsics[v];
    if fx != sfx || fy != sfy {
        return Err(invalid(
            label,
            format!("intrinsics[{v}]"),
            format!("focal ({fx}, {fy}) differs from the scene's ({sfx}, {sfy}): not its source"),
        ));
    }
    let lens = source.distortion.as_ref().map_or([0.0; 4], |d| d[v]);
    Ok((
        source.intrinsics[v],
        lens,
        [cx - scx, cy - scy],
        scene.image_size[v],
    ))
}

/// The scene pixel position of photo pixel position `p` (both with pixel centres at
/// +0.5) of view `v`: undistorted with the source camera's lens, then moved by the cut.
/// `None` when the lens cannot be inverted there or the point falls outside the scene's
/// image.
pub fn photo_to_scene(
    source: &Cameras,
    scene: &Cameras,
    v: usize,
    p: [f64; 2],
) -> Result<Option<[f64; 2]>> {
    let (intrinsics, lens, origin, [w, h]) = view_pair(source, scene, v)?;
    Ok(undistort_pixel(&intrinsics, &lens, p)
        .map(|q| [q[0] - origin[0], q[1] - origin[1]])
        .filter(|q| q[0] >= 0.0 && q[1] >= 0.0 && q[0] <= f64::from(w) && q[1] <= f64::from(h)))
}

/// A single-channel mask of the scene's view `v` (row-major, the scene image's size) laid
/// onto the original photo: every photo pixel takes the value of the scene pixel its
/// centre maps to (nearest), 0 where it maps outside the cut. The result has the photo's
/// size (`source.image_size[v]`).
pub fn scene_mask_to_photo(
    mask: &[u8],
    source: &Cameras,
    scene: &Cameras,
    v: usize,
) -> Result<Vec<u8>> {
    let (intrinsics, lens, origin, [w, h]) = view_pair(source, scene, v)?;
    let (w, h) = (w as usize, h as usize);
    if mask.len() != w * h {
        return Err(invalid(
            "mask",
            "size",
            format!("{} pixels, but the scene's view {v} is {w}x{h}", mask.len()),
        ));
    }
    let [pw, ph] = source.image_size[v].map(|s| s as usize);
    let mut out = vec![0u8; pw * ph];
    for (y, row) in out.chunks_exact_mut(pw).enumerate() {
        for (x, o) in row.iter_mut().enumerate() {
            let Some(q) = undistort_pixel(&intrinsics, &lens, pixel_centre(x, y)) else {
                continue;
            };
            let (sx, sy) = ((q[0] - origin[0]).floor(), (q[1] - origin[1]).floor());
            if sx >= 0.0 && sy >= 0.0 && (sx as usize) < w && (sy as usize) < h {
                *o = mask[sy as usize * w + sx as usize];
            }
        }
    }
    Ok(out)
}

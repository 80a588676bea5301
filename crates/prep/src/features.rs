//! `prep features`: replace the descriptor of every mask of a masks file, from the SAM
//! image embedding ([`sam_features`]) or a CLIP image encoder over mask crops
//! ([`clip_features`]); labels and offsets are kept as they are.

use std::path::Path;
use std::time::Instant;

use profuse_formats::{Cameras, Floats, Masks};
use serde::Serialize;

use crate::clip::{image_input, ClipModel};
use crate::error::{input, Result};
use crate::pool::pool_embedding;
use crate::sam::{secs, Sam};

/// Figures of a features run.
#[derive(Debug, Clone, Serialize)]
pub struct FeaturesReport {
    /// Which descriptor (`sam_embedding` or `clip_image`).
    pub feature: &'static str,
    /// Masks described.
    pub masks: usize,
    /// Descriptor dimension.
    pub dim: usize,
    /// Views with at least one mask (the others are not read).
    pub views: usize,
    /// Wall seconds.
    pub seconds: f64,
}

/// Checks that the masks file belongs to the cameras file.
fn check_views(masks: &Masks, cameras: &Cameras) -> Result<()> {
    if masks.view_names != cameras.image_names {
        return Err(input(
            "masks file",
            "its view_names differ from the cameras file's image_names (view v must be view v)",
        ));
    }
    Ok(())
}

/// One view's labels as u16 (`u16::MAX` = none).
pub fn view_labels(masks: &Masks, v: usize) -> Vec<u16> {
    let plane = masks.width * masks.height;
    (v * plane..(v + 1) * plane)
        .map(|i| {
            masks
                .labels
                .get(i)
                .map_or(u16::MAX, |l| l.min(u32::from(u16::MAX) - 1) as u16)
        })
        .collect()
}

/// The masks with new features (row-major [M, dim]) and a `feature` metadata entry.
fn with_features(masks: &Masks, features: Vec<f32>, dim: usize, feature: &str) -> Masks {
    let mut out = masks.clone();
    out.features = Floats::F32(features.into());
    out.dim = dim;
    out.extra.insert("feature".to_string(), feature.to_string());
    out
}

/// SAM-embedding descriptors: the encoder runs once per view with masks, the embedding is
/// pooled over each mask's label-map pixels ([`pool_embedding`]).
pub fn sam_features(
    sam: &mut Sam,
    masks: &Masks,
    cameras: &Cameras,
    images: &Path,
    progress: &dyn Fn(usize, usize),
) -> Result<(Masks, FeaturesReport)> {
    check_views(masks, cameras)?;
    if masks.num_views() > 0 && masks.masks_in_view(0) > usize::from(u16::MAX) {
        return Err(input(
            "masks file",
            "more masks in a view than u16 labels allow",
        ));
    }
    let t = Instant::now();
    let views: Vec<usize> = (0..masks.num_views())
        .filter(|v| masks.masks_in_view(*v) > 0)
        .collect();
    let mut feats = Vec::with_capacity(masks.num_masks() * crate::sam::EMBED_DIM);
    for (k, &v) in views.iter().enumerate() {
        let img = crate::image::load_view_image(images, cameras, v)?;
        let emb = sam.encode(&img)?;
        let labels = view_labels(masks, v);
        feats.extend(pool_embedding(
            &emb,
            &labels,
            (masks.height, masks.width),
            masks.masks_in_view(v),
        ));
        progress(k + 1, views.len());
    }
    let dim = crate::sam::EMBED_DIM;
    let report = FeaturesReport {
        feature: "sam_embedding",
        masks: masks.num_masks(),
        dim,
        views: views.len(),
        seconds: secs(t),
    };
    Ok((with_features(masks, feats, dim, "sam_embedding"), report))
}

/// CLIP image descriptors of mask crops ([`image_input`]): each mask's pixels are its
/// label-map cells scaled to the image (nearest cell), its box their bounding box.
pub fn clip_features(
    clip: &mut ClipModel,
    masks: &Masks,
    cameras: &Cameras,
    images: &Path,
    progress: &dyn Fn(usize, usize),
) -> Result<(Masks, FeaturesReport)> {
    check_views(masks, cameras)?;
    let t = Instant::now();
    let views: Vec<usize> = (0..masks.num_views())
        .filter(|v| masks.masks_in_view(*v) > 0)
        .collect();
    let mut feats = Vec::new();
    let mut dim = 0;
    for (k, &v) in views.iter().enumerate() {
        let img = crate::image::load_view_image(images, cameras, v)?;
        let labels = view_labels(masks, v);
        let (gw, gh) = (masks.width, masks.height);
        let cell_x: Vec<usize> = (0..img.width)
            .map(|x| (x * gw / img.width).min(gw - 1))
            .collect();
        let cell_y: Vec<usize> = (0..img.height)
            .map(|y| (y * gh / img.height).min(gh - 1))
            .collect();
        let boxes = image_boxes(
            &labels,
            (gh, gw),
            (img.width, img.height),
            masks.masks_in_view(v),
        );
        for (m, bbox) in boxes.iter().enumerate() {
            let bbox = bbox.unwrap_or([0, 0, img.width - 1, img.height - 1]);
            let inside = |x: usize, y: usize| usize::from(labels[cell_y[y] * gw + cell_x[x]]) == m;
            let e = clip.embed_image(image_input(&img, bbox, &inside))?;
            dim = e.len();
            feats.extend(e);
        }
        progress(k + 1, views.len());
    }
    if dim == 0 {
        return Err(input("masks file", "has no masks to describe"));
    }
    let report = FeaturesReport {
        feature: "clip_image",
        masks: masks.num_masks(),
        dim,
        views: views.len(),
        seconds: secs(t),
    };
    Ok((with_features(masks, feats, dim, "clip_image"), report))
}

/// Inclusive image-pixel boxes of each local mask (the image pixels whose nearest label
/// cell is the mask's), `None` for a mask without cells.
pub fn image_boxes(
    labels: &[u16],
    grid: (usize, usize),
    image: (usize, usize),
    masks: usize,
) -> Vec<Option<[usize; 4]>> {
    let (gh, gw) = grid;
    let (iw, ih) = image;
    let mut cells: Vec<Option<[usize; 4]>> = vec![None; masks];
    for y in 0..gh {
        for x in 0..gw {
            let l = usize::from(labels[y * gw + x]);
            if l < masks {
                cells[l] = Some(match cells[l] {
                    None => [x, y, x, y],
                    Some(b) => [b[0].min(x), b[1].min(y), b[2].max(x), b[3].max(y)],
                });
            }
        }
    }
    // Image pixel x maps to cell floor(x * gw / iw): cell c covers x in
    // [ceil(c * iw / gw), ceil((c + 1) * iw / gw) - 1].
    let first = |c: usize, n: usize, g: usize| (c * n).div_ceil(g);
    cells
        .into_iter()
        .map(|b| {
            b.map(|b| {
                [
                    first(b[0], iw, gw),
                    first(b[1], ih, gh),
                    (first(b[2] + 1, iw, gw) - 1).min(iw - 1),
                    (first(b[3] + 1, ih, gh) - 1).min(ih - 1),
                ]
            })
        })
        .collect()
}

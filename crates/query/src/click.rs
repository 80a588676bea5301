//! Query by click: the "prompt" is the descriptor of the mask under a pixel — its 3D Context
//! Proposal's pooled descriptor (paper eq. proposal-desc, formed by
//! [`profuse_fuse::pooled_descriptor`], the registration's own code) or the mask's own
//! feature — and it is scored, selected and rendered exactly like a text embedding.
//!
//! A click is a point (x, y) in pixel coordinates of the view's **image** (SPEC.md §3.3:
//! x is the column, y the row, pixel (c, r) covers [c, c+1) × [r, r+1), so the integer
//! pixel index itself selects that pixel). The masks' grid may be coarser or finer than
//! the image: the click falls into grid cell (⌊x·W/w⌋, ⌊y·H/h⌋).

use std::collections::BTreeMap;

use profuse_formats::{format_float, Masks, Prompts, Proposals, NO_PROPOSAL};
use profuse_fuse::{pooled_descriptor, Scene};

use crate::error::{QueryError, Result};
use crate::score::{unit_vector, CANONICAL_NEGATIVES};

/// What the clicked mask contributes as the query vector.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum ClickBy {
    /// The pooled descriptor of the mask's proposal, the descriptor the registration gave
    /// its pixels (a mask in no proposal falls back to its own feature, as fuse's default
    /// `singleton` orphans do).
    #[default]
    Proposal,
    /// The mask's own feature.
    Mask,
}

/// Where the query vector of a resolved click came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ClickSource {
    /// The pooled descriptor of the clicked mask's proposal.
    Proposal,
    /// The clicked mask's own feature (`--click-by mask`).
    Mask,
    /// The mask's own feature, because it is in no proposal.
    OrphanMask,
}

/// A click: view index and a point in that view's image, x = column, y = row.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Click {
    /// View index (into the cameras and masks files).
    pub view: usize,
    /// Column coordinate in pixels, in [0, image width).
    pub x: f64,
    /// Row coordinate in pixels, in [0, image height).
    pub y: f64,
}

/// A click resolved to its mask and query vector.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ClickTarget {
    /// The click.
    pub click: Click,
    /// The mask-grid cell (column, row) under it.
    pub cell: [usize; 2],
    /// The global id of the mask under it.
    pub mask: u32,
    /// Its proposal, if it has one (and proposals were given).
    pub proposal: Option<u32>,
    /// Masks pooled into the query vector (1 for a mask's own feature).
    pub members: usize,
    /// Where the query vector came from.
    pub source: ClickSource,
    /// The query vector, unit norm.
    #[serde(skip)]
    pub embedding: Vec<f32>,
}

/// Resolves `click` on `scene` (Gaussians, cameras, masks of the same views) to the mask
/// under it and its query vector. `proposals` (with its file name for messages) is
/// required for [`ClickBy::Proposal`]; `k` is the top-K of the mask-mass rendering (the
/// registration's K, so the descriptor is the one fuse registered).
pub fn resolve_click(
    scene: &Scene<'_>,
    proposals: Option<(&Proposals, &str)>,
    click: Click,
    by: ClickBy,
    k: usize,
) -> Result<ClickTarget> {
    let cameras = scene.cameras;
    if click.view >= cameras.len() {
        return Err(QueryError::ViewOutOfRange {
            path: scene.names.cameras.clone(),
            view: click.view,
            views: cameras.len(),
        });
    }
    scene.check()?;
    let masks = scene.masks;
    let cell = click_cell(scene, click)?;
    let mask = masks.mask_at(click.view, cell[0], cell[1]).ok_or_else(|| {
        QueryError::NoMaskUnderPixel {
            masks: scene.names.masks.clone(),
            view: click.view,
            x: click.x,
            y: click.y,
            cell,
        }
    })?;
    let proposal = match (by, proposals) {
        (ClickBy::Mask, _) => None,
        (ClickBy::Proposal, None) => return Err(QueryError::MissingProposals),
        (ClickBy::Proposal, Some((p, name))) => {
            p.check_against(masks, name)?;
            Some(p.mask_proposal[mask as usize]).filter(|p| *p != NO_PROPOSAL)
        }
    };
    let (embedding, members, source) = match (proposal, proposals) {
        (Some(id), Some((p, _))) => {
            let members: Vec<u32> = (0..p.mask_proposal.len() as u32)
                .filter(|&m| p.mask_proposal[m as usize] == id)
                .collect();
            // Members weigh as fuse's default registers them (mass times share).
            let shares = p.mask_share.as_deref();
            let pooled = pooled_descriptor(scene, &members, shares, k)?;
            let unit = pooled.as_deref().and_then(unit_vector).ok_or_else(|| {
                QueryError::NoClickDescriptor {
                    reason: format!(
                        "proposal {id} ({} masks) of the mask under the click is hit by no \
                         Gaussian, so it has no descriptor",
                        members.len()
                    ),
                }
            })?;
            (unit, members.len(), ClickSource::Proposal)
        }
        _ => {
            let source = match by {
                ClickBy::Mask => ClickSource::Mask,
                ClickBy::Proposal => ClickSource::OrphanMask,
            };
            (mask_feature(masks, mask, &scene.names.masks)?, 1, source)
        }
    };
    Ok(ClickTarget {
        click,
        cell,
        mask,
        proposal,
        members,
        source,
        embedding,
    })
}

/// The mask-grid cell under the click, or [`QueryError::PixelOutsideImage`].
fn click_cell(scene: &Scene<'_>, click: Click) -> Result<[usize; 2]> {
    let [w, h] = scene.cameras.image_size[click.view];
    let (iw, ih) = (f64::from(w), f64::from(h));
    let inside = |v: f64, size: f64| v.is_finite() && v >= 0.0 && v < size;
    if !(inside(click.x, iw) && inside(click.y, ih)) {
        return Err(QueryError::PixelOutsideImage {
            cameras: scene.names.cameras.clone(),
            view: click.view,
            x: click.x,
            y: click.y,
            width: w,
            height: h,
        });
    }
    let (gw, gh) = (scene.masks.width, scene.masks.height);
    let cx = ((click.x * gw as f64 / iw) as usize).min(gw - 1);
    let cy = ((click.y * gh as f64 / ih) as usize).min(gh - 1);
    Ok([cx, cy])
}

fn mask_feature(masks: &Masks, mask: u32, name: &str) -> Result<Vec<f32>> {
    let d = masks.dim;
    let mut row = vec![0f32; d];
    masks.features.read_into(mask as usize * d, &mut row);
    unit_vector(&row).ok_or_else(|| QueryError::NoClickDescriptor {
        reason: format!("{name}: the feature of mask {mask} is zero or not finite"),
    })
}

impl ClickTarget {
    /// The name the click's outputs use: `click_v<view>_x<x>_y<y>`, numbers in their
    /// shortest round-trip form.
    pub fn name(&self) -> String {
        let c = &self.click;
        format!(
            "click_v{}_x{}_y{}",
            c.view,
            format_float(c.x),
            format_float(c.y)
        )
    }

    /// A prompts table whose first row is the click's query vector (named
    /// [`ClickTarget::name`]), followed by the canonical negatives of `negatives` when
    /// given, so the LERF relevancy can score a click as it scores text.
    pub fn prompts(&self, negatives: Option<(&Prompts, &str)>) -> Result<Prompts> {
        let d = self.embedding.len();
        let mut names = vec![self.name()];
        let mut embeddings = self.embedding.clone();
        if let Some((p, path)) = negatives {
            if p.dim != d {
                return Err(QueryError::DimMismatch {
                    prompts: path.into(),
                    prompt_dim: p.dim,
                    descriptors: "the masks' features".into(),
                    descriptor_dim: d,
                });
            }
            for (q, n) in p.names.iter().enumerate() {
                if CANONICAL_NEGATIVES.contains(&n.as_str()) {
                    names.push(n.clone());
                    embeddings.extend_from_slice(p.embedding(q));
                }
            }
        }
        Ok(Prompts {
            names,
            dim: d,
            embeddings: embeddings.into(),
            class_ids: None,
            extra: BTreeMap::new(),
        })
    }

    /// Metadata for the selection file: where the query vector came from.
    pub fn metadata(&self) -> BTreeMap<String, String> {
        let c = &self.click;
        let mut m = BTreeMap::new();
        m.insert("click_view".into(), c.view.to_string());
        m.insert("click_x".into(), format_float(c.x));
        m.insert("click_y".into(), format_float(c.y));
        m.insert("click_mask".into(), self.mask.to_string());
        let source = match self.source {
            ClickSource::Proposal => "proposal",
            ClickSource::Mask => "mask",
            ClickSource::OrphanMask => "orphan_mask",
        };
        m.insert("click_by".into(), source.into());
        if let Some(p) = self.proposal {
            m.insert("click_proposal".into(), p.to_string());
        }
        m
    }
}

//! Input checks and the coordinate maps shared by every pair: warp grid cell -> mask
//! pixel of the source view, warp value -> mask or grid coordinates of a view.

use std::borrow::Cow;
use std::collections::HashMap;

use profuse_formats::{Cameras, Floats, Labels, Masks, Matches, WarpCoords};

use crate::error::{Result, WarpGraphError};

/// "No mask" in the label planes used internally (whatever the file's dtype).
pub(crate) const NONE: u32 = u32::MAX;

/// One axis of an affine map `out = scale * in + offset`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Axis {
    pub(crate) scale: f64,
    pub(crate) offset: f64,
}

impl Axis {
    #[inline]
    pub(crate) fn apply(self, v: f64) -> f64 {
        self.scale * v + self.offset
    }
}

/// The checked inputs and the maps derived from them.
#[derive(Debug)]
pub(crate) struct Frame<'a> {
    pub(crate) masks: &'a Masks,
    pub(crate) matches: &'a Matches,
    pub(crate) cameras: Option<&'a Cameras>,
    /// Warp grid width and height.
    pub(crate) gw: usize,
    pub(crate) gh: usize,
    /// Mask grid width and height.
    pub(crate) mw: usize,
    pub(crate) mh: usize,
    /// Mask column of each grid column's centre, and mask row of each grid row's centre.
    pub(crate) xmap: Vec<usize>,
    pub(crate) ymap: Vec<usize>,
    /// Row of `pairs` of each ordered pair.
    pub(crate) pair_index: HashMap<(u32, u32), usize>,
}

impl<'a> Frame<'a> {
    /// Checks that the inputs describe the same views and have consistent lengths.
    pub(crate) fn new(
        masks: &'a Masks,
        matches: &'a Matches,
        cameras: Option<&'a Cameras>,
    ) -> Result<Self> {
        let views = masks.num_views();
        if matches.num_views != views {
            return Err(WarpGraphError::ViewCountMismatch {
                masks: views,
                matches: matches.num_views,
            });
        }
        if let Some(c) = cameras {
            check_cameras(c, views)?;
        }
        check_masks(masks)?;
        let (gw, gh) = (matches.width, matches.height);
        let cells = matches.pairs.len() * gw * gh;
        check_len(
            "matches",
            "warp",
            matches.warp.len(),
            2 * cells,
            "P x H x W x 2",
        )?;
        check_len(
            "matches",
            "certainty",
            matches.certainty.len(),
            cells,
            "P x H x W",
        )?;
        let mut pair_index = HashMap::with_capacity(matches.pairs.len());
        for (row, &[i, j]) in matches.pairs.iter().enumerate() {
            for view in [i, j] {
                if view as usize >= views {
                    return Err(WarpGraphError::PairOutOfRange { row, view, views });
                }
            }
            if i == j {
                return Err(WarpGraphError::BadPair {
                    row,
                    i,
                    j,
                    reason: "a view paired with itself",
                });
            }
            if pair_index.insert((i, j), row).is_some() {
                return Err(WarpGraphError::BadPair {
                    row,
                    i,
                    j,
                    reason: "repeats an earlier ordered pair",
                });
            }
        }
        if matches.coords == WarpCoords::Pixels && cameras.is_none() {
            return Err(WarpGraphError::MissingCameras {
                what: "matches with `coords = pixels` (image sizes convert pixels to mask cells)",
            });
        }
        let (mw, mh) = (masks.width, masks.height);
        if (mw == 0 || mh == 0) && gw * gh > 0 {
            return Err(WarpGraphError::Shape {
                input: "masks",
                tensor: "labels",
                found: 0,
                expected: format!("a non-empty label grid per view (H x W is {mh} x {mw})"),
            });
        }
        Ok(Frame {
            masks,
            matches,
            cameras,
            gw,
            gh,
            mw,
            mh,
            xmap: centre_map(gw, mw),
            ymap: centre_map(gh, mh),
            pair_index,
        })
    }

    /// Image size of a view; only called where cameras are known to be present or the
    /// coordinates are normalised (where the size cancels out).
    fn image_size(&self, view: usize) -> [f64; 2] {
        self.cameras
            .and_then(|c| c.image_size.get(view))
            .map_or([1.0, 1.0], |s| [f64::from(s[0]), f64::from(s[1])])
    }

    /// Maps a warp value aimed at `view` to continuous coordinates of a `w x h` grid laid
    /// over that view's image (corner origin, cell centres at +0.5).
    fn warp_to(&self, view: usize, w: usize, h: usize) -> [Axis; 2] {
        let (w, h) = (w as f64, h as f64);
        match self.matches.coords {
            WarpCoords::Normalized => [
                Axis {
                    scale: w / 2.0,
                    offset: w / 2.0,
                },
                Axis {
                    scale: h / 2.0,
                    offset: h / 2.0,
                },
            ],
            WarpCoords::Pixels => {
                let [iw, ih] = self.image_size(view);
                [
                    Axis {
                        scale: w / iw,
                        offset: 0.0,
                    },
                    Axis {
                        scale: h / ih,
                        offset: 0.0,
                    },
                ]
            }
        }
    }

    /// Warp value aimed at `view` -> continuous mask-grid coordinates of `view`.
    pub(crate) fn warp_to_mask(&self, view: usize) -> [Axis; 2] {
        self.warp_to(view, self.mw, self.mh)
    }

    /// Warp value aimed at `view` -> continuous warp-grid coordinates of `view`.
    pub(crate) fn warp_to_grid(&self, view: usize) -> [Axis; 2] {
        self.warp_to(view, self.gw, self.gh)
    }

    /// Cells of one pair's grid.
    pub(crate) fn cells(&self) -> usize {
        self.gw * self.gh
    }

    /// The warp plane of pair row `p` as f32 (borrowed when stored as F32).
    pub(crate) fn warp_plane(&self, p: usize) -> Cow<'a, [f32]> {
        let n = 2 * self.cells();
        f32_plane(&self.matches.warp, p * n, n)
    }

    /// The certainty plane of pair row `p` as f32.
    pub(crate) fn certainty_plane(&self, p: usize) -> Cow<'a, [f32]> {
        let n = self.cells();
        f32_plane(&self.matches.certainty, p * n, n)
    }

    /// View `v`'s label plane (mask grid) as u32 with [`NONE`] for no mask, checked
    /// against the view's mask count.
    pub(crate) fn label_plane(&self, v: usize) -> Result<Vec<u32>> {
        let plane = self.mw * self.mh;
        let count = self.masks.masks_in_view(v);
        let start = v * plane;
        let out: Vec<u32> = match &self.masks.labels {
            Labels::U16(b) => b[start..start + plane]
                .iter()
                .map(|&l| if l == u16::MAX { NONE } else { u32::from(l) })
                .collect(),
            Labels::U32(b) => b[start..start + plane].to_vec(),
        };
        if let Some(pixel) = out.iter().position(|&l| l != NONE && l as usize >= count) {
            return Err(WarpGraphError::LabelOutOfRange {
                view: v,
                pixel,
                label: out[pixel],
                count,
            });
        }
        Ok(out)
    }
}

/// For each of `n` cells of a grid, the index of the cell of an `m`-cell grid over the
/// same extent that contains its centre.
fn centre_map(n: usize, m: usize) -> Vec<usize> {
    (0..n)
        .map(|x| {
            let c = ((x as f64 + 0.5) * m as f64 / n as f64).floor() as usize;
            c.min(m.saturating_sub(1))
        })
        .collect()
}

fn f32_plane(f: &Floats, start: usize, len: usize) -> Cow<'_, [f32]> {
    match f {
        Floats::F32(b) => Cow::Borrowed(&b[start..start + len]),
        Floats::F16(b) => Cow::Owned(b[start..start + len].iter().map(|v| v.to_f32()).collect()),
    }
}

fn check_len(
    input: &'static str,
    tensor: &'static str,
    found: usize,
    expected: usize,
    what: &str,
) -> Result<()> {
    if found == expected {
        Ok(())
    } else {
        Err(WarpGraphError::Shape {
            input,
            tensor,
            found,
            expected: format!("{expected} ({what})"),
        })
    }
}

fn check_masks(masks: &Masks) -> Result<()> {
    let views = masks.num_views();
    check_len(
        "masks",
        "labels",
        masks.labels.len(),
        views * masks.height * masks.width,
        "V x H x W",
    )?;
    check_len(
        "masks",
        "mask_offsets",
        masks.mask_offsets.len(),
        views + 1,
        "V + 1",
    )?;
    let offsets = &masks.mask_offsets;
    if offsets.first().is_some_and(|o| *o != 0) {
        return Err(WarpGraphError::BadOffsets {
            index: 0,
            value: offsets[0],
        });
    }
    if let Some(k) = offsets.windows(2).position(|w| w[1] < w[0]) {
        return Err(WarpGraphError::BadOffsets {
            index: k + 1,
            value: offsets[k + 1],
        });
    }
    Ok(())
}

fn check_cameras(c: &Cameras, views: usize) -> Result<()> {
    if c.len() != views {
        return Err(WarpGraphError::CameraCountMismatch {
            cameras: c.len(),
            masks: views,
        });
    }
    check_len("cameras", "image_size", c.image_size.len(), views, "V")?;
    check_len("cameras", "intrinsics", c.intrinsics.len(), views, "V")?;
    check_len(
        "cameras",
        "world_to_camera",
        c.world_to_camera.len(),
        views,
        "V",
    )?;
    if let Some(v) = c.image_size.iter().position(|s| s[0] == 0 || s[1] == 0) {
        return Err(WarpGraphError::BadCamera {
            view: v,
            reason: "image_size has a zero side".into(),
        });
    }
    Ok(())
}

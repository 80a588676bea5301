//! `vis_mask` of the gate: is the correspondence p (a cell of view i's grid) -> q (its
//! warp target in view j) a view of the same, unoccluded surface point?
//!
//! * **depth**: the 3D point seen at p (view i's rendered depth at p, unprojected)
//!   projected into view j has camera depth z_j; visible when
//!   |z_j − D_j(q)| <= tol · D_j(q), D_j = view j's rendered depth at the cell containing q.
//!   No depth evidence (accumulated alpha below `depth_min_alpha` at p or q, or q outside
//!   view j's grid) rejects nothing; z_j <= 0 (behind camera j) rejects.
//! * **fwd-bwd**: following the reverse warp (j, i) from q (bilinear in j's grid) must
//!   return within `tol` grid cells of p's centre; without a reverse warp, or with q
//!   outside view j's grid, there is no evidence and nothing is rejected.

use std::borrow::Cow;
use std::collections::VecDeque;
use std::sync::{Arc, Mutex};

use profuse_formats::{camera, Cameras};
use splat_raster::{DepthMode, Rasterizer, RenderOptions, ViewCamera, ViewRender};

use crate::error::{Result, WarpGraphError};
use crate::frame::Axis;
use crate::overlap::fast_floor;

/// The occlusion tests of one directed warp, evaluated per cell.
#[derive(Default)]
pub(crate) struct CellVisibility<'a> {
    pub(crate) fwd_bwd: Option<FwdBwd<'a>>,
    pub(crate) depth: Option<DepthTest>,
}

impl CellVisibility<'_> {
    /// Whether cell (x, y) (flat index c) with warp value (wx, wy) passes every test.
    #[inline]
    pub(crate) fn visible(&self, x: usize, y: usize, c: usize, wx: f64, wy: f64) -> bool {
        self.fwd_bwd
            .as_ref()
            .is_none_or(|t| t.visible(x, y, wx, wy))
            && self
                .depth
                .as_ref()
                .is_none_or(|t| t.visible(x, y, c, wx, wy))
    }
}

/// Forward-backward consistency against the reverse warp.
pub(crate) struct FwdBwd<'a> {
    /// The reverse warp (j -> i), (x, y) per cell of view j's grid.
    pub(crate) reverse: Cow<'a, [f32]>,
    /// Forward warp value -> continuous grid coordinates of view j.
    pub(crate) to_dst_grid: [Axis; 2],
    /// Reverse warp value -> continuous grid coordinates of view i.
    pub(crate) to_src_grid: [Axis; 2],
    pub(crate) gw: usize,
    pub(crate) gh: usize,
    /// Squared tolerance in grid cells.
    pub(crate) tol2: f64,
}

impl FwdBwd<'_> {
    #[inline]
    fn visible(&self, x: usize, y: usize, wx: f64, wy: f64) -> bool {
        let gx = self.to_dst_grid[0].apply(wx);
        let gy = self.to_dst_grid[1].apply(wy);
        let (w, h) = (self.gw as f64, self.gh as f64);
        if !(gx >= 0.0 && gx <= w && gy >= 0.0 && gy <= h) {
            return true;
        }
        let [rx, ry] = bilinear2(&self.reverse, self.gw, self.gh, gx, gy);
        let dx = self.to_src_grid[0].apply(rx) - (x as f64 + 0.5);
        let dy = self.to_src_grid[1].apply(ry) - (y as f64 + 0.5);
        // NaN (a non-finite reverse warp) fails the comparison: not visible.
        dx * dx + dy * dy <= self.tol2
    }
}

/// Bilinear interpolation of a two-channel grid at continuous grid coordinates (corner
/// origin, cell centres at +0.5), indices clamped at the border.
#[inline]
fn bilinear2(plane: &[f32], w: usize, h: usize, gx: f64, gy: f64) -> [f64; 2] {
    let (sx, sy) = (gx - 0.5, gy - 0.5);
    let (x0, y0) = (fast_floor(sx), fast_floor(sy));
    let (fx, fy) = (sx - x0, sy - y0);
    let cx = |v: f64| (v.max(0.0) as usize).min(w - 1);
    let cy = |v: f64| (v.max(0.0) as usize).min(h - 1);
    let (xa, xb, ya, yb) = (cx(x0), cx(x0 + 1.0), cy(y0), cy(y0 + 1.0));
    // Written out (no closures over channels): this runs once per gated cell.
    let (ia, ib) = (2 * (ya * w + xa), 2 * (ya * w + xb));
    let (ic, id) = (2 * (yb * w + xa), 2 * (yb * w + xb));
    let (w00, w10) = ((1.0 - fx) * (1.0 - fy), fx * (1.0 - fy));
    let (w01, w11) = ((1.0 - fx) * fy, fx * fy);
    let lerp = |k: usize| {
        w00 * f64::from(plane[ia + k])
            + w10 * f64::from(plane[ib + k])
            + w01 * f64::from(plane[ic + k])
            + w11 * f64::from(plane[id + k])
    };
    [lerp(0), lerp(1)]
}

/// Depth consistency against the depths rendered from the Gaussians.
pub(crate) struct DepthTest {
    /// View i's depth on the warp grid (0 = no evidence).
    pub(crate) src: Arc<Vec<f32>>,
    /// View j's depth on the warp grid (0 = no evidence).
    pub(crate) dst: Arc<Vec<f32>>,
    /// View i's intrinsics scaled to the grid (fx, fy, cx, cy in cells).
    pub(crate) src_intrinsics: [f64; 4],
    /// Third row of the relative pose camera i -> camera j (rotation row, translation).
    pub(crate) z_row: [f64; 3],
    pub(crate) z_offset: f64,
    pub(crate) to_dst_grid: [Axis; 2],
    pub(crate) gw: usize,
    pub(crate) gh: usize,
    pub(crate) tol: f64,
}

impl DepthTest {
    #[inline]
    fn visible(&self, x: usize, y: usize, c: usize, wx: f64, wy: f64) -> bool {
        let d = f64::from(self.src[c]);
        if d <= 0.0 {
            return true;
        }
        let gx = self.to_dst_grid[0].apply(wx);
        let gy = self.to_dst_grid[1].apply(wy);
        let (w, h) = (self.gw as f64, self.gh as f64);
        if !(gx >= 0.0 && gx <= w && gy >= 0.0 && gy <= h) {
            return true;
        }
        let q = (gy as usize).min(self.gh - 1) * self.gw + (gx as usize).min(self.gw - 1);
        let dq = f64::from(self.dst[q]);
        if dq <= 0.0 {
            return true;
        }
        let n = camera::pixel_to_normalised(&self.src_intrinsics, camera::pixel_centre(x, y));
        let p = [n[0] * d, n[1] * d, d];
        let zj = self.z_row[0] * p[0] + self.z_row[1] * p[1] + self.z_row[2] * p[2] + self.z_offset;
        zj > 0.0 && (zj - dq).abs() <= self.tol * dq
    }
}

/// The camera of `view` with its intrinsics scaled to a `gw x gh` grid over its image, so
/// that grid cell centres are the pixel centres of the scaled camera.
pub(crate) fn grid_camera(
    cameras: &Cameras,
    view: usize,
    gw: usize,
    gh: usize,
) -> Result<ViewCamera> {
    let cam = ViewCamera::from_cameras(cameras, view).map_err(|source| WarpGraphError::Raster {
        context: format!("camera of view {view}"),
        source,
    })?;
    Ok(cam.at_grid(gw as u32, gh as u32))
}

/// The z row of the relative pose from camera i to camera j: z_j = row · X_i + offset.
pub(crate) fn relative_z(cameras: &Cameras, i: usize, j: usize) -> ([f64; 3], f64) {
    let (ri, ti) = cameras.pose(i);
    let (rj, tj) = cameras.pose(j);
    // M = R_j R_iᵀ; t = t_j − M t_i; only the third row is needed.
    let row: [f64; 3] = std::array::from_fn(|k| (0..3).map(|l| rj[2][l] * ri[k][l]).sum());
    let offset = tj[2] - (0..3).map(|k| row[k] * ti[k]).sum::<f64>();
    (row, offset)
}

/// Depth maps on the warp grid, rendered on demand and kept for the most recently used
/// `capacity` views, so memory stays at a few views whatever the scene size.
pub(crate) struct DepthCache<'g> {
    raster: Rasterizer<'g>,
    cameras: &'g Cameras,
    gw: usize,
    gh: usize,
    min_alpha: f32,
    capacity: usize,
    entries: Mutex<VecDeque<(usize, Arc<Vec<f32>>)>>,
}

impl<'g> DepthCache<'g> {
    pub(crate) fn new(
        raster: Rasterizer<'g>,
        cameras: &'g Cameras,
        gw: usize,
        gh: usize,
        min_alpha: f32,
        capacity: usize,
    ) -> Self {
        DepthCache {
            raster,
            cameras,
            gw,
            gh,
            min_alpha,
            capacity,
            entries: Mutex::new(VecDeque::new()),
        }
    }

    /// The rasterizer the depth maps come from (prepared once per run).
    pub(crate) fn raster(&self) -> &Rasterizer<'g> {
        &self.raster
    }

    /// View `view`'s depth on the grid: Σωz/Σω where the accumulated alpha reaches
    /// `min_alpha`, else 0 (no evidence).
    pub(crate) fn get(&self, view: usize) -> Result<Arc<Vec<f32>>> {
        {
            let mut entries = self.entries.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(k) = entries.iter().position(|(v, _)| *v == view) {
                let hit = entries.remove(k);
                if let Some(hit) = hit {
                    let depth = Arc::clone(&hit.1);
                    entries.push_back(hit);
                    return Ok(depth);
                }
            }
        }
        // Rendered without holding the lock: the rasterizer runs on rayon, and a worker
        // that blocked on this lock while its holder waited for rayon could deadlock. Two
        // threads may then render the same view; the results are identical.
        let depth = Arc::new(self.render(view)?);
        let mut entries = self.entries.lock().unwrap_or_else(|e| e.into_inner());
        if !entries.iter().any(|(v, _)| *v == view) {
            entries.push_back((view, Arc::clone(&depth)));
            while entries.len() > self.capacity {
                entries.pop_front();
            }
        }
        Ok(depth)
    }

    fn render(&self, view: usize) -> Result<Vec<f32>> {
        let cam = grid_camera(self.cameras, view, self.gw, self.gh)?;
        let opts = RenderOptions {
            color: false,
            depth: DepthMode::Normalized,
            alpha: true,
            transmittance: false,
            top_k: None,
            background: [0.0; 3],
        };
        let mut out = ViewRender::default();
        self.raster
            .render_camera_into(&cam, view, &opts, &mut out)
            .map_err(|source| WarpGraphError::Raster {
                context: format!("rendering the depth of view {view} from the Gaussians"),
                source,
            })?;
        let (Some(depth), Some(alpha)) = (out.depth(), out.alpha()) else {
            return Ok(vec![0.0; self.gw * self.gh]);
        };
        Ok(depth
            .iter()
            .zip(alpha)
            .map(|(&d, &a)| {
                if a >= self.min_alpha && d > 0.0 {
                    d
                } else {
                    0.0
                }
            })
            .collect())
    }
}

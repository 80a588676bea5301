//! Dense warps from geometry: when a scene has only sparse matches (or none), the initial
//! Gaussians' rendered depth gives warp-graph the dense correspondence fields it reads
//! (SPEC.md §4.4, `profuse.matches`).
//!
//! # Definition (normative for [`depth_warps`])
//!
//! * **Grid.** One W x H grid for every pair, W = max(1, round(w₀ / stride)),
//!   H = max(1, round(h₀ / stride)) with (w₀, h₀) view 0's image size; cell (x, y) of view
//!   i is the image-i point ((x + 0.5)·w_i / W, (y + 0.5)·h_i / H) (SPEC.md §4.4).
//! * **Depth.** Each view's expected depth D = Σωz / Σω is rendered once, at its full image
//!   size (splat-raster), and sampled at the pixel containing each cell's centre; a cell
//!   whose accumulated alpha there is below `min_alpha` has no depth.
//! * **Warp.** Cell p of view i with depth d is unprojected to X = d·K_i⁻¹(p, 1) in camera
//!   i, moved to camera j (z_j its depth there) and projected: the warp value is that
//!   position q in view j's pixels (`coords = pixels`).
//! * **Certainty.** With D_j(q) the depth of view j's cell containing q and
//!   e = |z_j − D_j(q)| / D_j(q) the relative depth disagreement,
//!   certainty = 1 − (e / depth_tol)² when e <= depth_tol, else 0: 1 for exact agreement,
//!   0.75 at half the tolerance, 0 at the tolerance. It is 0 (and the warp 0 when there is
//!   no target) where p has no depth, z_j <= 0, q lies outside view j's image, or D_j(q) has
//!   no depth; and, with a finite `edge_tol` (off by default, [`DEFAULT_EDGE_TOL`]), where
//!   p is on a depth edge: a 4-neighbour's depth differs by more than `edge_tol` relative
//!   (the expected depth of a silhouette cell blends two surfaces). A point hidden in view j behind a nearer surface has D_j(q) < z_j and fails.
//! * **Pairs.** Given explicitly, or per view the `k` views with the nearest camera centres
//!   (ties to the lower index) and, so that warp-graph's mutual test has both directions,
//!   the reverse of every chosen pair; sorted by (i, j).
//!
//! # Memory and cost
//!
//! Every view's depth is rendered once (one full-size render alive at a time) and its grid
//! samples kept (4·W·H bytes a view); the output
//! tensors (12·W·H bytes a pair with F32 warp and certainty) are filled in place, pairs in
//! parallel, each cell by one thread in a fixed order, so the bytes do not depend on the
//! thread count.

use std::collections::BTreeMap;

use profuse_formats::{camera, Cameras, Floats, Gaussians, Matches, WarpCoords};
use rayon::prelude::*;
use serde::Serialize;
use splat_raster::Rasterizer;

use crate::error::{Result, WarpGraphError};
use splat_raster::{DepthMode, RenderOptions, ViewCamera, ViewRender};

/// Which ordered view pairs get a warp.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Pairs {
    /// Exactly these (i, j), i != j, each once.
    Explicit(Vec<[u32; 2]>),
    /// Each view with its `k` nearest views by camera centre, plus the reverse pairs.
    Nearest(usize),
    /// As `Nearest`, among the listed views only: the others take part in no pair (views
    /// without masks, or held out of the semantic half). Each listed once, in range.
    NearestAmong(usize, Vec<u32>),
}

/// Parameters of [`depth_warps`].
#[derive(Debug, Clone, PartialEq)]
pub struct DepthWarpParams {
    /// Image pixels per grid cell along each axis (>= 1).
    pub stride: usize,
    /// Relative depth tolerance of the certainty (> 0).
    pub depth_tol: f64,
    /// Relative depth step to a 4-neighbour cell above which a cell is on a depth edge
    /// and rejected (> 0; infinity turns the test off).
    pub edge_tol: f64,
    /// Accumulated alpha below which a rendered pixel has no depth, in (0, 1].
    pub min_alpha: f32,
    /// The pairs.
    pub pairs: Pairs,
}

impl Default for DepthWarpParams {
    /// Stride 4, tolerance 0.05 (the rendered depth of a solid surface is within 1% of
    /// the truth on the synthetic scene; 0.1 gave the same proposals), no edge test,
    /// alpha 0.5, the 4 nearest views.
    fn default() -> Self {
        DepthWarpParams {
            stride: 4,
            depth_tol: 0.05,
            edge_tol: DEFAULT_EDGE_TOL,
            min_alpha: 0.5,
            pairs: Pairs::Nearest(4),
        }
    }
}

/// What [`depth_warps`] produced.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DepthWarpReport {
    /// Views.
    pub views: usize,
    /// Ordered pairs written.
    pub pairs: usize,
    /// Grid (width, height).
    pub grid: [usize; 2],
    /// Cells over all pairs.
    pub cells: u64,
    /// Cells of view i with a depth.
    pub with_depth: u64,
    /// Cells with a depth that lie on a depth edge (rejected).
    pub depth_edge: u64,
    /// Cells with certainty > 0.
    pub kept: u64,
    /// Cells whose depth disagreed beyond the tolerance (occluded or off-surface).
    pub rejected_depth: u64,
    /// Cells projected outside view j's image or behind its camera.
    pub outside: u64,
    /// Views' depth maps rendered.
    pub depth_maps: usize,
}

/// Renders each view's depth from `gaussians` and writes, for every pair, where each grid
/// cell of view i lands in view j and how well the depths agree (see the module docs).
/// `progress(done, total)` is called after each depth map and each pair.
pub fn depth_warps(
    gaussians: &Gaussians,
    cameras: &Cameras,
    params: &DepthWarpParams,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<(Matches, DepthWarpReport)> {
    check(params)?;
    let v = cameras.len();
    if v < 2 {
        return Err(invalid("views", v.to_string(), "at least 2 views"));
    }
    let pairs = resolve_pairs(cameras, &params.pairs)?;
    let [w0, h0] = cameras.image_size[0];
    let cells_of = |s: u32| ((f64::from(s) / params.stride as f64).round() as usize).max(1);
    let (gw, gh) = (cells_of(w0), cells_of(h0));
    let raster = Rasterizer::new(gaussians).map_err(|source| WarpGraphError::Raster {
        context: "preparing the Gaussians for depth rendering".into(),
        source,
    })?;
    let mut used = vec![false; v];
    for [i, j] in &pairs {
        used[*i as usize] = true;
        used[*j as usize] = true;
    }
    let total = used.iter().filter(|u| **u).count() + pairs.len();
    let mut depth: Vec<Vec<f32>> = vec![Vec::new(); v];
    let mut done = 0;
    for view in (0..v).filter(|&x| used[x]) {
        depth[view] = sampled_depth(&raster, cameras, view, gw, gh, params.min_alpha)?;
        done += 1;
        progress(done, total);
    }
    let plane = gw * gh;
    let mut warp = vec![0f32; pairs.len() * plane * 2];
    let mut certainty = vec![0f32; pairs.len() * plane];
    let counted = std::sync::atomic::AtomicUsize::new(done);
    let counts: Vec<Counts> = warp
        .par_chunks_mut(plane * 2)
        .zip(certainty.par_chunks_mut(plane))
        .zip(pairs.par_iter())
        .map(|((w, c), &[i, j])| {
            let pair = PairGeometry::new(cameras, i as usize, j as usize, gw, gh);
            let counts = pair.fill(&depth[i as usize], &depth[j as usize], params, w, c);
            let n = counted.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress(n, total);
            counts
        })
        .collect();
    let sum = counts.iter().fold(Counts::default(), |a, b| a.add(b));
    let mut extra = BTreeMap::new();
    extra.insert(
        "generator".into(),
        format!("warp-graph {} depth_warps", env!("CARGO_PKG_VERSION")),
    );
    extra.insert("stride".into(), params.stride.to_string());
    extra.insert(
        "depth_tol".into(),
        profuse_formats::format_float(params.depth_tol),
    );
    extra.insert(
        "min_alpha".into(),
        profuse_formats::format_float(f64::from(params.min_alpha)),
    );
    let report = DepthWarpReport {
        views: v,
        pairs: pairs.len(),
        grid: [gw, gh],
        cells: (pairs.len() * plane) as u64,
        with_depth: sum.with_depth,
        depth_edge: sum.edge,
        kept: sum.kept,
        rejected_depth: sum.rejected_depth,
        outside: sum.outside,
        depth_maps: used.iter().filter(|u| **u).count(),
    };
    let matches = Matches {
        num_views: v,
        pairs: pairs.into(),
        height: gh,
        width: gw,
        warp: Floats::F32(warp.into()),
        certainty: Floats::F32(certainty.into()),
        coords: WarpCoords::Pixels,
        extra,
    };
    Ok((matches, report))
}

fn invalid(name: &'static str, value: String, expected: &'static str) -> WarpGraphError {
    WarpGraphError::InvalidParameter {
        name,
        value,
        expected,
    }
}

/// The depth-edge test is off by default: on the synthetic demo it made kept warps more
/// precise (within 1 px of the truth: 70% → 78%) but dropped so many cells that
/// warp-graph's link grouping lost completeness (ARI 0.887 without it, 0.793 at 0.15,
/// 0.777 at 0.05; synth's exact warps 0.911).
pub const DEFAULT_EDGE_TOL: f64 = f64::INFINITY;

fn check(p: &DepthWarpParams) -> Result<()> {
    if p.edge_tol.is_nan() || p.edge_tol <= 0.0 {
        return Err(invalid(
            "edge_tol",
            p.edge_tol.to_string(),
            "a number > 0 (infinity: off)",
        ));
    }
    if p.stride == 0 {
        return Err(invalid("stride", "0".into(), "an integer >= 1"));
    }
    if !(p.depth_tol.is_finite() && p.depth_tol > 0.0) {
        return Err(invalid(
            "depth_tol",
            p.depth_tol.to_string(),
            "a finite number > 0",
        ));
    }
    if !(p.min_alpha > 0.0 && p.min_alpha <= 1.0) {
        return Err(invalid(
            "min_alpha",
            p.min_alpha.to_string(),
            "a number in (0, 1]",
        ));
    }
    if matches!(p.pairs, Pairs::Nearest(0) | Pairs::NearestAmong(0, _)) {
        return Err(invalid("pairs", "0 nearest views".into(), "k >= 1"));
    }
    Ok(())
}

/// View `view`'s expected depth Σωz/Σω rendered at its full image size and sampled at the
/// pixel containing each grid cell's centre (0 where the accumulated alpha is below
/// `min_alpha`). Full resolution, not the grid: a coarse render blends each cell's 3D
/// footprint (on the synthetic scene the median relative error grows from 0.7% to 1.8% at
/// a third of the resolution), and the warp's accuracy is the depth's.
fn sampled_depth(
    raster: &Rasterizer<'_>,
    cameras: &Cameras,
    view: usize,
    gw: usize,
    gh: usize,
    min_alpha: f32,
) -> Result<Vec<f32>> {
    let err = |source| WarpGraphError::Raster {
        context: format!("rendering the depth of view {view} from the Gaussians"),
        source,
    };
    let cam = ViewCamera::from_cameras(cameras, view).map_err(err)?;
    let opts = RenderOptions {
        color: false,
        depth: DepthMode::Normalized,
        alpha: true,
        transmittance: false,
        top_k: None,
        background: [0.0; 3],
    };
    let mut out = ViewRender::default();
    raster
        .render_camera_into(&cam, view, &opts, &mut out)
        .map_err(err)?;
    let (w, h) = (cam.width as usize, cam.height as usize);
    let (Some(depth), Some(alpha)) = (out.depth(), out.alpha()) else {
        return Ok(vec![0.0; gw * gh]);
    };
    let mut samples = Vec::with_capacity(gw * gh);
    for y in 0..gh {
        let py = (((y as f64 + 0.5) * h as f64 / gh as f64) as usize).min(h - 1);
        for x in 0..gw {
            let px = (((x as f64 + 0.5) * w as f64 / gw as f64) as usize).min(w - 1);
            let (d, a) = (depth[py * w + px], alpha[py * w + px]);
            samples.push(if a >= min_alpha && d > 0.0 { d } else { 0.0 });
        }
    }
    Ok(samples)
}

/// The ordered pairs, checked (explicit) or chosen by camera-centre distance, sorted.
pub fn resolve_pairs(cameras: &Cameras, pairs: &Pairs) -> Result<Vec<[u32; 2]>> {
    let v = cameras.len();
    let mut out: Vec<[u32; 2]> = match pairs {
        Pairs::Explicit(list) => {
            let mut seen = std::collections::BTreeSet::new();
            for (row, &[i, j]) in list.iter().enumerate() {
                if let Some(&view) = [i, j].iter().find(|x| **x as usize >= v) {
                    return Err(WarpGraphError::PairOutOfRange {
                        row,
                        view,
                        views: v,
                    });
                }
                let reason = if i == j {
                    "a view paired with itself"
                } else if !seen.insert([i, j]) {
                    "repeats an earlier ordered pair"
                } else {
                    continue;
                };
                return Err(WarpGraphError::BadPair { row, i, j, reason });
            }
            list.clone()
        }
        Pairs::Nearest(k) => {
            let all: Vec<usize> = (0..v).collect();
            nearest_pairs(cameras, &all, *k)
        }
        Pairs::NearestAmong(k, views) => {
            let mut seen = std::collections::BTreeSet::new();
            for (row, &view) in views.iter().enumerate() {
                if view as usize >= v {
                    return Err(WarpGraphError::PairOutOfRange {
                        row,
                        view,
                        views: v,
                    });
                }
                if !seen.insert(view) {
                    return Err(invalid(
                        "pairs",
                        format!("view {view} listed twice"),
                        "each view of the subset once",
                    ));
                }
            }
            let among: Vec<usize> = seen.into_iter().map(|x| x as usize).collect();
            nearest_pairs(cameras, &among, *k)
        }
    };
    out.sort_unstable();
    out.dedup();
    Ok(out)
}

/// Each of `views` with its `k` nearest others of `views` by camera centre (ties to the
/// lower index), both directions.
fn nearest_pairs(cameras: &Cameras, views: &[usize], k: usize) -> Vec<[u32; 2]> {
    let centre = |x: usize| cameras.center(x);
    let mut out = Vec::new();
    for &i in views {
        let mut others: Vec<(f64, usize)> = views
            .iter()
            .filter(|&&j| j != i)
            .map(|&j| (dist2(centre(i), centre(j)), j))
            .collect();
        others.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        for &(_, j) in others.iter().take(k) {
            out.push([i as u32, j as u32]);
            out.push([j as u32, i as u32]);
        }
    }
    out
}

fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
    (0..3).map(|k| (a[k] - b[k]) * (a[k] - b[k])).sum()
}

#[derive(Debug, Default, Clone, Copy)]
struct Counts {
    with_depth: u64,
    edge: u64,
    kept: u64,
    rejected_depth: u64,
    outside: u64,
}

impl Counts {
    fn add(self, o: &Counts) -> Counts {
        Counts {
            with_depth: self.with_depth + o.with_depth,
            edge: self.edge + o.edge,
            kept: self.kept + o.kept,
            rejected_depth: self.rejected_depth + o.rejected_depth,
            outside: self.outside + o.outside,
        }
    }
}

/// The fixed geometry of one ordered pair on the grid.
struct PairGeometry {
    /// View i's intrinsics scaled to the grid.
    src_k: [f64; 4],
    /// Camera i → camera j: rotation rows and translation.
    rot: [[f64; 3]; 3],
    trans: [f64; 3],
    /// View j's full-size intrinsics and image size.
    dst_k: [f64; 4],
    dst_size: [f64; 2],
    gw: usize,
    gh: usize,
}

impl PairGeometry {
    fn new(cameras: &Cameras, i: usize, j: usize, gw: usize, gh: usize) -> PairGeometry {
        let (ri, ti) = cameras.pose(i);
        let (rj, tj) = cameras.pose(j);
        // X_j = R_j R_iᵀ (X_i − t_i) + t_j.
        let rot: [[f64; 3]; 3] = std::array::from_fn(|r| {
            std::array::from_fn(|c| (0..3).map(|l| rj[r][l] * ri[c][l]).sum())
        });
        let trans: [f64; 3] =
            std::array::from_fn(|r| tj[r] - (0..3).map(|c| rot[r][c] * ti[c]).sum::<f64>());
        let [wi, hi] = cameras.image_size[i];
        let [wj, hj] = cameras.image_size[j];
        PairGeometry {
            src_k: camera::rescale_intrinsics(
                &cameras.intrinsics[i],
                [wi, hi],
                [gw as u32, gh as u32],
            ),
            rot,
            trans,
            dst_k: cameras.intrinsics[j],
            dst_size: [f64::from(wj), f64::from(hj)],
            gw,
            gh,
        }
    }

    /// Whether a 4-neighbour's depth differs from `d` by more than `tol` relative (a
    /// neighbour without depth counts as an edge): at a silhouette the expected depth blends two surfaces into a point that lies
    /// on neither, whose warp would be wrong by many pixels yet may pass the depth test.
    fn on_depth_edge(&self, src: &[f32], x: usize, y: usize, d: f64, tol: f64) -> bool {
        let (w, h) = (self.gw, self.gh);
        let near = [
            (x > 0).then(|| src[y * w + x - 1]),
            (x + 1 < w).then(|| src[y * w + x + 1]),
            (y > 0).then(|| src[(y - 1) * w + x]),
            (y + 1 < h).then(|| src[(y + 1) * w + x]),
        ];
        near.iter()
            .flatten()
            .any(|&n| (f64::from(n) - d).abs() > tol * d)
    }

    /// Fills one pair's warp ([H, W, 2]) and certainty ([H, W]).
    fn fill(
        &self,
        src: &[f32],
        dst: &[f32],
        params: &DepthWarpParams,
        warp: &mut [f32],
        cert: &mut [f32],
    ) -> Counts {
        let mut counts = Counts::default();
        for y in 0..self.gh {
            for x in 0..self.gw {
                let c = y * self.gw + x;
                let d = f64::from(src[c]);
                if d <= 0.0 {
                    continue;
                }
                counts.with_depth += 1;
                if self.on_depth_edge(src, x, y, d, params.edge_tol) {
                    counts.edge += 1;
                    continue;
                }
                let n = camera::pixel_to_normalised(&self.src_k, camera::pixel_centre(x, y));
                let p = [n[0] * d, n[1] * d, d];
                let q: [f64; 3] = std::array::from_fn(|r| {
                    (0..3).map(|k| self.rot[r][k] * p[k]).sum::<f64>() + self.trans[r]
                });
                if q[2] <= 0.0 {
                    counts.outside += 1;
                    continue;
                }
                let [u, v] = camera::project(&self.dst_k, q);
                warp[2 * c] = u as f32;
                warp[2 * c + 1] = v as f32;
                let [w, h] = self.dst_size;
                if !(u >= 0.0 && u < w && v >= 0.0 && v < h) {
                    counts.outside += 1;
                    continue;
                }
                let gx = ((u * self.gw as f64 / w) as usize).min(self.gw - 1);
                let gy = ((v * self.gh as f64 / h) as usize).min(self.gh - 1);
                let dq = f64::from(dst[gy * self.gw + gx]);
                if dq <= 0.0 {
                    continue;
                }
                let e = (q[2] - dq).abs() / dq / params.depth_tol;
                if e <= 1.0 {
                    cert[c] = (1.0 - e * e) as f32;
                    counts.kept += 1;
                } else {
                    counts.rejected_depth += 1;
                }
            }
        }
        counts
    }
}

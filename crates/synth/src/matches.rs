//! Exact dense warps between neighbouring views, RoMa-style (normalised coordinates,
//! certainty 0 where the content is not visible in the target view).

use rayon::prelude::*;

use crate::camera::Camera;
use crate::config::Config;
use crate::rng::{tag, unit, Rng};
use crate::scene::{norm, sub, Scene};

/// For each view its `k` nearest other views by camera-centre distance (ties by index);
/// both ordered pairs of every neighbour relation, deduplicated and sorted.
pub fn neighbour_pairs(cameras: &[Camera], k: usize) -> Vec<[u32; 2]> {
    let centers: Vec<[f64; 3]> = cameras.iter().map(Camera::center).collect();
    let mut pairs = std::collections::BTreeSet::new();
    for (i, ci) in centers.iter().enumerate() {
        let mut others: Vec<(f64, usize)> = centers
            .iter()
            .enumerate()
            .filter(|(j, _)| *j != i)
            .map(|(j, cj)| (norm(sub(*ci, *cj)), j))
            .collect();
        others.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        for &(_, j) in others.iter().take(k) {
            pairs.insert([i as u32, j as u32]);
            pairs.insert([j as u32, i as u32]);
        }
    }
    pairs.into_iter().collect()
}

/// The warp and certainty of all pairs, on the match grid.
pub(crate) struct Warps {
    pub pairs: Vec<[u32; 2]>,
    pub width: usize,
    pub height: usize,
    /// [P, H, W, 2], normalised target (x, y) in view j.
    pub warp: Vec<f32>,
    /// [P, H, W].
    pub certainty: Vec<f32>,
}

/// Computes the warps of `pairs` (sorted by source view).
pub(crate) fn compute(
    scene: &Scene,
    cameras: &[Camera],
    config: &Config,
    pairs: Vec<[u32; 2]>,
) -> Warps {
    let (gw, gh) = config.match_grid();
    let cells = gw * gh;
    let mut warp = vec![0.0f32; pairs.len() * cells * 2];
    let mut certainty = vec![0.0f32; pairs.len() * cells];
    let mut warp_rest: &mut [f32] = &mut warp;
    let mut cert_rest: &mut [f32] = &mut certainty;
    let mut start = 0;
    while start < pairs.len() {
        let i = pairs[start][0] as usize;
        let end = start
            + pairs[start..]
                .iter()
                .take_while(|p| p[0] as usize == i)
                .count();
        let n = end - start;
        // The exact 3D point seen through each cell centre of view i.
        let cam = &cameras[i];
        let (sx, sy) = (
            f64::from(cam.width) / gw as f64,
            f64::from(cam.height) / gh as f64,
        );
        let center = cam.center();
        let points: Vec<Option<[f64; 3]>> = (0..cells)
            .into_par_iter()
            .map(|c| {
                let (x, y) = (c % gw, c / gw);
                let d = cam.ray((x as f64 + 0.5) * sx, (y as f64 + 0.5) * sy);
                scene.raycast(center, d).map(|h| h.point)
            })
            .collect();
        let (w_now, w_later) = std::mem::take(&mut warp_rest).split_at_mut(n * cells * 2);
        let (c_now, c_later) = std::mem::take(&mut cert_rest).split_at_mut(n * cells);
        warp_rest = w_later;
        cert_rest = c_later;
        let pair_slice = &pairs[start..end];
        w_now
            .par_chunks_mut(gw * 2)
            .zip(c_now.par_chunks_mut(gw))
            .enumerate()
            .for_each(|(row, (wr, cr))| {
                let (p, y) = (row / gh, row % gh);
                let j = pair_slice[p][1] as usize;
                for x in 0..gw {
                    let (t, c) = cell(
                        scene,
                        &cameras[j],
                        config,
                        [i as u64, j as u64],
                        y * gw + x,
                        points[y * gw + x],
                    );
                    wr[2 * x] = t[0];
                    wr[2 * x + 1] = t[1];
                    cr[x] = c;
                }
            });
        start = end;
    }
    Warps {
        pairs,
        width: gw,
        height: gh,
        warp,
        certainty,
    }
}

/// One cell: target in normalised coordinates of view j and certainty.
fn cell(
    scene: &Scene,
    cj: &Camera,
    config: &Config,
    pair: [u64; 2],
    c: usize,
    x: Option<[f64; 3]>,
) -> ([f32; 2], f32) {
    let seed = config.seed;
    let key = [seed, tag::CERTAINTY, pair[0], pair[1], c as u64];
    let (w, h) = (f64::from(cj.width), f64::from(cj.height));
    let (mut u, mut v, mut cert) = (f64::NAN, f64::NAN, 0.0);
    if let Some(p) = x {
        let q = cj.project(p);
        u = q[0];
        v = q[1];
        let inside = q[2] > 1e-9 && u >= 0.0 && u < w && v >= 0.0 && v < h;
        if inside && !occluded(scene, cj, p) {
            cert = 0.7 + 0.3 * unit(&key);
            if config.warp_noise_px > 0.0 {
                let mut rng = Rng::new(&[seed, tag::WARP_NOISE, pair[0], pair[1], c as u64]);
                u += config.warp_noise_px * rng.normal();
                v += config.warp_noise_px * rng.normal();
            }
        }
    }
    if config.outlier_frac > 0.0
        && unit(&[seed, tag::OUTLIER, pair[0], pair[1], c as u64]) < config.outlier_frac
    {
        let mut rng = Rng::new(&[seed, tag::OUTLIER, pair[0], pair[1], c as u64, 1]);
        u = w * rng.unit();
        v = h * rng.unit();
        cert = rng.range(0.5, 1.0);
    }
    let xn = (2.0 * u / w - 1.0) as f32;
    let yn = (2.0 * v / h - 1.0) as f32;
    let t = if xn.is_finite() && yn.is_finite() {
        [xn, yn]
    } else {
        [0.0, 0.0]
    };
    (t, cert as f32)
}

/// Whether something lies between camera j's centre and the point, with tolerance
/// |X − C| · 1e-4 + 1e-4 (the point's own surface is not an occluder).
pub(crate) fn occluded(scene: &Scene, cj: &Camera, p: [f64; 3]) -> bool {
    let c = cj.center();
    let d = sub(p, c);
    let dist = norm(d);
    if dist <= 1e-4 {
        return false;
    }
    let max_t = (1.0 - 1e-4) - 1e-4 / dist;
    scene.raycast_within(c, d, max_t).is_some()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pairs_are_symmetric_sorted_and_nearest() {
        let cams: Vec<Camera> = (0..6)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / 6.0;
                Camera::look_at(
                    [3.0 * a.cos(), 3.0 * a.sin(), 1.5],
                    [0.0, 0.0, 0.5],
                    16,
                    12,
                    60.0,
                )
            })
            .collect();
        let p = neighbour_pairs(&cams, 2);
        // On a hexagon each view's two nearest are its ring neighbours: 6 relations × 2.
        assert_eq!(p.len(), 12);
        assert!(p.windows(2).all(|w| w[0] < w[1]));
        for [i, j] in &p {
            assert!(p.contains(&[*j, *i]));
            assert!(matches!((i + 6 - j) % 6, 1 | 5));
        }
        assert!(neighbour_pairs(&cams[..1], 3).is_empty());
    }
}

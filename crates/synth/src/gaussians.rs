//! Ground-truth Gaussians on the visible surfaces.

use profuse_formats::{camera, Gaussians};
use rayon::prelude::*;

use crate::camera::Camera;
use crate::rng::{tag, Rng};
use crate::scene::Scene;

/// SH degree-0 constant: colour = C0 · dc + 0.5.
pub use profuse_formats::camera::SH_C0;

/// One Gaussian: mean, log-scales, rotation, SH DC, class.
type Row = ([f32; 3], [f32; 3], [f32; 4], [f32; 3], i32);

/// Tries per sample to find a pixel that sees a surface.
const TRIES: u64 = 64;

/// Samples `n` surface points uniformly over views × pixels (sample k's pixel is keyed by
/// (seed, k, try), so the result does not depend on the thread count), back-projects
/// them with the true depth, and makes one flat Gaussian per point: class from the
/// object, colour from the rendered image, local z along the surface normal, tangential
/// scale = 1.5 × the pixel footprint (depth / fx), normal scale 10% of that, opacity
/// logit 2, SH degree 0.
pub(crate) fn sample(scene: &Scene, cameras: &[Camera], seed: u64, n: usize) -> Gaussians {
    let rows: Vec<Option<Row>> = (0..n as u64)
        .into_par_iter()
        .map(|k| {
            for attempt in 0..TRIES {
                let mut rng = Rng::new(&[seed, tag::GAUSSIANS, k, attempt]);
                let cam = &cameras[rng.below(cameras.len())];
                let col = rng.below(cam.width as usize);
                let [x, y] = camera::pixel_centre(col, rng.below(cam.height as usize));
                let Some(hit) = scene.raycast(cam.center(), cam.ray(x, y)) else {
                    continue;
                };
                let depth = hit.t; // the ray has camera-z component 1
                let rgb = scene.shade(&hit);
                let class = scene.objects[hit.object as usize].class_id as i32;
                let s = depth / cam.intrinsics[0] * 1.5;
                let n = hit.normal;
                // Rotation taking local z to the normal: q = (1 + z·n, z × n), normalised.
                let q = if n[2] < -1.0 + 1e-9 {
                    [0.0, 1.0, 0.0, 0.0]
                } else {
                    let q = [1.0 + n[2], -n[1], n[0], 0.0];
                    let l = q.iter().map(|v| v * v).sum::<f64>().sqrt();
                    q.map(|v| v / l)
                };
                return Some((
                    hit.point.map(|v| v as f32),
                    [s.ln() as f32, s.ln() as f32, (0.1 * s).ln() as f32],
                    q.map(|v| v as f32),
                    rgb.map(camera::rgb8_to_sh_dc),
                    class,
                ));
            }
            None
        })
        .collect();
    let rows: Vec<_> = rows.into_iter().flatten().collect();
    Gaussians {
        means: rows.iter().map(|r| r.0).collect::<Vec<_>>().into(),
        log_scales: rows.iter().map(|r| r.1).collect::<Vec<_>>().into(),
        rotations: rows.iter().map(|r| r.2).collect::<Vec<_>>().into(),
        opacity_logits: vec![2.0f32; rows.len()].into(),
        sh_dc: rows.iter().map(|r| r.3).collect::<Vec<_>>().into(),
        sh_degree: 0,
        sh_rest: None,
        class_ids: Some(rows.iter().map(|r| r.4).collect::<Vec<_>>().into()),
        extra: [
            (
                "generator".to_string(),
                format!("synth {}", env!("CARGO_PKG_VERSION")),
            ),
            ("source".to_string(), "synthetic ground truth".to_string()),
        ]
        .into_iter()
        .collect(),
    }
}

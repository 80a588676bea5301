//! Pinhole cameras in the OpenCV convention and the orbit they are placed on.

use profuse_formats::{camera, Cameras};

use crate::config::Config;
use crate::rng::{tag, Rng};
use crate::scene::{cross, dot, normalize, sub};

/// A pinhole camera: OpenCV world-to-camera pose (x right, y down, z forward), intrinsics
/// with pixel centres at integer + 0.5.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Rows of R in x_cam = R x_world + t.
    pub rotation: [[f64; 3]; 3],
    /// t in x_cam = R x_world + t.
    pub translation: [f64; 3],
    /// fx, fy, cx, cy in pixels.
    pub intrinsics: [f64; 4],
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

impl Camera {
    /// A camera at `center` looking at `target` with the world z axis up (image y down),
    /// fx = fy from the horizontal field of view, cx = W/2, cy = H/2.
    /// (Not splat-raster's `look_at`: this one normalises by the reciprocal and falls back
    /// to the y axis as up, and the written scenes depend on that arithmetic.)
    pub fn look_at(
        center: [f64; 3],
        target: [f64; 3],
        width: u32,
        height: u32,
        hfov_deg: f64,
    ) -> Camera {
        let f = normalize(sub(target, center));
        let mut r = cross(f, [0.0, 0.0, 1.0]);
        if dot(r, r) < 1e-12 {
            r = cross(f, [0.0, 1.0, 0.0]);
        }
        let r = normalize(r);
        let d = cross(f, r);
        let rotation = [r, d, f];
        let translation = [-dot(r, center), -dot(d, center), -dot(f, center)];
        Camera {
            rotation,
            translation,
            intrinsics: camera::pinhole_intrinsics(width, height, hfov_deg),
            width,
            height,
        }
    }

    /// View `v` of a cameras file.
    pub fn from_cameras(cameras: &Cameras, v: usize) -> Camera {
        let (rotation, translation) = cameras.pose(v);
        let [width, height] = cameras.image_size[v];
        Camera {
            rotation,
            translation,
            intrinsics: cameras.intrinsics[v],
            width,
            height,
        }
    }

    /// Camera centre in world coordinates (−Rᵀt).
    pub fn center(&self) -> [f64; 3] {
        camera::camera_centre(&self.rotation, &self.translation)
    }

    /// World direction of the ray through image point (px, py) in pixels, scaled so that
    /// its camera-z component is 1: a hit at ray parameter t has depth (camera z) t.
    pub fn ray(&self, px: f64, py: f64) -> [f64; 3] {
        let [x, y] = camera::pixel_to_normalised(&self.intrinsics, [px, py]);
        camera::camera_to_world_direction(&self.rotation, [x, y, 1.0])
    }

    /// Camera coordinates of a world point.
    pub fn to_camera(&self, p: [f64; 3]) -> [f64; 3] {
        camera::world_to_camera(&self.rotation, &self.translation, p)
    }

    /// Projects a world point: pixel x, pixel y, depth (camera z). Not finite for points
    /// in the camera's plane.
    pub fn project(&self, p: [f64; 3]) -> [f64; 3] {
        let c = self.to_camera(p);
        let [u, v] = camera::project(&self.intrinsics, c);
        [u, v, c[2]]
    }

    /// Row-major `[R | t]` as stored in a cameras file.
    pub fn world_to_camera(&self) -> [f64; 12] {
        camera::pose_row(&self.rotation, &self.translation)
    }
}

/// A cameras table of these views (pinhole, no extra metadata), view `v` showing
/// `image_names[v]`.
pub fn cameras_table(cams: &[Camera], image_names: Vec<String>) -> Cameras {
    Cameras {
        image_names,
        image_size: cams
            .iter()
            .map(|c| [c.width, c.height])
            .collect::<Vec<_>>()
            .into(),
        intrinsics: cams.iter().map(|c| c.intrinsics).collect::<Vec<_>>().into(),
        world_to_camera: cams
            .iter()
            .map(Camera::world_to_camera)
            .collect::<Vec<_>>()
            .into(),
        distortion: None,
        extra: Default::default(),
    }
}

/// The cameras of a config: an elliptic orbit at `orbit_frac` of the room's half extents,
/// evenly spaced from a seeded start angle, each with seeded height and look-at jitter.
pub fn orbit(config: &Config) -> Vec<Camera> {
    let room = config.resolved_room();
    let (a, b) = (
        config.orbit_frac * room[0] / 2.0,
        config.orbit_frac * room[1] / 2.0,
    );
    let start = Rng::new(&[config.seed, tag::CAMERAS, u64::MAX]).range(0.0, std::f64::consts::TAU);
    (0..config.views)
        .map(|v| {
            let mut rng = Rng::new(&[config.seed, tag::CAMERAS, v as u64]);
            let theta = start + std::f64::consts::TAU * v as f64 / config.views as f64;
            let center = [
                a * theta.cos(),
                b * theta.sin(),
                config.camera_height + rng.range(-config.height_jitter, config.height_jitter),
            ];
            let j = config.target_jitter;
            let target = [
                rng.range(-j, j),
                rng.range(-j, j),
                (config.target_height + rng.range(-j, j)).max(0.0),
            ];
            Camera::look_at(center, target, config.width, config.height, config.hfov_deg)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_is_opencv() {
        let c = Camera::look_at([0.0, 0.0, 1.0], [5.0, 0.0, 1.0], 100, 50, 90.0);
        // Forward along +x, right along −y, down along −z.
        assert_eq!(c.rotation[2], [1.0, 0.0, 0.0]);
        assert_eq!(c.rotation[0], [0.0, -1.0, 0.0]);
        assert_eq!(c.rotation[1], [0.0, 0.0, -1.0]);
        let p = c.project([5.0, -1.0, 0.5]);
        assert!((p[2] - 5.0).abs() < 1e-12);
        assert!(p[0] > 50.0 && p[1] > 25.0);
        assert!((c.intrinsics[0] - 50.0).abs() < 1e-9);
        let ctr = c.center();
        assert!((ctr[2] - 1.0).abs() < 1e-12 && ctr[0].abs() < 1e-12);
        // ray() and project() are inverse.
        let d = c.ray(p[0], p[1]);
        let q = [
            ctr[0] + 5.0 * d[0],
            ctr[1] + 5.0 * d[1],
            ctr[2] + 5.0 * d[2],
        ];
        assert!(
            (q[0] - 5.0).abs() < 1e-9 && (q[1] + 1.0).abs() < 1e-9 && (q[2] - 0.5).abs() < 1e-9
        );
    }
}

//! One view's pinhole camera, and helpers to make preview cameras (look-at, orbit) for
//! scenes that come without cameras.

use profuse_formats::{camera, Cameras, Gaussians};

use crate::error::{RasterError, Result};
use crate::{MAX_PIXELS, MAX_SIDE};

/// A validated pinhole camera of one view (SPEC.md §3.3: OpenCV axes, world-to-camera,
/// pixel centres at integer + 0.5). Lens distortion is ignored: every stage after import
/// assumes pinhole cameras.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewCamera {
    /// World-to-camera rotation, row-major.
    pub rotation: [[f64; 3]; 3],
    /// World-to-camera translation.
    pub translation: [f64; 3],
    /// fx, fy, cx, cy in pixels.
    pub intrinsics: [f64; 4],
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

impl ViewCamera {
    /// Reads view `view` of `cameras`, checking that it exists and is usable.
    pub fn from_cameras(cameras: &Cameras, view: usize) -> Result<Self> {
        let views = cameras.len();
        if view >= views {
            return Err(RasterError::ViewOutOfRange { view, views });
        }
        let bad = |reason: String| RasterError::BadCamera { view, reason };
        let (Some(&[width, height]), Some(&intrinsics), Some(m)) = (
            cameras.image_size.get(view),
            cameras.intrinsics.get(view),
            cameras.world_to_camera.get(view),
        ) else {
            return Err(bad(
                "image_size, intrinsics or world_to_camera has no row for this view".into(),
            ));
        };
        let (rotation, translation) = camera::pose_from_row(m);
        let cam = ViewCamera {
            rotation,
            translation,
            intrinsics,
            width,
            height,
        };
        cam.check(view)?;
        Ok(cam)
    }

    /// Checks sizes, finiteness and focal lengths; `view` is only used in the error.
    pub fn check(&self, view: usize) -> Result<()> {
        let bad = |reason: String| RasterError::BadCamera { view, reason };
        if self.width == 0 || self.height == 0 {
            return Err(bad(format!(
                "image size {}x{} is empty",
                self.width, self.height
            )));
        }
        if self.width > MAX_SIDE
            || self.height > MAX_SIDE
            || u64::from(self.width) * u64::from(self.height) > MAX_PIXELS
        {
            return Err(RasterError::ImageTooLarge {
                width: self.width,
                height: self.height,
                max_side: MAX_SIDE,
                max_pixels: MAX_PIXELS,
            });
        }
        let [fx, fy, cx, cy] = self.intrinsics;
        if ![fx, fy, cx, cy].iter().all(|v| v.is_finite()) || fx <= 0.0 || fy <= 0.0 {
            return Err(bad(format!(
                "intrinsics {:?} must be finite with fx, fy > 0",
                self.intrinsics
            )));
        }
        let finite_pose = self.rotation.iter().flatten().all(|v| v.is_finite())
            && self.translation.iter().all(|v| v.is_finite());
        if !finite_pose {
            return Err(bad("world_to_camera is not finite".into()));
        }
        Ok(())
    }

    /// Camera centre in world coordinates (−Rᵀt).
    pub fn center(&self) -> [f64; 3] {
        camera::camera_centre(&self.rotation, &self.translation)
    }

    /// World point → camera coordinates.
    #[inline]
    pub fn to_camera(&self, p: [f64; 3]) -> [f64; 3] {
        camera::world_to_camera(&self.rotation, &self.translation, p)
    }

    /// The same camera rendered at a `width` x `height` grid over its image, with the
    /// intrinsics rescaled so that grid pixel (x, y) is the ray through the centre of the
    /// image region it covers (unchanged when the sizes agree).
    pub fn at_grid(&self, width: u32, height: u32) -> ViewCamera {
        ViewCamera {
            intrinsics: camera::rescale_intrinsics(
                &self.intrinsics,
                [self.width, self.height],
                [width, height],
            ),
            width,
            height,
            ..*self
        }
    }

    /// Number of 16x16 tiles across and down.
    pub fn tiles(&self) -> (usize, usize) {
        (
            (self.width as usize).div_ceil(crate::TILE),
            (self.height as usize).div_ceil(crate::TILE),
        )
    }
}

/// World-to-camera `[R | t]` (row-major 3x4, OpenCV axes) of a camera at `eye` looking at
/// `target`, with `up` the world direction that should appear upwards in the image.
/// `None` if `eye == target` or `up` is parallel to the viewing direction.
pub fn look_at(eye: [f64; 3], target: [f64; 3], up: [f64; 3]) -> Option<[f64; 12]> {
    let f = normalize(sub(target, eye))?;
    let r = normalize(cross(f, up))?;
    let d = cross(f, r);
    let rot = [r, d, f];
    let t: [f64; 3] = std::array::from_fn(|i| -dot(rot[i], eye));
    Some([
        r[0], r[1], r[2], t[0], d[0], d[1], d[2], t[1], f[0], f[1], f[2], t[2],
    ])
}

/// Pinhole intrinsics `[fx, fy, cx, cy]` with square pixels, the principal point at the
/// image centre and a horizontal field of view of `fov_x_deg` degrees.
pub use profuse_formats::camera::pinhole_intrinsics;

/// A cameras table with the given views (names `view_000`, ...), all with one image size and
/// intrinsics.
pub fn cameras_from_poses(
    poses: &[[f64; 12]],
    width: u32,
    height: u32,
    intrinsics: [f64; 4],
) -> Cameras {
    let v = poses.len();
    Cameras {
        image_names: (0..v).map(|i| format!("view_{i:03}")).collect(),
        image_size: vec![[width, height]; v].into(),
        intrinsics: vec![intrinsics; v].into(),
        world_to_camera: poses.to_vec().into(),
        distortion: None,
        extra: Default::default(),
    }
}

/// Where the Gaussians are: plain and robust centre and radius of the means.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneExtent {
    /// Mean of the means.
    pub centroid: [f64; 3],
    /// Root-mean-square distance of the means from `centroid`.
    pub rms_radius: f64,
    /// Per-axis median of the means (robust to floaters).
    pub median: [f64; 3],
    /// 90th percentile of the distances of the means from `median`.
    pub radius_p90: f64,
}

/// Centre and radius of the Gaussians' means (`None` for an empty set). Non-finite means
/// are skipped.
pub fn scene_extent(gaussians: &Gaussians) -> Option<SceneExtent> {
    let pts: Vec<[f64; 3]> = gaussians
        .means
        .iter()
        .filter(|m| m.iter().all(|v| v.is_finite()))
        .map(|m| m.map(f64::from))
        .collect();
    if pts.is_empty() {
        return None;
    }
    let n = pts.len() as f64;
    let centroid: [f64; 3] = std::array::from_fn(|a| pts.iter().map(|p| p[a]).sum::<f64>() / n);
    let rms_radius = (pts
        .iter()
        .map(|p| dot(sub(*p, centroid), sub(*p, centroid)))
        .sum::<f64>()
        / n)
        .sqrt();
    let median: [f64; 3] = std::array::from_fn(|a| {
        let mut v: Vec<f64> = pts.iter().map(|p| p[a]).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    });
    let mut dist: Vec<f64> = pts
        .iter()
        .map(|p| dot(sub(*p, median), sub(*p, median)).sqrt())
        .collect();
    dist.sort_by(f64::total_cmp);
    let radius_p90 = dist[((dist.len() - 1) as f64 * 0.9).round() as usize];
    Some(SceneExtent {
        centroid,
        rms_radius,
        median,
        radius_p90,
    })
}

/// An orbit pose around `center`: the camera sits at `distance` from it, at azimuth
/// `azimuth_deg` around the `up` axis and elevation `elevation_deg` above the plane
/// perpendicular to `up`, looking at `center` with `up` pointing up in the image.
pub fn orbit_pose(
    center: [f64; 3],
    distance: f64,
    up: [f64; 3],
    azimuth_deg: f64,
    elevation_deg: f64,
) -> Option<[f64; 12]> {
    let u = normalize(up)?;
    // Any unit vector perpendicular to `up` as the azimuth origin.
    let helper = if u[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let a = normalize(cross(u, helper))?;
    let b = cross(u, a);
    let (az, el) = (azimuth_deg.to_radians(), elevation_deg.to_radians());
    let dir: [f64; 3] =
        std::array::from_fn(|i| el.cos() * (az.cos() * a[i] + az.sin() * b[i]) + el.sin() * u[i]);
    let eye: [f64; 3] = std::array::from_fn(|i| center[i] + distance * dir[i]);
    look_at(eye, center, u)
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn normalize(a: [f64; 3]) -> Option<[f64; 3]> {
    let n = dot(a, a).sqrt();
    (n > 1e-12 && n.is_finite()).then(|| [a[0] / n, a[1] / n, a[2] / n])
}

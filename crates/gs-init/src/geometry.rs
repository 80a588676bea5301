//! Two-view geometry: pinhole views with optional OpenCV distortion, linear (DLT)
//! triangulation in normalised coordinates, and the rejection gates.

use nalgebra::Matrix4;
use profuse_formats::{camera, Cameras};
use serde::Serialize;

/// A posed pinhole view (SPEC.md §3.3): `x_cam = R x_world + t`, pixel centres at +0.5,
/// optional OpenCV radial-tangential distortion (k1, k2, p1, p2).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    /// Rows of R.
    pub rotation: [[f64; 3]; 3],
    /// t.
    pub translation: [f64; 3],
    /// fx, fy, cx, cy in pixels.
    pub intrinsics: [f64; 4],
    /// k1, k2, p1, p2; all zero for a pinhole camera.
    pub distortion: [f64; 4],
}

impl View {
    /// View `v` of a cameras file.
    pub fn from_cameras(cameras: &Cameras, v: usize) -> View {
        let (rotation, translation) = cameras.pose(v);
        View {
            rotation,
            translation,
            intrinsics: cameras.intrinsics[v],
            distortion: cameras.distortion.as_ref().map_or([0.0; 4], |d| d[v]),
        }
    }

    /// Camera centre in world coordinates (−Rᵀt).
    pub fn center(&self) -> [f64; 3] {
        camera::camera_centre(&self.rotation, &self.translation)
    }

    /// The optical axis (camera z) in world coordinates.
    pub fn axis(&self) -> [f64; 3] {
        self.rotation[2]
    }

    /// Camera coordinates of a world point.
    pub fn to_camera(&self, p: [f64; 3]) -> [f64; 3] {
        camera::world_to_camera(&self.rotation, &self.translation, p)
    }

    /// Mean focal length in pixels.
    pub fn focal(&self) -> f64 {
        0.5 * (self.intrinsics[0] + self.intrinsics[1])
    }

    /// Undistorted normalised image coordinates (x/z, y/z) of a pixel position.
    pub fn normalise(&self, pixel: [f64; 2]) -> [f64; 2] {
        let d = camera::pixel_to_normalised(&self.intrinsics, pixel);
        if self.distortion == [0.0; 4] {
            d
        } else {
            undistort(d, self.distortion)
        }
    }

    /// Pixel position of a world point (lens distortion applied where the view has one);
    /// the third value is the depth (camera z).
    pub fn project(&self, p: [f64; 3]) -> [f64; 3] {
        let c = self.to_camera(p);
        let n = distort([c[0] / c[2], c[1] / c[2]], self.distortion);
        let [u, v] = camera::normalised_to_pixel(&self.intrinsics, n);
        [u, v, c[2]]
    }
}

/// OpenCV radial-tangential model on normalised coordinates ([`camera::distort`]); the
/// identity, bit for bit, for a pinhole view.
pub fn distort(n: [f64; 2], k: [f64; 4]) -> [f64; 2] {
    if k == [0.0; 4] {
        return n;
    }
    camera::distort(&k, n)
}

/// Inverse of [`distort`] by fixed-point iteration (OpenCV's `undistortPoints` scheme),
/// run until the step is below 1e-14 or 50 iterations. Not [`camera::undistort`] (Newton,
/// rejecting points beyond the fold): that one would move the triangulated points of
/// distorted scenes, so gs-init keeps OpenCV's scheme.
pub fn undistort(d: [f64; 2], k: [f64; 4]) -> [f64; 2] {
    let [k1, k2, p1, p2] = k;
    let mut n = d;
    for _ in 0..50 {
        let (x, y) = (n[0], n[1]);
        let r2 = x * x + y * y;
        let radial = 1.0 + k1 * r2 + k2 * r2 * r2;
        let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        let next = [(d[0] - dx) / radial, (d[1] - dy) / radial];
        let step = (next[0] - n[0]).abs() + (next[1] - n[1]).abs();
        n = next;
        // NaN steps stop too.
        if step.partial_cmp(&1e-14) != Some(std::cmp::Ordering::Greater) {
            break;
        }
    }
    n
}

/// Why a triangulated point is rejected. The gates are checked in this order and the
/// first that fails is the reason.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Reason {
    /// The DLT solution is not finite or lies at infinity (parallel rays).
    NonFinite,
    /// The point is at or behind the near distance (camera z <= near) of either view.
    BehindCamera,
    /// The reprojection error exceeds the tolerance in either view.
    Reprojection,
    /// The angle between the two viewing rays at the point is below the minimum.
    LowAngle,
}

impl Reason {
    /// All reasons in gate order.
    pub const ALL: [Reason; 4] = [
        Reason::NonFinite,
        Reason::BehindCamera,
        Reason::Reprojection,
        Reason::LowAngle,
    ];

    /// The report's name of the reason.
    pub fn name(self) -> &'static str {
        match self {
            Reason::NonFinite => "non_finite",
            Reason::BehindCamera => "behind_camera",
            Reason::Reprojection => "reprojection",
            Reason::LowAngle => "low_angle",
        }
    }
}

/// The acceptance thresholds of a triangulated point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gates {
    /// Largest reprojection error in pixels accepted in each of the two views.
    pub max_reproj_px: f64,
    /// Smallest angle in degrees between the two viewing rays.
    pub min_angle_deg: f64,
    /// A point needs camera z > near in both views (scene units).
    pub near: f64,
}

/// A point triangulated from two views, with what the gates look at.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Triangulation {
    /// The point in world coordinates; `None` when the DLT solution is not finite or at
    /// infinity.
    pub point: Option<[f64; 3]>,
    /// Camera z of the point in the two views (NaN without a point).
    pub depths: [f64; 2],
    /// Reprojection error in pixels in the two views (infinite without a point).
    pub reproj_px: [f64; 2],
    /// Angle in degrees between the rays from the two camera centres to the point (0
    /// without a point).
    pub angle_deg: f64,
}

impl Triangulation {
    /// The larger of the two reprojection errors (the selection key between neighbours).
    pub fn max_reproj_px(&self) -> f64 {
        self.reproj_px[0].max(self.reproj_px[1])
    }

    /// Ok when every gate passes, else the first failing gate in [`Reason`] order.
    pub fn check(&self, gates: &Gates) -> Result<(), Reason> {
        // Written so that NaN fails every gate.
        let in_front = |z: &f64| *z > gates.near;
        let close = |e: &f64| *e <= gates.max_reproj_px;
        if self.point.is_none() {
            Err(Reason::NonFinite)
        } else if !self.depths.iter().all(in_front) {
            Err(Reason::BehindCamera)
        } else if !self.reproj_px.iter().all(close) {
            Err(Reason::Reprojection)
        } else if self.angle_deg >= gates.min_angle_deg {
            Ok(())
        } else {
            Err(Reason::LowAngle)
        }
    }
}

/// Triangulates pixel `pa` of view `a` with pixel `pb` of view `b` (pixel coordinates of
/// SPEC.md §3.3, distortion removed first). See [`triangulate_normalised`].
pub fn triangulate(a: &View, pa: [f64; 2], b: &View, pb: [f64; 2]) -> Triangulation {
    triangulate_normalised(a, a.normalise(pa), b, b.normalise(pb))
}

/// Linear (DLT) triangulation from undistorted normalised coordinates, then the errors
/// the gates need. Conditioning: the unknown point is expressed relative to `a`'s centre
/// in units of the baseline, so the 4x4 system is well scaled whatever the world frame;
/// each row is normalised to unit length. The solution is the right singular vector of
/// the smallest singular value; a homogeneous scale below 1e-12 of the point's norm (a
/// point more than 1e12 baselines away, or parallel rays) counts as infinity.
pub fn triangulate_normalised(a: &View, na: [f64; 2], b: &View, nb: [f64; 2]) -> Triangulation {
    let point = dlt(a, na, b, nb);
    let Some(x) = point else {
        return Triangulation {
            point: None,
            depths: [f64::NAN; 2],
            reproj_px: [f64::INFINITY; 2],
            angle_deg: 0.0,
        };
    };
    let (ca, cb) = (a.to_camera(x), b.to_camera(x));
    Triangulation {
        point,
        depths: [ca[2], cb[2]],
        reproj_px: [reproj_error(a, ca, na), reproj_error(b, cb, nb)],
        angle_deg: ray_angle_deg(sub(x, a.center()), sub(x, b.center())),
    }
}

/// Pixel distance between the pinhole projection of a camera-frame point and the
/// undistorted observation (both in normalised coordinates, scaled by fx and fy).
fn reproj_error(v: &View, cam: [f64; 3], n: [f64; 2]) -> f64 {
    let dx = v.intrinsics[0] * (cam[0] / cam[2] - n[0]);
    let dy = v.intrinsics[1] * (cam[1] / cam[2] - n[1]);
    // Not `hypot` (slow in libm): an overflow gives inf, which fails the gate anyway.
    let e = (dx * dx + dy * dy).sqrt();
    if e.is_nan() {
        f64::INFINITY
    } else {
        e
    }
}

fn dlt(a: &View, na: [f64; 2], b: &View, nb: [f64; 2]) -> Option<[f64; 3]> {
    let origin = a.center();
    let baseline = norm(sub(b.center(), origin));
    let s = if baseline > 0.0 && baseline.is_finite() {
        baseline
    } else {
        1.0
    };
    let mut m = Matrix4::<f64>::zeros();
    for (k, (v, n)) in [(a, na), (b, nb)].into_iter().enumerate() {
        // P' = [R | (R·origin + t)/s] maps the conditioned point Y = (X − origin)/s.
        let r = &v.rotation;
        let t: [f64; 3] = std::array::from_fn(|i| (dot(r[i], origin) + v.translation[i]) / s);
        let p = |i: usize| [r[i][0], r[i][1], r[i][2], t[i]];
        let (p0, p1, p2) = (p(0), p(1), p(2));
        for (row, (coord, pi)) in [(n[0], p0), (n[1], p1)].into_iter().enumerate() {
            let mut eq: [f64; 4] = std::array::from_fn(|c| coord * p2[c] - pi[c]);
            let len = eq.iter().map(|e| e * e).sum::<f64>().sqrt();
            if len > 0.0 && len.is_finite() {
                eq.iter_mut().for_each(|e| *e /= len);
            }
            for (c, e) in eq.into_iter().enumerate() {
                m[(2 * k + row, c)] = e;
            }
        }
    }
    if !m.iter().all(|e| e.is_finite()) {
        return None;
    }
    let svd = m.svd(false, true);
    let v_t = svd.v_t?;
    let smallest =
        (0..4).min_by(|&i, &j| svd.singular_values[i].total_cmp(&svd.singular_values[j]))?;
    let h = v_t.row(smallest);
    let (y, w) = ([h[0], h[1], h[2]], h[3]);
    let ny = norm(y);
    let at_infinity = w.abs() <= 1e-12 * ny || w.is_nan();
    if at_infinity || !ny.is_finite() {
        return None;
    }
    let x: [f64; 3] = std::array::from_fn(|i| origin[i] + s * y[i] / w);
    x.iter().all(|c| c.is_finite()).then_some(x)
}

/// Angle in degrees between two vectors, atan2(|u×v|, u·v) (accurate at small angles).
pub fn ray_angle_deg(u: [f64; 3], v: [f64; 3]) -> f64 {
    let c = [
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    ];
    norm(c).atan2(dot(u, v)).to_degrees()
}

pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(crate) fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn undistort_inverts_distort() {
        let k = [-0.12, 0.03, 0.001, -0.0007];
        for n in [[0.0, 0.0], [0.3, -0.2], [-0.5, 0.4], [0.6, 0.45]] {
            let back = undistort(distort(n, k), k);
            assert!((back[0] - n[0]).abs() < 1e-12 && (back[1] - n[1]).abs() < 1e-12);
        }
    }

    #[test]
    fn ray_angle_is_exact_for_known_vectors() {
        assert!((ray_angle_deg([1.0, 0.0, 0.0], [0.0, 2.0, 0.0]) - 90.0).abs() < 1e-12);
        assert!((ray_angle_deg([1.0, 0.0, 0.0], [1.0, 1.0, 0.0]) - 45.0).abs() < 1e-12);
        assert_eq!(ray_angle_deg([0.0, 0.0, 1.0], [0.0, 0.0, 3.0]), 0.0);
    }
}

//! Camera and colour math of SPEC.md §3.3 and §4.2, in one place so that every stage
//! projects, rescales, distorts and converts colours the same way, bit for bit.
//!
//! It lives in the formats crate because that crate owns the conventions (§3.3
//! "Coordinates and cameras", the `sh_dc` rule of §4.2) and is the one dependency every
//! stage already has; like the rest of the crate it works on plain `[f64; N]` arrays and
//! needs nothing else.
//!
//! Conventions (SPEC.md §3.3):
//! - poses are world-to-camera, `x_cam = R x_world + t`, OpenCV axes (x right, y down,
//!   z forward);
//! - pixel `(col, row)` covers `[col, col+1) x [row, row+1)`, its centre is
//!   `(col + 0.5, row + 0.5)`; `u = fx X/Z + cx`, `v = fy Y/Z + cy`;
//! - quaternions are `(w, x, y, z)`, not necessarily unit;
//! - lens distortion is OpenCV's radial-tangential model (k1, k2, p1, p2) on normalised
//!   coordinates;
//! - colour = [`SH_C0`] · dc + 0.5.
//!
//! The floating-point operation order of every function is part of its contract: the
//! pipeline's output files are compared byte for byte across refactors, so a function
//! here is only changed together with the expected bytes.
//!
//! # Example
//!
//! ```
//! use profuse_formats::camera::{
//!     pixel_centre, pixel_to_normalised, project, quaternion_to_rotation, rescale_intrinsics,
//!     world_to_camera,
//! };
//!
//! // A camera turned 90° about the world z axis, 2 units behind the origin along its view.
//! let h = std::f64::consts::FRAC_1_SQRT_2;
//! let r = quaternion_to_rotation([h, 0.0, 0.0, h]).expect("non-zero quaternion");
//! let t = [0.0, 0.0, 2.0];
//! let intrinsics = [100.0, 100.0, 32.0, 24.0]; // fx, fy, cx, cy for a 64 x 48 image
//!
//! // The world origin lands on the principal point, 2 units in front of the camera.
//! let c = world_to_camera(&r, &t, [0.0, 0.0, 0.0]);
//! assert_eq!(c, [0.0, 0.0, 2.0]);
//! assert_eq!(project(&intrinsics, c), [32.0, 24.0]);
//!
//! // The same camera on a 32 x 24 grid: the grid's pixel centres are the image's
//! // 2 x 2 block centres: grid pixel (3, 5) sees the ray through image point (7, 11).
//! let half = rescale_intrinsics(&intrinsics, [64, 48], [32, 24]);
//! assert_eq!(half, [50.0, 50.0, 16.0, 12.0]);
//! assert_eq!(
//!     pixel_to_normalised(&half, pixel_centre(3, 5)),
//!     pixel_to_normalised(&intrinsics, [7.0, 11.0]),
//! );
//! ```

/// A 3x3 matrix, row-major.
pub type Mat3 = [[f64; 3]; 3];

/// Pinhole intrinsics `[fx, fy, cx, cy]` in pixels.
pub type Intrinsics = [f64; 4];

/// OpenCV lens coefficients `[k1, k2, p1, p2]`.
pub type Lens = [f64; 4];

/// The degree-0 real spherical harmonic, 1 / (2 √π): colour = `SH_C0` · dc + 0.5.
pub const SH_C0: f64 = 0.282_094_791_773_878_14;

/// Colour in [0, 1] of a degree-0 SH coefficient (SPEC.md §4.2).
#[inline]
pub fn sh_dc_to_colour(dc: f64) -> f64 {
    SH_C0 * dc + 0.5
}

/// Degree-0 SH coefficient of a colour in [0, 1], the inverse of [`sh_dc_to_colour`].
#[inline]
pub fn colour_to_sh_dc(colour: f64) -> f64 {
    (colour - 0.5) / SH_C0
}

/// Degree-0 SH coefficient of an 8-bit colour channel (colour = value / 255), rounded to
/// the `sh_dc` tensor's f32.
#[inline]
pub fn rgb8_to_sh_dc(value: u8) -> f32 {
    colour_to_sh_dc(f64::from(value) / 255.0) as f32
}

/// Rotation matrix of a quaternion `(w, x, y, z)`, normalised first; `None` for a zero or
/// non-finite quaternion.
#[inline]
pub fn quaternion_to_rotation(q: [f64; 4]) -> Option<Mat3> {
    let [w, x, y, z] = q;
    let n = (w * w + x * x + y * y + z * z).sqrt();
    if !n.is_finite() || n == 0.0 {
        return None;
    }
    let (w, x, y, z) = (w / n, x / n, y / n, z / n);
    Some([
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ])
}

/// Rotation and translation of a row-major `[R | t]` (a `world_to_camera` row).
#[inline]
pub fn pose_from_row(m: &[f64; 12]) -> (Mat3, [f64; 3]) {
    (
        [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]],
        [m[3], m[7], m[11]],
    )
}

/// Row-major `[R | t]` (a `world_to_camera` row) of a rotation and translation.
#[inline]
pub fn pose_row(r: &Mat3, t: &[f64; 3]) -> [f64; 12] {
    [
        r[0][0], r[0][1], r[0][2], t[0], r[1][0], r[1][1], r[1][2], t[1], r[2][0], r[2][1],
        r[2][2], t[2],
    ]
}

/// Camera coordinates of a world point: `R p + t`.
#[inline]
pub fn world_to_camera(r: &Mat3, t: &[f64; 3], p: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|i| r[i][0] * p[0] + r[i][1] * p[1] + r[i][2] * p[2] + t[i])
}

/// World direction of a camera-frame direction: `Rᵀ d`.
#[inline]
pub fn camera_to_world_direction(r: &Mat3, d: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|i| r[0][i] * d[0] + r[1][i] * d[1] + r[2][i] * d[2])
}

/// Camera centre in world coordinates: `−Rᵀ t`.
#[inline]
pub fn camera_centre(r: &Mat3, t: &[f64; 3]) -> [f64; 3] {
    std::array::from_fn(|i| -(r[0][i] * t[0] + r[1][i] * t[1] + r[2][i] * t[2]))
}

/// Pixel position `(u, v)` of a camera-frame point: `u = fx X/Z + cx`, `v = fy Y/Z + cy`
/// (evaluated as `(fx X) / Z`). Not finite for points in the camera's plane.
#[inline]
pub fn project(intrinsics: &Intrinsics, c: [f64; 3]) -> [f64; 2] {
    let [fx, fy, cx, cy] = *intrinsics;
    [fx * c[0] / c[2] + cx, fy * c[1] / c[2] + cy]
}

/// Pixel position of normalised image coordinates `(X/Z, Y/Z)`: `(fx x + cx, fy y + cy)`.
/// Use it after [`distort`]; for an undistorted camera point [`project`] is the rule.
#[inline]
pub fn normalised_to_pixel(intrinsics: &Intrinsics, n: [f64; 2]) -> [f64; 2] {
    let [fx, fy, cx, cy] = *intrinsics;
    [fx * n[0] + cx, fy * n[1] + cy]
}

/// Normalised image coordinates `((u − cx) / fx, (v − cy) / fy)` of a pixel position: the
/// camera-frame ray through it at depth 1.
#[inline]
pub fn pixel_to_normalised(intrinsics: &Intrinsics, pixel: [f64; 2]) -> [f64; 2] {
    let [fx, fy, cx, cy] = *intrinsics;
    [(pixel[0] - cx) / fx, (pixel[1] - cy) / fy]
}

/// Centre `(col + 0.5, row + 0.5)` of pixel `(col, row)`.
#[inline]
pub fn pixel_centre(col: usize, row: usize) -> [f64; 2] {
    [col as f64 + 0.5, row as f64 + 0.5]
}

/// Intrinsics `[f, f, W/2, H/2]` of a `width` x `height` image with square pixels, the
/// principal point at the image centre and a horizontal field of view of `fov_x_deg`
/// degrees: `f = (W/2) / tan(fov_x / 2)`.
pub fn pinhole_intrinsics(width: u32, height: u32, fov_x_deg: f64) -> Intrinsics {
    let f = 0.5 * f64::from(width) / (0.5 * fov_x_deg.to_radians()).tan();
    [f, f, 0.5 * f64::from(width), 0.5 * f64::from(height)]
}

/// Intrinsics of the same camera on a `to = [width, height]` grid laid over its
/// `from = [width, height]` image: scaled by `to / from` per axis, so that each grid
/// pixel centre is the ray through the centre of the image region it covers. Unchanged
/// when the sizes agree.
#[inline]
pub fn rescale_intrinsics(intrinsics: &Intrinsics, from: [u32; 2], to: [u32; 2]) -> Intrinsics {
    let sx = f64::from(to[0]) / f64::from(from[0]);
    let sy = f64::from(to[1]) / f64::from(from[1]);
    let [fx, fy, cx, cy] = *intrinsics;
    [fx * sx, fy * sy, cx * sx, cy * sy]
}

/// OpenCV's radial-tangential model on undistorted normalised coordinates `(x, y)`:
///
/// ```text
/// r² = x² + y²,  s = 1 + k1 r² + k2 r⁴
/// x_d = x s + 2 p1 x y + p2 (r² + 2 x²)
/// y_d = y s + p1 (r² + 2 y²) + 2 p2 x y
/// ```
#[inline]
pub fn distort(lens: &Lens, n: [f64; 2]) -> [f64; 2] {
    let [k1, k2, p1, p2] = *lens;
    let [x, y] = n;
    let r2 = x * x + y * y;
    let s = 1.0 + k1 * r2 + k2 * r2 * r2;
    [
        x * s + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
        y * s + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
    ]
}

/// Newton iterations of [`undistort`] before it gives up.
const UNDISTORT_MAX_ITERATIONS: usize = 50;
/// Convergence tolerance of [`undistort`] on the residual, in normalised image units: far
/// below a thousandth of a pixel.
const UNDISTORT_TOLERANCE: f64 = 1e-12;

/// The Jacobian `∂(x_d, y_d)/∂(x, y)` of [`distort`], row-major.
fn distortion_jacobian(lens: &Lens, x: f64, y: f64) -> [f64; 4] {
    let [k1, k2, p1, p2] = *lens;
    let r2 = x * x + y * y;
    let s = 1.0 + k1 * r2 + k2 * r2 * r2;
    // ∂s/∂x = (k1 + 2 k2 r²) · 2x, and likewise for y.
    let ds = 2.0 * (k1 + 2.0 * k2 * r2);
    let (dsdx, dsdy) = (ds * x, ds * y);
    [
        s + x * dsdx + 2.0 * p1 * y + 6.0 * p2 * x,
        x * dsdy + 2.0 * p1 * x + 2.0 * p2 * y,
        y * dsdx + 2.0 * p1 * x + 2.0 * p2 * y,
        s + y * dsdy + 6.0 * p1 * y + 2.0 * p2 * x,
    ]
}

/// Inverts [`distort`]: the undistorted normalised coordinates of distorted ones.
///
/// The model has no closed-form inverse. OpenCV's `undistortPoints` runs a fixed number of
/// fixed-point iterations and returns whatever it reached; this is Newton's method on the
/// 2x2 Jacobian run to convergence, and `None` when it does not converge or converges
/// where the model folds over (Jacobian determinant <= 0, e.g. beyond the radius where a
/// negative k2 turns the radial factor back): such a point has no unique undistorted
/// position, and a guess would feed a wrong ray to triangulation.
pub fn undistort(lens: &Lens, distorted: [f64; 2]) -> Option<[f64; 2]> {
    let [xd, yd] = distorted;
    if !(xd.is_finite() && yd.is_finite()) {
        return None;
    }
    let (mut x, mut y) = (xd, yd);
    for _ in 0..UNDISTORT_MAX_ITERATIONS {
        let [fx, fy] = distort(lens, [x, y]);
        let (rx, ry) = (fx - xd, fy - yd);
        let [a, b, c, d] = distortion_jacobian(lens, x, y);
        let det = a * d - b * c;
        if rx.abs() < UNDISTORT_TOLERANCE && ry.abs() < UNDISTORT_TOLERANCE {
            return (det > 0.0).then_some([x, y]);
        }
        if det.is_nan() || det.abs() < 1e-300 {
            return None;
        }
        x -= (d * rx - b * ry) / det;
        y -= (a * ry - c * rx) / det;
        if !(x.is_finite() && y.is_finite()) {
            return None;
        }
    }
    None
}

/// Distorts a pinhole pixel position of a camera with these intrinsics and lens.
pub fn distort_pixel(intrinsics: &Intrinsics, lens: &Lens, pixel: [f64; 2]) -> [f64; 2] {
    normalised_to_pixel(
        intrinsics,
        distort(lens, pixel_to_normalised(intrinsics, pixel)),
    )
}

/// The pinhole pixel position of a distorted pixel position; `None` where [`undistort`]
/// rejects it.
pub fn undistort_pixel(intrinsics: &Intrinsics, lens: &Lens, pixel: [f64; 2]) -> Option<[f64; 2]> {
    let n = undistort(lens, pixel_to_normalised(intrinsics, pixel))?;
    Some(normalised_to_pixel(intrinsics, n))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    fn mat_close(a: &Mat3, b: &Mat3, tol: f64) -> bool {
        (0..3).all(|i| (0..3).all(|j| close(a[i][j], b[i][j], tol)))
    }

    /// Rodrigues' rotation of `v` about the unit `axis` by `angle`, an independent rule.
    fn rodrigues(axis: [f64; 3], angle: f64, v: [f64; 3]) -> [f64; 3] {
        let (s, c) = angle.sin_cos();
        let k = axis;
        let kxv = [
            k[1] * v[2] - k[2] * v[1],
            k[2] * v[0] - k[0] * v[2],
            k[0] * v[1] - k[1] * v[0],
        ];
        let kdv = k[0] * v[0] + k[1] * v[1] + k[2] * v[2];
        std::array::from_fn(|i| v[i] * c + kxv[i] * s + k[i] * kdv * (1.0 - c))
    }

    fn unit(v: [f64; 3]) -> [f64; 3] {
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        v.map(|x| x / n)
    }

    #[test]
    fn quaternion_is_w_first_and_matches_rodrigues() {
        let axes = [
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [1.0, -2.0, 0.5],
            [-0.3, 0.1, 0.9],
        ];
        for axis in axes.map(unit) {
            for angle in [0.0, 0.3, 1.0, 2.5, -1.7, std::f64::consts::PI] {
                let (s, c) = (0.5 * angle).sin_cos();
                // Scaled by 3.7: readers normalise (SPEC §4.2).
                let q = [c, s * axis[0], s * axis[1], s * axis[2]].map(|x| 3.7 * x);
                let r = quaternion_to_rotation(q).unwrap_or_default();
                for j in 0..3 {
                    let e: [f64; 3] = std::array::from_fn(|i| f64::from(u8::from(i == j)));
                    let want = rodrigues(axis, angle, e);
                    for i in 0..3 {
                        assert!(close(r[i][j], want[i], 1e-14), "{axis:?} {angle}: {r:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn quaternion_rotations_are_proper_and_zero_is_rejected() {
        let r = quaternion_to_rotation([0.9, 0.1, -0.3, 0.2]).unwrap_or_default();
        let rtr: Mat3 = std::array::from_fn(|i| {
            std::array::from_fn(|j| (0..3).map(|k| r[k][i] * r[k][j]).sum())
        });
        let eye = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert!(mat_close(&rtr, &eye, 1e-15));
        let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
            - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
            + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
        assert!(close(det, 1.0, 1e-15));
        assert_eq!(quaternion_to_rotation([2.0, 0.0, 0.0, 0.0]), Some(eye));
        // q and −q are the same rotation.
        assert_eq!(
            quaternion_to_rotation([-0.9, -0.1, 0.3, -0.2]),
            quaternion_to_rotation([0.9, 0.1, -0.3, 0.2])
        );
        assert_eq!(quaternion_to_rotation([0.0; 4]), None);
        assert_eq!(quaternion_to_rotation([f64::NAN, 0.0, 0.0, 1.0]), None);
        assert_eq!(quaternion_to_rotation([f64::INFINITY, 0.0, 0.0, 1.0]), None);
    }

    #[test]
    fn poses_are_world_to_camera() {
        let r = quaternion_to_rotation([0.9, 0.1, -0.3, 0.2]).unwrap_or_default();
        let t = [0.4, -1.5, 2.0];
        let row = pose_row(&r, &t);
        assert_eq!(row[3], 0.4);
        assert_eq!(row[4..7], r[1]);
        assert_eq!(pose_from_row(&row), (r, t));
        // x_cam = R x + t: the centre −Rᵀt maps to the camera origin ...
        let c = camera_centre(&r, &t);
        for v in world_to_camera(&r, &t, c) {
            assert!(close(v, 0.0, 1e-15));
        }
        // ... and a world point along Rᵀ e_z lies on the optical axis (OpenCV: z forward).
        let axis = camera_to_world_direction(&r, [0.0, 0.0, 1.0]);
        let p: [f64; 3] = std::array::from_fn(|i| c[i] + 2.5 * axis[i]);
        let q = world_to_camera(&r, &t, p);
        assert!(close(q[0], 0.0, 1e-14) && close(q[1], 0.0, 1e-14) && close(q[2], 2.5, 1e-14));
        // Rᵀ is R's inverse.
        let d = [0.3, -0.7, 1.1];
        let back = camera_to_world_direction(&r, world_to_camera(&r, &[0.0; 3], d));
        assert!((0..3).all(|i| close(back[i], d[i], 1e-15)));
    }

    #[test]
    fn projection_uses_pixel_centres_at_half_integers() {
        let k = [200.0, 150.0, 32.0, 24.0];
        // The optical axis hits the principal point; with cx = W/2 that is the image centre.
        assert_eq!(project(&k, [0.0, 0.0, 3.0]), [32.0, 24.0]);
        // A closed form: X/Z = 0.1, Y/Z = -0.2.
        assert_eq!(project(&k, [0.5, -1.0, 5.0]), [52.0, -6.0]);
        // Pixel (0, 0) covers [0, 1)²: its ray goes through (0.5, 0.5).
        assert_eq!(pixel_centre(0, 0), [0.5, 0.5]);
        assert_eq!(pixel_centre(7, 3), [7.5, 3.5]);
        let n = pixel_to_normalised(&k, pixel_centre(7, 3));
        assert_eq!(n, [(7.5 - 32.0) / 200.0, (3.5 - 24.0) / 150.0]);
        let back = project(&k, [4.0 * n[0], 4.0 * n[1], 4.0]);
        assert!(close(back[0], 7.5, 1e-12) && close(back[1], 3.5, 1e-12));
        assert_eq!(normalised_to_pixel(&k, [0.1, -0.2]), [52.0, -6.0]);
    }

    #[test]
    fn field_of_view_intrinsics_put_the_image_edges_at_half_the_angle() {
        let k = pinhole_intrinsics(100, 50, 90.0);
        assert!(close(k[0], 50.0, 1e-12) && k[0] == k[1]);
        assert_eq!(k[2..], [50.0, 25.0]);
        // The ray through the right image edge is fov_x / 2 = 30° off the axis.
        let k = pinhole_intrinsics(64, 48, 60.0);
        let [x, _] = pixel_to_normalised(&k, [64.0, 24.0]);
        assert!(close(x.atan().to_degrees(), 30.0, 1e-12));
    }

    #[test]
    fn rescaled_intrinsics_see_the_centre_of_each_covered_region() {
        let k = [410.0, 405.0, 321.5, 239.0];
        let (from, to) = ([640, 480], [160, 96]);
        let g = rescale_intrinsics(&k, from, to);
        assert_eq!(rescale_intrinsics(&k, from, from), k);
        // Grid pixel (i, j) covers image [i·W/w, (i+1)·W/w) x [j·H/h, (j+1)·H/h).
        let (sx, sy) = (640.0 / 160.0, 480.0 / 96.0);
        for (i, j) in [(0, 0), (17, 40), (159, 95)] {
            let image_centre = [(i as f64 + 0.5) * sx, (j as f64 + 0.5) * sy];
            let a = pixel_to_normalised(&g, pixel_centre(i, j));
            let b = pixel_to_normalised(&k, image_centre);
            assert!(
                close(a[0], b[0], 1e-15) && close(a[1], b[1], 1e-15),
                "{a:?} {b:?}"
            );
        }
        let want = [102.5, 81.0, 80.375, 47.8];
        assert!((0..4).all(|i| close(g[i], want[i], 1e-12)), "{g:?}");
    }

    const FOX: Lens = [0.0578421, -0.0805099, -0.000980296, 0.00015575];

    #[test]
    fn distort_matches_the_opencv_formula_on_a_hand_case() {
        // x = 0.3, y = -0.2: r² = 0.13, s = 1 + 0.1·0.13 + 0.01·0.0169 = 1.013169.
        let [xd, yd] = distort(&[0.1, 0.01, 0.001, 0.002], [0.3, -0.2]);
        let xe = 0.3 * 1.013169 + 2.0 * 0.001 * 0.3 * -0.2 + 0.002 * (0.13 + 2.0 * 0.09);
        let ye = -0.2 * 1.013169 + 0.001 * (0.13 + 2.0 * 0.04) + 2.0 * 0.002 * 0.3 * -0.2;
        assert!(close(xd, xe, 1e-15) && close(yd, ye, 1e-15));
        assert_eq!(distort(&[0.0; 4], [0.3, -0.2]), [0.3, -0.2]);
    }

    #[test]
    fn jacobian_agrees_with_finite_differences() {
        for (x, y) in [(0.1, 0.2), (-0.4, 0.3), (0.0, -0.6)] {
            let j = distortion_jacobian(&FOX, x, y);
            let h = 1e-7;
            let [ax, ay] = distort(&FOX, [x + h, y]);
            let [bx, by] = distort(&FOX, [x - h, y]);
            let [cx, cy] = distort(&FOX, [x, y + h]);
            let [dx, dy] = distort(&FOX, [x, y - h]);
            let num = [
                (ax - bx) / (2.0 * h),
                (cx - dx) / (2.0 * h),
                (ay - by) / (2.0 * h),
                (cy - dy) / (2.0 * h),
            ];
            for (a, b) in j.iter().zip(num) {
                assert!(close(*a, b, 1e-7), "{j:?} vs {num:?}");
            }
        }
    }

    #[test]
    fn undistort_inverts_distort_over_the_fox_image() {
        let k = [1375.52, 1374.49, 554.558, 965.268];
        let mut worst: f64 = 0.0;
        for v in (0..1920).step_by(37) {
            for u in (0..1080).step_by(29) {
                let p = pixel_centre(u, v);
                let d = distort_pixel(&k, &FOX, p);
                let back = undistort_pixel(&k, &FOX, d).unwrap_or([f64::NAN; 2]);
                worst = worst
                    .max((back[0] - p[0]).abs())
                    .max((back[1] - p[1]).abs());
            }
        }
        assert!(worst < 1e-8, "worst round-trip error {worst} px");
    }

    #[test]
    fn points_beyond_the_fold_are_rejected() {
        // s = 1 − r²: r_d = r − r³ peaks at r = 1/√3 (r_d ≈ 0.385); beyond it no inverse.
        let lens = [-1.0, 0.0, 0.0, 0.0];
        let n = undistort(&lens, [0.3, 0.0]).unwrap_or_default();
        // Closed form: the root of r − r³ = 0.3 below 1/√3.
        assert!(close(n[0] - n[0].powi(3), 0.3, 1e-12) && n[0] < 3f64.sqrt().recip());
        assert_eq!(undistort(&lens, [0.5, 0.0]), None);
        assert_eq!(undistort(&lens, [f64::NAN, 0.0]), None);
    }

    #[test]
    fn sh_constant_is_the_degree_zero_harmonic() {
        // Y_0^0 = 1 / (2 √π).
        assert!(close(SH_C0, 0.5 / std::f64::consts::PI.sqrt(), 1e-17));
        assert_eq!(SH_C0, 0.28209479177387814);
        assert_eq!(sh_dc_to_colour(0.0), 0.5);
        assert!(close(sh_dc_to_colour(colour_to_sh_dc(0.8)), 0.8, 1e-15));
        assert_eq!(rgb8_to_sh_dc(255), (0.5 / SH_C0) as f32);
        assert_eq!(rgb8_to_sh_dc(0), (-0.5 / SH_C0) as f32);
        let grey = f64::from(rgb8_to_sh_dc(51));
        assert!(close(sh_dc_to_colour(grey), 0.2, 1e-7));
    }
}

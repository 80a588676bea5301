//! Camera presets: each view of the cameras file in the form gsplat.js's camera takes.
//!
//! gsplat.js's camera is OpenCV-like, as SPEC.md §3.3 is: its view matrix is
//! `[Rᵀ | −Rᵀ p]` built from the camera's rotation R (camera to world, from the quaternion
//! it is given) and position p, and its projection maps camera (x, y, z) to clip
//! (2fx/W·x, −2fy/H·y, ·, z), so x right, y down, z forward with the focal lengths in pixels
//! and the principal point at the canvas centre. A preset therefore hands over the
//! camera centre, the camera-to-world rotation Rᵀ of the file's world-to-camera R as a
//! quaternion, fx and fy unchanged, and the principal point's offset from the image
//! centre, which the page applies by shifting a larger canvas behind an image-sized window.

use profuse_formats::camera::{camera_centre, pose_from_row, Mat3};
use profuse_formats::Cameras;

/// One view as the page sets it on gsplat.js's camera.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Preset {
    /// The view's image name.
    pub name: String,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal lengths in pixels.
    pub fx: f64,
    /// Focal lengths in pixels.
    pub fy: f64,
    /// Principal point minus the image centre, in pixels (x, y).
    pub principal_offset: [f64; 2],
    /// Camera centre in world coordinates.
    pub position: [f64; 3],
    /// Camera-to-world rotation as a unit quaternion (x, y, z, w), gsplat.js's order.
    pub rotation_xyzw: [f64; 4],
    /// Size of the canvas gsplat.js renders (the image grown by the principal point's
    /// offset on both sides, rounded up), whose centre is the principal point.
    pub canvas_size: [u32; 2],
    /// Where the canvas's top-left corner sits in the image window, in pixels: the image
    /// centre plus the principal offset minus half the canvas, rounded to whole pixels.
    pub canvas_origin: [i64; 2],
}

/// The presets of every view, in view order.
pub fn presets(cameras: &Cameras) -> Vec<Preset> {
    (0..cameras.len()).map(|v| preset(cameras, v)).collect()
}

fn preset(cameras: &Cameras, v: usize) -> Preset {
    let [width, height] = cameras.image_size[v];
    let [fx, fy, cx, cy] = cameras.intrinsics[v];
    let (r, t) = pose_from_row(&cameras.world_to_camera[v]);
    let offset = [cx - f64::from(width) / 2.0, cy - f64::from(height) / 2.0];
    let canvas = |size: u32, off: f64| size + 2 * off.abs().ceil() as u32;
    let canvas_size = [canvas(width, offset[0]), canvas(height, offset[1])];
    let origin = |size: u32, off: f64, grown: u32| {
        (f64::from(size) / 2.0 + off - f64::from(grown) / 2.0).round() as i64
    };
    Preset {
        name: cameras.image_names[v].clone(),
        width,
        height,
        fx,
        fy,
        principal_offset: offset,
        position: camera_centre(&r, &t),
        rotation_xyzw: rotation_to_quaternion(&transpose(&r)),
        canvas_size,
        canvas_origin: [
            origin(width, offset[0], canvas_size[0]),
            origin(height, offset[1], canvas_size[1]),
        ],
    }
}

fn transpose(m: &Mat3) -> Mat3 {
    std::array::from_fn(|i| std::array::from_fn(|j| m[j][i]))
}

/// The unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method: the branch on
/// the largest diagonal term keeps the square root away from zero).
pub fn rotation_to_quaternion(m: &Mat3) -> [f64; 4] {
    let trace = m[0][0] + m[1][1] + m[2][2];
    let q = if trace > 0.0 {
        let s = (trace + 1.0).sqrt() * 2.0;
        [
            (m[2][1] - m[1][2]) / s,
            (m[0][2] - m[2][0]) / s,
            (m[1][0] - m[0][1]) / s,
            s / 4.0,
        ]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
        [
            s / 4.0,
            (m[0][1] + m[1][0]) / s,
            (m[0][2] + m[2][0]) / s,
            (m[2][1] - m[1][2]) / s,
        ]
    } else if m[1][1] > m[2][2] {
        let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
        [
            (m[0][1] + m[1][0]) / s,
            s / 4.0,
            (m[1][2] + m[2][1]) / s,
            (m[0][2] - m[2][0]) / s,
        ]
    } else {
        let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
        [
            (m[0][2] + m[2][0]) / s,
            (m[1][2] + m[2][1]) / s,
            s / 4.0,
            (m[1][0] - m[0][1]) / s,
        ]
    };
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    q.map(|v| v / n)
}

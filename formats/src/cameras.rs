//! `profuse.cameras`: pinhole cameras in the OpenCV convention (SPEC.md "cameras").

use std::collections::BTreeMap;

use crate::camera;
use crate::check::{check_finite, check_len, invalid, out_of_range, TensorReader};
use crate::container::{Buffer, Container};
use crate::error::Result;
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// Largest |RᵀR − I| entry accepted for a rotation, and smallest determinant.
pub const ROTATION_TOLERANCE: f64 = 1e-4;

/// Views with intrinsics, world-to-camera poses and image sizes.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Cameras {
    /// Image path of each view, relative to the scene directory (metadata `image_names`).
    pub image_names: Vec<String>,
    /// `image_size` U32 [V, 2]: width, height in pixels.
    pub image_size: Buffer<[u32; 2]>,
    /// `intrinsics` F64 [V, 4]: fx, fy, cx, cy in pixels (pixel centres at integer + 0.5).
    pub intrinsics: Buffer<[f64; 4]>,
    /// `world_to_camera` F64 [V, 3, 4]: row-major `[R | t]`, x_cam = R x_world + t.
    pub world_to_camera: Buffer<[f64; 12]>,
    /// Optional `distortion` F64 [V, 4]: OpenCV k1, k2, p1, p2 (absent = pinhole).
    pub distortion: Option<Buffer<[f64; 4]>>,
    /// Other metadata, kept on round trips.
    pub extra: BTreeMap<String, String>,
}

/// A 3x3 rotation and a translation.
pub type Pose = ([[f64; 3]; 3], [f64; 3]);

impl Cameras {
    /// Number of views.
    pub fn len(&self) -> usize {
        self.image_names.len()
    }

    /// Whether there are no views.
    pub fn is_empty(&self) -> bool {
        self.image_names.is_empty()
    }

    /// Rotation and translation of view `v`.
    pub fn pose(&self, v: usize) -> Pose {
        camera::pose_from_row(&self.world_to_camera[v])
    }

    /// Camera centre of view `v` in world coordinates (−Rᵀt).
    pub fn center(&self, v: usize) -> [f64; 3] {
        let (r, t) = self.pose(v);
        camera::camera_centre(&r, &t)
    }

    /// Projects a world point into view `v` (pinhole, no distortion): pixel x, y and depth.
    pub fn project(&self, v: usize, p: [f64; 3]) -> [f64; 3] {
        let (r, t) = self.pose(v);
        let c = camera::world_to_camera(&r, &t, p);
        let [u, w] = camera::project(&self.intrinsics[v], c);
        [u, w, c[2]]
    }
}

impl FileKind for Cameras {
    const KIND: Kind = Kind::Cameras;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        let image_names = r.meta_strings("image_names")?;
        r.bind("V", image_names.len(), "metadata `image_names`");
        Ok(Cameras {
            image_size: r.req("image_size", "V,2")?,
            intrinsics: r.req("intrinsics", "V,4")?,
            world_to_camera: r.req("world_to_camera", "V,3,4")?,
            distortion: r.opt("distortion", "V,4")?,
            extra: r.extra_meta(&["image_names", "convention"]),
            image_names,
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        let v = self.image_names.len();
        check_len(
            path,
            "image_size",
            self.image_size.len(),
            v,
            "rows, one per image name",
        )?;
        check_len(
            path,
            "intrinsics",
            self.intrinsics.len(),
            v,
            "rows, one per image name",
        )?;
        check_len(
            path,
            "world_to_camera",
            self.world_to_camera.len(),
            v,
            "rows, one per image name",
        )?;
        if let Some(i) = self.image_names.iter().position(String::is_empty) {
            return Err(crate::check::meta_err(
                path,
                "image_names",
                &format!("non-empty names (entry {i} is empty)"),
            ));
        }
        for (i, [w, h]) in self.image_size.iter().enumerate() {
            if *w == 0 || *h == 0 {
                return Err(out_of_range(
                    path,
                    "image_size",
                    i,
                    format!("{w}x{h}"),
                    "a width and height >= 1",
                ));
            }
        }
        check_finite(
            path,
            "intrinsics",
            bytemuck::cast_slice::<_, f64>(&self.intrinsics),
        )?;
        for (i, k) in self.intrinsics.iter().enumerate() {
            for (j, f) in k[..2].iter().enumerate() {
                if *f <= 0.0 {
                    return Err(out_of_range(
                        path,
                        "intrinsics",
                        i * 4 + j,
                        f,
                        "a focal length > 0",
                    ));
                }
            }
        }
        check_finite(
            path,
            "world_to_camera",
            bytemuck::cast_slice::<_, f64>(&self.world_to_camera),
        )?;
        for i in 0..v {
            check_rotation(path, i, &self.pose(i).0)?;
        }
        if let Some(d) = &self.distortion {
            check_len(path, "distortion", d.len(), v, "rows, one per image name")?;
            check_finite(path, "distortion", bytemuck::cast_slice::<_, f64>(d))?;
        }
        Ok(())
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        let v = self.image_names.len();
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        w.meta_strings("image_names", &self.image_names)
            .meta("convention", "opencv_world_to_camera")
            .tensor("image_size", &[v, 2], &self.image_size)
            .tensor("intrinsics", &[v, 4], &self.intrinsics)
            .tensor("world_to_camera", &[v, 3, 4], &self.world_to_camera);
        if let Some(d) = &self.distortion {
            w.tensor("distortion", &[v, 4], d);
        }
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("views", self.len() as u64),
            ("distorted", u64::from(self.distortion.is_some())),
        ])
    }
}

fn check_rotation(path: &str, view: usize, r: &[[f64; 3]; 3]) -> Result<()> {
    for i in 0..3 {
        for j in 0..3 {
            let dot: f64 = (0..3).map(|k| r[k][i] * r[k][j]).sum();
            let want = if i == j { 1.0 } else { 0.0 };
            if (dot - want).abs() > ROTATION_TOLERANCE {
                return Err(invalid(
                    path,
                    "world_to_camera",
                    format!("view {view}: rotation is not orthonormal (RᵀR[{i}][{j}] = {dot:.6}, tolerance {ROTATION_TOLERANCE})"),
                ));
            }
        }
    }
    let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
        - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
        + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
    if det <= 0.0 {
        return Err(invalid(
            path,
            "world_to_camera",
            format!("view {view}: rotation has determinant {det:.6}, expected +1 (a reflection)"),
        ));
    }
    Ok(())
}

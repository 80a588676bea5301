//! The COLMAP sparse model as COLMAP stores it (before any conversion).

use std::collections::BTreeMap;
use std::path::PathBuf;

/// COLMAP camera models, with the ids of `cameras.bin` and the names of `cameras.txt`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum CameraModel {
    SimplePinhole,
    Pinhole,
    SimpleRadial,
    Radial,
    Opencv,
    OpencvFisheye,
    FullOpencv,
    Fov,
    SimpleRadialFisheye,
    RadialFisheye,
    ThinPrismFisheye,
    RadTanThinPrismFisheye,
}

impl CameraModel {
    /// Every model, indexed by its COLMAP id.
    pub const ALL: [CameraModel; 12] = [
        CameraModel::SimplePinhole,
        CameraModel::Pinhole,
        CameraModel::SimpleRadial,
        CameraModel::Radial,
        CameraModel::Opencv,
        CameraModel::OpencvFisheye,
        CameraModel::FullOpencv,
        CameraModel::Fov,
        CameraModel::SimpleRadialFisheye,
        CameraModel::RadialFisheye,
        CameraModel::ThinPrismFisheye,
        CameraModel::RadTanThinPrismFisheye,
    ];

    /// The model of a `cameras.bin` model id.
    pub fn from_id(id: i32) -> Option<CameraModel> {
        usize::try_from(id)
            .ok()
            .and_then(|i| CameraModel::ALL.get(i).copied())
    }

    /// The model of a `cameras.txt` model name.
    pub fn from_name(name: &str) -> Option<CameraModel> {
        CameraModel::ALL.into_iter().find(|m| m.name() == name)
    }

    /// The COLMAP id.
    pub fn id(self) -> i32 {
        CameraModel::ALL
            .iter()
            .position(|m| *m == self)
            .map_or(-1, |i| i as i32)
    }

    /// The COLMAP name.
    pub fn name(self) -> &'static str {
        match self {
            CameraModel::SimplePinhole => "SIMPLE_PINHOLE",
            CameraModel::Pinhole => "PINHOLE",
            CameraModel::SimpleRadial => "SIMPLE_RADIAL",
            CameraModel::Radial => "RADIAL",
            CameraModel::Opencv => "OPENCV",
            CameraModel::OpencvFisheye => "OPENCV_FISHEYE",
            CameraModel::FullOpencv => "FULL_OPENCV",
            CameraModel::Fov => "FOV",
            CameraModel::SimpleRadialFisheye => "SIMPLE_RADIAL_FISHEYE",
            CameraModel::RadialFisheye => "RADIAL_FISHEYE",
            CameraModel::ThinPrismFisheye => "THIN_PRISM_FISHEYE",
            CameraModel::RadTanThinPrismFisheye => "RAD_TAN_THIN_PRISM_FISHEYE",
        }
    }

    /// Number of parameters COLMAP stores for the model.
    pub fn num_params(self) -> usize {
        match self {
            CameraModel::SimplePinhole => 3,
            CameraModel::Pinhole | CameraModel::SimpleRadial | CameraModel::SimpleRadialFisheye => {
                4
            }
            CameraModel::Radial | CameraModel::Fov | CameraModel::RadialFisheye => 5,
            CameraModel::Opencv | CameraModel::OpencvFisheye => 8,
            CameraModel::FullOpencv | CameraModel::ThinPrismFisheye => 12,
            CameraModel::RadTanThinPrismFisheye => 16,
        }
    }
}

/// A camera (intrinsics shared by images).
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapCamera {
    pub id: u32,
    pub model: CameraModel,
    pub width: u64,
    pub height: u64,
    pub params: Vec<f64>,
}

/// Adds a camera to the model's table; a repeated CAMERA_ID is an error naming `file`
/// and `field` (the line or record the duplicate came from).
pub(crate) fn insert_camera(
    cameras: &mut BTreeMap<u32, ColmapCamera>,
    camera: ColmapCamera,
    file: &str,
    field: String,
) -> crate::error::Result<()> {
    let id = camera.id;
    if cameras.insert(id, camera).is_some() {
        return Err(crate::error::invalid(
            file,
            field,
            format!("camera {id} is listed twice"),
        ));
    }
    Ok(())
}

/// A registered image: world-to-camera pose and its 2D observations.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapImage {
    pub id: u32,
    /// Quaternion (w, x, y, z) of the world-to-camera rotation.
    pub qvec: [f64; 4],
    /// World-to-camera translation.
    pub tvec: [f64; 3],
    pub camera_id: u32,
    /// Image path relative to COLMAP's image directory.
    pub name: String,
    /// Keypoints (x, y) in pixels and the point3D id they observe (−1 = none).
    pub points2d: Vec<([f64; 2], i64)>,
}

/// A triangulated point.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapPoint {
    pub id: u64,
    pub xyz: [f64; 3],
    pub rgb: [u8; 3],
    pub error: f64,
    /// (image id, index into that image's `points2d`).
    pub track: Vec<(u32, u32)>,
}

/// Text (`*.txt`) or binary (`*.bin`) model files.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ColmapFormat {
    Text,
    Binary,
}

impl ColmapFormat {
    /// `text` or `binary`.
    pub fn name(self) -> &'static str {
        match self {
            ColmapFormat::Text => "text",
            ColmapFormat::Binary => "binary",
        }
    }

    pub(crate) fn extension(self) -> &'static str {
        match self {
            ColmapFormat::Text => "txt",
            ColmapFormat::Binary => "bin",
        }
    }
}

/// The three files of a model.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ModelFiles {
    pub format: ColmapFormat,
    pub cameras: PathBuf,
    pub images: PathBuf,
    pub points: PathBuf,
}

/// A whole sparse model.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapModel {
    pub files: ModelFiles,
    pub cameras: BTreeMap<u32, ColmapCamera>,
    pub images: Vec<ColmapImage>,
    pub points: Vec<ColmapPoint>,
}

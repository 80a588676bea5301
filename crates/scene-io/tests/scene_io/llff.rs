//! The LLFF `poses_bounds.npy` importer (issue 20, "importers users have"): checked
//! against a closed form (the same cameras written as a transforms.json), against
//! projections worked out from LLFF's [down, right, back] axes, at a downscale factor,
//! and on malformed scenes.
#![allow(clippy::needless_range_loop)]

use std::path::Path;

use scene_io::llff::{import_llff, LlffOptions};
use scene_io::npy::{write_npy, NpyArray, NpyData};
use scene_io::transforms::read_transforms;

/// An OpenGL camera-to-world pose: columns right, up, back (unit, right-handed) and the
/// centre.
struct GlPose {
    right: [f64; 3],
    up: [f64; 3],
    back: [f64; 3],
    centre: [f64; 3],
}

/// Three cameras: identity, a 90° turn about y, and a rotation by the 3-4-5 triangle
/// about x (exactly orthonormal in f64 up to rounding of 0.6 and 0.8).
fn poses() -> Vec<GlPose> {
    vec![
        GlPose {
            right: [1.0, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            back: [0.0, 0.0, 1.0],
            centre: [0.0, 0.0, 4.0],
        },
        GlPose {
            right: [0.0, 0.0, -1.0],
            up: [0.0, 1.0, 0.0],
            back: [1.0, 0.0, 0.0],
            centre: [3.0, 0.5, 0.0],
        },
        GlPose {
            right: [1.0, 0.0, 0.0],
            up: [0.0, 0.8, 0.6],
            back: [0.0, -0.6, 0.8],
            centre: [-1.0, 2.0, 3.5],
        },
    ]
}

const W: u32 = 64;
const H: u32 = 48;
const FOCAL: f64 = 50.0;

/// `poses_bounds.npy` rows for the poses: `[R | C | hwf]` row-major with R's columns
/// [down, right, back] = [−up, right, back], then near 0.5 and far 10 + i.
fn poses_bounds(poses: &[GlPose], hwf: [f64; 3]) -> NpyArray {
    let mut flat = Vec::new();
    for (i, p) in poses.iter().enumerate() {
        for r in 0..3 {
            flat.extend_from_slice(&[-p.up[r], p.right[r], p.back[r], p.centre[r], hwf[r]]);
        }
        flat.extend_from_slice(&[0.5, 10.0 + i as f64]);
    }
    NpyArray::new(vec![poses.len(), 17], NpyData::F64(flat)).unwrap()
}

/// The same cameras as a transforms.json (fl_x, w, h; principal point by default).
fn transforms_json(poses: &[GlPose]) -> String {
    let frames: Vec<String> = poses
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let row = |r: usize| {
                format!(
                    "[{:?}, {:?}, {:?}, {:?}]",
                    p.right[r], p.up[r], p.back[r], p.centre[r]
                )
            };
            format!(
                r#"{{"file_path": "images/v{i}.png", "transform_matrix": [{}, {}, {}, [0, 0, 0, 1]]}}"#,
                row(0),
                row(1),
                row(2)
            )
        })
        .collect();
    format!(
        r#"{{"fl_x": {FOCAL:?}, "fl_y": {FOCAL:?}, "w": {W}, "h": {H}, "frames": [{}]}}"#,
        frames.join(", ")
    )
}

fn png(path: &Path, w: u32, h: u32) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    image::RgbImage::new(w, h).save(path).unwrap();
}

/// A scene with `images/` (full size) and `images_2/` (half size) for the three poses.
fn scene(dir: &Path) {
    let poses = poses();
    write_npy(
        dir.join("poses_bounds.npy"),
        &poses_bounds(&poses, [f64::from(H), f64::from(W), FOCAL]),
    )
    .unwrap();
    std::fs::write(dir.join("transforms.json"), transforms_json(&poses)).unwrap();
    for i in 0..poses.len() {
        png(&dir.join(format!("images/v{i}.png")), W, H);
        png(&dir.join(format!("images_2/v{i}.png")), W / 2, H / 2);
    }
}

fn assert_close(a: &[f64], b: &[f64], what: &str) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert!((x - y).abs() < 1e-12, "{what}: {a:?} vs {b:?}");
    }
}

/// Closed form: the LLFF import of the scene equals the transforms.json import of the
/// same cameras (names, sizes, intrinsics exactly; poses to 1e-12).
#[test]
fn llff_equals_the_same_cameras_imported_from_transforms_json() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path());
    let (llff, report) = import_llff(dir.path(), &LlffOptions::default()).unwrap();
    let (tf, _) = read_transforms(dir.path().join("transforms.json")).unwrap();
    assert_eq!(report.views, 3);
    assert_eq!(report.images_dir, "images");
    assert_eq!((report.near_min, report.far_max), (0.5, 12.0));
    assert_eq!(llff.image_names, tf.image_names);
    assert_eq!(
        llff.image_names,
        ["images/v0.png", "images/v1.png", "images/v2.png"]
    );
    assert_eq!(llff.image_size, tf.image_size);
    assert_eq!(llff.intrinsics, tf.intrinsics);
    assert_eq!(llff.intrinsics[0], [50.0, 50.0, 32.0, 24.0]);
    assert!(llff.distortion.is_none() && tf.distortion.is_none());
    for v in 0..3 {
        assert_close(&llff.world_to_camera[v], &tf.world_to_camera[v], "pose");
    }
    assert_eq!(llff.extra.get("source").map(String::as_str), Some("llff"));
    // The path of the .npy itself works too.
    let (again, _) =
        import_llff(dir.path().join("poses_bounds.npy"), &LlffOptions::default()).unwrap();
    assert_eq!(again, llff);
}

/// Worked out from LLFF's axes, not from another importer: a point ahead of camera 1
/// (along −back) lands on the principal point at that depth; a step along LLFF's
/// "right" column moves it right (+u), along "down" moves it down (+v).
#[test]
fn llff_axes_project_as_down_right_back() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path());
    let (cams, _) = import_llff(dir.path(), &LlffOptions::default()).unwrap();
    let p = &poses()[1];
    let at = |d: f64, right: f64, down: f64| -> [f64; 3] {
        std::array::from_fn(|k| p.centre[k] - d * p.back[k] + right * p.right[k] - down * p.up[k])
    };
    let close = |a: [f64; 3], b: [f64; 3]| assert_close(&a, &b, "projection");
    close(cams.project(1, at(2.0, 0.0, 0.0)), [32.0, 24.0, 2.0]);
    close(
        cams.project(1, at(2.0, 0.4, 0.0)),
        [32.0 + 50.0 * 0.2, 24.0, 2.0],
    );
    close(
        cams.project(1, at(2.0, 0.0, 0.4)),
        [32.0, 24.0 + 50.0 * 0.2, 2.0],
    );
}

/// `factor = 2` reads `images_2/`, halves the focal length and the principal point, and
/// keeps the poses.
#[test]
fn llff_factor_scales_intrinsics_to_the_downscaled_images() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path());
    let (full, _) = import_llff(dir.path(), &LlffOptions::default()).unwrap();
    let (half, report) = import_llff(dir.path(), &LlffOptions { factor: 2 }).unwrap();
    assert_eq!(report.images_dir, "images_2");
    assert_eq!(half.image_names[2], "images_2/v2.png");
    assert_eq!(half.image_size[0], [32, 24]);
    assert_eq!(half.intrinsics[0], [25.0, 25.0, 16.0, 12.0]);
    assert_eq!(half.world_to_camera, full.world_to_camera);
}

fn err_text(dir: &Path, factor: u32) -> String {
    import_llff(dir, &LlffOptions { factor })
        .unwrap_err()
        .to_string()
}

/// Malformed scenes are errors naming the file and what was expected.
#[test]
fn llff_errors_name_the_problem() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path());
    let d = dir.path();
    // No images_4/: the folders present are listed.
    let msg = err_text(d, 4);
    assert!(msg.contains("missing directory `images_4/`"), "{msg}");
    assert!(msg.contains(r#"["images", "images_2"]"#), "{msg}");
    // Image count differs from the rows.
    std::fs::remove_file(d.join("images/v2.png")).unwrap();
    let msg = err_text(d, 1);
    assert!(
        msg.contains("2 image files (*JPG, *jpg, *png), but poses_bounds.npy has 3 rows"),
        "{msg}"
    );
    png(&d.join("images/v2.png"), W, H);
    // An image of the wrong size for the factor.
    png(&d.join("images_2/v1.png"), W, H / 2);
    let msg = err_text(d, 2);
    assert!(
        msg.contains("v1.png: image size: 64x24, but row 1"),
        "{msg}"
    );
    png(&d.join("images_2/v1.png"), W / 2, H / 2);
    // Wrong shape, non-finite values, a reflection.
    let npy = d.join("poses_bounds.npy");
    write_npy(
        &npy,
        &NpyArray::new(vec![3, 15], NpyData::F64(vec![0.0; 45])).unwrap(),
    )
    .unwrap();
    assert!(err_text(d, 1).contains("shape [3, 15] dtype f8, expected a float (N, 17)"));
    let mut rows = poses_bounds(&poses(), [48.0, 64.0, 50.0]);
    if let NpyData::F64(v) = &mut rows.data {
        v[17 + 3] = f64::NAN;
    }
    write_npy(&npy, &rows).unwrap();
    let msg = err_text(d, 1);
    assert!(msg.contains("row 1 column 3 of element 1 is NaN"), "{msg}");
    let mut rows = poses_bounds(&poses(), [48.0, 64.0, 50.0]);
    if let NpyData::F64(v) = &mut rows.data {
        for r in 0..3 {
            v[r * 5 + 2] = -v[r * 5 + 2]; // back → forward: a reflection
        }
    }
    write_npy(&npy, &rows).unwrap();
    let msg = err_text(d, 1);
    assert!(msg.contains("row 0 rotation [down, right, back]"), "{msg}");
    // No poses_bounds.npy at all.
    std::fs::remove_file(&npy).unwrap();
    assert!(err_text(d, 1).contains("missing poses_bounds.npy"));
    // An empty array.
    write_npy(
        &npy,
        &NpyArray::new(vec![0, 17], NpyData::F64(vec![])).unwrap(),
    )
    .unwrap();
    assert!(err_text(d, 1).contains("with N >= 1"));
}

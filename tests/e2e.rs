//! End-to-end tests across crates and tools: the command-line tools run as a user runs
//! them, on the golden vectors and on the real data in `../shared/data/`.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

// One module per stage tool; each uses the helpers defined in this file via `super::`.
#[path = "e2e/fox_semantic.rs"]
mod fox_semantic;
#[path = "e2e/fuse.rs"]
mod fuse;
#[path = "e2e/gs_init.rs"]
mod gs_init;
#[path = "e2e/metrics.rs"]
mod metrics;
#[path = "e2e/outputs.rs"]
mod outputs;
#[path = "e2e/pipeline.rs"]
mod pipeline;
#[path = "e2e/pq.rs"]
mod pq;
#[path = "e2e/query.rs"]
mod query;
#[path = "e2e/sweep.rs"]
mod sweep;
#[path = "e2e/vertex_transfer.rs"]
mod vertex_transfer;
#[path = "e2e/warp_graph.rs"]
mod warp_graph;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The directory of the built tool binaries (what the shell examples take as PROFUSE_BIN_DIR).
fn bin_dir() -> PathBuf {
    Path::new(env!("CARGO_BIN_EXE_profuse"))
        .parent()
        .unwrap()
        .to_path_buf()
}

fn profuse(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_profuse"))
        .args(args)
        .current_dir(root())
        .output()
        .unwrap()
}

/// Fails the test with the tool's stderr when it did not exit 0.
fn assert_succeeded(out: &Output) {
    assert!(
        out.status.success(),
        "exit {:?}: {}",
        out.status.code(),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Every file under `root` (relative path) with its bytes.
fn files(root: &Path) -> std::collections::BTreeMap<PathBuf, Vec<u8>> {
    let mut out = std::collections::BTreeMap::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.insert(
                    p.strip_prefix(root).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                );
            }
        }
    }
    out
}

fn json(out: &Output) -> serde_json::Value {
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "stdout is not JSON ({e}): {}",
            String::from_utf8_lossy(&out.stdout)
        )
    })
}

#[test]
fn inspect_reports_valid_files_with_exit_code_0() {
    let out = profuse(&["inspect", "formats/vectors/valid/masks.safetensors"]);
    assert_succeeded(&out);
    let j = json(&out);
    assert_eq!(j["valid"], true);
    assert_eq!(j["kind"], "masks");
    assert_eq!(j["counts"]["masks"], 5);
    assert_eq!(j["tensors"]["labels"]["dtype"], "U16");
    assert!(out.stderr.is_empty());
}

#[test]
fn inspect_fails_invalid_files_with_exit_code_1_and_the_error_on_stderr() {
    let out = profuse(&[
        "inspect",
        "formats/vectors/invalid/cameras__invalid.safetensors",
    ]);
    assert_eq!(out.status.code(), Some(1));
    let j = json(&out);
    assert_eq!(j["valid"], false);
    assert_eq!(j["error"]["code"], "invalid");
    assert_eq!(j["error"]["field"], "world_to_camera");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("cameras__invalid.safetensors") && err.contains("orthonormal"),
        "{err}"
    );

    let out = profuse(&["inspect", "no/such/file.safetensors"]);
    assert_eq!(out.status.code(), Some(1));
    assert_eq!(json(&out)["error"]["code"], "io");
}

/// Whether python3 can `import modules` (comma-separated). When it cannot, the test is
/// skipped with a message naming `install`, unless the environment variable `require` is
/// `1` (`.ci/run` sets it), which makes the absence a failure.
fn python_has(modules: &str, require: &str, install: &str) -> bool {
    let probe = Command::new("python3")
        .args(["-c", &format!("import {modules}")])
        .output();
    if probe.map(|o| o.status.success()).unwrap_or(false) {
        return true;
    }
    assert!(
        std::env::var(require).as_deref() != Ok("1"),
        "python3 with {modules} is required ({install}); {require}=1"
    );
    eprintln!("SKIPPED: python3 with {modules} not found; run `{install}`");
    false
}

/// The Python reader reads exactly what Rust wrote and prints the same inspect JSON, and
/// Rust reads what the Python writers write. Needs `numpy` and `safetensors` for python3;
/// skipped with a message when they are missing, unless PROFUSE_REQUIRE_PYTHON=1 (set by
/// `.ci/run`) makes that a failure.
#[test]
fn python_reader_agrees_with_rust_on_every_golden_vector() {
    if !python_has(
        "numpy, safetensors",
        "PROFUSE_REQUIRE_PYTHON",
        "pip install ./formats/python",
    ) {
        return;
    }
    // The reader's tests, then the writers' (every kind written by Python is read by
    // `profuse inspect`, and the golden vectors are rewritten byte for byte), then hostile
    // inputs (issue 20 items 2 and 3: huge empty shapes, and seeded mutations of the golden
    // vectors that must give a FormatError or a record in time, agreeing with Rust).
    for script in [
        "test_profuse_formats.py",
        "test_writers.py",
        "test_hostile_inputs.py",
    ] {
        let out = Command::new("python3")
            .arg(format!("formats/python/{script}"))
            .env("PROFUSE_RUST_INSPECT", env!("CARGO_BIN_EXE_profuse"))
            .current_dir(root())
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "python tests {script} failed:\n{}\n{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }
}

/// Runs a built tool binary of this package by name (`env!("CARGO_BIN_EXE_<name>")` path
/// passed in by the caller) from the repository root.
fn run_tool(exe: &str, args: &[&std::ffi::OsStr]) -> Output {
    Command::new(exe)
        .args(args)
        .current_dir(root())
        .output()
        .unwrap()
}

fn shared_data(rel: &str) -> Option<PathBuf> {
    let p = root().join("../shared/data").join(rel);
    if p.exists() {
        Some(p)
    } else {
        eprintln!(
            "SKIPPED: {} is absent (the shared data folder is not next to the checkout)",
            p.display()
        );
        None
    }
}

fn scene_io(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_scene-io"))
        .args(args)
        .current_dir(root())
        .output()
        .unwrap()
}

/// guitar.ply -> gaussians file that `profuse inspect` reports valid with 90854 Gaussians,
/// -> PLY again, whose re-import is bit-identical.
#[test]
fn scene_io_converts_guitar_ply_and_profuse_inspect_validates_it() {
    let Some(ply) = shared_data("splats/guitar.ply") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let g = dir.path().join("guitar.safetensors");
    let out = scene_io(&[
        "ply-import".as_ref(),
        ply.as_os_str(),
        "--out".as_ref(),
        g.as_os_str(),
    ]);
    assert_succeeded(&out);
    let report = json(&out);
    assert_eq!(report["gaussians"], 90854);
    assert_eq!(report["clamped_opacity"], 667);

    let out = profuse(&["inspect", g.to_str().unwrap()]);
    assert!(out.status.success());
    let j = json(&out);
    assert_eq!(
        (j["valid"].clone(), j["kind"].clone()),
        (true.into(), "gaussians".into())
    );
    assert_eq!(j["counts"]["gaussians"], 90854);
    assert_eq!(
        j["tensors"]["means"]["shape"],
        serde_json::json!([90854, 3])
    );

    let back_ply = dir.path().join("back.ply");
    let out = scene_io(&[
        "ply-export".as_ref(),
        g.as_os_str(),
        "--out".as_ref(),
        back_ply.as_os_str(),
    ]);
    assert_succeeded(&out);
    let again = dir.path().join("again.safetensors");
    let out = scene_io(&[
        "ply-import".as_ref(),
        back_ply.as_os_str(),
        "--out".as_ref(),
        again.as_os_str(),
        "--quiet".as_ref(),
    ]);
    assert!(out.status.success());
    assert_eq!(json(&out)["clamped_opacity"], 0);
    assert_eq!(
        std::fs::read(&g).unwrap(),
        std::fs::read(&again).unwrap(),
        "PLY round trip changed bytes"
    );
}

/// fox transforms.json -> 50 views (17 frames have no image: warnings on stderr), valid.
#[test]
fn scene_io_imports_fox_transforms_with_50_views() {
    let Some(tj) = shared_data("fox/transforms.json") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let cams = dir.path().join("cameras.safetensors");
    let out = scene_io(&[
        "transforms".as_ref(),
        tj.as_os_str(),
        "--out".as_ref(),
        cams.as_os_str(),
    ]);
    assert_succeeded(&out);
    assert_eq!(json(&out)["views"], 50);
    assert_eq!(
        String::from_utf8_lossy(&out.stderr)
            .matches("warning:")
            .count(),
        17
    );
    let j = json(&profuse(&["inspect", cams.to_str().unwrap()]));
    assert_eq!(j["counts"]["views"], 50);
    assert_eq!(j["valid"], true);
}

/// A failing import exits 1, names the file, and writes nothing.
#[test]
fn scene_io_failure_exits_1_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.ply");
    std::fs::write(&bad, b"ply\nformat binary_big_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n\0\0\0\0").unwrap();
    let target = dir.path().join("out.safetensors");
    let out = scene_io(&[
        "ply-import".as_ref(),
        bad.as_os_str(),
        "--out".as_ref(),
        target.as_os_str(),
    ]);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("bad.ply"));
    assert!(out.stdout.is_empty());
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        1,
        "something was written"
    );
}

/// Every file `synth` writes is valid for `profuse inspect` (tiny and demo presets), and
/// the tool's JSON summary describes what it wrote.
#[test]
fn profuse_inspect_validates_every_file_synth_writes() {
    for preset in ["tiny", "demo"] {
        let dir = tempfile::tempdir().unwrap();
        let out = Command::new(env!("CARGO_BIN_EXE_synth"))
            .args(["--preset", preset, "--seed", "3", "--quiet", "--out"])
            .arg(dir.path())
            .output()
            .unwrap();
        assert_succeeded(&out);
        let summary = json(&out);
        let mut files = Vec::new();
        let mut stack = vec![dir.path().to_path_buf()];
        while let Some(d) = stack.pop() {
            for e in std::fs::read_dir(&d).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    stack.push(p);
                } else if p.extension().is_some_and(|x| x == "safetensors") {
                    files.push(p);
                }
            }
        }
        files.sort();
        // cameras, masks, matches, prompts, gt/views, gt/mesh (+ gt/gaussians for demo)
        let expected = if preset == "demo" { 7 } else { 6 };
        assert_eq!(files.len(), expected, "{preset}: {files:?}");
        for f in &files {
            let out = profuse(&["inspect", f.to_str().unwrap()]);
            assert!(
                out.status.success(),
                "{}: {}",
                f.display(),
                String::from_utf8_lossy(&out.stderr)
            );
        }
        let cams = json(&profuse(&[
            "inspect",
            dir.path().join("cameras.safetensors").to_str().unwrap(),
        ]));
        assert_eq!(cams["counts"]["views"], summary["views"], "{preset}");
        let masks = json(&profuse(&[
            "inspect",
            dir.path().join("masks.safetensors").to_str().unwrap(),
        ]));
        assert_eq!(masks["counts"]["masks"], summary["masks"], "{preset}");
    }
}

fn splat_raster(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_splat-raster"))
        .args(args)
        .current_dir(root())
        .output()
        .unwrap()
}

/// The synthetic scene's ground-truth Gaussians render through its own cameras, and the
/// top-K dump is a valid `profuse.topk` file whose hits cover the image.
#[test]
fn splat_raster_renders_synth_views_and_dumps_valid_topk() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    let out = Command::new(env!("CARGO_BIN_EXE_synth"))
        .args([
            "--preset",
            "tiny",
            "--seed",
            "1",
            "--gaussians",
            "3000",
            "--quiet",
            "--out",
        ])
        .arg(&scene)
        .output()
        .unwrap();
    assert_succeeded(&out);
    let g = scene.join("gt/gaussians.safetensors");
    let cams = scene.join("cameras.safetensors");
    let topk = dir.path().join("topk.safetensors");
    let out = splat_raster(&[
        "topk".as_ref(),
        g.as_os_str(),
        "--cameras".as_ref(),
        cams.as_os_str(),
        "--view".as_ref(),
        "1".as_ref(),
        "--k".as_ref(),
        "8".as_ref(),
        "--out".as_ref(),
        topk.as_os_str(),
    ]);
    assert_succeeded(&out);
    let j = json(&profuse(&["inspect", topk.to_str().unwrap()]));
    assert_eq!(j["valid"], true, "{j}");
    assert_eq!(j["counts"]["k"], 8);
    let pixels = j["counts"]["width"].as_u64().unwrap() * j["counts"]["height"].as_u64().unwrap();
    // Surfels cover the closed room, so most pixels have several contributors.
    assert!(j["counts"]["hits"].as_u64().unwrap() > pixels, "{j}");

    let renders = dir.path().join("renders");
    let out = splat_raster(&[
        "render".as_ref(),
        g.as_os_str(),
        "--cameras".as_ref(),
        cams.as_os_str(),
        "--view".as_ref(),
        "1".as_ref(),
        "--out-dir".as_ref(),
        renders.as_os_str(),
        "--color".as_ref(),
        "--alpha".as_ref(),
        "--quiet".as_ref(),
    ]);
    assert_succeeded(&out);
    let files: Vec<_> = std::fs::read_dir(&renders)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(files.len(), 2, "{files:?}");
    assert!(files
        .iter()
        .all(|f| f.extension().is_some_and(|x| x == "png")
            && std::fs::metadata(f).unwrap().len() > 100));
}

/// An orbit preview of the real guitar.ply covers a sensible share of the image.
#[test]
fn splat_raster_orbit_preview_of_guitar_ply() {
    let Some(ply) = shared_data("splats/guitar.ply") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let out = splat_raster(&[
        "render".as_ref(),
        ply.as_os_str(),
        "--orbit-angle".as_ref(),
        "270".as_ref(),
        "--width".as_ref(),
        "160".as_ref(),
        "--height".as_ref(),
        "120".as_ref(),
        "--out-dir".as_ref(),
        dir.path().as_os_str(),
        "--color".as_ref(),
        "--quiet".as_ref(),
    ]);
    assert_succeeded(&out);
    let j = json(&out);
    assert_eq!(j["gaussians"], 90854);
    let coverage = j["coverage"].as_f64().unwrap();
    assert!((0.05..0.6).contains(&coverage), "coverage {coverage}");
}

/// Runs a tool with a file-size limit of `kb` KiB (`ulimit -f`, SIGXFSZ ignored): a write
/// past it fails with EFBIG like a write on a full disk, whoever runs the test (root
/// included, unlike a read-only directory).
fn run_tool_with_file_limit(kb: u64, exe: &str, args: &[&std::ffi::OsStr]) -> Output {
    Command::new("bash")
        .arg("-c")
        .arg("trap '' XFSZ; ulimit -f \"$1\"; shift; exec \"$@\"")
        .arg("limit")
        .arg(kb.to_string())
        .arg(exe)
        .args(args)
        .current_dir(root())
        .output()
        .unwrap()
}

//! End-to-end tests of `profuse run`: the same outputs as the plumbing tools composed in
//! `tools/pipeline.sh`, and a run killed at any point followed by a rerun gives the bytes
//! of an uninterrupted run.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use super::{assert_succeeded, root, run_tool};

fn tiny_scene(dir: &Path) {
    let out = run_tool(
        env!("CARGO_BIN_EXE_synth"),
        &[
            "--preset".as_ref(),
            "tiny".as_ref(),
            "--seed".as_ref(),
            "0".as_ref(),
            "--out".as_ref(),
            dir.as_os_str(),
            "--quiet".as_ref(),
        ],
    );
    assert_succeeded(&out);
}

fn profuse_run(scene: &Path, extra: &[&str]) -> std::process::Output {
    let mut args: Vec<&std::ffi::OsStr> = vec![
        "run".as_ref(),
        scene.as_os_str(),
        "--quiet".as_ref(),
        "--set".as_ref(),
        "pq.m=16".as_ref(),
    ];
    args.extend(extra.iter().map(std::ffi::OsStr::new));
    run_tool(env!("CARGO_BIN_EXE_profuse"), &args)
}

/// Every file under `dir` (completion records and run summaries aside) with its bytes.
fn files(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    fn walk(base: &Path, dir: &Path, out: &mut BTreeMap<PathBuf, Vec<u8>>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            if name.starts_with('.') || name.starts_with("summary") || name.starts_with("config") {
                continue;
            }
            if p.is_dir() {
                walk(base, &p, out);
            } else {
                out.insert(
                    p.strip_prefix(base).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                );
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(dir, dir, &mut out);
    out
}

fn bin_dir() -> PathBuf {
    Path::new(env!("CARGO_BIN_EXE_profuse"))
        .parent()
        .unwrap()
        .to_path_buf()
}

#[test]
fn shell_composition_of_the_tools_equals_profuse_run_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    tiny_scene(&scene);
    let out = Command::new("bash")
        .arg(root().join("tools/pipeline.sh"))
        .arg(&scene)
        .env("PROFUSE_BIN_DIR", bin_dir())
        .env("PQ_M", "16")
        .output()
        .unwrap();
    assert_succeeded(&out);
    let composed = files(&scene.join("out"));
    std::fs::remove_dir_all(scene.join("out")).unwrap();

    assert_succeeded(&profuse_run(&scene, &[]));
    let run = files(&scene.join("out"));
    assert_eq!(
        composed.keys().collect::<Vec<_>>(),
        run.keys().collect::<Vec<_>>(),
        "different files"
    );
    for (name, bytes) in &composed {
        assert!(&run[name] == bytes, "{} differs", name.display());
    }
    for must in [
        "gaussians.safetensors",
        "proposals.safetensors",
        "features.safetensors",
        "pq.safetensors",
        "vertex_labels_nyu19.safetensors",
        "vertex_labels_nyu15.safetensors",
        "vertex_labels_nyu10.safetensors",
    ] {
        assert!(run.contains_key(Path::new(must)), "{must} missing");
    }
    assert!(
        run.keys().any(|k| k.starts_with("query")),
        "no query outputs"
    );
}

#[test]
fn a_run_killed_mid_stage_is_completed_by_the_next_run_with_identical_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    tiny_scene(&scene);
    assert_succeeded(&profuse_run(&scene, &[]));
    let reference = files(&scene.join("out"));

    // Kill forced reruns at several moments: whatever stage was running, the next run must
    // finish the job and leave exactly the reference outputs.
    for delay_ms in [30u64, 120, 300, 700] {
        let mut child = Command::new(env!("CARGO_BIN_EXE_profuse"))
            .args(["run", "--quiet", "--force", "--set", "pq.m=16"])
            .arg(&scene)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(Duration::from_millis(delay_ms));
        let _ = child.kill();
        let _ = child.wait();
        let out = profuse_run(&scene, &[]);
        assert_succeeded(&out);
        assert_eq!(
            files(&scene.join("out")),
            reference,
            "after a kill at {delay_ms} ms"
        );
    }
}

#[test]
fn profuse_run_failure_names_the_stage_and_file_and_exits_1() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    tiny_scene(&scene);
    std::fs::write(scene.join("masks.safetensors"), b"truncated").unwrap();
    let out = profuse_run(&scene, &[]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("warp-graph") && err.contains("masks.safetensors"),
        "{err}"
    );
    let out = profuse_run(&scene, &["--set", "fuse.kk=3"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("kk"));
}

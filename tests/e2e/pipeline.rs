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

#[test]
fn shell_composition_of_the_tools_equals_profuse_run_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    tiny_scene(&scene);
    let out = Command::new("bash")
        .arg(root().join("tools/pipeline.sh"))
        .arg(&scene)
        .env("PROFUSE_BIN_DIR", super::bin_dir())
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

/// A run split as a cluster runs it (issue 21): `--until warp-graph`, then `fuse-shard`
/// per view range (each could run on another machine), then `--fuse-partials`: the same
/// bytes as one `profuse run`. Missing or foreign shards are refused, naming the cause.
#[test]
fn a_run_split_into_fuse_shards_equals_one_run_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    tiny_scene(&scene);
    assert_succeeded(&profuse_run(&scene, &[]));
    let reference = files(&scene.join("out"));
    std::fs::remove_dir_all(scene.join("out")).unwrap();

    let head = profuse_run(&scene, &["--until", "warp-graph"]);
    assert_succeeded(&head);
    let summary: serde_json::Value = serde_json::from_slice(&head.stdout).unwrap();
    let stages: Vec<&str> = summary["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["stage"].as_str().unwrap())
        .collect();
    assert_eq!(stages, ["gs-init", "warp-graph"]);
    assert!(summary["metrics"].is_null(), "an early stop is not scored");
    assert!(!scene.join("out/features.safetensors").exists());

    let shards = dir.path().join("shards");
    std::fs::create_dir(&shards).unwrap();
    let shard = |range: &str| {
        let path = shards.join(format!("{range}.safetensors"));
        let out = run_tool(
            env!("CARGO_BIN_EXE_profuse"),
            &[
                "fuse-shard".as_ref(),
                scene.as_os_str(),
                "--views".as_ref(),
                range.as_ref(),
                "--partial-out".as_ref(),
                path.as_os_str(),
                "--set".as_ref(),
                "pq.m=16".as_ref(),
                "--quiet".as_ref(),
            ],
        );
        assert_succeeded(&out);
        let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(report["partial_out"], path.to_str().unwrap());
        path.to_str().unwrap().to_string()
    };
    let (a, b) = (shard("0..1"), shard("1..4"));

    let missing = profuse_run(&scene, &["--fuse-partials", &a]);
    assert_eq!(missing.status.code(), Some(1));
    let err = String::from_utf8_lossy(&missing.stderr);
    assert!(err.contains("fuse") && err.contains("view"), "{err}");

    let tail = profuse_run(&scene, &["--fuse-partials", &b, &a]);
    assert_succeeded(&tail);
    assert_same_files(&reference, &files(&scene.join("out")));

    // A shard made with another K is not summed into this run's features.
    let other = shards.join("k20.safetensors");
    let out = run_tool(
        env!("CARGO_BIN_EXE_profuse"),
        &[
            "fuse-shard".as_ref(),
            scene.as_os_str(),
            "--views".as_ref(),
            "0..1".as_ref(),
            "--partial-out".as_ref(),
            other.as_os_str(),
            "--set".as_ref(),
            "fuse.k=20".as_ref(),
            "--quiet".as_ref(),
        ],
    );
    assert_succeeded(&out);
    let foreign = profuse_run(
        &scene,
        &["--force", "--fuse-partials", other.to_str().unwrap(), &b],
    );
    assert_eq!(foreign.status.code(), Some(1));
    let err = String::from_utf8_lossy(&foreign.stderr);
    assert!(err.contains("`k`"), "{err}");

    let bad = profuse_run(&scene, &["--until", "nowhere"]);
    assert_eq!(bad.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("stages: gs-init"));
}

/// The same files with the same bytes.
fn assert_same_files(reference: &BTreeMap<PathBuf, Vec<u8>>, split: &BTreeMap<PathBuf, Vec<u8>>) {
    assert_eq!(
        reference.keys().collect::<Vec<_>>(),
        split.keys().collect::<Vec<_>>(),
        "different files"
    );
    for (name, bytes) in reference {
        assert!(&split[name] == bytes, "{} differs", name.display());
    }
}

/// `profuse warp-shard` over `pairs`, with extra arguments; returns the file and the
/// report.
fn warp_shard(
    scene: &Path,
    dir: &Path,
    pairs: &str,
    extra: &[&str],
) -> (String, serde_json::Value) {
    let path = dir.join(format!(
        "pairs_{}{}.safetensors",
        pairs.replace("..", "_"),
        extra.len()
    ));
    let mut args: Vec<&std::ffi::OsStr> = vec![
        "warp-shard".as_ref(),
        scene.as_os_str(),
        "--pairs".as_ref(),
        pairs.as_ref(),
        "--partial-out".as_ref(),
        path.as_os_str(),
        "--set".as_ref(),
        "pq.m=16".as_ref(),
        "--quiet".as_ref(),
    ];
    args.extend(extra.iter().map(std::ffi::OsStr::new));
    let out = run_tool(env!("CARGO_BIN_EXE_profuse"), &args);
    assert_succeeded(&out);
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["partial_out"], path.to_str().unwrap());
    (path.to_str().unwrap().to_string(), report)
}

/// warp-graph split over view pairs (issue 21): `--until gs-init`, `warp-shard` per pair
/// range (`0..0` tells the number of view pairs), then `--warp-partials`: the same bytes
/// as one `profuse run`, every file. Missing or foreign shards are refused, naming the
/// cause.
#[test]
fn a_run_split_into_warp_shards_equals_one_run_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    tiny_scene(&scene);
    assert_succeeded(&profuse_run(&scene, &[]));
    let reference = files(&scene.join("out"));
    std::fs::remove_dir_all(scene.join("out")).unwrap();

    assert_succeeded(&profuse_run(&scene, &["--until", "gs-init"]));
    let shards = dir.path().join("shards");
    std::fs::create_dir(&shards).unwrap();
    let (probe, report) = warp_shard(&scene, &shards, "0..0", &[]);
    let t = report["view_pairs"].as_u64().unwrap();
    assert!(t >= 2, "{t} view pairs");
    assert_eq!(report["edges"], 0);
    let (a, _) = warp_shard(&scene, &shards, "0..1", &[]);
    let (b, _) = warp_shard(&scene, &shards, &format!("1..{t}"), &[]);

    let missing = profuse_run(&scene, &["--until", "warp-graph", "--warp-partials", &b]);
    assert_eq!(missing.status.code(), Some(1));
    let err = String::from_utf8_lossy(&missing.stderr);
    assert!(
        err.contains("warp-graph") && err.contains("in no shard"),
        "{err}"
    );

    let (foreign, _) = warp_shard(
        &scene,
        &shards,
        "0..1",
        &["--set", "warp_graph.tau_iou=0.3"],
    );
    let refused = profuse_run(&scene, &["--warp-partials", &foreign, &b]);
    assert_eq!(refused.status.code(), Some(1));
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(err.contains("input_params"), "{err}");

    let tail = profuse_run(&scene, &["--warp-partials", &b, &probe, &a]);
    assert_succeeded(&tail);
    assert_same_files(&reference, &files(&scene.join("out")));
}

/// The Ray driver (python/profuse_ray) on a local 3-node Ray cluster: byte-identical to
/// `profuse run`, also with a worker process killed mid-run; a rerun skips finished
/// shards. Needs python3 with Ray; skipped with a message when it is missing, unless
/// PROFUSE_REQUIRE_PYTHON=1 (set by `.ci/run`, which installs Ray) makes that a failure.
#[test]
fn ray_driver_is_byte_identical_to_profuse_run() {
    if !super::python_has(
        "ray.cluster_utils",
        "PROFUSE_REQUIRE_PYTHON",
        "pip install ./python/profuse_ray",
    ) {
        return;
    }
    let out = Command::new("python3")
        .arg(root().join("python/profuse_ray/test_cluster.py"))
        .env("PROFUSE_BIN_DIR", super::bin_dir())
        .current_dir(root())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "ray driver test failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("byte-identical") && text.contains("killed"),
        "{text}"
    );
}

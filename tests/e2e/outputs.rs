//! End-to-end tests of the output rules of issue 20 (`profuse_formats::output`): outputs
//! replace only regular files, non-UTF-8 output paths are reported, multi-file outputs
//! appear whole, leftovers of killed runs are cleaned.

use std::ffi::OsStr;
use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};
use std::process::Output;

use super::{assert_succeeded, files, json, run_tool};

fn os(s: &str) -> &OsStr {
    s.as_ref()
}

fn synth(args: &[&OsStr]) -> Output {
    run_tool(env!("CARGO_BIN_EXE_synth"), args)
}

/// `synth --preset tiny` into `out` (with `extra` flags).
fn synth_args<'a>(out: &'a Path, seed: &'a str, extra: &[&'a str]) -> Vec<&'a OsStr> {
    let mut args = vec![
        os("--preset"),
        os("tiny"),
        os("--seed"),
        os(seed),
        os("--quiet"),
        os("--out"),
        out.as_os_str(),
    ];
    args.extend(extra.iter().map(|s| os(s)));
    args
}

fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

fn mkfifo(path: &Path) {
    let ok = std::process::Command::new("mkfifo")
        .arg(path)
        .status()
        .unwrap()
        .success();
    assert!(ok, "mkfifo failed");
}

/// A tiny scene with 3000 ground-truth Gaussians and no matches (fast).
fn scene(dir: &Path) -> PathBuf {
    let scene = dir.join("scene");
    assert_succeeded(&synth(&synth_args(
        &scene,
        "2",
        &["--gaussians", "3000", "--no-matches"],
    )));
    scene
}

/// Issue 20 item 5: `--out` naming a FIFO, a socket or a directory is refused before any
/// work, naming what is there, and the thing stays what it was. The old code renamed a
/// regular file over the FIFO (and, as root, over `/dev/null`).
#[test]
fn outputs_refuse_to_replace_anything_but_a_regular_file() {
    use std::os::unix::fs::FileTypeExt;
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path());
    let fifo = dir.path().join("fifo");
    mkfifo(&fifo);
    let sock = dir.path().join("sock");
    let _listener = std::os::unix::net::UnixListener::bind(&sock).unwrap();
    let features = scene.join("gt/gaussians.safetensors");
    for (target, found) in [
        (&fifo, "FIFO"),
        (&sock, "socket"),
        (&scene.join("gt"), "directory"),
    ] {
        let pq = run_tool(
            env!("CARGO_BIN_EXE_pq"),
            &[
                os("train"),
                os("--features"),
                features.as_os_str(),
                os("--out"),
                target.as_os_str(),
            ],
        );
        let topk = run_tool(
            env!("CARGO_BIN_EXE_splat-raster"),
            &[
                os("topk"),
                features.as_os_str(),
                os("--cameras"),
                scene.join("cameras.safetensors").as_os_str(),
                os("--out"),
                target.as_os_str(),
            ],
        );
        for out in [pq, topk] {
            assert_eq!(out.status.code(), Some(1));
            let err = String::from_utf8_lossy(&out.stderr);
            assert!(
                err.contains(&format!(
                    "is a {found}; an output may only replace a regular file"
                )),
                "{err}"
            );
        }
    }
    assert!(std::fs::metadata(&fifo).unwrap().file_type().is_fifo());
    assert!(std::fs::metadata(&sock).unwrap().file_type().is_socket());
    assert_eq!(names(dir.path()), ["fifo", "scene", "sock"]);
}

/// Issue 20 item 9: a non-UTF-8 output path works and is reported with U+FFFD in the
/// JSON; the old pq, fuse and splat-raster panicked (or failed) after writing.
#[test]
fn non_utf8_output_paths_are_written_and_reported_lossily() {
    let dir = tempfile::tempdir().unwrap();
    let scene = scene(dir.path());
    let bad = |name: &[u8]| dir.path().join(OsStr::from_bytes(name));
    let lossy = |p: &Path| p.to_string_lossy().into_owned();
    let gaussians = scene.join("gt/gaussians.safetensors");
    let cameras = scene.join("cameras.safetensors");

    let features = bad(b"features-\xff.safetensors");
    let fuse = run_tool(
        env!("CARGO_BIN_EXE_fuse"),
        &[
            os("run"),
            os("--gaussians"),
            gaussians.as_os_str(),
            os("--cameras"),
            cameras.as_os_str(),
            os("--masks"),
            scene.join("masks.safetensors").as_os_str(),
            os("--no-proposals"),
            os("--quiet"),
            os("--out"),
            features.as_os_str(),
        ],
    );
    assert_succeeded(&fuse);
    assert_eq!(json(&fuse)["out"], lossy(&features));
    assert!(lossy(&features).contains('\u{fffd}'));

    let pq_out = bad(b"pq-\xfe.safetensors");
    let pq = run_tool(
        env!("CARGO_BIN_EXE_pq"),
        &[
            os("train"),
            os("--features"),
            features.as_os_str(),
            os("--out"),
            pq_out.as_os_str(),
            os("--m"),
            os("16"),
            os("--iters"),
            os("2"),
            os("--quiet"),
        ],
    );
    assert_succeeded(&pq);
    assert_eq!(json(&pq)["out"], lossy(&pq_out));
    assert!(pq_out.is_file());

    let topk_out = bad(b"topk-\xff.safetensors");
    let render_dir = bad(b"render-\xff");
    let common = [os("--cameras"), cameras.as_os_str(), os("--quiet")];
    let mut topk = vec![os("topk"), gaussians.as_os_str(), os("--out")];
    topk.extend([topk_out.as_os_str()].iter().chain(&common));
    let topk = run_tool(env!("CARGO_BIN_EXE_splat-raster"), &topk);
    assert_succeeded(&topk);
    assert_eq!(json(&topk)["out"], lossy(&topk_out));
    let mut render = vec![os("render"), gaussians.as_os_str(), os("--out-dir")];
    render.extend([render_dir.as_os_str()].iter().chain(&common));
    let render = run_tool(env!("CARGO_BIN_EXE_splat-raster"), &render);
    assert_succeeded(&render);
    let color = json(&render)["files"]["color"]
        .as_str()
        .unwrap()
        .to_string();
    assert_eq!(color, lossy(&render_dir.join("view_000_color.png")));
}

/// Issue 20 item 11: synth failing midway (a full disk; here a file-size limit that the
/// masks file exceeds, after the images were written) leaves the earlier scene exactly as
/// it was and no temporary directory; the old code had already replaced the images.
#[test]
fn synth_failing_midway_leaves_the_earlier_scene_whole() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    assert_succeeded(&synth(&synth_args(&scene, "0", &[])));
    let before = files(&scene);
    let image_max = before
        .iter()
        .filter(|(p, _)| p.starts_with("images"))
        .map(|(_, b)| b.len() as u64)
        .max()
        .unwrap();
    let limit_kb = image_max * 3 / 1024 + 1;
    assert!(limit_kb * 1024 < before[Path::new("masks.safetensors")].len() as u64);
    let failed = super::run_tool_with_file_limit(
        limit_kb,
        env!("CARGO_BIN_EXE_synth"),
        &synth_args(&scene, "1", &[]),
    );
    assert!(!failed.status.success(), "the limit did not bite");
    assert!(
        String::from_utf8_lossy(&failed.stderr).contains("File too large"),
        "{}",
        String::from_utf8_lossy(&failed.stderr)
    );
    assert!(files(&scene) == before, "the earlier scene changed");
    assert_eq!(names(dir.path()), ["scene"]);

    // A directory that is not a synth scene is never replaced.
    let foreign = dir.path().join("mine");
    std::fs::create_dir(&foreign).unwrap();
    std::fs::write(foreign.join("notes.txt"), b"keep").unwrap();
    let out = synth(&synth_args(&foreign, "0", &[]));
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("not a synth scene"));
    assert_eq!(names(&foreign), ["notes.txt"]);
}

/// Issue 20 item 11: temporary files and directories that killed runs left next to an
/// output (unclaimed `.profuse-tmp-*`, at least two seconds old) are removed by the next
/// run of a tool writing there; one that a live process holds is kept. The old code
/// never removed them.
#[test]
fn leftovers_next_to_an_output_are_removed_by_the_next_run() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::create_dir_all(d.join(".profuse-tmp-scene-Ab12/images")).unwrap();
    std::fs::write(d.join(".profuse-tmp-scene-Ab12/images/x.png"), b"x").unwrap();
    std::fs::write(d.join(".profuse-tmp-Cd34"), b"half a file").unwrap();
    std::fs::write(d.join(".profuse-tmp-live"), b"being written").unwrap();
    let live = std::fs::File::open(d.join(".profuse-tmp-live")).unwrap();
    live.lock().unwrap();
    std::thread::sleep(std::time::Duration::from_millis(2100));
    let scene = d.join("scene");
    assert_succeeded(&synth(&synth_args(&scene, "0", &["--no-matches"])));
    assert_eq!(names(d), [".profuse-tmp-live", "scene"]);
    drop(live);
}

//! `scene-io` command lines of issue 20 (items 3, 10, 12 and the LLFF importer): each
//! failure exits 1 with the file named and writes nothing; `llff` writes a cameras file
//! `profuse inspect` accepts.
#![allow(clippy::unwrap_used)]

use std::ffi::OsStr;
use std::path::Path;
use std::process::{Command, Output};

use profuse_formats::{Cameras, FileKind};
use scene_io::npy::{write_npy, NpyArray, NpyData};

fn scene_io(args: &[&OsStr]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_scene-io"))
        .args(args)
        .output()
        .unwrap()
}

/// Runs a failing command: exit code 1 (not a crash), `needle` on stderr, stdout empty,
/// and `out` not written.
fn assert_fails(args: &[&OsStr], out: &Path, needle: &str) {
    let run = scene_io(args);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains(needle), "{stderr}");
    assert!(run.stdout.is_empty());
    assert!(!out.exists(), "{} was written", out.display());
}

/// Item 3: a 45 KB `.npy` header killed `scannet-npy` with a stack overflow (SIGABRT);
/// now it exits 1 naming the file.
#[test]
fn scannet_npy_with_a_45_kb_header_exits_1() {
    let dir = tempfile::tempdir().unwrap();
    let npy = dir.path().join("s_vert_all.npy");
    let dict = format!("{{'descr': '<f4', 'shape': {}", "(".repeat(45_000));
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    bytes.extend_from_slice(dict.as_bytes());
    std::fs::write(&npy, bytes).unwrap();
    let out = dir.path().join("mesh.safetensors");
    assert_fails(
        &[
            "scannet-npy".as_ref(),
            dir.path().as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
        ],
        &out,
        "s_vert_all.npy: malformed header: the header is 45026 bytes",
    );
}

/// Item 10: a FIFO as the PLY of `ply-import` blocked forever; now it exits 1 at once.
#[cfg(unix)]
#[test]
fn ply_import_of_a_fifo_exits_1() {
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("scene.ply");
    assert!(Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap()
        .success());
    let out = dir.path().join("g.safetensors");
    assert_fails(
        &[
            "ply-import".as_ref(),
            fifo.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
        ],
        &out,
        "scene.ply: unsupported file type: a FIFO (named pipe)",
    );
}

/// Item 12: a COLMAP model with no image wrote a 0-view cameras file with exit 0.
#[test]
fn colmap_without_images_exits_1() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("cameras.txt"),
        "1 PINHOLE 64 48 50 50 32 24\n",
    )
    .unwrap();
    std::fs::write(dir.path().join("images.txt"), "# none\n").unwrap();
    std::fs::write(dir.path().join("points3D.txt"), "").unwrap();
    let out = dir.path().join("cameras.safetensors");
    assert_fails(
        &[
            "colmap".as_ref(),
            dir.path().as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
        ],
        &out,
        "images.txt: images: the model has no registered image",
    );
}

/// The LLFF subcommand: a one-view scene with `images_4/`, imported at `--factor 4`.
#[test]
fn llff_writes_a_valid_cameras_file() {
    let dir = tempfile::tempdir().unwrap();
    let mut row = vec![
        0.0, 1.0, 0.0, 0.0, 400.0, //
        1.0, 0.0, 0.0, 0.0, 600.0, //
        0.0, 0.0, -1.0, 2.0, 500.0,
    ];
    row.extend_from_slice(&[1.0, 9.0]);
    let array = NpyArray::new(vec![1, 17], NpyData::F64(row)).unwrap();
    write_npy(dir.path().join("poses_bounds.npy"), &array).unwrap();
    std::fs::create_dir_all(dir.path().join("images_4")).unwrap();
    image::RgbImage::new(150, 100)
        .save(dir.path().join("images_4/IMG_0001.JPG.png"))
        .unwrap();
    let out = dir.path().join("cameras.safetensors");
    let run = scene_io(&[
        "llff".as_ref(),
        dir.path().as_os_str(),
        "--factor".as_ref(),
        "4".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert_eq!(
        run.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    assert_eq!(report["command"], "llff");
    assert_eq!(report["views"], 1);
    assert_eq!(report["images_dir"], "images_4");
    let cams = Cameras::read(&out).unwrap();
    assert_eq!(cams.image_names, ["images_4/IMG_0001.JPG.png"]);
    assert_eq!(cams.intrinsics[0], [125.0, 125.0, 75.0, 50.0]);
    assert_eq!(cams.image_size[0], [150, 100]);
    assert_eq!(
        cams.extra["generator"],
        format!("scene-io {} llff", env!("CARGO_PKG_VERSION"))
    );
}

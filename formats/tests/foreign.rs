//! Issue 20 item 12: a file of another format given to a ProFuse reader (`profuse
//! inspect scene.ply`) was reported as "header length ... exceeds the limit"; now the
//! first bytes name it (PLY, NumPy .npy, zip/.npz) and say which tool reads it.
#![allow(clippy::unwrap_used)]

use profuse_formats::{inspect, FileKind, Gaussians};

#[test]
fn a_ply_given_as_gaussians_is_named_and_points_to_ply_import() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("scene.ply");
    std::fs::write(
        &path,
        b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\nend_header\n",
    )
    .unwrap();
    let err = Gaussians::read(&path).unwrap_err();
    assert_eq!(err.code(), "header");
    assert_eq!(
        err.to_string(),
        format!(
            "{}: invalid safetensors header: not a safetensors file: it is a PLY file; convert an INRIA 3DGS PLY with `scene-io ply-import FILE --out gaussians.safetensors`",
            path.display()
        )
    );
    let report = inspect(&path);
    let shown = report.error.unwrap().to_string();
    assert!(shown.contains("it is a PLY file"), "{shown}");
}

#[test]
fn npy_and_npz_are_named_and_other_bytes_keep_the_length_error() {
    let dir = tempfile::tempdir().unwrap();
    for (name, bytes, expected) in [
        (
            "a.npy",
            &b"\x93NUMPY\x01\x00v\x00{'descr': '<f4'}"[..],
            "it is a NumPy .npy array",
        ),
        (
            "a.npz",
            &b"PK\x03\x04\x14\x00\x00\x00\x08\x00"[..],
            "it is a zip archive",
        ),
        (
            "a.bin",
            &[0xff_u8; 16][..],
            "exceeds the 100000000-byte limit",
        ),
    ] {
        let path = dir.path().join(name);
        std::fs::write(&path, bytes).unwrap();
        let msg = Gaussians::read(&path).unwrap_err().to_string();
        assert!(msg.contains(expected), "{name}: {msg}");
    }
}

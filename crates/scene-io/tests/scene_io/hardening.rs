//! Regression tests of issue 20 (hardening) for the importers: items 3 (`.npy` header
//! recursion), 4 (`.npz` zip bombs), 10 (FIFOs, devices, oversized text) and 12 (image
//! paths, empty results, incomplete COLMAP models). Each test names its item; each
//! failed on the code before the fix. Inputs are crafted here, small (sparse files stand
//! in for big ones).
use std::io::Write;
use std::path::Path;
use std::sync::mpsc;
use std::time::Duration;

use profuse_formats::Cameras;
use scene_io::colmap::{import_colmap, ColmapOptions};
use scene_io::keypoints::{import_keypoint_pairs, KeypointOptions};
use scene_io::npy::{
    parse_npy, read_npy, read_npz, read_npz_capped, NpyArray, NpyData, MAX_HEADER_LEN,
};
use scene_io::ply::read_inria_ply;
use scene_io::scannet::read_matrix4;
use scene_io::transforms::read_transforms;
use scene_io::{SceneError, MAX_JSON_BYTES, MAX_SMALL_TEXT_BYTES};

fn write(path: &Path, bytes: &[u8]) {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).unwrap();
    }
    std::fs::write(path, bytes).unwrap();
}

/// A version-1.0 `.npy` with this header dictionary text (padded to 64 bytes) and data.
fn npy_v1(dict: &str, data: &[u8]) -> Vec<u8> {
    let mut header = dict.as_bytes().to_vec();
    while !(10 + header.len() + 1).is_multiple_of(64) {
        header.push(b' ');
    }
    header.push(b'\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(&header);
    out.extend_from_slice(data);
    out
}

/// `(field, detail)` of an `Invalid` error, or a panic naming what came instead.
fn invalid_parts(e: &SceneError) -> (String, String) {
    match e {
        SceneError::Invalid { field, detail, .. } => (field.clone(), detail.clone()),
        other => panic!("expected SceneError::Invalid, got {other:?}"),
    }
}

/// Item 3: a 45 KB header of nested `(` was parsed recursively, one stack frame per
/// `(`, and overflowed the stack (the process died). Now headers longer than NumPy's
/// own 10,000-byte limit are refused before parsing, naming the file.
#[test]
fn npy_header_of_45_kb_is_a_header_error_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("scene0000_00_vert_all.npy");
    let dict = format!(
        "{{'descr': '<f4', 'fortran_order': False, 'shape': {}",
        "(".repeat(45_000)
    );
    write(&path, &npy_v1(&dict, &[]));
    let err = read_npy(&path).unwrap_err();
    assert_eq!(err.code(), "header");
    let msg = err.to_string();
    assert!(msg.starts_with(&path.display().to_string()), "{msg}");
    assert!(
        msg.contains(&format!("above the {MAX_HEADER_LEN}-byte limit")),
        "{msg}"
    );
    assert!(msg.contains("the header is 45110 bytes"), "{msg}");
}

/// Item 3: within the length limit, nesting is bounded too (16 levels): 4,000 `(` give a
/// header error, not 4,000 stack frames; a real header padded to almost the limit and
/// a 16-deep one still parse.
#[test]
fn npy_header_nesting_is_bounded_and_long_valid_headers_still_read() {
    let deep = format!(
        "{{'descr': '<f4', 'fortran_order': False, 'shape': {}",
        "(".repeat(4_000)
    );
    let err = parse_npy(&npy_v1(&deep, &[]), "deep.npy").unwrap_err();
    assert_eq!(err.code(), "header");
    assert!(
        err.to_string().contains("nested deeper than 16 levels"),
        "{err}"
    );

    let padded = format!(
        "{{'descr': '<u1', 'fortran_order': False, 'shape': (3,), }}{}",
        " ".repeat(MAX_HEADER_LEN - 200)
    );
    let a = parse_npy(&npy_v1(&padded, &[7, 8, 9]), "padded.npy").unwrap();
    assert_eq!(a.shape, vec![3]);
    assert_eq!(a.data, NpyData::U8(vec![7, 8, 9]));

    // 16 levels (the limit) parse; a 17th is refused.
    let nested = |n: usize| {
        format!(
            "{{'descr': '<u1', 'fortran_order': False, 'shape': (1,), 'x': {}{} }}",
            "[".repeat(n),
            "]".repeat(n)
        )
    };
    assert!(parse_npy(&npy_v1(&nested(15), &[5]), "n15.npy").is_ok());
    let err = parse_npy(&npy_v1(&nested(17), &[5]), "n17.npy").unwrap_err();
    assert!(err.to_string().contains("nested deeper"), "{err}");
}

/// The `.npz` with one deflated member `name` holding `payload`.
fn deflated_npz(name: &str, payload: &[u8]) -> Vec<u8> {
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated)
        .large_file(payload.len() > u32::MAX as usize);
    zip.start_file(name, opts).unwrap();
    zip.write_all(payload).unwrap();
    zip.finish().unwrap().into_inner()
}

/// Overwrites the declared uncompressed size (local header and central directory) of
/// the only member of a zip made by [`deflated_npz`] (a zip bomb lies there).
fn lie_about_size(zip: &mut [u8], size: u32) {
    let find = |sig: &[u8]| zip.windows(4).position(|w| w == sig).unwrap();
    let local = find(b"PK\x03\x04");
    let central = find(b"PK\x01\x02");
    zip[local + 22..local + 26].copy_from_slice(&size.to_le_bytes());
    zip[central + 24..central + 28].copy_from_slice(&size.to_le_bytes());
}

/// Item 4: a member whose `.npy` header announces 64 bytes of data but whose deflate
/// stream inflates to 64 MiB, with the zip's declared size forged to match the header.
/// Before, the whole member was inflated (memory = inflated size; a 1 MB file reached
/// 5.2 GB) and only then compared; now at most the header's size + 1 byte is inflated.
#[test]
fn npz_zip_bomb_is_refused_after_inflating_at_most_the_header_size() {
    let dir = tempfile::tempdir().unwrap();
    let header = npy_v1(
        "{'descr': '<f4', 'fortran_order': False, 'shape': (16,), }",
        &[],
    );
    let expected = header.len() + 64;
    let mut payload = header.clone();
    payload.resize(header.len() + (64 << 20), 0);
    let mut bomb = deflated_npz("kpts_i.npy", &payload);
    assert!(bomb.len() < 200_000, "{} bytes", bomb.len());
    lie_about_size(&mut bomb, expected as u32);
    let path = dir.path().join("a_b.npz");
    write(&path, &bomb);
    let err = read_npz(&path).unwrap_err();
    let (field, detail) = invalid_parts(&err);
    assert_eq!(field, "size");
    assert!(
        detail.contains(&format!("inflates to more than {expected} bytes")),
        "{detail}"
    );
    assert!(err.to_string().contains("a_b.npz[kpts_i.npy]"), "{err}");

    // Without the forgery, the declared size disagrees with the header: refused before
    // inflating anything past the header.
    let honest = deflated_npz("kpts_i.npy", &payload);
    write(&path, &honest);
    let (field, detail) = invalid_parts(&read_npz(&path).unwrap_err());
    assert_eq!(field, "zip uncompressed size");
    assert!(
        detail.contains(&format!(
            "declares {} bytes, but the .npy header (shape [16] of <f4) makes the member {expected} bytes",
            payload.len()
        )),
        "{detail}"
    );
}

/// Item 4: a header that announces more than the cap (2^28 bytes + header > 256 MiB)
/// with a matching forged declared size is refused before inflating; the cap is an
/// argument ([`read_npz_capped`]); an archive within the cap reads.
#[test]
fn npz_member_sizes_are_capped_before_inflating() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.npz");
    let header = npy_v1(
        "{'descr': '|u1', 'fortran_order': False, 'shape': (268435456,), }",
        &[],
    );
    let mut zip = deflated_npz("big.npy", &[header.as_slice(), &[0u8; 4096]].concat());
    lie_about_size(&mut zip, (header.len() + (1 << 28)) as u32);
    write(&path, &zip);
    let (field, detail) = invalid_parts(&read_npz(&path).unwrap_err());
    assert_eq!(field, "size");
    assert!(
        detail.contains("above the 268435456 bytes left of the archive's inflate cap"),
        "{detail}"
    );

    let small = NpyArray::new(vec![2, 2], NpyData::F32(vec![1.0, 2.0, 3.0, 4.0])).unwrap();
    let bytes = small.to_bytes();
    write(&path, &deflated_npz("k.npy", &bytes));
    assert_eq!(read_npz(&path).unwrap()["k"], small);
    let err = read_npz_capped(&path, bytes.len() as u64 - 1).unwrap_err();
    assert!(err.to_string().contains("inflate cap"), "{err}");
    assert_eq!(
        read_npz_capped(&path, bytes.len() as u64).unwrap()["k"],
        small
    );
}

/// Item 4, found by the long fuzz run: a file of end-of-central-directory signatures.
/// zip, left to detect where the archive starts, searched the file for a central
/// directory once per candidate end record: quadratic (16,000 records, 350 KB: 2 s;
/// these 200,000 records, 4.4 MB, would take minutes). numpy writes archives from byte 0,
/// and with that offset given each candidate costs constant time: an error in well under
/// a second here.
#[test]
fn npz_of_end_record_signatures_is_refused_in_linear_time() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("eocd.npz");
    // "PK\x05\x06", disk 0, 1 entry, central directory of 46 bytes at offset 0, no comment.
    let mut record = b"PK\x05\x06".to_vec();
    for v in [0u16, 0, 1, 1] {
        record.extend_from_slice(&v.to_le_bytes());
    }
    record.extend_from_slice(&46u32.to_le_bytes());
    record.extend_from_slice(&0u32.to_le_bytes());
    record.extend_from_slice(&0u16.to_le_bytes());
    write(&path, &record.repeat(200_000));
    let err = within(60, move || read_npz(&path).map(|_| ()))
        .expect("read_npz did not return within 60 s")
        .unwrap_err();
    assert!(err.to_string().contains("eocd.npz"), "{err}");
}

/// Runs `f` on another thread; `None` when it has not returned within `secs` (the old
/// readers blocked forever on a FIFO).
fn within<T: Send + 'static>(secs: u64, f: impl FnOnce() -> T + Send + 'static) -> Option<T> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(Duration::from_secs(secs)).ok()
}

/// Item 10: a FIFO given as a PLY, a `.npy`, a transforms.json or an `.npz` blocked
/// forever in `open`; now it is refused at once as not a regular file.
#[cfg(unix)]
#[test]
fn fifo_inputs_are_refused_without_blocking() {
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("scene.ply");
    let status = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap();
    assert!(status.success());
    let p = fifo.clone();
    let results = within(10, move || {
        [
            read_inria_ply(&p).map(|_| ()).unwrap_err().to_string(),
            read_npy(&p).map(|_| ()).unwrap_err().to_string(),
            read_transforms(&p).map(|_| ()).unwrap_err().to_string(),
            read_npz(&p).map(|_| ()).unwrap_err().to_string(),
        ]
    });
    let Some(results) = results else {
        // Unblock the reader so the thread ends, then fail.
        let _ = std::fs::OpenOptions::new().write(true).open(&fifo);
        panic!("reading a FIFO blocked for 10 s");
    };
    for msg in results {
        assert_eq!(
            msg,
            format!(
                "{}: unsupported file type: a FIFO (named pipe); only regular files are read (copy the data into a file first)",
                fifo.display()
            )
        );
    }
}

/// Item 10: a character device (`/dev/zero` was read until memory ran out; `/dev/null`
/// stands in here, as it ends) is refused as not a regular file, and so is a directory.
#[cfg(unix)]
#[test]
fn devices_and_directories_are_refused_as_inputs() {
    for reader in [
        |p: &Path| read_inria_ply(p).map(|_| ()),
        |p: &Path| read_transforms(p).map(|_| ()),
        |p: &Path| read_npy(p).map(|_| ()),
    ] {
        let err = reader(Path::new("/dev/null")).unwrap_err();
        assert_eq!(err.code(), "unsupported");
        assert!(
            err.to_string()
                .starts_with("/dev/null: unsupported file type: a character device"),
            "{err}"
        );
    }
    let dir = tempfile::tempdir().unwrap();
    let err = read_inria_ply(dir.path()).unwrap_err();
    assert!(err.to_string().contains("a directory"), "{err}");
}

/// Item 10: text readers cap what they read: a transforms.json over 64 MiB (a sparse
/// file: no disk used) and a ScanNet pose over 1 MiB are refused from their size before
/// any byte is read; before, both were read whole.
#[test]
fn oversized_text_inputs_are_refused_by_size() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("transforms.json");
    std::fs::File::create(&json)
        .unwrap()
        .set_len(MAX_JSON_BYTES + 1)
        .unwrap();
    let (field, detail) = invalid_parts(&read_transforms(&json).unwrap_err());
    assert_eq!(field, "file size");
    assert_eq!(
        detail,
        format!(
            "{} bytes, above the {MAX_JSON_BYTES}-byte cap of this reader",
            MAX_JSON_BYTES + 1
        )
    );
    let pose = dir.path().join("0.txt");
    std::fs::File::create(&pose)
        .unwrap()
        .set_len(MAX_SMALL_TEXT_BYTES + 1)
        .unwrap();
    let (field, _) = invalid_parts(&read_matrix4(&pose).unwrap_err());
    assert_eq!(field, "file size");
}

/// Writes a one-camera COLMAP text model whose images have these names.
fn colmap_text_model(dir: &Path, names: &[&str]) {
    write(
        &dir.join("cameras.txt"),
        b"1 PINHOLE 64 48 50.0 50.0 32.0 24.0\n",
    );
    let mut images = String::new();
    for (i, name) in names.iter().enumerate() {
        images.push_str(&format!("{} 1 0 0 0 0 0 {} 1 {name}\n\n", i + 1, i + 1));
    }
    write(&dir.join("images.txt"), images.as_bytes());
    write(&dir.join("points3D.txt"), b"1 0 0 5 255 0 0 0.5 1 0\n");
}

/// Item 10: the COLMAP text cap is an option ([`ColmapOptions::max_text_bytes`], the
/// tool's `--max-text-mb`), and its error says how to raise it.
#[test]
fn colmap_text_cap_is_an_option() {
    let dir = tempfile::tempdir().unwrap();
    colmap_text_model(dir.path(), &["a.png"]);
    let options = ColmapOptions {
        max_text_bytes: 20,
        ..Default::default()
    };
    let (field, detail) = invalid_parts(&import_colmap(dir.path(), &options).unwrap_err());
    assert_eq!(field, "file size");
    assert!(
        detail.ends_with("above the 20-byte cap of this reader (raise it with --max-text-mb)"),
        "{detail}"
    );
    let import = import_colmap(dir.path(), &ColmapOptions::default()).unwrap();
    assert_eq!(import.cameras.image_names, vec!["images/a.png".to_string()]);
}

/// Item 12: a transforms.json `file_path` of `../../x.png` was accepted (only absolute
/// paths were refused) when the file existed; now any `..` component is an error.
#[test]
fn transforms_refuses_image_paths_leaving_the_scene_folder() {
    let root = tempfile::tempdir().unwrap();
    let scene = root.path().join("a").join("b");
    write(&root.path().join("x.png"), b"not read");
    let json = scene.join("transforms.json");
    for (file, why) in [
        ("../../x.png", "has a `..` component"),
        ("images/../../../x.png", "has a `..` component"),
        ("/etc/passwd", "is absolute"),
    ] {
        let text = format!(
            r#"{{"fl_x": 50, "w": 64, "h": 48, "frames": [{{"file_path": "{file}",
            "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}}]}}"#
        );
        write(&json, text.as_bytes());
        let (field, detail) = invalid_parts(&read_transforms(&json).unwrap_err());
        assert_eq!(field, "frames[0].file_path");
        assert_eq!(
            detail,
            format!("image path {file:?} {why} (image paths {})", {
                if why == "is absolute" {
                    "are relative to the scene folder"
                } else {
                    "must stay inside the scene folder"
                }
            })
        );
    }
}

/// Item 12: COLMAP image names with `..` or an absolute path were copied into the
/// cameras file; now they are errors naming the image record.
#[test]
fn colmap_refuses_image_names_leaving_the_scene_folder() {
    for name in ["../x.png", "/abs/x.png", "a/../../x.png"] {
        let dir = tempfile::tempdir().unwrap();
        colmap_text_model(dir.path(), &["ok.png", name]);
        let err = import_colmap(dir.path(), &ColmapOptions::default()).unwrap_err();
        let (field, detail) = invalid_parts(&err);
        assert_eq!(field, format!("image 2 ({name}) NAME"));
        assert!(
            detail.starts_with(&format!("image path {name:?} ")),
            "{detail}"
        );
        assert!(err.to_string().contains("images.txt"), "{err}");
    }
    // The prefix option is held to the same rule.
    let dir = tempfile::tempdir().unwrap();
    colmap_text_model(dir.path(), &["ok.png"]);
    let options = ColmapOptions {
        images_prefix: "/data/images".to_string(),
        ..Default::default()
    };
    let (field, _) = invalid_parts(&import_colmap(dir.path(), &options).unwrap_err());
    assert_eq!(field, "image 1 (ok.png) NAME with --images-prefix");
}

/// Item 12: a COLMAP model with no registered image gave a 0-view cameras file and
/// exit 0; now it is an error.
#[test]
fn colmap_model_without_images_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    colmap_text_model(dir.path(), &[]);
    let err = import_colmap(dir.path(), &ColmapOptions::default()).unwrap_err();
    let (field, detail) = invalid_parts(&err);
    assert_eq!(field, "images");
    assert_eq!(
        detail,
        "the model has no registered image, so there are no views to import"
    );
}

/// Issue 20 "COLMAP models without images.bin": the error named all six files; now it
/// names the missing one, the ones found, and why the missing one is needed.
#[test]
fn colmap_model_missing_images_names_the_missing_file() {
    let dir = tempfile::tempdir().unwrap();
    write(&dir.path().join("cameras.bin"), &0u64.to_le_bytes());
    write(&dir.path().join("points3D.bin"), &0u64.to_le_bytes());
    let err = import_colmap(dir.path(), &ColmapOptions::default()).unwrap_err();
    assert_eq!(err.code(), "missing");
    assert_eq!(
        err.to_string(),
        format!(
            "{}: missing images.bin (expected the binary model files cameras, images and points3D; found only cameras.bin, points3D.bin (images holds every registered image and its pose: without it there are no views to import))",
            dir.path().display()
        )
    );
    // Text: cameras.txt alone names both missing files.
    let dir = tempfile::tempdir().unwrap();
    write(&dir.path().join("cameras.txt"), b"");
    let err = import_colmap(dir.path(), &ColmapOptions::default()).unwrap_err();
    assert!(
        err.to_string()
            .contains("missing images.txt, points3D.txt (expected the text model files"),
        "{err}"
    );
}

/// Item 12: `keypoints` with every `.npz` skipped (names that match no view) wrote an
/// empty sparse_matches file with exit 0; now it is an error naming the skip reason.
#[test]
fn keypoints_with_every_file_skipped_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let cameras = Cameras {
        image_names: vec!["images/a.png".into(), "images/b.png".into()],
        image_size: vec![[64, 48]; 2].into(),
        intrinsics: vec![[50.0, 50.0, 32.0, 24.0]; 2].into(),
        world_to_camera: vec![[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]; 2]
            .into(),
        ..Default::default()
    };
    let file = dir.path().join("c_d.npz");
    let pts = NpyArray::new(vec![1, 2], NpyData::F32(vec![1.0, 2.0])).unwrap();
    let mut zip = zip::ZipWriter::new(std::fs::File::create(&file).unwrap());
    for key in ["kpts_i", "kpts_j"] {
        zip.start_file(
            format!("{key}.npy"),
            zip::write::SimpleFileOptions::default(),
        )
        .unwrap();
        zip.write_all(&pts.to_bytes()).unwrap();
    }
    zip.finish().unwrap();
    let opts = KeypointOptions::default();
    let err = import_keypoint_pairs(
        std::slice::from_ref(&file),
        &cameras,
        "cams.safetensors",
        &opts,
    )
    .unwrap_err();
    let (field, detail) = invalid_parts(&err);
    assert_eq!(field, "keypoint pair files");
    assert!(
        detail.starts_with("none names two views of these cameras, so there are no matches to write: all 1 files were skipped (first: "),
        "{detail}"
    );
    let err = import_keypoint_pairs(&[], &cameras, "cams.safetensors", &opts).unwrap_err();
    assert!(err.to_string().ends_with("no pair file was given"), "{err}");
}

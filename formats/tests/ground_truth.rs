//! The ground-truth readers (SPEC.md §6.1) against their committed golden vectors, and the
//! Python reader against the same vectors.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};
use std::process::Command;

use profuse_formats::ground_truth::{gt_expected_json, gt_vectors, read_gt_vector};

fn vectors_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("vectors")
}

#[test]
fn committed_gt_vectors_equal_what_the_code_writes() {
    let vectors = gt_vectors();
    for v in &vectors {
        let path = vectors_dir().join(&v.name);
        let committed = std::fs::read_to_string(&path).unwrap_or_else(|e| {
            panic!(
                "{}: {e} (run `cargo run -p profuse-formats --example write_vectors`)",
                path.display()
            )
        });
        assert_eq!(
            committed, v.text,
            "{} differs; regenerate the vectors",
            v.name
        );
    }
    let expected: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(vectors_dir().join("gt/expected.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(expected, gt_expected_json(&vectors));
}

#[test]
fn every_committed_gt_vector_gets_its_verdict() {
    let expected: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(vectors_dir().join("gt/expected.json")).unwrap(),
    )
    .unwrap();
    let entries = expected.as_object().unwrap();
    assert!(entries.len() >= 6);
    for (name, want) in entries {
        let got = read_gt_vector(&vectors_dir().join(name));
        match got {
            Ok(()) => assert_eq!(want["valid"], true, "{name} read as valid"),
            Err(e) => {
                assert_eq!(want["valid"], false, "{name}: {e}");
                assert_eq!(want["code"], e.code(), "{name}: {e}");
                assert_eq!(want["field"].as_str(), e.field(), "{name}: {e}");
            }
        }
    }
}

/// The Python reader's ground-truth tests (formats/python/test_ground_truth.py), skipped
/// without python3 + numpy + safetensors unless PROFUSE_REQUIRE_PYTHON=1.
#[test]
fn python_gt_reader_agrees_on_every_vector() {
    let available = Command::new("python3")
        .args(["-c", "import numpy, safetensors"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if !available {
        assert!(
            std::env::var("PROFUSE_REQUIRE_PYTHON").as_deref() != Ok("1"),
            "python3 with numpy and safetensors is required"
        );
        eprintln!("SKIPPED: python3 with numpy + safetensors not found");
        return;
    }
    let out = Command::new("python3")
        .arg("python/test_ground_truth.py")
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "python tests failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

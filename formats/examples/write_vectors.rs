//! Writes the golden vectors of SPEC.md into `formats/vectors/` (run from anywhere:
//! `cargo run -p profuse-formats --example write_vectors`).

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("vectors");
    for sub in ["valid", "invalid"] {
        let dir = root.join(sub);
        if dir.exists() {
            std::fs::remove_dir_all(&dir)?;
        }
        std::fs::create_dir_all(&dir)?;
    }
    let vectors = profuse_formats::samples::vectors();
    for v in &vectors {
        std::fs::write(root.join(&v.name), &v.bytes)?;
    }
    let expected = profuse_formats::samples::expected_json(&vectors);
    std::fs::write(
        root.join("expected.json"),
        serde_json::to_string_pretty(&expected)? + "\n",
    )?;
    eprintln!("wrote {} vectors to {}", vectors.len(), root.display());
    write_gt_vectors(&root)
}

/// The ground-truth JSON files (SPEC.md §6.1) under `vectors/gt/`, with their own
/// `expected.json`.
fn write_gt_vectors(root: &std::path::Path) -> Result<(), Box<dyn std::error::Error>> {
    let gt = root.join("gt");
    if gt.exists() {
        std::fs::remove_dir_all(&gt)?;
    }
    let vectors = profuse_formats::ground_truth::gt_vectors();
    for v in &vectors {
        let path = root.join(&v.name);
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        std::fs::write(path, &v.text)?;
    }
    let expected = profuse_formats::ground_truth::gt_expected_json(&vectors);
    std::fs::write(
        gt.join("expected.json"),
        serde_json::to_string_pretty(&expected)? + "\n",
    )?;
    eprintln!(
        "wrote {} ground-truth vectors to {}",
        vectors.len(),
        gt.display()
    );
    Ok(())
}

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
    Ok(())
}

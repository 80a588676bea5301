//! `profuse inspect FILE...` without the rest of the pipeline: prints each file's SPEC.md §5
//! report (the same pretty JSON as `profuse inspect`), one after another, and exits 1 when
//! any file is invalid. Used to measure the readers' peak memory (formats/README.md) and
//! as a light Rust reference for the Python tests (`PROFUSE_RUST_INSPECT`, one file).
//!
//! `cargo run -p profuse-formats --example inspect -- FILE...`

use std::io::Write;
use std::process::ExitCode;

fn main() -> ExitCode {
    let mut code = ExitCode::SUCCESS;
    let mut out = std::io::stdout().lock();
    let files: Vec<String> = std::env::args().skip(1).collect();
    if files.is_empty() || files.iter().any(|f| f == "--help") {
        eprintln!("usage: inspect FILE... (the `profuse inspect` report of each file)");
        return ExitCode::from(2);
    }
    // Accept `inspect FILE` as `profuse inspect FILE` is called.
    for file in files.iter().filter(|f| f.as_str() != "inspect") {
        let report = profuse_formats::inspect(file);
        let text = serde_json::to_string_pretty(&report.json).unwrap_or_else(|_| "{}".into());
        if writeln!(out, "{text}").is_err() {
            return ExitCode::FAILURE;
        }
        if let Some(e) = report.error {
            eprintln!("error: {e}");
            code = ExitCode::FAILURE;
        }
    }
    code
}

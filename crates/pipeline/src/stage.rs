//! Up-to-date checks and crash-safe completion records for pipeline stages.
//!
//! A stage is *done* when its completion record `out/.stamps/<stage>.json` exists, was
//! written after every input file was last modified, records the same parameters as the
//! current run, and every output it lists still exists. The record is written last, after
//! every output has been renamed into place, so a stage killed midway leaves either no
//! record or a record older than its new inputs: a later run redoes it instead of trusting
//! a partial result. Single-file outputs are already atomic (temp file + rename); stages
//! with many files write them into a temporary directory renamed at the end.

use std::path::{Path, PathBuf};
use std::time::SystemTime;

use serde::{Deserialize, Serialize};

/// What a completion record holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stamp {
    /// The stage's name.
    pub stage: String,
    /// The stage's effective parameters (any JSON value), compared on the next run.
    pub params: serde_json::Value,
    /// Input files, as given.
    pub inputs: Vec<PathBuf>,
    /// Output files or directories, as given.
    pub outputs: Vec<PathBuf>,
    /// Seconds the stage took when it ran.
    pub seconds: f64,
}

/// The completion-record path of `stage` under the output directory.
pub fn stamp_path(out_dir: &Path, stage: &str) -> PathBuf {
    out_dir.join(".stamps").join(format!("{stage}.json"))
}

fn modified(path: &Path) -> Option<SystemTime> {
    std::fs::metadata(path).and_then(|m| m.modified()).ok()
}

/// Why a stage must run, or `None` when its record proves it up to date.
pub fn needs_run(
    out_dir: &Path,
    stage: &str,
    params: &serde_json::Value,
    inputs: &[PathBuf],
    outputs: &[PathBuf],
) -> Option<String> {
    let path = stamp_path(out_dir, stage);
    let Some(written) = modified(&path) else {
        return Some("no completion record".into());
    };
    let Some(stamp) = std::fs::read(&path)
        .ok()
        .and_then(|b| serde_json::from_slice::<Stamp>(&b).ok())
    else {
        return Some("unreadable completion record".into());
    };
    if &stamp.params != params {
        return Some("parameters changed".into());
    }
    if stamp.outputs != outputs || outputs.iter().any(|o| !o.exists()) {
        return Some("an output is missing".into());
    }
    for input in inputs {
        match modified(input) {
            Some(t) if t <= written => {}
            Some(_) => return Some(format!("{} is newer than the last run", input.display())),
            None => return Some(format!("{} is missing", input.display())),
        }
    }
    None
}

/// Writes the completion record of a stage (atomically: temp file + rename).
pub fn write_stamp(out_dir: &Path, stamp: &Stamp) -> std::io::Result<()> {
    let path = stamp_path(out_dir, &stamp.stage);
    let dir = path.parent().unwrap_or(out_dir);
    std::fs::create_dir_all(dir)?;
    let tmp = dir.join(format!(".{}.tmp", stamp.stage));
    let text = serde_json::to_vec_pretty(stamp).map_err(std::io::Error::other)?;
    std::fs::write(&tmp, text)?;
    std::fs::rename(&tmp, &path)
}

/// Removes a stage's completion record (before re-running it, so that a crash during the
/// run cannot leave the old record next to half-replaced outputs).
pub fn clear_stamp(out_dir: &Path, stage: &str) -> std::io::Result<()> {
    match std::fs::remove_file(stamp_path(out_dir, stage)) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
        _ => Ok(()),
    }
}

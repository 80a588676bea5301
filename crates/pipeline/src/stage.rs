//! Up-to-date checks and crash-safe completion records for pipeline stages.
//!
//! A stage is *done* when its completion record `out/.stamps/<stage>.json` exists, is of
//! this version ([`STAMP_VERSION`]), records the same parameters and the same code
//! identity ([`code_identity`]) as the current run, and every input and output it lists
//! still has the [`Fingerprint`] recorded: size, inode, modification and status-change
//! times of each file (of every file beneath, for a directory). Any difference makes the
//! stage stale, whatever its direction, so an input replaced by a file with an *older*
//! modification time (`cp -p`, `rsync -t`, `tar x`) is noticed (through its inode or
//! status-change time, which no copy preserves). The record is written last, after every
//! output has been renamed into place, so a stage killed midway leaves no record: a later
//! run redoes it instead of trusting a partial result. Single-file outputs are already
//! atomic (temp file + rename); stages with many files write them into a temporary
//! directory swapped in at the end.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::fnv::Fnv;

/// Version of the completion-record format; a record of another version (or without one:
/// the mtime-only records before issue 20; version 2 had no code identity) makes its stage
/// run again.
pub const STAMP_VERSION: u32 = 3;

mod generated {
    include!(concat!(env!("OUT_DIR"), "/code_identity.rs"));
}

/// The code identity of a workspace crate the pipeline runs (see `build.rs`: the hash of
/// the crate's manifest and sources, of those of the workspace crates it depends on, and
/// of the workspace's `Cargo.lock`); `None` for a crate it does not run.
pub fn crate_code(krate: &str) -> Option<&'static str> {
    generated::CRATE_CODE
        .iter()
        .find(|(name, _)| *name == krate)
        .map(|(_, id)| *id)
}

/// The identity of the code a stage runs, as `CRATE@HEX+profuse-pipeline@HEX`: its crate's
/// [`crate_code`] and the pipeline's own sources (which call it). A crate the pipeline does
/// not run gets the identity of the whole pipeline (every crate it runs), which no edit
/// escapes.
pub fn code_identity(krate: &str) -> String {
    let (name, id) = match crate_code(krate) {
        Some(id) => (krate, id),
        None => (
            "profuse-pipeline",
            crate_code("profuse-pipeline").unwrap_or("unknown"),
        ),
    };
    format!("{name}@{id}+profuse-pipeline@{}", generated::GLUE_CODE)
}

/// What a completion record holds (README "Up-to-date rules" documents the JSON).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stamp {
    /// [`STAMP_VERSION`].
    #[serde(default)]
    pub version: u32,
    /// The stage's name.
    pub stage: String,
    /// The stage's effective parameters (any JSON value), compared on the next run.
    pub params: serde_json::Value,
    /// The identity of the code that ran ([`code_identity`]), compared on the next run.
    #[serde(default)]
    pub code: String,
    /// Input files and directories, as they were when the stage started.
    pub inputs: Vec<Fingerprint>,
    /// Output files and directories, as the stage left them.
    pub outputs: Vec<Fingerprint>,
    /// Seconds the stage took when it ran.
    pub seconds: f64,
}

/// The identity of a file or directory as the up-to-date check compares it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Fingerprint {
    /// The path as given (non-UTF-8 bytes as U+FFFD).
    pub path: String,
    /// `file` or `dir`.
    pub kind: String,
    /// A file's length in bytes; a directory's total over the files beneath it.
    pub size: u64,
    /// A file's inode number; a directory's count of files beneath it.
    pub inode: u64,
    /// A file's modification time (ns since the epoch); 0 for a directory.
    pub mtime_ns: i128,
    /// A file's status-change time (ctime, ns since the epoch; 0 where the platform has
    /// none); 0 for a directory.
    pub ctime_ns: i128,
    /// A directory's FNV-1a 64 (hex) over `relative path NUL size inode mtime_ns
    /// ctime_ns NUL` of each file beneath it in byte order of the paths; empty for a file.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub digest: String,
}

/// (size, inode, mtime ns, ctime ns) of a file's metadata.
fn identity(meta: &std::fs::Metadata) -> (u64, u64, i128, i128) {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        let ns = |s: i64, n: i64| i128::from(s) * 1_000_000_000 + i128::from(n);
        (
            meta.len(),
            meta.ino(),
            ns(meta.mtime(), meta.mtime_nsec()),
            ns(meta.ctime(), meta.ctime_nsec()),
        )
    }
    #[cfg(not(unix))]
    {
        let mtime = meta
            .modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_nanos() as i128);
        (meta.len(), 0, mtime, 0)
    }
}

/// The fingerprint of a file or directory; an error when it does not exist.
pub fn fingerprint(path: &Path) -> std::io::Result<Fingerprint> {
    let meta = std::fs::metadata(path)?;
    let shown = path.to_string_lossy().into_owned();
    if !meta.is_dir() {
        let (size, inode, mtime_ns, ctime_ns) = identity(&meta);
        return Ok(Fingerprint {
            path: shown,
            kind: "file".into(),
            size,
            inode,
            mtime_ns,
            ctime_ns,
            digest: String::new(),
        });
    }
    let files = crate::fnv::files_beneath(path)?;
    let mut hash = Fnv::new();
    let mut total = 0u64;
    for (rel, full) in &files {
        let (size, inode, mtime, ctime) = identity(&std::fs::metadata(full)?);
        total += size;
        hash = hash
            .bytes(rel.as_os_str().as_encoded_bytes())
            .bytes(format!("\0{size} {inode} {mtime} {ctime}\0").as_bytes());
    }
    Ok(Fingerprint {
        path: shown,
        kind: "dir".into(),
        size: total,
        inode: files.len() as u64,
        mtime_ns: 0,
        ctime_ns: 0,
        digest: format!("{:016x}", hash.0),
    })
}

/// The fingerprints of `paths`, in order.
pub fn fingerprints(paths: &[PathBuf]) -> Result<Vec<Fingerprint>, (PathBuf, std::io::Error)> {
    paths
        .iter()
        .map(|p| fingerprint(p).map_err(|e| (p.clone(), e)))
        .collect()
}

/// The completion-record path of `stage` under the output directory.
pub fn stamp_path(out_dir: &Path, stage: &str) -> PathBuf {
    out_dir.join(".stamps").join(format!("{stage}.json"))
}

/// The first of `paths` whose fingerprint differs from `recorded` (`None`: all agree), and
/// why.
fn first_change(recorded: &[Fingerprint], paths: &[PathBuf], role: &str) -> Option<String> {
    let shown: Vec<String> = paths
        .iter()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    let listed: Vec<&String> = recorded.iter().map(|f| &f.path).collect();
    if listed != shown.iter().collect::<Vec<_>>() {
        return Some(format!("its {role}s changed"));
    }
    for (path, old) in paths.iter().zip(recorded) {
        match fingerprint(path) {
            Err(_) => return Some(format!("{} is missing", path.display())),
            Ok(now) if &now != old => {
                return Some(format!("{} changed since the last run", path.display()))
            }
            Ok(_) => {}
        }
    }
    None
}

/// Why a stage must run, or `None` when its record proves it up to date.
pub fn needs_run(
    out_dir: &Path,
    stage: &str,
    code: &str,
    params: &serde_json::Value,
    inputs: &[PathBuf],
    outputs: &[PathBuf],
) -> Option<String> {
    let Ok(bytes) = std::fs::read(stamp_path(out_dir, stage)) else {
        return Some("no completion record".into());
    };
    let Ok(stamp) = serde_json::from_slice::<Stamp>(&bytes) else {
        return Some("unreadable completion record (or one of an older version)".into());
    };
    if stamp.version != STAMP_VERSION {
        return Some("completion record of an older version".into());
    }
    if &stamp.params != params {
        return Some("parameters changed".into());
    }
    if stamp.code != code {
        return Some("its code changed (another build)".into());
    }
    if let Some(why) = first_change(&stamp.outputs, outputs, "output") {
        return Some(if why.ends_with("is missing") {
            "an output is missing".into()
        } else {
            why
        });
    }
    first_change(&stamp.inputs, inputs, "input")
}

/// Writes the completion record of a stage (atomically: a `.profuse-tmp-*` file renamed
/// into place).
pub fn write_stamp(out_dir: &Path, stamp: &Stamp) -> std::io::Result<()> {
    let path = stamp_path(out_dir, &stamp.stage);
    let dir = path.parent().unwrap_or(out_dir);
    std::fs::create_dir_all(dir)?;
    let text = serde_json::to_vec_pretty(stamp).map_err(std::io::Error::other)?;
    profuse_formats::write_atomically(&path, |mut f| std::io::Write::write_all(&mut f, &text))
        .map_err(|(_, e)| e)
}

/// Removes a stage's completion record (before re-running it, so that a crash during the
/// run cannot leave the old record next to half-replaced outputs).
pub fn clear_stamp(out_dir: &Path, stage: &str) -> std::io::Result<()> {
    match std::fs::remove_file(stamp_path(out_dir, stage)) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
        _ => Ok(()),
    }
}

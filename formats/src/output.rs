//! The rules every ProFuse output follows (issue 20), in one place so that each tool and
//! stage applies the same ones:
//!
//! * **Only regular files are replaced.** [`check_output_file`]: an output path may name a
//!   regular file (replaced) or nothing (created); a device node, FIFO, socket or
//!   directory is an [`OutputError::NotAFile`] before any work is done
//!   ([`crate::write_atomically`] checks again right before writing).
//! * **Names from data stay inside the output directory.** [`safe_component`]: a name
//!   taken from a file (an image stem, a prompt) must be one plain path component.
//! * **Temporary names are unique and claimed.** Every temporary file or directory is
//!   named `.profuse-tmp-*` ([`TEMP_PREFIX`]) with a random part, and holds an advisory
//!   lock (`flock`) while its writer lives. [`clean_leftovers`] removes the ones no live
//!   process holds (what a killed run leaves behind).
//! * **Multi-file outputs appear whole.** [`StagedDir`] builds a directory next to its
//!   target and swaps it into place: the target is replaced as a whole.
//! * **One writer per output directory.** [`lock_dir`]: an exclusive advisory lock on the
//!   directory itself (no lock file is created).
//! * **Paths in reports never fail.** [`lossy_path`]: serde helpers that write a path as
//!   UTF-8 with invalid bytes replaced by U+FFFD.

use std::fs::{self, File, TryLockError};
use std::io;
use std::path::{Component, Path, PathBuf};
use std::time::Duration;

/// Prefix of every temporary file and directory ProFuse creates.
pub const TEMP_PREFIX: &str = ".profuse-tmp-";

/// How old an unlocked `.profuse-tmp-*` entry must be before [`clean_leftovers`] removes
/// it when the caller does not hold the directory's lock: a writer locks its temporary
/// file right after creating it, and this covers that instant.
pub const LEFTOVER_MIN_AGE: Duration = Duration::from_secs(2);

/// Why an output cannot be written where asked.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum OutputError {
    /// The output path names something other than a regular file.
    #[error("{path}: is a {found}; an output may only replace a regular file (or not exist)")]
    NotAFile {
        /// The path.
        path: String,
        /// What is there (`character device`, `FIFO`, `directory`, ...).
        found: &'static str,
    },
    /// An output directory path names something other than a directory.
    #[error("{path}: is a {found}; an output directory must be a directory (or not exist)")]
    NotADirectory {
        /// The path.
        path: String,
        /// What is there.
        found: &'static str,
    },
    /// An existing, non-empty directory that is not an earlier output of the same kind
    /// (replacing it would delete unrelated files).
    #[error("{path}: exists and is not {expected}; refusing to replace it (remove it or choose another output directory)")]
    Foreign {
        /// The directory.
        path: String,
        /// What it would have to be.
        expected: &'static str,
    },
    /// A name taken from data is not one plain path component.
    #[error("{context}: {what} {name:?} is not a plain file name (one path component: not empty, not `.` or `..`, no `/` or `\\`); an output path cannot be built from it")]
    UnsafeName {
        /// Where the name comes from (a file).
        context: String,
        /// What the name is (`image stem`, `prompt`).
        what: &'static str,
        /// The name.
        name: String,
    },
    /// Another process holds the output directory's lock.
    #[error("{path}: another process is writing this output directory (it holds its lock); wait for it to finish, or let this run wait for the lock (`profuse run --wait`)")]
    Locked {
        /// The directory.
        path: String,
    },
    /// A file-system call failed.
    #[error("{path}: {action}: {source}")]
    Io {
        /// The path.
        path: String,
        /// What was attempted.
        action: &'static str,
        /// The cause.
        #[source]
        source: io::Error,
    },
}

fn show(path: &Path) -> String {
    path.display().to_string()
}

fn io_err<'a>(path: &'a Path, action: &'static str) -> impl FnOnce(io::Error) -> OutputError + 'a {
    move |source| OutputError::Io {
        path: show(path),
        action,
        source,
    }
}

/// What a file type is, in words.
fn kind_name(t: fs::FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_char_device() {
            return "character device";
        }
        if t.is_block_device() {
            return "block device";
        }
        if t.is_fifo() {
            return "FIFO";
        }
        if t.is_socket() {
            return "socket";
        }
    }
    if t.is_dir() {
        "directory"
    } else if t.is_file() {
        "regular file"
    } else if t.is_symlink() {
        "symbolic link"
    } else {
        "special file"
    }
}

/// What `path` is when it exists (symbolic links followed; a dangling link counts as
/// absent, since writing replaces the link).
fn existing_kind(path: &Path) -> Result<Option<fs::FileType>, OutputError> {
    match fs::metadata(path) {
        Ok(m) => Ok(Some(m.file_type())),
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(io_err(path, "cannot inspect the output path")(e)),
    }
}

/// Checks that an output file may be written at `path`: nothing is there, or a regular
/// file (which is replaced). Anything else (device, FIFO, socket, directory) is
/// [`OutputError::NotAFile`].
pub fn check_output_file(path: &Path) -> Result<(), OutputError> {
    match existing_kind(path)? {
        Some(t) if !t.is_file() => Err(OutputError::NotAFile {
            path: show(path),
            found: kind_name(t),
        }),
        _ => Ok(()),
    }
}

/// Checks that an output directory may be written at `path`: nothing is there, or a
/// directory.
pub fn check_output_dir(path: &Path) -> Result<(), OutputError> {
    match existing_kind(path)? {
        Some(t) if !t.is_dir() => Err(OutputError::NotADirectory {
            path: show(path),
            found: kind_name(t),
        }),
        _ => Ok(()),
    }
}

/// Returns `name` when it is one plain path component (not empty, not `.` or `..`, no
/// `/` or `\`, not absolute), else [`OutputError::UnsafeName`] naming `context` (the file
/// the name comes from) and `what` it is. Every path built from data goes through this
/// before being joined under an output directory.
pub fn safe_component<'a>(
    context: &str,
    what: &'static str,
    name: &'a str,
) -> Result<&'a str, OutputError> {
    let mut parts = Path::new(name).components();
    let plain = matches!(
        (parts.next(), parts.next()),
        (Some(Component::Normal(c)), None) if c == name
    ) && !name.contains(['/', '\\']);
    if plain {
        Ok(name)
    } else {
        Err(OutputError::UnsafeName {
            context: context.to_string(),
            what,
            name: name.to_string(),
        })
    }
}

/// An exclusive advisory lock on an output directory, released when dropped (or when the
/// process dies).
#[derive(Debug)]
pub struct DirLock {
    _file: File,
}

/// Takes the exclusive lock of directory `dir` (an `flock` on the directory itself, so no
/// file is added): when another process holds it, waits for it with `wait`, else returns
/// [`OutputError::Locked`].
pub fn lock_dir(dir: &Path, wait: bool) -> Result<DirLock, OutputError> {
    let file = File::open(dir).map_err(io_err(dir, "cannot open the directory to lock it"))?;
    if wait {
        file.lock()
            .map_err(io_err(dir, "cannot lock the directory"))?;
    } else {
        match file.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => return Err(OutputError::Locked { path: show(dir) }),
            Err(TryLockError::Error(e)) => return Err(io_err(dir, "cannot lock the directory")(e)),
        }
    }
    Ok(DirLock { _file: file })
}

/// Seconds since `path`'s status last changed (ctime on Unix, else mtime); `None` when
/// unknown.
fn age(meta: &fs::Metadata) -> Option<Duration> {
    #[cfg(unix)]
    let changed = {
        use std::os::unix::fs::MetadataExt;
        let secs = u64::try_from(meta.ctime()).ok()?;
        let nanos = u32::try_from(meta.ctime_nsec()).ok()?;
        std::time::UNIX_EPOCH + Duration::new(secs, nanos)
    };
    #[cfg(not(unix))]
    let changed = meta.modified().ok()?;
    std::time::SystemTime::now().duration_since(changed).ok()
}

/// Removes the `.profuse-tmp-*` files and directories directly in `dir` that no live
/// process holds (their writer locks them; a killed writer's lock is gone) and that are
/// at least `min_age` old (use [`LEFTOVER_MIN_AGE`] unless the caller holds `dir`'s
/// lock, then zero). Best effort: what cannot be removed is left; returns what was
/// removed, sorted. Symbolic links and anything not named so are never touched.
pub fn clean_leftovers(dir: &Path, min_age: Duration) -> Vec<PathBuf> {
    let Ok(entries) = fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut removed = Vec::new();
    for entry in entries.flatten() {
        if !entry.file_name().to_string_lossy().starts_with(TEMP_PREFIX) {
            continue;
        }
        let path = entry.path();
        let Ok(meta) = fs::symlink_metadata(&path) else {
            continue;
        };
        if !(meta.is_file() || meta.is_dir()) || age(&meta).is_none_or(|a| a < min_age) {
            continue;
        }
        let Ok(file) = File::open(&path) else {
            continue;
        };
        if file.try_lock().is_err() {
            continue; // a live writer holds it
        }
        let done = if meta.is_dir() {
            fs::remove_dir_all(&path)
        } else {
            fs::remove_file(&path)
        };
        if done.is_ok() {
            removed.push(path);
        }
    }
    removed.sort();
    removed
}

/// Claims a new temporary file or directory: an exclusive lock held until `file` is
/// dropped (best effort: a file system without locks leaves it unclaimed, and then only
/// [`LEFTOVER_MIN_AGE`] protects it).
pub(crate) fn claim(file: &File) {
    let _ = file.lock();
}

/// A directory output built next to its target and swapped into place whole by
/// [`StagedDir::commit`]; dropped without a commit, it is removed. The target is
/// *replaced*: whatever it held before is gone after the commit, so [`StagedDir::new`]
/// refuses a non-empty target that its caller does not recognise as an earlier output.
#[derive(Debug)]
pub struct StagedDir {
    tmp: Option<tempfile::TempDir>,
    _claim: File,
    target: PathBuf,
}

fn parent_of(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

fn is_empty_dir(path: &Path) -> bool {
    fs::read_dir(path).is_ok_and(|mut d| d.next().is_none())
}

impl StagedDir {
    /// Creates `.profuse-tmp-<name>-XXXXXX` next to `target` (creating its parent) after
    /// removing leftovers there ([`clean_leftovers`]). `target` must not exist, be an empty
    /// directory, or be a directory for which `earlier_output` is true; otherwise
    /// [`OutputError::Foreign`] with `expected` (what `earlier_output` recognises).
    pub fn new(
        target: &Path,
        earlier_output: impl FnOnce(&Path) -> bool,
        expected: &'static str,
    ) -> Result<StagedDir, OutputError> {
        // `.`, `..` or `dir/..` name no entry that could be renamed: use the real path.
        let resolved;
        let target = if target.file_name().is_none() {
            resolved = fs::canonicalize(target).unwrap_or_else(|_| target.to_path_buf());
            resolved.as_path()
        } else {
            target
        };
        check_output_dir(target)?;
        if target.is_dir() && !is_empty_dir(target) && !earlier_output(target) {
            return Err(OutputError::Foreign {
                path: show(target),
                expected,
            });
        }
        let parent = parent_of(target);
        fs::create_dir_all(parent).map_err(io_err(parent, "cannot create the directory"))?;
        clean_leftovers(parent, LEFTOVER_MIN_AGE);
        let name = target
            .file_name()
            .map_or_else(|| "out".into(), |n| n.to_string_lossy().into_owned());
        let tmp = tempfile::Builder::new()
            .prefix(&format!("{TEMP_PREFIX}{name}-"))
            .tempdir_in(parent)
            .map_err(io_err(parent, "cannot create a temporary directory in"))?;
        let file = File::open(tmp.path())
            .map_err(io_err(tmp.path(), "cannot open the temporary directory"))?;
        claim(&file);
        Ok(StagedDir {
            tmp: Some(tmp),
            _claim: file,
            target: target.to_path_buf(),
        })
    }

    /// Where to write the outputs.
    pub fn path(&self) -> &Path {
        self.tmp.as_ref().map_or(&self.target, |t| t.path())
    }

    /// The final directory.
    pub fn target(&self) -> &Path {
        &self.target
    }

    /// Swaps the built directory into place: an existing target is first renamed to a
    /// `.profuse-tmp-old-*` name, the new one renamed onto the target, then the old one
    /// removed (a crash in between leaves the old one as a leftover the next run cleans;
    /// the target is then briefly absent, never partial).
    pub fn commit(mut self) -> Result<(), OutputError> {
        let Some(tmp) = self.tmp.take() else {
            return Ok(());
        };
        let parent = parent_of(&self.target).to_path_buf();
        let old = if fs::symlink_metadata(&self.target).is_ok() {
            let slot = tempfile::Builder::new()
                .prefix(&format!("{TEMP_PREFIX}old-"))
                .tempdir_in(&parent)
                .map_err(io_err(&parent, "cannot create a temporary directory in"))?
                .keep();
            // Renaming a directory onto an empty one replaces it.
            if let Err(e) = fs::rename(&self.target, &slot) {
                let _ = fs::remove_dir(&slot);
                return Err(io_err(&self.target, "cannot move the old output aside")(e));
            }
            Some(slot)
        } else {
            None
        };
        let built = tmp.keep();
        if let Err(e) = fs::rename(&built, &self.target) {
            if let Some(old) = &old {
                let _ = fs::rename(old, &self.target);
            }
            let _ = fs::remove_dir_all(&built);
            return Err(io_err(
                &self.target,
                "cannot move the new output into place",
            )(e));
        }
        if let Some(old) = old {
            let _ = fs::remove_dir_all(old);
        }
        Ok(())
    }
}

/// Serde helpers that write a path as a string, invalid UTF-8 replaced by U+FFFD (so a
/// report about a non-UTF-8 path never fails): `#[serde(serialize_with =
/// "profuse_formats::output::lossy_path::one")]`, `::option` or `::list`.
pub mod lossy_path {
    use std::path::{Path, PathBuf};

    /// One path.
    pub fn one<S: serde::Serializer>(path: &Path, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&path.to_string_lossy())
    }

    /// An optional path (`null` when absent).
    pub fn option<S: serde::Serializer>(path: &Option<PathBuf>, s: S) -> Result<S::Ok, S::Error> {
        match path {
            Some(p) => s.serialize_some(&p.to_string_lossy()),
            None => s.serialize_none(),
        }
    }

    /// A list of paths.
    pub fn list<S: serde::Serializer>(paths: &[PathBuf], s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(paths.iter().map(|p| p.to_string_lossy()))
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    /// Issue 20 item 5: only regular files (or nothing) may be replaced.
    #[test]
    fn only_regular_files_or_nothing_may_be_replaced() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a.bin");
        assert!(check_output_file(&file).is_ok());
        std::fs::write(&file, b"x").unwrap();
        assert!(check_output_file(&file).is_ok());
        let e = check_output_file(dir.path()).unwrap_err();
        assert!(
            matches!(
                e,
                OutputError::NotAFile {
                    found: "directory",
                    ..
                }
            ),
            "{e}"
        );
        #[cfg(unix)]
        {
            let e = check_output_file(Path::new("/dev/null")).unwrap_err();
            assert!(
                matches!(
                    e,
                    OutputError::NotAFile {
                        found: "character device",
                        ..
                    }
                ),
                "{e}"
            );
            let sock = dir.path().join("s.sock");
            let _l = std::os::unix::net::UnixListener::bind(&sock).unwrap();
            let e = check_output_file(&sock).unwrap_err();
            assert!(
                matches!(
                    e,
                    OutputError::NotAFile {
                        found: "socket",
                        ..
                    }
                ),
                "{e}"
            );
        }
        assert!(check_output_dir(dir.path()).is_ok());
        let e = check_output_dir(&file).unwrap_err();
        assert!(
            matches!(
                e,
                OutputError::NotADirectory {
                    found: "regular file",
                    ..
                }
            ),
            "{e}"
        );
    }

    /// Issue 20 item 6: names from data must be one plain component.
    #[test]
    fn only_plain_names_are_safe_components() {
        for ok in ["frame_00001", "a.b", "...", "chair", "x y"] {
            assert_eq!(safe_component("f", "image stem", ok).unwrap(), ok);
        }
        for bad in ["", ".", "..", "a/b", "/abs", "a\\b", "../x", "a/", "./a"] {
            let e = safe_component("cameras.safetensors", "image stem", bad).unwrap_err();
            assert!(e.to_string().contains("cameras.safetensors"), "{e}");
        }
    }

    /// Issue 20 item 7: a held directory lock is a typed error without `wait`.
    #[test]
    fn a_held_directory_lock_is_reported() {
        let dir = tempfile::tempdir().unwrap();
        let held = lock_dir(dir.path(), false).unwrap();
        let e = lock_dir(dir.path(), false).unwrap_err();
        assert!(matches!(e, OutputError::Locked { .. }), "{e}");
        drop(held);
        assert!(lock_dir(dir.path(), false).is_ok());
    }

    /// Issue 20 item 11: unlocked leftovers go, claimed ones and other names stay.
    #[test]
    fn leftovers_are_removed_unless_claimed() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        std::fs::write(d.join(".profuse-tmp-dead"), b"x").unwrap();
        std::fs::create_dir_all(d.join(".profuse-tmp-deaddir/sub")).unwrap();
        std::fs::write(d.join(".profuse-tmp-live"), b"x").unwrap();
        std::fs::write(d.join("keep.bin"), b"x").unwrap();
        std::fs::write(d.join(".other-tmp"), b"x").unwrap();
        let live = File::open(d.join(".profuse-tmp-live")).unwrap();
        live.lock().unwrap();
        // Too young for a caller without the directory lock.
        assert!(clean_leftovers(d, Duration::from_secs(3600)).is_empty());
        let removed = clean_leftovers(d, Duration::ZERO);
        assert_eq!(
            removed,
            vec![d.join(".profuse-tmp-dead"), d.join(".profuse-tmp-deaddir")]
        );
        for stays in [".profuse-tmp-live", "keep.bin", ".other-tmp"] {
            assert!(d.join(stays).exists(), "{stays}");
        }
    }

    /// Issue 20 item 11: a staged directory replaces its target whole on commit, and
    /// leaves nothing when dropped.
    #[test]
    fn a_staged_directory_replaces_whole_or_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("out");
        std::fs::create_dir(&target).unwrap();
        std::fs::write(target.join("old.txt"), b"old").unwrap();
        let e = StagedDir::new(&target, |_| false, "an earlier output").unwrap_err();
        assert!(matches!(e, OutputError::Foreign { .. }), "{e}");

        let staged = StagedDir::new(&target, |_| true, "x").unwrap();
        std::fs::write(staged.path().join("new.txt"), b"new").unwrap();
        drop(staged);
        assert_eq!(std::fs::read(target.join("old.txt")).unwrap(), b"old");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);

        let staged = StagedDir::new(&target, |_| true, "x").unwrap();
        std::fs::write(staged.path().join("new.txt"), b"new").unwrap();
        staged.commit().unwrap();
        // `out/sub/..` is `out` itself.
        std::fs::create_dir(target.join("sub")).unwrap();
        let staged = StagedDir::new(&target.join("sub/.."), |_| true, "x").unwrap();
        assert_eq!(staged.target(), target.canonicalize().unwrap());
        std::fs::write(staged.path().join("new.txt"), b"new").unwrap();
        staged.commit().unwrap();
        assert!(!target.join("old.txt").exists());
        assert_eq!(std::fs::read(target.join("new.txt")).unwrap(), b"new");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    /// Issue 20 item 9: paths that are not UTF-8 serialise lossily instead of failing.
    #[cfg(unix)]
    #[test]
    fn non_utf8_paths_serialise_lossily() {
        use std::os::unix::ffi::OsStrExt;
        #[derive(serde::Serialize)]
        struct R {
            #[serde(serialize_with = "lossy_path::one")]
            p: PathBuf,
            #[serde(serialize_with = "lossy_path::option")]
            o: Option<PathBuf>,
            #[serde(serialize_with = "lossy_path::list")]
            l: Vec<PathBuf>,
        }
        let bad = PathBuf::from(std::ffi::OsStr::from_bytes(b"out/\xff.bin"));
        let r = R {
            p: bad.clone(),
            o: Some(bad.clone()),
            l: vec![bad, PathBuf::from("ok")],
        };
        assert_eq!(
            serde_json::to_string(&r).unwrap(),
            r#"{"p":"out/\ufffd.bin","o":"out/\ufffd.bin","l":["out/\ufffd.bin","ok"]}"#
                .replace("\\ufffd", "\u{fffd}")
        );
    }
}

//! A scratch directory made once per fuzzing process (the readers that take a path get
//! their bytes through it). It lives in /dev/shm when there is one: a write to a disk
//! file costs milliseconds, a hundred times the reading it feeds.

use std::path::Path;
use std::sync::OnceLock;

pub fn dir() -> Option<&'static Path> {
    static DIR: OnceLock<Option<tempfile::TempDir>> = OnceLock::new();
    DIR.get_or_init(|| {
        let shm = Path::new("/dev/shm");
        if shm.is_dir() {
            tempfile::tempdir_in(shm).ok()
        } else {
            tempfile::tempdir().ok()
        }
    })
    .as_ref()
    .map(tempfile::TempDir::path)
}

/// Writes `bytes` to `name` in the scratch directory; `None` when that fails.
pub fn write(name: &str, bytes: &[u8]) -> Option<std::path::PathBuf> {
    let path = dir()?.join(name);
    std::fs::write(&path, bytes).ok()?;
    Some(path)
}

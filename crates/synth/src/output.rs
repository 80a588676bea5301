//! Atomic writes of the non-safetensors outputs (PNG, JSON): a temporary file in the
//! target directory renamed into place, like the format crate's writers.

use std::io::Write;
use std::path::Path;

use image::ExtendedColorType;
use serde::Serialize;

use crate::error::{io_err, Result, SynthError};

fn atomic_write(path: &Path, fill: impl FnOnce(&mut Vec<u8>) -> Result<()>) -> Result<()> {
    let mut bytes = Vec::new();
    fill(&mut bytes)?;
    profuse_formats::write_atomically(path, |mut f| f.write_all(&bytes))
        .map_err(|(action, e)| io_err(path, action)(e))
}

/// Writes an 8-bit RGB PNG.
pub(crate) fn write_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<()> {
    atomic_write(path, |buf| {
        *buf = profuse_formats::png::encode(rgb, width, height, ExtendedColorType::Rgb8).map_err(
            |source| SynthError::Image {
                path: path.display().to_string(),
                source,
            },
        )?;
        Ok(())
    })
}

/// Writes a value as JSON (pretty when `pretty`), with a trailing newline.
pub(crate) fn write_json(path: &Path, value: &impl Serialize, pretty: bool) -> Result<()> {
    atomic_write(path, |buf| {
        let r = if pretty {
            serde_json::to_writer_pretty(&mut *buf, value)
        } else {
            serde_json::to_writer(&mut *buf, value)
        };
        r.map_err(|source| SynthError::Json {
            path: path.display().to_string(),
            source,
        })?;
        buf.push(b'\n');
        Ok(())
    })
}

/// Creates a directory and its parents.
pub(crate) fn create_dir(path: &Path) -> Result<()> {
    std::fs::create_dir_all(path).map_err(io_err(path, "cannot create directory"))
}

/// Removes a file if it exists (stale output of an earlier run).
pub(crate) fn remove_stale(path: &Path) -> Result<()> {
    match std::fs::remove_file(path) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(io_err(path, "cannot remove stale file")(e)),
    }
}

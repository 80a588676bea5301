//! File-system helpers shared by the importers: reads that name the file in their
//! errors, the atomic temp-file + rename write, and image sizes from headers.

use std::fs;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use crate::error::{io_err, Result, SceneError};

/// The path as shown in error messages.
pub(crate) fn show(path: &Path) -> String {
    path.display().to_string()
}

/// Reads a whole file.
pub(crate) fn read_bytes(path: &Path) -> Result<Vec<u8>> {
    fs::read(path).map_err(|e| io_err(&show(path), "cannot read", e))
}

/// Reads a whole UTF-8 text file.
pub(crate) fn read_text(path: &Path) -> Result<String> {
    let bytes = read_bytes(path)?;
    String::from_utf8(bytes).map_err(|e| {
        crate::error::invalid(
            &show(path),
            "text",
            format!(
                "not valid UTF-8 (first bad byte at offset {})",
                e.utf8_error().valid_up_to()
            ),
        )
    })
}

/// Lists the entries of a directory, sorted by file name (so imports are deterministic).
pub(crate) fn list_dir(dir: &Path) -> Result<Vec<PathBuf>> {
    let label = show(dir);
    let mut paths = Vec::new();
    for entry in fs::read_dir(dir).map_err(|e| io_err(&label, "cannot list the directory", e))? {
        let entry = entry.map_err(|e| io_err(&label, "cannot list the directory", e))?;
        paths.push(entry.path());
    }
    paths.sort();
    Ok(paths)
}

/// Writes a file atomically ([`profuse_formats::write_atomically`]: temporary file in the
/// target's directory, flushed, renamed over the target), buffered, with errors naming
/// the file.
pub(crate) fn write_atomically(
    path: &Path,
    fill: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<()> {
    profuse_formats::write_atomically(path, |file| {
        let mut out = BufWriter::new(file);
        fill(&mut out)?;
        out.flush()
    })
    .map_err(|(action, e)| io_err(&show(path), action, e))
}

/// Width and height of an image, read from its header only (the pixels are not decoded).
pub fn image_dimensions(path: &Path) -> Result<[u32; 2]> {
    let label = show(path);
    let reader = image::ImageReader::open(path)
        .map_err(|e| io_err(&label, "cannot open the image", e))?
        .with_guessed_format()
        .map_err(|e| io_err(&label, "cannot read the image", e))?;
    let (w, h) = reader
        .into_dimensions()
        .map_err(|source| SceneError::Image {
            path: label.clone(),
            source,
        })?;
    if w == 0 || h == 0 {
        return Err(crate::error::invalid(
            &label,
            "image size",
            format!("{w}x{h}, expected at least 1x1"),
        ));
    }
    Ok([w, h])
}

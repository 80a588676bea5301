//! File-system helpers shared by the importers: reads that name the file in their
//! errors and refuse anything but regular files, size caps for text, the atomic
//! temp-file + rename write, image sizes from headers, and the one rule for image paths.

use std::fs::{self, File};
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Component, Path, PathBuf};

use crate::error::{invalid, io_err, unsupported, Result, SceneError};

/// Cap of [`read_text`] for small text inputs (ScanNet 4x4 matrices, `<scene>.txt`).
pub const MAX_SMALL_TEXT_BYTES: u64 = 1 << 20;

/// Cap of a `transforms.json` (64 MiB: a real one is ~0.6 KB per frame, so this is
/// about 100,000 frames; parsing into a JSON tree takes ~16x the file size in memory,
/// measured, so the cap bounds a read at ~1 GiB).
pub const MAX_JSON_BYTES: u64 = 64 << 20;

/// The path as shown in error messages.
pub(crate) fn show(path: &Path) -> String {
    path.display().to_string()
}

/// What a non-regular file is, for the error message.
fn file_type_name(t: fs::FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_fifo() {
            return "a FIFO (named pipe)";
        }
        if t.is_char_device() {
            return "a character device";
        }
        if t.is_block_device() {
            return "a block device";
        }
        if t.is_socket() {
            return "a socket";
        }
    }
    if t.is_dir() {
        "a directory"
    } else {
        "not a regular file"
    }
}

fn not_regular(label: &str, t: fs::FileType) -> SceneError {
    unsupported(
        label,
        "file type",
        format!(
            "{}; only regular files are read (copy the data into a file first)",
            file_type_name(t)
        ),
    )
}

/// Opens a regular file for reading and returns it with its size. FIFOs, devices,
/// sockets and directories are refused *before* opening (opening a FIFO blocks until a
/// writer appears; `/dev/zero` never ends), and the opened file is checked again.
pub(crate) fn open_regular(path: &Path) -> Result<(File, u64)> {
    let label = show(path);
    let meta = fs::metadata(path).map_err(|e| io_err(&label, "cannot read", e))?;
    if !meta.is_file() {
        return Err(not_regular(&label, meta.file_type()));
    }
    let file = File::open(path).map_err(|e| io_err(&label, "cannot open", e))?;
    let meta = file
        .metadata()
        .map_err(|e| io_err(&label, "cannot read", e))?;
    if !meta.is_file() {
        return Err(not_regular(&label, meta.file_type()));
    }
    Ok((file, meta.len()))
}

/// Reads a whole regular file, at most `cap` bytes (an error beyond, naming `option`,
/// the way to raise the cap, when there is one).
fn read_capped(path: &Path, cap: u64, option: &str) -> Result<Vec<u8>> {
    let label = show(path);
    let (file, len) = open_regular(path)?;
    let too_big = |n: String| {
        invalid(
            &label,
            "file size",
            format!("{n} bytes, above the {cap}-byte cap of this reader{option}"),
        )
    };
    if len > cap {
        return Err(too_big(len.to_string()));
    }
    let mut bytes = Vec::new();
    // The size of a regular file (not of what it claims inside) sizes the buffer; a
    // sparse file too big for memory is an error here, not an abort.
    bytes
        .try_reserve_exact(usize::try_from(len).unwrap_or(usize::MAX))
        .map_err(|_| {
            invalid(
                &label,
                "file size",
                format!("{len} bytes do not fit in memory"),
            )
        })?;
    file.take(cap.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(|e| io_err(&label, "cannot read", e))?;
    if bytes.len() as u64 > cap {
        return Err(too_big(format!("more than {cap}")));
    }
    Ok(bytes)
}

/// Reads a whole regular file (binary inputs: memory is the file size).
pub(crate) fn read_bytes(path: &Path) -> Result<Vec<u8>> {
    read_capped(path, u64::MAX - 1, "")
}

/// Reads a whole UTF-8 text file of at most [`MAX_SMALL_TEXT_BYTES`].
pub(crate) fn read_text(path: &Path) -> Result<String> {
    read_text_capped(path, MAX_SMALL_TEXT_BYTES, "")
}

/// Reads a whole UTF-8 text file of at most `cap` bytes; `option` (e.g.
/// `" (raise it with --max-text-mb)"`) is appended to the error beyond the cap.
pub(crate) fn read_text_capped(path: &Path, cap: u64, option: &str) -> Result<String> {
    let bytes = read_capped(path, cap, option)?;
    String::from_utf8(bytes).map_err(|e| {
        invalid(
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

/// An image reader on a regular file (see [`open_regular`]), its format taken from the
/// extension and, failing that, from the first bytes.
pub(crate) fn open_image(path: &Path) -> Result<image::ImageReader<BufReader<File>>> {
    let label = show(path);
    let (file, _) = open_regular(path)?;
    let mut reader = image::ImageReader::new(BufReader::new(file));
    if let Ok(format) = image::ImageFormat::from_path(path) {
        reader.set_format(format);
    }
    reader
        .with_guessed_format()
        .map_err(|e| io_err(&label, "cannot read the image", e))
}

/// Width and height of an image, read from its header only (the pixels are not decoded).
pub fn image_dimensions(path: &Path) -> Result<[u32; 2]> {
    let label = show(path);
    let (w, h) = open_image(path)?
        .into_dimensions()
        .map_err(|source| SceneError::Image {
            path: label.clone(),
            source,
        })?;
    if w == 0 || h == 0 {
        return Err(invalid(
            &label,
            "image size",
            format!("{w}x{h}, expected at least 1x1"),
        ));
    }
    Ok([w, h])
}

/// The one rule for image paths read from an input (transforms.json `file_path`, COLMAP
/// image names, a cameras file's `image_names`): relative to the scene folder and inside
/// it, i.e. not empty, not absolute, and without a `..` component. Returns the normal
/// components (`./a/b.png` → `["a", "b.png"]`), or why the path breaks the rule.
pub fn scene_relative_parts(name: &str) -> Result<Vec<String>, &'static str> {
    let mut parts = Vec::new();
    for c in Path::new(name).components() {
        match c {
            Component::Normal(s) => parts.push(s.to_string_lossy().into_owned()),
            Component::CurDir => {}
            Component::ParentDir => {
                return Err("has a `..` component (image paths must stay inside the scene folder)")
            }
            Component::RootDir | Component::Prefix(_) => {
                return Err("is absolute (image paths are relative to the scene folder)")
            }
        }
    }
    if parts.is_empty() {
        return Err("names no file");
    }
    Ok(parts)
}

/// [`scene_relative_parts`] as an error naming `label` and `field`.
pub(crate) fn check_image_name(label: &str, field: &str, name: &str) -> Result<Vec<String>> {
    scene_relative_parts(name)
        .map_err(|why| invalid(label, field, format!("image path {name:?} {why}")))
}

#[cfg(test)]
mod tests {
    use super::scene_relative_parts;

    #[test]
    fn image_path_rule() {
        assert_eq!(
            scene_relative_parts("./images/a.png"),
            Ok(vec!["images".to_string(), "a.png".to_string()])
        );
        assert!(scene_relative_parts("/abs/a.png").is_err());
        assert!(scene_relative_parts(".").is_err());
        assert!(scene_relative_parts("").is_err());
        assert!(scene_relative_parts("../../x.png").is_err());
        assert!(scene_relative_parts("images/../../x.png").is_err());
        assert!(scene_relative_parts("images/../a.png").is_err());
    }
}

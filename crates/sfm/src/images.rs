//! The image files of the input folder, as COLMAP names them.

use std::path::Path;

use crate::SfmError;

/// File extensions (compared case-insensitively) that are handed to COLMAP.
pub(crate) const EXTENSIONS: [&str; 6] = ["jpg", "jpeg", "png", "tif", "tiff", "bmp"];

/// Subfolders deeper than this are not searched (a symbolic-link loop ends here).
const MAX_DEPTH: usize = 8;

/// The images under `dir`, subfolders included, as COLMAP names them: paths relative to
/// `dir` with `/` separators, sorted. Names that are not UTF-8 or hold a line break are
/// left out (they could not be written to COLMAP's image list).
pub(crate) fn list_images(dir: &Path) -> Result<Vec<String>, SfmError> {
    let mut names = Vec::new();
    walk(dir, "", 0, &mut names)?;
    if names.is_empty() {
        return Err(SfmError::NoImages {
            path: dir.to_path_buf(),
        });
    }
    names.sort();
    Ok(names)
}

fn walk(dir: &Path, prefix: &str, depth: usize, names: &mut Vec<String>) -> Result<(), SfmError> {
    let entries = std::fs::read_dir(dir).map_err(|source| SfmError::ImagesDir {
        path: dir.to_path_buf(),
        source,
    })?;
    for entry in entries {
        let entry = entry.map_err(|source| SfmError::ImagesDir {
            path: dir.to_path_buf(),
            source,
        })?;
        let Ok(name) = entry.file_name().into_string() else {
            continue;
        };
        if name.starts_with('.') || name.contains(['\n', '\r']) {
            continue;
        }
        let path = entry.path();
        // Follows symbolic links; an entry that cannot be inspected is skipped.
        let Ok(meta) = std::fs::metadata(&path) else {
            continue;
        };
        let rel = format!("{prefix}{name}");
        if meta.is_dir() {
            if depth < MAX_DEPTH {
                walk(&path, &format!("{rel}/"), depth + 1, names)?;
            }
        } else if meta.is_file() && is_image_name(&name) {
            names.push(rel);
        }
    }
    Ok(())
}

fn is_image_name(name: &str) -> bool {
    name.rsplit_once('.').is_some_and(|(stem, ext)| {
        !stem.is_empty() && EXTENSIONS.iter().any(|e| e.eq_ignore_ascii_case(ext))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn image_names_by_extension() {
        assert!(is_image_name("0001.jpg"));
        assert!(is_image_name("a.JPEG"));
        assert!(is_image_name("b.Png"));
        assert!(!is_image_name(".jpg"));
        assert!(!is_image_name("notes.txt"));
        assert!(!is_image_name("jpg"));
    }
}

//! Which of the four capture layouts an input is, and the photo checks made before
//! anything is written.

use std::path::{Path, PathBuf};

use serde::Serialize;

use super::PrepareError;

/// Photo file extensions a folder of photos is recognised by (case-insensitive).
pub const PHOTO_EXTENSIONS: [&str; 3] = ["jpg", "jpeg", "png"];

/// The capture layouts `profuse prepare` reads (the fourth, "any of these plus a trained
/// splat", is [`super::PrepareOptions::gaussians`] on top of one of them).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Layout {
    /// A folder of photos and nothing else: poses come from COLMAP.
    Photos {
        /// The folder holding the photos (INPUT or INPUT/images).
        images: PathBuf,
    },
    /// A COLMAP project: `images/` and a sparse model (`sparse/0`, or `sparse/`).
    Colmap {
        /// The folder the model's image names are relative to.
        images: PathBuf,
        /// The folder holding cameras, images and points3D (`.bin` or `.txt`).
        model: PathBuf,
    },
    /// A nerfstudio / instant-ngp `transforms.json` with its photos (names relative to
    /// the file's folder).
    Transforms {
        /// The transforms.json file.
        json: PathBuf,
    },
}

impl Layout {
    /// The layout's name in reports.
    pub fn name(&self) -> &'static str {
        match self {
            Layout::Photos { .. } => "photos",
            Layout::Colmap { .. } => "colmap",
            Layout::Transforms { .. } => "transforms",
        }
    }
}

/// Whether `path` names a photo by its extension.
pub fn is_photo(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| PHOTO_EXTENSIONS.iter().any(|p| p.eq_ignore_ascii_case(e)))
}

/// The photos directly inside `dir` (regular files with a photo extension), sorted by name.
pub fn photos_in(dir: &Path) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut photos: Vec<PathBuf> = entries
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        // Follows symbolic links, as COLMAP's image listing does (profuse_sfm::list_images).
        .filter(|p| p.is_file())
        .filter(|p| is_photo(p))
        .collect();
    photos.sort();
    photos
}

/// The sparse model folder of a COLMAP project: `sparse/0` when it holds a model, else
/// `sparse` itself.
fn colmap_model(input: &Path) -> Option<PathBuf> {
    let has_model = |d: &Path| {
        ["bin", "txt"].iter().any(|ext| {
            ["cameras", "images", "points3D"]
                .iter()
                .any(|f| d.join(format!("{f}.{ext}")).is_file())
        })
    };
    [input.join("sparse").join("0"), input.join("sparse")]
        .into_iter()
        .find(|d| has_model(d))
}

/// Detects the layout of `input`. With `photos_only`, every pose source (transforms.json,
/// a sparse model) is ignored and the photos alone are used.
pub fn detect(input: &Path, photos_only: bool) -> Result<Layout, PrepareError> {
    let err = |detail: String| PrepareError::Layout {
        input: input.display().to_string(),
        detail,
    };
    if input.is_file() {
        if photos_only {
            return Err(err(
                "--photos-only needs a folder of photos, not a file".into()
            ));
        }
        if input.extension().is_some_and(|e| e == "json") {
            return Ok(Layout::Transforms {
                json: input.to_path_buf(),
            });
        }
        return Err(err(
            "is a file, but only a transforms.json file or a folder is read".into(),
        ));
    }
    if !input.is_dir() {
        return Err(err("does not exist".into()));
    }
    let images = input.join("images");
    if !photos_only {
        let json = input.join("transforms.json");
        if json.is_file() {
            return Ok(Layout::Transforms { json });
        }
        if let Some(model) = colmap_model(input) {
            return Ok(Layout::Colmap { images, model });
        }
    }
    for dir in [images, input.to_path_buf()] {
        if !photos_in(&dir).is_empty() {
            return Ok(Layout::Photos { images: dir });
        }
    }
    let looked = if photos_only {
        "no photos (.jpg, .jpeg, .png) in it or in its images/ folder"
    } else {
        "no transforms.json, no COLMAP model (sparse/0 or sparse/ with cameras, images and \
         points3D as .bin or .txt), and no photos (.jpg, .jpeg, .png) in it or in its \
         images/ folder"
    };
    Err(err(format!(
        "is none of the layouts prepare reads: {looked}"
    )))
}

/// Reads every photo's header and checks that all share one size; returns it. Errors
/// name the first photo that cannot be read and, for mixed sizes, two photos that differ.
pub fn check_photo_sizes(photos: &[PathBuf]) -> Result<[u32; 2], PrepareError> {
    let mut first: Option<([u32; 2], &Path)> = None;
    for p in photos {
        let size = scene_io::image_dimensions(p).map_err(|e| {
            let path = p.display().to_string();
            let text = e.to_string();
            // scene-io's error already starts with the path.
            let detail = text
                .strip_prefix(&format!("{path}: "))
                .unwrap_or(&text)
                .to_string();
            PrepareError::Photos { path, detail }
        })?;
        match first {
            None => first = Some((size, p)),
            Some((s, q)) if s != size => {
                return Err(PrepareError::Photos {
                    path: p.display().to_string(),
                    detail: format!(
                        "is {}x{}, but {} is {}x{}: the photos of one capture must share one \
                         size (one camera)",
                        size[0],
                        size[1],
                        q.display(),
                        s[0],
                        s[1]
                    ),
                })
            }
            Some(_) => {}
        }
    }
    first.map(|(s, _)| s).ok_or_else(|| PrepareError::Photos {
        path: String::new(),
        detail: "no photos".into(),
    })
}

/// Decodes every photo fully (in parallel), so that a corrupt file is found before any
/// stage writes: the error names the photo.
pub fn check_photos_decode(photos: &[PathBuf]) -> Result<(), PrepareError> {
    use rayon::prelude::*;
    photos.par_iter().try_for_each(|p| {
        image::ImageReader::open(p)
            .and_then(|r| r.with_guessed_format())
            .map_err(|e| e.to_string())
            .and_then(|r| r.decode().map(|_| ()).map_err(|e| e.to_string()))
            .map_err(|detail| PrepareError::Photos {
                path: p.display().to_string(),
                detail: format!("cannot be decoded: {detail}"),
            })
    })
}

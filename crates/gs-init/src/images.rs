//! Where the reference colours come from: an [`ImageSource`] hands out one view's RGB
//! image at a time, so only the images of the references being processed are in memory.

use std::path::{Path, PathBuf};

use crate::error::{InitError, Result};

/// An 8-bit RGB image, rows top to bottom, 3 bytes per pixel.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ViewImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width * height * 3` bytes.
    pub rgb: Vec<u8>,
}

impl ViewImage {
    /// An image of one colour.
    pub fn filled(width: u32, height: u32, rgb: [u8; 3]) -> ViewImage {
        ViewImage {
            width,
            height,
            rgb: rgb.repeat(width as usize * height as usize),
        }
    }

    /// Bilinear colour in [0, 1] at a pixel position (SPEC.md §3.3: pixel (c, r) has its
    /// centre at (c + 0.5, r + 0.5)); positions outside the image take the border colour.
    pub fn sample(&self, x: f64, y: f64) -> [f32; 3] {
        let (w, h) = (self.width as usize, self.height as usize);
        if w == 0 || h == 0 || self.rgb.len() < w * h * 3 {
            return [0.5; 3];
        }
        let fx = (x - 0.5).clamp(0.0, (w - 1) as f64);
        let fy = (y - 0.5).clamp(0.0, (h - 1) as f64);
        let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (tx, ty) = (fx - x0 as f64, fy - y0 as f64);
        let px = |xx: usize, yy: usize, c: usize| f64::from(self.rgb[(yy * w + xx) * 3 + c]);
        std::array::from_fn(|c| {
            let top = px(x0, y0, c) * (1.0 - tx) + px(x1, y0, c) * tx;
            let bottom = px(x0, y1, c) * (1.0 - tx) + px(x1, y1, c) * tx;
            ((top * (1.0 - ty) + bottom * ty) / 255.0) as f32
        })
    }
}

/// Images of the views, by view index.
pub trait ImageSource: Sync {
    /// Names the image of view `v` in messages (its path, for files).
    fn label(&self, v: usize) -> String;

    /// Width and height of view `v`'s image; cheap where possible (a file's header only).
    fn dimensions(&self, v: usize) -> Result<[u32; 2]>;

    /// View `v`'s image as 8-bit RGB.
    fn load(&self, v: usize) -> Result<ViewImage>;
}

/// Images held in memory, one per view.
impl ImageSource for [ViewImage] {
    fn label(&self, v: usize) -> String {
        format!("<image of view {v}>")
    }

    fn dimensions(&self, v: usize) -> Result<[u32; 2]> {
        let img = self.get(v).ok_or_else(|| InitError::ImageMissing {
            path: self.label(v),
            view: v,
        })?;
        Ok([img.width, img.height])
    }

    fn load(&self, v: usize) -> Result<ViewImage> {
        self.get(v).cloned().ok_or_else(|| InitError::ImageMissing {
            path: self.label(v),
            view: v,
        })
    }
}

impl ImageSource for Vec<ViewImage> {
    fn label(&self, v: usize) -> String {
        self.as_slice().label(v)
    }
    fn dimensions(&self, v: usize) -> Result<[u32; 2]> {
        self.as_slice().dimensions(v)
    }
    fn load(&self, v: usize) -> Result<ViewImage> {
        self.as_slice().load(v)
    }
}

/// Image files named by `cameras.image_names` under a root folder: `root/name` (the
/// scene directory of SPEC.md §6, where names read `images/frame_00000.png`), or else
/// `root/<file name of name>` (a folder holding the images themselves). PNG or JPEG.
#[derive(Debug, Clone)]
pub struct ImageDir {
    root: PathBuf,
    names: Vec<String>,
}

impl ImageDir {
    /// Images of `image_names` under `root`.
    pub fn new(root: impl Into<PathBuf>, image_names: &[String]) -> ImageDir {
        ImageDir {
            root: root.into(),
            names: image_names.to_vec(),
        }
    }

    /// The file of view `v`: the first candidate that exists, else the first candidate.
    pub fn path(&self, v: usize) -> PathBuf {
        let Some(name) = self.names.get(v) else {
            return self.root.join(format!("<no image name for view {v}>"));
        };
        let direct = self.root.join(name);
        if direct.is_file() {
            return direct;
        }
        match Path::new(name).file_name() {
            Some(file) if self.root.join(file).is_file() => self.root.join(file),
            _ => direct,
        }
    }

    fn image_error(&self, v: usize, path: &Path, e: image::ImageError) -> InitError {
        let missing = matches!(&e, image::ImageError::IoError(io) if io.kind() == std::io::ErrorKind::NotFound);
        if missing {
            InitError::ImageMissing {
                path: path.display().to_string(),
                view: v,
            }
        } else {
            InitError::Image {
                path: path.display().to_string(),
                source: e,
            }
        }
    }
}

impl ImageSource for ImageDir {
    fn label(&self, v: usize) -> String {
        self.path(v).display().to_string()
    }

    fn dimensions(&self, v: usize) -> Result<[u32; 2]> {
        let path = self.path(v);
        let (w, h) = image::image_dimensions(&path).map_err(|e| self.image_error(v, &path, e))?;
        Ok([w, h])
    }

    fn load(&self, v: usize) -> Result<ViewImage> {
        let path = self.path(v);
        let img = image::open(&path)
            .map_err(|e| self.image_error(v, &path, e))?
            .to_rgb8();
        Ok(ViewImage {
            width: img.width(),
            height: img.height(),
            rgb: img.into_raw(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bilinear_sampling_hits_pixel_centres_and_interpolates_between() {
        let img = ViewImage {
            width: 2,
            height: 1,
            rgb: vec![0, 0, 0, 255, 51, 0],
        };
        assert_eq!(img.sample(0.5, 0.5), [0.0, 0.0, 0.0]);
        assert_eq!(img.sample(1.5, 0.5), [1.0, 0.2, 0.0]);
        let mid = img.sample(1.0, 0.5);
        assert!((mid[0] - 0.5).abs() < 1e-6 && (mid[1] - 0.1).abs() < 1e-6);
        // Outside: the border colour.
        assert_eq!(img.sample(-3.0, 7.0), [0.0, 0.0, 0.0]);
        assert_eq!(img.sample(9.0, -1.0), [1.0, 0.2, 0.0]);
    }
}

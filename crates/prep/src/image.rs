//! Decoded RGB images and the bilinear resampling every model input is made with.

use std::path::Path;

use crate::error::{PrepError, Result};

/// An 8-bit RGB image, row-major, 3 bytes per pixel.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbImage {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// `height * width * 3` bytes.
    pub pixels: Vec<u8>,
}

impl RgbImage {
    /// The pixel's channel `c` at (x, y).
    #[inline]
    pub fn at(&self, x: usize, y: usize, c: usize) -> u8 {
        self.pixels[(y * self.width + x) * 3 + c]
    }
}

/// Most pixels an image may declare (about 200 megapixels): a header that claims more is
/// refused before anything is allocated for it.
pub const MAX_PIXELS: u64 = 200_000_000;

/// The path of the image named `name` (a cameras file's `image_names` entry) inside
/// `dir`: a relative path without `..`, so a cameras file cannot make prep open
/// `/etc/shadow` or `../../secret`.
pub fn image_path(dir: &Path, name: &str) -> Result<std::path::PathBuf> {
    let relative = Path::new(name);
    let inside = !name.is_empty()
        && relative.components().all(|c| {
            matches!(
                c,
                std::path::Component::Normal(_) | std::path::Component::CurDir
            )
        });
    if !inside {
        return Err(PrepError::Image {
            path: dir.join(name),
            message: format!(
                "the image name {name:?} must be a relative path inside {} (no `..`, not absolute)",
                dir.display()
            ),
        });
    }
    Ok(dir.join(relative))
}

/// Reads and decodes an image file (PNG or JPEG) as RGB.
pub fn load_rgb(path: &Path) -> Result<RgbImage> {
    load_rgb_sized(path, None)
}

/// Reads and decodes an image file (PNG or JPEG) as RGB, refusing before decoding a path
/// that is not a regular file (a FIFO would block), a header over [`MAX_PIXELS`], and,
/// with `expected` = (width, height), a header of another size.
pub fn load_rgb_sized(path: &Path, expected: Option<(usize, usize)>) -> Result<RgbImage> {
    let err = |message: String| PrepError::Image {
        path: path.to_path_buf(),
        message,
    };
    let meta = std::fs::metadata(path).map_err(|e| err(e.to_string()))?;
    if !meta.is_file() {
        return Err(err("not a regular file".to_string()));
    }
    let reader = || {
        image::ImageReader::open(path)
            .map_err(|e| err(e.to_string()))?
            .with_guessed_format()
            .map_err(|e| err(e.to_string()))
    };
    let (w, h) = reader()?
        .into_dimensions()
        .map_err(|e| err(e.to_string()))?;
    if u64::from(w) * u64::from(h) > MAX_PIXELS {
        return Err(err(format!(
            "the header declares {w} x {h} pixels, more than {MAX_PIXELS}"
        )));
    }
    if let Some((ew, eh)) = expected {
        if (w as usize, h as usize) != (ew, eh) {
            return Err(err(format!(
                "the image is {w} x {h}, its camera says {ew} x {eh}"
            )));
        }
    }
    let img = reader()?
        .decode()
        .map_err(|e| err(e.to_string()))?
        .into_rgb8();
    Ok(RgbImage {
        width: img.width() as usize,
        height: img.height() as usize,
        pixels: img.into_raw(),
    })
}

/// The image of view `v` of `cameras` inside `dir`, checked by [`image_path`] and against
/// the camera's size before it is decoded.
pub fn load_view_image(
    dir: &Path,
    cameras: &profuse_formats::Cameras,
    v: usize,
) -> Result<RgbImage> {
    let path = image_path(dir, &cameras.image_names[v])?;
    let [w, h] = cameras.image_size[v];
    load_rgb_sized(&path, Some((w as usize, h as usize)))
}

/// Source taps of bilinear resampling from `src` to `dst` samples with half-pixel
/// centres (OpenCV's INTER_LINEAR, no antialiasing): for each output sample the two
/// input indices and the weight of the second.
pub fn taps(src: usize, dst: usize) -> Vec<(usize, usize, f32)> {
    let ratio = src as f64 / dst as f64;
    (0..dst)
        .map(|i| {
            let s = ((i as f64 + 0.5) * ratio - 0.5).max(0.0);
            let i0 = (s.floor() as usize).min(src - 1);
            let i1 = (i0 + 1).min(src - 1);
            (i0, i1, (s - i0 as f64) as f32)
        })
        .collect()
}

/// Bilinear resampling of a region of `img` (x0, y0, w, h) to `dw x dh`, channel `c`
/// through `f(value) -> out` into a planar buffer `out[c][y][x]` of row stride `stride`.
pub(crate) fn resample_planar(
    img: &RgbImage,
    region: (usize, usize, usize, usize),
    size: (usize, usize),
    stride: usize,
    plane: usize,
    out: &mut [f32],
    f: impl Fn(usize, f32) -> f32,
) {
    let (x0, y0, w, h) = region;
    let (dw, dh) = size;
    let xs = taps(w, dw);
    let ys = taps(h, dh);
    for (y, &(ya, yb, fy)) in ys.iter().enumerate() {
        for (x, &(xa, xb, fx)) in xs.iter().enumerate() {
            for c in 0..3 {
                let p = |xx: usize, yy: usize| f32::from(img.at(x0 + xx, y0 + yy, c));
                let top = p(xa, ya) * (1.0 - fx) + p(xb, ya) * fx;
                let bottom = p(xa, yb) * (1.0 - fx) + p(xb, yb) * fx;
                out[c * plane + y * stride + x] = f(c, top * (1.0 - fy) + bottom * fy);
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn image_names_must_stay_inside_the_folder() {
        let dir = Path::new("/scene/images");
        assert_eq!(
            image_path(dir, "sub/0001.png").unwrap(),
            dir.join("sub/0001.png")
        );
        for bad in ["../../etc/passwd", "/etc/shadow", "a/../../b.png", ""] {
            let e = image_path(dir, bad).unwrap_err().to_string();
            assert!(e.contains("must be a relative path"), "{bad}: {e}");
        }
    }

    /// CRC-32 (PNG's), bit by bit: the test patches a header and must re-sign it.
    fn crc32(bytes: &[u8]) -> u32 {
        let mut c = !0u32;
        for &b in bytes {
            c ^= u32::from(b);
            for _ in 0..8 {
                c = if c & 1 == 1 {
                    0xEDB8_8320 ^ (c >> 1)
                } else {
                    c >> 1
                };
            }
        }
        !c
    }

    /// A real 2 x 2 PNG whose header then claims `w` x `h`.
    fn png_claiming(path: &Path, w: u32, h: u32) {
        let mut bytes = Vec::new();
        image::RgbImage::new(2, 2)
            .write_to(
                &mut std::io::Cursor::new(&mut bytes),
                image::ImageFormat::Png,
            )
            .unwrap();
        // Signature (8), IHDR length (4), "IHDR" (4), width, height, ...; CRC after 13 bytes.
        bytes[16..20].copy_from_slice(&w.to_be_bytes());
        bytes[20..24].copy_from_slice(&h.to_be_bytes());
        let crc = crc32(&bytes[12..29]);
        bytes[29..33].copy_from_slice(&crc.to_be_bytes());
        std::fs::write(path, bytes).unwrap();
    }

    #[test]
    fn a_huge_or_wrongly_sized_header_is_refused_before_decoding() {
        let dir = tempfile::tempdir().unwrap();
        let small = dir.path().join("small.png");
        png_claiming(&small, 2, 2);
        assert_eq!(load_rgb_sized(&small, Some((2, 2))).unwrap().width, 2);
        let e = load_rgb_sized(&small, Some((4, 3)))
            .unwrap_err()
            .to_string();
        assert!(e.contains("2 x 2") && e.contains("4 x 3"), "{e}");
        // 20000 x 20000 would be 1.2 GB of RGB: refused from the header alone.
        let huge = dir.path().join("huge.png");
        png_claiming(&huge, 20_000, 20_000);
        assert!(std::fs::metadata(&huge).unwrap().len() < 1000);
        let e = load_rgb_sized(&huge, None).unwrap_err().to_string();
        assert!(
            e.contains("20000 x 20000") && e.contains("more than"),
            "{e}"
        );
        let e = load_rgb_sized(&huge, Some((1080, 1920)))
            .unwrap_err()
            .to_string();
        assert!(e.contains("20000 x 20000"), "{e}");
    }

    #[test]
    fn a_fifo_is_refused_instead_of_blocking() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("view.png");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        if !made.is_ok_and(|s| s.success()) {
            eprintln!("SKIP: mkfifo is not available");
            return;
        }
        let e = load_rgb(&fifo).unwrap_err().to_string();
        assert!(e.contains("not a regular file"), "{e}");
        let e = load_rgb(dir.path()).unwrap_err().to_string();
        assert!(e.contains("not a regular file"), "{e}");
    }
}

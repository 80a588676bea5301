//! The one PNG encoding of the project (feature `png`): every PNG a crate or tool writes
//! (query masks and overlays, synth views, splat-raster renders, undistorted images) is
//! encoded here, with fast deflate and adaptive filtering (chosen for the many small mask
//! PNGs a query writes). The setting changes the file size and the time, never a pixel.
//!
//! ```
//! let grey = [0u8, 255, 255, 0];
//! let bytes = profuse_formats::png::encode(&grey, 2, 2, profuse_formats::png::Color::L8).unwrap();
//! assert_eq!(&bytes[1..4], b"PNG");
//! ```

use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::ImageEncoder;

/// The pixel layouts the project writes (`Rgb8`, `L8`, `L16` big-endian samples as PNG
/// stores them, ...).
pub use image::ExtendedColorType as Color;
/// The encoder's error.
pub use image::ImageError as Error;

/// Encodes `pixels` (row-major, `width` x `height`, in the layout `color`) as a PNG file's
/// bytes.
pub fn encode(pixels: &[u8], width: u32, height: u32, color: Color) -> Result<Vec<u8>, Error> {
    let mut bytes = Vec::new();
    PngEncoder::new_with_quality(&mut bytes, CompressionType::Fast, FilterType::Adaptive)
        .write_image(pixels, width, height, color)?;
    Ok(bytes)
}

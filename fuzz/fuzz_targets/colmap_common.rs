//! Shared by the COLMAP targets: the input is split into cameras, images and points3D
//! files by two little-endian u16 lengths at its start, written to a temporary model
//! directory (made once per process), and imported (`import_colmap`: parse, then cameras and seeded Gaussians).

use crate::scratch;

pub fn run(data: &[u8], ext: &str) {
    if data.len() < 4 {
        return;
    }
    let a = usize::from(u16::from_le_bytes([data[0], data[1]]));
    let b = usize::from(u16::from_le_bytes([data[2], data[3]]));
    let rest = &data[4..];
    let a = a.min(rest.len());
    let b = b.min(rest.len() - a);
    let (cameras, rest) = rest.split_at(a);
    let (images, points) = rest.split_at(b);
    for (name, bytes) in [
        ("cameras", cameras),
        ("images", images),
        ("points3D", points),
    ] {
        if scratch::write(&format!("{name}.{ext}"), bytes).is_none() {
            return;
        }
    }
    if let Some(dir) = scratch::dir() {
        let _ = scene_io::import_colmap(dir, &scene_io::ColmapOptions::default());
    }
}

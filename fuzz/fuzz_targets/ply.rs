//! The PLY reader and the two readers on top of it: INRIA 3DGS Gaussians and ScanNet's
//! labelled meshes (paths only: the bytes go to a temporary file).
#![no_main]

use libfuzzer_sys::fuzz_target;

#[path = "scratch.rs"]
mod scratch;

fuzz_target!(|data: &[u8]| {
    if let Ok(ply) = scene_io::ply::parse_ply(data, "fuzz.ply") {
        let _ = scene_io::ply::gaussians_from_ply(&ply, "fuzz.ply");
    }
    if let Some(path) = scratch::write("fuzz.ply", data) {
        let _ = scene_io::read_inria_ply(&path);
        let _ = scene_io::scannet::read_scannet_labels_ply(&path);
    }
});

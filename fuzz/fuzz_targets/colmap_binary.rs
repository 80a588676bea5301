//! The COLMAP binary model reader (cameras.bin, images.bin, points3D.bin).
#![no_main]

use libfuzzer_sys::fuzz_target;

#[path = "colmap_common.rs"]
mod colmap_common;
#[path = "scratch.rs"]
mod scratch;

fuzz_target!(|data: &[u8]| colmap_common::run(data, "bin"));

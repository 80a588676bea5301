//! The `.npz` reader (a zip of `.npy` members): the bytes are written to a temporary file,
//! since `read_npz` takes a path.
#![no_main]

use libfuzzer_sys::fuzz_target;

#[path = "scratch.rs"]
mod scratch;

fuzz_target!(|data: &[u8]| {
    if let Some(path) = scratch::write("fuzz.npz", data) {
        let _ = scene_io::npy::read_npz(path);
    }
});

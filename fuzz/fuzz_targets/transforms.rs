//! The `transforms.json` importer (a path: the bytes go to a temporary directory, where
//! relative image paths resolve to nothing).
#![no_main]

use libfuzzer_sys::fuzz_target;

#[path = "scratch.rs"]
mod scratch;

fuzz_target!(|data: &[u8]| {
    if let Some(path) = scratch::write("transforms.json", data) {
        let _ = scene_io::read_transforms(path);
    }
});

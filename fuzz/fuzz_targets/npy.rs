//! The `.npy` parser (header dict, dtype, shape, data).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = scene_io::npy::parse_npy(data, "fuzz.npy");
});

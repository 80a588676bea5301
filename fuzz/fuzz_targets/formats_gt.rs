//! The ground-truth JSON readers (`gt/scene.json`, `gt/mask_objects.json`).
#![no_main]

use libfuzzer_sys::fuzz_target;
use profuse_formats::ground_truth::{MaskObjects, SceneTruth};

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = SceneTruth::parse(text, "scene.json");
        let _ = MaskObjects::parse(text, "mask_objects.json");
    }
});

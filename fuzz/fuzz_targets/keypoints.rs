//! The keypoint-pair importer: the bytes are one `<stem_i>_<stem_j>.npz` between the two
//! views of a fixed, distorted camera set (so undistortion runs too).
#![no_main]

use libfuzzer_sys::fuzz_target;
use profuse_formats::Cameras;
use scene_io::keypoints::{import_keypoint_pairs, KeypointOptions};

#[path = "scratch.rs"]
mod scratch;

fn cameras() -> Cameras {
    let pose = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 4.0];
    Cameras {
        image_names: vec!["images/a.png".into(), "images/b.png".into()],
        image_size: vec![[64, 48], [64, 48]].into(),
        intrinsics: vec![[50.0, 50.0, 32.0, 24.0]; 2].into(),
        world_to_camera: vec![pose; 2].into(),
        distortion: Some(vec![[-0.05, 0.01, 0.001, -0.001]; 2].into()),
        extra: Default::default(),
    }
}

fuzz_target!(|data: &[u8]| {
    if let Some(path) = scratch::write("a_b.npz", data) {
        let _ = import_keypoint_pairs(&[path], &cameras(), "cameras", &KeypointOptions::default());
    }
});

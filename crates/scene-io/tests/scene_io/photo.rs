//! `scene_io::photo`: the scene's pixels and the original photo's, through the lens and
//! the cut, against the forward model (distortion of the uncut pinhole pixel).

use profuse_formats::Cameras;
use scene_io::photo::{photo_to_scene, scene_mask_to_photo};
use scene_io::undistort::{cropped, distort_pixel, valid_rects};

/// One 120 x 90 view with a phone-like lens (the fox's coefficients, scaled focal), and
/// the scene camera of `profuse prepare`: undistorted and cut to its valid rectangle.
fn cameras() -> (Cameras, Cameras) {
    let source = Cameras {
        image_names: vec!["photos/a.jpg".into()],
        image_size: vec![[120, 90]].into(),
        intrinsics: vec![[95.0, 94.0, 61.3, 44.2]].into(),
        world_to_camera: vec![[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]].into(),
        distortion: Some(vec![[0.0578, -0.0805, -0.00098, 0.00016]].into()),
        ..Default::default()
    };
    let rects = valid_rects(&source, "test").unwrap();
    let scene = Cameras {
        image_names: vec!["images/a.png".into()],
        ..cropped(&source, &rects)
    };
    (source, scene)
}

#[test]
fn photo_points_map_to_the_scene_pixels_whose_distortion_they_are() {
    let (source, scene) = cameras();
    let [fx, fy, cx, cy] = scene.intrinsics[0];
    let [scx, scy] = [source.intrinsics[0][2], source.intrinsics[0][3]];
    let lens = source.distortion.as_ref().unwrap()[0];
    let [w, h] = scene.image_size[0];
    assert!(w < 120 && h < 90, "the lens must cut something: {w}x{h}");
    for (x, y) in [
        (0.5, 0.5),
        (10.25, 70.75),
        (f64::from(w) - 0.5, f64::from(h) - 0.5),
    ] {
        // Forward: scene pixel -> uncut pinhole pixel -> distorted photo pixel.
        let uncut = [x + (scx - cx), y + (scy - cy)];
        let photo = distort_pixel(&source.intrinsics[0], &lens, uncut);
        let back = photo_to_scene(&source, &scene, 0, photo).unwrap().unwrap();
        assert!(
            (back[0] - x).abs() < 1e-6 && (back[1] - y).abs() < 1e-6,
            "{back:?} vs ({x}, {y})"
        );
        assert_eq!([fx, fy], [95.0, 94.0]);
    }
    // The photo's corner lies in the black border the cut removed.
    assert_eq!(
        photo_to_scene(&source, &scene, 0, [0.5, 0.5]).unwrap(),
        None
    );
}

#[test]
fn a_scene_mask_lands_on_the_photo_pixels_that_see_it() {
    let (source, scene) = cameras();
    let [w, h] = scene.image_size[0].map(|s| s as usize);
    // A 5 x 4 block of scene pixels.
    let mut mask = vec![0u8; w * h];
    for y in 20..24 {
        for x in 30..35 {
            mask[y * w + x] = 255;
        }
    }
    let on_photo = scene_mask_to_photo(&mask, &source, &scene, 0).unwrap();
    assert_eq!(on_photo.len(), 120 * 90);
    // Brute force: each photo pixel is set exactly when its centre maps into the block.
    let mut set = 0;
    for y in 0..90 {
        for x in 0..120 {
            let p = [x as f64 + 0.5, y as f64 + 0.5];
            let inside = photo_to_scene(&source, &scene, 0, p)
                .unwrap()
                .is_some_and(|q| (30.0..35.0).contains(&q[0]) && (20.0..24.0).contains(&q[1]));
            assert_eq!(
                on_photo[y * 120 + x] == 255,
                inside,
                "photo pixel ({x}, {y})"
            );
            set += usize::from(inside);
        }
    }
    // The lens magnifies little here: about the block's 20 pixels land on the photo.
    assert!((14..=28).contains(&set), "{set} photo pixels");
}

#[test]
fn cameras_of_another_photo_or_size_are_refused() {
    let (source, mut scene) = cameras();
    let e = scene_mask_to_photo(&[0; 3], &source, &scene, 0)
        .unwrap_err()
        .to_string();
    assert!(e.contains("mask") && e.contains("size"), "{e}");
    let e = photo_to_scene(&source, &scene, 1, [1.0, 1.0])
        .unwrap_err()
        .to_string();
    assert!(e.contains("out of range"), "{e}");
    scene.image_names = vec!["images/b.png".into()];
    let e = photo_to_scene(&source, &scene, 0, [1.0, 1.0])
        .unwrap_err()
        .to_string();
    assert!(e.contains("image_names[0]"), "{e}");
}

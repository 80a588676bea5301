//! Integration tests of the synthetic scene generator: determinism, ground-truth
//! self-consistency, the fault model, prompts, and that every written file validates.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use profuse_formats::camera::quaternion_to_rotation;
use profuse_formats::{
    Cameras, FileKind, Gaussians, Masks, Matches, Mesh, Prompts, ViewMaps, NO_OBJECT,
};
use synth::{generate, prototype, Camera, Config, FaultModel, Preset, Scene};

fn tiny(seed: u64) -> Config {
    Config::preset(Preset::Tiny, seed)
}

/// A small but less coarse config for statistics.
fn small(seed: u64) -> Config {
    Config {
        views: 6,
        width: 128,
        height: 96,
        objects: 7,
        gaussians: 2000,
        eval_every: 2,
        ..Config::preset(Preset::Tiny, seed)
    }
}

fn gen(config: &Config) -> (tempfile::TempDir, synth::Summary) {
    let dir = tempfile::tempdir().unwrap();
    let summary = generate(config, dir.path()).unwrap();
    (dir, summary)
}

fn files(root: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.insert(
                    p.strip_prefix(root).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                );
            }
        }
    }
    out
}

fn in_pool<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(f)
}

#[test]
fn determinism_across_thread_counts_and_seeds() {
    let mut config = tiny(11);
    config.gaussians = 300;
    config.warp_noise_px = 0.5;
    config.outlier_frac = 0.02;
    let a = tempfile::tempdir().unwrap();
    let b = tempfile::tempdir().unwrap();
    in_pool(1, || generate(&config, a.path())).unwrap();
    in_pool(4, || generate(&config, b.path())).unwrap();
    let (fa, fb) = (files(a.path()), files(b.path()));
    let names: Vec<&PathBuf> = fa.keys().collect();
    assert_eq!(names, fb.keys().collect::<Vec<_>>());
    for expected in [
        "cameras.safetensors",
        "masks.safetensors",
        "matches.safetensors",
        "prompts.safetensors",
        "gt/scene.json",
        "gt/views.safetensors",
        "gt/mesh.safetensors",
        "gt/gaussians.safetensors",
        "gt/mask_objects.json",
        "gt/label/frame_00000.json",
        "gt/label/frame_00002.json",
        "images/frame_00000.png",
        "images/frame_00003.png",
    ] {
        assert!(
            fa.contains_key(Path::new(expected)),
            "{expected} missing: {names:?}"
        );
    }
    for (name, bytes) in &fa {
        assert!(
            bytes == &fb[name],
            "{} differs between 1 and 4 threads",
            name.display()
        );
    }
    // Regenerating into the same directory gives the same bytes again.
    generate(&config, a.path()).unwrap();
    assert_eq!(files(a.path()), fa);

    // Another seed changes every data file.
    config.seed = 12;
    let c = tempfile::tempdir().unwrap();
    generate(&config, c.path()).unwrap();
    let fc = files(c.path());
    for name in [
        "cameras.safetensors",
        "masks.safetensors",
        "matches.safetensors",
        "prompts.safetensors",
        "gt/scene.json",
        "gt/views.safetensors",
        "gt/mesh.safetensors",
        "gt/gaussians.safetensors",
        "images/frame_00000.png",
    ] {
        assert_ne!(
            fa[Path::new(name)],
            fc[Path::new(name)],
            "{name} did not change with the seed"
        );
    }
}

#[test]
fn every_file_validates_with_the_format_readers() {
    let (dir, s) = gen(&small(5));
    let d = dir.path();
    let cams = Cameras::read(d.join("cameras.safetensors")).unwrap();
    assert_eq!(cams.len(), 6);
    for name in &cams.image_names {
        let img = std::fs::read(d.join(name)).unwrap();
        assert_eq!(&img[1..4], b"PNG");
    }
    let masks = Masks::read(d.join("masks.safetensors")).unwrap();
    assert_eq!(masks.view_names, cams.image_names);
    assert_eq!((masks.width, masks.height, masks.dim), (128, 96, 64));
    assert_eq!(masks.num_masks(), s.masks);
    let matches = Matches::read(d.join("matches.safetensors")).unwrap();
    assert_eq!(
        (matches.width, matches.height, matches.pairs.len()),
        (64, 48, s.pairs)
    );
    let prompts = Prompts::read(d.join("prompts.safetensors")).unwrap();
    assert_eq!(prompts.dim, 64);
    let views = ViewMaps::read(d.join("gt/views.safetensors")).unwrap();
    assert_eq!(views.num_objects, s.scene_objects);
    let mesh = Mesh::read(d.join("gt/mesh.safetensors")).unwrap();
    assert_eq!(mesh.vertices.len(), s.mesh[0]);
    let g = Gaussians::read(d.join("gt/gaussians.safetensors")).unwrap();
    assert_eq!(g.len(), 2000);
    // JSON files parse.
    for name in [
        "gt/scene.json",
        "gt/mask_objects.json",
        "gt/label/frame_00000.json",
    ] {
        let _: serde_json::Value =
            serde_json::from_slice(&std::fs::read(d.join(name)).unwrap()).unwrap();
    }
    // Disabled outputs are not written (and stale ones removed).
    let mut c = small(5);
    c.write_masks = false;
    c.write_matches = false;
    c.gaussians = 0;
    c.views = 4;
    generate(&c, d).unwrap();
    for gone in [
        "masks.safetensors",
        "matches.safetensors",
        "gt/gaussians.safetensors",
        "gt/mask_objects.json",
        "images/frame_00005.png",
        "gt/label/frame_00004.json",
    ] {
        assert!(!d.join(gone).exists(), "{gone} should be gone");
    }
    assert!(d.join("prompts.safetensors").exists());
}

#[test]
fn warps_land_on_the_same_object() {
    let (dir, _) = gen(&small(2));
    let d = dir.path();
    let scene = Scene::from_json(d.join("gt/scene.json")).unwrap();
    let cams = Cameras::read(d.join("cameras.safetensors")).unwrap();
    let views = ViewMaps::read(d.join("gt/views.safetensors")).unwrap();
    let ids = views.object_ids.as_ref().unwrap();
    let m = Matches::read(d.join("matches.safetensors")).unwrap();
    let (gw, gh) = (m.width, m.height);
    let (mut certain, mut zero, mut exact, mut nearest, mut within_one, mut depth_ok) =
        (0usize, 0usize, 0usize, 0usize, 0usize, 0usize);
    for (p, [i, j]) in m.pairs.iter().enumerate() {
        let (ci, cj) = (
            Camera::from_cameras(&cams, *i as usize),
            Camera::from_cameras(&cams, *j as usize),
        );
        let (w, h) = (f64::from(cj.width), f64::from(cj.height));
        for y in 0..gh {
            for x in 0..gw {
                let cell = (p * gh + y) * gw + x;
                let c = m.certainty.get(cell);
                let (sx, sy) = (
                    (x as f64 + 0.5) * w / gw as f64,
                    (y as f64 + 0.5) * h / gh as f64,
                );
                let hit = scene.raycast(ci.center(), ci.ray(sx, sy)).unwrap();
                let (xn, yn) = (
                    f64::from(m.warp.get(2 * cell)),
                    f64::from(m.warp.get(2 * cell + 1)),
                );
                let (u, v) = ((xn + 1.0) / 2.0 * w, (yn + 1.0) / 2.0 * h);
                // The warp is the exact projection (also where the certainty is 0).
                let q = cj.project(hit.point);
                let tol = |a: f64| 1e-3 + 1e-6 * a.abs();
                if q[0].is_finite() && q[1].is_finite() && q[2] > 1e-3 {
                    assert!(
                        (q[0] - u).abs() < tol(q[0]) && (q[1] - v).abs() < tol(q[1]),
                        "pair {p} cell ({x}, {y}): {q:?} vs {u}, {v}"
                    );
                }
                if c == 0.0 {
                    zero += 1;
                    continue;
                }
                assert!((0.7..=1.0).contains(&c), "{c}");
                certain += 1;
                // At the exact target, view j sees the same surface point.
                let back = scene.raycast(cj.center(), cj.ray(u, v)).unwrap();
                if back.object == hit.object && (back.t - q[2]).abs() < 1e-4 {
                    exact += 1;
                }
                // The nearest pixel of view j shows the same object, or (silhouettes) one
                // of its 8 neighbours does.
                let (px, py) = (u.floor() as i64, v.floor() as i64);
                let at = |dx: i64, dy: i64| {
                    let (xx, yy) = (px + dx, py + dy);
                    (xx >= 0 && yy >= 0 && xx < w as i64 && yy < h as i64)
                        .then(|| views.index(*j as usize, xx as usize, yy as usize))
                };
                let k = at(0, 0).unwrap();
                if ids[k] == hit.object {
                    nearest += 1;
                }
                if (-1..=1)
                    .any(|dy| (-1..=1).any(|dx| at(dx, dy).is_some_and(|k| ids[k] == hit.object)))
                {
                    within_one += 1;
                }
                if (f64::from(views.depth[k]) - q[2]).abs() < 0.05 * q[2] {
                    depth_ok += 1;
                }
            }
        }
    }
    let share = |n: usize| n as f64 / certain as f64;
    eprintln!(
        "certain {certain}, zero {zero}; exact {:.4}, nearest pixel {:.4}, within one pixel {:.4}, depth {:.4}",
        share(exact),
        share(nearest),
        share(within_one),
        share(depth_ok)
    );
    assert!(certain > 10_000, "{certain} certain cells");
    assert!(
        zero > 1000,
        "some cells must be invisible in the other view: {zero}"
    );
    assert!(share(exact) >= 0.999, "exact target: {exact} / {certain}");
    assert!(
        share(within_one) >= 0.99,
        "within one pixel: {within_one} / {certain}"
    );
    // At 128x96 about 3% of the certain cells land within half a pixel of a silhouette
    // in view j (foreshortened faces), so the nearest pixel centre can see the neighbour.
    assert!(
        share(nearest) >= 0.96,
        "nearest pixel: {nearest} / {certain}"
    );
    assert!(share(depth_ok) >= 0.96, "depth: {depth_ok} / {certain}");
}

#[test]
fn depth_reprojects_onto_the_surface() {
    let (dir, _) = gen(&tiny(4));
    let d = dir.path();
    let scene = Scene::from_json(d.join("gt/scene.json")).unwrap();
    let cams = Cameras::read(d.join("cameras.safetensors")).unwrap();
    let views = ViewMaps::read(d.join("gt/views.safetensors")).unwrap();
    let ids = views.object_ids.as_ref().unwrap();
    for v in 0..cams.len() {
        let cam = Camera::from_cameras(&cams, v);
        let c = cam.center();
        for y in 0..views.height {
            for x in 0..views.width {
                let k = views.index(v, x, y);
                let depth = f64::from(views.depth[k]);
                assert!(depth > 0.0, "closed room: every pixel sees a surface");
                let r = cam.ray(x as f64 + 0.5, y as f64 + 0.5);
                let p = [
                    c[0] + depth * r[0],
                    c[1] + depth * r[1],
                    c[2] + depth * r[2],
                ];
                // The back-projected point is on the surface ...
                let dist = scene.distance_to_surface(p);
                assert!(dist < 1e-4, "view {v} pixel ({x}, {y}): {dist}");
                // ... and re-casting toward it from the camera gives the same hit.
                let dir = [p[0] - c[0], p[1] - c[1], p[2] - c[2]];
                let hit = scene.raycast(c, dir).unwrap();
                assert!(
                    (hit.t - 1.0).abs() * depth < 1e-4,
                    "view {v} pixel ({x}, {y}): t = {}",
                    hit.t
                );
                assert_eq!(hit.object, ids[k]);
                // The camera-space z of the point is the stored depth.
                assert!((cam.project(p)[2] - depth).abs() < 1e-9);
            }
        }
    }
}

#[test]
fn mesh_labels_agree_with_object_maps() {
    // The demo's 5 cm mesh spacing (at 25 cm most vertices of small objects sit on edges).
    let (dir, _) = gen(&Config {
        mesh_spacing: 0.05,
        ..small(3)
    });
    let d = dir.path();
    let cams = Cameras::read(d.join("cameras.safetensors")).unwrap();
    let views = ViewMaps::read(d.join("gt/views.safetensors")).unwrap();
    let ids = views.object_ids.as_ref().unwrap();
    let mesh = Mesh::read(d.join("gt/mesh.safetensors")).unwrap();
    let (labels, inst) = (
        mesh.labels.as_ref().unwrap(),
        mesh.instances.as_ref().unwrap(),
    );
    let scene = Scene::from_json(d.join("gt/scene.json")).unwrap();
    for (l, i) in labels.iter().zip(inst.iter()) {
        assert_eq!(*l, scene.objects[*i as usize - 1].class_id);
    }
    let (mut visible, mut agree) = (0usize, 0usize);
    for v in 0..cams.len() {
        let cam = Camera::from_cameras(&cams, v);
        for (p, i) in mesh.vertices.iter().zip(inst.iter()) {
            let q = cam.project(p.map(f64::from));
            if !(q[2] > 0.0 && q[0] >= 0.0 && q[1] >= 0.0 && q[0] < 128.0 && q[1] < 96.0) {
                continue;
            }
            let k = views.index(v, q[0] as usize, q[1] as usize);
            let z = f64::from(views.depth[k]);
            if (q[2] - z).abs() > 0.01 * z + 0.01 {
                continue;
            }
            visible += 1;
            if ids[k] == i - 1 {
                agree += 1;
            }
        }
    }
    eprintln!(
        "visible vertices {visible}, agreeing {:.4}",
        agree as f64 / visible as f64
    );
    assert!(visible > 50_000, "{visible}");
    assert!(agree as f64 >= 0.95 * visible as f64, "{agree} / {visible}");
}

/// Even-odd rasterisation by pixel-centre test.
fn rasterise(poly: &[[f64; 2]], w: usize, h: usize, out: &mut [bool]) {
    for y in 0..h {
        let py = y as f64 + 0.5;
        let mut xs: Vec<f64> = Vec::new();
        for k in 0..poly.len() {
            let (a, b) = (poly[k], poly[(k + 1) % poly.len()]);
            if (a[1] > py) != (b[1] > py) {
                xs.push(a[0] + (py - a[1]) / (b[1] - a[1]) * (b[0] - a[0]));
            }
        }
        xs.sort_by(f64::total_cmp);
        for x in 0..w {
            let px = x as f64 + 0.5;
            if xs.iter().filter(|c| **c > px).count() % 2 == 1 {
                out[y * w + x] = !out[y * w + x];
            }
        }
    }
}

/// Pixels of 4-connected components with at least `min` pixels of the given objects.
fn big_components(
    ids: &[u32],
    w: usize,
    h: usize,
    objects: &BTreeSet<u32>,
    min: usize,
) -> Vec<bool> {
    let mut seen = vec![false; ids.len()];
    let mut keep = vec![false; ids.len()];
    for s in 0..ids.len() {
        if seen[s] || !objects.contains(&ids[s]) {
            continue;
        }
        let mut comp = vec![s];
        seen[s] = true;
        let mut k = 0;
        while k < comp.len() {
            let i = comp[k];
            k += 1;
            let (x, y) = (i % w, i / w);
            let mut n = Vec::new();
            if x > 0 {
                n.push(i - 1);
            }
            if x + 1 < w {
                n.push(i + 1);
            }
            if y > 0 {
                n.push(i - w);
            }
            if y + 1 < h {
                n.push(i + w);
            }
            for j in n {
                if !seen[j] && ids[j] == ids[s] {
                    seen[j] = true;
                    comp.push(j);
                }
            }
        }
        if comp.len() >= min {
            for i in comp {
                keep[i] = true;
            }
        }
    }
    keep
}

#[test]
fn label_polygons_reproduce_the_object_regions() {
    let (dir, s) = gen(&small(6));
    let d = dir.path();
    let views = ViewMaps::read(d.join("gt/views.safetensors")).unwrap();
    let ids = views.object_ids.as_ref().unwrap();
    let scene = Scene::from_json(d.join("gt/scene.json")).unwrap();
    let (w, h) = (views.width, views.height);
    assert_eq!(s.eval_frames, vec![0, 2, 4]);
    let mut checked = 0;
    for &v in &s.eval_frames {
        let json: serde_json::Value = serde_json::from_slice(
            &std::fs::read(d.join(format!("gt/label/frame_{v:05}.json"))).unwrap(),
        )
        .unwrap();
        assert_eq!(json["info"]["name"], format!("frame_{v:05}.png"));
        assert_eq!(json["info"]["width"], 128);
        assert_eq!(json["info"]["height"], 96);
        let plane = &ids[v * w * h..(v + 1) * w * h];
        let mut by_cat: BTreeMap<String, Vec<bool>> = BTreeMap::new();
        for o in json["objects"].as_array().unwrap() {
            let poly: Vec<[f64; 2]> = o["segmentation"]
                .as_array()
                .unwrap()
                .iter()
                .map(|p| [p[0].as_f64().unwrap(), p[1].as_f64().unwrap()])
                .collect();
            let bbox: Vec<f64> = o["bbox"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect();
            assert!(poly
                .iter()
                .all(|p| p[0] >= bbox[0] && p[0] <= bbox[2] && p[1] >= bbox[1] && p[1] <= bbox[3]));
            let mut own = vec![false; w * h];
            rasterise(&poly, w, h, &mut own);
            let cat = by_cat
                .entry(o["category"].as_str().unwrap().to_string())
                .or_insert_with(|| vec![false; w * h]);
            for (c, x) in cat.iter_mut().zip(own) {
                *c |= x;
            }
        }
        // Every visible non-room category with a component of >= 20 px has polygons.
        let visible: BTreeSet<&str> = plane
            .iter()
            .filter(|o| **o != NO_OBJECT && !scene.objects[**o as usize].room)
            .map(|o| scene.objects[*o as usize].class_name.as_str())
            .collect();
        for cat in visible {
            let objs: BTreeSet<u32> = scene
                .objects
                .iter()
                .filter(|o| o.class_name == cat)
                .map(|o| o.index)
                .collect();
            let truth = big_components(plane, w, h, &objs, synth::MIN_COMPONENT_PX);
            if !truth.iter().any(|t| *t) {
                continue;
            }
            let pred = by_cat
                .get(cat)
                .unwrap_or_else(|| panic!("frame {v}: no polygons for {cat}"));
            let inter = truth.iter().zip(pred).filter(|(a, b)| **a && **b).count();
            let union = truth.iter().zip(pred).filter(|(a, b)| **a || **b).count();
            let iou = inter as f64 / union as f64;
            assert!(iou > 0.95, "frame {v} {cat}: IoU {iou}");
            assert_eq!(
                inter, union,
                "frame {v} {cat}: the crack-following polygon is exact"
            );
            checked += 1;
        }
    }
    assert!(checked >= 6, "{checked}");
}

/// Per mask: (pixel count, pixels per object).
fn mask_composition(masks: &Masks, views: &ViewMaps) -> Vec<(u64, BTreeMap<u32, u64>)> {
    let ids = views.object_ids.as_ref().unwrap();
    let mut out = vec![(0u64, BTreeMap::new()); masks.num_masks()];
    for v in 0..masks.num_views() {
        for y in 0..masks.height {
            for x in 0..masks.width {
                if let Some(m) = masks.mask_at(v, x, y) {
                    let e = &mut out[m as usize];
                    e.0 += 1;
                    *e.1.entry(ids[views.index(v, x, y)]).or_default() += 1;
                }
            }
        }
    }
    out
}

#[test]
fn fault_model_exact_and_default() {
    // All fault probabilities 0: masks are the visible object regions exactly.
    let mut c = small(8);
    c.faults = FaultModel::exact();
    let (dir, _) = gen(&c);
    let masks = Masks::read(dir.path().join("masks.safetensors")).unwrap();
    let views = ViewMaps::read(dir.path().join("gt/views.safetensors")).unwrap();
    let ids = views.object_ids.as_ref().unwrap();
    let comp = mask_composition(&masks, &views);
    let mut visible_total = 0;
    for v in 0..masks.num_views() {
        let plane = &ids[v * 128 * 96..(v + 1) * 128 * 96];
        let visible: BTreeSet<u32> = plane.iter().copied().collect();
        visible_total += visible.len();
        assert_eq!(masks.masks_in_view(v), visible.len(), "view {v}");
        // Every pixel has a mask, and object -> mask is one-to-one.
        let mut mask_of = BTreeMap::new();
        for (i, o) in plane.iter().enumerate() {
            let m = masks
                .mask_at(v, i % 128, i / 128)
                .expect("every pixel has a mask");
            assert_eq!(*mask_of.entry(*o).or_insert(m), m);
        }
    }
    assert_eq!(masks.num_masks(), visible_total);
    assert!(
        comp.iter().all(|(n, objs)| *n > 0 && objs.len() == 1),
        "purity 1.0 everywhere"
    );
    let mo: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("gt/mask_objects.json")).unwrap())
            .unwrap();
    assert!(mo["masks"]
        .as_array()
        .unwrap()
        .iter()
        .all(|m| m["purity"] == 1.0));

    // Default faults: impure masks and a different mask count.
    let (dir, _) = gen(&small(8));
    let masks = Masks::read(dir.path().join("masks.safetensors")).unwrap();
    let views = ViewMaps::read(dir.path().join("gt/views.safetensors")).unwrap();
    let comp = mask_composition(&masks, &views);
    let impure = comp
        .iter()
        .filter(|(n, objs)| objs.values().max().copied().unwrap_or(0) < *n)
        .count();
    assert!(impure > 0);
    assert_ne!(masks.num_masks(), visible_total);
    let mo: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("gt/mask_objects.json")).unwrap())
            .unwrap();
    let entries = mo["masks"].as_array().unwrap();
    assert_eq!(entries.len(), masks.num_masks());
    for (e, (n, objs)) in entries.iter().zip(&comp) {
        // The recorded dominant object and purity match the maps.
        let (best, count) = objs
            .iter()
            .max_by_key(|(o, c)| (**c, std::cmp::Reverse(**o)))
            .unwrap();
        assert_eq!(e["pixels"], *n);
        assert_eq!(e["object"], *best);
        assert!((e["purity"].as_f64().unwrap() - *count as f64 / *n as f64).abs() < 1e-12);
    }
    // Features sit near the prototype of their mask's dominant class.
    let scene = Scene::from_json(dir.path().join("gt/scene.json")).unwrap();
    let classes: BTreeSet<(u32, String)> = scene
        .objects
        .iter()
        .map(|o| (o.class_id, o.class_name.clone()))
        .collect();
    let protos: Vec<(u32, Vec<f64>)> = classes
        .iter()
        .map(|(id, n)| (*id, prototype(8, 64, n)))
        .collect();
    let mut right = 0;
    for (m, e) in entries.iter().enumerate() {
        let f: Vec<f64> = (0..64)
            .map(|k| f64::from(masks.features.get(m * 64 + k)))
            .collect();
        let best = protos
            .iter()
            .max_by(|a, b| dot(&f, &a.1).total_cmp(&dot(&f, &b.1)))
            .unwrap()
            .0;
        if e["feature_class"] == best {
            right += 1;
        }
    }
    assert!(
        right as f64 >= 0.9 * entries.len() as f64,
        "{right} / {}",
        entries.len()
    );
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[test]
fn prompts_are_near_but_not_at_their_class() {
    let c = Config {
        feature_dim: 512,
        ..small(9)
    };
    let (dir, _) = gen(&c);
    let p = Prompts::read(dir.path().join("prompts.safetensors")).unwrap();
    let ids = p.class_ids.as_ref().unwrap();
    let scene = Scene::from_json(dir.path().join("gt/scene.json")).unwrap();
    let classes: BTreeSet<(u32, String)> = scene
        .objects
        .iter()
        .map(|o| (o.class_id, o.class_name.clone()))
        .collect();
    // One prompt per class present, distractors and negatives with class -1.
    for (id, name) in &classes {
        let q = p
            .index_of(name)
            .unwrap_or_else(|| panic!("no prompt for {name}"));
        assert_eq!(ids[q], *id as i32);
    }
    for name in [
        "guitar", "banana", "umbrella", "object", "things", "stuff", "texture",
    ] {
        assert_eq!(ids[p.index_of(name).unwrap()], -1, "{name}");
    }
    assert_eq!(p.len(), classes.len() + 7);
    let mut protos: Vec<(String, Vec<f64>)> = classes
        .iter()
        .map(|(_, n)| (n.clone(), prototype(9, 512, n)))
        .collect();
    for d in ["guitar", "banana", "umbrella"] {
        protos.push((d.to_string(), prototype(9, 512, d)));
    }
    for q in 0..p.len() {
        let e: Vec<f64> = p.embedding(q).iter().map(|x| f64::from(*x)).collect();
        assert!((dot(&e, &e) - 1.0).abs() < 1e-5);
        let name = &p.names[q];
        if ["object", "things", "stuff", "texture"].contains(&name.as_str()) {
            continue;
        }
        let (best, _) = protos
            .iter()
            .map(|(n, v)| (n, dot(&e, v)))
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        assert_eq!(best, name);
        let own = dot(&e, &protos.iter().find(|(n, _)| n == name).unwrap().1);
        assert!(own < 0.999 && own > 0.8, "{name}: cosine {own}");
    }
}

#[test]
fn scene_json_rebuilds_the_same_geometry() {
    let (dir, s) = gen(&tiny(13));
    let d = dir.path();
    let scene = Scene::from_json(d.join("gt/scene.json")).unwrap();
    assert_eq!(scene.len(), s.scene_objects);
    let cams = Cameras::read(d.join("cameras.safetensors")).unwrap();
    let views = ViewMaps::read(d.join("gt/views.safetensors")).unwrap();
    let plane = 64 * 48;
    let (mut depth, mut ids, mut rgb) =
        (vec![0f32; plane], vec![0u32; plane], vec![0u8; plane * 3]);
    for v in 0..cams.len() {
        synth::render(
            &scene,
            &Camera::from_cameras(&cams, v),
            &mut depth,
            &mut ids,
            &mut rgb,
        );
        assert_eq!(depth[..], views.depth[v * plane..(v + 1) * plane]);
        assert_eq!(
            ids[..],
            views.object_ids.as_ref().unwrap()[v * plane..(v + 1) * plane]
        );
    }
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(d.join("gt/scene.json")).unwrap()).unwrap();
    assert_eq!(json["seed"], 13);
    assert_eq!(json["objects"].as_array().unwrap().len(), s.scene_objects);
    assert_eq!(json["fault_model"]["p_split"], 0.15);
    assert_eq!(json["masks"]["per_view"].as_array().unwrap().len(), 4);
    let kinds: BTreeSet<&str> = json["objects"]
        .as_array()
        .unwrap()
        .iter()
        .map(|o| o["shape"]["kind"].as_str().unwrap())
        .collect();
    assert!(kinds.contains("cuboid"));
}

#[test]
fn demo_sized_scene_has_every_class() {
    // The demo's object mix (10 objects) at a small resolution.
    let c = Config {
        width: 64,
        height: 48,
        views: 3,
        gaussians: 0,
        write_matches: false,
        mesh_spacing: 0.5,
        ..Config::preset(Preset::Demo, 0)
    };
    let (dir, s) = gen(&c);
    assert_eq!(s.objects, 10);
    let scene = Scene::from_json(dir.path().join("gt/scene.json")).unwrap();
    let classes: BTreeSet<u32> = scene.objects.iter().map(|o| o.class_id).collect();
    for id in synth::classes::FURNITURE
        .iter()
        .chain(&synth::classes::ROOM)
    {
        assert!(classes.contains(id), "class {id} missing");
    }
}

#[test]
fn gaussians_lie_on_visible_surfaces() {
    let (dir, _) = gen(&small(10));
    let d = dir.path();
    let scene = Scene::from_json(d.join("gt/scene.json")).unwrap();
    let g = Gaussians::read(d.join("gt/gaussians.safetensors")).unwrap();
    let classes: BTreeSet<i32> = scene.objects.iter().map(|o| o.class_id as i32).collect();
    let cls = g.class_ids.as_ref().unwrap();
    let mut per_class = BTreeMap::<i32, usize>::new();
    let mut off_surface = 0;
    for k in 0..g.len() {
        let p = g.means[k].map(f64::from);
        assert!(scene.distance_to_surface(p) < 1e-4);
        assert!(classes.contains(&cls[k]));
        *per_class.entry(cls[k]).or_default() += 1;
        // Local z (the thin axis) is along the surface normal: the point nudged along it
        // leaves the surface.
        let r = quaternion_to_rotation(g.rotations[k].map(f64::from)).unwrap();
        let n = [r[0][2], r[1][2], r[2][2]];
        let q = [p[0] + 0.01 * n[0], p[1] + 0.01 * n[1], p[2] + 0.01 * n[2]];
        if scene.distance_to_surface(q) > 0.009 {
            off_surface += 1;
        }
        let s = g.log_scales[k];
        assert!((s[2] - s[0] - 0.1f32.ln()).abs() < 1e-5);
        assert!((g.opacity(k) - 0.880_797).abs() < 1e-5);
    }
    // (Not all: points within 1 cm of another surface, at contacts and corners.)
    assert!(off_surface as f64 > 0.97 * g.len() as f64, "{off_surface}");
    // Walls and the floor dominate, but objects are sampled too.
    assert!(per_class.len() >= 4, "{per_class:?}");
}

#[test]
fn bad_parameters_are_named() {
    let mut c = tiny(0);
    c.faults.p_split = 1.5;
    let e = generate(&c, tempfile::tempdir().unwrap().path()).unwrap_err();
    assert!(e.to_string().contains("p_split"), "{e}");
    let mut c = tiny(0);
    c.match_scale = 0.0;
    let e = generate(&c, tempfile::tempdir().unwrap().path()).unwrap_err();
    assert!(e.to_string().contains("match_scale"), "{e}");
    assert!(Preset::parse("huge").is_err());
    let e = Scene::from_json_str("{\"room\": {\"size\": [1, 1, 1], \"slab_thickness\": 0.1}, \"objects\": [{\"index\": 0, \"name\": \"x\", \"class_id\": 3, \"class_name\": \"cabinet\", \"room\": false, \"shape\": {\"kind\": \"ball\", \"radius\": -1}, \"translation\": [0, 0, 0], \"yaw\": 0, \"color\": [1, 2, 3], \"texture\": {\"kind\": \"plain\"}}]}").unwrap_err();
    assert!(e.to_string().contains("dimensions"), "{e}");
}

#[test]
fn crop_noise_makes_small_masks_noisier_than_large_ones() {
    // With crop noise, a mask of a pixels gets noise feature_noise · sqrt(crop / a): the
    // cosine to the own class prototype falls for small masks and not for large ones.
    let mean_cos = |crop: f64| -> (f64, f64) {
        let mut c = small(3);
        c.faults = FaultModel {
            feature_noise: 0.5,
            p_wrong_class: 0.0,
            crop_noise_px: crop,
            ..FaultModel::exact()
        };
        let (dir, _) = gen(&c);
        let masks = Masks::read(dir.path().join("masks.safetensors")).unwrap();
        let gt: serde_json::Value = serde_json::from_slice(
            &std::fs::read(dir.path().join("gt/mask_objects.json")).unwrap(),
        )
        .unwrap();
        let scene = Scene::from_json(dir.path().join("gt/scene.json")).unwrap();
        let (mut small_sum, mut small_n, mut big_sum, mut big_n) = (0.0, 0, 0.0, 0);
        for (m, e) in gt["masks"].as_array().unwrap().iter().enumerate() {
            let (Some(px), Some(cls)) = (e["pixels"].as_u64(), e["feature_class"].as_u64()) else {
                continue;
            };
            let Some(cname) = scene
                .objects
                .iter()
                .find(|o| u64::from(o.class_id) == cls)
                .map(|o| o.class_name.clone())
            else {
                continue;
            };
            let p = prototype(3, 64, &cname);
            let f: Vec<f64> = (0..64)
                .map(|k| f64::from(masks.features.get(m * 64 + k)))
                .collect();
            let cos = dot(&f, &p);
            if px < 400 {
                small_sum += cos;
                small_n += 1;
            } else if px > 3000 {
                big_sum += cos;
                big_n += 1;
            }
        }
        assert!(small_n > 3 && big_n > 3, "{small_n} {big_n}");
        (small_sum / f64::from(small_n), big_sum / f64::from(big_n))
    };
    let (small_off, big_off) = mean_cos(0.0);
    let (small_on, big_on) = mean_cos(6000.0);
    // Without crop noise size does not matter; with it small crops lose most of their signal.
    assert!((small_off - big_off).abs() < 0.1, "{small_off} {big_off}");
    assert!(small_on < small_off - 0.2, "{small_on} vs {small_off}");
    assert!((big_on - big_off).abs() < 0.1, "{big_on} vs {big_off}");
}

//! End-to-end tests of the `query` tool on tiny synthetic scenes whose ground-truth
//! Gaussians carry their class prototype as descriptor (an ideal registration).

use std::collections::BTreeMap;
use std::ffi::{OsStr, OsString};
use std::path::{Path, PathBuf};
use std::process::Output;

use super::files;
use profuse_formats::{
    Features, FileKind, Floats, Gaussians, Prompts, Selection, ViewMaps, NO_OBJECT,
};

fn query(args: &[&OsStr]) -> Output {
    super::run_tool(env!("CARGO_BIN_EXE_query"), args)
}

/// `synth --preset tiny` at `width` x 3/4 `width` with `gaussians` ground-truth Gaussians,
/// plus `features.safetensors` (each Gaussian's class prototype) and, with `pq`, its
/// product quantisation `pq.safetensors` (the prototypes slightly perturbed so that
/// k-means has distinct points).
fn scene(dir: &Path, seed: u64, width: u32, gaussians: usize, pq: bool) -> PathBuf {
    let root = dir.join("scene");
    let out = super::run_tool(
        env!("CARGO_BIN_EXE_synth"),
        &[
            "--preset".as_ref(),
            "tiny".as_ref(),
            "--seed".as_ref(),
            seed.to_string().as_ref(),
            "--width".as_ref(),
            width.to_string().as_ref(),
            "--height".as_ref(),
            (width * 3 / 4).to_string().as_ref(),
            "--gaussians".as_ref(),
            gaussians.to_string().as_ref(),
            "--no-matches".as_ref(),
            "--quiet".as_ref(),
            "--out".as_ref(),
            root.as_os_str(),
        ],
    );
    super::assert_succeeded(&out);
    let g = Gaussians::read(root.join("gt/gaussians.safetensors")).unwrap();
    let p = Prompts::read(root.join("prompts.safetensors")).unwrap();
    let features = class_features(&g, &p, seed, if pq { 0.2 } else { 0.0 });
    features.write(root.join("features.safetensors")).unwrap();
    if pq {
        let params = profuse_pq::TrainParams {
            m: 16,
            iters: 10,
            ..Default::default()
        };
        profuse_pq::train(&features, &params)
            .unwrap()
            .encode_features(&features)
            .unwrap()
            .write(root.join("pq.safetensors"))
            .unwrap();
    }
    root
}

/// Gaussian g's descriptor = normalize(prototype of its class + noise · u_g / sqrt(D)),
/// u_g a fixed pseudo-random vector of entries in [-1, 1]; invalid without a class.
fn class_features(g: &Gaussians, p: &Prompts, seed: u64, noise: f32) -> Features {
    let classes = p.class_ids.as_ref().unwrap();
    let protos: BTreeMap<i32, Vec<f64>> = (0..p.len())
        .filter(|&i| classes[i] >= 0)
        .map(|i| (classes[i], synth::prototype(seed, p.dim, &p.names[i])))
        .collect();
    let d = p.dim;
    let mut rows = vec![0f32; g.len() * d];
    let mut valid = vec![0u8; g.len()];
    for (i, c) in g.class_ids.as_ref().unwrap().iter().enumerate() {
        let Some(proto) = protos.get(c) else { continue };
        let mut h = (i as u64 + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        let row: Vec<f64> = proto
            .iter()
            .map(|x| {
                h ^= h >> 29;
                h = h.wrapping_mul(0xbf58_476d_1ce4_e5b9);
                let u = (h >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0;
                x + f64::from(noise) * u / (d as f64).sqrt()
            })
            .collect();
        let n = row.iter().map(|x| x * x).sum::<f64>().sqrt();
        for (o, x) in rows[i * d..(i + 1) * d].iter_mut().zip(&row) {
            *o = (x / n) as f32;
        }
        valid[i] = 1;
    }
    Features {
        dim: d,
        features: Floats::F32(rows.into()),
        valid: valid.into(),
        weight_sum: None,
        extra: Default::default(),
    }
}

fn base_args(root: &Path, descriptors: &str) -> Vec<OsString> {
    let mut v: Vec<OsString> = vec!["run".into()];
    for (flag, file) in [
        ("--gaussians", "gt/gaussians.safetensors"),
        ("--cameras", "cameras.safetensors"),
        (
            descriptors,
            if descriptors == "--pq" {
                "pq.safetensors"
            } else {
                "features.safetensors"
            },
        ),
        ("--prompts", "prompts.safetensors"),
    ] {
        v.push(flag.into());
        v.push(root.join(file).into());
    }
    v
}

fn run(args: Vec<OsString>, extra: &[&str], out: &Path) -> Output {
    let mut all = args;
    all.extend(extra.iter().map(OsString::from));
    all.push("--out".into());
    all.push(out.into());
    all.push("--quiet".into());
    let refs: Vec<&OsStr> = all.iter().map(|s| s.as_os_str()).collect();
    query(&refs)
}

/// Every class prompt selects exactly its class's Gaussians, and the masks match the
/// ground-truth object-id maps (pooled IoU over classes and views).
#[test]
fn query_run_selects_each_class_and_masks_match_the_ground_truth() {
    let dir = tempfile::tempdir().unwrap();
    let root = scene(dir.path(), 2, 192, 25_000, false);
    let out_dir = dir.path().join("out");
    let out = run(
        base_args(&root, "--features"),
        &["--all-classes", "--threshold", "0.6"],
        &out_dir,
    );
    super::assert_succeeded(&out);
    let report = super::json(&out);
    let g = Gaussians::read(root.join("gt/gaussians.safetensors")).unwrap();
    let p = Prompts::read(root.join("prompts.safetensors")).unwrap();
    let gt_class = g.class_ids.as_ref().unwrap();
    let prompt_class = p.class_ids.as_ref().unwrap();
    let views = ViewMaps::read(root.join("gt/views.safetensors")).unwrap();
    let ids = views.object_ids.as_ref().unwrap();
    let objects = synth::Scene::from_json(root.join("gt/scene.json"))
        .unwrap()
        .objects;
    let entries = report["prompts"].as_array().unwrap();
    assert_eq!(
        entries.len(),
        prompt_class.iter().filter(|c| **c >= 0).count()
    );
    assert_eq!(report["views"].as_array().unwrap().len(), 4);
    let (mut inter, mut union) = (0u64, 0u64);
    for e in entries {
        let name = e["prompt"].as_str().unwrap();
        let class = prompt_class[p.index_of(name).unwrap()];
        let want = gt_class.iter().filter(|c| **c == class).count();
        assert_eq!(e["selected"], want, "{name}");
        assert_eq!(e["views_written"], 4);
        assert_eq!(e["threshold"], 0.6);
        let sel = Selection::read(out_dir.join(name).join("selection.safetensors")).unwrap();
        assert_eq!(sel.gaussian_ids.len(), want);
        assert!(sel
            .gaussian_ids
            .iter()
            .all(|&i| gt_class[i as usize] == class));
        for v in 0..4 {
            let png = out_dir.join(name).join(format!("masks/frame_{v:05}.png"));
            let mask = image::open(&png).unwrap().into_luma8();
            assert_eq!(mask.dimensions(), (192, 144));
            assert!(out_dir
                .join(name)
                .join(format!("overlay/frame_{v:05}.png"))
                .exists());
            for (x, y, px) in mask.enumerate_pixels() {
                assert!(px[0] == 0 || px[0] == 255);
                let o = ids[views.index(v, x as usize, y as usize)];
                let truth = o != NO_OBJECT && objects[o as usize].class_id as i32 == class;
                let pred = px[0] == 255;
                inter += u64::from(truth && pred);
                union += u64::from(truth || pred);
            }
        }
    }
    // Measured 0.92 (see crates/query/tests for the per-class numbers).
    let iou = inter as f64 / union as f64;
    assert!(iou > 0.9, "pooled IoU {iou}");
}

/// Several prompts in one run (one render per view) write the same bytes as one run per
/// prompt, the output does not change between runs, and the LERF layout with the label
/// frames writes `OUT/<frame>/<prompt>.png` for the evaluation frames only.
#[test]
fn query_run_shares_the_render_across_prompts_and_is_deterministic() {
    let dir = tempfile::tempdir().unwrap();
    let root = scene(dir.path(), 4, 64, 3000, false);
    let args = || base_args(&root, "--features");
    let both = dir.path().join("both");
    let extra = [
        "--score",
        "relevancy",
        "--prompt",
        "wall",
        "--prompt",
        "floor",
    ];
    super::assert_succeeded(&run(args(), &extra, &both));
    let mut separate = BTreeMap::new();
    for name in ["wall", "floor"] {
        let d = dir.path().join(format!("only_{name}"));
        let out = run(args(), &["--score", "relevancy", "--prompt", name], &d);
        super::assert_succeeded(&out);
        assert_eq!(super::json(&out)["rule"], "threshold=0.5");
        separate.extend(files(&d));
    }
    let together = files(&both);
    assert_eq!(together.len(), 2 * (1 + 4 + 4));
    assert_eq!(together, separate);
    let again = dir.path().join("again");
    super::assert_succeeded(&run(args(), &extra, &again));
    assert_eq!(files(&again), together);

    let lerf = dir.path().join("lerf");
    let labels = root.join("gt/label");
    let out = run(
        args(),
        &[
            "--prompt",
            "wall",
            "--top-frac",
            "0.25",
            "--layout",
            "lerf",
            "--no-overlay",
            "--views-from-labels",
            labels.to_str().unwrap(),
        ],
        &lerf,
    );
    super::assert_succeeded(&out);
    let names: Vec<PathBuf> = files(&lerf).into_keys().collect();
    let want: Vec<PathBuf> = [
        "frame_00000/wall.png",
        "frame_00002/wall.png",
        "selection/wall.safetensors",
    ]
    .iter()
    .map(PathBuf::from)
    .collect();
    assert_eq!(names, want);
    let report = super::json(&out);
    let valid = Features::read(root.join("features.safetensors"))
        .unwrap()
        .valid
        .iter()
        .filter(|v| **v == 1)
        .count();
    assert_eq!(
        report["prompts"][0]["selected"],
        (valid as f64 * 0.25 - 1e-9).ceil() as u64
    );
}

/// `query scores` with PQ codes lists the best Gaussians by the ADC shortlist re-ranked
/// with the decoded descriptors, all of the prompt's class, and writes every score; and
/// `query run --pq` selects what `--features` selects.
#[test]
fn query_scores_and_run_with_pq_codes() {
    let dir = tempfile::tempdir().unwrap();
    let root = scene(dir.path(), 6, 64, 3000, true);
    let scores_dir = dir.path().join("scores");
    let args: Vec<OsString> = vec![
        "scores".into(),
        "--pq".into(),
        root.join("pq.safetensors").into(),
        "--prompts".into(),
        root.join("prompts.safetensors").into(),
        "--prompt".into(),
        "wall".into(),
        "--top".into(),
        "5".into(),
        "--out-dir".into(),
        scores_dir.clone().into(),
    ];
    let refs: Vec<&OsStr> = args.iter().map(|s| s.as_os_str()).collect();
    let out = query(&refs);
    super::assert_succeeded(&out);
    let j = super::json(&out);
    assert_eq!(j["top_method"], "adc_shortlist_exact_rerank");
    let g = Gaussians::read(root.join("gt/gaussians.safetensors")).unwrap();
    let gt_class = g.class_ids.as_ref().unwrap();
    let p = Prompts::read(root.join("prompts.safetensors")).unwrap();
    let wall = p.class_ids.as_ref().unwrap()[p.index_of("wall").unwrap()];
    let top = j["prompts"][0]["top"].as_array().unwrap();
    assert_eq!(top.len(), 5);
    for t in top {
        assert_eq!(gt_class[t[0].as_u64().unwrap() as usize], wall);
        assert!(t[1].as_f64().unwrap() > 0.9);
    }
    let all = Selection::read(scores_dir.join("wall.safetensors")).unwrap();
    assert_eq!(
        all.gaussian_ids.len(),
        j["prompts"][0]["valid"].as_u64().unwrap() as usize
    );
    assert!(j["prompts"][0]["max"].as_f64().unwrap() >= t_max(top));

    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let extra = ["--all-classes", "--threshold", "0.6", "--views", "1,3"];
    let ra = run(base_args(&root, "--features"), &extra, &a);
    let rb = run(base_args(&root, "--pq"), &extra, &b);
    super::assert_succeeded(&ra);
    super::assert_succeeded(&rb);
    let (ja, jb) = (super::json(&ra), super::json(&rb));
    for (x, y) in ja["prompts"]
        .as_array()
        .unwrap()
        .iter()
        .zip(jb["prompts"].as_array().unwrap())
    {
        assert_eq!(x["selected"], y["selected"], "{}", x["prompt"]);
    }
    let masks = |d: &Path| -> BTreeMap<PathBuf, Vec<u8>> {
        files(d)
            .into_iter()
            .filter(|(k, _)| k.to_string_lossy().contains("/masks/"))
            .collect()
    };
    assert_eq!(masks(&a), masks(&b));
    assert_eq!(masks(&a).len(), ja["prompts"].as_array().unwrap().len() * 2);
}

fn t_max(top: &[serde_json::Value]) -> f64 {
    top.iter()
        .map(|t| t[1].as_f64().unwrap())
        .fold(f64::MIN, f64::max)
        - 1e-6
}

/// Bad input exits 1 with the offending file named on stderr and writes nothing.
#[test]
fn query_bad_input_exits_1_naming_the_file_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let root = scene(dir.path(), 3, 64, 1000, false);
    // Descriptors of another Gaussian set (10 rows).
    let f = Features::read(root.join("features.safetensors")).unwrap();
    let d = f.dim;
    let rows: Vec<f32> = (0..10 * d).map(|i| f.features.get(i)).collect();
    let short = Features {
        features: Floats::F32(rows.into()),
        valid: f.valid[..10].to_vec().into(),
        ..f
    };
    let bad = root.join("short_features.safetensors");
    short.write(&bad).unwrap();
    let out_dir = dir.path().join("out");
    let mut args = base_args(&root, "--features");
    args[6] = bad.into();
    let out = run(args, &["--prompt", "wall", "--threshold", "0.5"], &out_dir);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("short_features.safetensors") && err.contains("gaussians.safetensors"),
        "{err}"
    );
    assert!(out.stdout.is_empty());
    assert!(!out_dir.exists(), "something was written");

    // An unknown prompt, and cosine without a threshold: the same.
    for extra in [
        &["--prompt", "piano", "--threshold", "0.5"][..],
        &["--prompt", "wall"][..],
    ] {
        let out = run(base_args(&root, "--features"), extra, &out_dir);
        assert_eq!(out.status.code(), Some(1), "{extra:?}");
        assert!(!out_dir.exists(), "{extra:?}: something was written");
    }
    let out = run(
        base_args(&root, "--features"),
        &["--prompt", "piano", "--threshold", "0.5"],
        &out_dir,
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("prompts.safetensors") && err.contains("piano"),
        "{err}"
    );
}

/// Issue 20 item 11: a query that fails midway (a full disk; here a file-size limit that
/// the overlays exceed) leaves the earlier output exactly as it was and no temporary
/// directory. The old code wrote into `--out` directly and had already replaced the
/// masks of the new run when the overlay failed.
#[test]
fn a_query_failing_midway_leaves_the_earlier_output_whole() {
    let dir = tempfile::tempdir().unwrap();
    let root = scene(dir.path(), 2, 192, 3000, false);
    let out_dir = dir.path().join("out");
    let first = run(
        base_args(&root, "--features"),
        &["--all-classes", "--threshold", "0.6"],
        &out_dir,
    );
    super::assert_succeeded(&first);
    let before = files(&out_dir);
    let size = |overlay: bool| {
        before
            .iter()
            .filter(|(p, _)| p.components().any(|c| c.as_os_str() == "overlay") == overlay)
            .map(|(_, b)| b.len() as u64)
            .max()
            .unwrap()
    };
    let (small, big) = (size(false), size(true));
    let limit_kb = small * 2 / 1024 + 1;
    assert!(limit_kb * 1024 < big, "no gap: {small} vs {big} bytes");

    // Another threshold and γ: selection files (written first; the threshold is in their
    // metadata) and masks with other bytes; the overlays then fail.
    let mut args = base_args(&root, "--features");
    for a in [
        "--all-classes",
        "--threshold",
        "0.55",
        "--gamma",
        "0.05",
        "--quiet",
        "--out",
    ] {
        args.push(a.into());
    }
    args.push(out_dir.clone().into());
    let refs: Vec<&OsStr> = args.iter().map(|s| s.as_os_str()).collect();
    // Without the limit that run writes other masks (so writing in place would show).
    let free = dir.path().join("free");
    let mut free_refs = refs.clone();
    *free_refs.last_mut().unwrap() = free.as_os_str();
    super::assert_succeeded(&query(&free_refs));
    let changed = files(&free);
    let differs = |p: &Path| changed[p] != before[p];
    assert!(differs(Path::new("wall/selection.safetensors")));
    assert!(changed
        .keys()
        .any(|p| p.starts_with("wall/masks") && differs(p)));
    std::fs::remove_dir_all(&free).unwrap();
    let failed = super::run_tool_with_file_limit(limit_kb, env!("CARGO_BIN_EXE_query"), &refs);
    assert!(!failed.status.success(), "the limit did not bite");
    assert!(
        String::from_utf8_lossy(&failed.stderr).contains("File too large"),
        "{}",
        String::from_utf8_lossy(&failed.stderr)
    );
    assert!(files(&out_dir) == before, "the earlier output changed");
    let mut names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names, ["out", "scene"]);
}

/// `query run --click` by mask with `--export-ply`: the clicked mask's selection, its
/// files, and the PLY (read back by scene-io) holding exactly the selected Gaussians; a
/// click outside the image exits 1 naming the view and writes nothing.
#[test]
fn query_click_selects_and_exports_a_ply() {
    let dir = tempfile::tempdir().unwrap();
    let root = scene(dir.path(), 2, 96, 8000, false);
    // Synth's mask features are class prototypes, as are the test's descriptors.
    let masks = profuse_formats::Masks::read(root.join("masks.safetensors")).unwrap();
    let cams = profuse_formats::Cameras::read(root.join("cameras.safetensors")).unwrap();
    let [w, h] = cams.image_size[0];
    let (cx, cy) = (0..masks.height)
        .flat_map(|y| (0..masks.width).map(move |x| (x, y)))
        .find(|&(x, y)| masks.mask_at(0, x, y).is_some() && x > 4 && y > 4)
        .unwrap();
    let x = (cx as f64 + 0.5) * f64::from(w) / masks.width as f64;
    let y = (cy as f64 + 0.5) * f64::from(h) / masks.height as f64;
    let mut args = base_args(&root, "--features");
    args.truncate(7); // no --prompts: a click needs none
    let ply = dir.path().join("sel.ply");
    let out_dir = dir.path().join("out");
    let click = [
        "--click".to_string(),
        "0".into(),
        x.to_string(),
        y.to_string(),
    ];
    let masks_path = root
        .join("masks.safetensors")
        .to_string_lossy()
        .into_owned();
    let ply_arg = ply.to_string_lossy().into_owned();
    let mut extra: Vec<&str> = click.iter().map(String::as_str).collect();
    extra.extend([
        "--masks",
        &masks_path,
        "--click-by",
        "mask",
        "--threshold",
        "0.7",
        "--export-ply",
        &ply_arg,
    ]);
    let out = run(args.clone(), &extra, &out_dir);
    super::assert_succeeded(&out);
    let report = super::json(&out);
    let name = format!("click_v0_x{x}_y{y}");
    assert_eq!(report["prompts"][0]["prompt"], name.as_str());
    assert_eq!(report["click"]["source"], "mask");
    let sel = Selection::read(out_dir.join(&name).join("selection.safetensors")).unwrap();
    assert!(!sel.gaussian_ids.is_empty());
    assert_eq!(sel.extra["click_by"], "mask");
    assert!(out_dir.join(&name).join("masks/frame_00001.png").is_file());
    let (back, _) = scene_io::ply::read_inria_ply(&ply).unwrap();
    let g = Gaussians::read(root.join("gt/gaussians.safetensors")).unwrap();
    assert_eq!(back.len(), sel.gaussian_ids.len());
    for (k, &i) in sel.gaussian_ids.iter().enumerate() {
        assert_eq!(back.means[k], g.means[i as usize]);
    }
    assert_eq!(report["export_ply"]["gaussians"], sel.gaussian_ids.len());

    // Outside the image: exit 1, the view named, nothing written.
    let out_dir = dir.path().join("out2");
    let outside = w.to_string();
    let mut extra = vec!["--click", "0", &outside, "1", "--masks", &masks_path];
    extra.extend(["--click-by", "mask", "--threshold", "0.7"]);
    let out = run(args, &extra, &out_dir);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("outside view 0's image"), "{err}");
    assert!(!out_dir.exists());
}

//! End-to-end tests of the `vertex-transfer` tool: small hand-made files through `run`
//! (features, PQ codes, named classes), a bad input that must exit 1 naming the file and
//! write nothing, and `bench` on the real ScanNet scene (skipped when absent).

use std::ffi::OsStr;
use std::path::{Path, PathBuf};

use profuse_formats::{Features, FileKind, Gaussians, Mesh, Prompts, VertexLabels};

fn tool(args: &[&OsStr]) -> std::process::Output {
    super::run_tool(env!("CARGO_BIN_EXE_vertex-transfer"), args)
}

/// Three Gaussians on the x axis (chair, table, chair; the third invalid), a chair/table
/// prompt pair plus a distractor, four mesh vertices (one far from everything).
/// Returns (gaussians, features, prompts, mesh) paths.
fn small_scene(dir: &Path) -> [PathBuf; 4] {
    let n = 3;
    let g = Gaussians {
        means: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]].into(),
        log_scales: vec![[0.2f32.ln(); 3]; n].into(),
        rotations: vec![[1.0, 0.0, 0.0, 0.0]; n].into(),
        opacity_logits: vec![2.0; n].into(),
        sh_dc: vec![[0.0; 3]; n].into(),
        ..Default::default()
    };
    // 4-d descriptors so that PQ with M = 2, dsub = 2 can encode them.
    let f = Features {
        features: vec![
            1.0f32, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
        ]
        .into(),
        dim: 4,
        valid: vec![1u8, 1, 0].into(),
        weight_sum: None,
        extra: Default::default(),
    };
    let p = Prompts {
        names: vec!["chair".into(), "table".into(), "object".into()],
        dim: 4,
        embeddings: vec![1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.5, 0.5, 0.5, 0.5].into(),
        class_ids: Some(vec![5, 7, -1].into()),
        ..Default::default()
    };
    let mesh = Mesh {
        vertices: vec![[0.1, 0.0, 0.0], [0.95, 0.1, 0.0], [2.0, 0.0, 0.0], [9.0; 3]].into(),
        extra: [("label_space".to_string(), "nyu40".to_string())].into(),
        ..Default::default()
    };
    let paths =
        ["gaussians", "features", "prompts", "mesh"].map(|s| dir.join(format!("{s}.safetensors")));
    g.write(&paths[0]).unwrap();
    f.write(&paths[1]).unwrap();
    p.write(&paths[2]).unwrap();
    mesh.write(&paths[3]).unwrap();
    paths
}

fn run_args<'a>(
    paths: &'a [PathBuf; 4],
    descriptor_flag: &'a str,
    descriptors: &'a Path,
    out: &'a Path,
) -> Vec<&'a OsStr> {
    vec![
        "run".as_ref(),
        "--gaussians".as_ref(),
        paths[0].as_os_str(),
        descriptor_flag.as_ref(),
        descriptors.as_os_str(),
        "--prompts".as_ref(),
        paths[2].as_os_str(),
        "--mesh".as_ref(),
        paths[3].as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]
}

#[test]
fn run_labels_a_small_mesh_from_features_and_writes_a_valid_file() {
    let dir = tempfile::tempdir().unwrap();
    let paths = small_scene(dir.path());
    let out = dir.path().join("labels.safetensors");
    let mut args = run_args(&paths, "--features", &paths[1], &out);
    args.push("--quiet".as_ref());
    let o = tool(&args);
    super::assert_succeeded(&o);
    assert!(
        o.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let j = super::json(&o);
    assert_eq!(j["vertices"], 4);
    assert_eq!(j["labelled"], 2);
    assert_eq!(j["valid_gaussians"], 2);
    assert_eq!(j["class_labels"], serde_json::json!([5, 7]));
    assert_eq!(j["label_space"], "nyu40");
    assert!(j["seconds"].as_f64().unwrap() >= 0.0);
    let labels = VertexLabels::read(&out).unwrap();
    // The third Gaussian is invalid: the vertex on it has no candidate.
    assert_eq!(labels.labels.to_vec(), vec![5, 7, -1, -1]);
    assert!(labels.confidence.unwrap()[0] > 0.99);
    assert!(labels.extra["generator"].starts_with("vertex-transfer"));

    // `profuse inspect` agrees that the output is a valid vertex_labels file.
    let j = super::json(&super::profuse(&["inspect", out.to_str().unwrap()]));
    assert_eq!(
        (j["valid"].clone(), j["counts"]["labelled"].clone()),
        (true.into(), 2.into())
    );
}

#[test]
fn run_from_pq_codes_and_with_named_classes() {
    let dir = tempfile::tempdir().unwrap();
    let paths = small_scene(dir.path());
    let features = Features::read(&paths[1]).unwrap();
    // A hand-made codebook (M = 2, dsub = 2): sub-quantiser 0 has the centroids (1, 0) and
    // (0, 1) at codes 1 and 2, everything else is zero; it encodes these features exactly.
    let mut centroids = vec![0.0f32; 2 * profuse_pq::KSUB * 2];
    centroids[2..4].copy_from_slice(&[1.0, 0.0]);
    centroids[4..6].copy_from_slice(&[0.0, 1.0]);
    let pq = profuse_pq::Codebook::new(2, 2, centroids)
        .unwrap()
        .encode_features(&features)
        .unwrap();
    assert_eq!(pq.codes.to_vec(), vec![1, 0, 2, 0, 0, 0]);
    let pq_path = dir.path().join("pq.safetensors");
    pq.write(&pq_path).unwrap();
    let out = dir.path().join("from_pq.safetensors");
    let o = tool(&run_args(&paths, "--pq", &pq_path, &out));
    super::assert_succeeded(&o);
    assert_eq!(super::json(&o)["labelled"], 2);
    assert_eq!(
        VertexLabels::read(&out).unwrap().labels.to_vec(),
        vec![5, 7, -1, -1]
    );

    // Only "table" as a class: every covered vertex becomes a table.
    let mut args = run_args(&paths, "--features", &paths[1], &out);
    args.extend(["--classes", "table", "--sigma", "3"].map(OsStr::new));
    let o = tool(&args);
    super::assert_succeeded(&o);
    assert_eq!(super::json(&o)["class_labels"], serde_json::json!([7]));
    assert_eq!(
        VertexLabels::read(&out).unwrap().labels.to_vec(),
        vec![7, 7, -1, -1]
    );
}

#[test]
fn a_bad_input_exits_1_names_the_file_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let paths = small_scene(dir.path());
    // Features with two rows for three Gaussians.
    let bad = dir.path().join("short_features.safetensors");
    Features {
        features: vec![1.0f32, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0].into(),
        dim: 4,
        valid: vec![1u8, 1].into(),
        weight_sum: None,
        extra: Default::default(),
    }
    .write(&bad)
    .unwrap();
    let before = std::fs::read_dir(dir.path()).unwrap().count();
    let out = dir.path().join("labels.safetensors");
    let o = tool(&run_args(&paths, "--features", &bad, &out));
    assert_eq!(o.status.code(), Some(1));
    assert!(o.stdout.is_empty());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("short_features.safetensors") && err.contains("one per Gaussian"),
        "{err}"
    );
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        before,
        "something was written"
    );

    // A features path that holds a mesh: the reader's error names the file.
    let o = tool(&run_args(&paths, "--features", &paths[3], &out));
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("mesh.safetensors"));
    assert!(!out.exists());
}

/// `bench` on the real ScanNet scene prints one JSON object with the throughput, the
/// exact-feature scores (100) and the noisy ones.
#[test]
fn bench_on_scannet_prints_scores_and_throughput() {
    let Some(dir) = super::shared_data("scannet/scene0000_00") else {
        return;
    };
    let o = tool(&[
        "bench".as_ref(),
        "--scannet".as_ref(),
        dir.as_os_str(),
        "--repeat".as_ref(),
        "1".as_ref(),
        "--quiet".as_ref(),
    ]);
    super::assert_succeeded(&o);
    let j = super::json(&o);
    assert_eq!(j["vertices"], 81_369);
    for set in ["19", "15", "10"] {
        assert_eq!(j[format!("miou{set}")], 100.0, "{j}");
        let noisy = j[format!("noisy_miou{set}")].as_f64().unwrap();
        assert!(noisy > 50.0 && noisy < 100.0, "{j}");
    }
    assert!(j["vertices_per_s"].as_f64().unwrap() > 0.0);
    assert!(j["peak_rss_mb"].as_f64().unwrap() > 0.0);
}

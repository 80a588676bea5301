//! End-to-end tests of the `fuse` tool.

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::Output;

use profuse_formats::{FileKind, Masks};

fn fuse(args: &[&OsStr]) -> Output {
    super::run_tool(env!("CARGO_BIN_EXE_fuse"), args)
}

/// A tiny synth scene with 3000 ground-truth Gaussians and proposals from its ground truth
/// (every object's masks form one proposal) written as `proposals.safetensors`.
fn tiny_scene(dir: &Path) -> PathBuf {
    let scene = dir.join("scene");
    let out = super::run_tool(
        env!("CARGO_BIN_EXE_synth"),
        &[
            "--preset".as_ref(),
            "tiny".as_ref(),
            "--seed".as_ref(),
            "2".as_ref(),
            "--gaussians".as_ref(),
            "3000".as_ref(),
            "--no-matches".as_ref(),
            "--quiet".as_ref(),
            "--out".as_ref(),
            scene.as_os_str(),
        ],
    );
    super::assert_succeeded(&out);
    let masks = Masks::read(scene.join("masks.safetensors")).unwrap();
    let proposals = profuse_fuse::testing::proposals_from_mask_objects(
        scene.join("gt/mask_objects.json"),
        &masks,
        1,
    )
    .unwrap();
    proposals
        .write(scene.join("proposals.safetensors"))
        .unwrap();
    scene
}

/// The input flags of a run on `scene`.
fn inputs(scene: &Path) -> Vec<PathBuf> {
    ["gaussians", "cameras", "masks", "proposals"]
        .iter()
        .flat_map(|kind| {
            let file = match *kind {
                "gaussians" => scene.join("gt/gaussians.safetensors"),
                k => scene.join(format!("{k}.safetensors")),
            };
            [PathBuf::from(format!("--{kind}")), file]
        })
        .collect()
}

fn run_args<'a>(inputs: &'a [PathBuf], extra: &[&'a OsStr]) -> Vec<&'a OsStr> {
    let mut args: Vec<&OsStr> = vec!["run".as_ref()];
    args.extend(inputs.iter().map(|p| p.as_os_str()));
    args.extend_from_slice(extra);
    args
}

/// `fuse run` registers most Gaussians and writes a valid features file; two view shards
/// merged by `fuse merge` give the same bytes; the thread count changes nothing.
#[test]
fn fuse_run_and_sharded_merge_give_identical_features() {
    let dir = tempfile::tempdir().unwrap();
    let scene = tiny_scene(dir.path());
    let ins = inputs(&scene);
    let whole = dir.path().join("whole.safetensors");
    let out = fuse(&run_args(
        &ins,
        &["--out".as_ref(), whole.as_os_str(), "--quiet".as_ref()],
    ));
    super::assert_succeeded(&out);
    let j = super::json(&out);
    assert_eq!(j["gaussians"], 3000);
    assert_eq!(j["views"], serde_json::json!([0, 4]));
    assert_eq!(j["grouping"], "proposals");
    let valid = j["valid"].as_u64().unwrap();
    assert!((2000..=3000).contains(&valid), "{j}");
    assert!(j["nnz"].as_u64().unwrap() >= valid, "{j}");
    assert!(j["mask_mass"]["total"].as_f64().unwrap() > 0.0, "{j}");
    assert!(
        out.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let inspect = super::json(&super::profuse(&["inspect", whole.to_str().unwrap()]));
    assert_eq!(inspect["valid"], true, "{inspect}");
    assert_eq!(inspect["kind"], "features");
    assert_eq!(inspect["counts"]["valid"].as_u64(), Some(valid));

    let parts: Vec<PathBuf> = (0..2)
        .map(|i| dir.path().join(format!("part{i}.partial")))
        .collect();
    for (range, part) in ["0..1", "1..4"].iter().zip(&parts) {
        let out = fuse(&run_args(
            &ins,
            &[
                "--views".as_ref(),
                range.as_ref(),
                "--partial-out".as_ref(),
                part.as_os_str(),
            ],
        ));
        super::assert_succeeded(&out);
    }
    let merged = dir.path().join("merged.safetensors");
    let out = fuse(&[
        "merge".as_ref(),
        parts[1].as_os_str(),
        parts[0].as_os_str(),
        "--out".as_ref(),
        merged.as_os_str(),
    ]);
    super::assert_succeeded(&out);
    assert_eq!(super::json(&out)["valid"].as_u64(), Some(valid));
    assert_eq!(
        std::fs::read(&merged).unwrap(),
        std::fs::read(&whole).unwrap(),
        "sharded + merged differs from the single run"
    );

    let one_thread = dir.path().join("t1.safetensors");
    let out = fuse(&run_args(
        &ins,
        &[
            "--out".as_ref(),
            one_thread.as_os_str(),
            "--threads".as_ref(),
            "1".as_ref(),
        ],
    ));
    super::assert_succeeded(&out);
    assert_eq!(
        std::fs::read(&one_thread).unwrap(),
        std::fs::read(&whole).unwrap()
    );
}

/// The baseline without proposals registers every mask's own feature.
#[test]
fn fuse_no_proposals_baseline() {
    let dir = tempfile::tempdir().unwrap();
    let scene = tiny_scene(dir.path());
    let ins = inputs(&scene);
    let out_file = dir.path().join("baseline.safetensors");
    let out = fuse(&run_args(
        &ins[..6],
        &[
            "--no-proposals".as_ref(),
            "--precision".as_ref(),
            "f32".as_ref(),
            "--out".as_ref(),
            out_file.as_os_str(),
        ],
    ));
    super::assert_succeeded(&out);
    let j = super::json(&out);
    let masks = Masks::read(scene.join("masks.safetensors")).unwrap();
    assert_eq!(j["grouping"], "masks");
    assert_eq!(j["groups"].as_u64(), Some(masks.num_masks() as u64));
    assert_eq!(j["precision"], "f32");
    assert!(j["valid"].as_u64().unwrap() > 2000, "{j}");
    let inspect = super::json(&super::profuse(&["inspect", out_file.to_str().unwrap()]));
    assert_eq!(inspect["tensors"]["features"]["dtype"], "F32", "{inspect}");
}

/// `--registration blend`: the features record grouping `blend`, view shards merged by
/// `fuse merge` give the single run's bytes, and it cannot be combined with
/// `--no-proposals`.
#[test]
fn fuse_blend_registration_shards_merge_to_the_single_run() {
    let dir = tempfile::tempdir().unwrap();
    let scene = tiny_scene(dir.path());
    let ins = inputs(&scene);
    let whole = dir.path().join("blend.safetensors");
    let blend: [&OsStr; 2] = ["--registration".as_ref(), "blend".as_ref()];
    let mut extra = blend.to_vec();
    extra.extend(["--out".as_ref(), whole.as_os_str()]);
    let out = fuse(&run_args(&ins, &extra));
    super::assert_succeeded(&out);
    let j = super::json(&out);
    let masks = Masks::read(scene.join("masks.safetensors")).unwrap();
    assert_eq!(j["grouping"], "blend");
    assert_eq!(j["groups"].as_u64(), Some(masks.num_masks() as u64));
    assert!(j["valid"].as_u64().unwrap() > 2000, "{j}");
    let inspect = super::json(&super::profuse(&["inspect", whole.to_str().unwrap()]));
    assert_eq!(inspect["valid"], true, "{inspect}");
    assert_eq!(inspect["metadata"]["grouping"], "blend", "{inspect}");

    let parts: Vec<PathBuf> = (0..2)
        .map(|i| dir.path().join(format!("blend{i}.partial")))
        .collect();
    for (range, part) in ["0..3", "3..4"].iter().zip(&parts) {
        let mut extra = blend.to_vec();
        extra.extend([
            "--views".as_ref(),
            range.as_ref(),
            "--partial-out".as_ref(),
            part.as_os_str(),
        ]);
        super::assert_succeeded(&fuse(&run_args(&ins, &extra)));
    }
    let merged = dir.path().join("merged.safetensors");
    let out = fuse(&[
        "merge".as_ref(),
        parts[1].as_os_str(),
        parts[0].as_os_str(),
        "--out".as_ref(),
        merged.as_os_str(),
    ]);
    super::assert_succeeded(&out);
    assert_eq!(
        std::fs::read(&merged).unwrap(),
        std::fs::read(&whole).unwrap(),
        "sharded + merged blend differs from the single run"
    );

    let mut extra = blend.to_vec();
    let never = dir.path().join("never.safetensors");
    extra.extend([
        "--no-proposals".as_ref(),
        "--out".as_ref(),
        never.as_os_str(),
    ]);
    let out = fuse(&run_args(&ins[..6], &extra));
    assert!(!out.status.success());
    assert!(!never.exists());
}

/// A corrupt input exits 1, names the file on stderr and writes nothing; so does a merge
/// whose partial files miss views.
#[test]
fn fuse_bad_input_exits_1_naming_the_file_and_writing_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let scene = tiny_scene(dir.path());
    let masks = scene.join("masks.safetensors");
    let bytes = std::fs::read(&masks).unwrap();
    let bad = dir.path().join("bad_masks.safetensors");
    std::fs::write(&bad, &bytes[..bytes.len() - 100]).unwrap();
    let mut ins = inputs(&scene);
    ins[5] = bad.clone();
    let out_dir = dir.path().join("out");
    std::fs::create_dir(&out_dir).unwrap();
    let target = out_dir.join("features.safetensors");
    let out = fuse(&run_args(&ins, &["--out".as_ref(), target.as_os_str()]));
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("bad_masks.safetensors"), "{err}");
    assert!(out.stdout.is_empty());
    assert_eq!(
        std::fs::read_dir(&out_dir).unwrap().count(),
        0,
        "something was written"
    );

    // A shard alone cannot be merged into features.
    let part = dir.path().join("p.partial");
    let out = fuse(&run_args(
        &inputs(&scene),
        &[
            "--views".as_ref(),
            "0..1".as_ref(),
            "--partial-out".as_ref(),
            part.as_os_str(),
        ],
    ));
    super::assert_succeeded(&out);
    let out = fuse(&[
        "merge".as_ref(),
        part.as_os_str(),
        "--out".as_ref(),
        target.as_os_str(),
    ]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("1..4"), "{err}");
    assert_eq!(std::fs::read_dir(&out_dir).unwrap().count(), 0);

    // A views range beyond the cameras.
    let out = fuse(&run_args(
        &inputs(&scene),
        &[
            "--views".as_ref(),
            "2..9".as_ref(),
            "--out".as_ref(),
            target.as_os_str(),
        ],
    ));
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("2..9"));
    assert_eq!(std::fs::read_dir(&out_dir).unwrap().count(), 0);
}

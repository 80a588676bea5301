//! End-to-end tests of the `warp-graph` tool: a tiny synthetic scene through `run` (with
//! and without Gaussians for depth visibility), byte-identical output for 1 and 4 threads,
//! and bad inputs that exit 1 naming the file and write nothing.

use std::ffi::OsStr;
use std::path::Path;
use std::process::{Command, Output};

use profuse_formats::{FileKind, Masks, Proposals};

fn synth(dir: &Path, extra: &[&str]) {
    let mut args: Vec<&OsStr> = vec![
        "--preset".as_ref(),
        "tiny".as_ref(),
        "--seed".as_ref(),
        "0".as_ref(),
        "--out".as_ref(),
        dir.as_os_str(),
        "--quiet".as_ref(),
    ];
    args.extend(extra.iter().map(OsStr::new));
    super::assert_succeeded(&super::run_tool(env!("CARGO_BIN_EXE_synth"), &args));
}

fn warp_graph(scene: &Path, out: &Path, extra: &[&str], threads: Option<&str>) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_warp-graph"));
    cmd.arg("run")
        .arg("--masks")
        .arg(scene.join("masks.safetensors"))
        .arg("--matches")
        .arg(scene.join("matches.safetensors"))
        .arg("--out")
        .arg(out)
        .args(extra)
        .current_dir(super::root());
    if let Some(t) = threads {
        cmd.env("RAYON_NUM_THREADS", t);
    }
    cmd.output().unwrap()
}

#[test]
fn run_on_a_tiny_synthetic_scene_writes_valid_proposals() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    synth(&scene, &["--gaussians", "3000"]);
    let out = dir.path().join("proposals.safetensors");
    let cams = scene.join("cameras.safetensors");
    let gauss = scene.join("gt/gaussians.safetensors");
    let geometry = [
        "--cameras",
        cams.to_str().unwrap(),
        "--gaussians",
        gauss.to_str().unwrap(),
        "--quiet",
        "--grouping",
        "links",
    ];
    // With cameras and Gaussians the default (auto) is the consensus grouping.
    let auto = dir.path().join("auto.safetensors");
    let o = warp_graph(&scene, &auto, &geometry[..5], None);
    super::assert_succeeded(&o);
    assert_eq!(super::json(&o)["grouping"], "consensus");
    let p = Proposals::read(&auto).unwrap();
    assert_eq!(
        p.extra.get("grouping").map(String::as_str),
        Some("consensus")
    );
    let o = warp_graph(&scene, &out, &geometry, None);
    super::assert_succeeded(&o);
    let r = super::json(&o);
    assert_eq!(r["views"], 4);
    assert_eq!(r["pairs"], 12);
    assert_eq!(r["view_pairs"], 6);
    assert_eq!(r["visibility"], "both");
    assert_eq!(r["sampling"], "bilinear");
    assert!(r["edges_accepted"].as_u64().unwrap() >= 4, "{r}");
    assert!(r["edges_tested"].as_u64() >= r["edges_accepted"].as_u64());
    let cells = &r["cells"];
    assert_eq!(
        cells["total"].as_u64().unwrap(),
        cells["low_certainty"].as_u64().unwrap()
            + cells["occluded"].as_u64().unwrap()
            + cells["gated"].as_u64().unwrap()
    );
    assert!(r["proposals"].as_u64().unwrap() >= 2, "{r}");
    assert_eq!(r["out"], out.to_str().unwrap());
    assert!(
        o.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );

    let masks = Masks::read(scene.join("masks.safetensors")).unwrap();
    let p = Proposals::read(&out).unwrap();
    p.check_against(&masks, "proposals").unwrap();
    assert_eq!(p.len() as u64, r["proposals"].as_u64().unwrap());
    assert_eq!(p.extra.get("visibility").map(String::as_str), Some("both"));
    assert_eq!(p.extra.get("tau_iou").map(String::as_str), Some("0.2"));
    // With the link grouping and Gaussians the masks are lifted to 3D and the extent rules
    // run (default on).
    assert_eq!(r["extents"], true, "{r}");
    assert_eq!(
        p.extra.get("extent_merge_iou").map(String::as_str),
        Some("0.1")
    );
    assert!(r["extent_merges"].is_u64() && r["extent_refused_links"].is_u64());
    // Both rules 0 = the same-view guard alone.
    let off = dir.path().join("off.safetensors");
    let extra: Vec<&str> = geometry
        .iter()
        .copied()
        .chain(["--extent-agreement", "0", "--extent-merge-iou", "0"])
        .collect();
    let o = warp_graph(&scene, &off, &extra, None);
    super::assert_succeeded(&o);
    let r = super::json(&o);
    assert_eq!(r["extents"], false, "{r}");
    assert_eq!(
        (
            r["extent_merges"].as_u64(),
            r["extent_refused_links"].as_u64()
        ),
        (Some(0), Some(0))
    );
    let p = Proposals::read(&off).unwrap();
    assert_eq!(
        p.extra.get("extent_agreement").map(String::as_str),
        Some("none")
    );
    // The extents are built view-parallel: same bytes with 1 and 4 threads.
    let (one, four) = (
        dir.path().join("g1.safetensors"),
        dir.path().join("g4.safetensors"),
    );
    for (path, t) in [(&one, "1"), (&four, "4")] {
        super::assert_succeeded(&warp_graph(&scene, path, &geometry, Some(t)));
    }
    assert_eq!(std::fs::read(&one).unwrap(), std::fs::read(&four).unwrap());

    // Same bytes with 1 and 4 threads; without Gaussians `auto` is fwd-bwd.
    let one = dir.path().join("one.safetensors");
    let four = dir.path().join("four.safetensors");
    for (path, t) in [(&one, "1"), (&four, "4")] {
        let o = warp_graph(&scene, path, &["--tau-alpha", "0.6", "--quiet"], Some(t));
        super::assert_succeeded(&o);
        assert_eq!(super::json(&o)["visibility"], "fwd-bwd");
    }
    assert_eq!(std::fs::read(&one).unwrap(), std::fs::read(&four).unwrap());
    let p = Proposals::read(&one).unwrap();
    assert_eq!(p.extra.get("tau_alpha").map(String::as_str), Some("0.6"));
}

#[test]
fn bad_inputs_exit_1_name_the_file_and_write_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    synth(&scene, &[]);
    let out = dir.path().join("proposals.safetensors");

    // A truncated masks file.
    let bad = dir.path().join("bad_masks.safetensors");
    let bytes = std::fs::read(scene.join("masks.safetensors")).unwrap();
    std::fs::write(&bad, &bytes[..bytes.len() / 2]).unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_warp-graph"))
        .args(["run", "--quiet", "--masks"])
        .arg(&bad)
        .arg("--matches")
        .arg(scene.join("matches.safetensors"))
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(o.stdout.is_empty());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("bad_masks.safetensors"), "{err}");
    assert!(!out.exists());

    // Matches of a 5-view scene against masks of 4 views.
    let other = dir.path().join("other");
    synth(&other, &["--views", "5"]);
    let o = Command::new(env!("CARGO_BIN_EXE_warp-graph"))
        .args(["run", "--masks"])
        .arg(scene.join("masks.safetensors"))
        .arg("--matches")
        .arg(other.join("matches.safetensors"))
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("other/matches.safetensors") && err.contains("num_views` is 5"),
        "{err}"
    );
    assert!(!out.exists());

    // Depth visibility without Gaussians is refused before anything is written.
    let o = warp_graph(&scene, &out, &["--visibility", "depth"], None);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--gaussians"));
    assert!(!out.exists());
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 3);
}

#[test]
fn bench_prints_throughput_and_memory() {
    let o = super::run_tool(
        env!("CARGO_BIN_EXE_warp-graph"),
        &[
            "bench".as_ref(),
            "--width".as_ref(),
            "120".as_ref(),
            "--height".as_ref(),
            "90".as_ref(),
            "--views".as_ref(),
            "3".as_ref(),
            "--masks-per-view".as_ref(),
            "10".as_ref(),
            "--quiet".as_ref(),
        ],
    );
    super::assert_succeeded(&o);
    let r = super::json(&o);
    assert_eq!(r["pairs"], 4);
    assert!(r["pairs_per_s"].as_f64().unwrap() > 0.0);
    assert!(r["peak_rss_mb"].as_f64().unwrap() > 0.0);
    assert!(r["ari"].as_f64().unwrap() > 0.9, "{r}");
}

/// `warp-graph warps`: dense warps from the Gaussians' depth, written as a matches file
/// that `warp-graph run` reads; 1 and 4 threads write the same bytes; a bad pair exits 1
/// and writes nothing.
#[test]
fn warps_from_depth_feed_run_and_are_deterministic() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene");
    synth(&scene, &["--gaussians", "3000", "--no-matches"]);
    let warps = |out: &Path, extra: &[&str], threads: &str| {
        Command::new(env!("CARGO_BIN_EXE_warp-graph"))
            .arg("warps")
            .arg("--gaussians")
            .arg(scene.join("gt/gaussians.safetensors"))
            .arg("--cameras")
            .arg(scene.join("cameras.safetensors"))
            .arg("--out")
            .arg(out)
            .args(extra)
            .arg("--quiet")
            .env("RAYON_NUM_THREADS", threads)
            .output()
            .unwrap()
    };
    let m1 = dir.path().join("m1.safetensors");
    let o = warps(&m1, &["--stride", "2", "--nearest", "2"], "1");
    super::assert_succeeded(&o);
    let report = super::json(&o);
    assert_eq!(report["grid"], serde_json::json!([32, 24]));
    assert!(report["kept"].as_u64().unwrap() > 0, "{report}");
    let m4 = dir.path().join("m4.safetensors");
    super::assert_succeeded(&warps(&m4, &["--stride", "2", "--nearest", "2"], "4"));
    assert_eq!(std::fs::read(&m1).unwrap(), std::fs::read(&m4).unwrap());
    // `prep warps` is the same command (issue 17's name for it).
    let via_prep = dir.path().join("prep.safetensors");
    let o = Command::new(env!("CARGO_BIN_EXE_prep"))
        .arg("warps")
        .arg("--gaussians")
        .arg(scene.join("gt/gaussians.safetensors"))
        .arg("--cameras")
        .arg(scene.join("cameras.safetensors"))
        .arg("--out")
        .arg(&via_prep)
        .args(["--stride", "2", "--nearest", "2", "--quiet"])
        .output()
        .unwrap();
    super::assert_succeeded(&o);
    assert_eq!(
        std::fs::read(&m1).unwrap(),
        std::fs::read(&via_prep).unwrap()
    );
    // The proposals from these warps.
    std::fs::copy(&m1, scene.join("matches.safetensors")).unwrap();
    let proposals = dir.path().join("p.safetensors");
    let cams = scene.join("cameras.safetensors");
    let gauss = scene.join("gt/gaussians.safetensors");
    let geometry = [
        "--cameras",
        cams.to_str().unwrap(),
        "--gaussians",
        gauss.to_str().unwrap(),
        "--quiet",
    ];
    super::assert_succeeded(&warp_graph(&scene, &proposals, &geometry, None));
    let p = Proposals::read(&proposals).unwrap();
    p.check_against(&Masks::read(scene.join("masks.safetensors")).unwrap(), "p")
        .unwrap();
    assert!(!p.is_empty());
    // A pair of a view with itself.
    let bad = dir.path().join("bad.safetensors");
    let o = warps(&bad, &["--pairs", "0-1,2-2"], "1");
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("gaussians.safetensors") && err.contains("row 1"),
        "{err}"
    );
    assert!(!bad.exists());
}

//! End-to-end tests of the accuracy harness (issue 16): `synth --faults` writes the
//! documented parameters, and `profuse sweep` rows equal separate `profuse demo` runs.

use std::path::Path;

use serde_json::Value;

use super::{assert_succeeded, json, run_tool};

fn synth(dir: &Path, extra: &[&str]) -> Value {
    let mut args: Vec<&std::ffi::OsStr> = vec![
        "--preset".as_ref(),
        "tiny".as_ref(),
        "--quiet".as_ref(),
        "--no-matches".as_ref(),
        "--out".as_ref(),
        dir.as_os_str(),
    ];
    args.extend(extra.iter().map(std::ffi::OsStr::new));
    let out = run_tool(env!("CARGO_BIN_EXE_synth"), &args);
    assert_succeeded(&out);
    json(&out)
}

/// The parameters gt/scene.json records.
fn parameters(dir: &Path) -> Value {
    let text = std::fs::read_to_string(dir.join("gt/scene.json")).unwrap();
    serde_json::from_str::<Value>(&text).unwrap()["parameters"].clone()
}

#[test]
fn synth_fault_sets_write_their_documented_parameters_and_flags_win() {
    let dir = tempfile::tempdir().unwrap();
    let plain = dir.path().join("plain");
    synth(&plain, &[]);
    let preset = parameters(&plain);
    // (set, [(path, value)]) on top of the preset; every other parameter unchanged.
    let default = [
        ("faults.feature_noise", 1.5),
        ("faults.p_wrong_class", 0.1),
        ("faults.crop_noise_px", 40000.0),
    ];
    let sets: [(&str, &[(&str, f64)]); 4] = [
        ("default", &[]),
        (
            "noisy-features",
            &[
                ("faults.feature_noise", 2.5),
                ("faults.p_wrong_class", 0.25),
            ],
        ),
        (
            "harsh-segmentation",
            &[("faults.p_split", 0.35), ("faults.p_merge", 0.3)],
        ),
        (
            "sparse-views",
            &[
                ("views", 12.0),
                ("warp_noise_px", 1.0),
                ("outlier_frac", 0.1),
            ],
        ),
    ];
    for (name, changes) in sets {
        let scene = dir.path().join(name);
        let summary = synth(&scene, &["--faults", name]);
        assert_eq!(summary["faults"], name);
        let mut expected = preset.clone();
        for (path, value) in default.iter().chain(changes) {
            let pointer = format!("/{}", path.replace('.', "/"));
            let slot = expected.pointer_mut(&pointer).unwrap();
            *slot = if slot.is_u64() {
                Value::from(*value as u64)
            } else {
                Value::from(*value)
            };
        }
        assert_eq!(parameters(&scene), expected, "{name}");
        if name == "sparse-views" {
            assert_eq!(summary["views"], 12);
        }
    }
    // Individual flags are applied after the set.
    let scene = dir.path().join("flags");
    synth(
        &scene,
        &[
            "--faults",
            "sparse-views",
            "--views",
            "6",
            "--feature-noise",
            "0.7",
        ],
    );
    let p = parameters(&scene);
    assert_eq!(
        (p["views"].clone(), p["warp_noise_px"].clone()),
        (6.into(), 1.0.into())
    );
    assert_eq!(p["faults"]["feature_noise"], 0.7);
    assert_eq!(p["faults"]["p_wrong_class"], 0.1);
    // Unknown names are rejected with the list of sets.
    let out = run_tool(
        env!("CARGO_BIN_EXE_synth"),
        &[
            "--faults".as_ref(),
            "noisy".as_ref(),
            "--out".as_ref(),
            dir.path().as_os_str(),
        ],
    );
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("harsh-segmentation"));
}

const ROW_KEYS: [&str; 15] = [
    "seed",
    "faults",
    "lerf_miou",
    "baseline_lerf_miou",
    "lerf_acc25",
    "baseline_lerf_acc25",
    "scannet_miou19",
    "baseline_scannet_miou19",
    "ari",
    "member_ari",
    "purity",
    "completeness",
    "wrong_class_pixel_share",
    "baseline_wrong_class_pixel_share",
    "seconds",
];

const MEAN_KEYS: [&str; 7] = [
    "mean_delta_lerf_miou",
    "min_delta_lerf_miou",
    "mean_delta_scannet_miou19",
    "mean_ari",
    "mean_member_ari",
    "mean_purity",
    "rows",
];

fn mean(rows: &[&Value], f: impl Fn(&Value) -> f64) -> f64 {
    rows.iter().map(|r| f(r)).sum::<f64>() / rows.len() as f64
}

fn close(a: &Value, b: f64) -> bool {
    (a.as_f64().unwrap() - b).abs() <= 1e-9 * b.abs().max(1.0)
}

fn check_means(m: &Value, rows: &[&Value]) {
    for k in MEAN_KEYS {
        assert!(m.get(k).is_some(), "summary lacks {k}: {m}");
    }
    let f = |k: &'static str| move |r: &Value| r[k].as_f64().unwrap();
    let delta = |a: &'static str, b: &'static str| {
        move |r: &Value| r[a].as_f64().unwrap() - r[b].as_f64().unwrap()
    };
    assert_eq!(m["rows"], rows.len());
    assert!(close(
        &m["mean_delta_lerf_miou"],
        mean(rows, delta("lerf_miou", "baseline_lerf_miou"))
    ));
    let min = rows
        .iter()
        .map(|r| delta("lerf_miou", "baseline_lerf_miou")(r))
        .fold(f64::INFINITY, f64::min);
    assert!(close(&m["min_delta_lerf_miou"], min));
    assert!(close(
        &m["mean_delta_scannet_miou19"],
        mean(rows, delta("scannet_miou19", "baseline_scannet_miou19"))
    ));
    assert!(close(&m["mean_ari"], mean(rows, f("ari"))));
    assert!(close(&m["mean_member_ari"], mean(rows, f("member_ari"))));
    assert!(close(&m["mean_purity"], mean(rows, f("purity"))));
}

/// 2 seeds x 2 fault sets on the tiny preset: every key, rows in (faults, seed) order,
/// each row equal to a separate `profuse demo` of the same scene (the one compared took
/// its Gaussians from an earlier row), means equal to the means of the rows.
#[test]
fn sweep_rows_equal_separate_demo_runs_and_the_summary_averages_them() {
    let dir = tempfile::tempdir().unwrap();
    let out = run_tool(
        env!("CARGO_BIN_EXE_profuse"),
        &[
            "sweep".as_ref(),
            "--seeds".as_ref(),
            "0,2".as_ref(),
            "--faults".as_ref(),
            "default,harsh-segmentation".as_ref(),
            "--preset".as_ref(),
            "tiny".as_ref(),
            "--set".as_ref(),
            "pq.m=16".as_ref(),
            "--json".as_ref(),
            "--out".as_ref(),
            dir.path().as_os_str(),
        ],
    );
    assert_succeeded(&out);
    // Not a terminal: no progress on stderr.
    assert!(
        out.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report = json(&out);
    let rows: Vec<&Value> = report["rows"].as_array().unwrap().iter().collect();
    let order: Vec<(u64, &str)> = rows
        .iter()
        .map(|r| (r["seed"].as_u64().unwrap(), r["faults"].as_str().unwrap()))
        .collect();
    assert_eq!(
        order,
        [
            (0, "default"),
            (2, "default"),
            (0, "harsh-segmentation"),
            (2, "harsh-segmentation")
        ]
    );
    // harsh-segmentation changes masks only: its rows take the default rows' Gaussians.
    let reused: Vec<bool> = rows
        .iter()
        .map(|r| r["geometry_reused"].as_bool().unwrap())
        .collect();
    assert_eq!(reused, [false, false, true, true]);
    for r in &rows {
        for k in ROW_KEYS {
            assert!(r.get(k).is_some_and(|v| !v.is_null()), "row lacks {k}: {r}");
        }
    }
    // Row directories are removed; the report is written next to them.
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(left, ["sweep.json"]);
    let mut written: Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("sweep.json")).unwrap()).unwrap();
    written["summary"]["seconds"] = report["summary"]["seconds"].clone();
    assert_eq!(written, report);

    let summary = &report["summary"];
    check_means(summary, &rows);
    assert!(summary["seconds"].as_f64().unwrap() > 0.0);
    for name in ["default", "harsh-segmentation"] {
        let of: Vec<&Value> = rows
            .iter()
            .copied()
            .filter(|r| r["faults"] == name)
            .collect();
        check_means(&summary["by_faults"][name], &of);
    }

    // The same experiment through `profuse demo`.
    let scene = dir.path().join("demo");
    let out = run_tool(
        env!("CARGO_BIN_EXE_profuse"),
        &[
            "demo".as_ref(),
            "--seed".as_ref(),
            "2".as_ref(),
            "--preset".as_ref(),
            "tiny".as_ref(),
            "--faults".as_ref(),
            "harsh-segmentation".as_ref(),
            "--set".as_ref(),
            "pq.m=16".as_ref(),
            "--json".as_ref(),
            "--out".as_ref(),
            scene.as_os_str(),
        ],
    );
    assert_succeeded(&out);
    let demo = json(&out);
    let row = rows[3];
    for k in ROW_KEYS {
        match k {
            "seconds" => {}
            "seed" | "faults" => assert_eq!(demo[k], row[k], "{k}"),
            _ => assert_eq!(demo[k], row[k], "{k}: demo {} vs sweep {}", demo[k], row[k]),
        }
    }
    assert_eq!(demo["proposals_ari"], row["ari"]);
}

#[test]
fn sweep_rejects_bad_lists_with_exit_code_1() {
    for (seeds, faults) in [("3-1", "default"), ("0", "noisy"), ("0,0", "default")] {
        let out = run_tool(
            env!("CARGO_BIN_EXE_profuse"),
            &[
                "sweep".as_ref(),
                "--seeds".as_ref(),
                seeds.as_ref(),
                "--faults".as_ref(),
                faults.as_ref(),
                "--quiet".as_ref(),
            ],
        );
        assert_eq!(out.status.code(), Some(1), "{seeds} {faults}");
        assert!(out.stdout.is_empty());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(seeds) || err.contains(faults), "{err}");
    }
}

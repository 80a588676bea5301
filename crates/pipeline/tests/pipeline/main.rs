//! The pipeline on the synthetic `tiny` scene: metric floors that a broken stage would
//! miss, and the up-to-date rules (skip, parameter change, newer input, lost record).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::Path;

use profuse_experiments::evaluate::evaluate;
use profuse_formats::FileKind;
use profuse_pipeline::config::Config;
use profuse_pipeline::{run, Paths, RunOptions, Summary};

mod prepare;

fn tiny_scene(dir: &Path) {
    synth::generate(&synth::Config::preset(synth::Preset::Tiny, 0), dir).unwrap();
}

fn tiny_config() -> Config {
    // tiny's descriptors are 64-d: 16 sub-quantisers of 4 dimensions, as the default 128 of 512.
    Config::default()
        .with_overrides(&["pq.m=16".into()])
        .unwrap()
}

/// An error and its sources, as the tools print them.
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut next = e.source();
    while let Some(cause) = next {
        text = format!("{text}: {cause}");
        next = cause.source();
    }
    text
}

fn ran(s: &Summary) -> Vec<(&str, bool)> {
    s.stages.iter().map(|l| (l.stage.as_str(), l.ran)).collect()
}

#[test]
fn tiny_run_meets_metric_floors() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let s = run(dir.path(), &tiny_config(), &RunOptions::default(), &|_| {}).unwrap();
    assert_eq!(
        ran(&s),
        vec![
            ("gs-init", true),
            ("warp-graph", true),
            ("fuse", true),
            ("pq", true),
            ("query", true),
            ("vertex-transfer", true)
        ]
    );
    let m = evaluate(&Paths::new(dir.path(), &s.out, false)).unwrap();
    let get = |k: &str| m[k].as_f64().unwrap();
    // Measured on tiny seed 0 (64x48 views) with the default consensus grouping and
    // singleton orphans: 6e-9, 0.47, 49.9, 71.4, 27.4 (the link grouping with ignored
    // orphans: ARI 0.70, LERF 34.3 / 57.1, ScanNet 19.4; four views give the consensus few
    // observers). The floors sit well below, and far above what any broken stage gives
    // (random descriptors select nothing: LERF mIoU ~0; missing proposals: ARI ~0; a
    // wrong triangulation: >1e-2).
    assert!(get("init_median_surface_dist_rel") < 1e-4, "{m:?}");
    assert!(get("proposals_ari") > 0.35, "{m:?}");
    assert!(get("lerf_miou") > 25.0, "{m:?}");
    assert!(get("lerf_acc25") > 40.0, "{m:?}");
    assert!(get("scannet_miou19") > 12.0, "{m:?}");
    // OpenGaussian's ScanNet protocol: one labelling per class set, with only that set's
    // ids, and each score recomputed here by brute force from its own file.
    let paths = Paths::new(dir.path(), &s.out, false);
    let truth = profuse_formats::Mesh::read(paths.mesh().unwrap())
        .unwrap()
        .labels
        .unwrap()
        .to_vec();
    for (set, file) in &paths.vertex_labels {
        let name = file.file_name().unwrap().to_string_lossy().into_owned();
        assert_eq!(name, format!("vertex_labels_nyu{}.safetensors", set.name()));
        let pred = profuse_formats::VertexLabels::read(file)
            .unwrap()
            .labels
            .to_vec();
        let ids: Vec<i32> = set.ids().iter().map(|&i| i as i32).collect();
        assert!(pred.iter().all(|l| *l == -1 || ids.contains(l)), "{name}");
        let mut ious = Vec::new();
        for &c in &ids {
            let (mut tp, mut fp, mut fn_) = (0u64, 0u64, 0u64);
            for (&p, &g) in pred.iter().zip(&truth) {
                let g = g as i32;
                if !ids.contains(&g) {
                    continue; // vertices outside the set are ignored
                }
                match (g == c, p == c) {
                    (true, true) => tp += 1,
                    (true, false) => fn_ += 1,
                    (false, true) => fp += 1,
                    _ => {}
                }
            }
            if tp + fn_ > 0 {
                ious.push(100.0 * tp as f64 / (tp + fp + fn_) as f64);
            }
        }
        let brute = ious.iter().sum::<f64>() / ious.len() as f64;
        let key = format!("scannet_miou{}", set.name());
        assert!(
            (get(&key) - brute).abs() < 1e-9,
            "{key}: {} vs {brute}",
            get(&key)
        );
    }
    for k in ["geometry", "semantics", "indexing", "total", "evaluation"] {
        assert!(s.timing_s.contains_key(k), "{k}");
    }
    let cfg = std::fs::read_to_string(s.out.join("config.toml")).unwrap();
    assert_eq!(
        Config::from_toml(&cfg, "config.toml").unwrap(),
        tiny_config()
    );
}

#[test]
fn up_to_date_stages_are_skipped_and_changes_rerun_exactly_what_depends_on_them() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let cfg = tiny_config();
    let opts = RunOptions::default();
    let first = run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    let features = std::fs::read(first.out.join("features.safetensors")).unwrap();

    let again = run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    assert!(again.stages.iter().all(|l| !l.ran), "{:?}", ran(&again));

    // A changed fuse parameter redoes fuse and what reads its output, not the geometry.
    let k5 = cfg.with_overrides(&["fuse.k=5".into()]).unwrap();
    let s = run(dir.path(), &k5, &opts, &|_| {}).unwrap();
    let r = ran(&s);
    assert_eq!(
        &r[..3],
        &[("gs-init", false), ("warp-graph", false), ("fuse", true)]
    );
    assert!(r[3..].iter().all(|(_, ran)| *ran), "{r:?}");

    // Back to the defaults: the same bytes as the first run.
    run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    assert_eq!(
        std::fs::read(first.out.join("features.safetensors")).unwrap(),
        features
    );

    // A newer input (the masks) redoes warp-graph and everything after it.
    std::thread::sleep(std::time::Duration::from_millis(20));
    let masks = dir.path().join("masks.safetensors");
    let bytes = std::fs::read(&masks).unwrap();
    std::fs::write(&masks, bytes).unwrap();
    let s = run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    let r = ran(&s);
    assert_eq!(r[0], ("gs-init", false));
    assert!(r[1..].iter().all(|(_, ran)| *ran), "{r:?}");

    // An interrupted stage (outputs present, completion record missing) is redone.
    std::fs::remove_file(first.out.join(".stamps/pq.json")).unwrap();
    std::fs::write(first.out.join("pq.safetensors"), b"half-written").unwrap();
    let s = run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    let r = ran(&s);
    assert!(
        r.contains(&("pq", true)) && r.contains(&("fuse", false)),
        "{r:?}"
    );
    assert!(profuse_formats::inspect(first.out.join("pq.safetensors"))
        .error
        .is_none());
}

#[test]
fn missing_inputs_and_bad_parameters_name_the_file_or_key_and_write_nothing() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    std::fs::remove_file(dir.path().join("masks.safetensors")).unwrap();
    let e = run(dir.path(), &tiny_config(), &RunOptions::default(), &|_| {}).unwrap_err();
    assert!(e.to_string().contains("masks.safetensors"), "{e}");
    assert!(!dir.path().join("out").exists());

    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let mut cfg = tiny_config();
    cfg.warp_graph.tau_iou = 1.5;
    let e = run(dir.path(), &cfg, &RunOptions::default(), &|_| {}).unwrap_err();
    assert!(
        e.to_string().contains("warp_graph") && e.to_string().contains("tau_iou"),
        "{e}"
    );
    assert!(!dir.path().join("out").exists());

    // A stage error names the stage and, through its cause, the file.
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    std::fs::write(
        dir.path().join("prompts.safetensors"),
        b"not a safetensors file",
    )
    .unwrap();
    let e = run(dir.path(), &tiny_config(), &RunOptions::default(), &|_| {}).unwrap_err();
    let chain = format!(
        "{e}: {}",
        std::error::Error::source(&e)
            .map(|s| s.to_string())
            .unwrap_or_default()
    );
    assert!(
        chain.contains("query") && chain.contains("prompts.safetensors"),
        "{chain}"
    );
}

/// What used to fail only when its stage ran, after gs-init, warp-graph and fuse had run,
/// fails before any stage: PQ's sub-quantisers that do not divide the descriptors'
/// dimension (the default 128 on tiny's 64-d), prompts of another dimension, and
/// out-of-domain fuse, pq and query values. Nothing is written.
#[test]
fn parameters_and_inputs_that_would_fail_a_late_stage_fail_before_any_stage() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let fails = |cfg: &Config, key: &str| {
        let e = run(dir.path(), cfg, &RunOptions::default(), &|_| {}).unwrap_err();
        assert!(e.to_string().contains(key), "{key}: {e}");
        assert!(!dir.path().join("out").exists(), "{key}: out/ was written");
        e.to_string()
    };
    let e = fails(&Config::default(), "pq.m");
    assert!(
        e.contains("128") && e.contains("64") && e.contains("pq.m=64"),
        "{e}"
    );
    for (set, key) in [
        ("fuse.k=0", "fuse.k"),
        ("fuse.min_share=1.5", "fuse.min_share"),
        ("pq.m=0", "pq.m"),
        ("query.threshold=nan", "query.threshold"),
        ("query.k=300", "query.k"),
    ] {
        let cfg = tiny_config().with_overrides(&[set.into()]).unwrap();
        fails(&cfg, key);
    }
    // Prompts of another encoder: 8-d embeddings against 64-d descriptors.
    let prompts = profuse_formats::Prompts {
        names: vec!["sofa".into()],
        dim: 8,
        embeddings: vec![0.5f32; 8].into(),
        class_ids: None,
        extra: Default::default(),
    };
    prompts
        .write(dir.path().join("prompts.safetensors"))
        .unwrap();
    let e = fails(&tiny_config(), "prompts");
    assert!(e.contains("8-d") && e.contains("64-d"), "{e}");
}

/// `RunOptions::proposals` replaces warp-graph by a given file (here the ground truth's,
/// through `sweep::run_oracle`): the proposals are exactly the ground truth (ARI 1), the
/// stage is skipped when up to date, a file of the wrong length is refused naming both
/// files, and warp-graph runs again when it is next asked for.
#[test]
fn given_proposals_replace_warp_graph() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let scores = profuse_experiments::sweep::run_oracle(dir.path(), &tiny_config(), None).unwrap();
    assert_eq!(scores["proposals"]["ari"].as_f64(), Some(1.0), "{scores:?}");
    assert_eq!(scores["proposals"]["purity"].as_f64(), Some(1.0));
    assert!(scores["lerf_miou"].as_f64().unwrap() > 25.0, "{scores:?}");

    let out = dir.path().join("out_oracle");
    let given = out.join("ground_truth_proposals.safetensors");
    let opts = RunOptions {
        out: Some(out.clone()),
        force: false,
        proposals: Some(given.clone()),
        ..RunOptions::default()
    };
    let again = run(dir.path(), &tiny_config(), &opts, &|_| {}).unwrap();
    assert_eq!(again.stages[1].stage, "proposals");
    assert!(again.stages.iter().all(|l| !l.ran), "{:?}", ran(&again));

    // One entry too few (a valid file: every mask unassigned).
    let masks = profuse_formats::Masks::read(dir.path().join("masks.safetensors")).unwrap();
    let short = profuse_formats::Proposals {
        mask_proposal: vec![u32::MAX; masks.num_masks() - 1].into(),
        proposal_size: Vec::<u32>::new().into(),
        proposal_views: Vec::<u32>::new().into(),
        mask_share: None,
        mask_instance: None,
        extra: Default::default(),
    };
    let bad = dir.path().join("short.safetensors");
    short.write(&bad).unwrap();
    let e = run(
        dir.path(),
        &tiny_config(),
        &RunOptions {
            proposals: Some(bad.clone()),
            ..opts.clone()
        },
        &|_| {},
    )
    .unwrap_err();
    let e = error_chain(&e);
    assert!(
        e.contains("short.safetensors") && e.contains("one per mask"),
        "{e}"
    );

    let back = run(
        dir.path(),
        &tiny_config(),
        &RunOptions {
            proposals: None,
            ..opts
        },
        &|_| {},
    )
    .unwrap();
    assert_eq!(back.stages[1].stage, "warp-graph");
    assert!(back.stages[1].ran, "{:?}", ran(&back));
}

/// A given Gaussians file replaces gs-init and gs-refine (`RunOptions::gaussians`, what
/// the sweep uses for rows of one geometry): its bytes become out/gaussians, every later
/// output equals that of the run that computed them, a second run is up to date, a file
/// that is not Gaussians is refused by name without touching out/, and without the option
/// gs-init and gs-refine run again.
#[test]
fn given_gaussians_replace_the_geometry_stages_with_the_same_outputs() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let cfg = tiny_config()
        .with_overrides(&["gs_refine.iterations=20".into()])
        .unwrap();
    let computed = dir.path().join("computed");
    let a = run(
        dir.path(),
        &cfg,
        &RunOptions {
            out: Some(computed.clone()),
            ..RunOptions::default()
        },
        &|_| {},
    )
    .unwrap();
    assert_eq!(ran(&a)[..2], [("gs-init", true), ("gs-refine", true)]);

    let given = computed.join("gaussians.safetensors");
    let out = dir.path().join("given");
    let opts = RunOptions {
        out: Some(out.clone()),
        gaussians: Some(given.clone()),
        ..RunOptions::default()
    };
    let b = run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    assert_eq!(ran(&b)[..2], [("gaussians", true), ("warp-graph", true)]);
    assert_eq!(b.stages.len(), a.stages.len() - 1);
    for file in [
        "gaussians.safetensors",
        "proposals.safetensors",
        "features.safetensors",
        "pq.safetensors",
        "vertex_labels_nyu19.safetensors",
    ] {
        let (x, y) = (computed.join(file), out.join(file));
        assert_eq!(
            std::fs::read(&x).unwrap(),
            std::fs::read(&y).unwrap(),
            "{file}"
        );
    }
    let again = run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    assert!(again.stages.iter().all(|l| !l.ran), "{:?}", ran(&again));

    let before = std::fs::read(out.join("gaussians.safetensors")).unwrap();
    let not_gaussians = dir.path().join("masks.safetensors");
    let e = run(
        dir.path(),
        &cfg,
        &RunOptions {
            gaussians: Some(not_gaussians),
            ..opts.clone()
        },
        &|_| {},
    )
    .unwrap_err();
    let e = error_chain(&e);
    assert!(
        e.contains("gaussians") && e.contains("masks.safetensors"),
        "{e}"
    );
    assert_eq!(
        std::fs::read(out.join("gaussians.safetensors")).unwrap(),
        before
    );

    let back = run(
        dir.path(),
        &cfg,
        &RunOptions {
            gaussians: None,
            ..opts
        },
        &|_| {},
    )
    .unwrap();
    assert_eq!(ran(&back)[..2], [("gs-init", true), ("gs-refine", true)]);
    assert_eq!(
        std::fs::read(out.join("gaussians.safetensors")).unwrap(),
        before
    );
}

/// Issue 20 item 8: an input replaced by a different file with an *older* modification
/// time (what `cp -p`, `rsync -t` and `tar x` do) makes the stages that read it stale;
/// the old mtime-only check called every stage up to date and kept stale outputs.
#[test]
fn an_input_replaced_by_an_older_file_makes_its_stages_stale() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let other = tempfile::tempdir().unwrap();
    synth::generate(&synth::Config::preset(synth::Preset::Tiny, 1), other.path()).unwrap();
    let (cfg, opts) = (tiny_config(), RunOptions::default());
    run(dir.path(), &cfg, &opts, &|_| {}).unwrap();

    // `cp -p`: another scene's masks, dated a day back.
    let masks = dir.path().join("masks.safetensors");
    std::fs::copy(other.path().join("masks.safetensors"), &masks).unwrap();
    let day_ago = std::time::SystemTime::now() - std::time::Duration::from_secs(86_400);
    let f = std::fs::File::options().write(true).open(&masks).unwrap();
    f.set_modified(day_ago).unwrap();
    drop(f);
    let s = run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    let r = ran(&s);
    assert_eq!(r[0], ("gs-init", false));
    assert!(r[1..].iter().all(|(_, ran)| *ran), "{r:?}");
    assert!(
        s.stages[1].reason.contains("masks.safetensors changed"),
        "{}",
        s.stages[1].reason
    );

    // The same bytes rewritten in place with the old modification time restored: only
    // the status-change time tells, and it does.
    let stamp = std::fs::metadata(&masks).unwrap().modified().unwrap();
    let bytes = std::fs::read(&masks).unwrap();
    std::fs::write(&masks, &bytes).unwrap();
    let f = std::fs::File::options().write(true).open(&masks).unwrap();
    f.set_modified(stamp).unwrap();
    drop(f);
    let s = run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    assert_eq!(ran(&s)[1], ("warp-graph", true));

    // Untouched: everything up to date, and the record says what it compares.
    let s = run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    assert!(s.stages.iter().all(|l| !l.ran), "{:?}", ran(&s));
    let record: serde_json::Value =
        serde_json::from_slice(&std::fs::read(s.out.join(".stamps/warp-graph.json")).unwrap())
            .unwrap();
    assert_eq!(record["version"], 3);
    let first = &record["inputs"][0];
    assert_eq!(first["path"], masks.to_string_lossy().as_ref());
    assert_eq!(first["kind"], "file");
    assert_eq!(first["size"], bytes.len() as u64);
    for key in ["inode", "mtime_ns", "ctime_ns"] {
        assert!(first[key].as_u64().is_some_and(|v| v > 0), "{key}: {first}");
    }
}

/// A record made by other code (another build: an edited crate, another `Cargo.lock`)
/// makes its stage and what depends on it run again, even with the same parameters and
/// untouched files; each record names the crate its stage runs. The old records (version
/// 2, without a code identity) are stale too.
#[test]
fn a_record_of_other_code_makes_its_stage_stale() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let cfg = tiny_config();
    let opts = RunOptions::default();
    let first = run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    let features = std::fs::read(first.out.join("features.safetensors")).unwrap();
    let stamp_of = |stage: &str| first.out.join(format!(".stamps/{stage}.json"));
    let read = |stage: &str| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(stamp_of(stage)).unwrap()).unwrap()
    };

    let mut identities = std::collections::BTreeSet::new();
    for (stage, krate) in [
        ("gs-init", "gs-init"),
        ("warp-graph", "warp-graph"),
        ("fuse", "profuse-fuse"),
        ("pq", "profuse-pq"),
        ("query", "profuse-query"),
    ] {
        let code = read(stage)["code"].as_str().unwrap().to_string();
        let want = profuse_pipeline::stage::crate_code(krate).unwrap();
        assert!(
            code.starts_with(&format!("{krate}@{want}+profuse-pipeline@")),
            "{stage}: {code}"
        );
        assert_eq!(code, profuse_pipeline::stage::code_identity(krate));
        identities.insert(want);
    }
    assert_eq!(identities.len(), 5, "{identities:?}");

    // warp-graph's record as another build would have left it.
    let mut record = read("warp-graph");
    record["code"] = "warp-graph@0000000000000000+profuse-pipeline@0000000000000000".into();
    std::fs::write(stamp_of("warp-graph"), serde_json::to_vec(&record).unwrap()).unwrap();
    let s = run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    let r = ran(&s);
    assert_eq!(r[0], ("gs-init", false));
    assert_eq!(r[1], ("warp-graph", true));
    assert!(
        s.stages[1].reason.contains("code changed"),
        "{}",
        s.stages[1].reason
    );
    // warp-graph rewrote its output, so fuse and the rest follow; the bytes are the same.
    assert!(r[2..].iter().all(|(_, ran)| *ran), "{r:?}");
    assert_eq!(
        std::fs::read(first.out.join("features.safetensors")).unwrap(),
        features
    );

    // A record of the previous format (version 2, no code identity) reruns its stage.
    let mut record = read("pq");
    record["version"] = 2.into();
    record.as_object_mut().unwrap().remove("code");
    std::fs::write(stamp_of("pq"), serde_json::to_vec(&record).unwrap()).unwrap();
    let s = run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    let r = ran(&s);
    assert!(
        r.contains(&("pq", true)) && r.contains(&("fuse", false)),
        "{r:?}"
    );
}

/// Issue 20 item 7: a run on an output directory that another run holds fails at once
/// with a typed error naming the directory and writes nothing; with `wait` it waits for
/// the lock; two concurrent runs on one scene both succeed (the old code had no lock and
/// a shared fixed temporary directory for the query stage).
#[test]
fn runs_on_one_output_directory_are_serialised_by_its_lock() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let cfg = tiny_config();
    let out = dir.path().join("out");
    std::fs::create_dir(&out).unwrap();
    let held = profuse_formats::output::lock_dir(&out, false).unwrap();
    let e = run(dir.path(), &cfg, &RunOptions::default(), &|_| {}).unwrap_err();
    assert!(
        matches!(
            e,
            profuse_pipeline::PipelineError::Output(
                profuse_formats::output::OutputError::Locked { .. }
            )
        ),
        "{e}"
    );
    assert!(e.to_string().contains(&*out.to_string_lossy()), "{e}");
    assert_eq!(std::fs::read_dir(&out).unwrap().count(), 0);

    let release = std::thread::spawn(move || {
        std::thread::sleep(std::time::Duration::from_millis(300));
        drop(held);
    });
    let waiting = RunOptions {
        wait: true,
        ..RunOptions::default()
    };
    let s = run(dir.path(), &cfg, &waiting, &|_| {}).unwrap();
    release.join().unwrap();
    assert!(s.stages.iter().all(|l| l.ran));
    let reference = std::fs::read(out.join("pq.safetensors")).unwrap();

    let forced = RunOptions {
        force: true,
        wait: true,
        ..RunOptions::default()
    };
    let runs: Vec<_> = (0..2)
        .map(|_| {
            let (scene, cfg, opts) = (dir.path().to_path_buf(), cfg.clone(), forced.clone());
            std::thread::spawn(move || run(&scene, &cfg, &opts, &|_| {}).map(|_| ()))
        })
        .collect();
    for r in runs {
        r.join().unwrap().unwrap();
    }
    assert_eq!(
        std::fs::read(out.join("pq.safetensors")).unwrap(),
        reference
    );
}

/// Issue 20 item 11: what killed runs leave in the output directory (unclaimed
/// `.profuse-tmp-*` files and directories, the fixed temporary names of earlier
/// versions) is removed by the next run; the old code left them forever.
#[test]
fn leftovers_of_killed_runs_are_removed_by_the_next_run() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let (cfg, opts) = (tiny_config(), RunOptions::default());
    let first = run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    let out = first.out;
    std::fs::write(out.join(".profuse-tmp-AbC123"), b"half").unwrap();
    std::fs::create_dir_all(out.join(".profuse-tmp-query-XyZ/wall/masks")).unwrap();
    std::fs::write(out.join(".profuse-tmp-query-XyZ/wall/masks/a.png"), b"x").unwrap();
    std::fs::write(out.join(".stamps/.profuse-tmp-q1"), b"{").unwrap();
    std::fs::create_dir_all(out.join(".query.tmp/x")).unwrap();
    std::fs::write(out.join(".stamps/.pq.tmp"), b"{").unwrap();
    let s = run(dir.path(), &cfg, &opts, &|_| {}).unwrap();
    assert!(s.stages.iter().all(|l| !l.ran), "{:?}", ran(&s));
    for d in [out.clone(), out.join(".stamps")] {
        let names: Vec<String> = std::fs::read_dir(&d)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with(".profuse-tmp") || n.ends_with(".tmp"))
            .collect();
        assert!(names.is_empty(), "{}: {names:?}", d.display());
    }
}

/// The gs-refine stage (issue 18): off by default; with iterations it runs between gs-init
/// and warp-graph, gs-init then writes `gaussians_init` and gs-refine the `gaussians` every
/// later stage reads; a second run finds everything up to date; `until` stops after it.
#[test]
fn gs_refine_stage_runs_between_gs_init_and_warp_graph_when_configured() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let config = tiny_config()
        .with_overrides(&[
            "gs_refine.iterations=6".into(),
            "gs_refine.scale=1.0".into(),
            "gs_refine.sh_degree=1".into(),
        ])
        .unwrap();
    let until = RunOptions {
        until: Some(profuse_pipeline::StageName::GsRefine),
        ..RunOptions::default()
    };
    let s = run(dir.path(), &config, &until, &|_| {}).unwrap();
    assert_eq!(ran(&s), vec![("gs-init", true), ("gs-refine", true)]);
    let out = dir.path().join("out");
    let init = profuse_formats::Gaussians::read(out.join("gaussians_init.safetensors")).unwrap();
    let refined = profuse_formats::Gaussians::read(out.join("gaussians.safetensors")).unwrap();
    assert_eq!(init.len(), refined.len(), "no pruning configured");
    assert_ne!(init.means, refined.means, "six Adam steps move the means");
    let report = &s.stages[1].report;
    assert_eq!(report["iterations"], 6);
    assert_eq!(report["train_views"], 4);
    // The SH raise reaches the file every later stage reads; one loss window per iteration.
    assert_eq!((init.sh_degree, refined.sh_degree), (0, 1));
    assert_eq!(report["sh_degree"], 1);
    assert_eq!(report["loss_window"], 1);
    assert_eq!(report["loss_windows"].as_array().map(Vec::len), Some(6));
    assert_eq!(report["loss_windows"][0], report["first_loss"]);

    let all = run(dir.path(), &config, &RunOptions::default(), &|_| {}).unwrap();
    let stages: Vec<&str> = all.stages.iter().map(|l| l.stage.as_str()).collect();
    assert_eq!(
        stages,
        [
            "gs-init",
            "gs-refine",
            "warp-graph",
            "fuse",
            "pq",
            "query",
            "vertex-transfer"
        ]
    );
    assert!(!all.stages[0].ran && !all.stages[1].ran, "{:?}", ran(&all));
    assert!(all.stages[2..].iter().all(|l| l.ran), "{:?}", ran(&all));
    let again = run(dir.path(), &config, &RunOptions::default(), &|_| {}).unwrap();
    assert!(again.stages.iter().all(|l| !l.ran), "{:?}", ran(&again));

    // Off by default: no gs-refine line, and gs-init writes the gaussians itself.
    let plain = tempfile::tempdir().unwrap();
    tiny_scene(plain.path());
    let until_init = RunOptions {
        until: Some(profuse_pipeline::StageName::GsRefine),
        ..RunOptions::default()
    };
    let s = run(plain.path(), &tiny_config(), &until_init, &|_| {}).unwrap();
    assert_eq!(ran(&s), vec![("gs-init", true)]);
    assert!(plain.path().join("out/gaussians.safetensors").is_file());
    assert!(!plain.path().join("out/gaussians_init.safetensors").exists());
}

/// `query.semantics` index and both (issue 24): fuse writes the semantic index beside the
/// features, query and vertex-transfer read it (both: with the PQ codes for the Gaussians
/// without a dominant proposal), the scores meet the same floors as the PQ run, and
/// switching between index and both reruns only the stages that read the semantics.
#[test]
fn index_and_both_semantics_run_end_to_end_and_meet_the_pq_floors() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let opts = RunOptions::default();
    let with = |mode: &str| {
        tiny_config()
            .with_overrides(&[format!("query.semantics=\"{mode}\"")])
            .unwrap()
    };
    let s = run(dir.path(), &with("index"), &opts, &|_| {}).unwrap();
    assert!(s.stages.iter().all(|l| l.ran), "{:?}", ran(&s));
    let paths = Paths::new(dir.path(), &s.out, false);
    let index = profuse_formats::SemanticIndex::read(&paths.semantic_index).unwrap();
    let gaussians = profuse_formats::Gaussians::read(&paths.gaussians).unwrap();
    assert_eq!(index.num_gaussians(), gaussians.len());
    let proposals = profuse_formats::Proposals::read(&paths.proposals).unwrap();
    // The rows are the proposals, then one per orphan mask (SPEC.md §4.17, singleton
    // orphans by default).
    assert!(
        index.num_proposals() > proposals.len(),
        "{} rows",
        index.num_proposals()
    );
    let dominant = (0..index.num_gaussians())
        .filter(|&g| index.is_dominant(g))
        .count();
    assert!(dominant > index.num_gaussians() / 2, "{dominant} dominant");
    let floors = |mode: &str| {
        let m = evaluate(&Paths::new(dir.path(), &s.out, false)).unwrap();
        let get = |k: &str| m[k].as_f64().unwrap();
        assert!(get("lerf_miou") > 25.0, "{mode}: {m:?}");
        assert!(get("scannet_miou19") > 12.0, "{mode}: {m:?}");
    };
    floors("index");

    let s = run(dir.path(), &with("both"), &opts, &|_| {}).unwrap();
    let r = ran(&s);
    for (stage, expected) in [
        ("gs-init", false),
        ("warp-graph", false),
        ("fuse", false),
        ("query", true),
        ("vertex-transfer", true),
    ] {
        assert!(r.contains(&(stage, expected)), "{stage}: {r:?}");
    }
    floors("both");
}

#[test]
fn a_scene_with_its_own_gaussians_and_no_prompts_is_fused_and_answers_clicks_only() {
    // What `profuse prepare` writes for real photos without a text encoder: the geometry
    // as SCENE/gaussians.safetensors, dense warps, masks, no prompts, no sparse matches.
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path());
    let computed = dir.path().join("computed");
    let opts = RunOptions {
        out: Some(computed.clone()),
        ..RunOptions::default()
    };
    let a = run(dir.path(), &tiny_config(), &opts, &|_| {}).unwrap();
    std::fs::copy(
        computed.join("gaussians.safetensors"),
        dir.path().join("gaussians.safetensors"),
    )
    .unwrap();
    std::fs::remove_file(dir.path().join("prompts.safetensors")).unwrap();
    let _ = std::fs::remove_file(dir.path().join("sparse_matches.safetensors"));
    let b = run(dir.path(), &tiny_config(), &RunOptions::default(), &|_| {}).unwrap();
    assert_eq!(
        ran(&b),
        vec![
            ("gaussians", true),
            ("warp-graph", true),
            ("fuse", true),
            ("pq", true),
            ("query", false)
        ]
    );
    let skipped = &b.stages[4];
    assert!(
        skipped.reason.contains("no prompts.safetensors"),
        "{}",
        skipped.reason
    );
    // The same geometry gives the same registration as the run that computed it.
    for file in ["proposals.safetensors", "features.safetensors"] {
        assert_eq!(
            std::fs::read(computed.join(file)).unwrap(),
            std::fs::read(b.out.join(file)).unwrap(),
            "{file}"
        );
    }
    assert!(a.stages.iter().any(|l| l.stage == "query" && l.ran));
    // A second run is up to date, the skipped query included.
    let c = run(dir.path(), &tiny_config(), &RunOptions::default(), &|_| {}).unwrap();
    assert!(c.stages.iter().all(|l| !l.ran), "{:?}", ran(&c));
}

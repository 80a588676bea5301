//! End-to-end tests of the `pq` tool.

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::Output;

use profuse_formats::{FileKind, Pq, Prompts};
use profuse_pq::synthetic::Clustered;

fn pq(args: &[&OsStr]) -> Output {
    super::run_tool(env!("CARGO_BIN_EXE_pq"), args)
}

fn os(s: &str) -> &OsStr {
    s.as_ref()
}

/// 3000 clustered 64-d descriptors of 12 classes (every 10th invalid) and a prompts file
/// with one text-like embedding per class, named `class0`..`class11`.
fn inputs(dir: &Path) -> (Clustered, PathBuf, PathBuf) {
    let gen = Clustered::new(64, 12, 0.6, 4);
    let features = dir.join("features.safetensors");
    gen.features(3000, 10).write(&features).unwrap();
    let prompts = Prompts {
        names: (0..12).map(|c| format!("class{c}")).collect(),
        dim: 64,
        embeddings: (0..12)
            .flat_map(|c| gen.query(c, 0.4, c as u64))
            .collect::<Vec<f32>>()
            .into(),
        ..Default::default()
    };
    let prompts_path = dir.join("prompts.safetensors");
    prompts.write(&prompts_path).unwrap();
    (gen, features, prompts_path)
}

fn train(features: &Path, out: &Path, m: &str) -> Output {
    pq(&[
        os("train"),
        os("--features"),
        features.as_os_str(),
        os("--out"),
        out.as_os_str(),
        os("--m"),
        os(m),
        os("--iters"),
        os("6"),
        os("--quiet"),
    ])
}

#[test]
fn pq_trains_encodes_and_queries_a_features_file() {
    let dir = tempfile::tempdir().unwrap();
    let (gen, features, prompts) = inputs(dir.path());
    let out = dir.path().join("pq.safetensors");
    let res = train(&features, &out, "16");
    super::assert_succeeded(&res);
    assert!(
        res.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&res.stderr)
    );
    let j = super::json(&res);
    assert_eq!(j["vectors"], 3000);
    assert_eq!(j["valid"], 2700);
    assert_eq!((j["m"].clone(), j["dsub"].clone()), (16.into(), 4.into()));
    assert_eq!(j["train_samples"], 2700);
    let cos = j["reconstruction_cosine_mean"].as_f64().unwrap();
    assert!(cos > 0.9 && cos < 1.0, "{cos}");

    // The file is a valid pq file.
    let code = Pq::read(&out).unwrap();
    assert_eq!((code.len(), code.m, code.dsub), (3000, 16, 4));
    assert_eq!(code.valid[9], 0);

    // Query: the top 20 are descriptors of the prompt's class, best first, and agree with
    // the library.
    let query = |scan: &str| {
        let res = pq(&[
            os("query"),
            os("--pq"),
            out.as_os_str(),
            os("--prompts"),
            prompts.as_os_str(),
            os("--prompt"),
            os("class7"),
            os("--k"),
            os("20"),
            os("--scan"),
            os(scan),
            os("--quiet"),
        ]);
        super::assert_succeeded(&res);
        assert!(res.stderr.is_empty());
        super::json(&res)
    };
    let j = query("fast");
    let ids: Vec<u64> = j["ids"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap())
        .collect();
    let scores: Vec<f64> = j["scores"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert_eq!(ids.len(), 20);
    assert!(
        ids.iter().all(|&i| gen.class_of(i) == 7 && i % 10 != 9),
        "{ids:?}"
    );
    assert_eq!(j["scan"], "fast");
    assert!(j["candidates"].as_u64().unwrap() >= 20, "{j}");
    assert!(j["prepare_ms"].as_f64().unwrap() >= 0.0);
    // The exhaustive scan returns the same ids and scores.
    let exhaustive = query("exhaustive");
    assert_eq!(exhaustive["scan"], "exhaustive");
    assert_eq!(exhaustive["ids"], j["ids"]);
    assert_eq!(exhaustive["scores"], j["scores"]);
    assert!(scores.windows(2).all(|w| w[0] >= w[1]), "{scores:?}");
    let p = Prompts::read(&prompts).unwrap();
    let lib = profuse_pq::search(&code, p.embedding(7), profuse_pq::DEFAULT_SHORTLIST, 20).unwrap();
    assert_eq!(ids, lib.iter().map(|r| u64::from(r.0)).collect::<Vec<_>>());

    // Encoding the same features with the trained codebook reproduces the file, and
    // training again reproduces it too (seeded).
    let again = dir.path().join("again.safetensors");
    let res = pq(&[
        os("encode"),
        os("--pq"),
        out.as_os_str(),
        os("--features"),
        features.as_os_str(),
        os("--out"),
        again.as_os_str(),
    ]);
    super::assert_succeeded(&res);
    assert_eq!(super::json(&res)["valid"], 2700);
    assert_eq!(std::fs::read(&out).unwrap(), std::fs::read(&again).unwrap());
    super::assert_succeeded(&train(&features, &again, "16"));
    assert_eq!(std::fs::read(&out).unwrap(), std::fs::read(&again).unwrap());
}

#[test]
fn pq_failures_exit_1_name_the_problem_and_write_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let (_, features, prompts) = inputs(dir.path());
    let before = std::fs::read_dir(dir.path()).unwrap().count();
    let out = dir.path().join("pq.safetensors");

    // 64 dimensions do not split into 5 sub-quantisers.
    let res = train(&features, &out, "5");
    assert_eq!(res.status.code(), Some(1));
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(
        err.contains("features.safetensors") && err.contains("divisible"),
        "{err}"
    );
    assert!(res.stdout.is_empty());
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), before);

    // A missing input file.
    let res = train(&dir.path().join("nope.safetensors"), &out, "16");
    assert_eq!(res.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&res.stderr).contains("nope.safetensors"));
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), before);

    // An unknown prompt and a prompt of the wrong dimension.
    super::assert_succeeded(&train(&features, &out, "16"));
    let res = pq(&[
        os("query"),
        os("--pq"),
        out.as_os_str(),
        os("--prompts"),
        prompts.as_os_str(),
        os("--prompt"),
        os("sofa"),
    ]);
    assert_eq!(res.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&res.stderr).contains("\"sofa\""));
    let wrong = dir.path().join("wrong.safetensors");
    Prompts {
        names: vec!["x".into()],
        dim: 3,
        embeddings: vec![1.0, 0.0, 0.0].into(),
        ..Default::default()
    }
    .write(&wrong)
    .unwrap();
    let res = pq(&[
        os("query"),
        os("--pq"),
        out.as_os_str(),
        os("--prompts"),
        wrong.as_os_str(),
        os("--prompt"),
        os("x"),
    ]);
    assert_eq!(res.status.code(), Some(1));
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(
        err.contains("wrong.safetensors") && err.contains("3 dimensions"),
        "{err}"
    );

    // Encoding features of another dimension with this codebook.
    let other = dir.path().join("other.safetensors");
    Clustered::new(32, 3, 0.5, 1)
        .features(300, 0)
        .write(&other)
        .unwrap();
    let target = dir.path().join("never.safetensors");
    let res = pq(&[
        os("encode"),
        os("--pq"),
        out.as_os_str(),
        os("--features"),
        other.as_os_str(),
        os("--out"),
        target.as_os_str(),
    ]);
    assert_eq!(res.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&res.stderr).contains("other.safetensors"));
    assert!(!target.exists());
}

#[test]
fn pq_bench_reports_the_measured_keys() {
    let res = pq(&[
        os("bench"),
        os("--n"),
        os("6000"),
        os("--dim"),
        os("64"),
        os("--m"),
        os("16"),
        os("--iters"),
        os("3"),
        os("--sample"),
        os("2048"),
        os("--classes"),
        os("30"),
        os("--queries"),
        os("2"),
        os("--quiet"),
    ]);
    super::assert_succeeded(&res);
    let j = super::json(&res);
    for key in [
        "query_ms",
        "query_cpu_ms",
        "adc_ms",
        "encode_per_s",
        "train_s",
        "peak_rss_mb",
        "reconstruction_cosine",
    ] {
        assert!(j[key].as_f64().unwrap() > 0.0, "{key}: {j}");
    }
    assert!(j["recall_at_100"].as_f64().unwrap() >= 0.99, "{j}");
    assert_eq!(j["n"], 6000);
    for key in [
        "fast_query_ms",
        "fast_prepare_ms",
        "fast_candidates",
        "fast_packed_mb",
    ] {
        assert!(j[key].as_f64().unwrap() > 0.0, "{key}: {j}");
    }
    // Every query's fast-scan result is the exhaustive one.
    assert_eq!(j["fast_same_as_exhaustive"], 1.0, "{j}");
}

/// `crates/pq/python/bench_vs_faiss.py --quick` (issue 23) runs ours (this build's `pq`)
/// and faiss-cpu on the same data and prints every ratio and recall. The figures of a
/// 20,000-vector debug run mean nothing for speed; what is checked is that the comparison
/// runs end to end and that both sides find most of the exact top 100 (a broken side
/// would not). Needs python3 with numpy, safetensors and faiss; skipped with a message
/// when they are missing, unless PROFUSE_REQUIRE_FAISS=1.
#[test]
fn bench_vs_faiss_quick_reports_every_ratio_and_recall() {
    if !super::python_has(
        "numpy, safetensors, faiss",
        "PROFUSE_REQUIRE_FAISS",
        "pip install -r crates/pq/python/requirements.txt",
    ) {
        return;
    }
    let out = std::process::Command::new("python3")
        .arg(super::root().join("crates/pq/python/bench_vs_faiss.py"))
        .args(["--quick", "--n", "5000", "--queries", "3", "--repeat", "1"])
        .arg("--pq-bin")
        .arg(env!("CARGO_BIN_EXE_pq"))
        .output()
        .unwrap();
    super::assert_succeeded(&out);
    let j = super::json(&out);
    for key in [
        "train_ratio",
        "encode_ratio",
        "query_ratio_indexpq",
        "query_ratio_fastscan",
    ] {
        assert!(j[key].as_f64().unwrap() > 0.0, "{key}: {j}");
    }
    for key in [
        "recall_at_100_ours",
        "recall_at_100_faiss",
        "recall_at_100_fastscan",
    ] {
        let r = j[key].as_f64().unwrap();
        assert!((0.3..=1.0).contains(&r), "{key}: {j}");
    }
    // The fast scan finds what the exhaustive scan finds.
    assert_eq!(
        j["recall_at_100_ours"], j["recall_at_100_ours_exhaustive"],
        "{j}"
    );
    assert!(j["prepare_ms_ours"].as_f64().unwrap() > 0.0, "{j}");
    assert_eq!(j["n"], 5000);
}

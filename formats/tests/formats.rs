//! Integration tests of the format crate: golden vectors, the error of every defect
//! class, write-then-read round trips (property tests), atomic writes and zero-copy views.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};

use profuse_formats::samples::{self, Vector};
use profuse_formats::{
    f16, fixed_point, fixed_point_words, inspect, quantise_share, Cameras, Container, Features,
    FileKind, FileWriter, Floats, FusePartial, Gaussians, Labels, Masks, Matches, Mesh, Pq,
    Prompts, Proposals, Selection, SemanticIndex, SparseMatches, TopK, VertexLabels, ViewMaps,
    WarpCoords, WarpPartial, MAX_U16_PROPOSALS, WARP_COUNTERS,
};
use proptest::prelude::*;

fn vectors_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("vectors")
}

#[test]
fn committed_vectors_equal_what_the_code_writes() {
    let vectors = samples::vectors();
    let dir = vectors_dir();
    for v in &vectors {
        let on_disk = std::fs::read(dir.join(&v.name)).unwrap_or_else(|e| {
            panic!(
                "{}: {e} (run `cargo run -p profuse-formats --example write_vectors`)",
                v.name
            )
        });
        assert!(
            on_disk == v.bytes,
            "{} differs from what the code writes; regenerate the vectors",
            v.name
        );
    }
    for sub in ["valid", "invalid"] {
        let count = std::fs::read_dir(dir.join(sub)).unwrap().count();
        let expected = vectors.iter().filter(|v| v.name.starts_with(sub)).count();
        assert_eq!(count, expected, "stale files in vectors/{sub}");
    }
    let expected: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("expected.json")).unwrap()).unwrap();
    assert_eq!(
        expected,
        samples::expected_json(&vectors),
        "expected.json is stale"
    );
}

#[test]
fn every_valid_vector_reads_and_every_invalid_one_fails_with_its_code_and_field() {
    let vectors = samples::vectors();
    let dir = vectors_dir();
    let mut invalid_seen = 0;
    for Vector {
        name, expect_error, ..
    } in &vectors
    {
        let report = inspect(dir.join(name));
        match expect_error {
            None => assert!(report.error.is_none(), "{name}: {:?}", report.error),
            Some((code, field)) => {
                let err = report
                    .error
                    .unwrap_or_else(|| panic!("{name} was accepted"));
                assert_eq!((err.code(), err.field()), (*code, *field), "{name}: {err}");
                assert!(
                    err.to_string().contains(name.as_str()),
                    "{name}: error does not name the file: {err}"
                );
                invalid_seen += 1;
            }
        }
    }
    assert!(invalid_seen > 200, "only {invalid_seen} invalid vectors");
}

/// Every reader (not only `inspect`'s dispatch) rejects its kind's defects and other kinds.
#[test]
fn each_typed_reader_rejects_its_defects() {
    fn check<K: FileKind + std::fmt::Debug>(stem: &str) {
        let dir = vectors_dir();
        let valid = dir.join(format!("valid/{stem}.safetensors"));
        K::read(&valid).unwrap_or_else(|e| panic!("{e}"));
        let mut n = 0;
        for v in samples::vectors() {
            let Some((code, field)) = v.expect_error else {
                continue;
            };
            if !v.name.starts_with(&format!("invalid/{stem}__")) {
                continue;
            }
            let err = K::read(dir.join(&v.name)).expect_err(&v.name);
            assert_eq!(
                (err.code(), err.field()),
                (code, field),
                "{}: {err}",
                v.name
            );
            n += 1;
        }
        assert!(n >= 15, "{stem}: only {n} defect classes");
        // A file of another kind is a wrong_kind error, not a misread.
        let other = if stem == "mesh" { "cameras" } else { "mesh" };
        let err = K::read(dir.join(format!("valid/{other}.safetensors"))).unwrap_err();
        assert_eq!(err.code(), "wrong_kind");
    }
    check::<Cameras>("cameras");
    check::<Gaussians>("gaussians");
    check::<Masks>("masks");
    check::<Matches>("matches");
    check::<SparseMatches>("sparse_matches");
    check::<Proposals>("proposals");
    check::<Features>("features");
    check::<Pq>("pq");
    check::<Prompts>("prompts");
    check::<Selection>("selection");
    check::<VertexLabels>("vertex_labels");
    check::<Mesh>("mesh");
    check::<ViewMaps>("view_maps");
    check::<TopK>("topk");
    check::<FusePartial>("fuse_partial");
    check::<WarpPartial>("warp_partial");
}

#[test]
fn missing_file_is_an_io_error_naming_it() {
    let err = Gaussians::read("/nonexistent/g.safetensors").unwrap_err();
    assert_eq!(err.code(), "io");
    assert!(err.to_string().contains("/nonexistent/g.safetensors"));
}

/// A FIFO would block the open (and a reader) forever: it is refused at once, like a folder.
#[test]
fn a_fifo_or_folder_is_refused_instead_of_blocking() {
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("g.safetensors");
    if !std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .is_ok_and(|s| s.success())
    {
        eprintln!("SKIP: mkfifo is not available");
        return;
    }
    for path in [fifo.as_path(), dir.path()] {
        let err = Gaussians::read(path).unwrap_err();
        assert_eq!(err.code(), "io");
        assert!(err.to_string().contains("not a regular file"), "{err}");
    }
}

#[test]
fn samples_round_trip_and_are_zero_copy() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("g.safetensors");
    let g = samples::gaussians();
    g.write(&p).unwrap();
    let back = Gaussians::read(&p).unwrap();
    assert_eq!(back, g);
    assert!(back.means.is_zero_copy() && back.sh_rest.as_ref().unwrap().is_zero_copy());
    assert_eq!(back.counts().get("gaussians"), Some(&4));
}

/// The fuse_partial sample round-trips with its u128 sums intact (one above 2^64), its
/// counts are the hand-counted ones, and the writer refuses a file its reader would refuse.
#[test]
fn fuse_partial_round_trips_and_the_writer_validates() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("f.safetensors");
    let f = samples::fuse_partial();
    f.write(&p).unwrap();
    let back = FusePartial::read(&p).unwrap();
    assert_eq!(back, f);
    let sums: Vec<u128> = back.w_sums.iter().map(|w| fixed_point(*w)).collect();
    assert_eq!(sums, [3 << 40, 1 << 40, 2 << 40, 1u128 << 64]);
    assert_eq!(fixed_point_words(u128::MAX - 1), [u64::MAX - 1, u64::MAX]);
    let counts: Vec<(&str, u64)> = back.counts().into_iter().collect();
    assert_eq!(
        counts,
        [
            ("entries", 4),
            ("feature_dim", 2),
            ("gaussians", 4),
            ("groups", 3),
            ("masks", 3),
            ("summed_views", 2),
            ("views", 3)
        ]
    );
    let mut bad = f.clone();
    bad.w_sums = vec![[1, 0], [1, 0], [1, 0]].into();
    let err = bad.write(dir.path().join("bad.safetensors")).unwrap_err();
    assert_eq!((err.code(), err.field()), ("shape", Some("w_sums")));
    assert!(!dir.path().join("bad.safetensors").exists());
}

/// The warp_partial sample round-trips with its f64 scores bit for bit and its counters
/// and inputs under their metadata keys; the writer refuses scores that do not match the
/// links.
#[test]
fn warp_partial_round_trips_and_the_writer_validates() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("w.safetensors");
    let mut w = samples::warp_partial();
    w.edge_scores = vec![[0.1 + 0.2, 1.0 / 3.0], [f64::MIN_POSITIVE, 1.0]].into();
    w.write(&p).unwrap();
    let back = WarpPartial::read(&p).unwrap();
    assert_eq!(back, w);
    assert_eq!(back.edge_scores[0][0].to_bits(), (0.1f64 + 0.2).to_bits());
    let c = Container::open(&p).unwrap();
    assert_eq!(c.metadata()["cells_gated"], "80");
    assert_eq!(c.metadata()["input_gaussians"], "none");
    assert_eq!(WARP_COUNTERS[5], "cells_gated");
    let counts: Vec<(&str, u64)> = back.counts().into_iter().collect();
    assert_eq!(
        counts,
        [
            ("edges", 2),
            ("masks", 6),
            ("shard_pairs", 2),
            ("view_pairs", 4),
            ("views", 3)
        ]
    );
    let mut bad = w.clone();
    bad.edge_scores = vec![[0.5, 0.5]].into();
    let err = bad.write(dir.path().join("bad.safetensors")).unwrap_err();
    assert_eq!((err.code(), err.field()), ("shape", Some("edge_scores")));
    assert!(!dir.path().join("bad.safetensors").exists());
}

/// Past 65,535 proposals the index is U32 (SPEC.md §4.17): proposal 65,535 is then a
/// real proposal, and only u32::MAX means "none". It round-trips, and a U16 index is
/// refused for that many proposals with an error naming the tensor and the rule.
#[test]
fn a_semantic_index_over_more_than_65535_proposals_round_trips_as_u32() {
    let p = MAX_U16_PROPOSALS + 2;
    let table: Vec<f16> = (0..p)
        .map(|r| f16::from_f32(if r % 2 == 0 { 1.0 } else { -1.0 }))
        .collect();
    let ids = [Some(65_535), Some(0), None, Some(65_536), Some(7)];
    let si = SemanticIndex {
        descriptors: Floats::F16(table.into()),
        dim: 1,
        index: SemanticIndex::index_of(p, &ids),
        share: Some(vec![255u8, 128, 0, 200, 1].into()),
        min_share: quantise_share(0.5),
        extra: Default::default(),
    };
    assert!(matches!(si.index, Labels::U32(_)));
    round_trip(&si);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("si.safetensors");
    si.write(&path).unwrap();
    let back = SemanticIndex::read(&path).unwrap();
    let got: Vec<Option<u32>> = (0..5).map(|g| back.proposal(g)).collect();
    assert_eq!(got, ids);
    let dominant: Vec<bool> = (0..5).map(|g| back.is_dominant(g)).collect();
    assert_eq!(dominant, [true, true, false, true, false]);
    // The same proposals stored as U16 (65,535 would read as "none") are refused.
    let mut narrow = si.clone();
    narrow.index = Labels::U16(vec![65_535u16, 0, 65_535, 1, 7].into());
    let mut w = FileWriter::new(profuse_formats::Kind::SemanticIndex);
    narrow.fill(&mut w);
    let bytes = w.to_bytes().unwrap();
    let c = Container::from_vec("narrow.safetensors", bytes).unwrap();
    let err = SemanticIndex::from_checked_container(&c).unwrap_err();
    assert_eq!((err.code(), err.field()), ("dtype", Some("index")), "{err}");
    assert!(err.to_string().contains("U16 iff P <= 65535"), "{err}");
}

/// With `min_share` 0 the share cannot change which Gaussians are dominant, so the file
/// may omit it: the index alone, 2 bytes a Gaussian (SPEC.md §4.17). With `min_share` > 0
/// a missing share is a `missing_tensor` error naming it.
#[test]
fn a_semantic_index_without_share_is_two_bytes_a_gaussian_and_needs_min_share_0() {
    let mut si = samples::semantic_index();
    si.share = None;
    si.min_share = 0;
    round_trip(&si);
    let n = si.num_gaussians();
    let dominant: Vec<bool> = (0..n).map(|g| si.is_dominant(g)).collect();
    assert_eq!(dominant, [true, true, true, false, true]);
    let shares: Vec<u8> = (0..n).map(|g| si.share_of(g)).collect();
    assert_eq!(shares, [255, 255, 255, 0, 255]);
    let with = samples::semantic_index().to_bytes().unwrap();
    let without = si.to_bytes().unwrap();
    let c = Container::from_vec("x", without.clone()).unwrap();
    assert!(!c.tensors().contains_key("share"));
    // The tensor data shrinks by exactly the share's N bytes (headers differ too).
    assert!(without.len() < with.len());
    let mut needs = si.clone();
    needs.min_share = 1;
    let err = needs.to_bytes().unwrap_err();
    assert_eq!(
        (err.code(), err.field()),
        ("missing_tensor", Some("share")),
        "{err}"
    );
    let mut w = FileWriter::new(profuse_formats::Kind::SemanticIndex);
    needs.fill(&mut w);
    let c = Container::from_vec("needs.safetensors", w.to_bytes().unwrap()).unwrap();
    let err = SemanticIndex::from_checked_container(&c).unwrap_err();
    assert_eq!(
        (err.code(), err.field()),
        ("missing_tensor", Some("share")),
        "{err}"
    );
}

#[test]
fn misaligned_tensors_are_copied_not_rejected() {
    // Header padded to a length that leaves the data section 4 bytes off 8-alignment.
    let bytes = samples::cameras().to_bytes().unwrap();
    let shifted = samples::rewrite_header(&bytes, |h| {
        h.insert(
            "__pad__".into(),
            serde_json::json!({"dtype": "U8", "shape": [0], "data_offsets": [0, 0]}),
        );
    });
    let n = u64::from_le_bytes(shifted[..8].try_into().unwrap()) as usize;
    let mut text = shifted[8..8 + n].to_vec();
    text.extend_from_slice(b"    ");
    let mut odd = ((n + 4) as u64).to_le_bytes().to_vec();
    odd.extend_from_slice(&text);
    odd.extend_from_slice(&shifted[8 + n..]);
    let c = Container::from_vec("odd", odd).unwrap();
    let cams = Cameras::from_checked_container(&c).unwrap();
    assert!(!cams.intrinsics.is_zero_copy());
    assert_eq!(cams, samples::cameras());
}

#[test]
fn failed_write_leaves_the_existing_file_and_no_temporaries() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("prompts.safetensors");
    samples::prompts().write(&p).unwrap();
    let before = std::fs::read(&p).unwrap();
    let mut bad = samples::prompts();
    bad.names[1] = "chair".into();
    let err = bad.write(&p).unwrap_err();
    assert_eq!(err.code(), "metadata");
    assert_eq!(std::fs::read(&p).unwrap(), before);
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names.len(), 1, "{names:?}");
}

#[test]
fn write_to_a_missing_directory_is_an_io_error() {
    let err = samples::mesh()
        .write("/nonexistent-dir/x/mesh.safetensors")
        .unwrap_err();
    assert_eq!(err.code(), "io");
}

#[test]
fn helpers_agree_with_hand_computation() {
    let cams = samples::cameras();
    // View 0 sits at (0, 0, -4) looking down +z: the origin projects to the principal point.
    assert_eq!(cams.center(0), [0.0, 0.0, -4.0]);
    assert_eq!(cams.project(0, [0.0, 0.0, 0.0]), [4.0, 3.0, 4.0]);
    // View 1 is rotated so world +x maps to camera -z... its centre is at (-4, 0, 0)·R.
    let c1 = cams.center(1);
    let back = cams.project(1, [0.0, 0.0, 0.0]);
    assert!((back[2] - 4.0).abs() < 1e-12 && c1.iter().map(|v| v * v).sum::<f64>() == 16.0);
    let m = samples::masks();
    assert_eq!(m.view_of(0), 0);
    assert_eq!(m.view_of(3), 1);
    assert_eq!(m.mask_at(1, 2, 0), Some(3));
    assert_eq!(m.mask_at(0, 3, 1), None);
}

// ---------------------------------------------------------------------------------------
// Property tests: arbitrary valid values of every kind survive write-then-read exactly.

fn finite() -> impl Strategy<Value = f32> {
    -1e6f32..1e6f32
}

fn unit_rows(n: usize, d: usize) -> impl Strategy<Value = Vec<f32>> {
    proptest::collection::vec(proptest::collection::vec(-1.0f32..1.0, d), n).prop_map(move |rows| {
        rows.into_iter()
            .flat_map(|mut r| {
                r[0] += 2.0; // never the zero row
                let norm = r.iter().map(|v| v * v).sum::<f32>().sqrt();
                r.into_iter().map(move |v| v / norm)
            })
            .collect()
    })
}

fn round_trip<K: FileKind + PartialEq + std::fmt::Debug>(value: &K) {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("x.safetensors");
    value.write(&p).unwrap();
    let back = K::read(&p).unwrap();
    assert_eq!(&back, value);
    assert_eq!(value.to_bytes().unwrap(), std::fs::read(&p).unwrap());
}

fn rotation(a: f64, b: f64) -> [f64; 9] {
    let (ca, sa, cb, sb) = (a.cos(), a.sin(), b.cos(), b.sin());
    // Rz(a) * Rx(b)
    [ca, -sa * cb, sa * sb, sa, ca * cb, -ca * sb, 0.0, sb, cb]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn cameras_round_trip(views in proptest::collection::vec((1u32..4000, 1u32..4000, 1.0f64..5000.0, -3.2f64..3.2, -3.2f64..3.2, -100.0f64..100.0), 0..5), distorted in any::<bool>()) {
        let n = views.len();
        let cams = Cameras {
            image_names: (0..n).map(|i| format!("images/{i:04}.jpg")).collect(),
            image_size: views.iter().map(|v| [v.0, v.1]).collect::<Vec<_>>().into(),
            intrinsics: views.iter().map(|v| [v.2, v.2 * 1.01, f64::from(v.0) / 2.0, f64::from(v.1) / 2.0]).collect::<Vec<_>>().into(),
            world_to_camera: views.iter().map(|v| {
                let r = rotation(v.3, v.4);
                [r[0], r[1], r[2], v.5, r[3], r[4], r[5], -v.5, r[6], r[7], r[8], 1.0]
            }).collect::<Vec<_>>().into(),
            distortion: distorted.then(|| vec![[0.01, -0.002, 0.0, 1e-4]; n].into()),
            extra: Default::default(),
        };
        round_trip(&cams);
    }

    #[test]
    fn gaussians_round_trip(n in 0usize..20, degree in 0usize..4, seed in any::<u32>(), labelled in any::<bool>()) {
        let v = |k: usize| ((seed as usize).wrapping_mul(31).wrapping_add(k * 17) % 1000) as f32 / 100.0 - 5.0;
        let coeffs = profuse_formats::SH_REST_COEFFS[degree];
        let g = Gaussians {
            means: (0..n).map(|i| [v(i), v(i + 1), v(i + 2)]).collect::<Vec<_>>().into(),
            log_scales: (0..n).map(|i| [v(i) / 2.0, -1.0, v(i + 5) / 3.0]).collect::<Vec<_>>().into(),
            rotations: (0..n).map(|i| [1.0 + v(i).abs(), v(i), 0.0, v(i + 3)]).collect::<Vec<_>>().into(),
            opacity_logits: (0..n).map(v).collect::<Vec<_>>().into(),
            sh_dc: (0..n).map(|i| [v(i + 7), v(i + 8), v(i + 9)]).collect::<Vec<_>>().into(),
            sh_degree: degree,
            sh_rest: (degree > 0).then(|| (0..n * coeffs * 3).map(v).collect::<Vec<_>>().into()),
            class_ids: labelled.then(|| (0..n).map(|i| (i % 5) as i32 - 1).collect::<Vec<_>>().into()),
            extra: Default::default(),
        };
        round_trip(&g);
    }

    #[test]
    fn masks_round_trip(views in 0usize..4, h in 1usize..6, w in 1usize..6, per_view in 0u32..5, wide in any::<bool>(), seed in any::<u64>()) {
        let m = per_view as usize * views;
        let mut rng = seed;
        let mut next = move || { rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407); (rng >> 33) as u32 };
        let labels: Vec<u32> = (0..views * h * w).map(|_| { let r = next() % (per_view + 1); if r == per_view { u32::MAX } else { r } }).collect();
        let feats: Vec<f32> = (0..m).flat_map(|i| { let mut r = [0.0f32; 8]; r[i % 8] = 1.0; r }).collect();
        let masks = Masks {
            view_names: (0..views).map(|i| format!("v{i}")).collect(),
            width: w, height: h,
            labels: if wide { Labels::U32(labels.into()) } else { Labels::U16(labels.into_iter().map(|l| if l == u32::MAX { u16::MAX } else { l as u16 }).collect::<Vec<_>>().into()) },
            mask_offsets: (0..=views as u32).map(|v| v * per_view).collect::<Vec<_>>().into(),
            features: if wide { Floats::F32(feats.into()) } else { Floats::F16(feats.into_iter().map(f16::from_f32).collect::<Vec<_>>().into()) },
            dim: 8,
            extra: Default::default(),
        };
        round_trip(&masks);
    }

    #[test]
    fn matches_round_trip(pairs in 0usize..4, h in 0usize..5, w in 0usize..5, half in any::<bool>(), vals in proptest::collection::vec(0.0f32..1.0, 200)) {
        let cells = pairs * h * w;
        let warp: Vec<f32> = (0..cells * 2).map(|i| vals[i % 200] * 4.0 - 2.0).collect();
        let cert: Vec<f32> = (0..cells).map(|i| vals[(i * 7) % 200]).collect();
        let to = |v: Vec<f32>| if half { Floats::F16(v.into_iter().map(f16::from_f32).collect::<Vec<_>>().into()) } else { Floats::F32(v.into()) };
        let m = Matches {
            num_views: 5,
            pairs: (0..pairs as u32).map(|p| [p, p + 1]).collect::<Vec<_>>().into(),
            height: h, width: w,
            warp: to(warp), certainty: to(cert),
            coords: if half { WarpCoords::Pixels } else { WarpCoords::Normalized },
            extra: Default::default(),
        };
        round_trip(&m);
    }

    #[test]
    fn sparse_matches_round_trip(counts in proptest::collection::vec(0u64..6, 0..5), p in (finite(), finite())) {
        let n = counts.iter().sum::<u64>() as usize;
        let mut offsets = vec![0u64];
        for c in &counts { offsets.push(offsets.last().unwrap() + c); }
        let m = SparseMatches {
            num_views: counts.len() + 1,
            pairs: (0..counts.len() as u32).map(|i| [i + 1, i]).collect::<Vec<_>>().into(),
            pair_offsets: offsets.into(),
            points_i: vec![[p.0, p.1]; n].into(),
            points_j: vec![[p.1, p.0]; n].into(),
            certainty: (0..n).map(|i| (i % 3) as f32 / 2.0).collect::<Vec<_>>().into(),
            extra: Default::default(),
        };
        round_trip(&m);
    }

    /// `merged` against a brute force: for every ordered pair, the matches of both inputs
    /// in input order; each pair once; a valid file.
    #[test]
    fn sparse_matches_merge_keeps_every_match_of_every_pair(
        a in proptest::collection::vec((0u32..4, 0u32..4, 0u64..4), 0..6),
        b in proptest::collection::vec((0u32..4, 0u32..4, 0u64..4), 0..6),
    ) {
        let build = |spec: &[(u32, u32, u64)], tag: f32| {
            let mut seen = std::collections::BTreeSet::new();
            let rows: Vec<(u32, u32, u64)> = spec.iter().copied().filter(|(i, j, _)| i != j && seen.insert((*i, *j))).collect();
            let mut offsets = vec![0u64];
            let (mut pi, mut pj) = (Vec::new(), Vec::new());
            for (p, (_, _, c)) in rows.iter().enumerate() {
                for k in 0..*c { pi.push([tag, p as f32]); pj.push([k as f32, tag]); }
                offsets.push(pi.len() as u64);
            }
            let n = pi.len();
            SparseMatches {
                num_views: 4,
                pairs: rows.iter().map(|(i, j, _)| [*i, *j]).collect::<Vec<_>>().into(),
                pair_offsets: offsets.into(),
                points_i: pi.into(),
                points_j: pj.into(),
                certainty: vec![tag / 2.0; n].into(),
                extra: Default::default(),
            }
        };
        let (x, y) = (build(&a, 1.0), build(&b, 2.0));
        let m = x.merged(&y);
        round_trip(&m);
        let brute = |f: &SparseMatches, pair: [u32; 2]| -> Vec<([f32; 2], [f32; 2], f32)> {
            f.pairs.iter().position(|p| *p == pair).map(|p| f.range(p).map(|k| (f.points_i[k], f.points_j[k], f.certainty[k])).collect()).unwrap_or_default()
        };
        let mut pairs: Vec<[u32; 2]> = x.pairs.iter().chain(y.pairs.iter()).copied().collect();
        pairs.sort_unstable(); pairs.dedup();
        prop_assert_eq!(m.pairs.len(), pairs.len());
        for pair in pairs {
            let mut want = brute(&x, pair);
            want.extend(brute(&y, pair));
            prop_assert_eq!(brute(&m, pair), want);
        }
        prop_assert_eq!(m.points_i.len(), x.points_i.len() + y.points_i.len());
    }

    #[test]
    fn proposals_round_trip(assign in proptest::collection::vec(0u32..6, 0..30)) {
        // Value 5 means "none"; proposals are the distinct ids used, renumbered densely.
        let mut ids: Vec<u32> = assign.iter().copied().filter(|a| *a < 5).collect();
        ids.sort_unstable(); ids.dedup();
        let mask_proposal: Vec<u32> = assign.iter().map(|a| ids.iter().position(|i| i == a).map_or(u32::MAX, |p| p as u32)).collect();
        let size: Vec<u32> = (0..ids.len() as u32).map(|p| mask_proposal.iter().filter(|m| **m == p).count() as u32).collect();
        // Shares in (0, 1] for the even cases, none for the odd ones.
        let mask_share = (assign.len() % 2 == 0).then(|| assign.iter().map(|a| (*a + 1) as f32 / 6.0).collect::<Vec<f32>>().into());
        let p = Proposals { mask_proposal: mask_proposal.into(), proposal_views: size.clone().into(), proposal_size: size.into(), mask_share, mask_instance: None, extra: Default::default() };
        round_trip(&p);
    }

    #[test]
    fn features_round_trip(valid in proptest::collection::vec(any::<bool>(), 0..12), rows in unit_rows(12, 6), half in any::<bool>()) {
        let n = valid.len();
        let mut f = rows[..n * 6].to_vec();
        for (i, v) in valid.iter().enumerate() { if !v { f[i * 6..(i + 1) * 6].fill(0.0); } }
        let feats = if half {
            // Renormalise after rounding so F16 rows stay within the F16 tolerance.
            Floats::F16(f.iter().map(|v| f16::from_f32(*v)).collect::<Vec<_>>().into())
        } else { Floats::F32(f.into()) };
        let x = Features {
            features: feats, dim: 6,
            valid: valid.iter().map(|v| u8::from(*v)).collect::<Vec<_>>().into(),
            weight_sum: Some(valid.iter().map(|v| if *v { 0.5 } else { 0.0 }).collect::<Vec<_>>().into()),
            extra: Default::default(),
        };
        round_trip(&x);
    }

    #[test]
    fn pq_round_trip(n in 0usize..10, m in 1usize..4, dsub in 1usize..3, seed in any::<u8>()) {
        let q = Pq {
            m, dsub,
            centroids: (0..m * 256 * dsub).map(|i| (i as f32 * 0.37 + f32::from(seed)).sin()).collect::<Vec<_>>().into(),
            codes: (0..n * m).map(|i| (i * 13 + usize::from(seed)) as u8).collect::<Vec<_>>().into(),
            norms: (0..n).map(|i| if i % 3 == 2 { 0.0 } else { 1.0 + i as f32 }).collect::<Vec<_>>().into(),
            valid: (0..n).map(|i| u8::from(i % 3 != 2)).collect::<Vec<_>>().into(),
            extra: Default::default(),
        };
        round_trip(&q);
    }

    #[test]
    fn prompts_round_trip(names in proptest::collection::btree_set("[a-z ]{1,12}", 0..6), rows in unit_rows(6, 5)) {
        let names: Vec<String> = names.into_iter().collect();
        let q = names.len();
        let p = Prompts { dim: 5, embeddings: rows[..q * 5].to_vec().into(), class_ids: Some((0..q as i32).map(|i| i - 1).collect::<Vec<_>>().into()), names, extra: Default::default() };
        round_trip(&p);
    }

    #[test]
    fn selection_round_trip(ids in proptest::collection::btree_set(0u32..1000, 0..50), prompt in "[a-zA-Z ]{1,20}") {
        let s = Selection { prompt, num_gaussians: 1000, scores: ids.iter().map(|i| *i as f32 / 1000.0).collect::<Vec<_>>().into(), gaussian_ids: ids.into_iter().collect::<Vec<_>>().into(), extra: Default::default() };
        round_trip(&s);
    }

    #[test]
    fn vertex_labels_and_mesh_round_trip(labels in proptest::collection::vec(-1i32..41, 0..40)) {
        let n = labels.len();
        let vl = VertexLabels { confidence: Some(labels.iter().map(|l| if *l < 0 { 0.0 } else { 0.5 }).collect::<Vec<_>>().into()), labels: labels.clone().into(), extra: Default::default() };
        round_trip(&vl);
        let mesh = Mesh {
            vertices: (0..n).map(|i| [i as f32, 0.5, -1.0]).collect::<Vec<_>>().into(),
            colors: Some((0..n).map(|i| [i as u8, 0, 255]).collect::<Vec<_>>().into()),
            faces: (n >= 3).then(|| (0..n as u32 - 2).map(|i| [i, i + 1, i + 2]).collect::<Vec<_>>().into()),
            labels: Some(labels.iter().map(|l| (*l).max(0) as u32).collect::<Vec<_>>().into()),
            instances: None,
            extra: Default::default(),
        };
        round_trip(&mesh);
    }

    #[test]
    fn view_maps_round_trip(views in 0usize..3, h in 0usize..4, w in 0usize..4, ids in any::<bool>()) {
        let n = views * h * w;
        let m = ViewMaps {
            view_names: (0..views).map(|i| format!("v{i}")).collect(),
            num_objects: 4, width: w, height: h,
            depth: (0..n).map(|i| i as f32 * 0.5).collect::<Vec<_>>().into(),
            object_ids: ids.then(|| (0..n as u32).map(|i| if i % 5 == 4 { u32::MAX } else { i % 4 }).collect::<Vec<_>>().into()),
            extra: Default::default(),
        };
        round_trip(&m);
    }

    #[test]
    fn topk_round_trip(h in 0usize..4, w in 0usize..4, k in 1usize..5, hits in proptest::collection::vec(0usize..5, 16)) {
        let pixels = h * w;
        let mut ids = Vec::new();
        let mut weights = Vec::new();
        let mut t = Vec::new();
        for p in 0..pixels {
            let n = hits[p % 16].min(k);
            let mut remaining = 1.0f32;
            for s in 0..k {
                if s < n { ids.push((p * 3 + s) as u32 % 10); weights.push(remaining * 0.5); remaining *= 0.5; } else { ids.push(u32::MAX); weights.push(0.0); }
            }
            t.push(remaining);
        }
        let x = TopK { num_gaussians: 10, width: w, height: h, k, ids: ids.into(), weights: weights.into(), transmittance: t.into(), extra: Default::default() };
        round_trip(&x);
    }
}

/// The reference safetensors implementation accepts every valid file we write, and
/// sees the same tensors and metadata.
#[test]
fn reference_safetensors_crate_reads_our_files() {
    for v in samples::vectors()
        .iter()
        .filter(|v| v.expect_error.is_none())
    {
        let st = safetensors::SafeTensors::deserialize(&v.bytes)
            .unwrap_or_else(|e| panic!("{}: {e}", v.name));
        let ours = Container::from_vec(v.name.clone(), v.bytes.clone()).unwrap();
        assert_eq!(st.len(), ours.tensors().len(), "{}", v.name);
        for (name, info) in ours.tensors() {
            let t = st.tensor(name).unwrap();
            assert_eq!(t.shape(), info.shape.as_slice(), "{} {name}", v.name);
            assert_eq!(t.data(), ours.raw(name).unwrap(), "{} {name}", v.name);
        }
        let (_, meta) = safetensors::SafeTensors::read_metadata(&v.bytes).unwrap();
        let meta: std::collections::BTreeMap<String, String> = meta
            .metadata()
            .clone()
            .unwrap_or_default()
            .into_iter()
            .collect();
        assert_eq!(&meta, ours.metadata(), "{}", v.name);
    }
}

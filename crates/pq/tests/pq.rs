//! Integration tests of `profuse-pq` against independent references: brute-force
//! nearest centroids, decoded dot products, brute-force exact top-k, Lloyd fixed points,
//! and faiss itself (through `python/test_faiss_compat.py`).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

use profuse_formats::{f16, Features, FileKind, Floats, Pq};
use profuse_pq::{
    adc_scores, decode, decode_all, exact_cosine, search, synthetic::Clustered, train,
    train_vectors, Codebook, FastScan, LookupTable, PqError, TrainParams, DEFAULT_SHORTLIST, KSUB,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn random_codebook(m: usize, dsub: usize, seed: u64) -> Codebook {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let c: Vec<f32> = (0..m * KSUB * dsub)
        .map(|_| rng.random_range(-1.0f32..1.0))
        .collect();
    Codebook::new(m, dsub, c).unwrap()
}

fn small_params(m: usize) -> TrainParams {
    TrainParams {
        m,
        iters: 8,
        sample: 4096,
        seed: 11,
    }
}

fn features_from(data: Vec<f32>, dim: usize, valid: Vec<u8>) -> Features {
    Features {
        features: Floats::F32(data.into()),
        dim,
        valid: valid.into(),
        weight_sum: None,
        extra: BTreeMap::new(),
    }
}

fn dist_f64(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(&x, &y)| (f64::from(x) - f64::from(y)).powi(2))
        .sum()
}

#[test]
fn encode_picks_the_nearest_centroid_by_brute_force() {
    let (m, dsub) = (6, 3);
    let cb = random_codebook(m, dsub, 1);
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let mut code = vec![0u8; m];
    let mut near_ties = 0;
    for _ in 0..500 {
        let x: Vec<f32> = (0..m * dsub)
            .map(|_| rng.random_range(-1.2f32..1.2))
            .collect();
        cb.encode(&x, &mut code);
        for s in 0..m {
            let xs = &x[s * dsub..(s + 1) * dsub];
            let d: Vec<f64> = (0..KSUB).map(|k| dist_f64(xs, cb.centroid(s, k))).collect();
            let best = (0..KSUB)
                .min_by(|&a, &b| d[a].total_cmp(&d[b]).then(a.cmp(&b)))
                .unwrap();
            if best != code[s] as usize {
                // Only an f32 rounding near-tie may pick another centroid.
                assert!(
                    (d[code[s] as usize] - d[best]).abs() <= 1e-6 * d[best].max(1e-6),
                    "subspace {s}: picked {} at {}, nearest {best} at {}",
                    code[s],
                    d[code[s] as usize],
                    d[best]
                );
                near_ties += 1;
            }
        }
    }
    assert!(near_ties <= 1, "{near_ties} near-ties out of 3000");
}

#[test]
fn encode_breaks_ties_toward_the_lower_centroid_index() {
    let (m, dsub) = (2, 2);
    let mut c = vec![5.0f32; m * KSUB * dsub];
    // Sub-quantiser 0: centroids 7 and 200 are the same point; sub-quantiser 1: 3 and 9
    // are equidistant from the query sub-vector (0, 0).
    c[7 * 2..7 * 2 + 2].copy_from_slice(&[1.0, 1.0]);
    c[200 * 2..200 * 2 + 2].copy_from_slice(&[1.0, 1.0]);
    let off = KSUB * dsub;
    c[off + 9 * 2..off + 9 * 2 + 2].copy_from_slice(&[0.0, -0.5]);
    c[off + 3 * 2..off + 3 * 2 + 2].copy_from_slice(&[0.5, 0.0]);
    let cb = Codebook::new(m, dsub, c).unwrap();
    let mut code = [0u8; 2];
    cb.encode(&[1.0, 1.0, 0.0, 0.0], &mut code);
    assert_eq!(code, [7, 3]);
}

#[test]
fn decode_of_encode_is_exact_for_centroid_concatenations() {
    let (m, dsub) = (8, 4);
    let cb = random_codebook(m, dsub, 3);
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let n = 300;
    let mut want_codes = vec![0u8; n * m];
    rng.fill(&mut want_codes[..]);
    let mut data = vec![0f32; n * m * dsub];
    for (row, code) in data
        .chunks_exact_mut(m * dsub)
        .zip(want_codes.chunks_exact(m))
    {
        for (s, &c) in code.iter().enumerate() {
            row[s * dsub..(s + 1) * dsub].copy_from_slice(cb.centroid(s, c as usize));
        }
    }
    let mut codes = vec![0u8; n * m];
    cb.encode_batch(&data, &mut codes);
    assert_eq!(codes, want_codes);
    let pq = cb.to_pq(codes, vec![1.0; n], vec![1; n]);
    assert_eq!(decode_all(&pq), data);
    let mut one = vec![0f32; m * dsub];
    decode(&pq, 17, &mut one);
    assert_eq!(one, &data[17 * m * dsub..18 * m * dsub]);
}

/// Encoded features: 3000 clustered 64-d vectors, every 7th invalid, M = 16.
fn encoded_clustered(n: usize) -> (Clustered, Features, Pq) {
    let gen = Clustered::new(64, 40, 0.6, 5);
    let features = gen.features(n, 7);
    let cb = train(&features, &small_params(16)).unwrap();
    let pq = cb.encode_features(&features).unwrap();
    (gen, features, pq)
}

#[test]
fn invalid_rows_get_code_0_norm_0_decode_to_zero_and_score_0() {
    let (gen, features, pq) = encoded_clustered(3000);
    assert_eq!(&pq.valid[..], &features.valid[..]);
    let decoded = decode_all(&pq);
    let q = gen.query(2, 0.3, 1);
    let scores = adc_scores(&pq, &q).unwrap();
    for i in 0..pq.len() {
        let row = &decoded[i * 64..(i + 1) * 64];
        if i % 7 == 6 {
            assert_eq!(pq.valid[i], 0);
            assert!(pq.codes[i * 16..(i + 1) * 16].iter().all(|&c| c == 0));
            assert_eq!(pq.norms[i], 0.0);
            assert!(row.iter().all(|&v| v == 0.0));
            assert_eq!(scores[i], 0.0);
        } else {
            let norm = row
                .iter()
                .map(|&v| f64::from(v).powi(2))
                .sum::<f64>()
                .sqrt();
            assert!((f64::from(pq.norms[i]) - norm).abs() < 1e-6, "row {i}");
        }
    }
    let top = search(&pq, &q, pq.len(), pq.len()).unwrap();
    assert_eq!(top.len(), pq.len() - pq.len() / 7);
    assert!(top.iter().all(|&(id, _)| id % 7 != 6));

    // The file round-trips through the validated writer and reader.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("pq.safetensors");
    pq.write(&path).unwrap();
    let back = Pq::read(&path).unwrap();
    assert_eq!(back, pq);
    assert_eq!(back.extra["train_samples"], "2572");
    assert_eq!(back.extra["kmeans_iters"], "8");
    assert_eq!(back.extra["seed"], "11");
}

#[test]
fn adc_inner_product_equals_the_decoded_dot_product() {
    let (gen, _, pq) = encoded_clustered(3000);
    let decoded = decode_all(&pq);
    let q = gen.query(5, 0.3, 2);
    let lut = LookupTable::new(&pq, &q).unwrap();
    let qn = q.iter().map(|&v| f64::from(v).powi(2)).sum::<f64>().sqrt();
    let scores = adc_scores(&pq, &q).unwrap();
    let mut ips = vec![0f32; pq.len()];
    lut.inner_products(&pq.codes, &mut ips);
    for i in (0..pq.len()).filter(|&i| pq.valid[i] == 1) {
        let x = &decoded[i * 64..(i + 1) * 64];
        let dot: f64 = x
            .iter()
            .zip(&q)
            .map(|(&a, &b)| f64::from(a) * f64::from(b))
            .sum();
        let code = &pq.codes[i * 16..(i + 1) * 16];
        let ip = lut.inner_product(code);
        assert!((f64::from(ip) - dot).abs() < 1e-5, "{i}: {ip} vs {dot}");
        // The batched kernel adds in the same order, so it agrees bit for bit.
        assert_eq!(ips[i].to_bits(), ip.to_bits(), "{i}");
        let cos = dot / (qn * f64::from(pq.norms[i]));
        assert!((f64::from(scores[i]) - cos).abs() < 1e-5, "{i}");
        assert!((f64::from(exact_cosine(&pq, i, &q)) - cos).abs() < 1e-6);
    }
    // Scattered ids (repeats, any order, a remainder past the groups of four) too.
    let ids: Vec<u32> = (0..1003u32).map(|i| (i * 7919 + 13) % 3000).collect();
    let mut got = vec![0f32; ids.len()];
    lut.inner_products_of(&pq.codes, &ids, &mut got);
    for (&id, g) in ids.iter().zip(&got) {
        assert_eq!(g.to_bits(), ips[id as usize].to_bits(), "{id}");
    }
}

/// The exact top-k by brute force over decoded vectors (f64), best first, ties by id.
fn brute_force_top(pq: &Pq, q: &[f32], k: usize) -> Vec<(u32, f32)> {
    let d = pq.dim();
    let decoded = decode_all(pq);
    let qn = q.iter().map(|&v| f64::from(v).powi(2)).sum::<f64>().sqrt();
    let mut all: Vec<(u32, f32)> = (0..pq.len())
        .filter(|&i| pq.valid[i] == 1)
        .map(|i| {
            let x = &decoded[i * d..(i + 1) * d];
            let dot: f64 = x
                .iter()
                .zip(q)
                .map(|(&a, &b)| f64::from(a) * f64::from(b))
                .sum();
            let xn = x.iter().map(|&v| f64::from(v).powi(2)).sum::<f64>().sqrt();
            (i as u32, (dot / (qn * xn)) as f32)
        })
        .collect();
    all.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    all.truncate(k);
    all
}

#[test]
fn search_with_a_full_shortlist_equals_brute_force_exact_top_k() {
    let (gen, _, pq) = encoded_clustered(3000);
    for (qi, k) in [(0usize, 10usize), (7, 100), (13, 2999)] {
        let q = gen.query(qi, 0.4, qi as u64);
        let got = search(&pq, &q, pq.len(), k).unwrap();
        let want = brute_force_top(&pq, &q, k);
        assert_eq!(got, want, "query {qi}, k {k}");
    }
}

#[test]
fn search_orders_equal_scores_by_id() {
    // Duplicated vectors have identical codes and scores: they must come by ascending id.
    let gen = Clustered::new(32, 3, 0.3, 9);
    let base = gen.features(400, 0);
    let mut data = vec![0f32; 800 * 32];
    base.features.read_into(0, &mut data[..400 * 32]);
    base.features.read_into(0, &mut data[400 * 32..]);
    let features = features_from(data, 32, vec![1; 800]);
    let cb = train(&features, &small_params(8)).unwrap();
    let pq = cb.encode_features(&features).unwrap();
    let got = search(&pq, gen.prototype(1), 50, 20).unwrap();
    for pair in got.windows(2) {
        assert!(pair[0].1 > pair[1].1 || (pair[0].1 == pair[1].1 && pair[0].0 < pair[1].0));
    }
    assert_eq!(got[0].0 + 400, got[1].0, "{got:?}");
    assert_eq!(got, brute_force_top(&pq, gen.prototype(1), 20));
}

#[test]
fn adc_shortlist_is_the_top_of_all_adc_scores_in_rank_order() {
    // 70000 random codes (two scan chunks of 65536); the second half repeats the first,
    // so equal scores straddle the chunk boundary and the id tie-break decides.
    let cb = random_codebook(8, 4, 12);
    let half = 35_000;
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let mut codes = vec![0u8; half * 8];
    rng.fill(&mut codes[..]);
    codes.extend_from_within(..);
    let valid: Vec<u8> = (0..2 * half).map(|i| u8::from(i % 13 != 0)).collect();
    for (i, &v) in valid.iter().enumerate() {
        if v == 0 {
            codes[i * 8..(i + 1) * 8].fill(0);
        }
    }
    let norms: Vec<f32> = codes
        .chunks_exact(8)
        .zip(&valid)
        .map(|(c, &v)| if v == 1 { cb.decoded_norm(c) } else { 0.0 })
        .collect();
    let pq = cb.to_pq(codes, norms, valid);
    let q: Vec<f32> = (0..32).map(|i| (i as f32 * 0.7).cos()).collect();
    let scores = adc_scores(&pq, &q).unwrap();
    let mut all: Vec<(u32, f32)> = (0..2 * half as u32)
        .filter(|&i| pq.valid[i as usize] == 1)
        .map(|i| (i, scores[i as usize]))
        .collect();
    all.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    for len in [1, 37, 500, 4000, 70_000] {
        let got = profuse_pq::adc_shortlist(&pq, &q, len).unwrap();
        assert_eq!(got, all[..len.min(all.len())], "shortlist {len}");
    }
    assert!(search(&pq, &q, 10, 0).unwrap().is_empty());
    // A shortlist below k is raised to k.
    assert_eq!(
        search(&pq, &q, 1, 50).unwrap(),
        brute_force_top(&pq, &q, 50)
    );
}

#[test]
fn adc_shortlist_recall_at_100_is_at_least_0_99_at_the_default_shortlist() {
    // 20000 CLIP-like vectors in 128-d, 200 classes (100 vectors each), M = 32 (dsub 4).
    let gen = Clustered::new(128, 200, 0.62, 21);
    let features = gen.features(20_000, 0);
    let params = TrainParams {
        m: 32,
        iters: 4,
        sample: 4096,
        seed: 3,
    };
    let cb = train(&features, &params).unwrap();
    let pq = cb.encode_features(&features).unwrap();
    let mut recall = 0.0;
    let queries = 8;
    for qi in 0..queries {
        let q = gen.query(qi * 25, 0.5, qi as u64);
        let truth = brute_force_top(&pq, &q, 100);
        let short = profuse_pq::adc_shortlist(&pq, &q, DEFAULT_SHORTLIST).unwrap();
        let ids: std::collections::HashSet<u32> = short.iter().map(|r| r.0).collect();
        recall += truth.iter().filter(|r| ids.contains(&r.0)).count() as f64 / 100.0;
        // And the re-ranked result is the exact top 100.
        assert_eq!(search(&pq, &q, DEFAULT_SHORTLIST, 100).unwrap(), truth);
    }
    recall /= queries as f64;
    assert!(recall >= 0.99, "recall@100 {recall}");
    // The quantiser keeps the descriptors recognisable.
    let cos = profuse_pq::reconstruction_cosine(&features, &pq).unwrap();
    assert!(cos > 0.9, "reconstruction cosine {cos}");
}

/// A pq of `n` CLIP-like 128-d vectors in `classes` classes (every 11th invalid), M = 32.
fn clip_like_pq(n: usize, classes: usize, seed: u64) -> (Clustered, Pq) {
    let gen = Clustered::new(128, classes, 0.62, seed);
    let pq = gen.quick_pq(n, 32).unwrap();
    (gen, pq)
}

#[test]
fn fast_scan_returns_the_exact_top_k() {
    // Few large classes: the ADC top 1000 of a query is a sliver of its class, ranked by
    // detail that the 4-bit codes do not see, so the candidate rounds must find it.
    for (n, classes, seed) in [
        (30_000usize, 6usize, 31u64),
        (20_000, 200, 32),
        (5_000, 1, 33),
    ] {
        let (gen, pq) = clip_like_pq(n, classes, seed);
        let fs = FastScan::new(&pq).unwrap();
        assert_eq!(fs.packed_bytes(), n.div_ceil(32) * 16 * 32);
        for qi in 0..6 {
            let q = gen.query(qi % classes, 0.5, qi as u64 + 100);
            let exact = brute_force_top(&pq, &q, 100);
            assert_eq!(search(&pq, &q, DEFAULT_SHORTLIST, 100).unwrap(), exact);
            for k in [100, 10, 40, 1] {
                let (got, stats) = fs.search(&pq, &q, k).unwrap();
                assert_eq!(got, exact[..k], "n {n} classes {classes} query {qi} k {k}");
                assert!(stats.candidates >= k);
                assert!(stats.rounds >= 1);
            }
        }
    }
}

#[test]
fn fast_scan_handles_ties_invalid_rows_tiny_inputs_and_k_0() {
    // Duplicated vectors (equal scores across block boundaries), every 13th invalid.
    let cb = random_codebook(6, 4, 41);
    let half = 1_000;
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let mut codes = vec![0u8; half * 6];
    rng.fill(&mut codes[..]);
    codes.extend_from_within(..);
    let valid: Vec<u8> = (0..2 * half).map(|i| u8::from(i % 13 != 0)).collect();
    let norms: Vec<f32> = codes
        .chunks_exact(6)
        .zip(&valid)
        .map(|(c, &v)| if v == 1 { cb.decoded_norm(c) } else { 0.0 })
        .collect();
    let pq = cb.to_pq(codes, norms, valid);
    let fs = FastScan::new(&pq).unwrap();
    for qi in 0..5 {
        let q: Vec<f32> = (0..24)
            .map(|i| ((i * (qi + 2)) as f32 * 0.37).sin())
            .collect();
        for k in [100, 3, 2000, 1] {
            let want = brute_force_top(&pq, &q, k);
            assert_eq!(fs.search(&pq, &q, k).unwrap().0, want, "q {qi} k {k}");
        }
        assert!(fs.search(&pq, &q, 0).unwrap().0.is_empty());
    }
    // Fewer vectors than a block, and no valid vector at all.
    let small = cb.to_pq(
        pq.codes[..5 * 6].to_vec(),
        pq.norms[..5].to_vec(),
        vec![1, 0, 1, 1, 0],
    );
    let q: Vec<f32> = (0..24).map(|i| i as f32 - 11.5).collect();
    let fs_small = FastScan::new(&small).unwrap();
    assert_eq!(
        fs_small.search(&small, &q, 10).unwrap().0,
        brute_force_top(&small, &q, 10)
    );
    let none = cb.to_pq(vec![0; 3 * 6], vec![0.0; 3], vec![0; 3]);
    assert!(FastScan::new(&none)
        .unwrap()
        .search(&none, &q, 10)
        .unwrap()
        .0
        .is_empty());
    // Wrong pq, wrong query: typed errors.
    assert!(matches!(
        fs.search(&small, &q, 10),
        Err(PqError::Inconsistent(_))
    ));
    assert!(matches!(
        fs.search(&pq, &q[..20], 10),
        Err(PqError::QueryDim { .. })
    ));
    assert!(matches!(
        fs.search(&pq, &[0.0; 24], 10),
        Err(PqError::DegenerateQuery)
    ));
}

#[test]
fn fast_scan_groups_cover_16_groups_per_subspace() {
    let (_, pq) = clip_like_pq(8_000, 20, 51);
    let fs = FastScan::new(&pq).unwrap();
    for s in 0..pq.m {
        let groups: std::collections::BTreeSet<u8> =
            (0..=255u8).map(|c| fs.group_of(s, c)).collect();
        assert!(groups.iter().all(|&g| g < 16));
        assert_eq!(groups.len(), 16, "subspace {s} uses every group");
    }
}

#[test]
fn training_is_identical_with_1_and_4_threads() {
    let gen = Clustered::new(32, 30, 0.6, 2);
    let features = gen.features(6000, 9);
    let params = TrainParams {
        m: 8,
        iters: 5,
        sample: 3000,
        seed: 77,
    };
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                let cb = train(&features, &params).unwrap();
                cb.encode_features(&features).unwrap()
            })
    };
    let (one, four) = (run(1), run(4));
    assert_eq!(one, four);
    let dir = tempfile::tempdir().unwrap();
    one.write(dir.path().join("a.safetensors")).unwrap();
    four.write(dir.path().join("b.safetensors")).unwrap();
    assert_eq!(
        std::fs::read(dir.path().join("a.safetensors")).unwrap(),
        std::fs::read(dir.path().join("b.safetensors")).unwrap()
    );
    // Another seed gives another codebook.
    let other = train(&features, &TrainParams { seed: 78, ..params }).unwrap();
    assert_ne!(other.centroids(), &one.centroids[..]);
}

/// Assigns points to their nearest centroid (f64 brute force) and returns the means.
fn lloyd_means(points: &[f32], dsub: usize, centroids: &[f32]) -> (Vec<f64>, Vec<usize>) {
    let mut sums = vec![0f64; KSUB * dsub];
    let mut counts = vec![0usize; KSUB];
    for x in points.chunks_exact(dsub) {
        let best = (0..KSUB)
            .min_by(|&a, &b| {
                dist_f64(x, &centroids[a * dsub..(a + 1) * dsub])
                    .total_cmp(&dist_f64(x, &centroids[b * dsub..(b + 1) * dsub]))
            })
            .unwrap();
        counts[best] += 1;
        for j in 0..dsub {
            sums[best * dsub + j] += f64::from(x[j]);
        }
    }
    for k in 0..KSUB {
        for j in 0..dsub {
            sums[k * dsub + j] /= counts[k].max(1) as f64;
        }
    }
    (sums, counts)
}

#[test]
fn converged_kmeans_is_a_lloyd_fixed_point_without_empty_clusters() {
    // 1200 points in 2 subspaces of 2 dims, many iterations: every centroid must be the
    // mean of the points nearest to it, and every cluster must hold points.
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let data: Vec<f32> = (0..1200 * 4)
        .map(|_| rng.random_range(0.0f32..1.0))
        .collect();
    let params = TrainParams {
        m: 2,
        iters: 150,
        sample: 65536,
        seed: 4,
    };
    let cb = train_vectors(&data, 4, &params).unwrap();
    for s in 0..2 {
        let points: Vec<f32> = data
            .chunks_exact(4)
            .flat_map(|r| r[s * 2..s * 2 + 2].to_vec())
            .collect();
        let cents = &cb.centroids()[s * KSUB * 2..(s + 1) * KSUB * 2];
        let (means, counts) = lloyd_means(&points, 2, cents);
        assert!(counts.iter().all(|&c| c > 0), "empty cluster in {s}");
        for (i, (&c, &mu)) in cents.iter().zip(&means).enumerate() {
            assert!(
                (f64::from(c) - mu).abs() < 1e-5,
                "sub {s} value {i}: {c} vs {mu}"
            );
        }
    }
    // And it beats its own starting point (random sample points) on quantisation error.
    let start = train_vectors(&data, 4, &TrainParams { iters: 0, ..params }).unwrap();
    let err = |cb: &Codebook| {
        let mut codes = vec![0u8; 1200 * 2];
        cb.encode_batch(&data, &mut codes);
        let mut y = [0f32; 4];
        data.chunks_exact(4)
            .zip(codes.chunks_exact(2))
            .map(|(x, c)| {
                cb.decode(c, &mut y);
                dist_f64(x, &y)
            })
            .sum::<f64>()
    };
    assert!(
        err(&cb) < 0.8 * err(&start),
        "{} vs {}",
        err(&cb),
        err(&start)
    );
}

#[test]
fn f16_features_encode_like_their_f32_widening() {
    let gen = Clustered::new(32, 10, 0.5, 3);
    let f32s = gen.features(600, 5);
    let Floats::F32(v) = &f32s.features else {
        unreachable!()
    };
    let halves: Vec<f16> = v.iter().map(|&x| f16::from_f32(x)).collect();
    let widened: Vec<f32> = halves.iter().map(|h| h.to_f32()).collect();
    let f16s = Features {
        features: Floats::F16(halves.into()),
        ..f32s.clone()
    };
    let cb = train(&f16s, &small_params(8)).unwrap();
    let a = cb.encode_features(&f16s).unwrap();
    let b = cb
        .encode_features(&features_from(widened, 32, f32s.valid.to_vec()))
        .unwrap();
    assert_eq!(a, b);
}

#[test]
fn bad_inputs_are_typed_errors() {
    let gen = Clustered::new(30, 5, 0.5, 1);
    let features = gen.features(600, 0);
    assert_eq!(
        train(&features, &small_params(4)).unwrap_err(),
        PqError::DimNotDivisible { dim: 30, m: 4 }
    );
    assert_eq!(
        train(&features, &small_params(0)).unwrap_err(),
        PqError::DimNotDivisible { dim: 30, m: 0 }
    );
    // 600 rows, but only 255 valid.
    let mut valid = vec![0u8; 600];
    valid[..255].fill(1);
    let mut data = vec![0f32; 600 * 30];
    features.features.read_into(0, &mut data);
    data[255 * 30..].fill(0.0);
    let few = features_from(data, 30, valid);
    assert_eq!(
        train(&few, &small_params(5)).unwrap_err(),
        PqError::TooFewVectors {
            valid: 255,
            needed: 256
        }
    );
    assert!(matches!(
        train(
            &features,
            &TrainParams {
                sample: 100,
                ..small_params(5)
            }
        ),
        Err(PqError::SampleTooSmall { sample: 100, .. })
    ));

    let cb = train(&features, &small_params(5)).unwrap();
    let pq = cb.encode_features(&features).unwrap();
    assert_eq!(
        search(&pq, &[1.0; 29], 10, 5).unwrap_err(),
        PqError::QueryDim {
            got: 29,
            expected: 30
        }
    );
    assert_eq!(
        adc_scores(&pq, &[0.0; 30]).unwrap_err(),
        PqError::DegenerateQuery
    );
    let mut nan = vec![1.0f32; 30];
    nan[3] = f32::NAN;
    assert_eq!(
        LookupTable::new(&pq, &nan).unwrap_err(),
        PqError::DegenerateQuery
    );
    let other = Clustered::new(40, 5, 0.5, 1).features(300, 0);
    assert_eq!(
        cb.encode_features(&other).unwrap_err(),
        PqError::FeatureDim {
            got: 40,
            expected: 30
        }
    );
    let mut broken = pq.clone();
    broken.norms = vec![1.0f32; 3].into();
    assert!(matches!(
        adc_scores(&broken, &[1.0; 30]),
        Err(PqError::Inconsistent(_))
    ));
    assert!(matches!(
        Codebook::new(2, 3, vec![0.0; 10]),
        Err(PqError::Inconsistent(_))
    ));
}

/// Our codes and decodes agree with faiss's `ProductQuantizer` loaded with our centroids.
/// Needs python3 with numpy, safetensors and faiss (`pip install -r
/// crates/pq/python/requirements.txt`); skipped with a message when faiss is missing,
/// unless PROFUSE_REQUIRE_FAISS=1.
#[test]
fn faiss_product_quantizer_agrees_with_our_codes_and_decodes() {
    let probe = Command::new("python3")
        .args(["-c", "import numpy, safetensors, faiss"])
        .output();
    if !probe.map(|o| o.status.success()).unwrap_or(false) {
        assert!(
            std::env::var("PROFUSE_REQUIRE_FAISS").as_deref() != Ok("1"),
            "python3 with numpy, safetensors and faiss is required \
             (pip install -r crates/pq/python/requirements.txt)"
        );
        eprintln!(
            "SKIPPED: python3 with numpy + safetensors + faiss not found; \
             run `pip install -r crates/pq/python/requirements.txt`"
        );
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    // The default layout (M = 128, dsub = 4) over 512-d CLIP-like features, few iterations
    // to keep the dev-profile test short; every 11th row invalid.
    let gen = Clustered::new(512, 50, 0.62, 17);
    let features = gen.features(3000, 11);
    let params = TrainParams {
        iters: 4,
        sample: 2048,
        ..TrainParams::default()
    };
    let pq = train(&features, &params)
        .unwrap()
        .encode_features(&features)
        .unwrap();
    let fpath = dir.path().join("features.safetensors");
    let ppath = dir.path().join("pq.safetensors");
    features.write(&fpath).unwrap();
    pq.write(&ppath).unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("python/test_faiss_compat.py");
    let out = Command::new("python3")
        .arg(&script)
        .arg(&fpath)
        .arg(&ppath)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "faiss compatibility failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("{stdout}");
    let report: serde_like::Report = serde_like::parse(&stdout);
    assert_eq!(report.code_mismatches, 0, "{stdout}");
    assert!(report.reconstruction_cosine > 0.9, "{stdout}");
    let ours = profuse_pq::reconstruction_cosine(&features, &pq).unwrap();
    assert!(
        (ours - report.reconstruction_cosine).abs() < 1e-4,
        "{ours} vs {stdout}"
    );
}

/// Minimal reader of the script's `key=value` report (no JSON dependency here).
mod serde_like {
    pub struct Report {
        pub code_mismatches: usize,
        pub reconstruction_cosine: f64,
    }

    pub fn parse(text: &str) -> Report {
        let get = |key: &str| -> String {
            text.lines()
                .find_map(|l| l.strip_prefix(&format!("{key}=")))
                .unwrap_or_else(|| panic!("no {key}= in {text}"))
                .trim()
                .to_string()
        };
        Report {
            code_mismatches: get("code_mismatches").parse().unwrap(),
            reconstruction_cosine: get("reconstruction_cosine").parse().unwrap(),
        }
    }
}

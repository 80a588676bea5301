//! `pq bench`: train, encode (streamed in chunks) and query N synthetic clustered unit
//! vectors (class prototypes + noise, like CLIP features of a scene).

use std::time::Instant;

use profuse_pq::rayon::prelude::*;
use profuse_pq::{
    exact_cosine, search, synthetic::Clustered, train_vectors, FastScan, TrainParams,
};
use serde_json::{json, Value};

use crate::common::{self, Progress};
use crate::BoxError;

/// The benchmark's parameters (the `pq bench` arguments).
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct Params {
    /// Vectors to encode and search.
    #[arg(long, default_value_t = 1_000_000)]
    pub n: usize,
    /// Vector dimension.
    #[arg(long, default_value_t = 512)]
    pub dim: usize,
    /// Sub-quantisers M.
    #[arg(long, default_value_t = TrainParams::default().m)]
    pub m: usize,
    /// k-means iterations.
    #[arg(long, default_value_t = TrainParams::default().iters)]
    pub iters: usize,
    /// Training sample size.
    #[arg(long, default_value_t = TrainParams::default().sample)]
    pub sample: usize,
    /// Seed of the data and of training.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Class prototypes of the synthetic data.
    #[arg(long, default_value_t = 1000)]
    pub classes: usize,
    /// Noise norm added to a prototype (0.62: cosine 0.85 to the prototype).
    #[arg(long, default_value_t = 0.62)]
    pub noise: f32,
    /// Text queries (each near a different class prototype).
    #[arg(long, default_value_t = 10)]
    pub queries: usize,
    /// Shortlist size of the measured search.
    #[arg(long, default_value_t = profuse_pq::DEFAULT_SHORTLIST)]
    pub shortlist: usize,
}

/// Vectors generated and encoded at a time (the data is never held whole).
const CHUNK: usize = 1 << 16;

/// Runs the benchmark.
pub fn run(a: &Params, progress: &dyn Progress) -> Result<Value, BoxError> {
    if a.dim == 0 || a.classes == 0 || a.queries == 0 {
        return Err("--dim, --classes and --queries must be >= 1".into());
    }
    let params = TrainParams {
        m: a.m,
        iters: a.iters,
        sample: a.sample,
        seed: a.seed,
    };
    let gen = Clustered::new(a.dim, a.classes, a.noise, a.seed);
    let generate = |start: usize, len: usize| -> Vec<f32> {
        let mut v = vec![0f32; len * a.dim];
        v.par_chunks_mut(a.dim)
            .enumerate()
            .for_each(|(i, row)| gen.vector((start + i) as u64, row));
        v
    };

    progress.start("training", 0);
    let train_n = a.sample.min(a.n);
    let train_data = generate(0, train_n);
    let t0 = Instant::now();
    let codebook = train_vectors(&train_data, a.dim, &params)?;
    let train_s = t0.elapsed().as_secs_f64();
    drop(train_data);
    progress.finish();

    progress.start("encoding", a.n as u64);
    let mut codes = vec![0u8; a.n * a.m];
    let mut norms = vec![0f32; a.n];
    let mut encode_s = 0.0;
    let mut recon = (0.0f64, 0usize);
    for start in (0..a.n).step_by(CHUNK) {
        let len = CHUNK.min(a.n - start);
        let x = generate(start, len);
        let c = &mut codes[start * a.m..(start + len) * a.m];
        let t0 = Instant::now();
        codebook.encode_batch(&x, c);
        norms[start..start + len]
            .par_iter_mut()
            .zip(c.par_chunks(a.m))
            .for_each(|(nm, code)| *nm = codebook.decoded_norm(code));
        encode_s += t0.elapsed().as_secs_f64();
        // Reconstruction quality on the first vector of every 64.
        let mut y = vec![0f32; a.dim];
        for i in (0..len).step_by(64) {
            codebook.decode(&c[i * a.m..(i + 1) * a.m], &mut y);
            recon.0 += profuse_pq::cosine_f64(&x[i * a.dim..(i + 1) * a.dim], &y);
            recon.1 += 1;
        }
        progress.inc(len as u64);
    }
    progress.finish();
    let pq = codebook.to_pq(codes, norms, vec![1u8; a.n]);
    let q = query_timings(a, &gen, &pq, progress)?;
    let k = 100.min(a.n);
    Ok(json!({
        "n": a.n,
        "dim": a.dim,
        "m": a.m,
        "train_samples": train_n,
        "kmeans_iters": a.iters,
        "threads": profuse_pq::rayon::current_num_threads(),
        "train_s": train_s,
        "encode_s": encode_s,
        "encode_per_s": a.n as f64 / encode_s,
        "shortlist": a.shortlist.max(k),
        "query_ms": q.query_ms,
        "query_cpu_ms": q.query_cpu_ms,
        "adc_ms": q.adc_ms,
        "fast_prepare_ms": q.fast.prepare_ms,
        "fast_query_ms": q.fast.query_ms,
        "fast_query_cpu_ms": q.fast.query_cpu_ms,
        "fast_candidates": q.fast.candidates,
        "fast_rounds": q.fast.rounds,
        "fast_same_as_exhaustive": q.fast.same,
        "fast_kernel": q.fast.kernel,
        "fast_packed_mb": q.fast.packed_mb,
        "recall_at_100": q.recall,
        "recall_at_100_shortlist_100": q.recall_shortlist_k,
        "reconstruction_cosine": recon.0 / recon.1.max(1) as f64,
        "code_bytes": pq.codes.len(),
        "peak_rss_mb": common::peak_rss_mb(),
    }))
}

/// Medians over the queries, and mean recalls.
struct QueryTimings {
    query_ms: f64,
    query_cpu_ms: f64,
    adc_ms: f64,
    recall: f64,
    recall_shortlist_k: f64,
    fast: FastTimings,
}

/// The fast-scan search on the same queries: medians, and the share of queries whose
/// result equals the exhaustive search's.
struct FastTimings {
    prepare_ms: f64,
    query_ms: f64,
    query_cpu_ms: f64,
    candidates: f64,
    rounds: f64,
    same: f64,
    kernel: &'static str,
    packed_mb: f64,
}

fn query_timings(
    a: &Params,
    gen: &Clustered,
    pq: &profuse_pq::Pq,
    progress: &dyn Progress,
) -> Result<QueryTimings, BoxError> {
    let t0 = Instant::now();
    let fast = FastScan::new(pq)?;
    let prepare_ms = t0.elapsed().as_secs_f64() * 1e3;
    let (mut fast_ms, mut fast_cpu, mut fast_cand, mut fast_rounds) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut same = 0usize;
    progress.start("queries", a.queries as u64);
    let (mut query_ms, mut query_cpu_ms, mut adc_ms) = (Vec::new(), Vec::new(), Vec::new());
    let (mut recalls, mut recalls_k) = (Vec::new(), Vec::new());
    let k = 100.min(a.n);
    for qi in 0..a.queries {
        let q = gen.query(qi * a.classes / a.queries, 0.5, qi as u64);
        // Untimed warm-up, then the fastest of five runs: other load on the machine only
        // ever slows a run down.
        search(pq, &q, a.shortlist, k)?;
        let (mut best, mut best_cpu, mut best_adc) = (f64::INFINITY, f64::INFINITY, f64::INFINITY);
        for _ in 0..5 {
            let cpu0 = common::process_cpu_s();
            let t0 = Instant::now();
            std::hint::black_box(search(pq, &q, a.shortlist, k)?);
            best = best.min(t0.elapsed().as_secs_f64() * 1e3);
            best_cpu = best_cpu.min((common::process_cpu_s() - cpu0) * 1e3);
            let t0 = Instant::now();
            std::hint::black_box(profuse_pq::adc_scores(pq, &q)?);
            best_adc = best_adc.min(t0.elapsed().as_secs_f64() * 1e3);
        }
        query_ms.push(best);
        query_cpu_ms.push(best_cpu);
        adc_ms.push(best_adc);
        let (fast_top, stats) = fast.search(pq, &q, k)?;
        same += usize::from(fast_top == search(pq, &q, a.shortlist, k)?);
        fast_cand.push(stats.candidates as f64);
        fast_rounds.push(stats.rounds as f64);
        let (mut best, mut best_cpu) = (f64::INFINITY, f64::INFINITY);
        for _ in 0..5 {
            let cpu0 = common::process_cpu_s();
            let t0 = Instant::now();
            std::hint::black_box(fast.search(pq, &q, k)?);
            best = best.min(t0.elapsed().as_secs_f64() * 1e3);
            best_cpu = best_cpu.min((common::process_cpu_s() - cpu0) * 1e3);
        }
        fast_ms.push(best);
        fast_cpu.push(best_cpu);
        let exact: Vec<(u32, f32)> = (0..a.n)
            .into_par_iter()
            .map(|i| (i as u32, exact_cosine(pq, i, &q)))
            .collect();
        let truth = profuse_pq::top_n(exact, k);
        let recall = |len: usize| -> Result<f64, BoxError> {
            let short = profuse_pq::adc_shortlist(pq, &q, len)?;
            let mut ids: Vec<u32> = short.iter().map(|r| r.0).collect();
            ids.sort_unstable();
            let hit = truth
                .iter()
                .filter(|r| ids.binary_search(&r.0).is_ok())
                .count();
            Ok(hit as f64 / k.max(1) as f64)
        };
        recalls.push(recall(a.shortlist.max(k))?);
        recalls_k.push(recall(k)?);
        progress.inc(1);
    }
    progress.finish();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    Ok(QueryTimings {
        query_ms: common::median(&mut query_ms),
        query_cpu_ms: common::median(&mut query_cpu_ms),
        adc_ms: common::median(&mut adc_ms),
        recall: mean(&recalls),
        recall_shortlist_k: mean(&recalls_k),
        fast: FastTimings {
            prepare_ms,
            query_ms: common::median(&mut fast_ms),
            query_cpu_ms: common::median(&mut fast_cpu),
            candidates: common::median(&mut fast_cand),
            rounds: common::median(&mut fast_rounds),
            same: same as f64 / a.queries.max(1) as f64,
            kernel: fast.kernel(),
            packed_mb: fast.packed_bytes() as f64 / 1e6,
        },
    })
}

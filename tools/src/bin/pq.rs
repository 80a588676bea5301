//! `pq`: train a product quantiser on Gaussian descriptors and encode them, encode more
//! descriptors with an existing codebook, query the codes with a text prompt, and
//! benchmark (paper §3.4).
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error goes to stderr, the exit code is 1 and no file is written.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use profuse_formats::{Features, FileKind, Pq, Prompts};
use profuse_pq::{
    exact_cosine, reconstruction_cosine, search, synthetic::Clustered, train, train_vectors,
    Codebook, PqError, TrainParams, DEFAULT_SHORTLIST,
};
use profuse_tools::{chatty, peak_rss_mb, run, BoxError};
use serde_json::{json, Value};

#[derive(Debug, Parser)]
#[command(
    name = "pq",
    version,
    about = "Product quantisation of Gaussian descriptors: train, encode, query, bench",
    long_about = "Product quantisation of per-Gaussian language descriptors (paper 3.4), faiss \
                  compatible (SPEC.md 4.8: centroids F32 [M,256,dsub], codes U8 [N,M]). `train` \
                  runs seeded k-means per sub-quantiser on a sample of the valid descriptors \
                  of a features file and encodes all of them; `encode` encodes a features file \
                  with the centroids of an existing pq file; `query` scores the codes against \
                  a text prompt (ADC shortlist, exact re-rank with decoded vectors); `bench` \
                  measures all of it on synthetic clustered vectors. Prints one JSON report \
                  on stdout."
)]
struct Cli {
    /// Do not print progress on stderr.
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Train M x 256 centroids on the valid descriptors of a features file, encode every
    /// descriptor (invalid ones get codes 0, norm 0, valid 0) and write a pq file. Reports
    /// train/encode seconds and the mean cosine between descriptors and their decodes.
    Train {
        /// Features file (profuse.features) to train on and encode.
        #[arg(long)]
        features: PathBuf,
        /// The pq .safetensors file to write.
        #[arg(long)]
        out: PathBuf,
        /// Sub-quantisers M; must divide the feature dimension (128 over 512-d = 4 dims each).
        #[arg(long, default_value_t = TrainParams::default().m)]
        m: usize,
        /// k-means (Lloyd) iterations per sub-quantiser (faiss's default 25).
        #[arg(long, default_value_t = TrainParams::default().iters)]
        iters: usize,
        /// Most training vectors, sampled uniformly from the valid descriptors (default
        /// 65536 = 256 per centroid, faiss's cap).
        #[arg(long, default_value_t = TrainParams::default().sample)]
        sample: usize,
        /// Seed of the training sample, initial centroids and empty-cluster splits.
        #[arg(long, default_value_t = TrainParams::default().seed)]
        seed: u64,
    },
    /// Encode the descriptors of a features file with the centroids of an existing pq
    /// file and write a new pq file (same codebook, new codes).
    Encode {
        /// Existing pq file whose centroids are used.
        #[arg(long)]
        pq: PathBuf,
        /// Features file (profuse.features) to encode; its dimension must match.
        #[arg(long)]
        features: PathBuf,
        /// The pq .safetensors file to write.
        #[arg(long)]
        out: PathBuf,
    },
    /// Score every code against one prompt's text embedding: ADC cosine over all codes,
    /// keep the best `--shortlist`, re-rank them by exact cosine with the decoded
    /// vectors, print the top `--k` ids and scores (best first, ties by id).
    Query {
        /// The pq file to search.
        #[arg(long)]
        pq: PathBuf,
        /// Prompts file (profuse.prompts) holding the text embeddings.
        #[arg(long)]
        prompts: PathBuf,
        /// Name of the prompt to search for.
        #[arg(long)]
        prompt: String,
        /// Results to return.
        #[arg(long, default_value_t = 100)]
        k: usize,
        /// ADC candidates re-ranked exactly (raised to k if smaller).
        #[arg(long, default_value_t = DEFAULT_SHORTLIST)]
        shortlist: usize,
    },
    /// Benchmark on N synthetic clustered unit vectors (class prototypes + noise, like
    /// CLIP features of a scene): train, encode (streamed in chunks), then text queries.
    /// Prints `train_s`, `encode_per_s`, `query_ms` (median over queries of the fastest
    /// of five runs of one search: ADC pass over all N codes + exact re-rank of the
    /// shortlist), `query_cpu_ms` (its CPU time summed over threads), `adc_ms`
    /// (`adc_scores` alone),
    /// `recall_at_100` (share of the exact decoded-cosine top 100 that the ADC shortlist
    /// contains, mean over queries; `recall_at_100_shortlist_100` the same for a
    /// shortlist of only 100), `reconstruction_cosine` (mean cosine between a vector and
    /// its decode, every 64th vector) and `peak_rss_mb`.
    Bench {
        /// Vectors to encode and search.
        #[arg(long, default_value_t = 1_000_000)]
        n: usize,
        /// Vector dimension.
        #[arg(long, default_value_t = 512)]
        dim: usize,
        /// Sub-quantisers M.
        #[arg(long, default_value_t = TrainParams::default().m)]
        m: usize,
        /// k-means iterations.
        #[arg(long, default_value_t = TrainParams::default().iters)]
        iters: usize,
        /// Training sample size.
        #[arg(long, default_value_t = TrainParams::default().sample)]
        sample: usize,
        /// Seed of the data and of training.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Class prototypes of the synthetic data.
        #[arg(long, default_value_t = 1000)]
        classes: usize,
        /// Noise norm added to a prototype (0.62: cosine 0.85 to the prototype).
        #[arg(long, default_value_t = 0.62)]
        noise: f32,
        /// Text queries (each near a different class prototype).
        #[arg(long, default_value_t = 10)]
        queries: usize,
        /// Shortlist size of the measured search.
        #[arg(long, default_value_t = DEFAULT_SHORTLIST)]
        shortlist: usize,
        /// Worker threads (default: rayon's, i.e. RAYON_NUM_THREADS or the core count).
        #[arg(long)]
        threads: Option<usize>,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| execute(cli.command, quiet))
}

fn execute(command: Command, quiet: bool) -> Result<Value, BoxError> {
    let show = chatty(quiet);
    match command {
        Command::Train {
            features,
            out,
            m,
            iters,
            sample,
            seed,
        } => {
            let f = Features::read(&features)?;
            let params = TrainParams {
                m,
                iters,
                sample,
                seed,
            };
            let spinner = spinner(show, "training k-means");
            let t0 = Instant::now();
            let codebook = train(&f, &params).map_err(|e| in_file(&features, e))?;
            let train_s = t0.elapsed().as_secs_f64();
            spinner.set_message("encoding");
            let t0 = Instant::now();
            let pq = codebook
                .encode_features(&f)
                .map_err(|e| in_file(&features, e))?;
            let encode_s = t0.elapsed().as_secs_f64();
            spinner.finish_and_clear();
            let recon = reconstruction_cosine(&f, &pq);
            pq.write(&out)?;
            Ok(json!({
                "vectors": pq.len(),
                "valid": valid_count(&pq),
                "dim": pq.dim(),
                "m": pq.m,
                "dsub": pq.dsub,
                "train_samples": pq
                    .extra
                    .get("train_samples")
                    .and_then(|s| s.parse::<u64>().ok()),
                "kmeans_iters": iters,
                "seed": seed,
                "train_s": train_s,
                "encode_s": encode_s,
                "reconstruction_cosine_mean": recon,
                "out": out,
            }))
        }
        Command::Encode { pq, features, out } => {
            let existing = Pq::read(&pq)?;
            let f = Features::read(&features)?;
            let codebook = Codebook::from_pq(&existing).map_err(|e| in_file(&pq, e))?;
            let spinner = spinner(show, "encoding");
            let t0 = Instant::now();
            let encoded = codebook
                .encode_features(&f)
                .map_err(|e| in_file(&features, e))?;
            let encode_s = t0.elapsed().as_secs_f64();
            spinner.finish_and_clear();
            let recon = reconstruction_cosine(&f, &encoded);
            encoded.write(&out)?;
            Ok(json!({
                "vectors": encoded.len(),
                "valid": valid_count(&encoded),
                "dim": encoded.dim(),
                "m": encoded.m,
                "encode_s": encode_s,
                "reconstruction_cosine_mean": recon,
                "out": out,
            }))
        }
        Command::Query {
            pq,
            prompts,
            prompt,
            k,
            shortlist,
        } => {
            let codes = Pq::read(&pq)?;
            let p = Prompts::read(&prompts)?;
            let q = p.index_of(&prompt).ok_or_else(|| {
                format!(
                    "{}: no prompt named {prompt:?} in metadata `names` (have {:?})",
                    prompts.display(),
                    p.names
                )
            })?;
            let t0 = Instant::now();
            let top = search(&codes, p.embedding(q), shortlist, k).map_err(|e| {
                format!(
                    "{} `embeddings` row {q} ({prompt:?}) against {}: {e}",
                    prompts.display(),
                    pq.display()
                )
            })?;
            let query_ms = t0.elapsed().as_secs_f64() * 1e3;
            Ok(json!({
                "prompt": prompt,
                "k": k,
                "shortlist": shortlist.max(k),
                "vectors": codes.len(),
                "query_ms": query_ms,
                "ids": top.iter().map(|r| r.0).collect::<Vec<_>>(),
                "scores": top.iter().map(|r| r.1).collect::<Vec<_>>(),
            }))
        }
        Command::Bench {
            n,
            dim,
            m,
            iters,
            sample,
            seed,
            classes,
            noise,
            queries,
            shortlist,
            threads,
        } => {
            if let Some(t) = threads {
                profuse_pq::rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .build_global()?;
            }
            bench(
                BenchArgs {
                    n,
                    dim,
                    params: TrainParams {
                        m,
                        iters,
                        sample,
                        seed,
                    },
                    classes,
                    noise,
                    queries,
                    shortlist,
                },
                show,
            )
        }
    }
}

struct BenchArgs {
    n: usize,
    dim: usize,
    params: TrainParams,
    classes: usize,
    noise: f32,
    queries: usize,
    shortlist: usize,
}

/// Vectors generated and encoded at a time in the bench (the data is never held whole).
const BENCH_CHUNK: usize = 1 << 16;

fn bench(a: BenchArgs, show: bool) -> Result<Value, BoxError> {
    use profuse_pq::rayon::prelude::*;
    if a.dim == 0 || a.classes == 0 || a.queries == 0 {
        return Err("--dim, --classes and --queries must be >= 1".into());
    }
    let gen = Clustered::new(a.dim, a.classes, a.noise, a.params.seed);
    let generate = |start: usize, len: usize| -> Vec<f32> {
        let mut v = vec![0f32; len * a.dim];
        v.par_chunks_mut(a.dim)
            .enumerate()
            .for_each(|(i, row)| gen.vector((start + i) as u64, row));
        v
    };

    let spinner = spinner(show, "training");
    let train_n = a.params.sample.min(a.n);
    let train_data = generate(0, train_n);
    let t0 = Instant::now();
    let codebook = train_vectors(&train_data, a.dim, &a.params)?;
    let train_s = t0.elapsed().as_secs_f64();
    drop(train_data);

    let bar = progress(show, a.n as u64, "encoding");
    spinner.finish_and_clear();
    let mut codes = vec![0u8; a.n * a.params.m];
    let mut norms = vec![0f32; a.n];
    let mut encode_s = 0.0;
    let mut recon = (0.0f64, 0usize);
    for start in (0..a.n).step_by(BENCH_CHUNK) {
        let len = BENCH_CHUNK.min(a.n - start);
        let x = generate(start, len);
        let c = &mut codes[start * a.params.m..(start + len) * a.params.m];
        let t0 = Instant::now();
        codebook.encode_batch(&x, c);
        norms[start..start + len]
            .par_iter_mut()
            .zip(c.par_chunks(a.params.m))
            .for_each(|(nm, code)| *nm = codebook.decoded_norm(code));
        encode_s += t0.elapsed().as_secs_f64();
        // Reconstruction quality on the first vector of every 64.
        let mut y = vec![0f32; a.dim];
        for i in (0..len).step_by(64) {
            codebook.decode(&c[i * a.params.m..(i + 1) * a.params.m], &mut y);
            recon.0 += profuse_pq::cosine_f64(&x[i * a.dim..(i + 1) * a.dim], &y);
            recon.1 += 1;
        }
        bar.inc(len as u64);
    }
    bar.finish_and_clear();
    let pq = codebook.to_pq(codes, norms, vec![1u8; a.n]);

    let bar = progress(show, a.queries as u64, "queries");
    let (mut query_ms, mut query_cpu_ms, mut adc_ms) = (Vec::new(), Vec::new(), Vec::new());
    let (mut recalls, mut recalls_k) = (Vec::new(), Vec::new());
    let k = 100.min(a.n);
    for qi in 0..a.queries {
        let q = gen.query(qi * a.classes / a.queries, 0.5, qi as u64);
        // Untimed warm-up, then the fastest of five runs: other load on the machine only
        // ever slows a run down.
        search(&pq, &q, a.shortlist, k)?;
        let (mut best, mut best_cpu, mut best_adc) = (f64::INFINITY, f64::INFINITY, f64::INFINITY);
        for _ in 0..5 {
            let cpu0 = process_cpu_ms();
            let t0 = Instant::now();
            std::hint::black_box(search(&pq, &q, a.shortlist, k)?);
            best = best.min(t0.elapsed().as_secs_f64() * 1e3);
            best_cpu = best_cpu.min(process_cpu_ms() - cpu0);
            let t0 = Instant::now();
            std::hint::black_box(profuse_pq::adc_scores(&pq, &q)?);
            best_adc = best_adc.min(t0.elapsed().as_secs_f64() * 1e3);
        }
        query_ms.push(best);
        query_cpu_ms.push(best_cpu);
        adc_ms.push(best_adc);

        let exact: Vec<(u32, f32)> = (0..a.n)
            .into_par_iter()
            .map(|i| (i as u32, exact_cosine(&pq, i, &q)))
            .collect();
        let truth = profuse_pq::top_n(exact, k);
        let recall = |len: usize| -> Result<f64, BoxError> {
            let short = profuse_pq::adc_shortlist(&pq, &q, len)?;
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
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(json!({
        "n": a.n,
        "dim": a.dim,
        "m": a.params.m,
        "train_samples": train_n,
        "kmeans_iters": a.params.iters,
        "threads": profuse_pq::rayon::current_num_threads(),
        "train_s": train_s,
        "encode_s": encode_s,
        "encode_per_s": a.n as f64 / encode_s,
        "shortlist": a.shortlist.max(k),
        "query_ms": median(&mut query_ms),
        "query_cpu_ms": median(&mut query_cpu_ms),
        "adc_ms": median(&mut adc_ms),
        "recall_at_100": recalls.iter().sum::<f64>() / recalls.len() as f64,
        "recall_at_100_shortlist_100": recalls_k.iter().sum::<f64>() / recalls_k.len() as f64,
        "reconstruction_cosine": recon.0 / recon.1.max(1) as f64,
        "code_bytes": pq.codes.len(),
        "peak_rss_mb": peak_rss_mb(),
    }))
}

/// A library error with the file it concerns.
fn in_file(path: &Path, e: PqError) -> BoxError {
    format!("{}: {e}", path.display()).into()
}

fn valid_count(pq: &Pq) -> usize {
    pq.valid.iter().filter(|&&v| v == 1).count()
}

/// CPU time of this process so far (all threads, from /proc/self/task/*/schedstat) in
/// ms; 0 where unavailable. Unlike wall time it does not grow when other processes
/// compete for the cores.
fn process_cpu_ms() -> f64 {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
        return 0.0;
    };
    tasks
        .flatten()
        .filter_map(|t| std::fs::read_to_string(t.path().join("schedstat")).ok())
        .filter_map(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .sum::<f64>()
        / 1e6
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        0.0
    } else {
        v[v.len() / 2]
    }
}

fn spinner(show: bool, msg: &'static str) -> ProgressBar {
    if !show {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new_spinner();
    pb.set_message(msg);
    pb.enable_steady_tick(std::time::Duration::from_millis(120));
    pb
}

fn progress(show: bool, len: u64, msg: &'static str) -> ProgressBar {
    if !show {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new(len);
    if let Ok(style) = ProgressStyle::with_template("{msg} {bar:40} {pos}/{len} [{elapsed}]") {
        pb.set_style(style);
    }
    pb.set_message(msg);
    pb
}

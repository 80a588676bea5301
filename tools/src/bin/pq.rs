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

use clap::{Parser, Subcommand, ValueEnum};
use profuse_bench::pq as bench;
use profuse_formats::{FileKind, Pq, Prompts};
use profuse_pq::{job, search, FastScan, TrainParams, DEFAULT_SHORTLIST};
use profuse_tools::{chatty, check_outputs, init_threads, run, spinner, Bars, BoxError};
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

/// How `query` finds its candidates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Scan {
    /// 4-bit first pass, 8-bit ADC on its candidates, exact re-rank.
    Fast,
    /// 8-bit ADC over every code, exact re-rank of the shortlist.
    Exhaustive,
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
    /// Top `--k` codes for one prompt's text embedding by exact cosine with the decoded
    /// vectors (best first, ties by id). `--scan fast` (default): a 4-bit first pass over
    /// every vector (16-entry tables in SIMD registers) finds the candidates, the 8-bit
    /// ADC scores them, and every candidate that can still reach the top k is re-ranked
    /// exactly; `--scan exhaustive`: the 8-bit ADC over every code, the best
    /// `--shortlist` re-ranked. Reports `query_ms` (the search alone) and, for fast,
    /// `prepare_ms` (grouping and packing the 4-bit codes once per load).
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
        /// How candidates are found: `fast` (4-bit first pass) or `exhaustive` (8-bit ADC
        /// over every code).
        #[arg(long, value_enum, default_value_t = Scan::Fast)]
        scan: Scan,
        /// `--scan exhaustive` only: ADC candidates re-ranked exactly (raised to k if
        /// smaller). The fast scan re-ranks every candidate that can still reach the top k.
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
    /// its decode, every 64th vector), `peak_rss_mb`, and the fast scan on the same
    /// queries: `fast_query_ms`, `fast_query_cpu_ms`, `fast_prepare_ms`,
    /// `fast_candidates`, `fast_rounds`, `fast_same_as_exhaustive` (share of queries whose
    /// result equals the exhaustive search's), `fast_kernel`, `fast_packed_mb`.
    Bench {
        #[command(flatten)]
        params: bench::Params,
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
            let params = TrainParams {
                m,
                iters,
                sample,
                seed,
            };
            check_outputs([out.as_path()])?;
            let spinner = spinner(show, "training k-means, then encoding");
            let report = job::train_file(&features, &out, &params);
            spinner.finish_and_clear();
            Ok(serde_json::to_value(report?)?)
        }
        Command::Encode { pq, features, out } => {
            check_outputs([out.as_path()])?;
            let spinner = spinner(show, "encoding");
            let report = job::encode_file(&pq, &features, &out);
            spinner.finish_and_clear();
            Ok(serde_json::to_value(report?)?)
        }
        Command::Query {
            pq,
            prompts,
            prompt,
            k,
            scan,
            shortlist,
        } => query(&pq, &prompts, &prompt, k, scan, shortlist),
        Command::Bench { params, threads } => {
            init_threads(threads)?;
            bench::run(&params, &Bars::new(show))
        }
    }
}

fn query(
    pq: &Path,
    prompts: &Path,
    prompt: &str,
    k: usize,
    scan: Scan,
    shortlist: usize,
) -> Result<Value, BoxError> {
    let codes = Pq::read(pq)?;
    let p = Prompts::read(prompts)?;
    let q = p.index_of(prompt).ok_or_else(|| {
        format!(
            "{}: no prompt named {prompt:?} in metadata `names` (have {:?})",
            prompts.display(),
            p.names
        )
    })?;
    let name_error = |e: profuse_pq::PqError| {
        format!(
            "{} `embeddings` row {q} ({prompt:?}) against {}: {e}",
            prompts.display(),
            pq.display()
        )
    };
    let mut report = json!({
        "prompt": prompt,
        "k": k,
        "vectors": codes.len(),
    });
    let top = match scan {
        Scan::Exhaustive => {
            let t0 = Instant::now();
            let top = search(&codes, p.embedding(q), shortlist, k).map_err(name_error)?;
            report["query_ms"] = json!(t0.elapsed().as_secs_f64() * 1e3);
            report["scan"] = json!("exhaustive");
            report["shortlist"] = json!(shortlist.max(k));
            top
        }
        Scan::Fast => {
            let t0 = Instant::now();
            let fast = FastScan::new(&codes).map_err(|e| format!("{}: {e}", pq.display()))?;
            report["prepare_ms"] = json!(t0.elapsed().as_secs_f64() * 1e3);
            let t0 = Instant::now();
            let (top, stats) = fast.search(&codes, p.embedding(q), k).map_err(name_error)?;
            report["query_ms"] = json!(t0.elapsed().as_secs_f64() * 1e3);
            report["scan"] = json!("fast");
            report["kernel"] = json!(stats.kernel);
            report["candidates"] = json!(stats.candidates);
            report["reranked"] = json!(stats.reranked);
            report["rounds"] = json!(stats.rounds);
            top
        }
    };
    report["ids"] = top.iter().map(|r| r.0).collect();
    report["scores"] = top.iter().map(|r| r.1).collect();
    Ok(report)
}

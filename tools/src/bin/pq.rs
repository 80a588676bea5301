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
use profuse_bench::pq as bench;
use profuse_formats::{FileKind, Pq, Prompts};
use profuse_pq::{job, search, TrainParams, DEFAULT_SHORTLIST};
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
            shortlist,
        } => query(&pq, &prompts, &prompt, k, shortlist),
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

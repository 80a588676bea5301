//! `query bench`: scoring (exact F16 and PQ, cosine and relevancy), selection, ADC
//! search and activation masks on random data (their cost does not depend on the data).

use std::time::Instant;

use profuse_formats::label_space::CANONICAL_NEGATIVES;
use profuse_formats::rng::SplitMix64;
use profuse_formats::{f16, Features, Floats, Prompts};
use profuse_query::{
    activation, score_prompts, select, ActiveSet, Descriptors, Membership, Rule, ScoreKind,
};
use serde_json::{json, Value};

use crate::common;
use crate::BoxError;

/// The benchmark's parameters (the `query bench` arguments).
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct Params {
    /// Gaussians with PQ codes.
    #[arg(long, default_value_t = 1_000_000)]
    pub gaussians: usize,
    /// Gaussians with exact F16 descriptors (N x D x 2 bytes are allocated).
    #[arg(long, default_value_t = 200_000)]
    pub exact_gaussians: usize,
    /// Descriptor dimension D.
    #[arg(long, default_value_t = 512)]
    pub dim: usize,
    /// PQ sub-quantisers M (D must be a multiple).
    #[arg(long, default_value_t = 128)]
    pub m: usize,
    /// Prompts scored together.
    #[arg(long, default_value_t = 4)]
    pub prompts: usize,
    /// Width of the synthetic top-K buffer.
    #[arg(long, default_value_t = 1920)]
    pub width: usize,
    /// Height of the synthetic top-K buffer.
    #[arg(long, default_value_t = 1080)]
    pub height: usize,
    /// K of the synthetic top-K buffer.
    #[arg(long, default_value_t = 10)]
    pub k: usize,
    /// Repetitions per measurement (the fastest is reported).
    #[arg(long, default_value_t = 3)]
    pub repeat: usize,
    /// Instead of the stage benchmark: one text query (relevancy, selection included)
    /// over --gaussians Gaussians with this semantics, and with PQ codes in the same run;
    /// prints `query_us` and `bytes_per_gaussian` of both (issue 24).
    #[arg(long, value_enum)]
    pub semantics: Option<profuse_query::Semantics>,
    /// Proposals P of the semantic index (--semantics).
    #[arg(long, default_value_t = 1000)]
    pub proposals: usize,
}

/// Runs the benchmark.
pub fn run(a: &Params) -> Result<Value, BoxError> {
    if a.dim == 0 || a.m == 0 || !a.dim.is_multiple_of(a.m) {
        return Err(format!("--dim {} must be a positive multiple of --m {}", a.dim, a.m).into());
    }
    if let Some(semantics) = a.semantics {
        return crate::semantics::run(a, semantics);
    }
    let d = a.dim;
    let mut rng = SplitMix(SplitMix64::new(0x9e37_79b9));
    // Prompts: random unit vectors, plus the four canonical negatives for relevancy.
    let mut names: Vec<String> = (0..a.prompts).map(|i| format!("prompt_{i}")).collect();
    names.extend(CANONICAL_NEGATIVES.map(String::from));
    let embeddings: Vec<f32> = (0..names.len() * d).map(|_| rng.normal()).collect();
    let prompts = Prompts {
        names,
        dim: d,
        embeddings: embeddings.into(),
        ..Default::default()
    };
    let which: Vec<usize> = (0..a.prompts).collect();

    // Exact F16 descriptors.
    let t = Instant::now();
    let exact = random_features(&mut rng, a.exact_gaussians, d);
    let make_exact_s = t.elapsed().as_secs_f64();
    let desc = Descriptors::Features(&exact);
    let exact_cos = fastest(a.repeat, || {
        score_prompts(desc, &prompts, &which, ScoreKind::Cosine)
    })?;
    let exact_rel = fastest(a.repeat, || {
        score_prompts(desc, &prompts, &which, ScoreKind::Relevancy)
    })?;
    drop(exact);

    // PQ codes over random centroids (ADC cost does not depend on the data).
    let pq = random_pq(&mut rng, a.gaussians, d, a.m)?;
    let desc = Descriptors::Pq(&pq);
    let one = [0usize];
    let pq_cos1 = fastest(a.repeat, || {
        score_prompts(desc, &prompts, &one, ScoreKind::Cosine)
    })?;
    let pq_cos = fastest(a.repeat, || {
        score_prompts(desc, &prompts, &which, ScoreKind::Cosine)
    })?;
    let pq_rel = fastest(a.repeat, || {
        score_prompts(desc, &prompts, &which, ScoreKind::Relevancy)
    })?;
    let scores = score_prompts(desc, &prompts, &one, ScoreKind::Cosine)?;
    let sel_thr = fastest(a.repeat, || select(&scores[0], Rule::Threshold(0.05)))?;
    let sel_frac = fastest(a.repeat, || select(&scores[0], Rule::TopFraction(0.01)))?;
    let search = fastest(a.repeat, || {
        profuse_pq::search(
            &pq,
            prompts.embedding(0),
            profuse_pq::DEFAULT_SHORTLIST,
            100,
        )
    })?;

    // Activation masks from a synthetic top-K buffer: every pixel's K ids random.
    let pixels = a.width * a.height;
    let ids: Vec<u32> = (0..pixels * a.k)
        .map(|_| (rng.next() % a.gaussians.max(1) as u64) as u32)
        .collect();
    let weights: Vec<f32> = (0..pixels * a.k)
        .map(|i| 0.5f32.powi((i % a.k) as i32 + 1))
        .collect();
    let sets: Vec<ActiveSet> = (0..a.prompts)
        .map(|q| select(&scores[0], Rule::TopFraction(0.01 * (q + 1) as f64)))
        .collect::<Result<_, _>>()?;
    let refs: Vec<&ActiveSet> = sets.iter().collect();
    let membership = Membership::new(a.gaussians, &refs);
    let act = fastest(a.repeat, || {
        activation(&ids, &weights, a.width, a.height, a.k, &membership)
    })?;
    Ok(json!({
        "gaussians": a.gaussians,
        "exact_gaussians": a.exact_gaussians,
        "dim": d,
        "m": a.m,
        "prompts": a.prompts,
        "threads": profuse_pq::rayon::current_num_threads(),
        "exact_f16_cosine_s": exact_cos,
        "exact_f16_relevancy_s": exact_rel,
        "exact_make_s": make_exact_s,
        "pq_cosine_1_prompt_s": pq_cos1,
        "pq_cosine_s": pq_cos,
        "pq_relevancy_s": pq_rel,
        "pq_search_top100_s": search,
        "select_threshold_s": sel_thr,
        "select_top_frac_s": sel_frac,
        "activation_s": act,
        "activation_mpix_per_s": pixels as f64 / 1e6 / act,
        "width": a.width,
        "height": a.height,
        "k": a.k,
        "repeat": a.repeat,
        "peak_rss_mb": common::peak_rss_mb(),
    }))
}

/// Seconds of the fastest of `repeat` runs of `f` (at least one).
pub(crate) fn fastest<T, E: Into<BoxError>>(
    repeat: usize,
    mut f: impl FnMut() -> Result<T, E>,
) -> Result<f64, BoxError> {
    let mut best = f64::INFINITY;
    for _ in 0..repeat.max(1) {
        let t = Instant::now();
        let out = f().map_err(Into::into)?;
        best = best.min(t.elapsed().as_secs_f64());
        drop(out);
    }
    Ok(best)
}

fn random_features(rng: &mut SplitMix, n: usize, d: usize) -> Features {
    let mut rows = Vec::with_capacity(n * d);
    let mut row = vec![0f32; d];
    for _ in 0..n {
        row.iter_mut().for_each(|v| *v = rng.normal());
        let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
        rows.extend(row.iter().map(|v| f16::from_f32(v / norm)));
    }
    Features {
        dim: d,
        features: Floats::F16(rows.into()),
        valid: vec![1u8; n].into(),
        weight_sum: None,
        extra: Default::default(),
    }
}

pub(crate) fn random_pq(
    rng: &mut SplitMix,
    n: usize,
    d: usize,
    m: usize,
) -> Result<profuse_formats::Pq, BoxError> {
    let dsub = d / m;
    let centroids: Vec<f32> = (0..m * profuse_pq::KSUB * dsub)
        .map(|_| rng.normal() / (d as f32).sqrt())
        .collect();
    let book = profuse_pq::Codebook::new(m, dsub, centroids)?;
    let codes: Vec<u8> = (0..n * m).map(|_| rng.next() as u8).collect();
    let norms: Vec<f32> = codes
        .chunks_exact(m)
        .map(|c| book.decoded_norm(c))
        .collect();
    Ok(book.to_pq(codes, norms, vec![1u8; n]))
}

/// The workspace's SplitMix64 with Box–Muller normals, for benchmark data.
pub(crate) struct SplitMix(pub(crate) SplitMix64);

impl SplitMix {
    pub(crate) fn next(&mut self) -> u64 {
        self.0.next_u64()
    }

    fn uniform(&mut self) -> f64 {
        self.0.unit()
    }

    /// A standard normal sample (Box-Muller).
    pub(crate) fn normal(&mut self) -> f32 {
        let (u, v) = (self.uniform(), self.uniform());
        ((-2.0 * (1.0 - u).ln()).sqrt() * (std::f64::consts::TAU * v).cos()) as f32
    }
}

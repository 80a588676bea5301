//! `query bench --semantics index|both|pq` (issue 24): one text query, LERF relevancy
//! against the canonical negatives with the default threshold and the selection
//! included, over N Gaussians, through a semantic index and through PQ codes in the same
//! run. Storage is counted per Gaussian as the files hold it: PQ = M code bytes, plus 4
//! (norm) and 1 (valid); index = 2 (the U16 index: `--semantics index` builds it with
//! `min_share` 0 and no share, as `fuse --min-share 0` does) or 3 (with the share that a
//! `both` fallback reads), plus the [P, D] F16 table once.

use profuse_formats::label_space::CANONICAL_NEGATIVES;
use profuse_formats::rng::SplitMix64;
use profuse_formats::{f16, Floats, Prompts, SemanticIndex};
use profuse_query::{
    score_prompts, select, ActiveSet, Descriptors, IndexQuery, IndexTable, Indexed, Rule,
    ScoreKind, SelectBuffers, Semantics, DEFAULT_RELEVANCY_THRESHOLD,
};
use serde_json::{json, Value};

use crate::common;
use crate::query::{fastest, random_pq, Params, SplitMix};
use crate::BoxError;

/// Runs the comparison; `semantics` picks the figures reported at the top level.
pub fn run(a: &Params, semantics: Semantics) -> Result<Value, BoxError> {
    check_params(a)?;
    let mut rng = SplitMix(SplitMix64::new(0x51ab_1e24));
    let prompts = random_prompts(&mut rng, a.dim);
    let pq = random_pq(&mut rng, a.gaussians, a.dim, a.m)?;
    let index = random_index(
        &mut rng,
        a.gaussians,
        a.proposals,
        a.dim,
        semantics == Semantics::Both,
    );
    let rule = Rule::Threshold(DEFAULT_RELEVANCY_THRESHOLD);

    let pq_s = fastest(
        if std::env::var_os("SKIPPQ").is_some() {
            1
        } else {
            a.repeat
        },
        || {
            let scores = score_prompts(Descriptors::Pq(&pq), &prompts, &[0], ScoreKind::Relevancy)?;
            select(&scores[0], rule)
        },
    )?;
    let pq_selected = {
        let scores = score_prompts(Descriptors::Pq(&pq), &prompts, &[0], ScoreKind::Relevancy)?;
        select(&scores[0], rule)?.len()
    };
    let indexed = Indexed {
        index: &index,
        fallback: (semantics == Semantics::Both).then_some(&pq),
    };
    // The table is converted once per index (as a viewer or a server holding the index
    // does); that preparation is timed on its own.
    let prepare_s = fastest(a.repeat, || Ok::<_, BoxError>(IndexTable::new(&index)))?;
    let table = IndexTable::new(&index);
    let query = |x: &Indexed<'_>| {
        IndexQuery::with_table(x, &table, &prompts, 0, ScoreKind::Relevancy)?.select(x, rule)
    };
    // A server answering queries keeps its selection buffers: the steady state reuses
    // mapped memory (`query_us`); a one-off query maps fresh pages (`cold_query_us`).
    let cold_s = fastest(a.repeat, || query(&indexed))?;
    let (mut buffers, mut selection) = (SelectBuffers::default(), ActiveSet::default());
    let index_s =
        fastest(a.repeat, || {
            IndexQuery::with_table(&indexed, &table, &prompts, 0, ScoreKind::Relevancy)?
                .select_into(&indexed, rule, &mut buffers, &mut selection)
        })?;
    let index_selected = query(&indexed)?.len();
    let flagged = (0..a.gaussians).filter(|&g| !index.is_dominant(g)).count();

    let per_gaussian = |bytes: usize| bytes as f64 / a.gaussians.max(1) as f64;
    let pq_bytes = per_gaussian(pq.codes.len() + 4 * pq.norms.len() + pq.valid.len());
    let index_bytes = per_gaussian(
        index.index.dtype().size() * index.index.len()
            + index.share.as_ref().map_or(0, |s| s.len()),
    );
    let table_bytes = 2 * index.descriptors.len();
    let pq_entry = json!({
        "query_us": pq_s * 1e6,
        "bytes_per_gaussian": pq_bytes,
        "selected": pq_selected,
    });
    let index_entry = json!({
        "query_us": index_s * 1e6,
        "cold_query_us": cold_s * 1e6,
        "prepare_us": prepare_s * 1e6,
        "bytes_per_gaussian": index_bytes,
        "table_bytes": table_bytes,
        "selected": index_selected,
        "flagged": flagged,
    });
    let top = if semantics == Semantics::Pq {
        &pq_entry
    } else {
        &index_entry
    };
    Ok(json!({
        "semantics": semantics.name(),
        "query_us": top["query_us"],
        "bytes_per_gaussian": top["bytes_per_gaussian"],
        "index": index_entry,
        "pq": pq_entry,
        "gaussians": a.gaussians,
        "proposals": a.proposals,
        "dim": a.dim,
        "m": a.m,
        "score": "relevancy",
        "threshold": DEFAULT_RELEVANCY_THRESHOLD,
        "threads": profuse_pq::rayon::current_num_threads(),
        "repeat": a.repeat,
        "peak_rss_mb": common::peak_rss_mb(),
    }))
}

/// That `--dim` is a positive multiple of `--m` and there is a proposal.
fn check_params(a: &Params) -> Result<(), BoxError> {
    if a.dim == 0 || a.m == 0 || !a.dim.is_multiple_of(a.m) || a.proposals == 0 {
        return Err(format!(
            "--dim {} must be a positive multiple of --m {}, and --proposals >= 1",
            a.dim, a.m
        )
        .into());
    }
    Ok(())
}

/// One query prompt plus the four canonical negatives, random unit-free embeddings.
fn random_prompts(rng: &mut SplitMix, d: usize) -> Prompts {
    let mut names = vec!["query".to_string()];
    names.extend(CANONICAL_NEGATIVES.map(String::from));
    let embeddings: Vec<f32> = (0..names.len() * d).map(|_| rng.normal()).collect();
    Prompts {
        names,
        dim: d,
        embeddings: embeddings.into(),
        ..Default::default()
    }
}

/// N Gaussians spread over P random F16 unit rows; with `shares`, shares uniform in
/// [1/255, 1] with the default `min_share` (about half the Gaussians dominant), else no
/// share and `min_share` 0 (every Gaussian dominant).
fn random_index(rng: &mut SplitMix, n: usize, p: usize, d: usize, shares: bool) -> SemanticIndex {
    let mut table = Vec::with_capacity(p * d);
    let mut row = vec![0f32; d];
    for _ in 0..p {
        row.iter_mut().for_each(|v| *v = rng.normal());
        let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
        table.extend(row.iter().map(|v| f16::from_f32(v / norm)));
    }
    let ids: Vec<Option<u32>> = (0..n)
        .map(|_| Some((rng.next() % p as u64) as u32))
        .collect();
    SemanticIndex {
        descriptors: Floats::F16(table.into()),
        dim: d,
        index: SemanticIndex::index_of(p, &ids),
        share: shares.then(|| {
            (0..n)
                .map(|_| 1 + (rng.next() % 255) as u8)
                .collect::<Vec<u8>>()
                .into()
        }),
        min_share: match shares {
            true => profuse_formats::quantise_share(profuse_fuse::DEFAULT_MIN_SHARE),
            false => 0,
        },
        extra: Default::default(),
    }
}

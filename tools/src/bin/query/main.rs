//! `query`: open-vocabulary 3D selection (paper §3.4, §4.2). Scores every Gaussian's
//! descriptor against text prompts (or the descriptor of a clicked mask), selects the
//! active Gaussians in 3D, and writes per view activation masks (PNG), overlays and the
//! selection files (and, on request, the selected Gaussians as an INRIA PLY).
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; progress goes to stderr when it is a terminal and `--quiet` is not given.
//! On failure the error goes to stderr and the exit code is 1; bad input writes nothing.

use std::process::ExitCode;
use std::time::Instant;

use clap::Parser;
use profuse_bench::query as bench;
use profuse_formats::FileKind;
use profuse_query::{
    stats, DescriptorPath, Inputs, Layout, QueryOptions, Rule, ScoreInputs, ScoreKind,
    ViewSelection,
};
use profuse_tools::{chatty, init_threads, progress_bar, run, BoxError};
use serde_json::{json, Value};

mod args;
mod click;

use args::{Cli, Command, RunArgs, ScoresArgs};

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| match cli.command {
        Command::Run(a) => run_query(*a, quiet),
        Command::Scores(a) => scores(a),
        Command::Bench { params, threads } => {
            init_threads(threads)?;
            bench::run(&params)
        }
    })
}

fn run_query(a: RunArgs, quiet: bool) -> Result<Value, BoxError> {
    let t0 = Instant::now();
    let source = a.descriptors.source()?;
    let (inputs, target) = match &a.click.click {
        Some(c) => {
            let (inputs, target) = click::inputs(&a, c, &source)?;
            (inputs, Some(target))
        }
        None => {
            let prompts = a.descriptors.prompts()?;
            let inputs = Inputs::load(&a.gaussians, &a.cameras, &source, prompts)?;
            (inputs, None)
        }
    };
    let load_s = t0.elapsed().as_secs_f64();
    let rule = match (a.threshold, a.top_frac) {
        (Some(t), _) => Some(Rule::Threshold(t)),
        (None, Some(f)) => Some(Rule::TopFraction(f)),
        (None, None) => None,
    };
    let views = if let Some(dir) = &a.views_from_labels {
        ViewSelection::FromLabels(dir.clone())
    } else if a.views.is_empty() {
        ViewSelection::All
    } else {
        ViewSelection::List(a.views.clone())
    };
    let options = QueryOptions {
        prompts: match &target {
            Some(t) => profuse_query::PromptSelection::Names(vec![t.name()]),
            None => a.prompt.selection()?,
        },
        score: a.prompt.score,
        rule,
        gamma: a.gamma,
        k: usize::from(a.k),
        scale: a.scale,
        views,
        layout: a.layout,
        overlay: !a.no_overlay,
    };
    let mut plan = inputs.plan(&options)?;
    if let Some(t) = &target {
        plan.prompts[0].extra = t.metadata();
    }
    // The subset is cut before anything is written, so a bad request writes nothing.
    let export = match (&a.export_ply, plan.prompts.as_slice()) {
        (None, _) => None,
        (Some(path), [one]) => Some((
            path,
            profuse_query::selected_gaussians(&inputs.gaussians, &one.active.ids)?,
        )),
        (Some(_), many) => {
            return Err(format!(
                "--export-ply writes one selection, but {} prompts are queried",
                many.len()
            )
            .into())
        }
    };
    let bar = progress_bar(chatty(quiet), plan.views.len() as u64, "query", "views");
    bar.set_message(format!("{} prompts", plan.prompts.len()));
    let report = plan.run_replacing(&inputs.gaussians, &a.out, &mut |_, _| bar.inc(1));
    bar.finish_and_clear();
    let report = report?;
    let mut value = serde_json::to_value(&report)?;
    if let Some((path, subset)) = &export {
        scene_io::ply::write_inria_ply(path, subset)?;
        value["export_ply"] = json!({"path": path.to_string_lossy(), "gaussians": subset.len()});
    }
    if let Some(t) = &target {
        value["click"] = serde_json::to_value(t)?;
    }
    value["out"] = json!(a.out.to_string_lossy());
    value["gaussians"] = json!(inputs.gaussians.len());
    value["descriptors"] = json!(source.path().to_string_lossy());
    value["load_s"] = json!(load_s);
    value["total_s"] = json!(t0.elapsed().as_secs_f64());
    Ok(value)
}

fn scores(a: ScoresArgs) -> Result<Value, BoxError> {
    let source = a.descriptors.source()?;
    let inputs = ScoreInputs::load(&source, a.descriptors.prompts()?)?;
    let kind: ScoreKind = a.prompt.score;
    let which = inputs.resolve_prompts(&a.prompt.selection()?)?;
    let t0 = Instant::now();
    let all = inputs.scores(&which, kind)?;
    let score_s = t0.elapsed().as_secs_f64();
    if let Some(dir) = &a.out_dir {
        std::fs::create_dir_all(dir)
            .map_err(|e| format!("{}: cannot create directory: {e}", dir.display()))?;
    }
    let mut prompts = Vec::new();
    for (&q, s) in which.iter().zip(&all) {
        let stats = stats::prompt_scores(&inputs, q, s, kind, a.top, a.shortlist)?;
        let mut entry = serde_json::to_value(&stats)?;
        if let Some(dir) = &a.out_dir {
            let name = profuse_query::file_name_of(&stats.prompt, Layout::Prompt)?;
            let path = dir.join(format!("{name}.safetensors"));
            stats::every_valid_selection(&stats.prompt, kind, s)?.write(&path)?;
            entry["file"] = json!(path.to_string_lossy());
        }
        prompts.push(entry);
    }
    Ok(json!({
        "score": kind,
        "descriptors": source.path().to_string_lossy(),
        "gaussians": inputs.descriptors().len(),
        "top_method": match (&source, kind) {
            (DescriptorPath::Pq(_), ScoreKind::Cosine) => "adc_shortlist_exact_rerank",
            _ => "full_scan",
        },
        "prompts": prompts,
        "score_s": score_s,
    }))
}

//! `profuse`: the umbrella command of the ProFuse pipeline: `inspect` (SPEC.md §5 report of
//! any file), `run` (every stage with up-to-date checks), `demo` (the paper's experiment
//! against the `--no-proposals` baseline on a synth scene) and `sweep` (the demo over
//! seeds and fault sets), `view` (the browser viewer of `profuse_view`). The work lives in `profuse_pipeline` (`cli`, `demo`, `sweep`);
//! this tool parses arguments, displays progress and prints.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::Parser;
use profuse_experiments::demo::{self, DemoOptions};
use profuse_experiments::record;
use profuse_experiments::sweep::{self, SweepEvent, SweepOptions};
use profuse_pipeline::cli;
use profuse_pipeline::RunOptions;
use profuse_tools::stages::StageBars;
use profuse_tools::{chatty, print_result, run, BoxError};
use serde_json::Value;

mod args;
mod prepare;
use args::{Cli, Command, Common, SceneArgs};

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::Inspect { file } => inspect(&file),
        Command::Prepare(a) => run(|| prepare::run(a)),
        Command::Run {
            scene,
            proposals,
            gaussians,
            until,
            fuse_partials,
            warp_partials,
            semantics,
            mut common,
        } => run(|| {
            if let Some(s) = semantics {
                common.set.push(format!("query.semantics=\"{}\"", s.name()));
            }
            let opts = RunOptions {
                proposals,
                gaussians,
                until,
                fuse_partials,
                warp_partials,
                ..run_options(&common)
            };
            run_scene(&scene, &opts, &common)
        }),
        Command::FuseShard {
            scene,
            views,
            partial_out,
            common,
        } => run(|| fuse_shard(&scene, views, &partial_out, &common)),
        Command::WarpShard {
            scene,
            pairs,
            partial_out,
            common,
        } => run(|| warp_shard(&scene, pairs, &partial_out, &common)),
        Command::Demo {
            out,
            seed,
            scene,
            json,
            common,
        } => print_result(demo(out, seed, &scene, json, &common)),
        Command::View {
            dir,
            port,
            host,
            gaussians_only,
            quiet,
        } => view(&dir, host, port, gaussians_only, quiet),
        Command::Sweep {
            seeds,
            faults,
            preset,
            json,
            out,
            keep,
            oracle,
            config,
            set,
            quiet,
        } => print_result((|| {
            let opts = SweepOptions {
                seeds: sweep::parse_seeds(&seeds)?,
                faults: sweep::parse_fault_sets(&faults)?,
                preset,
                out,
                keep,
                config: record::demo_config(config.as_deref(), &set)?,
                oracle,
            };
            run_sweep(&opts, json, quiet)
        })()),
    }
}

fn inspect(file: &Path) -> ExitCode {
    let report = profuse_formats::inspect(file);
    let text = serde_json::to_string_pretty(&report.json).unwrap_or_else(|_| "{}".to_string());
    if writeln!(std::io::stdout().lock(), "{text}").is_err() {
        return ExitCode::FAILURE;
    }
    match report.error {
        None => ExitCode::SUCCESS,
        Some(e) => {
            profuse_tools::report_error(&e);
            ExitCode::FAILURE
        }
    }
}

fn run_options(common: &Common) -> RunOptions {
    RunOptions {
        out: common.out_dir.clone(),
        force: common.force,
        wait: common.wait,
        ..RunOptions::default()
    }
}

fn run_scene(scene: &Path, opts: &RunOptions, common: &Common) -> Result<Value, BoxError> {
    let config = cli::run_config(common.config.as_deref(), &common.set)?;
    let bars = StageBars::new(chatty(common.quiet));
    let value = record::run_and_record(scene, &config, opts, &|e| bars.event(e))?;
    print_timing(common.quiet, &value);
    Ok(value)
}

fn fuse_shard(
    scene: &Path,
    views: std::ops::Range<usize>,
    partial_out: &Path,
    common: &Common,
) -> Result<Value, BoxError> {
    let config = cli::run_config(common.config.as_deref(), &common.set)?;
    let out = common.out_dir.clone().unwrap_or_else(|| scene.join("out"));
    let bar =
        profuse_tools::progress_bar(chatty(common.quiet), views.len() as u64, "fuse", "views");
    let report =
        profuse_pipeline::fuse_shard(scene, &out, &config, views, partial_out, &mut |_| {
            bar.inc(1)
        })?;
    bar.finish_and_clear();
    Ok(serde_json::to_value(report)?)
}

fn warp_shard(
    scene: &Path,
    pairs: std::ops::Range<usize>,
    partial_out: &Path,
    common: &Common,
) -> Result<Value, BoxError> {
    let config = cli::run_config(common.config.as_deref(), &common.set)?;
    let out = common.out_dir.clone().unwrap_or_else(|| scene.join("out"));
    let bar = profuse_tools::progress_bar(
        chatty(common.quiet),
        pairs.len() as u64,
        "warp-graph",
        "view pairs",
    );
    let report =
        profuse_pipeline::warp_shard(scene, &out, &config, pairs, partial_out, &|_, _| bar.inc(1))?;
    bar.finish_and_clear();
    Ok(serde_json::to_value(report)?)
}

/// The paper's Table 4 on stderr, from a summary's `timing_s`, unless quiet.
fn print_timing(quiet: bool, summary: &Value) {
    if chatty(quiet) {
        if let Ok(timing) = serde_json::from_value(summary["timing_s"].clone()) {
            eprintln!("{}", cli::timing_table(&timing));
        }
    }
}

fn demo(
    out: Option<PathBuf>,
    seed: u64,
    scene: &SceneArgs,
    as_json: bool,
    common: &Common,
) -> Result<String, BoxError> {
    let show = chatty(common.quiet);
    let opts = DemoOptions {
        scene: out,
        seed,
        preset: scene.preset,
        faults: synth::FaultSet::parse(&scene.faults)?,
        config: record::demo_config(common.config.as_deref(), &common.set)?,
        run: run_options(common),
    };
    let bars = StageBars::new(show);
    let value = demo::run_demo(&opts, &|e| bars.event(e), &|msg| {
        if show {
            eprintln!("{msg}");
        }
    })?;
    print_timing(common.quiet, &value);
    Ok(if as_json {
        serde_json::to_string_pretty(&value)?
    } else {
        demo::demo_text(&value)
    })
}

fn run_sweep(opts: &SweepOptions, as_json: bool, quiet: bool) -> Result<String, BoxError> {
    let show = chatty(quiet);
    let events = |e: SweepEvent<'_>| {
        if show {
            eprintln!("{}", e.line());
        }
    };
    let report = sweep::sweep(opts, &events)?;
    if show && opts.keep {
        eprintln!("scenes kept under {}", sweep::parent_dir(opts).display());
    }
    Ok(if as_json {
        serde_json::to_string_pretty(&report)?
    } else {
        sweep::text_table(&report)
    })
}

/// Opens the output, binds, prints the URL and serves until the process is stopped.
fn view(dir: &Path, host: std::net::IpAddr, port: u16, only: bool, quiet: bool) -> ExitCode {
    use profuse_view::{OutputPaths, ViewScene};
    if !host.is_loopback() {
        // Said even with --quiet: the scene becomes readable by anyone who can reach it.
        eprintln!(
            "profuse view: warning: --host {host} serves the scene and its PLY export to every \
             machine that can reach this one, without authentication; use 127.0.0.1 (the \
             default) unless that is what you want"
        );
    }
    let opened = profuse_view::listen(host, port).and_then(|listener| {
        let paths = if only {
            OutputPaths::find_gaussians_only(dir)?
        } else {
            OutputPaths::find(dir)?
        };
        Ok((listener, ViewScene::open_paths(paths)?))
    });
    let (listener, scene) = match opened {
        Ok(both) => both,
        Err(e) => return print_result(Err(e.into())),
    };
    let line = serde_json::json!({ "url": listener.url() }).to_string();
    let mut out = std::io::stdout().lock();
    if writeln!(out, "{line}").and_then(|()| out.flush()).is_err() {
        return ExitCode::FAILURE;
    }
    drop(out);
    if !quiet {
        eprintln!(
            "profuse view: serving {} on {} (Ctrl-C to stop)",
            dir.display(),
            listener.url()
        );
    }
    listener.serve(&scene);
    ExitCode::SUCCESS
}

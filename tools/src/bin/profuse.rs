//! `profuse`: the umbrella command of the ProFuse pipeline.
//!
//! `profuse inspect FILE` prints a JSON report of any ProFuse file (SPEC.md §5) and
//! exits 1 when the file is invalid. Further subcommands (`run`, `demo`) arrive with the
//! pipeline stages.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(
    name = "profuse",
    version,
    about = "ProFuse: open-vocabulary 3D Gaussians without render-supervised training"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Validate a ProFuse file and print its kind, version, tensors, metadata and counts as
    /// JSON on stdout. Exit code 0 when valid, 1 when invalid (the error also goes to stderr).
    Inspect {
        /// The file to inspect (any kind of SPEC.md).
        file: PathBuf,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::Inspect { file } => inspect(&file),
    }
}

fn inspect(file: &std::path::Path) -> ExitCode {
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

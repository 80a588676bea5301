//! Shared plumbing of the command-line tools: one JSON object on stdout, messages on
//! stderr, exit code 1 with the full error chain on failure.

use std::error::Error;
use std::io::{IsTerminal, Write};
use std::process::ExitCode;

/// Boxed error of a tool's main body.
pub type BoxError = Box<dyn Error + Send + Sync + 'static>;

/// Runs a tool body: prints its JSON result on stdout (pretty, one object), or the error
/// and its causes on stderr with exit code 1.
pub fn run(body: impl FnOnce() -> Result<serde_json::Value, BoxError>) -> ExitCode {
    match body() {
        Ok(value) => {
            let text = serde_json::to_string_pretty(&value).unwrap_or_else(|_| "{}".to_string());
            let mut out = std::io::stdout().lock();
            if writeln!(out, "{text}").is_err() {
                return ExitCode::FAILURE;
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            report_error(&*e);
            ExitCode::FAILURE
        }
    }
}

/// Prints `error: ...` and each `caused by: ...` on stderr.
pub fn report_error(e: &(dyn Error + 'static)) {
    let mut err = std::io::stderr().lock();
    let _ = writeln!(err, "error: {e}");
    let mut source = e.source();
    while let Some(s) = source {
        let _ = writeln!(err, "  caused by: {s}");
        source = s.source();
    }
}

/// Whether progress and informational messages should be shown: not with `--quiet`, and
/// not when stderr is not a terminal (piped or redirected).
pub fn chatty(quiet: bool) -> bool {
    !quiet && std::io::stderr().is_terminal()
}

/// Prints a warning on stderr (warnings are shown even when not chatty, unless quiet).
pub fn warn(quiet: bool, msg: &str) {
    if !quiet {
        let _ = writeln!(std::io::stderr().lock(), "warning: {msg}");
    }
}

/// Peak resident set size (VmHWM) of this process in MiB, from /proc/self/status
/// (0 where unavailable). The `bench` subcommands report it.
pub fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<f64>().ok())
        })
        .map_or(0.0, |kb| kb / 1024.0)
}

/// Writes a tool's output file (JSON, PNG) atomically with
/// [`profuse_formats::write_atomically`]; the error names the file and the failed step.
pub fn write_file(path: &std::path::Path, bytes: &[u8]) -> Result<(), BoxError> {
    profuse_formats::write_atomically(path, |mut f| f.write_all(bytes))
        .map_err(|(action, e)| format!("{}: {action}: {e}", path.display()).into())
}

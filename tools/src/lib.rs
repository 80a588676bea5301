//! Shared plumbing of the command-line tools: one JSON object on stdout, messages on
//! stderr, exit code 1 with the full error chain on failure.

pub mod scene;
pub mod stages;
pub mod warps;

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

/// Prints `text` and a newline on stdout, or on failure the error (exit code 1): for
/// commands whose result is text rather than one JSON object.
pub fn print_result(result: Result<String, BoxError>) -> ExitCode {
    match result {
        Ok(text) => {
            if writeln!(std::io::stdout().lock(), "{text}").is_err() {
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

/// A progress bar of `len` units on stderr when `show` (hidden otherwise):
/// `PREFIX [bar] pos/len UNIT [elapsed < eta] msg`.
pub fn progress_bar(show: bool, len: u64, prefix: &str, unit: &str) -> indicatif::ProgressBar {
    if !show {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(len);
    let template =
        format!("{{prefix}} {{bar:40}} {{pos}}/{{len}} {unit} [{{elapsed}} < {{eta}}] {{msg}}");
    if let Ok(style) = indicatif::ProgressStyle::with_template(&template) {
        bar.set_style(style);
    }
    bar.set_prefix(prefix.to_string());
    bar
}

/// A spinner with a message on stderr when `show` (hidden otherwise), for work of
/// unknown length.
pub fn spinner(show: bool, msg: &str) -> indicatif::ProgressBar {
    if !show {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new_spinner();
    bar.set_message(msg.to_string());
    bar.enable_steady_tick(std::time::Duration::from_millis(120));
    bar
}

/// A benchmark's progress ([`profuse_bench::common::Progress`]) as bars on stderr: a
/// spinner for a phase of unknown length, else a bar.
#[derive(Debug)]
pub struct Bars {
    show: bool,
    bar: std::sync::Mutex<indicatif::ProgressBar>,
}

impl Bars {
    /// Bars shown when `show` (see [`chatty`]).
    pub fn new(show: bool) -> Bars {
        Bars {
            show,
            bar: std::sync::Mutex::new(indicatif::ProgressBar::hidden()),
        }
    }
}

impl profuse_bench::common::Progress for Bars {
    fn start(&self, phase: &str, len: u64) {
        let bar = if len == 0 {
            spinner(self.show, phase)
        } else {
            progress_bar(self.show, len, phase, "")
        };
        if let Ok(mut b) = self.bar.lock() {
            b.finish_and_clear();
            *b = bar;
        }
    }

    fn inc(&self, n: u64) {
        if let Ok(b) = self.bar.lock() {
            b.inc(n);
        }
    }

    fn finish(&self) {
        if let Ok(b) = self.bar.lock() {
            b.finish_and_clear();
        }
    }

    fn note(&self, message: &str) {
        if self.show {
            let _ = writeln!(std::io::stderr().lock(), "{message}");
        }
    }
}

/// Sets the size of rayon's global thread pool (`--threads`); `None` keeps rayon's
/// default (RAYON_NUM_THREADS or the core count). Results never depend on it.
pub fn init_threads(threads: Option<usize>) -> Result<(), BoxError> {
    if let Some(n) = threads {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global()?;
    }
    Ok(())
}

/// Encodes a PNG (8-bit RGB, 8- or 16-bit grey) and writes it atomically.
pub fn write_png(
    path: &std::path::Path,
    data: &[u8],
    width: u32,
    height: u32,
    color: image::ExtendedColorType,
) -> Result<(), BoxError> {
    let bytes = profuse_formats::png::encode(data, width, height, color)
        .map_err(|e| format!("cannot encode {}: {e}", path.display()))?;
    write_file(path, &bytes)
}

/// Writes a tool's output file (JSON, PNG) atomically with
/// [`profuse_formats::write_atomically`]; the error names the file and the failed step.
pub fn write_file(path: &std::path::Path, bytes: &[u8]) -> Result<(), BoxError> {
    profuse_formats::write_atomically(path, |mut f| f.write_all(bytes))
        .map_err(|(action, e)| format!("{}: {action}: {e}", path.display()).into())
}

/// Checks a command's output files before it does any work (issue 20): each must name a
/// regular file (which is replaced) or nothing, never a device, FIFO, socket or
/// directory ([`profuse_formats::output::check_output_file`]); unclaimed temporary files
/// that killed runs left next to them are removed
/// ([`profuse_formats::output::clean_leftovers`]).
pub fn check_outputs<'a>(
    paths: impl IntoIterator<Item = &'a std::path::Path>,
) -> Result<(), BoxError> {
    use profuse_formats::output::{check_output_file, clean_leftovers, LEFTOVER_MIN_AGE};
    for path in paths {
        check_output_file(path)?;
        let dir = path.parent().filter(|p| !p.as_os_str().is_empty());
        clean_leftovers(dir.unwrap_or(std::path::Path::new(".")), LEFTOVER_MIN_AGE);
    }
    Ok(())
}

/// A half-open range `A..B` of `what` (views, view pairs) from the command line, A <= B.
pub fn half_open_range(s: &str, what: &str) -> Result<std::ops::Range<usize>, String> {
    let (a, b) = s
        .split_once("..")
        .ok_or_else(|| format!("expected A..B (half-open {what} range), got {s:?}"))?;
    let parse = |x: &str| {
        x.trim()
            .parse::<usize>()
            .map_err(|e| format!("{x:?} in {s:?}: {e}"))
    };
    let (a, b) = (parse(a)?, parse(b)?);
    if a > b {
        return Err(format!("{what} range {s:?}: A must not exceed B"));
    }
    Ok(a..b)
}

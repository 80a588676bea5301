//! Runs one COLMAP step as a subprocess: its output is streamed line by line to a log file
//! and to a line handler (progress), and its last lines are kept for the error message.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::Instant;

use crate::{SfmError, SfmStep};

/// Lines of standard error kept for [`SfmError::StepFailed`].
const TAIL_LINES: usize = 20;
/// A line longer than this is split (a program that never writes a newline cannot grow
/// our memory without bound).
const MAX_LINE_BYTES: u64 = 64 * 1024;

#[derive(Clone, Copy)]
enum Stream {
    Out,
    Err,
}

/// Spawns `cmd`, trying again for up to a second while the program is "text file busy"
/// (ETXTBSY): an executable just written (a wrapper script) stays busy while any process
/// forked meanwhile, by another thread of this program, still holds its write descriptor
/// between fork and exec. Any other error is returned at once.
fn spawn_retrying_busy(cmd: &mut Command) -> std::io::Result<std::process::Child> {
    let mut tries = 0;
    loop {
        match cmd.spawn() {
            Err(e) if e.kind() == std::io::ErrorKind::ExecutableFileBusy && tries < 20 => {
                tries += 1;
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
            other => return other,
        }
    }
}

/// Runs `cmd` to completion; returns the wall-clock seconds it took. The full output
/// (standard output and error, interleaved as they arrive) goes to `log`.
pub(crate) fn run_step(
    step: SfmStep,
    mut cmd: Command,
    log: &Path,
    on_line: &mut dyn FnMut(&str),
) -> Result<f64, SfmError> {
    let mut log_file = std::fs::File::create(log).map_err(|e| SfmError::io(log, e))?;
    let program = Path::new(cmd.get_program()).to_path_buf();
    let start = Instant::now();
    cmd.stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let mut child = spawn_retrying_busy(&mut cmd).map_err(|source| SfmError::Spawn {
        step,
        program,
        source,
    })?;
    let (tx, rx) = mpsc::channel::<(Stream, String)>();
    let mut readers = Vec::new();
    if let Some(out) = child.stdout.take() {
        let tx = tx.clone();
        readers.push(std::thread::spawn(move || forward(out, Stream::Out, &tx)));
    }
    if let Some(err) = child.stderr.take() {
        let tx = tx.clone();
        readers.push(std::thread::spawn(move || forward(err, Stream::Err, &tx)));
    }
    drop(tx);
    let (mut err_tail, mut out_tail) = (VecDeque::new(), VecDeque::new());
    let mut write_error = None;
    for (stream, line) in rx {
        if write_error.is_none() {
            write_error = writeln!(log_file, "{line}").err();
        }
        on_line(&line);
        let tail = match stream {
            Stream::Out => &mut out_tail,
            Stream::Err => &mut err_tail,
        };
        if tail.len() == TAIL_LINES {
            tail.pop_front();
        }
        tail.push_back(line);
    }
    let status = child.wait().map_err(|e| SfmError::io(log, e))?;
    for reader in readers {
        // A reader thread only returns; it cannot panic on our data.
        let _ = reader.join();
    }
    let seconds = start.elapsed().as_secs_f64();
    if let Some(e) = write_error {
        return Err(SfmError::io(log, e));
    }
    if !status.success() {
        let tail = if err_tail.is_empty() {
            out_tail
        } else {
            err_tail
        };
        return Err(SfmError::StepFailed {
            step,
            status: status.to_string(),
            tail: Vec::from(tail).join("\n"),
            log: log.to_path_buf(),
        });
    }
    Ok(seconds)
}

/// Sends the lines of `stream` (lossily decoded, carriage returns and line breaks
/// trimmed) until it ends or fails.
fn forward(stream: impl Read, kind: Stream, tx: &mpsc::Sender<(Stream, String)>) {
    let mut reader = BufReader::new(stream);
    let mut buf = Vec::new();
    loop {
        buf.clear();
        match (&mut reader)
            .take(MAX_LINE_BYTES)
            .read_until(b'\n', &mut buf)
        {
            Ok(0) | Err(_) => return,
            Ok(_) => {
                let line = String::from_utf8_lossy(&buf);
                let line = line.trim_end_matches(['\n', '\r']).to_string();
                if tx.send((kind, line)).is_err() {
                    return;
                }
            }
        }
    }
}

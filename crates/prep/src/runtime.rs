//! Finding and loading the ONNX Runtime shared library, and opening model sessions.
//!
//! `ort` is built with `load-dynamic`: nothing is downloaded or linked at build time; the
//! library is opened at run time from, in order, an explicit path (`--ort-lib`), the
//! `ORT_DYLIB_PATH` environment variable, or the `onnxruntime` Python package's `capi/`
//! folder (asked from `python3`, a convenience for machines where the wheel is installed).

use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

pub use ort::environment::Environment;
use ort::session::Session;

use crate::error::{PrepError, Result};

/// The library of the process, loaded once (ONNX Runtime allows one per process).
static ENVIRONMENT: OnceLock<(PathBuf, Environment)> = OnceLock::new();
static LOADING: Mutex<()> = Mutex::new(());

/// Where the ONNX Runtime library is: `explicit`, else `ORT_DYLIB_PATH`, else the
/// `onnxruntime` Python package's library. The error lists what was tried.
pub fn find_library(explicit: Option<&Path>) -> Result<PathBuf> {
    let mut tried = Vec::new();
    if let Some(p) = explicit {
        if p.is_file() {
            return Ok(p.to_path_buf());
        }
        tried.push(format!("--ort-lib {} (no such file)", p.display()));
    }
    match std::env::var_os("ORT_DYLIB_PATH") {
        Some(p) if Path::new(&p).is_file() => return Ok(PathBuf::from(p)),
        Some(p) => tried.push(format!(
            "ORT_DYLIB_PATH={} (no such file)",
            Path::new(&p).display()
        )),
        None => tried.push("ORT_DYLIB_PATH (not set)".to_string()),
    }
    match python_library() {
        Some(p) => return Ok(p),
        None => tried.push("python3 -c 'import onnxruntime' (no library found)".to_string()),
    }
    Err(PrepError::RuntimeNotFound {
        tried: tried.join("; "),
    })
}

/// The `libonnxruntime.so*` inside the installed `onnxruntime` Python package, if any.
fn python_library() -> Option<PathBuf> {
    let out = std::process::Command::new("python3")
        .args([
            "-c",
            "import onnxruntime, os; print(os.path.join(os.path.dirname(onnxruntime.__file__), 'capi'))",
        ])
        .stderr(std::process::Stdio::null())
        .output()
        .ok()?;
    if !out.status.success() {
        return None;
    }
    let dir = PathBuf::from(String::from_utf8(out.stdout).ok()?.trim());
    let mut libs: Vec<PathBuf> = std::fs::read_dir(&dir)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("libonnxruntime.so") || n == "libonnxruntime.dylib")
        })
        .collect();
    // The longest name is the versioned file (libonnxruntime.so.1.32.0), not a link.
    libs.sort_by_key(|p| std::cmp::Reverse(p.as_os_str().len()));
    libs.into_iter().next()
}

/// Loads the library (once per process) and returns the environment sessions are made in.
/// A second call with another path uses the library already loaded.
pub fn environment(library: &Path) -> Result<&'static Environment> {
    if let Some((_, env)) = ENVIRONMENT.get() {
        return Ok(env);
    }
    let _guard = LOADING.lock().unwrap_or_else(|e| e.into_inner());
    if let Some((_, env)) = ENVIRONMENT.get() {
        return Ok(env);
    }
    let load = |message: String| PrepError::RuntimeLoad {
        path: library.to_path_buf(),
        message,
    };
    let absolute = std::fs::canonicalize(library).map_err(|e| load(e.to_string()))?;
    let env = ort::init_from(&absolute)
        .map_err(|e| load(e.to_string()))?
        .with_name("profuse-prep")
        .build()
        .map_err(|e| load(e.to_string()))?;
    Ok(&ENVIRONMENT.get_or_init(|| (absolute, env)).1)
}

/// Opens a model with `threads` intra-op threads.
pub fn open_session(env: &Environment, model: &Path, threads: usize) -> Result<Session> {
    let err = |action, e: String| PrepError::Onnx {
        model: model.to_path_buf(),
        action,
        message: e,
    };
    if !model.is_file() {
        return Err(err("cannot open the model", "no such file".to_string()));
    }
    Session::builder(env)
        .map_err(|e| err("cannot create a session", e.to_string()))?
        .with_intra_threads(threads.max(1))
        .map_err(|e| err("cannot set threads", e.to_string()))?
        .commit_from_file(model)
        .map_err(|e| err("cannot load the model", e.to_string()))
}

/// The names of a session's inputs and outputs.
pub fn io_names(session: &Session) -> (Vec<String>, Vec<String>) {
    (
        session
            .inputs()
            .iter()
            .map(|i| i.name().to_string())
            .collect(),
        session
            .outputs()
            .iter()
            .map(|o| o.name().to_string())
            .collect(),
    )
}

/// Checks that a session has the named inputs and outputs.
pub fn require_io(
    session: &Session,
    model: &Path,
    inputs: &[&str],
    outputs: &[&str],
) -> Result<()> {
    let (have_in, have_out) = io_names(session);
    for (want, have, what) in [(inputs, &have_in, "input"), (outputs, &have_out, "output")] {
        if let Some(missing) = want.iter().find(|n| !have.iter().any(|h| h == *n)) {
            return Err(PrepError::ModelInterface {
                model: model.to_path_buf(),
                message: format!("no {what} `{missing}` (has {have:?}); expected {want:?}"),
            });
        }
    }
    Ok(())
}

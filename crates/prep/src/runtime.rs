//! Finding and loading the ONNX Runtime shared library, and opening model sessions.
//!
//! `ort` is built with `load-dynamic`: nothing is downloaded or linked at build time; the
//! library is opened at run time from, in order, an explicit path (`--ort-lib`), the
//! `ORT_DYLIB_PATH` environment variable, or the `onnxruntime` Python package's `capi/`
//! folder (asked from `python3 -I`, a convenience for machines where the wheel is
//! installed). A given path or variable that names no file is an error, not a reason to
//! look elsewhere.

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
    // An explicit path is the user's choice: a wrong one is an error, never a silent
    // fallback to another library.
    if let Some(p) = explicit {
        if p.is_file() {
            return Ok(p.to_path_buf());
        }
        return Err(PrepError::RuntimeNotFound {
            tried: format!("--ort-lib {} (no such file)", p.display()),
        });
    }
    let mut tried = Vec::new();
    match std::env::var_os("ORT_DYLIB_PATH") {
        Some(p) if Path::new(&p).is_file() => return Ok(PathBuf::from(p)),
        Some(p) => {
            return Err(PrepError::RuntimeNotFound {
                tried: format!("ORT_DYLIB_PATH={} (no such file)", Path::new(&p).display()),
            })
        }
        None => tried.push("ORT_DYLIB_PATH (not set)".to_string()),
    }
    match python_library() {
        Some(p) => return Ok(p),
        None => tried.push("python3 -I -c 'import onnxruntime' (no library found)".to_string()),
    }
    Err(PrepError::RuntimeNotFound {
        tried: tried.join("; "),
    })
}

/// The command that asks `python3` where the `onnxruntime` package is.
fn python_probe() -> std::process::Command {
    let mut cmd = std::process::Command::new("python3");
    // -I (isolated): neither the current directory nor PYTHON* variables reach sys.path,
    // so an `onnxruntime.py` planted in a scene folder is not imported and run.
    cmd.args([
        "-I",
        "-c",
        "import onnxruntime, os; print(os.path.join(os.path.dirname(onnxruntime.__file__), 'capi'))",
    ])
    .stderr(std::process::Stdio::null());
    cmd
}

/// The `libonnxruntime.so*` inside the installed `onnxruntime` Python package, if any.
fn python_library() -> Option<PathBuf> {
    let out = python_probe().output().ok()?;
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

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_given_library_path_that_names_no_file_is_an_error_not_a_fallback() {
        let e = find_library(Some(Path::new("/nonexistent/libonnxruntime.so"))).unwrap_err();
        let text = e.to_string();
        assert!(text.contains("/nonexistent/libonnxruntime.so"), "{text}");
        assert!(!text.contains("python3"), "no fallback was tried: {text}");
    }

    /// A scene folder with a planted `onnxruntime.py`: probing from there must not import
    /// (and so run) it.
    #[test]
    fn the_python_probe_does_not_import_from_the_current_directory() {
        if std::process::Command::new("python3")
            .arg("-V")
            .output()
            .is_err()
        {
            eprintln!("SKIP: no python3");
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let marker = dir.path().join("ran");
        std::fs::write(
            dir.path().join("onnxruntime.py"),
            format!(
                "open({:?}, 'w').write('planted')\n__file__ = '/x'\n",
                marker
            ),
        )
        .unwrap();
        let _ = python_probe().current_dir(dir.path()).output().unwrap();
        assert!(!marker.exists(), "the planted onnxruntime.py ran");
        // The same command without -I does import it: the test can fail.
        let _ = std::process::Command::new("python3")
            .args(["-c", "import onnxruntime"])
            .current_dir(dir.path())
            .stderr(std::process::Stdio::null())
            .output()
            .unwrap();
        assert!(
            marker.exists(),
            "the control run did not import the planted module"
        );
    }
}

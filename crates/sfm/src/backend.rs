//! Finding COLMAP: the `colmap` command line (Debian's `colmap` package) or PyPI's
//! `pycolmap` under a Python interpreter.

use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use serde::{Deserialize, Serialize};

use crate::SfmError;

/// Which COLMAP front end runs the steps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BackendKind {
    /// The `colmap` program (`apt-get install colmap`): the fallback.
    ColmapCli,
    /// The `pycolmap` module (`pip install pycolmap`, 4.x), which bundles COLMAP: the
    /// default (see the crate documentation for why).
    Pycolmap,
}

impl BackendKind {
    /// The backend tried first when the caller has no preference.
    pub const DEFAULT: BackendKind = BackendKind::Pycolmap;

    /// The oldest pycolmap major version whose API the step script uses.
    pub const MIN_PYCOLMAP_MAJOR: u32 = 4;

    /// The fallback when `self` is not installed.
    pub fn other(self) -> BackendKind {
        match self {
            BackendKind::ColmapCli => BackendKind::Pycolmap,
            BackendKind::Pycolmap => BackendKind::ColmapCli,
        }
    }

    /// `colmap` or `pycolmap`.
    pub fn name(self) -> &'static str {
        match self {
            BackendKind::ColmapCli => "colmap",
            BackendKind::Pycolmap => "pycolmap",
        }
    }
}

impl std::fmt::Display for BackendKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A usable COLMAP: which front end, the program that runs it (`colmap`, or the Python
/// interpreter that imports `pycolmap`) and the version it reported.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Backend {
    pub kind: BackendKind,
    pub program: PathBuf,
    /// `3.8` for Debian 12's `colmap`, `4.2.1` for pycolmap 4.2.1.
    pub version: String,
}

impl Backend {
    /// Checks that `program` runs this backend and asks its version: `colmap help` for
    /// the command line; `python3 -I -c "import pycolmap"` for pycolmap (`-I`: isolated
    /// mode, so that a `pycolmap.py` in the working directory is never imported).
    /// `program` is a path, or a bare name looked up on `PATH`.
    pub fn probe(kind: BackendKind, program: impl AsRef<Path>) -> Result<Backend, String> {
        let program = program.as_ref();
        let resolved = resolve(program, std::env::var_os("PATH"))
            .ok_or_else(|| format!("{} not found", program.display()))?;
        let version = match kind {
            BackendKind::ColmapCli => {
                let out = capture(Command::new(&resolved).arg("help"))?;
                colmap_version(&out).ok_or_else(|| {
                    format!(
                        "{} help printed no `COLMAP <version>` line",
                        resolved.display()
                    )
                })?
            }
            BackendKind::Pycolmap => {
                let out = capture(Command::new(&resolved).args([
                    "-I",
                    "-c",
                    "import pycolmap; print('PYCOLMAP', pycolmap.__version__)",
                ]))
                .map_err(|e| format!("{} cannot import pycolmap: {e}", resolved.display()))?;
                out.lines()
                    .find_map(|l| l.strip_prefix("PYCOLMAP "))
                    .map(|v| v.trim().to_string())
                    .ok_or_else(|| format!("{} printed no pycolmap version", resolved.display()))?
            }
        };
        let backend = Backend {
            kind,
            program: resolved,
            version,
        };
        let too_old = backend
            .version_number()
            .is_none_or(|(major, _)| major < BackendKind::MIN_PYCOLMAP_MAJOR);
        if kind == BackendKind::Pycolmap && too_old {
            return Err(format!(
                "pycolmap {} under {} is too old (4.x is needed: pip install -U pycolmap)",
                backend.version,
                backend.program.display()
            ));
        }
        Ok(backend)
    }

    /// The (major, minor) of [`Backend::version`], when it parses.
    pub fn version_number(&self) -> Option<(u32, u32)> {
        let mut parts = self.version.split(|c: char| !c.is_ascii_digit());
        let major = parts.next()?.parse().ok()?;
        let minor = parts.next().and_then(|m| m.parse().ok()).unwrap_or(0);
        Some((major, minor))
    }
}

/// Where to look for each backend; [`Locator::default`] is `colmap` and `python3` on
/// `PATH`. Tests and callers with their own installs set the fields.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Locator {
    /// The `colmap` program: a path, or a name looked up on [`Locator::search_path`].
    pub colmap: PathBuf,
    /// The Python interpreter that should import `pycolmap`: a path, or a name.
    pub python: PathBuf,
    /// The `PATH` to search bare names on; `None`: this process's `PATH`.
    pub search_path: Option<OsString>,
}

impl Default for Locator {
    fn default() -> Locator {
        Locator {
            colmap: PathBuf::from("colmap"),
            python: PathBuf::from("python3"),
            search_path: None,
        }
    }
}

impl Locator {
    /// The first usable backend: `preference` ([`BackendKind::DEFAULT`], pycolmap, when
    /// `None`), then the other one. When neither runs, [`SfmError::NoBackend`] names the
    /// install commands.
    pub fn find(&self, preference: Option<BackendKind>) -> Result<Backend, SfmError> {
        let first = preference.unwrap_or(BackendKind::DEFAULT);
        let mut tried = Vec::new();
        for kind in [first, first.other()] {
            match self.probe(kind) {
                Ok(backend) => return Ok(backend),
                Err(why) => tried.push(format!("{kind}: {}", why.replace('\n', " "))),
            }
        }
        Err(SfmError::NoBackend { tried })
    }

    /// [`Backend::probe`] of one kind with this locator's program and search path.
    pub fn probe(&self, kind: BackendKind) -> Result<Backend, String> {
        let program = match kind {
            BackendKind::ColmapCli => &self.colmap,
            BackendKind::Pycolmap => &self.python,
        };
        let path = self
            .search_path
            .clone()
            .or_else(|| std::env::var_os("PATH"));
        let resolved = resolve(program, path)
            .ok_or_else(|| format!("{} not found on PATH", program.display()))?;
        Backend::probe(kind, resolved)
    }
}

/// [`Locator::find`] with the default locator (`colmap`, `python3` on `PATH`).
pub fn find_backend(preference: Option<BackendKind>) -> Result<Backend, SfmError> {
    Locator::default().find(preference)
}

/// `program` itself when it names a path (has a separator), else the first executable
/// file of that name in the directories of `path`.
fn resolve(program: &Path, path: Option<OsString>) -> Option<PathBuf> {
    if program.components().count() > 1 || program.is_absolute() {
        return is_executable(program).then(|| program.to_path_buf());
    }
    let path = path?;
    std::env::split_paths(&path)
        .filter(|dir| !dir.as_os_str().is_empty())
        .map(|dir| dir.join(program))
        .find(|candidate| is_executable(candidate))
}

fn is_executable(path: &Path) -> bool {
    let Ok(meta) = std::fs::metadata(path) else {
        return false;
    };
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        meta.is_file() && meta.permissions().mode() & 0o111 != 0
    }
    #[cfg(not(unix))]
    {
        meta.is_file()
    }
}

/// Runs a short probe command; its standard output, or why it failed (one line).
fn capture(cmd: &mut Command) -> Result<String, String> {
    let out = cmd
        .stdin(Stdio::null())
        .output()
        .map_err(|e| format!("cannot run {}: {e}", cmd.get_program().to_string_lossy()))?;
    if !out.status.success() {
        let stderr = String::from_utf8_lossy(&out.stderr);
        return Err(match stderr.lines().rev().find(|l| !l.trim().is_empty()) {
            Some(last) => format!("{} ({})", out.status, last.trim()),
            None => out.status.to_string(),
        });
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// `3.8` from `COLMAP 3.8 -- Structure-from-Motion and Multi-View Stereo`.
pub(crate) fn colmap_version(help: &str) -> Option<String> {
    help.lines().find_map(|line| {
        let rest = line.trim().strip_prefix("COLMAP ")?;
        let version = rest.split_whitespace().next()?;
        version
            .starts_with(|c: char| c.is_ascii_digit())
            .then(|| version.to_string())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_colmap_versions() {
        let help = "COLMAP 3.8 -- Structure-from-Motion and Multi-View Stereo\n  (Commit Unknown)";
        assert_eq!(colmap_version(help).as_deref(), Some("3.8"));
        assert_eq!(
            colmap_version("COLMAP 3.14.0.dev0 -- x").as_deref(),
            Some("3.14.0.dev0")
        );
        assert_eq!(colmap_version("usage: colmap"), None);
        let b = |v: &str| Backend {
            kind: BackendKind::ColmapCli,
            program: PathBuf::from("colmap"),
            version: v.into(),
        };
        assert_eq!(b("3.8").version_number(), Some((3, 8)));
        assert_eq!(b("3.14.0.dev0").version_number(), Some((3, 14)));
        assert_eq!(b("4").version_number(), Some((4, 0)));
        assert_eq!(b("dev").version_number(), None);
    }
}

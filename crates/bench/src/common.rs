//! What every benchmark shares: measuring (peak RSS, process CPU time, medians) and the
//! benchmark scene's life cycle (generated in a child process, reused, removed).

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::BoxError;

/// Where a benchmark reports progress (the tools draw bars on stderr).
pub trait Progress {
    /// A phase of `len` units starts (0: unknown length).
    fn start(&self, phase: &str, len: u64);
    /// `n` more units are done.
    fn inc(&self, n: u64);
    /// The phase is over.
    fn finish(&self);
}

/// No progress output.
#[derive(Debug, Clone, Copy, Default)]
pub struct Silent;

impl Progress for Silent {
    fn start(&self, _: &str, _: u64) {}
    fn inc(&self, _: u64) {}
    fn finish(&self) {}
}

/// Peak resident set size (VmHWM) of this process in MiB, from /proc/self/status
/// (0 where unavailable).
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

/// CPU seconds used so far by all threads of this process (the sum of the per-thread run
/// times in /proc/self/task/*/schedstat; 0 where unavailable). Other load on the machine
/// does not inflate it, unlike wall-clock time.
pub fn process_cpu_s() -> f64 {
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else {
        return 0.0;
    };
    dir.filter_map(|e| e.ok())
        .filter_map(|e| std::fs::read_to_string(e.path().join("schedstat")).ok())
        .filter_map(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .sum::<f64>()
        / 1e9
}

/// The median (mean of the two middle values for an even count; 0 for none).
pub fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        0.0
    } else if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// The upper median of counts (0 for none).
pub fn median_count(v: &mut [usize]) -> usize {
    v.sort_unstable();
    v.get(v.len() / 2).copied().unwrap_or(0)
}

/// Parses a command-line choice by its serde name (e.g. `blend` for
/// `profuse_fuse::job::Register::Blend`).
pub fn choice<T: serde::de::DeserializeOwned>(s: &str) -> Result<T, String> {
    serde_json::from_value(serde_json::Value::String(s.to_string())).map_err(|e| e.to_string())
}

/// Parses a top-K (1..=256, what the rasterizer supports).
pub fn top_k(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(k) if (1..=256).contains(&k) => Ok(k),
        _ => Err(format!("expected an integer in 1..=256, got {s:?}")),
    }
}

/// A benchmark scene directory: a given one (kept), or a temporary one removed when
/// this is dropped.
#[derive(Debug)]
pub struct SceneDir {
    path: PathBuf,
    temporary: bool,
}

impl SceneDir {
    /// `dir` when given, else a fresh temporary directory named after `bench`.
    pub fn new(dir: Option<&Path>, bench: &str) -> SceneDir {
        match dir {
            Some(d) => SceneDir {
                path: d.to_path_buf(),
                temporary: false,
            },
            None => SceneDir {
                path: std::env::temp_dir()
                    .join(format!("profuse-{bench}-bench-{}", std::process::id())),
                temporary: true,
            },
        }
    }

    /// The directory.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for SceneDir {
    fn drop(&mut self) {
        if self.temporary {
            let _ = std::fs::remove_dir_all(&self.path);
        }
    }
}

/// Whether `dir` holds a scene generated with exactly `config` (and the files a
/// benchmark reads).
pub fn scene_matches(dir: &Path, config: &synth::Config, files: &[&str]) -> bool {
    let Ok(text) = std::fs::read_to_string(dir.join("gt/scene.json")) else {
        return false;
    };
    let Ok(json) = serde_json::from_str::<serde_json::Value>(&text) else {
        return false;
    };
    serde_json::to_value(config).is_ok_and(|c| json["parameters"] == c)
        && files.iter().all(|f| dir.join(f).exists())
}

/// The hidden subcommand of a tool with a benchmark: `GENERATE_COMMAND --out DIR --config
/// JSON` must call [`generate`].
pub const GENERATE_COMMAND: &str = "generate-bench-scene";

/// What the hidden subcommand runs: generates the scene of a JSON synth configuration.
pub fn generate(out: &Path, config_json: &str) -> Result<serde_json::Value, BoxError> {
    let config: synth::Config = serde_json::from_str(config_json)?;
    Ok(serde_json::to_value(synth::generate(&config, out)?)?)
}

/// Makes sure `dir` holds the scene of `config`: when it does not, runs this executable's
/// hidden [`GENERATE_COMMAND`] in a child process, so that the generator's memory does
/// not count in the benchmark's peak RSS. Returns the generation seconds, `None` when the
/// scene was reused.
pub fn generate_in_child(
    dir: &Path,
    config: &synth::Config,
    files: &[&str],
    show: bool,
) -> Result<Option<f64>, BoxError> {
    if scene_matches(dir, config, files) {
        return Ok(None);
    }
    if show {
        eprintln!("generating the scene in {} (not timed) ...", dir.display());
    }
    let t0 = Instant::now();
    let status = std::process::Command::new(std::env::current_exe()?)
        .arg(GENERATE_COMMAND)
        .arg("--out")
        .arg(dir)
        .arg("--config")
        .arg(serde_json::to_string(config)?)
        .stdout(std::process::Stdio::null())
        .status()?;
    if !status.success() {
        return Err(format!("generating the benchmark scene in {} failed", dir.display()).into());
    }
    Ok(Some(t0.elapsed().as_secs_f64()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn medians_of_odd_even_and_empty_lists() {
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0]), 2.5);
        assert_eq!(median(&mut []), 0.0);
        assert_eq!(median_count(&mut [5, 1, 9, 7]), 7);
        assert_eq!(median_count(&mut []), 0);
    }

    #[test]
    fn measurements_are_positive_on_linux() {
        let spin: u64 = (0..2_000_000u64).map(std::hint::black_box).sum();
        assert!(spin > 0);
        assert!(process_cpu_s() > 0.0);
        assert!(peak_rss_mb() > 1.0);
    }

    #[test]
    fn a_temporary_scene_dir_is_removed_and_a_given_one_kept() {
        let kept = std::env::temp_dir().join(format!("profuse-bench-kept-{}", std::process::id()));
        std::fs::create_dir_all(&kept).unwrap_or_default();
        let tmp;
        {
            let t = SceneDir::new(None, "unit");
            tmp = t.path().to_path_buf();
            std::fs::create_dir_all(&tmp).unwrap_or_default();
            let _k = SceneDir::new(Some(&kept), "unit");
        }
        assert!(!tmp.exists());
        assert!(kept.exists());
        let _ = std::fs::remove_dir_all(&kept);
    }
}

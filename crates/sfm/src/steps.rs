//! The three COLMAP steps as commands, for either backend.

use std::ffi::OsString;
use std::path::Path;
use std::process::Command;

use crate::{Backend, BackendKind, Matcher, SfmOptions, SfmStep};

/// The pycolmap side: one step per interpreter run (`python3 -I -c SCRIPT STEP JSON`).
const PYCOLMAP_SCRIPT: &str = include_str!("pycolmap_step.py");

/// The paths a step works on.
#[derive(Debug, Clone, Copy)]
pub(crate) struct StepPaths<'a> {
    pub images_dir: &'a Path,
    pub image_list: &'a Path,
    pub database: &'a Path,
    pub sparse: &'a Path,
}

/// The command of `step`; `matcher` is already resolved for the image count (never
/// [`Matcher::Auto`]) and `images` is that count.
pub(crate) fn command(
    backend: &Backend,
    step: SfmStep,
    paths: StepPaths<'_>,
    opts: &SfmOptions,
    matcher: Matcher,
    images: usize,
) -> Command {
    let mut cmd = match backend.kind {
        BackendKind::ColmapCli => colmap_command(backend, step, paths, opts, matcher),
        BackendKind::Pycolmap => pycolmap_command(backend, step, paths, opts, matcher, images),
    };
    if let Some(threads) = opts.threads {
        // COLMAP's OpenMP loops (bundle adjustment helpers) follow this too.
        cmd.env("OMP_NUM_THREADS", threads.to_string());
    }
    cmd
}

fn colmap_command(
    backend: &Backend,
    step: SfmStep,
    paths: StepPaths<'_>,
    opts: &SfmOptions,
    matcher: Matcher,
) -> Command {
    // COLMAP 3.13 renamed the Sift* device options to Feature* (colmap/colmap#3465).
    let renamed = backend.version_number().is_some_and(|v| v >= (3, 13));
    let (extraction, matching) = if renamed {
        ("FeatureExtraction", "FeatureMatching")
    } else {
        ("SiftExtraction", "SiftMatching")
    };
    let threads = opts.threads.map(|t| t.to_string());
    let mut args: Vec<OsString> = Vec::new();
    let mut arg = |name: &str, value: &dyn AsRef<std::ffi::OsStr>| {
        args.push(format!("--{name}").into());
        args.push(value.as_ref().to_os_string());
    };
    let command = match step {
        SfmStep::Extract => {
            arg("database_path", &paths.database);
            arg("image_path", &paths.images_dir);
            arg("image_list_path", &paths.image_list);
            arg("ImageReader.camera_model", &opts.camera_model);
            arg("ImageReader.single_camera", &bool01(opts.single_camera));
            if let Some(params) = &opts.camera_params {
                arg("ImageReader.camera_params", &join_params(params));
            }
            arg(&format!("{extraction}.use_gpu"), &"0");
            if let Some(size) = opts.max_image_size {
                let owner = if renamed {
                    extraction
                } else {
                    "SiftExtraction"
                };
                arg(&format!("{owner}.max_image_size"), &size.to_string());
            }
            if let Some(n) = opts.max_num_features {
                arg("SiftExtraction.max_num_features", &n.to_string());
            }
            if let Some(t) = &threads {
                arg(&format!("{extraction}.num_threads"), t);
            }
            "feature_extractor"
        }
        SfmStep::Match => {
            arg("database_path", &paths.database);
            arg(&format!("{matching}.use_gpu"), &"0");
            if let Some(t) = &threads {
                arg(&format!("{matching}.num_threads"), t);
            }
            match matcher {
                Matcher::Sequential { overlap } => {
                    arg("SequentialMatching.overlap", &overlap.to_string());
                    "sequential_matcher"
                }
                _ => "exhaustive_matcher",
            }
        }
        SfmStep::Map => {
            arg("database_path", &paths.database);
            arg("image_path", &paths.images_dir);
            arg("output_path", &paths.sparse);
            if let Some(t) = &threads {
                arg("Mapper.num_threads", t);
            }
            "mapper"
        }
    };
    if let Some(seed) = opts.seed {
        args.push("--random_seed".into());
        args.push(seed.to_string().into());
    }
    let mut cmd = Command::new(&backend.program);
    cmd.arg(command).args(args);
    cmd
}

fn pycolmap_command(
    backend: &Backend,
    step: SfmStep,
    paths: StepPaths<'_>,
    opts: &SfmOptions,
    matcher: Matcher,
    images: usize,
) -> Command {
    let lossy = |p: &Path| p.to_string_lossy().into_owned();
    let (matcher_name, overlap) = match matcher {
        Matcher::Sequential { overlap } => ("sequential", overlap),
        _ => ("exhaustive", 0),
    };
    let args = serde_json::json!({
        "database": lossy(paths.database),
        "images": lossy(paths.images_dir),
        "image_list": lossy(paths.image_list),
        "output": lossy(paths.sparse),
        "camera_model": opts.camera_model,
        "single_camera": opts.single_camera,
        "camera_params": opts.camera_params.as_deref().map(join_params),
        "max_image_size": opts.max_image_size,
        "max_num_features": opts.max_num_features,
        "threads": opts.threads,
        "seed": opts.seed,
        "matcher": matcher_name,
        "overlap": overlap,
        "total": images,
    });
    let step_name = match step {
        SfmStep::Extract => "extract",
        SfmStep::Match => "match",
        SfmStep::Map => "map",
    };
    let mut cmd = Command::new(&backend.program);
    cmd.args(["-I", "-c", PYCOLMAP_SCRIPT, step_name])
        .arg(args.to_string())
        // Python's own output unbuffered, so that progress lines arrive as they happen;
        // glog (COLMAP's log) to standard error.
        .env("PYTHONUNBUFFERED", "1")
        .env("GLOG_logtostderr", "1");
    cmd
}

fn bool01(b: bool) -> &'static str {
    if b {
        "1"
    } else {
        "0"
    }
}

/// COLMAP's `camera_params` text: comma-separated, shortest round-trip form.
fn join_params(params: &[f64]) -> String {
    params
        .iter()
        .map(|p| p.to_string())
        .collect::<Vec<_>>()
        .join(",")
}

/// Per-item progress from one output line: `(done, total)`. `kind` tells whose output it
/// is: pycolmap's mapper progress comes from our script's `PROFUSE_SFM_PROGRESS` lines
/// only (COLMAP's own log lines would count twice).
pub(crate) fn parse_progress(
    kind: BackendKind,
    step: SfmStep,
    line: &str,
    images: usize,
) -> Option<(usize, usize)> {
    if let Some(rest) = line.trim().strip_prefix("PROFUSE_SFM_PROGRESS ") {
        let mut it = rest.split_whitespace().map(|x| x.parse::<usize>().ok());
        return Some((it.next()??, it.next()??));
    }
    if kind == BackendKind::Pycolmap && step == SfmStep::Map {
        return None;
    }
    match step {
        // `Processed file [12/50]`
        SfmStep::Extract => bracket_pair(line.split("Processed file [").nth(1)?),
        // Exhaustive: `Matching block [1/2, 2/2]` (COLMAP 4: `Processing block`);
        // sequential: `Matching image [7/50]`.
        SfmStep::Match => {
            let block = line
                .split("Matching block [")
                .nth(1)
                .or_else(|| line.split("Processing block [").nth(1));
            if let Some(rest) = block {
                let (a, b) = rest.split_once(',')?;
                let (i, n) = fraction(a)?;
                let (j, m) = fraction(b.split(']').next()?)?;
                let total = n.checked_mul(m)?;
                Some((i.checked_sub(1)?.checked_mul(m)?.checked_add(j)?, total))
            } else {
                bracket_pair(line.split("Matching image [").nth(1)?)
            }
        }
        // `Registering image #12 (5)`: the number in parentheses counts registered images.
        SfmStep::Map => {
            let rest = line.split("Registering image #").nth(1)?;
            let inside = rest.split('(').nth(1)?.split(')').next()?;
            let digits: String = inside.chars().filter(char::is_ascii_digit).collect();
            Some((digits.parse().ok()?, images))
        }
    }
}

fn bracket_pair(rest: &str) -> Option<(usize, usize)> {
    fraction(rest.split(']').next()?)
}

fn fraction(s: &str) -> Option<(usize, usize)> {
    let (a, b) = s.split_once('/')?;
    Some((a.trim().parse().ok()?, b.trim().parse().ok()?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_colmap_progress_lines() {
        let p = |step, line| parse_progress(BackendKind::ColmapCli, step, line, 50);
        assert_eq!(
            p(SfmStep::Extract, "Processed file [12/50]"),
            Some((12, 50))
        );
        assert_eq!(p(SfmStep::Match, "Matching block [2/3, 1/3]"), Some((4, 9)));
        assert_eq!(p(SfmStep::Match, "Matching image [7/50]"), Some((7, 50)));
        let glog = "I20261207 21:25:45.776422 1406 pairing.cc:214] Processing block [1/1, 1/1]";
        assert_eq!(p(SfmStep::Match, glog), Some((1, 1)));
        assert_eq!(p(SfmStep::Map, "Registering image #12 (5)"), Some((5, 50)));
        assert_eq!(
            p(
                SfmStep::Map,
                "I0101 mapper.cc:1] Registering image #3 (num_reg_frames=4)"
            ),
            Some((4, 50))
        );
        assert_eq!(p(SfmStep::Map, "PROFUSE_SFM_PROGRESS 3 8"), Some((3, 8)));
        let py = |line| parse_progress(BackendKind::Pycolmap, SfmStep::Map, line, 50);
        assert_eq!(py("PROFUSE_SFM_PROGRESS 3 8"), Some((3, 8)));
        assert_eq!(py("Registering image #3 (num_reg_frames=2)"), None);
        for junk in [
            "",
            "Processed file [",
            "Matching block [0/1, 1/1]",
            "Registering image #",
        ] {
            assert_eq!(p(SfmStep::Extract, junk), None);
            assert_eq!(p(SfmStep::Map, junk), None);
            assert_eq!(p(SfmStep::Match, junk), None);
        }
    }
}

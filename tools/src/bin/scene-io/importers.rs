//! Subcommands whose bodies do not fit `main.rs`: ScanNet folders, LLFF scenes and COLMAP
//! tracks.

use std::path::{Path, PathBuf};

use profuse_formats::{Cameras, FileKind};
use profuse_tools::{warn, BoxError};
use scene_io::colmap::{read_colmap_model_capped, track_matches, TrackOptions};
use scene_io::llff::{import_llff, LlffOptions};
use scene_io::scannet::{
    import_scannet_folder, read_axis_alignment, AxisAlignment, ScannetOptions,
};
use serde_json::Value;

use crate::args::TracksArgs;
use crate::{save, stamp, warn_all};

/// `scene-io scannet`: `align` is (`--axis-align`, `--no-axis-align`).
pub fn scannet(
    scene_dir: &Path,
    out: &Path,
    stride: u64,
    align: (Option<PathBuf>, bool),
    image_size: Option<[u32; 2]>,
    quiet: bool,
) -> Result<Value, BoxError> {
    let axis_alignment = match align {
        (_, true) => AxisAlignment::Off,
        (Some(txt), false) => AxisAlignment::Matrix(read_axis_alignment(&txt)?),
        (None, false) => AxisAlignment::Auto,
    };
    let options = ScannetOptions {
        stride: usize::try_from(stride)?,
        axis_alignment,
        image_size,
    };
    let (mut cams, report) = import_scannet_folder(scene_dir, &options)?;
    warn_all(quiet, &report.warnings);
    stamp(&mut cams.extra, "scannet");
    save(&cams, "scannet", scene_dir, out, &report, quiet)
}

/// `scene-io llff`.
pub fn llff(scene: &Path, out: &Path, factor: u32, quiet: bool) -> Result<Value, BoxError> {
    let (mut cams, report) = import_llff(scene, &LlffOptions { factor })?;
    stamp(&mut cams.extra, "llff");
    save(&cams, "llff", scene, out, &report, quiet)
}

/// `scene-io tracks`.
pub fn tracks(args: TracksArgs, quiet: bool) -> Result<Value, BoxError> {
    let model =
        read_colmap_model_capped(&args.model_dir, args.max_text_mb.saturating_mul(1 << 20))?;
    let cams = Cameras::read(&args.cameras)?;
    let target = args
        .pinhole_cameras
        .as_deref()
        .map(Cameras::read)
        .transpose()?;
    let options = TrackOptions {
        neighbours: args.neighbours,
        min_shared: args.min_shared,
        exclude_views: args.exclude,
        target,
        one_per_point: !args.all_pairs,
    };
    let (mut matches, report) = track_matches(&model, &cams, &options)?;
    if !report.views_without_pair.is_empty() {
        let msg = format!(
            "views {:?} belong to no pair (too few shared points): gs-init seeds no Gaussian from them",
            report.views_without_pair
        );
        warn(quiet, &msg);
    }
    stamp(&mut matches.extra, "tracks");
    save(
        &matches,
        "tracks",
        &args.model_dir,
        &args.out,
        &report,
        quiet,
    )
}

//! Subcommands whose bodies do not fit `main.rs`: ScanNet folders and LLFF scenes.

use std::path::{Path, PathBuf};

use profuse_tools::BoxError;
use scene_io::llff::{import_llff, LlffOptions};
use scene_io::scannet::{
    import_scannet_folder, read_axis_alignment, AxisAlignment, ScannetOptions,
};
use serde_json::Value;

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

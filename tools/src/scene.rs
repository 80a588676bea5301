//! The scene and view arguments the rendering tools share: Gaussians from a
//! `profuse.gaussians` file or an INRIA PLY, and one view from a cameras file or an orbit
//! camera around the Gaussians.

use std::path::{Path, PathBuf};

use clap::Args;
use profuse_bench::raster::OrbitArgs;
use profuse_formats::{Cameras, FileKind, Gaussians};
use serde_json::{json, Value};
use splat_raster::camera;

use crate::{warn, BoxError};

/// A view: `--cameras` and `--view`, or `--orbit-angle` and the orbit options.
#[derive(Debug, Args)]
pub struct ViewArgs {
    /// Cameras file (profuse.cameras); pick the view with --view.
    #[arg(
        long,
        conflicts_with = "orbit_angle",
        required_unless_present = "orbit_angle"
    )]
    pub cameras: Option<PathBuf>,
    /// View index in the cameras file.
    #[arg(long, default_value_t = 0, requires = "cameras")]
    pub view: usize,
    /// Orbit camera instead of a cameras file: azimuth in degrees around the up axis.
    #[arg(long, value_name = "DEG")]
    pub orbit_angle: Option<f64>,
    /// Orbit image width.
    #[arg(long, default_value_t = 640, requires = "orbit_angle")]
    pub width: u32,
    /// Orbit image height.
    #[arg(long, default_value_t = 480, requires = "orbit_angle")]
    pub height: u32,
    #[command(flatten)]
    pub orbit: OrbitArgs,
}

/// Reads a gaussians file or an INRIA PLY (by extension).
pub fn load_scene(path: &Path, quiet: bool) -> Result<Gaussians, BoxError> {
    let (g, report) = scene_io::ply::read_gaussians(path)?;
    if let Some(r) = &report {
        warn_clamped(quiet, path, r);
    }
    Ok(g)
}

/// Warns when the PLY reader had to clamp opacity logits.
pub fn warn_clamped(quiet: bool, path: &Path, report: &scene_io::PlyReport) {
    if report.clamped_opacity > 0 {
        let n = report.clamped_opacity;
        let msg = format!(
            "{}: clamped {n} non-finite opacity logits to ±20",
            path.display()
        );
        warn(quiet, &msg);
    }
}

/// The cameras, view index, output stem and report entry of the requested view.
pub fn resolve_view(
    g: &Gaussians,
    args: &ViewArgs,
) -> Result<(Cameras, usize, String, Value), BoxError> {
    if let Some(path) = &args.cameras {
        let cams = Cameras::read(path)?;
        if args.view >= cams.len() {
            return Err(format!(
                "--view {} is out of range: {} has {} views",
                args.view,
                path.display(),
                cams.len()
            )
            .into());
        }
        let name = cams.image_names[args.view].clone();
        Ok((
            cams,
            args.view,
            format!("view_{:03}", args.view),
            json!({"cameras": path.to_string_lossy(), "index": args.view, "image_name": name}),
        ))
    } else {
        let angle = args.orbit_angle.ok_or("give --cameras or --orbit-angle")?;
        let ext = camera::scene_extent(g).ok_or("the scene has no Gaussians to orbit")?;
        let pose = args.orbit.pose(&ext, angle)?;
        let intr = camera::pinhole_intrinsics(args.width, args.height, args.orbit.fov);
        let cams = camera::cameras_from_poses(&[pose], args.width, args.height, intr);
        let center = cams.center(0);
        Ok((
            cams,
            0,
            format!("orbit_{angle:.0}"),
            json!({
                "orbit_angle": angle,
                "elevation": args.orbit.elevation,
                "up": format!("{:?}", args.orbit.up.vector()),
                "target": ext.median,
                "radius_p90": ext.radius_p90,
                "distance": args.orbit.distance * ext.radius_p90,
                "camera_center": center,
                "intrinsics": intr,
            }),
        ))
    }
}

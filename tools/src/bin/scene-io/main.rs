//! `scene-io`: import scenes into ProFuse files and export Gaussians to INRIA PLY.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; warnings (skipped frames, ...) go to stderr unless `--quiet`. On
//! failure the error goes to stderr, the exit code is 1, and no output file is written.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::Parser;
use profuse_formats::{Cameras, FileKind, Gaussians};
use profuse_tools::{chatty, run, warn, BoxError};
use scene_io::colmap::{import_colmap, ColmapOptions};
use scene_io::keypoints::KeypointOptions;
use scene_io::ply::{read_inria_ply, write_inria_ply};
use scene_io::scannet::read_scannet_npy;
use scene_io::transforms::read_transforms;
use serde_json::{json, Map, Value};

mod args;
mod importers;
mod photo;
use args::{Cli, Command};

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| execute(cli.command, quiet))
}

fn execute(command: Command, quiet: bool) -> Result<Value, BoxError> {
    match command {
        Command::PlyImport { ply, out } => {
            let (mut g, report) = read_inria_ply(&ply)?;
            profuse_tools::scene::warn_clamped(quiet, &ply, &report);
            stamp(&mut g.extra, "ply-import");
            save(&g, "ply-import", &ply, &out, &report, quiet)
        }
        Command::PlyExport { gaussians, out } => {
            let g = Gaussians::read(&gaussians)?;
            write_inria_ply(&out, &g)?;
            done(quiet, &out);
            let report = json!({ "gaussians": g.len(), "sh_degree": g.sh_degree });
            Ok(with_paths("ply-export", &gaussians, &out, &report)?)
        }
        Command::Transforms {
            transforms_json,
            out,
        } => {
            let (mut cams, report) = read_transforms(&transforms_json)?;
            warn_all(quiet, &report.warnings);
            stamp(&mut cams.extra, "transforms");
            save(&cams, "transforms", &transforms_json, &out, &report, quiet)
        }
        Command::Colmap {
            sparse_dir,
            out,
            points_out,
            images_prefix,
            max_text_mb,
        } => {
            let options = ColmapOptions {
                images_prefix,
                max_text_bytes: max_text_mb.saturating_mul(1 << 20),
            };
            colmap(&sparse_dir, &out, points_out.as_deref(), &options, quiet)
        }
        Command::Scannet {
            scene_dir,
            out,
            stride,
            axis_align,
            no_axis_align,
            width,
            height,
        } => {
            let size = width.zip(height).map(|(w, h)| [w, h]);
            let align = (axis_align, no_axis_align);
            importers::scannet(&scene_dir, &out, stride, align, size, quiet)
        }
        Command::Llff { scene, out, factor } => importers::llff(&scene, &out, factor, quiet),
        Command::Tracks(args) => importers::tracks(args, quiet),
        Command::ToPhoto { at, mask, out } => photo::to_photo(&at, &mask, &out),
        Command::PhotoPoint { at, x, y } => photo::photo_point(&at, x, y),
        Command::ScannetMesh {
            labels_ply,
            out,
            axis_align,
        } => importers::scannet_mesh(&labels_ply, &out, axis_align.as_deref(), quiet),
        Command::ScannetNpy { dir_or_prefix, out } => {
            let (mut mesh, report) = read_scannet_npy(&dir_or_prefix)?;
            stamp(&mut mesh.extra, "scannet-npy");
            save(&mesh, "scannet-npy", &dir_or_prefix, &out, &report, quiet)
        }
        Command::Langsplat {
            features_dir,
            out,
            cameras,
            level,
        } => importers::langsplat(&features_dir, &out, cameras.as_deref(), level, quiet),
        Command::Keypoints {
            inputs,
            cameras,
            out,
            key_i,
            key_j,
            corner_origin,
            no_undistort,
            pinhole_cameras,
        } => {
            let options = KeypointOptions {
                key_i,
                key_j,
                integer_centres: !corner_origin,
                undistort: !no_undistort,
                target: None,
            };
            let pinhole = pinhole_cameras.as_deref();
            importers::keypoints(&inputs, &cameras, &out, options, pinhole, quiet)
        }
        Command::Undistort {
            cameras,
            scene_dir,
            out_dir,
            cameras_only,
            crop,
        } => importers::undistort(&cameras, &scene_dir, &out_dir, cameras_only, crop, quiet),
    }
}

fn colmap(
    sparse_dir: &Path,
    out: &Path,
    points_out: Option<&Path>,
    options: &ColmapOptions,
    quiet: bool,
) -> Result<Value, BoxError> {
    let mut import = import_colmap(sparse_dir, options)?;
    stamp(&mut import.cameras.extra, "colmap");
    stamp(&mut import.gaussians.extra, "colmap");
    write_cameras_and_points(
        &import.cameras,
        points_out.map(|p| (p, &import.gaussians)),
        out,
    )?;
    done(quiet, out);
    let mut value = with_paths("colmap", sparse_dir, out, &import.report)?;
    if let (Some(p), Value::Object(map)) = (points_out, &mut value) {
        done(quiet, p);
        map.insert("points_output".to_string(), json!(p.display().to_string()));
    }
    Ok(value)
}

/// The `.npz` files named on the command line, directories expanded (sorted).
fn npz_files(inputs: &[PathBuf]) -> Result<Vec<PathBuf>, BoxError> {
    let mut files = Vec::new();
    for input in inputs {
        if input.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(input)
                .map_err(|e| format!("{}: cannot list the directory: {e}", input.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|x| x == "npz"))
                .collect();
            found.sort();
            files.extend(found);
        } else {
            files.push(input.clone());
        }
    }
    Ok(files)
}

/// Writes a file and reports it (see [`with_paths`]).
fn save<T: FileKind>(
    file: &T,
    command: &str,
    input: &Path,
    out: &Path,
    report: &impl serde::Serialize,
    quiet: bool,
) -> Result<Value, BoxError> {
    file.write(out)?;
    done(quiet, out);
    with_paths(command, input, out, report)
}

/// Records the producing tool in the file's metadata (SPEC.md 3.1 `generator`).
fn stamp(extra: &mut std::collections::BTreeMap<String, String>, command: &str) {
    extra.insert(
        "generator".to_string(),
        format!("scene-io {} {command}", env!("CARGO_PKG_VERSION")),
    );
}

/// The report object with `command`, `input` and `output` added.
fn with_paths(
    command: &str,
    input: &Path,
    output: &Path,
    report: &impl serde::Serialize,
) -> Result<Value, BoxError> {
    let mut map = match serde_json::to_value(report)? {
        Value::Object(map) => map,
        other => Map::from_iter([("report".to_string(), other)]),
    };
    map.insert("command".to_string(), json!(command));
    map.insert("input".to_string(), json!(input.display().to_string()));
    map.insert("output".to_string(), json!(output.display().to_string()));
    Ok(Value::Object(map))
}

fn warn_all(quiet: bool, warnings: &[String]) {
    for w in warnings {
        warn(quiet, w);
    }
}

fn done(quiet: bool, path: &Path) {
    if chatty(quiet) {
        eprintln!("wrote {}", path.display());
    }
}

/// Writes the cameras and, when asked, the points: both are validated before either is
/// written, and a failed second write removes the first, so failure leaves nothing.
fn write_cameras_and_points(
    cameras: &Cameras,
    points: Option<(&Path, &Gaussians)>,
    out: &Path,
) -> Result<(), BoxError> {
    cameras.validate(&out.display().to_string())?;
    if let Some((path, g)) = points {
        g.validate(&path.display().to_string())?;
    }
    cameras.write(out)?;
    if let Some((path, g)) = points {
        if let Err(e) = g.write(path) {
            let _ = std::fs::remove_file(out);
            return Err(e.into());
        }
    }
    Ok(())
}

//! `scene-io`: import scenes into ProFuse files and export Gaussians to INRIA PLY.
//!
//! Every input and output is a command-line argument. On success one JSON report object
//! goes to stdout; warnings (skipped frames, ...) go to stderr unless `--quiet`. On
//! failure the error goes to stderr, the exit code is 1, and no output file is written.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use profuse_formats::{Cameras, FileKind, Gaussians};
use profuse_tools::{chatty, run, warn, BoxError};
use scene_io::colmap::{import_colmap, ColmapOptions};
use scene_io::keypoints::{import_keypoint_pairs, KeypointOptions};
use scene_io::langsplat::{import_langsplat, LangSplatOptions};
use scene_io::ply::{read_inria_ply, write_inria_ply};
use scene_io::scannet::{
    align_mesh, import_scannet_folder, read_axis_alignment, read_scannet_labels_ply,
    read_scannet_npy, AxisAlignment, ScannetOptions,
};
use scene_io::transforms::read_transforms;
use scene_io::undistort::undistort_scene;
use serde_json::{json, Map, Value};

#[derive(Debug, Parser)]
#[command(
    name = "scene-io",
    version,
    about = "Import INRIA PLY, transforms.json, COLMAP, ScanNet and LangSplat data into ProFuse files; export Gaussians to INRIA PLY",
    long_about = "Import INRIA PLY, transforms.json, COLMAP, ScanNet and LangSplat data into ProFuse files \
                  (SPEC.md), and export Gaussians to INRIA PLY. Prints one JSON report on stdout; warnings \
                  go to stderr. Exit code 1 on failure, with nothing written."
)]
struct Cli {
    /// Do not print warnings or progress on stderr (the JSON report still goes to stdout).
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// INRIA 3DGS PLY (binary little-endian or ascii) → gaussians file. Non-finite opacity
    /// logits are clamped to ±20 and counted.
    PlyImport {
        /// The INRIA 3DGS PLY file to read.
        ply: PathBuf,
        /// The gaussians file to write (.safetensors).
        #[arg(long)]
        out: PathBuf,
    },
    /// Gaussians file → INRIA 3DGS binary PLY (INRIA `save_ply` property order, zero normals).
    PlyExport {
        /// The gaussians file to read.
        gaussians: PathBuf,
        /// The PLY file to write.
        #[arg(long)]
        out: PathBuf,
    },
    /// instant-ngp / NeRF transforms.json → cameras file; image names are relative to the
    /// JSON's directory, frames whose image is missing are skipped with a warning.
    Transforms {
        /// The transforms.json to read.
        transforms_json: PathBuf,
        /// The cameras file to write.
        #[arg(long)]
        out: PathBuf,
    },
    /// COLMAP sparse model (binary or text, auto-detected) → cameras file, and optionally
    /// the 3D points as seeded Gaussians.
    Colmap {
        /// Directory holding cameras/images/points3D as .bin or .txt (e.g. sparse/0).
        sparse_dir: PathBuf,
        /// The cameras file to write.
        #[arg(long)]
        out: PathBuf,
        /// Also write the points as a gaussians file seeded like INRIA 3DGS.
        #[arg(long, value_name = "GAUSSIANS")]
        points_out: Option<PathBuf>,
        /// Prefix added to COLMAP image names so they are relative to the scene directory
        /// (use "" for none).
        #[arg(long, default_value = "images/")]
        images_prefix: String,
    },
    /// ScanNet SensReader export (color/, pose/, intrinsic/) → cameras file, axis-aligned
    /// by <scene>.txt when present; frames with non-finite poses are skipped.
    Scannet {
        /// The scene directory (e.g. scans/scene0000_00).
        scene_dir: PathBuf,
        /// The cameras file to write.
        #[arg(long)]
        out: PathBuf,
        /// Keep every N-th frame.
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
        stride: u64,
        /// Take the axis alignment from this <scene>.txt instead of SCENE_DIR/<name>.txt.
        #[arg(long, value_name = "SCENE_TXT", conflicts_with = "no_axis_align")]
        axis_align: Option<PathBuf>,
        /// Keep poses in raw ScanNet coordinates.
        #[arg(long)]
        no_axis_align: bool,
        /// Image width in pixels (default: read from the first colour image).
        #[arg(long, requires = "height")]
        width: Option<u32>,
        /// Image height in pixels (default: read from the first colour image).
        #[arg(long, requires = "width")]
        height: Option<u32>,
    },
    /// ScanNet *_vh_clean_2.labels.ply → mesh file with NYU40 vertex labels.
    ScannetMesh {
        /// The labels PLY to read.
        labels_ply: PathBuf,
        /// The mesh file to write.
        #[arg(long)]
        out: PathBuf,
        /// Move the vertices into the axis-aligned frame of this <scene>.txt.
        #[arg(long, value_name = "SCENE_TXT")]
        axis_align: Option<PathBuf>,
    },
    /// ScanNet NumPy vertex arrays (*_vert_all.npy, *_sem_label_all.npy,
    /// *_ins_label_all.npy) → mesh file.
    ScannetNpy {
        /// A directory holding one *_vert_all.npy, or the prefix before `_vert_all.npy`.
        dir_or_prefix: PathBuf,
        /// The mesh file to write.
        #[arg(long)]
        out: PathBuf,
    },
    /// LangSplat language_features/ (<stem>_s.npy, <stem>_f.npy) → one masks file.
    Langsplat {
        /// The language_features directory.
        features_dir: PathBuf,
        /// The masks file to write.
        #[arg(long)]
        out: PathBuf,
        /// Cameras file giving the view order and names (default: sorted stems).
        #[arg(long)]
        cameras: Option<PathBuf>,
        /// Seg-map level: 0 default, 1 s, 2 m, 3 l.
        #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u8).range(0..=3))]
        level: u8,
    },
    /// Keypoint-pair files (`<stem_i>_<stem_j>.npz`, two (n, 2) arrays: XFeat, LightGlue,
    /// LoFTR) → sparse_matches file. Keypoints are shifted by +0.5 (OpenCV integer pixel
    /// centres) and undistorted when the cameras carry a lens model; files naming views the
    /// cameras lack are skipped with a warning.
    Keypoints {
        /// Pair files, or directories whose *.npz files are all read.
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
        /// The cameras file whose image stems the file names refer to.
        #[arg(long)]
        cameras: PathBuf,
        /// The sparse_matches file to write.
        #[arg(long)]
        out: PathBuf,
        /// Array name of the view-i keypoints.
        #[arg(long, default_value = "kpts_i")]
        key_i: String,
        /// Array name of the view-j keypoints.
        #[arg(long, default_value = "kpts_j")]
        key_j: String,
        /// The keypoints already use SPEC.md's corner origin (pixel centres at +0.5): do not
        /// shift them.
        #[arg(long)]
        corner_origin: bool,
        /// Keep distorted keypoints even when the cameras have a lens model.
        #[arg(long)]
        no_undistort: bool,
    },
    /// Undistort a scene's images with its cameras' OpenCV lens model: writes
    /// OUT_DIR/images/<stem>.png and OUT_DIR/cameras.safetensors (pinhole, same intrinsics).
    Undistort {
        /// The cameras file (with `distortion`).
        #[arg(long)]
        cameras: PathBuf,
        /// The directory the cameras' image names are relative to.
        #[arg(long)]
        scene_dir: PathBuf,
        /// The output scene directory.
        #[arg(long)]
        out_dir: PathBuf,
        /// Write only OUT_DIR/cameras.safetensors (pinhole, image names unchanged): for
        /// images undistorted elsewhere, or stages that need no pixels.
        #[arg(long)]
        cameras_only: bool,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let quiet = cli.quiet;
    run(|| execute(cli.command, quiet))
}

fn execute(command: Command, quiet: bool) -> Result<Value, BoxError> {
    match command {
        Command::PlyImport { ply, out } => {
            let (mut g, report) = read_inria_ply(&ply)?;
            if report.clamped_opacity > 0 {
                warn(
                    quiet,
                    &format!(
                        "{}: clamped {} non-finite opacity logits to ±20",
                        ply.display(),
                        report.clamped_opacity
                    ),
                );
            }
            stamp(&mut g.extra, "ply-import");
            g.write(&out)?;
            done(quiet, &out);
            Ok(with_paths("ply-import", &ply, &out, &report)?)
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
            cams.write(&out)?;
            done(quiet, &out);
            Ok(with_paths("transforms", &transforms_json, &out, &report)?)
        }
        Command::Colmap {
            sparse_dir,
            out,
            points_out,
            images_prefix,
        } => {
            let mut import = import_colmap(&sparse_dir, &ColmapOptions { images_prefix })?;
            stamp(&mut import.cameras.extra, "colmap");
            stamp(&mut import.gaussians.extra, "colmap");
            write_cameras_and_points(
                &import.cameras,
                points_out.as_deref().map(|p| (p, &import.gaussians)),
                &out,
            )?;
            done(quiet, &out);
            let mut value = with_paths("colmap", &sparse_dir, &out, &import.report)?;
            if let (Some(p), Value::Object(map)) = (&points_out, &mut value) {
                done(quiet, p);
                map.insert("points_output".to_string(), json!(p.display().to_string()));
            }
            Ok(value)
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
            let axis_alignment = match (axis_align, no_axis_align) {
                (_, true) => AxisAlignment::Off,
                (Some(txt), false) => AxisAlignment::Matrix(read_axis_alignment(&txt)?),
                (None, false) => AxisAlignment::Auto,
            };
            let options = ScannetOptions {
                stride: usize::try_from(stride)?,
                axis_alignment,
                image_size: width.zip(height).map(|(w, h)| [w, h]),
            };
            let (mut cams, report) = import_scannet_folder(&scene_dir, &options)?;
            warn_all(quiet, &report.warnings);
            stamp(&mut cams.extra, "scannet");
            cams.write(&out)?;
            done(quiet, &out);
            Ok(with_paths("scannet", &scene_dir, &out, &report)?)
        }
        Command::ScannetMesh {
            labels_ply,
            out,
            axis_align,
        } => {
            let (mut mesh, report) = read_scannet_labels_ply(&labels_ply)?;
            if let Some(txt) = &axis_align {
                align_mesh(&mut mesh, &read_axis_alignment(txt)?);
                mesh.extra
                    .insert("axis_aligned".to_string(), "true".to_string());
            }
            stamp(&mut mesh.extra, "scannet-mesh");
            mesh.write(&out)?;
            done(quiet, &out);
            let mut value = with_paths("scannet-mesh", &labels_ply, &out, &report)?;
            if let Value::Object(map) = &mut value {
                map.insert("axis_aligned".to_string(), json!(axis_align.is_some()));
            }
            Ok(value)
        }
        Command::ScannetNpy { dir_or_prefix, out } => {
            let (mut mesh, report) = read_scannet_npy(&dir_or_prefix)?;
            stamp(&mut mesh.extra, "scannet-npy");
            mesh.write(&out)?;
            done(quiet, &out);
            Ok(with_paths("scannet-npy", &dir_or_prefix, &out, &report)?)
        }
        Command::Langsplat {
            features_dir,
            out,
            cameras,
            level,
        } => {
            let cameras = cameras.as_deref().map(Cameras::read).transpose()?;
            let options = LangSplatOptions {
                level: usize::from(level),
                cameras,
            };
            let (mut masks, report) = import_langsplat(&features_dir, &options)?;
            stamp(&mut masks.extra, "langsplat");
            masks.write(&out)?;
            done(quiet, &out);
            Ok(with_paths("langsplat", &features_dir, &out, &report)?)
        }
        Command::Keypoints {
            inputs,
            cameras,
            out,
            key_i,
            key_j,
            corner_origin,
            no_undistort,
        } => {
            let cams = Cameras::read(&cameras)?;
            let files = npz_files(&inputs)?;
            let options = KeypointOptions {
                key_i,
                key_j,
                integer_centres: !corner_origin,
                undistort: !no_undistort,
            };
            let label = cameras.display().to_string();
            let (mut matches, report) = import_keypoint_pairs(&files, &cams, &label, &options)?;
            warn_all(quiet, &report.skipped);
            stamp(&mut matches.extra, "keypoints");
            matches.write(&out)?;
            done(quiet, &out);
            Ok(with_paths("keypoints", &cameras, &out, &report)?)
        }
        Command::Undistort {
            cameras,
            scene_dir,
            out_dir,
            cameras_only,
        } => {
            let cams = Cameras::read(&cameras)?;
            let (mut pinhole, report) = if cameras_only {
                std::fs::create_dir_all(&out_dir)?;
                (scene_io::undistort::pinhole(&cams), Default::default())
            } else {
                undistort_scene(&cams, &scene_dir, &out_dir)?
            };
            stamp(&mut pinhole.extra, "undistort");
            let out = out_dir.join("cameras.safetensors");
            pinhole.write(&out)?;
            done(quiet, &out);
            Ok(with_paths("undistort", &cameras, &out, &report)?)
        }
    }
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

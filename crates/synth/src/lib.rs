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

/// What the masks phase reports to the scene description.
struct Semantics {
    classes_present: Vec<(u32, String)>,
    num_masks: usize,
    num_prompts: usize,
    provenance: Vec<ViewProvenance>,
}

/// The classes placed in the scene, sorted by id, each once.
fn classes_present(scene: &Scene) -> Vec<(u32, String)> {
    let mut c: Vec<(u32, String)> = scene
        .objects
        .iter()
        .map(|o| (o.class_id, o.class_name.clone()))
        .collect();
    c.sort();
    c.dedup();
    c
}

/// Derives the faulty "SAM-like" masks with their features (or removes a stale masks
/// file when masks are off) and writes the prompts file.
fn write_masks_and_prompts(
    config: &Config,
    scene: &Scene,
    views: &RenderedViews,
    out: &Path,
    generator: &str,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<Semantics> {
    let classes_present = classes_present(scene);
    let protos = Prototypes::new(config.seed, config.feature_dim, &classes_present);
    let gt = out.join("gt");
    let mut num_masks = 0;
    let mut provenance = Vec::new();
    if config.write_masks {
        progress("deriving masks");
        let class_of: Vec<u32> = scene.objects.iter().map(|o| o.class_id).collect();
        let per_view: Vec<masks::ViewMasks> = (0..config.views)
            .into_par_iter()
            .map(|v| masks::view_masks(config, v, views.ids_of(v), views.width, &class_of, &protos))
            .collect();
        let all = assemble_masks(per_view, scene, config.views * views.plane());
        provenance = all.provenance;
        num_masks = all.entries.len();
        Masks {
            view_names: views.names.clone(),
            width: views.width,
            height: views.height,
            labels: Labels::U16(all.labels.into()),
            mask_offsets: all.offsets.into(),
            features: Floats::F16(all.features.into()),
            dim: config.feature_dim,
            extra: meta(generator),
        }
        .write(out.join("masks.safetensors"))?;
        output::write_json(
            &gt.join("mask_objects.json"),
            &MaskObjects {
                num_masks,
                masks: all.entries,
            },
            false,
        )?;
    } else {
        output::remove_stale(&out.join("masks.safetensors"))?;
        output::remove_stale(&gt.join("mask_objects.json"))?;
    }
    let prompt_rows = masks::prompts(config, &protos);
    Prompts {
        names: prompt_rows.iter().map(|p| p.0.clone()).collect(),
        dim: config.feature_dim,
        embeddings: prompt_rows
            .iter()
            .flat_map(|p| p.1.iter().copied())
            .collect::<Vec<f32>>()
            .into(),
        class_ids: Some(prompt_rows.iter().map(|p| p.2).collect::<Vec<i32>>().into()),
        extra: meta(generator),
    }
    .write(out.join("prompts.safetensors"))?;
    Ok(Semantics {
        classes_present,
        num_masks,
        num_prompts: prompt_rows.len(),
        provenance,
    })
}

/// Writes the dense warps between neighbouring views (or removes a stale file);
/// returns the number of view pairs.
fn write_matches(
    config: &Config,
    scene: &Scene,
    views: &RenderedViews,
    out: &Path,
    generator: &str,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<usize> {
    if !config.write_matches {
        output::remove_stale(&out.join("matches.safetensors"))?;
        return Ok(0);
    }
    progress("computing warps");
    let (file, pairs) = matches_file(config, scene, &views.cams, generator);
    file.write(out.join("matches.safetensors"))?;
    Ok(pairs)
}

/// Samples the ground-truth Gaussians on the visible surfaces (or removes a stale
/// file when none are asked for); returns their number.
fn write_gt_gaussians(
    config: &Config,
    scene: &Scene,
    views: &RenderedViews,
    gt: &Path,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<usize> {
    if config.gaussians == 0 {
        output::remove_stale(&gt.join("gaussians.safetensors"))?;
        return Ok(0);
    }
    progress("sampling ground-truth Gaussians");
    let g = gaussians::sample(scene, &views.cams, config.seed, config.gaussians);
    g.write(gt.join("gaussians.safetensors"))?;
    Ok(g.len())
}

/// Writes the LERF-style polygon labels of every evaluation frame and removes those of
/// frames an earlier run evaluated; returns the evaluation frames.
fn write_label_frames(
    config: &Config,
    scene: &Scene,
    views: &RenderedViews,
    label_dir: &Path,
) -> Result<Vec<usize>> {
    let eval_frames: Vec<usize> = (0..config.views).step_by(config.eval_every).collect();
    for &v in &eval_frames {
        let file_name = format!("frame_{v:05}");
        let lf = labels::frame_labels(
            scene,
            views.ids_of(v),
            views.width,
            format!("{file_name}.png"),
        );
        output::write_json(&label_dir.join(format!("{file_name}.json")), &lf, false)?;
    }
    remove_stale_frames(label_dir, "json", &eval_frames)?;
    Ok(eval_frames)
}

/// Writes the labelled ground-truth mesh; returns its vertex and face counts.
fn write_mesh(config: &Config, scene: &Scene, gt: &Path) -> Result<[usize; 2]> {
    let mesh = mesh::build(scene, config.mesh_spacing);
    let size = [
        mesh.vertices.len(),
        mesh.faces.as_ref().map_or(0, |f| f.len()),
    ];
    mesh.write(gt.join("mesh.safetensors"))?;
    Ok(size)
}

/// Writes the exact per-view depth and object-id maps (consumes them: they are the
/// largest buffers of a scene).
fn write_view_maps(
    views: RenderedViews,
    num_objects: usize,
    gt: &Path,
    generator: &str,
) -> Result<()> {
    ViewMaps {
        view_names: views.names,
        num_objects,
        width: views.width,
        height: views.height,
        depth: views.depth.into(),
        object_ids: Some(views.ids.into()),
        extra: meta(generator),
    }
    .write(gt.join("views.safetensors"))?;
    Ok(())
}

/// What [`write_scene`] produced, for the scene description and the summary.
struct Written {
    image_names: Vec<String>,
    eval_frames: Vec<usize>,
    masks: usize,
    pairs: usize,
    gaussians: usize,
    mesh: [usize; 2],
}

/// Writes `gt/scene.json`, the scene description (SPEC.md §6.1).
fn write_scene_json(
    config: &Config,
    scene: &Scene,
    semantics: &Semantics,
    written: &Written,
    generator: &str,
    gt: &Path,
) -> Result<()> {
    let (gw, gh) = config.match_grid();
    let (objects, classes) = scene_tables(scene, &semantics.classes_present);
    let file = SceneFile {
        format: "synth.scene",
        version: 1,
        generator: generator.to_string(),
        preset: config.preset.clone(),
        seed: config.seed,
        label_space: "nyu40",
        room: scene.room_json(),
        classes,
        objects_requested: config.objects,
        objects_placed: scene.objects.iter().filter(|o| !o.room).count(),
        objects,
        cameras: CamerasJson {
            views: config.views,
            width: config.width,
            height: config.height,
            hfov_deg: config.hfov_deg,
            image_names: written.image_names.clone(),
        },
        eval_frames: written.eval_frames.clone(),
        fault_model: &config.faults,
        masks: config.write_masks.then_some(MasksJson {
            total: written.masks,
            per_view: semantics.provenance.clone(),
        }),
        matches: config.write_matches.then_some(MatchesJson {
            pairs: written.pairs,
            grid: [gw, gh],
            coords: "normalized",
            precision: config.match_precision,
        }),
        gaussians: written.gaussians,
        mesh: written.mesh,
        parameters: config,
    };
    output::write_json(&gt.join("scene.json"), &file, true)
}

/// The scene description's object and class tables.
fn scene_tables<'a>(
    scene: &'a Scene,
    classes_present: &[(u32, String)],
) -> (Vec<ObjectJson<'a>>, Vec<ClassJson>) {
    let objects = scene
        .objects
        .iter()
        .map(|o| ObjectJson {
            spec: o,
            shape_kind: o.shape.kind(),
            rotation_wxyz: o.rotation_wxyz(),
        })
        .collect();
    let classes = classes_present
        .iter()
        .map(|(id, name)| ClassJson {
            id: *id,
            name: name.clone(),
            room: classes::ROOM.contains(id),
            instances: scene.objects.iter().filter(|o| o.class_id == *id).count(),
        })
        .collect();
    (objects, classes)
}

/// Every view's masks in one table: the label planes, the per-view offsets, the f16
/// features, the ground-truth entries and the per-view provenance.
struct AssembledMasks {
    labels: Vec<u16>,
    offsets: Vec<u32>,
    features: Vec<f16>,
    entries: Vec<MaskObject>,
    provenance: Vec<ViewProvenance>,
}

fn assemble_masks(per_view: Vec<masks::ViewMasks>, scene: &Scene, pixels: usize) -> AssembledMasks {
    let mut all = AssembledMasks {
        labels: Vec::with_capacity(pixels),
        offsets: vec![0u32],
        features: Vec::new(),
        entries: Vec::new(),
        provenance: Vec::new(),
    };
    for (v, vm) in per_view.into_iter().enumerate() {
        all.labels.extend_from_slice(&vm.labels);
        for (local, m) in vm.masks.iter().enumerate() {
            all.features
                .extend(m.feature.iter().map(|x| f16::from_f32(*x)));
            let object = scene.objects.get(m.object as usize);
            all.entries.push(MaskObject {
                id: all.entries.len(),
                view: v,
                local,
                object: (m.object != NO_OBJECT).then_some(m.object),
                object_name: object.map(|o| o.name.clone()),
                class_id: object.map(|o| o.class_id),
                purity: m.purity,
                pixels: m.pixels,
                objects: m.objects.clone(),
                split_half: m.half,
                feature_class: m.class_id,
                wrong_class: m.wrong_class,
            });
        }
        all.offsets.push(all.entries.len() as u32);
        all.provenance.push(vm.provenance);
    }
    all
}

/// The matches file of the scene's neighbouring view pairs, and the number of pairs.
fn matches_file(
    config: &Config,
    scene: &Scene,
    cams: &[Camera],
    generator: &str,
) -> (Matches, usize) {
    let pairs = neighbour_pairs(cams, config.neighbours);
    let num_pairs = pairs.len();
    let warps = matches::compute(scene, cams, config, pairs);
    let half = |v: Vec<f32>| {
        Floats::F16(
            v.iter()
                .map(|x| f16::from_f32(*x))
                .collect::<Vec<_>>()
                .into(),
        )
    };
    let (warp, certainty) = match config.match_precision {
        MatchPrecision::F32 => (
            Floats::F32(warps.warp.into()),
            Floats::F32(warps.certainty.into()),
        ),
        MatchPrecision::F16 => (half(warps.warp), half(warps.certainty)),
    };
    let file = Matches {
        num_views: config.views,
        pairs: warps.pairs.into(),
        height: warps.height,
        width: warps.width,
        warp,
        certainty,
        coords: WarpCoords::Normalized,
        extra: meta(generator),
    };
    (file, num_pairs)
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

fn meta(generator: &str) -> BTreeMap<String, String> {
    BTreeMap::from([("generator".to_string(), generator.to_string())])
}

/// Removes `frame_NNNNN.<ext>` files in `dir` whose index is not in `keep`.
fn remove_stale_frames(dir: &Path, ext: &str, keep: &[usize]) -> Result<()> {
    let entries = std::fs::read_dir(dir).map_err(error::io_err(dir, "cannot list directory"))?;
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let index = name
            .strip_prefix("frame_")
            .and_then(|r| r.strip_suffix(&format!(".{ext}")))
            .filter(|n| n.len() == 5)
            .and_then(|n| n.parse::<usize>().ok());
        if let Some(i) = index {
            if !keep.contains(&i) {
                output::remove_stale(&e.path())?;
            }
        }
    }
    Ok(())
}

#[derive(Serialize)]
struct MaskObjects {
    num_masks: usize,
    masks: Vec<MaskObject>,
}

/// One line of `gt/mask_objects.json`.
#[derive(Serialize)]
struct MaskObject {
    /// Global mask id.
    id: usize,
    view: usize,
    /// View-local index (the value in the label map).
    local: usize,
    /// Dominant ground-truth object (most pixels), null for a mask on no object.
    object: Option<u32>,
    object_name: Option<String>,
    /// NYU40 class of the dominant object.
    class_id: Option<u32>,
    /// Share of the mask's pixels on the dominant object.
    purity: f64,
    pixels: u64,
    /// Object regions the fault model joined into this mask.
    objects: Vec<u32>,
    /// 0 or 1 if the mask is one half of a split, else null.
    split_half: Option<u8>,
    /// Class whose prototype dominates the feature.
    feature_class: u32,
    /// Class the feature was biased toward, if any.
    wrong_class: Option<u32>,
}

#[derive(Serialize)]
struct ObjectJson<'a> {
    #[serde(flatten)]
    spec: &'a ObjectSpec,
    shape_kind: &'static str,
    rotation_wxyz: [f64; 4],
}

#[derive(Serialize)]
struct ClassJson {
    id: u32,
    name: String,
    room: bool,
    instances: usize,
}

#[derive(Serialize)]
struct CamerasJson {
    views: usize,
    width: u32,
    height: u32,
    hfov_deg: f64,
    image_names: Vec<String>,
}

#[derive(Serialize)]
struct MasksJson {
    total: usize,
    per_view: Vec<ViewProvenance>,
}

#[derive(Serialize)]
struct MatchesJson {
    pairs: usize,
    grid: [usize; 2],
    coords: &'static str,
    precision: MatchPrecision,
}

#[derive(Serialize)]
struct SceneFile<'a> {
    format: &'static str,
    version: u32,
    generator: String,
    preset: String,
    seed: u64,
    label_space: &'static str,
    room: scene::RoomJson,
    classes: Vec<ClassJson>,
    objects_requested: usize,
    objects_placed: usize,
    objects: Vec<ObjectJson<'a>>,
    cameras: CamerasJson,
    eval_frames: Vec<usize>,
    fault_model: &'a FaultModel,
    masks: Option<MasksJson>,
    matches: Option<MatchesJson>,
    gaussians: usize,
    mesh: [usize; 2],
    parameters: &'a Config,
}

//! The files of a scene directory, one writer each: masks and prompts, matches, ground-truth
//! Gaussians, label frames, mesh, view maps and the scene description (gt/scene.json,
//! gt/mask_objects.json).

use super::*;

/// What the masks phase reports to the scene description.
pub(super) struct Semantics {
    pub(super) classes_present: Vec<(u32, String)>,
    pub(super) num_masks: usize,
    pub(super) num_prompts: usize,
    pub(super) provenance: Vec<ViewProvenance>,
}

/// The classes placed in the scene, sorted by id, each once.
pub(super) fn classes_present(scene: &Scene) -> Vec<(u32, String)> {
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
pub(super) fn write_masks_and_prompts(
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
pub(super) fn write_matches(
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
pub(super) fn write_gt_gaussians(
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
pub(super) fn write_label_frames(
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
pub(super) fn write_mesh(config: &Config, scene: &Scene, gt: &Path) -> Result<[usize; 2]> {
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
pub(super) fn write_view_maps(
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
pub(super) struct Written {
    pub(super) image_names: Vec<String>,
    pub(super) eval_frames: Vec<usize>,
    pub(super) masks: usize,
    pub(super) pairs: usize,
    pub(super) gaussians: usize,
    pub(super) mesh: [usize; 2],
}

/// Writes `gt/scene.json`, the scene description (SPEC.md §6.1).
pub(super) fn write_scene_json(
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
pub(super) fn scene_tables<'a>(
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
pub(super) struct AssembledMasks {
    pub(super) labels: Vec<u16>,
    pub(super) offsets: Vec<u32>,
    pub(super) features: Vec<f16>,
    pub(super) entries: Vec<MaskObject>,
    pub(super) provenance: Vec<ViewProvenance>,
}

pub(super) fn assemble_masks(
    per_view: Vec<masks::ViewMasks>,
    scene: &Scene,
    pixels: usize,
) -> AssembledMasks {
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
pub(super) fn matches_file(
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
pub(super) fn meta(generator: &str) -> BTreeMap<String, String> {
    BTreeMap::from([("generator".to_string(), generator.to_string())])
}

/// Removes `frame_NNNNN.<ext>` files in `dir` whose index is not in `keep`.
pub(super) fn remove_stale_frames(dir: &Path, ext: &str, keep: &[usize]) -> Result<()> {
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
pub(super) struct MaskObjects {
    pub(super) num_masks: usize,
    pub(super) masks: Vec<MaskObject>,
}

/// One line of `gt/mask_objects.json`.
#[derive(Serialize)]
pub(super) struct MaskObject {
    /// Global mask id.
    pub(super) id: usize,
    pub(super) view: usize,
    /// View-local index (the value in the label map).
    pub(super) local: usize,
    /// Dominant ground-truth object (most pixels), null for a mask on no object.
    pub(super) object: Option<u32>,
    pub(super) object_name: Option<String>,
    /// NYU40 class of the dominant object.
    pub(super) class_id: Option<u32>,
    /// Share of the mask's pixels on the dominant object.
    pub(super) purity: f64,
    pub(super) pixels: u64,
    /// Object regions the fault model joined into this mask.
    pub(super) objects: Vec<u32>,
    /// 0 or 1 if the mask is one half of a split, else null.
    pub(super) split_half: Option<u8>,
    /// Class whose prototype dominates the feature.
    pub(super) feature_class: u32,
    /// Class the feature was biased toward, if any.
    pub(super) wrong_class: Option<u32>,
}

#[derive(Serialize)]
pub(super) struct ObjectJson<'a> {
    #[serde(flatten)]
    pub(super) spec: &'a ObjectSpec,
    pub(super) shape_kind: &'static str,
    pub(super) rotation_wxyz: [f64; 4],
}

#[derive(Serialize)]
pub(super) struct ClassJson {
    pub(super) id: u32,
    pub(super) name: String,
    pub(super) room: bool,
    pub(super) instances: usize,
}

#[derive(Serialize)]
pub(super) struct CamerasJson {
    pub(super) views: usize,
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) hfov_deg: f64,
    pub(super) image_names: Vec<String>,
}

#[derive(Serialize)]
pub(super) struct MasksJson {
    pub(super) total: usize,
    pub(super) per_view: Vec<ViewProvenance>,
}

#[derive(Serialize)]
pub(super) struct MatchesJson {
    pub(super) pairs: usize,
    pub(super) grid: [usize; 2],
    pub(super) coords: &'static str,
    pub(super) precision: MatchPrecision,
}

#[derive(Serialize)]
pub(super) struct SceneFile<'a> {
    pub(super) format: &'static str,
    pub(super) version: u32,
    pub(super) generator: String,
    pub(super) preset: String,
    pub(super) seed: u64,
    pub(super) label_space: &'static str,
    pub(super) room: scene::RoomJson,
    pub(super) classes: Vec<ClassJson>,
    pub(super) objects_requested: usize,
    pub(super) objects_placed: usize,
    pub(super) objects: Vec<ObjectJson<'a>>,
    pub(super) cameras: CamerasJson,
    pub(super) eval_frames: Vec<usize>,
    pub(super) fault_model: &'a FaultModel,
    pub(super) masks: Option<MasksJson>,
    pub(super) matches: Option<MatchesJson>,
    pub(super) gaussians: usize,
    pub(super) mesh: [usize; 2],
    pub(super) parameters: &'a Config,
}

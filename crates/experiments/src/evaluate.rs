//! Scores of a run against the scene's ground truth (synthetic scenes carry it under
//! `gt/`): the figures `profuse demo --json` reports.

use std::collections::BTreeMap;

use profuse_formats::{
    FileKind, Gaussians, Masks, Mesh, Prompts, Proposals, VertexLabels, ViewMaps,
};
use serde_json::{json, Value};

use profuse_pipeline::config::Config;
use profuse_pipeline::support::{fuse_job, stage_err};
use profuse_pipeline::{Paths, RegisteredMasks, Result, Summary};

/// Every score the ground truth allows, as a JSON object with keys:
/// `init_median_surface_dist_rel` and `init_surface` (gt/scene.json; of the Gaussians the
/// run registers onto: gs-init's, or gs-refine's when it runs — the key keeps its first
/// name), `proposals_ari` and
/// `proposals` (the object instances: members and attached masks) and `proposal_members`
/// (the members alone) (gt/mask_objects.json), `lerf_miou`, `lerf_acc25` and `lerf` (gt/label/),
/// `scannet_miou19/15/10`, `scannet_macc19/15/10` (gt/mesh.safetensors labels; each set
/// from its own `vertex_labels_nyu<set>` file).
/// Keys whose ground truth or stage output is absent are left out.
pub fn evaluate(p: &Paths) -> Result<BTreeMap<String, Value>> {
    let mut s = BTreeMap::new();
    let scene_json = p.gt.join("scene.json");
    if scene_json.is_file() && p.gaussians.is_file() && p.suffix.is_empty() {
        let scene = synth::Scene::from_json(&scene_json).map_err(stage_err("evaluate"))?;
        let g = Gaussians::read(&p.gaussians).map_err(stage_err("evaluate"))?;
        let d =
            profuse_metrics::surface::surface_distances(&g.means, |x| scene.distance_to_surface(x));
        let extent = profuse_metrics::surface::scene_extent(scene.room_size);
        let sum = profuse_metrics::surface::summarize(&d, extent);
        s.insert("init_median_surface_dist_rel".into(), json!(sum.median_rel));
        s.insert(
            "init_surface".into(),
            serde_json::to_value(&sum).unwrap_or(Value::Null),
        );
    }
    let mask_objects = p.gt.join("mask_objects.json");
    if mask_objects.is_file() && p.proposals.is_file() && p.suffix.is_empty() {
        let truth = profuse_metrics::cluster::read_mask_objects(&mask_objects)
            .map_err(stage_err("evaluate"))?;
        let props = Proposals::read(&p.proposals).map_err(stage_err("evaluate"))?;
        let c = profuse_metrics::cluster::proposal_scores(&props, &truth)
            .map_err(stage_err("evaluate"))?;
        let members = profuse_metrics::cluster::member_scores(&props, &truth)
            .map_err(stage_err("evaluate"))?;
        s.insert("proposals_ari".into(), json!(c.ari));
        s.insert(
            "proposals".into(),
            serde_json::to_value(&c).unwrap_or(Value::Null),
        );
        s.insert(
            "proposal_members".into(),
            serde_json::to_value(&members).unwrap_or(Value::Null),
        );
    }
    if let (Some(dir), true) = (p.labels(), p.query.is_dir()) {
        let labels = profuse_metrics::lerf::read_label_dir(&dir).map_err(stage_err("evaluate"))?;
        let src = profuse_metrics::lerf::PredDir {
            dir: p.query.clone(),
        };
        let sc = profuse_metrics::lerf::evaluate_scene(&labels, &src, None)
            .map_err(stage_err("evaluate"))?;
        s.insert("lerf_miou".into(), json!(sc.miou));
        s.insert("lerf_acc25".into(), json!(sc.acc25));
        s.insert(
            "lerf".into(),
            json!({ "pairs": sc.pairs, "missing": sc.missing, "frames": sc.frames,
                    "per_query": serde_json::to_value(&sc.per_query).unwrap_or(Value::Null) }),
        );
    }
    // Each class set is scored on its own labelling (argmax over that set's prompts only,
    // OpenGaussian's protocol), not on one labelling over every class.
    if let Some(mesh) = p.mesh() {
        let present: Vec<_> = p
            .vertex_labels
            .iter()
            .filter(|(_, f)| f.is_file())
            .collect();
        if !present.is_empty() {
            let m = Mesh::read(&mesh).map_err(stage_err("evaluate"))?;
            let truth = profuse_metrics::scannet::ground_truth_labels(&m, mesh.display())
                .map_err(stage_err("evaluate"))?;
            for (set, file) in present {
                let pred = VertexLabels::read(file).map_err(stage_err("evaluate"))?;
                let sc = profuse_metrics::scannet::evaluate(&pred.labels, &truth, *set)
                    .map_err(stage_err("evaluate"))?;
                s.insert(format!("scannet_miou{}", set.name()), json!(sc.miou));
                s.insert(format!("scannet_macc{}", set.name()), json!(sc.macc));
            }
        }
    }
    Ok(s)
}

/// [`evaluate`] plus the wrong-class pixel share of the run's registration
/// ([`wrong_class`]): keys `wrong_class_pixel_share` and `wrong_class` (its counts) when
/// the scene has `gt/views.safetensors` with object ids, `gt/scene.json` and prompts with
/// class ids. `summary` is what [`profuse_pipeline::run`] returned for this variant (its in-memory
/// registration is used when the fuse stage ran; otherwise it is recomputed).
pub fn evaluate_run(
    p: &Paths,
    config: &Config,
    summary: &Summary,
) -> Result<BTreeMap<String, Value>> {
    let mut s = evaluate(p)?;
    if let Some(w) = wrong_class(p, config, summary.registered.as_ref())? {
        s.insert("wrong_class_pixel_share".into(), json!(w.share));
        s.insert(
            "wrong_class".into(),
            serde_json::to_value(&w).unwrap_or(Value::Null),
        );
    }
    Ok(s)
}

/// The wrong-class pixel share ([`profuse_metrics::wrong_class`]) of the registration of
/// the variant `p` names (`p.suffix`: proposals, or the `_baseline` of
/// `fuse.no_proposals`): every mask pixel with a ground-truth object is scored by the best
/// class prompt of the descriptor its mask registers; masks that register nothing (ignored
/// orphans) count as wrong. `registered` is the run's in-memory registration; when `None`
/// the fuse accumulation is redone in memory from the run's files (about a second on the
/// demo scene; nothing is written). `None` when the ground truth or class prompts are
/// absent, or when `gt/views.safetensors` is not on the masks' grid and views.
pub fn wrong_class(
    p: &Paths,
    config: &Config,
    registered: Option<&RegisteredMasks>,
) -> Result<Option<profuse_metrics::wrong_class::WrongClassShare>> {
    let views_path = p.gt.join("views.safetensors");
    let scene_json = p.gt.join("scene.json");
    if !views_path.is_file() || !scene_json.is_file() || !p.masks.is_file() {
        return Ok(None);
    }
    let prompts = Prompts::read(&p.prompts).map_err(stage_err("evaluate"))?;
    if prompts.class_ids.is_none() {
        return Ok(None);
    }
    let views = ViewMaps::read(&views_path).map_err(stage_err("evaluate"))?;
    let masks = Masks::read(&p.masks).map_err(stage_err("evaluate"))?;
    // Synth writes both on the image grid; other scenes may not match pixel for pixel.
    if views.object_ids.is_none()
        || (views.width, views.height) != (masks.width, masks.height)
        || views.view_names != masks.view_names
    {
        return Ok(None);
    }
    let recomputed;
    let registered = match registered {
        Some(r) => r,
        None => {
            let mut config = config.clone();
            config.fuse.no_proposals = !p.suffix.is_empty();
            let run = profuse_fuse::job::run(&fuse_job(&config, p), &config.fuse, &mut |_| {})
                .map_err(stage_err("fuse"))?;
            recomputed = RegisteredMasks(std::sync::Arc::new(
                profuse_fuse::registered_mask_descriptors(&run.partial),
            ));
            &recomputed
        }
    };
    let classes = profuse_metrics::wrong_class::mask_classes(
        &registered.0,
        &prompts,
        &p.prompts.display().to_string(),
    )
    .map_err(stage_err("evaluate"))?;
    let object_class = profuse_metrics::wrong_class::read_object_classes(&scene_json)
        .map_err(stage_err("evaluate"))?;
    let share = profuse_metrics::wrong_class::wrong_class_pixel_share(
        &masks,
        &views,
        &views_path.display().to_string(),
        &object_class,
        &classes,
    )
    .map_err(stage_err("evaluate"))?;
    Ok(Some(share))
}

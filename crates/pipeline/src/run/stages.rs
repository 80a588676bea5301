//! One function per stage of a run: its inputs checked, its parameters from the config, its
//! outputs and its summary line (gs-init, gs-refine or given Gaussians, warp-graph or given
//! proposals, fuse, pq, query, vertex-transfer).

use super::*;

impl Runner<'_> {
    /// Progress of the running stage: `done` of `total` units.
    pub(crate) fn progress(&self, done: usize, total: usize) {
        (self.events)(Event::Progress {
            done: done as u64,
            total: total as u64,
        })
    }
}

/// gs-init: cameras + images + matches -> gaussians.
pub(super) fn gs_init_stage(r: &Runner<'_>, config: &Config, p: &Paths) -> Result<StageLine> {
    let images = image_paths(p)?;
    let mut inputs = vec![p.cameras.clone(), p.matches.clone()];
    inputs.extend(images);
    stage(
        r,
        "gs-init",
        to_json(&config.gs_init),
        inputs,
        vec![p.gaussians_init.clone()],
        || {
            let params = gs_init::Params::from(config.gs_init);
            let match_file = if p.sparse {
                gs_init::MatchFile::Sparse(p.matches.clone())
            } else {
                gs_init::MatchFile::Dense(p.matches.clone())
            };
            let job = gs_init::job::Job {
                inputs: gs_init::Inputs {
                    cameras: p.cameras.clone(),
                    images: p.scene.clone(),
                    matches: match_file,
                },
                out: p.gaussians_init.clone(),
            };
            let report = gs_init::job::run(&job, &params, &|d, t| r.progress(d, t))
                .map_err(stage_err("gs-init"))?;
            Ok(to_json(&report))
        },
    )
}

/// gs-refine: gs-init's Gaussians + cameras + photos -> refined gaussians.
pub(super) fn gs_refine_stage(r: &Runner<'_>, config: &Config, p: &Paths) -> Result<StageLine> {
    let mut inputs = vec![p.gaussians_init.clone(), p.cameras.clone()];
    inputs.extend(image_paths(p)?);
    stage(
        r,
        "gs-refine",
        to_json(&config.gs_refine),
        inputs,
        vec![p.gaussians.clone()],
        || {
            let job = gs_refine::job::Job {
                gaussians: p.gaussians_init.clone(),
                cameras: p.cameras.clone(),
                images: p.scene.clone(),
                out: p.gaussians.clone(),
                exclude: Vec::new(),
                save_every: 0,
            };
            let total = config.gs_refine.iterations;
            let report = gs_refine::job::run(&job, &config.gs_refine, &mut |it, _, _| {
                r.progress(it, total)
            })
            .map_err(stage_err("gs-refine"))?;
            Ok(to_json(&report))
        },
    )
}

/// gaussians: a given Gaussians file (instead of gs-init and gs-refine) ->
/// out/gaussians, its bytes unchanged once it reads as a valid Gaussians file. Running it
/// removes the records of gs-init and gs-refine, whose output it replaces, so that they run
/// again when they are next asked for.
pub(super) fn given_gaussians_stage(r: &Runner<'_>, p: &Paths, given: &Path) -> Result<StageLine> {
    stage(
        r,
        "gaussians",
        json!({ "from": given }),
        vec![given.to_path_buf()],
        vec![p.gaussians.clone()],
        || {
            for replaced in ["gs-init", "gs-refine"] {
                clear_stamp(r.out, replaced)
                    .map_err(io_err(r.out, "cannot remove a completion record"))?;
            }
            let g = Gaussians::read(given).map_err(stage_err("gaussians"))?;
            let mut src = std::fs::File::open(given)
                .map_err(io_err(given, "cannot open the given Gaussians"))?;
            profuse_formats::write_atomically(&p.gaussians, |mut f| {
                std::io::copy(&mut src, &mut f).map(|_| ())
            })
            .map_err(|(action, e)| io_err(&p.gaussians, action)(e))?;
            Ok(json!({ "from": given, "gaussians": g.len() }))
        },
    )
}

/// warp-graph: masks + matches (+ cameras, gaussians for visibility) -> proposals.
pub(super) fn warp_graph_stage(
    r: &Runner<'_>,
    config: &Config,
    p: &Paths,
    partials: &[PathBuf],
) -> Result<StageLine> {
    if p.sparse {
        return Err(PipelineError::MissingInput {
            stage: "warp-graph",
            path: p.scene.join("matches.safetensors").display().to_string(),
            expected: "dense matches (warp-graph warps mask label maps; sparse matches cannot)",
        });
    }
    stage(
        r,
        "warp-graph",
        to_json(&config.warp_graph),
        vec![
            p.masks.clone(),
            p.matches.clone(),
            p.cameras.clone(),
            p.gaussians.clone(),
        ],
        vec![p.proposals.clone()],
        || {
            let job = warp_graph_job(p);
            let report = if partials.is_empty() {
                warp_graph::job::run(&job, &config.warp_graph, &|d, t| r.progress(d, t))
            } else {
                warp_graph::job::run_merged(&job, &config.warp_graph, partials)
            }
            .map_err(stage_err("warp-graph"))?;
            Ok(to_json(&report))
        },
    )
}

/// The warp-graph job of a run: its masks, matches, cameras and Gaussians.
pub(super) fn warp_graph_job(p: &Paths) -> warp_graph::job::Job {
    warp_graph::job::Job {
        masks: p.masks.clone(),
        matches: p.matches.clone(),
        cameras: Some(p.cameras.clone()),
        gaussians: Some(p.gaussians.clone()),
        out: p.proposals.clone(),
    }
}

/// One view-pair shard of the warp-graph stage of a run: computes the mask-pair evidence
/// of view pairs `pairs` (of the run's list, ascending (i, j)) from the scene and the
/// run's Gaussians (`out_dir`, written by a run that reached gs-init, or gs-refine when
/// it is on) with the run's configuration, and writes it to `partial_out` (atomically)
/// for [`RunOptions::warp_partials`]. Takes no lock: shards run in parallel, anywhere the
/// files are visible. The report's `view_pairs` is the run's T.
pub fn warp_shard(
    scene: &Path,
    out_dir: &Path,
    config: &Config,
    pairs: std::ops::Range<usize>,
    partial_out: &Path,
    on_pair: &(dyn Fn(usize, usize) + Sync),
) -> Result<warp_graph::job::ShardReport> {
    config.validate()?;
    if config.fuse.no_proposals {
        return Err(PipelineError::Stage {
            stage: "warp-graph",
            source: "the configuration sets fuse.no_proposals, so a run has no warp-graph \
                     stage to shard"
                .into(),
        });
    }
    let p = Paths::new(scene, out_dir, false).with_refinement(config.gs_refine.iterations > 0);
    check_input("warp-graph", &p.masks, "masks file")?;
    check_input(
        "warp-graph",
        &p.gaussians,
        "gaussians of a run that reached gs-init (gs-refine when it is on)",
    )?;
    profuse_formats::output::check_output_file(partial_out)?;
    warp_graph::job::run_shard(
        &warp_graph_job(&p),
        &config.warp_graph,
        pairs,
        partial_out,
        on_pair,
    )
    .map_err(stage_err("warp-graph"))
}

/// proposals: a given proposals file (instead of warp-graph) -> out/proposals, after
/// checking that it has one entry per mask. Running it removes warp-graph's completion
/// record, whose output it replaces, so that warp-graph runs again when it is next asked
/// for.
pub(super) fn given_proposals_stage(r: &Runner<'_>, p: &Paths, given: &Path) -> Result<StageLine> {
    stage(
        r,
        "proposals",
        json!({ "from": given }),
        vec![given.to_path_buf(), p.masks.clone()],
        vec![p.proposals.clone()],
        || {
            clear_stamp(r.out, "warp-graph")
                .map_err(io_err(r.out, "cannot remove a completion record"))?;
            let props = Proposals::read(given).map_err(stage_err("proposals"))?;
            let masks = Masks::read(&p.masks).map_err(stage_err("proposals"))?;
            if props.mask_proposal.len() != masks.num_masks() {
                return Err(PipelineError::Stage {
                    stage: "proposals",
                    source: format!(
                        "{}: mask_proposal has {} entries, expected one per mask of {} ({})",
                        given.display(),
                        props.mask_proposal.len(),
                        p.masks.display(),
                        masks.num_masks()
                    )
                    .into(),
                });
            }
            props.write(&p.proposals).map_err(stage_err("proposals"))?;
            Ok(json!({
                "from": given,
                "proposals": props.len(),
                "masks": masks.num_masks(),
            }))
        },
    )
}

/// fuse: gaussians + cameras + masks (+ proposals) -> features, and what every mask
/// registered (for the wrong-class share).
pub(super) fn fuse_stage(
    r: &Runner<'_>,
    config: &Config,
    p: &Paths,
    partials: &[PathBuf],
) -> Result<(StageLine, Option<RegisteredMasks>)> {
    let fuse_name = if config.fuse.no_proposals {
        "fuse_baseline"
    } else {
        "fuse"
    };
    let mut registered = None;
    let mut fuse_inputs = vec![p.gaussians.clone(), p.cameras.clone(), p.masks.clone()];
    if !config.fuse.no_proposals {
        fuse_inputs.push(p.proposals.clone());
    }
    let line = stage(
        r,
        fuse_name,
        to_json(&config.fuse),
        fuse_inputs,
        fuse_outputs(config, p),
        || {
            let mut job = fuse_job(config, p).with_out(&p.features);
            if config.query.semantics.needs_index() {
                job.semantic_index = Some(p.semantic_index.clone());
            }
            let run = if partials.is_empty() {
                let views = Cameras::read(&p.cameras).map_or(0, |c| c.len());
                let mut done = 0;
                profuse_fuse::job::run(&job, &config.fuse, &mut |_| {
                    done += 1;
                    r.progress(done, views)
                })
            } else {
                profuse_fuse::job::run_merged(&job, &config.fuse, partials)
            }
            .map_err(stage_err("fuse"))?;
            registered = Some(RegisteredMasks(std::sync::Arc::new(
                profuse_fuse::registered_mask_descriptors(&run.partial),
            )));
            Ok(to_json(&run.report))
        },
    )?;
    Ok((line, registered))
}

/// The fuse stage's files: the features, and the semantic index when the query reads one.
pub(super) fn fuse_outputs(config: &Config, p: &Paths) -> Vec<PathBuf> {
    let mut out = vec![p.features.clone()];
    if config.query.semantics.needs_index() {
        out.push(p.semantic_index.clone());
    }
    out
}

/// The per-Gaussian semantics files the query and vertex-transfer stages read.
pub(super) fn semantics_files(config: &Config, p: &Paths) -> Vec<PathBuf> {
    let s = config.query.semantics;
    let mut files = Vec::new();
    if s.needs_index() {
        files.push(p.semantic_index.clone());
    }
    if s.needs_pq() {
        files.push(p.pq.clone());
    }
    files
}

/// The query's descriptors under `query.semantics`.
pub(super) fn query_descriptors(config: &Config, p: &Paths) -> profuse_query::DescriptorPath {
    use profuse_query::{DescriptorPath, Semantics};
    match config.query.semantics {
        Semantics::Pq => DescriptorPath::Pq(p.pq.clone()),
        Semantics::Index => DescriptorPath::Indexed {
            index: p.semantic_index.clone(),
            fallback: None,
        },
        Semantics::Both => DescriptorPath::Indexed {
            index: p.semantic_index.clone(),
            fallback: Some(p.pq.clone()),
        },
    }
}

/// vertex-transfer's descriptors under `query.semantics`.
pub(super) fn transfer_descriptors(config: &Config, p: &Paths) -> vertex_transfer::DescriptorFile {
    use vertex_transfer::DescriptorFile;
    match query_descriptors(config, p) {
        profuse_query::DescriptorPath::Indexed { index, fallback } => {
            DescriptorFile::Indexed { index, fallback }
        }
        _ => DescriptorFile::Pq(p.pq.clone()),
    }
}

/// pq: features -> pq.
pub(super) fn pq_stage(r: &Runner<'_>, config: &Config, p: &Paths) -> Result<StageLine> {
    stage(
        r,
        &format!("pq{}", p.suffix),
        to_json(&config.pq),
        vec![p.features.clone()],
        vec![p.pq.clone()],
        || {
            let report = profuse_pq::job::train_file(&p.features, &p.pq, &config.pq)
                .map_err(stage_err("pq"))?;
            Ok(to_json(&report))
        },
    )
}

/// query: gaussians + cameras + pq + prompts -> masks per (view, prompt) + selections.
pub(super) fn query_stage(r: &Runner<'_>, config: &Config, p: &Paths) -> Result<StageLine> {
    let prompts = query_prompts(config, p)?;
    let mut query_inputs = vec![p.gaussians.clone(), p.cameras.clone()];
    query_inputs.extend(semantics_files(config, p));
    query_inputs.push(p.prompts.clone());
    if let Some(l) = p.labels() {
        query_inputs.push(l);
    }
    stage(
        r,
        &format!("query{}", p.suffix),
        json!({ "query": to_json(&config.query), "prompts": prompts }),
        query_inputs,
        vec![p.query.clone()],
        || run_query(config, p, &prompts, &|d, t| r.progress(d, t)),
    )
}

/// vertex-transfer, when the scene has a labelled mesh (synthetic ground truth): one
/// labelling per class set of the ScanNet protocol (OpenGaussian's); the vocabulary is the
/// set's own class prompts, so each vertex takes the argmax over that set only.
pub(super) fn vertex_transfer_stage(
    r: &Runner<'_>,
    config: &Config,
    p: &Paths,
    mesh: &Path,
) -> Result<StageLine> {
    let sets: Vec<&str> = p.vertex_labels.iter().map(|(s, _)| s.name()).collect();
    stage(
        r,
        &format!("vertex-transfer{}", p.suffix),
        json!({ "vertex_transfer": to_json(&config.vertex_transfer), "class_sets": sets }),
        [p.gaussians.clone()]
            .into_iter()
            .chain(semantics_files(config, p))
            .chain([p.prompts.clone(), mesh.to_path_buf()])
            .collect(),
        p.vertex_labels.iter().map(|(_, f)| f.clone()).collect(),
        || {
            let mut reports = serde_json::Map::new();
            for (set, out) in &p.vertex_labels {
                let job = vertex_transfer::Job {
                    gaussians: p.gaussians.clone(),
                    descriptors: transfer_descriptors(config, p),
                    prompts: p.prompts.clone(),
                    classes: None,
                    // NYU40 ids are 1..=40: they fit i32.
                    class_filter: Some(set.ids().iter().map(|&id| id as i32).collect()),
                    mesh: mesh.to_path_buf(),
                    out: out.clone(),
                    // The same stamp as the vertex-transfer tool, so the bytes agree.
                    generator: Some(format!("vertex-transfer {} run", env!("CARGO_PKG_VERSION"))),
                };
                let report = vertex_transfer::run_job(&job, &config.vertex_transfer)
                    .map_err(stage_err("vertex-transfer"))?;
                reports.insert(format!("nyu{}", set.name()), to_json(&report));
            }
            Ok(Value::Object(reports))
        },
    )
}

/// The fuse stage's job over every view: the proposals under the configured
/// registration, or one group per mask for `fuse.no_proposals`; it writes nothing.
pub fn fuse_job(config: &Config, p: &Paths) -> profuse_fuse::job::Job {
    let job = profuse_fuse::job::Job::new(&p.gaussians, &p.cameras, &p.masks);
    if config.fuse.no_proposals {
        job.baseline()
    } else {
        job.with_proposals(&p.proposals)
    }
}
/// The prompts to query: the configured ones, else the categories of the LERF label files
/// that the prompts file has, else every class prompt.
pub(super) fn query_prompts(config: &Config, p: &Paths) -> Result<Vec<String>> {
    if !config.query.prompts.is_empty() {
        return Ok(config.query.prompts.clone());
    }
    let prompts = profuse_formats::Prompts::read(&p.prompts).map_err(stage_err("query"))?;
    if let Some(dir) = p.labels() {
        let scene = profuse_metrics::lerf::read_label_dir(&dir).map_err(stage_err("query"))?;
        let mut cats: Vec<String> = scene
            .frames
            .iter()
            .flat_map(|f| f.objects.iter().map(|o| o.category.clone()))
            .filter(|c| prompts.names.contains(c))
            .collect();
        cats.sort();
        cats.dedup();
        return Ok(cats);
    }
    Ok(match &prompts.class_ids {
        Some(ids) => prompts
            .names
            .iter()
            .zip(ids.iter())
            .filter(|(_, id)| **id >= 0)
            .map(|(n, _)| n.clone())
            .collect(),
        None => prompts
            .names
            .iter()
            .filter(|n| !profuse_formats::label_space::CANONICAL_NEGATIVES.contains(&n.as_str()))
            .cloned()
            .collect(),
    })
}

/// The query stage: the LERF layout over the labelled frames when the scene has labels,
/// else the per-prompt layout over every view; written to a uniquely named temporary
/// directory swapped into place at the end (`Plan::run_replacing`), so an interrupted
/// query leaves no partial folder behind.
pub(super) fn run_query(
    config: &Config,
    p: &Paths,
    prompts: &[String],
    progress: &dyn Fn(usize, usize),
) -> Result<Value> {
    let q = &config.query;
    let inputs = profuse_query::Inputs::load(
        &p.gaussians,
        &p.cameras,
        &query_descriptors(config, p),
        &p.prompts,
    )
    .map_err(stage_err("query"))?;
    let score = q.score;
    let (views, layout) = match p.labels() {
        Some(dir) => (
            profuse_query::ViewSelection::FromLabels(dir),
            profuse_query::Layout::Lerf,
        ),
        None => (
            profuse_query::ViewSelection::All,
            profuse_query::Layout::Prompt,
        ),
    };
    let options = profuse_query::QueryOptions {
        prompts: profuse_query::PromptSelection::Names(prompts.to_vec()),
        score,
        rule: Some(profuse_query::Rule::Threshold(q.threshold)),
        gamma: q.gamma,
        k: q.k,
        scale: None,
        views,
        layout,
        overlay: q.overlay,
    };
    let plan = inputs.plan(&options).map_err(stage_err("query"))?;
    let report = plan
        .run_replacing(&inputs.gaussians, &p.query, &mut |d, t| progress(d, t))
        .map_err(stage_err("query"))?;
    Ok(to_json(&report))
}

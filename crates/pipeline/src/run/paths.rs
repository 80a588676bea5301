//! The paths of a scene directory (SPEC.md §6) and of one run's outputs.

use super::*;

/// The paths of a scene directory (SPEC.md §6) and of one run's outputs.
#[derive(Debug, Clone)]
pub struct Paths {
    /// The scene directory.
    pub scene: PathBuf,
    /// The output directory.
    pub out: PathBuf,
    /// `cameras.safetensors`.
    pub cameras: PathBuf,
    /// Dense `matches.safetensors`, or sparse `sparse_matches.safetensors` when only that exists.
    pub matches: PathBuf,
    /// Whether `matches` is the sparse kind.
    pub sparse: bool,
    /// `masks.safetensors`.
    pub masks: PathBuf,
    /// `prompts.safetensors`.
    pub prompts: PathBuf,
    /// `out/gaussians.safetensors`: the Gaussians every later stage reads.
    pub gaussians: PathBuf,
    /// What gs-init writes: `gaussians` itself, or `out/gaussians_init.safetensors` when
    /// the gs-refine stage runs ([`Paths::with_refinement`]) and writes `gaussians`.
    pub gaussians_init: PathBuf,
    /// `out/proposals.safetensors`.
    pub proposals: PathBuf,
    /// `out/features[_baseline].safetensors`.
    pub features: PathBuf,
    /// `out/pq[_baseline].safetensors`.
    pub pq: PathBuf,
    /// `out/semantic_index[_baseline].safetensors` (written with `query.semantics` index
    /// or both).
    pub semantic_index: PathBuf,
    /// `out/query[_baseline]/`.
    pub query: PathBuf,
    /// Per class set of the ScanNet protocol ([`SCANNET_SETS`]), the labelling with that
    /// set's vocabulary: `out/vertex_labels_nyu<19|15|10>[_baseline].safetensors`.
    pub vertex_labels: Vec<(ClassSet, PathBuf)>,
    /// `gt/` (synthetic scenes).
    pub gt: PathBuf,
    /// Suffix of the variant's outputs (`_baseline` for `fuse.no_proposals`).
    pub suffix: &'static str,
}

impl Paths {
    /// With the gs-refine stage on, gs-init writes `out/gaussians_init.safetensors` and
    /// gs-refine writes the refined `out/gaussians.safetensors`.
    pub fn with_refinement(mut self, on: bool) -> Paths {
        if on {
            self.gaussians_init = self.out.join("gaussians_init.safetensors");
        }
        self
    }

    /// The paths for a scene, an output directory and a variant.
    pub fn new(scene: &Path, out: &Path, baseline: bool) -> Paths {
        let suffix = if baseline { "_baseline" } else { "" };
        let dense = scene.join("matches.safetensors");
        let sparse_path = scene.join("sparse_matches.safetensors");
        let sparse = !dense.is_file() && sparse_path.is_file();
        Paths {
            scene: scene.to_path_buf(),
            out: out.to_path_buf(),
            cameras: scene.join("cameras.safetensors"),
            matches: if sparse { sparse_path } else { dense },
            sparse,
            masks: scene.join("masks.safetensors"),
            prompts: scene.join("prompts.safetensors"),
            gaussians: out.join("gaussians.safetensors"),
            gaussians_init: out.join("gaussians.safetensors"),
            proposals: out.join("proposals.safetensors"),
            features: out.join(format!("features{suffix}.safetensors")),
            pq: out.join(format!("pq{suffix}.safetensors")),
            semantic_index: out.join(format!("semantic_index{suffix}.safetensors")),
            query: out.join(format!("query{suffix}")),
            vertex_labels: SCANNET_SETS
                .iter()
                .map(|&set| {
                    let name = format!("vertex_labels_nyu{}{suffix}.safetensors", set.name());
                    (set, out.join(name))
                })
                .collect(),
            gt: scene.join("gt"),
            suffix,
        }
    }

    /// `SCENE/gaussians.safetensors`, when the scene brings its geometry (`profuse
    /// prepare` writes it: refined Gaussians or the user's own splat): the run then uses
    /// it as [`RunOptions::gaussians`] instead of running gs-init and gs-refine.
    pub fn prepared_gaussians(&self) -> Option<PathBuf> {
        let p = self.scene.join("gaussians.safetensors");
        p.is_file().then_some(p)
    }

    /// LERF-style label files (`gt/label/`), when the scene has them.
    pub fn labels(&self) -> Option<PathBuf> {
        let p = self.gt.join("label");
        p.is_dir().then_some(p)
    }

    /// The labelled mesh (`gt/mesh.safetensors`), when the scene has one.
    pub fn mesh(&self) -> Option<PathBuf> {
        let p = self.gt.join("mesh.safetensors");
        p.is_file().then_some(p)
    }
}

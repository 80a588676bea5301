//! The Gaussian field: prepared kernels, class probabilities and the KD-tree, and the
//! per-vertex vote.

use std::collections::BTreeMap;
use std::num::NonZeroUsize;

use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::SquaredEuclidean;
use profuse_formats::{Features, FileKind, Gaussians, Pq, SemanticIndex, VertexLabels};
use rayon::prelude::*;

use crate::classes::ClassSet;
use crate::error::{Result, TransferError};
use crate::kernel::{class_probabilities, Kernel};
use crate::Source;

/// Default shortlist size K (paper §4.3).
pub const DEFAULT_K: usize = 64;
/// Default Mahalanobis gate σ (paper §4.3).
pub const DEFAULT_SIGMA: f32 = 3.0;
/// Default softmax temperature (the paper gives none). At CLIP's own logit scale
/// (T = 0.01) each Gaussian votes almost one-hot, so Gaussians of classes outside the
/// evaluated set and noisy ones vote hard for a wrong class; on the ScanNet oracle
/// (README) mIoU rises from 75.5 at T = 0.01 to a plateau at T = 0.1..1.
pub const DEFAULT_TEMPERATURE: f32 = 0.1;
/// Default smallest standard deviation of a Gaussian axis, in scene units (0.1 mm for
/// metric scenes such as ScanNet): flat or underflowing axes are clamped to it.
pub const DEFAULT_MIN_SCALE: f32 = 1e-4;

/// Vertices per parallel task.
const VERTEX_CHUNK: usize = 512;

/// The transfer's parameters; [`Params::default`] holds the paper's values. As serde, the
/// pipeline's `[vertex_transfer]` section; with the `clap` feature, the tool's flags.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
#[serde(default, deny_unknown_fields)]
pub struct Params {
    /// Shortlist: the K nearest valid Gaussian centres (Euclidean) of a vertex.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DEFAULT_K))]
    pub k: usize,
    /// Gate: a shortlisted Gaussian is a candidate when its Mahalanobis distance d <= σ.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DEFAULT_SIGMA))]
    pub sigma: f32,
    /// Softmax temperature T of the class logits cos(f, e_c) / T (0.01 = CLIP's own logit
    /// scale; lower values make every Gaussian vote nearly one-hot).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DEFAULT_TEMPERATURE))]
    pub temperature: f32,
    /// Smallest standard deviation per axis (scene units).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DEFAULT_MIN_SCALE))]
    pub min_scale: f32,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            k: DEFAULT_K,
            sigma: DEFAULT_SIGMA,
            temperature: DEFAULT_TEMPERATURE,
            min_scale: DEFAULT_MIN_SCALE,
        }
    }
}

impl Params {
    /// Checks every parameter's domain.
    pub fn validate(&self) -> Result<()> {
        let bad = |name, value: String, expected| {
            Err(TransferError::Parameter {
                name,
                value,
                expected,
            })
        };
        if self.k == 0 || u32::try_from(self.k).is_err() {
            return bad("k", self.k.to_string(), "an integer >= 1");
        }
        if !(self.sigma.is_finite() && self.sigma > 0.0) {
            return bad("sigma", self.sigma.to_string(), "a finite number > 0");
        }
        if !(self.temperature.is_finite() && self.temperature > 0.0) {
            return bad(
                "temperature",
                self.temperature.to_string(),
                "a finite number > 0",
            );
        }
        if !(self.min_scale.is_finite() && self.min_scale > 0.0) {
            return bad(
                "min_scale",
                self.min_scale.to_string(),
                "a finite number > 0",
            );
        }
        Ok(())
    }
}

/// Where the per-Gaussian descriptors come from.
#[derive(Debug, Clone, Copy)]
pub enum Descriptors<'a> {
    /// Decoded descriptors (a `features` file).
    Features(Source<'a, Features>),
    /// Product-quantised descriptors (a `pq` file), decoded with `profuse_pq::decode`
    /// one Gaussian at a time.
    Pq(Source<'a, Pq>),
    /// A semantic index (issue 24): every Gaussian takes its dominant proposal's
    /// descriptor (hence that proposal's class probabilities); with `fallback`, the
    /// Gaussians without a dominant proposal take their decoded PQ code instead.
    Indexed {
        /// The semantic index.
        index: Source<'a, SemanticIndex>,
        /// PQ codes of the same Gaussians.
        fallback: Option<Source<'a, Pq>>,
    },
}

impl Descriptors<'_> {
    fn file(&self) -> &str {
        match self {
            Descriptors::Features(f) => f.file,
            Descriptors::Pq(p) => p.file,
            Descriptors::Indexed { index, .. } => index.file,
        }
    }

    fn validate(&self) -> Result<()> {
        match self {
            Descriptors::Features(f) => f.data.validate(f.file)?,
            Descriptors::Pq(p) => p.data.validate(p.file)?,
            Descriptors::Indexed { index, fallback } => {
                index.data.validate(index.file)?;
                if let Some(pq) = fallback {
                    pq.data.validate(pq.file)?;
                    if pq.data.len() != index.data.num_gaussians() {
                        return Err(TransferError::CountMismatch {
                            file: pq.file.to_string(),
                            tensor: "codes",
                            found: pq.data.len(),
                            gaussians_file: index.file.to_string(),
                            expected: index.data.num_gaussians(),
                        });
                    }
                    if pq.data.dim() != index.data.dim {
                        return Err(TransferError::DimMismatch {
                            file: pq.file.to_string(),
                            found: pq.data.dim(),
                            prompts_file: index.file.to_string(),
                            expected: index.data.dim,
                        });
                    }
                }
            }
        }
        Ok(())
    }

    /// Rows and the tensor that defines them.
    fn rows(&self) -> (usize, &'static str) {
        match self {
            Descriptors::Features(f) => (f.data.len(), "valid"),
            Descriptors::Pq(p) => (p.data.len(), "codes"),
            Descriptors::Indexed { index, .. } => (index.data.num_gaussians(), "index"),
        }
    }

    fn dim(&self) -> usize {
        match self {
            Descriptors::Features(f) => f.data.dim,
            Descriptors::Pq(p) => p.data.dim(),
            Descriptors::Indexed { index, .. } => index.data.dim,
        }
    }

    /// The PQ codes Gaussian `g` falls back to, if it does.
    fn fallback_of(&self, g: usize) -> Option<&Pq> {
        match self {
            Descriptors::Indexed {
                index,
                fallback: Some(pq),
            } if !index.data.is_dominant(g) => Some(pq.data),
            _ => None,
        }
    }

    fn is_valid(&self, g: usize) -> bool {
        if let Some(pq) = self.fallback_of(g) {
            return pq.valid[g] == 1;
        }
        match self {
            Descriptors::Features(f) => f.data.valid[g] == 1,
            Descriptors::Pq(p) => p.data.valid[g] == 1,
            Descriptors::Indexed { index, .. } => index.data.proposal(g).is_some(),
        }
    }

    /// Copies descriptor `g` into `out` (length D) as f32; inputs were validated, so
    /// the PQ tensors are consistent and `decode` cannot panic.
    fn read(&self, g: usize, out: &mut [f32]) {
        if let Some(pq) = self.fallback_of(g) {
            return profuse_pq::decode(pq, g, out);
        }
        match self {
            Descriptors::Features(f) => f.data.features.read_into(g * f.data.dim, out),
            Descriptors::Pq(p) => profuse_pq::decode(p.data, g, out),
            Descriptors::Indexed { index, .. } => {
                let d = index.data.dim;
                let row = index.data.proposal(g).unwrap_or(0) as usize;
                index.data.descriptors.read_into(row * d, out);
            }
        }
    }
}

/// One gated candidate of a vertex.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate {
    /// Index of the Gaussian in the gaussians file.
    pub gaussian: usize,
    /// Squared Mahalanobis distance d² of the vertex under the Gaussian's covariance.
    pub mahalanobis_sq: f32,
    /// exp(−d²/2) · opacity.
    pub weight: f32,
}

/// Labels of a set of vertices.
#[derive(Debug, Clone, PartialEq)]
pub struct Labelling {
    /// Label per vertex (a class's label), −1 where no candidate carried weight.
    pub labels: Vec<i32>,
    /// max_c score_c / Σ weights, in [0, 1]; 0 where unlabelled.
    pub confidence: Vec<f32>,
    /// Counters over all vertices.
    pub stats: Stats,
}

/// Counters of a labelling (sums over vertices, identical for any thread count).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
pub struct Stats {
    /// Vertices labelled.
    pub vertices: u64,
    /// Vertices with a label (>= 0).
    pub labelled: u64,
    /// Gated candidates summed over vertices.
    pub candidates: u64,
    /// Vertices whose whole shortlist of K passed the gate, so that Gaussians beyond the
    /// K-th nearest might have passed too (raise K if this is large). Always 0 for the
    /// brute force.
    pub saturated: u64,
}

/// Gaussians prepared for label transfer: one [`Kernel`] and one row of class
/// probabilities per valid Gaussian, and a KD-tree over their centres.
#[derive(Debug)]
pub struct GaussianField {
    params: Params,
    kernels: Vec<Kernel>,
    /// Index in the gaussians file of each kernel, ascending.
    ids: Vec<u32>,
    /// kernels.len() x classes, row-major.
    probs: Vec<f32>,
    labels: Vec<i32>,
    class_names: Vec<String>,
    tree: Option<ImmutableKdTree<f32, u32, 3, 32>>,
    /// Squared Euclidean radius beyond which no Gaussian can pass the gate (∞ if unknown).
    reach_sq: f32,
}

impl GaussianField {
    /// Validates the inputs, keeps the valid Gaussians (descriptor `valid` = 1), builds
    /// their kernels and class probabilities, and the KD-tree over their centres.
    ///
    /// Errors: any SPEC.md violation of the inputs, descriptors that do not have one row
    /// per Gaussian ([`TransferError::CountMismatch`]) or whose dimension differs from
    /// the prompts' ([`TransferError::DimMismatch`]), parameters out of their domain.
    pub fn new(
        gaussians: Source<'_, Gaussians>,
        descriptors: Descriptors<'_>,
        classes: &ClassSet,
        params: &Params,
    ) -> Result<GaussianField> {
        params.validate()?;
        let g = gaussians.data;
        g.validate(gaussians.file)?;
        descriptors.validate()?;
        let (rows, tensor) = descriptors.rows();
        if rows != g.len() {
            return Err(TransferError::CountMismatch {
                file: descriptors.file().to_string(),
                tensor,
                found: rows,
                gaussians_file: gaussians.file.to_string(),
                expected: g.len(),
            });
        }
        if descriptors.dim() != classes.dim() {
            return Err(TransferError::DimMismatch {
                file: descriptors.file().to_string(),
                found: descriptors.dim(),
                prompts_file: classes.file().to_string(),
                expected: classes.dim(),
            });
        }
        let ids = valid_ids(g.len(), |i| descriptors.is_valid(i), gaussians.file)?;
        let kernels: Vec<Kernel> = ids
            .par_iter()
            .map(|&i| {
                let i = i as usize;
                Kernel::new(
                    g.means[i],
                    g.log_scales[i],
                    g.rotations[i],
                    g.opacity_logits[i],
                    params.min_scale,
                )
            })
            .collect();
        let c = classes.len();
        let mut probs = vec![0.0f32; ids.len() * c];
        probs.par_chunks_mut(c).zip(ids.par_iter()).for_each_init(
            || (vec![0.0f32; classes.dim()], Vec::new()),
            |(descriptor, logits), (row, &i)| {
                descriptors.read(i as usize, descriptor);
                class_probabilities(descriptor, classes, params.temperature, logits, row);
            },
        );
        let means: Vec<[f32; 3]> = kernels.iter().map(|k| k.mean).collect();
        let tree = (!means.is_empty()).then(|| ImmutableKdTree::new_from_slice(&means));
        let reach_sq = gate_reach_sq(g, &ids, params);
        Ok(GaussianField {
            params: *params,
            kernels,
            ids,
            probs,
            labels: classes.labels().to_vec(),
            class_names: classes.names().to_vec(),
            tree,
            reach_sq,
        })
    }

    /// The parameters.
    pub fn params(&self) -> &Params {
        &self.params
    }

    /// Number of valid Gaussians (the candidates' pool).
    pub fn valid_gaussians(&self) -> usize {
        self.kernels.len()
    }

    /// The label of each class index.
    pub fn class_labels(&self) -> &[i32] {
        &self.labels
    }

    /// The kernel of Gaussian `gaussian` (index in the gaussians file), `None` if invalid.
    pub fn kernel(&self, gaussian: usize) -> Option<&Kernel> {
        self.slot(gaussian).map(|s| &self.kernels[s])
    }

    /// The class probabilities of Gaussian `gaussian`, `None` if invalid.
    pub fn probabilities(&self, gaussian: usize) -> Option<&[f32]> {
        let c = self.labels.len();
        self.slot(gaussian).map(|s| &self.probs[s * c..(s + 1) * c])
    }

    fn slot(&self, gaussian: usize) -> Option<usize> {
        let g = u32::try_from(gaussian).ok()?;
        self.ids.binary_search(&g).ok()
    }

    /// The gated candidates of a point among its K nearest valid Gaussians, in ascending
    /// Gaussian index.
    pub fn candidates(&self, x: [f32; 3]) -> Vec<Candidate> {
        let mut scratch = Vec::new();
        self.shortlist(x, &mut scratch);
        self.describe(&scratch)
    }

    /// The gated candidates of a point among *all* valid Gaussians (the reference).
    pub fn candidates_brute_force(&self, x: [f32; 3]) -> Vec<Candidate> {
        let mut scratch = Vec::new();
        self.scan_all(x, &mut scratch);
        self.describe(&scratch)
    }

    fn describe(&self, slots: &[Slot]) -> Vec<Candidate> {
        slots
            .iter()
            .map(|s| Candidate {
                gaussian: self.ids[s.slot as usize] as usize,
                mahalanobis_sq: s.d2,
                weight: s.weight,
            })
            .collect()
    }

    /// Labels every vertex with the K-nearest shortlist (parallel, deterministic).
    pub fn label_vertices(&self, vertices: &[[f32; 3]]) -> Labelling {
        self.label_all(vertices, false, &|_| {})
    }

    /// [`Self::label_vertices`] calling `progress(n)` after each chunk of n vertices
    /// (from worker threads, in any order).
    pub fn label_vertices_with_progress(
        &self,
        vertices: &[[f32; 3]],
        progress: &(dyn Fn(u64) + Sync),
    ) -> Labelling {
        self.label_all(vertices, false, progress)
    }

    /// Labels every vertex from all valid Gaussians without the tree: the reference the
    /// shortlist is tested against. Equal to [`Self::label_vertices`] bit for bit at every
    /// vertex whose K nearest Gaussians include all gated ones.
    pub fn label_vertices_brute_force(&self, vertices: &[[f32; 3]]) -> Labelling {
        self.label_all(vertices, true, &|_| {})
    }

    fn label_all(
        &self,
        vertices: &[[f32; 3]],
        brute_force: bool,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Labelling {
        let n = vertices.len();
        let mut labels = vec![-1i32; n];
        let mut confidence = vec![0.0f32; n];
        let stats = labels
            .par_chunks_mut(VERTEX_CHUNK)
            .zip(confidence.par_chunks_mut(VERTEX_CHUNK))
            .zip(vertices.par_chunks(VERTEX_CHUNK))
            .map_init(
                || (Vec::new(), vec![0.0f64; self.labels.len()]),
                |(slots, scores), ((labels, confidence), xs)| {
                    let mut stats = Stats::default();
                    for ((l, c), x) in labels.iter_mut().zip(confidence.iter_mut()).zip(xs) {
                        let saturated = if brute_force {
                            self.scan_all(*x, slots);
                            false
                        } else {
                            self.shortlist(*x, slots)
                        };
                        (*l, *c) = self.vote(slots, scores);
                        stats.vertices += 1;
                        stats.labelled += u64::from(*l >= 0);
                        stats.candidates += slots.len() as u64;
                        stats.saturated += u64::from(saturated);
                    }
                    progress(xs.len() as u64);
                    stats
                },
            )
            .reduce(Stats::default, |a, b| Stats {
                vertices: a.vertices + b.vertices,
                labelled: a.labelled + b.labelled,
                candidates: a.candidates + b.candidates,
                saturated: a.saturated + b.saturated,
            });
        Labelling {
            labels,
            confidence,
            stats,
        }
    }

    /// Fills `out` with (slot, weight) of the gated Gaussians among the K nearest, in
    /// ascending slot (= Gaussian index) order; returns whether all K passed the gate.
    fn shortlist(&self, x: [f32; 3], out: &mut Vec<Slot>) -> bool {
        out.clear();
        let (Some(tree), Some(k)) = (&self.tree, NonZeroUsize::new(self.params.k)) else {
            return false;
        };
        let gate = self.params.sigma * self.params.sigma;
        // The K nearest within the reach: beyond it no Gaussian passes the gate, so the
        // gated candidates are those of the plain K nearest, found with less search.
        let nearest = if self.reach_sq.is_finite() {
            tree.nearest_n_within::<SquaredEuclidean>(&x, self.reach_sq, k, false)
        } else {
            tree.nearest_n::<SquaredEuclidean>(&x, k)
        };
        for nb in &nearest {
            let kernel = &self.kernels[nb.item as usize];
            let d2 = kernel.mahalanobis_sq(x);
            if d2 <= gate {
                out.push(Slot {
                    slot: nb.item,
                    d2,
                    weight: kernel.weight(d2),
                });
            }
        }
        // The sum over candidates then runs in Gaussian order, as in the brute force.
        out.sort_unstable_by_key(|c| c.slot);
        nearest.len() == self.params.k && out.len() == nearest.len()
    }

    fn scan_all(&self, x: [f32; 3], out: &mut Vec<Slot>) {
        out.clear();
        let gate = self.params.sigma * self.params.sigma;
        for (s, kernel) in self.kernels.iter().enumerate() {
            let d2 = kernel.mahalanobis_sq(x);
            if d2 <= gate {
                out.push(Slot {
                    slot: s as u32,
                    d2,
                    weight: kernel.weight(d2),
                });
            }
        }
    }

    /// score_c = Σ w p_c over the candidates (f64, in the given order); label = argmax
    /// (ties to the smaller class index); confidence = max score / Σ w.
    fn vote(&self, slots: &[Slot], scores: &mut [f64]) -> (i32, f32) {
        let c = self.labels.len();
        scores.iter_mut().for_each(|s| *s = 0.0);
        let mut total = 0.0f64;
        for s in slots {
            let w = f64::from(s.weight);
            total += w;
            let p = &self.probs[s.slot as usize * c..(s.slot as usize + 1) * c];
            for (score, p) in scores.iter_mut().zip(p) {
                *score += w * f64::from(*p);
            }
        }
        if total.is_nan() || total <= 0.0 {
            return (-1, 0.0);
        }
        let mut best = 0;
        for (i, s) in scores.iter().enumerate().skip(1) {
            if *s > scores[best] {
                best = i;
            }
        }
        let confidence = (scores[best] / total).clamp(0.0, 1.0) as f32;
        (self.labels[best], confidence)
    }

    /// A `vertex_labels` file of a labelling, with the label space and the transfer's
    /// parameters and classes in its metadata.
    pub fn to_file(&self, labelling: &Labelling, label_space: &str) -> VertexLabels {
        let json = |v: serde_json::Value| v.to_string();
        let extra = BTreeMap::from([
            ("label_space".to_string(), label_space.to_string()),
            (
                "class_labels".to_string(),
                json(serde_json::json!(self.labels)),
            ),
            (
                "class_names".to_string(),
                json(serde_json::json!(self.class_names)),
            ),
            ("k".to_string(), self.params.k.to_string()),
            ("sigma".to_string(), self.params.sigma.to_string()),
            (
                "temperature".to_string(),
                self.params.temperature.to_string(),
            ),
            ("min_scale".to_string(), self.params.min_scale.to_string()),
        ]);
        VertexLabels {
            labels: labelling.labels.clone().into(),
            confidence: Some(labelling.confidence.clone().into()),
            extra,
        }
    }
}

/// (σ · the largest standard deviation of any valid Gaussian)², widened for rounding: a
/// Gaussian farther than σ·s_max from x has d > σ, as d >= |x − μ| / s_max.
fn gate_reach_sq(g: &Gaussians, ids: &[u32], params: &Params) -> f32 {
    let largest = ids
        .iter()
        .flat_map(|&i| g.log_scales[i as usize])
        .fold(f32::NEG_INFINITY, f32::max);
    let s = f64::from(largest).exp().max(f64::from(params.min_scale));
    let reach = f64::from(params.sigma) * s;
    let sq = (reach * reach * (1.0 + 1e-4)) as f32;
    if sq.is_finite() {
        sq
    } else {
        f32::INFINITY
    }
}

/// A gated Gaussian of one query: its kernel slot, d² and weight.
#[derive(Debug, Clone, Copy)]
struct Slot {
    slot: u32,
    d2: f32,
    weight: f32,
}

/// Indices of the valid Gaussians, which must fit the tree's u32 items.
fn valid_ids(n: usize, is_valid: impl Fn(usize) -> bool, file: &str) -> Result<Vec<u32>> {
    let mut ids = Vec::new();
    for i in (0..n).filter(|&i| is_valid(i)) {
        ids.push(u32::try_from(i).map_err(|_| TransferError::Parameter {
            name: "gaussians",
            value: format!("{n} Gaussians in {file}"),
            expected: "fewer than 2^32 Gaussians",
        })?);
    }
    Ok(ids)
}

//! The oracle fixture (cargo feature `oracle`, off by default): Gaussians placed on the vertices of a labelled mesh, carrying
//! synthetic CLIP-like features of their vertex's class, so the transfer can be measured
//! on a real mesh (ScanNet) without a real feature pipeline.
//!
//! * **Class prompts** are the seeded random unit prototypes of the NYU40 class names,
//!   `synth::prototype(seed, D, name)` — the same CLIP stand-ins the synthetic scenes use
//!   (no CLIP model is available here). Independent names are nearly orthogonal.
//! * **Gaussians** sit on a seeded subset of the vertices (every vertex at
//!   `fraction = 1`), isotropic with σ = `scale_factor` × the median distance from a
//!   Gaussian centre to its nearest other centre, identity rotation, opacity `opacity`,
//!   colour from the vertex colour.
//! * **Features**: a Gaussian on a vertex of NYU40 class c gets
//!   `normalize(p_c + noise · g)`, `g ~ N(0, I/D)` (so |g| ≈ 1), keyed by (seed, vertex);
//!   vertices with label 0 (unannotated) or outside 1..=40 give invalid Gaussians.
//!
//! [`OracleConfig::exact`] (noise 0, every vertex, σ a quarter of the spacing) must
//! reproduce the ground truth exactly; [`OracleConfig::noisy`] (20% of the vertices,
//! noise 8 in 512-d, σ = the spacing) is the realistic case reported in the README: with
//! noise ν the cosine to the own prompt is ≈ 1/√(1+ν²) = 0.124 and the cosines to other
//! prompts spread with standard deviation ≈ ν/√((1+ν²)·D) = 0.044, a margin-to-spread
//! ratio of 2.8, as for CLIP ViT-B/16 mask embeddings against class-name prompts (correct
//! class ≈ 0.25–0.30, wrong classes ≈ 0.15–0.22 ± 0.03–0.04; the softmax is invariant to
//! the common offset of CLIP cosines, so only the margin and the spread matter).

use profuse_formats::camera::rgb8_to_sh_dc;
use profuse_formats::rng::{SplitMix64, GOLDEN_GAMMA};
use profuse_formats::{Features, FileKind, Gaussians, Mesh, Prompts};

use crate::classes::ClassSet;
use crate::error::{Result, TransferError};
use crate::kernel::dot;
use crate::Source;

use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::SquaredEuclidean;
use rayon::prelude::*;

/// The NYU40 class names; class id `i` (1-based) is `NYU40[i - 1]`.
pub use profuse_formats::label_space::NYU40;

/// How the fixture places Gaussians and makes their features.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OracleConfig {
    /// Share of the vertices that carry a Gaussian, in (0, 1].
    pub fraction: f64,
    /// Seed of the subset, the prototypes and the noise.
    pub seed: u64,
    /// Feature and prompt dimension D.
    pub dim: usize,
    /// Noise norm ν: feature = normalize(p_c + ν g), g ~ N(0, I/D).
    pub noise: f64,
    /// Isotropic σ as a multiple of the median nearest-centre distance.
    pub scale_factor: f64,
    /// Opacity of every Gaussian, in (0, 1).
    pub opacity: f64,
}

impl OracleConfig {
    /// Every vertex, exact features, σ = spacing / 4, opacity 0.95, D = 512.
    pub fn exact() -> OracleConfig {
        OracleConfig {
            fraction: 1.0,
            seed: 0,
            dim: 512,
            noise: 0.0,
            scale_factor: 0.25,
            opacity: 0.95,
        }
    }

    /// 20% of the vertices, noise 8 (CLIP-like, see the module docs), σ = spacing,
    /// opacity 0.95, D = 512.
    pub fn noisy() -> OracleConfig {
        OracleConfig {
            fraction: 0.2,
            noise: 8.0,
            scale_factor: 1.0,
            ..OracleConfig::exact()
        }
    }

    fn validate(&self) -> Result<()> {
        let bad = |name, value: f64, expected| {
            Err(TransferError::Parameter {
                name,
                value: value.to_string(),
                expected,
            })
        };
        if !(self.fraction > 0.0 && self.fraction <= 1.0) {
            return bad("fraction", self.fraction, "a share in (0, 1]");
        }
        if self.dim == 0 {
            return bad("dim", 0.0, "a dimension >= 1");
        }
        if !(self.noise.is_finite() && self.noise >= 0.0) {
            return bad("noise", self.noise, "a finite number >= 0");
        }
        if !(self.scale_factor.is_finite() && self.scale_factor > 0.0) {
            return bad("scale_factor", self.scale_factor, "a finite number > 0");
        }
        if !(self.opacity > 0.0 && self.opacity < 1.0) {
            return bad("opacity", self.opacity, "a number in (0, 1)");
        }
        Ok(())
    }
}

/// Gaussians and features made by [`place_gaussians`].
#[derive(Debug, Clone, PartialEq)]
pub struct OracleScene {
    /// The Gaussians, `class_ids` = their vertex's NYU40 class (−1 for none).
    pub gaussians: Gaussians,
    /// Their features (invalid where the vertex has no NYU40 class).
    pub features: Features,
    /// The vertex each Gaussian sits on, ascending.
    pub vertex_of: Vec<u32>,
    /// Median distance from a Gaussian centre to its nearest other centre.
    pub spacing: f64,
    /// The isotropic standard deviation used.
    pub scale: f64,
}

/// Places Gaussians with synthetic features on a labelled mesh (see the module docs).
pub fn place_gaussians(mesh: Source<'_, Mesh>, config: &OracleConfig) -> Result<OracleScene> {
    config.validate()?;
    let m = mesh.data;
    m.validate(mesh.file)?;
    let Some(labels) = &m.labels else {
        return Err(TransferError::MissingMeshLabels {
            file: mesh.file.to_string(),
        });
    };
    let vertex_of = subset(m.vertices.len(), config.fraction, config.seed);
    let means: Vec<[f32; 3]> = vertex_of.iter().map(|&v| m.vertices[v as usize]).collect();
    let spacing = median_spacing(&means).max(1e-6);
    let scale = config.scale_factor * spacing;
    let n = vertex_of.len();
    let class_of = |v: u32| {
        let l = labels[v as usize];
        (1..=NYU40.len() as u32).contains(&l).then_some(l)
    };
    let logit = (config.opacity / (1.0 - config.opacity)).ln() as f32;
    let sh_dc: Vec<[f32; 3]> = vertex_of
        .iter()
        .map(|&v| {
            let rgb = m.colors.as_ref().map_or([128; 3], |c| c[v as usize]);
            rgb.map(rgb8_to_sh_dc)
        })
        .collect();
    let gaussians = Gaussians {
        means: means.into(),
        log_scales: vec![[scale.ln() as f32; 3]; n].into(),
        rotations: vec![[1.0, 0.0, 0.0, 0.0]; n].into(),
        opacity_logits: vec![logit; n].into(),
        sh_dc: sh_dc.into(),
        sh_degree: 0,
        sh_rest: None,
        class_ids: Some(
            vertex_of
                .iter()
                .map(|&v| class_of(v).map_or(-1, |c| c as i32))
                .collect::<Vec<i32>>()
                .into(),
        ),
        extra: Default::default(),
    };
    let prototypes: Vec<Vec<f32>> = NYU40
        .iter()
        .map(|name| to_f32(&synth::prototype(config.seed, config.dim, name)))
        .collect();
    let d = config.dim;
    let mut features = vec![0.0f32; n * d];
    let mut valid = vec![0u8; n];
    features
        .par_chunks_mut(d)
        .zip(valid.par_iter_mut())
        .zip(vertex_of.par_iter())
        .for_each(|((row, ok), &v)| {
            if let Some(c) = class_of(v) {
                noisy_feature(&prototypes[c as usize - 1], config, v, row);
                *ok = 1;
            }
        });
    Ok(OracleScene {
        gaussians,
        features: Features {
            features: features.into(),
            dim: d,
            valid: valid.into(),
            weight_sum: None,
            extra: Default::default(),
        },
        vertex_of,
        spacing,
        scale,
    })
}

/// A prompts file naming NYU40 classes with their prototypes as embeddings and
/// `class_ids` = the NYU40 ids. Ids outside 1..=40 are skipped.
pub fn nyu40_prompts(class_ids: &[u32], dim: usize, seed: u64) -> Prompts {
    let ids: Vec<u32> = class_ids
        .iter()
        .copied()
        .filter(|c| (1..=NYU40.len() as u32).contains(c))
        .collect();
    let mut embeddings = Vec::with_capacity(ids.len() * dim);
    for &c in &ids {
        embeddings.extend(to_f32(&synth::prototype(seed, dim, NYU40[c as usize - 1])));
    }
    Prompts {
        names: ids
            .iter()
            .map(|&c| NYU40[c as usize - 1].to_string())
            .collect(),
        dim,
        embeddings: embeddings.into(),
        class_ids: Some(ids.iter().map(|&c| c as i32).collect::<Vec<i32>>().into()),
        extra: [("label_space".to_string(), "nyu40".to_string())].into(),
    }
}

/// Share of the valid Gaussians whose class is one of `classes` and whose most similar
/// class prompt (the per-Gaussian argmax, before any spatial vote) is their own class.
pub fn descriptor_accuracy(scene: &OracleScene, classes: &ClassSet) -> f64 {
    let Some(truth) = &scene.gaussians.class_ids else {
        return 0.0;
    };
    let d = scene.features.dim;
    let feats = &scene.features.features;
    let (hits, total) = (0..scene.features.len())
        .into_par_iter()
        .filter(|&g| scene.features.valid[g] == 1 && classes.labels().contains(&truth[g]))
        .map_init(
            || vec![0.0f32; d],
            |row, g| {
                feats.read_into(g * d, row);
                let best = (0..classes.prompts())
                    .map(|q| (dot(row, classes.prompt_embedding(q)), q))
                    .fold((f32::NEG_INFINITY, 0), |a, b| if b.0 > a.0 { b } else { a });
                let label = classes.labels()[classes.prompt_class(best.1)];
                (u64::from(label == truth[g]), 1u64)
            },
        )
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    hits as f64 / total.max(1) as f64
}

/// `normalize(p + noise · g)` with g ~ N(0, I/D) keyed by (seed, vertex).
fn noisy_feature(prototype: &[f32], config: &OracleConfig, vertex: u32, out: &mut [f32]) {
    let mut rng = SplitMix::new(config.seed, u64::from(vertex));
    let s = config.noise / (config.dim as f64).sqrt();
    let v: Vec<f64> = prototype
        .iter()
        .map(|p| {
            let g = if config.noise > 0.0 {
                rng.normal()
            } else {
                0.0
            };
            f64::from(*p) + s * g
        })
        .collect();
    let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt();
    for (o, x) in out.iter_mut().zip(&v) {
        *o = (x / norm) as f32;
    }
}

/// The `round(fraction · n)` vertices (at least one when n > 0) with the smallest seeded
/// hash, in ascending order: a deterministic uniform subset.
fn subset(n: usize, fraction: f64, seed: u64) -> Vec<u32> {
    if fraction >= 1.0 {
        return (0..n as u32).collect();
    }
    let m = ((fraction * n as f64).round() as usize).clamp(usize::from(n > 0), n);
    let mut keyed: Vec<(u64, u32)> = (0..n as u32)
        .map(|i| (SplitMix::new(seed, u64::from(i)).next_u64(), i))
        .collect();
    if m < n {
        keyed.select_nth_unstable(m);
    }
    let mut chosen: Vec<u32> = keyed[..m].iter().map(|k| k.1).collect();
    chosen.sort_unstable();
    chosen
}

/// Median over points of the distance to the nearest other point (1 for fewer than two).
fn median_spacing(points: &[[f32; 3]]) -> f64 {
    if points.len() < 2 {
        return 1.0;
    }
    let tree: ImmutableKdTree<f32, u32, 3, 32> = ImmutableKdTree::new_from_slice(points);
    let two = std::num::NonZeroUsize::MIN.saturating_add(1);
    let mut d: Vec<f64> = points
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            tree.nearest_n::<SquaredEuclidean>(p, two)
                .iter()
                .find(|nb| nb.item as usize != i)
                .map_or(0.0, |nb| f64::from(nb.distance).sqrt())
        })
        .collect();
    let mid = d.len() / 2;
    d.select_nth_unstable_by(mid, f64::total_cmp);
    d[mid]
}

fn to_f32(v: &[f64]) -> Vec<f32> {
    v.iter().map(|x| *x as f32).collect()
}

/// SplitMix64 stream keyed by (seed, index), with Box–Muller normals: no third-party RNG,
/// so the fixture never changes with a dependency version.
struct SplitMix {
    stream: SplitMix64,
    spare: Option<f64>,
}

impl SplitMix {
    fn new(seed: u64, index: u64) -> SplitMix {
        let start = SplitMix64::new(seed ^ 0x5654_5846_4552_0000).next_u64(); // "VTXFER"
        let keyed = SplitMix64::new(start ^ index.wrapping_mul(GOLDEN_GAMMA)).next_u64();
        SplitMix {
            stream: SplitMix64::new(keyed),
            spare: None,
        }
    }

    fn next_u64(&mut self) -> u64 {
        self.stream.next_u64()
    }

    /// Uniform in (0, 1].
    fn unit_open(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 1.0) * (1.0 / (1u64 << 53) as f64)
    }

    fn normal(&mut self) -> f64 {
        if let Some(z) = self.spare.take() {
            return z;
        }
        let r = (-2.0 * self.unit_open().ln()).sqrt();
        let t = std::f64::consts::TAU * self.unit_open();
        self.spare = Some(r * t.sin());
        r * t.cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subset_is_deterministic_sorted_and_of_the_requested_size() {
        let a = subset(1000, 0.2, 7);
        assert_eq!(a.len(), 200);
        assert!(a.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(a, subset(1000, 0.2, 7));
        assert_ne!(a, subset(1000, 0.2, 8));
        assert_eq!(subset(3, 0.01, 0).len(), 1);
        assert_eq!(subset(5, 1.0, 0), vec![0, 1, 2, 3, 4]);
    }

    #[test]
    fn normals_have_unit_variance() {
        let mut rng = SplitMix::new(1, 2);
        let xs: Vec<f64> = (0..200_000).map(|_| rng.normal()).collect();
        let mean = xs.iter().sum::<f64>() / xs.len() as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / xs.len() as f64;
        assert!(
            mean.abs() < 0.01 && (var - 1.0).abs() < 0.02,
            "{mean} {var}"
        );
    }

    #[test]
    fn median_spacing_of_a_grid_is_its_step() {
        let pts: Vec<[f32; 3]> = (0..100)
            .map(|i| [(i % 10) as f32 * 0.5, (i / 10) as f32 * 0.5, 0.0])
            .collect();
        assert!((median_spacing(&pts) - 0.5).abs() < 1e-6);
    }
}

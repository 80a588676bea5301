//! 3DGS adaptive density control (Kerbl et al. 2023, `densify_and_prune`): Gaussians whose
//! mean screen-space position gradient is large are under-reconstructing. Small ones are
//! cloned (the copy and the original then drift apart along their own gradients), large
//! ones are split into two samples of their own distribution at 1/1.6 of the scale; nearly
//! transparent ones are removed.
//!
//! The correspondence-initialised Gaussians of EDGS start dense where matches were found,
//! but plain walls and fur have none: there, without densification, a fixed set of SH-0
//! Gaussians underfits even the training views (issue 18's fox: training PSNR 23 dB).

use profuse_formats::camera;
use profuse_formats::rng::SplitMix64;

use crate::params::{rest_coeffs, Params};

/// When and how to densify (3DGS defaults where 3DGS has them).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct DensifyConfig {
    /// Last iteration that densifies (0: never densify).
    pub until: usize,
    /// First iteration that densifies (3DGS: 500).
    pub from: usize,
    /// Densify every this many iterations (3DGS: 100).
    pub every: usize,
    /// Threshold on the mean norm of the positional gradient in NDC units, i.e. the pixel
    /// gradient times (width / 2, height / 2) (3DGS: 0.0002).
    pub grad_threshold: f64,
    /// Gaussians whose largest scale is at most this share of the scene extent are cloned,
    /// larger ones split (3DGS: 0.01).
    pub percent_dense: f64,
    /// Never grow beyond this many Gaussians (0: no cap); above it only the candidates with
    /// the largest gradients are densified.
    pub max_gaussians: usize,
}

impl Default for DensifyConfig {
    fn default() -> Self {
        DensifyConfig {
            until: 0,
            from: 500,
            every: 100,
            grad_threshold: 0.0002,
            percent_dense: 0.01,
            max_gaussians: 0,
        }
    }
}

impl DensifyConfig {
    /// Whether iteration `step` (1-based, after its update) densifies.
    pub fn due(&self, step: usize) -> bool {
        self.until > 0
            && self.every > 0
            && step >= self.from
            && step <= self.until
            && step.is_multiple_of(self.every)
    }

    /// Whether the positional gradients of iteration `step` (1-based) are still needed.
    pub fn accumulating(&self, step: usize) -> bool {
        self.until > 0 && self.every > 0 && step <= self.until
    }
}

/// Per Gaussian, the summed norm of its NDC positional gradient and the number of views it
/// was drawn in since the last densification (3DGS `xyz_gradient_accum`, `denom`).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct GradStats {
    /// Summed gradient norms.
    pub sum: Vec<f64>,
    /// Views each Gaussian was drawn in.
    pub count: Vec<u32>,
}

impl GradStats {
    /// Zeroed statistics for `n` Gaussians.
    pub fn new(n: usize) -> Self {
        GradStats {
            sum: vec![0.0; n],
            count: vec![0; n],
        }
    }

    /// Adds one view: `drawn` yields (Gaussian id, pixel gradient of its centre) for every
    /// Gaussian the view drew (zero gradients included, as 3DGS's visibility filter).
    pub fn add_view(
        &mut self,
        width: usize,
        height: usize,
        drawn: impl Iterator<Item = (u32, [f64; 2])>,
    ) {
        let (hx, hy) = (0.5 * width as f64, 0.5 * height as f64);
        for (id, [gu, gv]) in drawn {
            let i = id as usize;
            self.sum[i] += (gu * hx).hypot(gv * hy);
            self.count[i] += 1;
        }
    }

    /// The mean gradient norm of Gaussian `i` (0 when it was never drawn).
    pub fn mean(&self, i: usize) -> f64 {
        match self.count.get(i) {
            Some(&c) if c > 0 => self.sum[i] / f64::from(c),
            _ => 0.0,
        }
    }
}

/// A new Gaussian: a copy of `parent` with its own mean and log-scales.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Child {
    /// Index of the Gaussian it copies (before [`Plan::keep`] is applied).
    pub parent: u32,
    /// Its mean.
    pub mean: [f32; 3],
    /// Its log-scales.
    pub log_scale: [f32; 3],
}

/// The outcome of one densification: which Gaussians stay (ascending) and which are added
/// after them.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Plan {
    /// Gaussians kept, ascending.
    pub keep: Vec<u32>,
    /// Gaussians appended after the kept ones, in order.
    pub children: Vec<Child>,
    /// Candidates cloned.
    pub cloned: usize,
    /// Candidates split (each replaced by two children).
    pub split: usize,
    /// Gaussians removed for low opacity.
    pub pruned: usize,
}

/// 3DGS's split factor: each of the two samples gets the parent's scales / (0.8 · 2).
const SPLIT_SCALE: f64 = 1.0 / 1.6;

/// Plans one densification of `p` from `stats`: candidates have a mean NDC gradient at or
/// above the threshold (the largest first when `max_gaussians` caps the growth) and an
/// opacity at or above `prune_opacity`; a candidate whose largest scale is at most
/// `percent_dense · extent` is cloned in place, a larger one is replaced by two samples of
/// N(mean, R S² Rᵀ) with scales divided by 1.6 (drawn from `rng` in index order); every
/// Gaussian with opacity below `prune_opacity` is removed.
pub fn plan(
    p: &Params,
    stats: &GradStats,
    cfg: &DensifyConfig,
    extent: f64,
    prune_opacity: f64,
    rng: &mut SplitMix64,
) -> Plan {
    let n = p.len();
    let mut candidates: Vec<u32> = (0..n as u32)
        .filter(|&i| {
            let i = i as usize;
            stats.mean(i) >= cfg.grad_threshold && p.opacity(i) >= prune_opacity
        })
        .collect();
    if cfg.max_gaussians > 0 {
        let room = cfg.max_gaussians.saturating_sub(n);
        if candidates.len() > room {
            candidates.sort_by(|&a, &b| {
                let (ga, gb) = (stats.mean(a as usize), stats.mean(b as usize));
                gb.total_cmp(&ga).then(a.cmp(&b))
            });
            candidates.truncate(room);
            candidates.sort_unstable();
        }
    }
    let mut out = Plan::default();
    let mut removed = vec![false; n];
    let big = cfg.percent_dense * extent;
    for &c in &candidates {
        let i = c as usize;
        let ls = p.log_scales[i];
        let largest = ls.iter().map(|&l| f64::from(l).exp()).fold(0.0, f64::max);
        if largest <= big {
            out.cloned += 1;
            out.children.push(Child {
                parent: c,
                mean: p.means[i],
                log_scale: ls,
            });
            continue;
        }
        out.split += 1;
        removed[i] = true;
        // A zero quaternion cannot reach here (splat-raster's validation rejects it and
        // Adam keeps it off zero in practice); fall back to the identity if it did.
        let rot = camera::quaternion_to_rotation(p.rotations[i].map(f64::from)).unwrap_or([
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ]);
        let child_scale = ls.map(|l| (f64::from(l) + SPLIT_SCALE.ln()) as f32);
        for _ in 0..2 {
            let z = [normal(rng), normal(rng), normal(rng)];
            let local: [f64; 3] = std::array::from_fn(|a| z[a] * f64::from(ls[a]).exp());
            let mean: [f32; 3] = std::array::from_fn(|r| {
                let off = rot[r][0] * local[0] + rot[r][1] * local[1] + rot[r][2] * local[2];
                (f64::from(p.means[i][r]) + off) as f32
            });
            out.children.push(Child {
                parent: c,
                mean,
                log_scale: child_scale,
            });
        }
    }
    for (i, r) in removed.iter_mut().enumerate() {
        if !*r && p.opacity(i) < prune_opacity {
            *r = true;
            out.pruned += 1;
        }
    }
    out.keep = (0..n as u32).filter(|&i| !removed[i as usize]).collect();
    out
}

/// A standard normal sample (Box–Muller, one of the pair; 1 − u keeps the log finite).
fn normal(rng: &mut SplitMix64) -> f64 {
    let u = 1.0 - rng.unit();
    let v = rng.unit();
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
}

/// Applies `plan` to `p`: the kept Gaussians in order, then the children (copies of their
/// parents with their own mean and log-scales).
pub fn apply(p: &Params, plan: &Plan) -> Params {
    let mut out = p.subset(&plan.keep);
    let per = rest_coeffs(p.sh_degree) * 3;
    for c in &plan.children {
        let i = c.parent as usize;
        out.means.push(c.mean);
        out.log_scales.push(c.log_scale);
        out.rotations.push(p.rotations[i]);
        out.opacity_logits.push(p.opacity_logits[i]);
        out.sh_dc.push(p.sh_dc[i]);
        if per > 0 {
            out.sh_rest.extend_from_slice(p.rest(i));
        }
    }
    out
}

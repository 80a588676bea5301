//! The optimisation: one view per iteration in a seeded order, the 3DGS loss, Adam with the
//! 3DGS learning rates and exponential position decay, optional 3DGS densification
//! ([`crate::densify`]) and opacity pruning.

use profuse_formats::rng::SplitMix64;
use rayon::prelude::*;
use splat_raster::ViewCamera;

use crate::densify::{self, DensifyConfig, GradStats};
use crate::error::{RefineError, Result};
use crate::images::Target;
use crate::loss::{loss_and_grad, psnr};
use crate::params::{rest_coeffs, Grads, Params};
use crate::raster::{backward, forward, ViewState};

/// Learning rates (INRIA 3DGS `OptimizationParams` defaults; the position rate is
/// multiplied by the scene extent and decays exponentially from `position_init` to
/// `position_final` over the run).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct LearningRates {
    /// Initial position rate (× extent).
    pub position_init: f64,
    /// Final position rate (× extent).
    pub position_final: f64,
    /// SH DC rate.
    pub sh_dc: f64,
    /// Higher SH rate (3DGS: DC rate / 20).
    pub sh_rest: f64,
    /// Opacity-logit rate.
    pub opacity: f64,
    /// Log-scale rate.
    pub scaling: f64,
    /// Quaternion rate.
    pub rotation: f64,
}

impl Default for LearningRates {
    fn default() -> Self {
        LearningRates {
            position_init: 1.6e-4,
            position_final: 1.6e-6,
            sh_dc: 2.5e-3,
            sh_rest: 2.5e-3 / 20.0,
            opacity: 0.05,
            scaling: 5e-3,
            rotation: 1e-3,
        }
    }
}

/// Settings of a refinement.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Config {
    /// Iterations (one view each).
    pub iterations: usize,
    /// Seed of the view order.
    pub seed: u64,
    /// Background colour behind the Gaussians.
    pub background: [f32; 3],
    /// Learning rates.
    pub lr: LearningRates,
    /// Remove Gaussians whose opacity is below `prune_opacity` every this many iterations
    /// (0: never).
    pub prune_every: usize,
    /// Opacity threshold of the pruning and of the densification's pruning (3DGS: 0.005).
    pub prune_opacity: f64,
    /// Adaptive density control (off unless `densify.until > 0`).
    pub densify: DensifyConfig,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            iterations: 2000,
            seed: 0,
            background: [0.0; 3],
            lr: LearningRates::default(),
            prune_every: 0,
            prune_opacity: 0.005,
            densify: DensifyConfig::default(),
        }
    }
}

/// 3DGS's `getNerfppNorm` radius: 1.1 × the largest distance of a camera centre from
/// their mean (the scale of the position learning rate).
pub fn cameras_extent(cams: &[ViewCamera]) -> f64 {
    let centres: Vec<[f64; 3]> = cams.iter().map(|c| c.center()).collect();
    let n = centres.len().max(1) as f64;
    let mean: [f64; 3] = std::array::from_fn(|a| centres.iter().map(|c| c[a]).sum::<f64>() / n);
    let far = centres
        .iter()
        .map(|c| (0..3).map(|a| (c[a] - mean[a]).powi(2)).sum::<f64>().sqrt())
        .fold(0.0, f64::max);
    1.1 * far.max(1e-6)
}

/// Adam moments of one tensor.
#[derive(Debug, Clone, Default)]
struct Moments {
    m: Vec<f32>,
    v: Vec<f32>,
}

impl Moments {
    fn new(n: usize) -> Self {
        Moments {
            m: vec![0.0; n],
            v: vec![0.0; n],
        }
    }

    /// One Adam step (β = 0.9, 0.999, ε = 1e-15 as 3DGS) of `p` along `g` at step `t`.
    fn step(&mut self, p: &mut [f32], g: &[f64], lr: f64, t: i32) {
        const B1: f64 = 0.9;
        const B2: f64 = 0.999;
        let c1 = 1.0 - B1.powi(t);
        let c2 = (1.0 - B2.powi(t)).sqrt();
        p.par_iter_mut()
            .zip(self.m.par_iter_mut())
            .zip(self.v.par_iter_mut())
            .zip(g.par_iter())
            .for_each(|(((p, m), v), &g)| {
                let mm = B1 * f64::from(*m) + (1.0 - B1) * g;
                let vv = B2 * f64::from(*v) + (1.0 - B2) * g * g;
                *m = mm as f32;
                *v = vv as f32;
                let upd = lr / c1 * mm / (vv.sqrt() / c2 + 1e-15);
                *p = (f64::from(*p) - upd) as f32;
            });
    }

    /// Keeps the entries of the Gaussians in `keep` (`per` values each), then appends
    /// zero moments for `added` new Gaussians (3DGS: new tensors start with fresh state).
    fn retain(&mut self, keep: &[u32], per: usize, added: usize) {
        let pick = |x: &Vec<f32>| {
            let mut out: Vec<f32> = keep
                .iter()
                .flat_map(|&i| x[i as usize * per..(i as usize + 1) * per].iter().copied())
                .collect();
            out.resize(out.len() + added * per, 0.0);
            out
        };
        self.m = pick(&self.m);
        self.v = pick(&self.v);
    }
}

/// Statistics of one iteration.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct StepStats {
    /// Iteration number, from 1.
    pub iteration: usize,
    /// The view trained on.
    pub view: usize,
    /// Its loss.
    pub loss: f64,
    /// Its PSNR (dB) against the target.
    pub psnr: f64,
    /// Gaussians now.
    pub gaussians: usize,
    /// Whether this iteration densified.
    pub densified: bool,
}

/// A refinement in progress.
#[derive(Debug)]
pub struct Trainer {
    params: Params,
    /// Input index of every current Gaussian (pruning removes entries; a Gaussian made by
    /// densification has its parent's).
    kept: Vec<u32>,
    /// Positional gradient statistics since the last densification.
    grad_stats: GradStats,
    /// Draws the split samples (separate from the view order, so that densification
    /// settings do not change which views are visited).
    densify_rng: SplitMix64,
    cams: Vec<(usize, ViewCamera)>,
    targets: Vec<Target>,
    config: Config,
    extent: f64,
    moments: [Moments; 6],
    grads: Grads,
    state: ViewState,
    dl: Vec<f32>,
    order: Vec<usize>,
    rng: SplitMix64,
    step: usize,
}

impl Trainer {
    /// A trainer over `views`: (view id, camera at the training size, its target). The
    /// position learning rate is scaled by [`cameras_extent`] of these cameras.
    pub fn new(
        params: Params,
        views: Vec<(usize, ViewCamera, Target)>,
        config: Config,
    ) -> Result<Self> {
        if views.is_empty() {
            return Err(RefineError::NoViews {
                reason: "every view was excluded".into(),
            });
        }
        if config.iterations == 0 {
            return Err(RefineError::Config {
                name: "iterations",
                value: "0".into(),
                expected: "at least 1",
            });
        }
        for (v, cam, t) in &views {
            if [cam.width, cam.height] != [t.width, t.height] {
                return Err(RefineError::NoViews {
                    reason: format!("view {v}: camera and target sizes differ"),
                });
            }
        }
        let (cams, targets): (Vec<_>, Vec<_>) =
            views.into_iter().map(|(v, c, t)| ((v, c), t)).unzip();
        let only: Vec<ViewCamera> = cams.iter().map(|(_, c)| *c).collect();
        let n = params.len();
        let moments = [
            Moments::new(n * 3),
            Moments::new(n * 3),
            Moments::new(n * 4),
            Moments::new(n),
            Moments::new(n * 3),
            Moments::new(params.sh_rest.len()),
        ];
        Ok(Trainer {
            grads: Grads::zeros(&params),
            kept: (0..n as u32).collect(),
            grad_stats: GradStats::new(if config.densify.until > 0 { n } else { 0 }),
            densify_rng: SplitMix64::new(config.seed ^ 0xD3A5_1F7E_0000_0001),
            params,
            extent: cameras_extent(&only),
            cams,
            targets,
            rng: SplitMix64::new(config.seed),
            config,
            moments,
            state: ViewState::default(),
            dl: Vec::new(),
            order: Vec::new(),
            step: 0,
        })
    }

    /// The current parameters.
    pub fn params(&self) -> &Params {
        &self.params
    }

    /// Input index of every current Gaussian.
    pub fn kept(&self) -> &[u32] {
        &self.kept
    }

    /// Iterations done.
    pub fn iteration(&self) -> usize {
        self.step
    }

    /// Scene extent scaling the position learning rate.
    pub fn extent(&self) -> f64 {
        self.extent
    }

    /// The position learning rate at iteration `t` (0-based) of `total`.
    pub fn position_lr(&self, t: usize) -> f64 {
        let lr = &self.config.lr;
        let f = (t as f64 / self.config.iterations.max(1) as f64).min(1.0);
        let ln = lr.position_init.ln() * (1.0 - f) + lr.position_final.ln() * f;
        ln.exp() * self.extent
    }

    /// The next view of the seeded order: a fresh shuffle of all views each epoch.
    fn next_view(&mut self) -> usize {
        if self.order.is_empty() {
            self.order = (0..self.cams.len()).collect();
            for i in (1..self.order.len()).rev() {
                let j = self.rng.below(i + 1);
                self.order.swap(i, j);
            }
        }
        self.order.pop().unwrap_or(0)
    }

    /// One iteration: render a view, take the loss and its gradient, one Adam step.
    pub fn step(&mut self) -> StepStats {
        let k = self.next_view();
        let (view, cam) = self.cams[k];
        let bg = self.config.background;
        forward(&self.params, &cam, bg, &mut self.state);
        let tgt = &self.targets[k];
        let (w, h) = (cam.width as usize, cam.height as usize);
        let out = loss_and_grad(self.state.color(), &tgt.rgb, w, h, &mut self.dl);
        self.grads.clear();
        backward(
            &self.params,
            &cam,
            bg,
            &mut self.state,
            &self.dl,
            &mut self.grads,
        );
        if self.config.densify.accumulating(self.step + 1) {
            self.grad_stats
                .add_view(w, h, self.state.drawn_center_grads());
        }
        self.apply();
        self.step += 1;
        let densified = self.config.densify.due(self.step) && self.step < self.config.iterations;
        if densified {
            self.densify();
        }
        let every = self.config.prune_every;
        if every > 0 && self.step.is_multiple_of(every) && self.step < self.config.iterations {
            self.prune();
        }
        StepStats {
            iteration: self.step,
            view,
            loss: out.loss,
            psnr: psnr(out.mse),
            gaussians: self.params.len(),
            densified,
        }
    }

    /// One 3DGS densification from the gradients gathered since the last one: clone or
    /// split the under-reconstructing Gaussians, drop the nearly transparent ones, restart
    /// the statistics.
    pub fn densify(&mut self) -> densify::Plan {
        let plan = densify::plan(
            &self.params,
            &self.grad_stats,
            &self.config.densify,
            self.extent,
            self.config.prune_opacity,
            &mut self.densify_rng,
        );
        let added = plan.children.len();
        let per = self.values_per_gaussian();
        for (m, p) in self.moments.iter_mut().zip(per) {
            m.retain(&plan.keep, p, added);
        }
        self.params = densify::apply(&self.params, &plan);
        let kept = &self.kept;
        self.kept = plan
            .keep
            .iter()
            .map(|&i| kept[i as usize])
            .chain(plan.children.iter().map(|c| kept[c.parent as usize]))
            .collect();
        self.grads = Grads::zeros(&self.params);
        self.grad_stats = GradStats::new(self.params.len());
        plan
    }

    fn apply(&mut self) {
        let t = (self.step + 1) as i32;
        let lr = self.config.lr;
        let pos = self.position_lr(self.step);
        let (p, g, m) = (&mut self.params, &self.grads, &mut self.moments);
        m[0].step(p.means.as_flattened_mut(), g.means.as_flattened(), pos, t);
        m[1].step(
            p.log_scales.as_flattened_mut(),
            g.log_scales.as_flattened(),
            lr.scaling,
            t,
        );
        m[2].step(
            p.rotations.as_flattened_mut(),
            g.rotations.as_flattened(),
            lr.rotation,
            t,
        );
        m[3].step(&mut p.opacity_logits, &g.opacity_logits, lr.opacity, t);
        m[4].step(
            p.sh_dc.as_flattened_mut(),
            g.sh_dc.as_flattened(),
            lr.sh_dc,
            t,
        );
        m[5].step(&mut p.sh_rest, &g.sh_rest, lr.sh_rest, t);
    }

    /// Values per Gaussian of each Adam-moment tensor (means, log-scales, quaternions,
    /// opacity logits, SH DC, higher SH).
    fn values_per_gaussian(&self) -> [usize; 6] {
        [3, 3, 4, 1, 3, rest_coeffs(self.params.sh_degree) * 3]
    }

    /// Drops Gaussians below the opacity threshold (and their Adam moments).
    pub fn prune(&mut self) {
        let thr = self.config.prune_opacity;
        let keep: Vec<u32> = (0..self.params.len() as u32)
            .filter(|&i| self.params.opacity(i as usize) >= thr)
            .collect();
        if keep.len() == self.params.len() {
            return;
        }
        let per = self.values_per_gaussian();
        for (m, p) in self.moments.iter_mut().zip(per) {
            m.retain(&keep, p, 0);
        }
        self.params.retain(&keep);
        self.kept = keep.iter().map(|&i| self.kept[i as usize]).collect();
        self.grads = Grads::zeros(&self.params);
        if !self.grad_stats.sum.is_empty() {
            let stats = &self.grad_stats;
            self.grad_stats = GradStats {
                sum: keep.iter().map(|&i| stats.sum[i as usize]).collect(),
                count: keep.iter().map(|&i| stats.count[i as usize]).collect(),
            };
        }
    }

    /// Renders training view index `k` (into the trainer's cameras) and returns the loss
    /// statistics against its target without changing anything.
    pub fn evaluate(&mut self, k: usize) -> StepStats {
        let (view, cam) = self.cams[k];
        forward(&self.params, &cam, self.config.background, &mut self.state);
        let tgt = &self.targets[k];
        let out = loss_and_grad(
            self.state.color(),
            &tgt.rgb,
            cam.width as usize,
            cam.height as usize,
            &mut self.dl,
        );
        StepStats {
            iteration: self.step,
            view,
            loss: out.loss,
            psnr: psnr(out.mse),
            gaussians: self.params.len(),
            densified: false,
        }
    }

    /// Number of training views.
    pub fn views(&self) -> usize {
        self.cams.len()
    }
}

//! The refinement as a file-level job: read Gaussians, cameras and photos, run the
//! optimisation, write the refined Gaussians (atomically; also every `save_every`
//! iterations) and report. The `gs-refine` tool and the pipeline's `gs-refine` stage
//! both run this, so they print the same report.

use std::path::{Path, PathBuf};
use std::time::Instant;

use profuse_formats::{Cameras, FileKind, Gaussians};
use serde::{Deserialize, Serialize};

use crate::views::load_views;
use crate::{Config, DensifyConfig, Params, RefineError, Result, Trainer};

/// The parameters of a refinement (the pipeline's `[gs_refine]` section).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct JobParams {
    /// Iterations, one view each; 0: no refinement (the pipeline skips the stage, its
    /// default, so that runs without photos of real scenes stay fast).
    pub iterations: usize,
    /// Training image scale in (0, 1] (intrinsics rescaled, photos area-averaged).
    pub scale: f64,
    /// Seed of the view order.
    pub seed: u64,
    /// Remove Gaussians with opacity below `prune_opacity` every this many iterations
    /// (0: never).
    pub prune_every: usize,
    /// Opacity threshold of the pruning (3DGS: 0.005).
    pub prune_opacity: f64,
    /// Raise the SH degree to this before training (new coefficients start at zero; never
    /// lowers the input's degree).
    pub sh_degree: usize,
    /// Last iteration that densifies (0: no densification).
    pub densify_until: usize,
    /// First iteration that densifies.
    pub densify_from: usize,
    /// Densify every this many iterations.
    pub densify_every: usize,
    /// Mean NDC positional gradient at which a Gaussian is densified.
    pub densify_grad: f64,
    /// Largest scale (share of the scene extent) up to which a Gaussian is cloned, not split.
    pub percent_dense: f64,
    /// Cap on the number of Gaussians densification may reach (0: none).
    pub max_gaussians: usize,
}

impl Default for JobParams {
    fn default() -> Self {
        let c = Config::default();
        JobParams {
            iterations: 0,
            scale: 0.5,
            seed: c.seed,
            prune_every: c.prune_every,
            prune_opacity: c.prune_opacity,
            sh_degree: 0,
            densify_until: c.densify.until,
            densify_from: c.densify.from,
            densify_every: c.densify.every,
            densify_grad: c.densify.grad_threshold,
            percent_dense: c.densify.percent_dense,
            max_gaussians: c.densify.max_gaussians,
        }
    }
}

impl JobParams {
    /// The optimiser's settings these parameters ask for.
    pub fn config(&self) -> Config {
        Config {
            iterations: self.iterations,
            seed: self.seed,
            prune_every: self.prune_every,
            prune_opacity: self.prune_opacity,
            densify: DensifyConfig {
                until: self.densify_until,
                from: self.densify_from,
                every: self.densify_every,
                grad_threshold: self.densify_grad,
                percent_dense: self.percent_dense,
                max_gaussians: self.max_gaussians,
            },
            ..Config::default()
        }
    }
}

/// The files of one run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Job {
    /// Gaussians to refine (profuse.gaussians).
    pub gaussians: PathBuf,
    /// Cameras (profuse.cameras), pinhole.
    pub cameras: PathBuf,
    /// Folder the cameras' image names are relative to (or holding the images).
    pub images: PathBuf,
    /// The refined Gaussians file to write.
    pub out: PathBuf,
    /// Views left out of training (e.g. held-out test views).
    pub exclude: Vec<usize>,
    /// Write the current Gaussians to `out` every this many iterations (0: only at the end).
    pub save_every: usize,
}

/// What a run did: the same object from the tool (stdout) and the pipeline.
#[derive(Debug, Clone, Serialize)]
pub struct JobReport {
    /// The refined Gaussians file (non-UTF-8 bytes shown as U+FFFD in JSON).
    #[serde(serialize_with = "profuse_formats::output::lossy_path::one")]
    pub out: PathBuf,
    /// Gaussians read.
    pub gaussians_in: usize,
    /// Gaussians written (fewer after pruning, more after densification).
    pub gaussians_out: usize,
    /// SH degree written.
    pub sh_degree: usize,
    /// Iterations run.
    pub iterations: usize,
    /// Training image scale.
    pub scale: f64,
    /// Training image width.
    pub width: u32,
    /// Training image height.
    pub height: u32,
    /// Views trained on.
    pub train_views: usize,
    /// Views left out.
    pub excluded: Vec<usize>,
    /// Loss of the first iteration.
    pub first_loss: Option<f64>,
    /// Exponential moving average (0.95) of the loss at the end.
    pub final_loss_ema: Option<f64>,
    /// Exponential moving average (0.95) of the training PSNR at the end.
    pub final_psnr_ema: Option<f64>,
    /// Mean training loss of each consecutive window of `loss_window` iterations (the
    /// last window may be shorter): the smoothed loss curve.
    pub loss_windows: Vec<f64>,
    /// Iterations per entry of `loss_windows` (iterations / 20, at least 1).
    pub loss_window: usize,
    /// The scene extent that scales the position learning rate.
    pub extent: f64,
    /// Seconds, reading and writing included.
    pub seconds: f64,
    /// The optimiser's settings.
    pub config: Config,
}

/// Progress of a run: iteration, smoothed loss, smoothed PSNR.
pub type OnStep<'a> = &'a mut dyn FnMut(usize, f64, f64);

/// Runs a job; `on_step` is called after every iteration.
pub fn run(job: &Job, params: &JobParams, on_step: OnStep<'_>) -> Result<JobReport> {
    let t0 = Instant::now();
    let template = Gaussians::read(&job.gaussians)?;
    let cams = Cameras::read(&job.cameras)?;
    let views = load_views(&cams, &job.images, params.scale, &job.exclude)?;
    let (width, height) = views.first().map_or((0, 0), |v| (v.1.width, v.1.height));
    let config = params.config();
    let train_views = views.len();
    let mut start = Params::from_gaussians(&template)?;
    start.raise_sh_degree(params.sh_degree)?;
    let mut tr = Trainer::new(start, views, config.clone())?;
    let (mut ema_loss, mut ema_psnr, mut first_loss) = (None::<f64>, None::<f64>, None);
    let loss_window = (params.iterations / 20).max(1);
    let (mut loss_windows, mut window_sum) = (Vec::new(), 0.0);
    for it in 1..=params.iterations {
        let s = tr.step();
        first_loss.get_or_insert(s.loss);
        window_sum += s.loss;
        if it % loss_window == 0 || it == params.iterations {
            let len = (it - 1) % loss_window + 1;
            loss_windows.push(window_sum / len as f64);
            window_sum = 0.0;
        }
        let ema = |e: Option<f64>, v: f64| Some(e.map_or(v, |e| 0.95 * e + 0.05 * v));
        ema_loss = ema(ema_loss, s.loss);
        ema_psnr = ema(ema_psnr, s.psnr);
        on_step(it, ema_loss.unwrap_or(0.0), ema_psnr.unwrap_or(0.0));
        if job.save_every > 0 && it % job.save_every == 0 && it < params.iterations {
            save(&tr, &template, &job.out)?;
        }
    }
    let gaussians_out = save(&tr, &template, &job.out)?;
    let sh_degree = tr.params().sh_degree;
    Ok(JobReport {
        out: job.out.clone(),
        gaussians_in: template.len(),
        gaussians_out,
        sh_degree,
        iterations: params.iterations,
        scale: params.scale,
        width,
        height,
        train_views,
        excluded: job.exclude.clone(),
        first_loss,
        final_loss_ema: ema_loss,
        final_psnr_ema: ema_psnr,
        loss_windows,
        loss_window,
        extent: tr.extent(),
        seconds: t0.elapsed().as_secs_f64(),
        config,
    })
}

/// Writes the current Gaussians atomically (creating the folder); returns their number.
fn save(tr: &Trainer, template: &Gaussians, out: &Path) -> Result<usize> {
    let g = tr.params().to_gaussians(template, Some(tr.kept()));
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|source| RefineError::OutputFolder {
            path: parent.display().to_string(),
            source,
        })?;
    }
    g.write(out)?;
    Ok(g.len())
}

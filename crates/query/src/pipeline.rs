//! The whole query: load and cross-check the files, score and select every prompt, then
//! render each view's top-K once and write every prompt's mask, overlay and selection.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::time::Instant;

use image::ExtendedColorType;
use profuse_formats::{
    camera, format_float, Cameras, Features, FileKind, Gaussians, Pq, Prompts, Selection,
    SemanticIndex,
};
use serde::Serialize;
use splat_raster::{Rasterizer, RenderOptions};

use crate::activation::{activation, Membership};
use crate::error::{io_err, QueryError, Result};
use crate::output::{create_dir, overlay, write_png};
use crate::score::{score_prompts, Descriptors, ScoreKind, CANONICAL_NEGATIVES};
use crate::select::{select, ActiveSet, Rule};
use crate::semantic::Indexed;

mod inputs;

pub use inputs::*;

/// Default number of top-K contributors per pixel (design.md, splat-raster).
pub const DEFAULT_TOP_K: usize = 10;
/// Default silhouette threshold γ of the activation mask: a pixel is selected when the
/// active Gaussians carry at least half of its top-K blending weight.
pub const DEFAULT_GAMMA: f32 = 0.5;
/// Default relevancy threshold: relevancy >= 0.5 exactly when the prompt is at least as
/// similar as every canonical negative.
pub const DEFAULT_RELEVANCY_THRESHOLD: f32 = 0.5;

/// Which views to write masks for.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum ViewSelection {
    /// Every view of the cameras file.
    #[default]
    All,
    /// These view indices (in this order, repeats dropped).
    List(Vec<usize>),
    /// The views whose image stem has a label file `DIR/<stem>.json` (LERF-style
    /// `gt/label/`), in view order.
    FromLabels(PathBuf),
}

/// Where the outputs go (see the crate docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Layout {
    /// `OUT/<prompt>/selection.safetensors`, `OUT/<prompt>/masks/<stem>.png`,
    /// `OUT/<prompt>/overlay/<stem>.png`.
    #[default]
    Prompt,
    /// What the LERF-OVS evaluation reads: `OUT/<stem>/<prompt>.png`, plus
    /// `OUT/selection/<prompt>.safetensors` and `OUT/overlay/<stem>/<prompt>.png`.
    Lerf,
}

impl Layout {
    /// `prompt` or `lerf`.
    pub fn name(self) -> &'static str {
        match self {
            Layout::Prompt => "prompt",
            Layout::Lerf => "lerf",
        }
    }

    /// Folder names of the layout that a view stem must not take.
    fn reserved(self) -> &'static [&'static str] {
        match self {
            Layout::Prompt => &[],
            Layout::Lerf => &["selection", "overlay"],
        }
    }

    /// The selection file of a prompt.
    pub fn selection_path(self, out: &Path, prompt: &str) -> PathBuf {
        match self {
            Layout::Prompt => out.join(prompt).join("selection.safetensors"),
            Layout::Lerf => out.join("selection").join(format!("{prompt}.safetensors")),
        }
    }

    /// The mask PNG of a prompt in a view.
    pub fn mask_path(self, out: &Path, prompt: &str, stem: &str) -> PathBuf {
        match self {
            Layout::Prompt => out.join(prompt).join("masks").join(format!("{stem}.png")),
            Layout::Lerf => out.join(stem).join(format!("{prompt}.png")),
        }
    }

    /// The overlay PNG of a prompt in a view.
    pub fn overlay_path(self, out: &Path, prompt: &str, stem: &str) -> PathBuf {
        match self {
            Layout::Prompt => out.join(prompt).join("overlay").join(format!("{stem}.png")),
            Layout::Lerf => out.join("overlay").join(stem).join(format!("{prompt}.png")),
        }
    }
}

/// Everything a run needs besides the files.
#[derive(Debug, Clone, PartialEq)]
pub struct QueryOptions {
    /// The prompts to query.
    pub prompts: PromptSelection,
    /// The score.
    pub score: ScoreKind,
    /// Threshold or fraction; `None` = [`DEFAULT_RELEVANCY_THRESHOLD`] for relevancy, an
    /// error for cosine (the paper tunes τ per method).
    pub rule: Option<Rule>,
    /// Silhouette threshold γ of the masks.
    pub gamma: f32,
    /// Top-K contributors per pixel.
    pub k: usize,
    /// Render at this multiple of each camera's image size (`None` = 1).
    pub scale: Option<f64>,
    /// The views.
    pub views: ViewSelection,
    /// Output layout.
    pub layout: Layout,
    /// Also write overlays (renders colour too).
    pub overlay: bool,
}

impl Default for QueryOptions {
    fn default() -> Self {
        QueryOptions {
            prompts: PromptSelection::All,
            score: ScoreKind::Cosine,
            rule: None,
            gamma: DEFAULT_GAMMA,
            k: DEFAULT_TOP_K,
            scale: None,
            views: ViewSelection::All,
            layout: Layout::Prompt,
            overlay: true,
        }
    }
}

/// One prompt of a plan: its active set and the name its files use.
#[derive(Debug, Clone, PartialEq)]
pub struct PlannedPrompt {
    /// Index in the prompts file.
    pub index: usize,
    /// The prompt text.
    pub name: String,
    /// The name in file paths (path separators and control characters replaced by `_`).
    pub file_name: String,
    /// The selected Gaussians.
    pub active: ActiveSet,
    /// Gaussians with a descriptor (the population a fraction is taken of).
    pub valid: usize,
    /// More metadata for the prompt's selection file (a click's origin); empty from
    /// [`Inputs::plan`].
    pub extra: BTreeMap<String, String>,
}

/// One view of a plan.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct PlannedView {
    /// Index in the cameras file.
    pub view: usize,
    /// Output stem: the image name's file stem.
    pub stem: String,
}

/// A validated run: scores and active sets computed, views resolved, nothing written.
#[derive(Debug, Clone)]
pub struct Plan {
    /// The prompts.
    pub prompts: Vec<PlannedPrompt>,
    /// The views.
    pub views: Vec<PlannedView>,
    /// The cameras, scaled.
    pub cameras: Cameras,
    /// The options.
    pub options: QueryOptions,
    /// The rule used (after defaults).
    pub rule: Rule,
    /// Label files that matched no view (with [`ViewSelection::FromLabels`]).
    pub unmatched_labels: Vec<String>,
    /// Seconds spent scoring and selecting.
    pub score_s: f64,
}

/// Per prompt, what a run wrote.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PromptReport {
    /// The prompt.
    pub prompt: String,
    /// Selected Gaussians.
    pub selected: usize,
    /// Gaussians with a descriptor.
    pub valid: usize,
    /// The effective threshold, widened from f32 by its shortest decimal (0.6, not
    /// 0.6000000238418579); null in JSON when a fraction selected nothing.
    pub threshold: f64,
    /// The selection file (non-UTF-8 bytes shown as U+FFFD in JSON).
    #[serde(serialize_with = "profuse_formats::output::lossy_path::one")]
    pub selection: PathBuf,
    /// Masks written (one per view).
    pub views_written: usize,
    /// Share of selected pixels over all written masks.
    pub mask_coverage: f64,
}

/// What a run did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    /// `cosine` or `relevancy`.
    pub score: ScoreKind,
    /// `threshold` or `top_frac`.
    pub rule: String,
    /// γ.
    pub gamma: f64,
    /// K.
    pub k: usize,
    /// The layout.
    pub layout: Layout,
    /// The views written.
    pub views: Vec<PlannedView>,
    /// Per prompt.
    pub prompts: Vec<PromptReport>,
    /// Label files without a view.
    pub unmatched_labels: Vec<String>,
    /// Seconds scoring and selecting.
    pub score_s: f64,
    /// Seconds rendering top-K (and colour).
    pub render_s: f64,
    /// Seconds computing activations and writing files.
    pub write_s: f64,
}

impl Inputs {
    /// Scores and selects every prompt and resolves the views: every check that can fail
    /// on input happens here, before anything is written.
    pub fn plan(&self, options: &QueryOptions) -> Result<Plan> {
        check_parameters(options)?;
        let rule = match (options.rule, options.score) {
            (Some(r), _) => r,
            (None, ScoreKind::Relevancy) => Rule::Threshold(DEFAULT_RELEVANCY_THRESHOLD),
            (None, ScoreKind::Cosine) => return Err(QueryError::MissingThreshold),
        };
        rule.validate()?;
        let (views, unmatched_labels) = self.resolve_views(&options.views, options.layout)?;
        let cameras = match options.scale {
            Some(s) => scale_cameras(&self.cameras, s)?,
            None => self.cameras.clone(),
        };
        // A camera the rasterizer would refuse (e.g. scaled beyond its size limit) must
        // fail here, before anything is written.
        for v in &views {
            splat_raster::ViewCamera::from_cameras(&cameras, v.view)?;
        }

        let t0 = Instant::now();
        let scoring = &self.scoring;
        let which = scoring.resolve_prompts(&options.prompts)?;
        let scores = scoring.scores(&which, options.score)?;
        let valid = scoring.descriptors().valid_count();
        let mut prompts = Vec::with_capacity(which.len());
        let mut file_names = BTreeMap::new();
        for (&index, s) in which.iter().zip(&scores) {
            let name = scoring.prompts.names[index].clone();
            let file_name = file_name_of(&name, options.layout)?;
            if let Some(other) = file_names.insert(file_name.clone(), name.clone()) {
                return Err(QueryError::ReservedName {
                    what: "prompt",
                    name: format!("{name} (same file name as {other})"),
                    layout: options.layout.name(),
                });
            }
            prompts.push(PlannedPrompt {
                index,
                name,
                file_name,
                active: select(s, rule)?,
                valid,
                extra: BTreeMap::new(),
            });
        }
        Ok(Plan {
            prompts,
            views,
            cameras,
            options: options.clone(),
            rule,
            unmatched_labels,
            score_s: t0.elapsed().as_secs_f64(),
        })
    }

    fn resolve_views(
        &self,
        selection: &ViewSelection,
        layout: Layout,
    ) -> Result<(Vec<PlannedView>, Vec<String>)> {
        let cams = &self.cameras;
        let mut unmatched = Vec::new();
        let indices: Vec<usize> = match selection {
            ViewSelection::All => (0..cams.len()).collect(),
            ViewSelection::List(list) => {
                let mut out = Vec::new();
                for &v in list {
                    if v >= cams.len() {
                        return Err(QueryError::ViewOutOfRange {
                            path: self.cameras_path.clone(),
                            view: v,
                            views: cams.len(),
                        });
                    }
                    if !out.contains(&v) {
                        out.push(v);
                    }
                }
                out
            }
            ViewSelection::FromLabels(dir) => {
                let stems = label_stems(dir)?;
                let by_view: Vec<usize> = (0..cams.len())
                    .filter(|&v| stems.contains(&image_stem(&cams.image_names[v], v)))
                    .collect();
                let have: BTreeSet<String> = by_view
                    .iter()
                    .map(|&v| image_stem(&cams.image_names[v], v))
                    .collect();
                unmatched = stems.difference(&have).cloned().collect();
                if by_view.is_empty() {
                    return Err(QueryError::NoViews {
                        reason: format!(
                            "{}: no label file <stem>.json matches an image of {}",
                            dir.display(),
                            self.cameras_path
                        ),
                    });
                }
                by_view
            }
        };
        if indices.is_empty() {
            return Err(QueryError::NoViews {
                reason: format!("{}: no view selected", self.cameras_path),
            });
        }
        let mut seen: BTreeMap<String, usize> = BTreeMap::new();
        let mut views = Vec::with_capacity(indices.len());
        for v in indices {
            let stem = image_stem(&cams.image_names[v], v);
            // `...png` has the stem `..`: every output path built from it must stay
            // inside the output directory.
            profuse_formats::output::safe_component(
                &format!("{} `image_names` entry {v}", self.cameras_path),
                "image stem",
                &stem,
            )?;
            if layout.reserved().contains(&stem.as_str()) {
                return Err(QueryError::ReservedName {
                    what: "image stem",
                    name: stem,
                    layout: layout.name(),
                });
            }
            if let Some(&first) = seen.get(&stem) {
                return Err(QueryError::DuplicateStem {
                    path: self.cameras_path.clone(),
                    stem,
                    first,
                    second: v,
                });
            }
            seen.insert(stem.clone(), v);
            views.push(PlannedView { view: v, stem });
        }
        Ok((views, unmatched))
    }
}

fn check_parameters(o: &QueryOptions) -> Result<()> {
    if !o.gamma.is_finite() {
        return Err(QueryError::BadParameter {
            name: "gamma",
            value: o.gamma.to_string(),
            expected: "a finite number (default 0.5)",
        });
    }
    if o.k == 0 || o.k > splat_raster::MAX_TOP_K {
        return Err(QueryError::BadParameter {
            name: "k",
            value: o.k.to_string(),
            expected: "1..=256",
        });
    }
    if let Some(s) = o.scale {
        if !(s.is_finite() && s > 0.0) {
            return Err(QueryError::BadParameter {
                name: "scale",
                value: s.to_string(),
                expected: "a positive number",
            });
        }
    }
    Ok(())
}

/// The file stem of an image name (`images/frame_00003.png` → `frame_00003`), or
/// `view_<v>` when it has none.
pub fn image_stem(image_name: &str, view: usize) -> String {
    Path::new(image_name)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| format!("view_{view:05}"))
}

/// The name a prompt's files use: `/`, `\` and control characters become `_`; `.`, `..`
/// and the layout's reserved folder names are refused.
pub fn file_name_of(prompt: &str, layout: Layout) -> Result<String> {
    let name = profuse_formats::label_space::prompt_file_stem(prompt);
    if name.is_empty() || name == "." || name == ".." || layout.reserved().contains(&name.as_str())
    {
        return Err(QueryError::ReservedName {
            what: "prompt",
            name,
            layout: layout.name(),
        });
    }
    Ok(name)
}

fn label_stems(dir: &Path) -> Result<BTreeSet<String>> {
    let entries = std::fs::read_dir(dir).map_err(io_err(dir, "cannot list label files"))?;
    let mut stems = BTreeSet::new();
    for e in entries {
        let p = e.map_err(io_err(dir, "cannot list label files"))?.path();
        if p.extension().is_some_and(|x| x == "json") {
            if let Some(s) = p.file_stem() {
                stems.insert(s.to_string_lossy().into_owned());
            }
        }
    }
    Ok(stems)
}

/// The cameras rendered at `scale` × their image size: each size is rounded (at least
/// 1 pixel) and fx, cx scale by new_width / width, fy, cy by new_height / height, so the
/// image covers the same field of view.
pub fn scale_cameras(cameras: &Cameras, scale: f64) -> Result<Cameras> {
    if !(scale.is_finite() && scale > 0.0) {
        return Err(QueryError::BadParameter {
            name: "scale",
            value: scale.to_string(),
            expected: "a positive number",
        });
    }
    let mut sizes = Vec::with_capacity(cameras.len());
    let mut intrinsics = Vec::with_capacity(cameras.len());
    for (&[w, h], k) in cameras.image_size.iter().zip(cameras.intrinsics.iter()) {
        let nw = (f64::from(w) * scale)
            .round()
            .clamp(1.0, f64::from(u32::MAX)) as u32;
        let nh = (f64::from(h) * scale)
            .round()
            .clamp(1.0, f64::from(u32::MAX)) as u32;
        sizes.push([nw, nh]);
        intrinsics.push(camera::rescale_intrinsics(k, [w, h], [nw, nh]));
    }
    Ok(Cameras {
        image_size: sizes.into(),
        intrinsics: intrinsics.into(),
        ..cameras.clone()
    })
}

impl Plan {
    /// Renders each planned view's top-K once (and its colour for overlays), computes
    /// every prompt's activation mask from it, and writes the outputs under `out`.
    /// `progress(done, total)` is called after each view.
    pub fn run(
        &self,
        gaussians: &Gaussians,
        out: &Path,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<Report> {
        let o = &self.options;
        let raster = Rasterizer::new(gaussians)?;
        self.create_dirs(out)?;
        for p in &self.prompts {
            self.selection_file(p, gaussians.len())
                .write(o.layout.selection_path(out, &p.file_name))?;
        }
        let sets: Vec<&ActiveSet> = self.prompts.iter().map(|p| &p.active).collect();
        let membership = Membership::new(gaussians.len(), &sets);
        let render = RenderOptions {
            color: o.overlay,
            top_k: Some(o.k),
            ..RenderOptions::default()
        };
        let mut selected_px = vec![0u64; self.prompts.len()];
        let mut total_px = 0u64;
        let (mut render_s, mut write_s) = (0.0, 0.0);
        let mut t = Instant::now();
        let total = self.views.len();
        let mut done = 0;
        raster.for_each_view(
            &self.cameras,
            self.views.iter().map(|v| v.view),
            &render,
            |_, r| -> Result<()> {
                render_s += t.elapsed().as_secs_f64();
                let t_write = Instant::now();
                let view = &self.views[done];
                let (w, h) = (r.width(), r.height());
                let (ids, weights) = (r.topk_ids().unwrap_or(&[]), r.topk_weights().unwrap_or(&[]));
                let act = activation(ids, weights, w, h, o.k, &membership)?;
                total_px += (w * h) as u64;
                for (q, p) in self.prompts.iter().enumerate() {
                    let mask = act.mask(q, o.gamma);
                    selected_px[q] += mask.iter().filter(|m| **m > 0).count() as u64;
                    let path = o.layout.mask_path(out, &p.file_name, &view.stem);
                    write_png(&path, w, h, &mask, ExtendedColorType::L8)?;
                    if let Some(rgb) = r.color().filter(|_| o.overlay) {
                        let path = o.layout.overlay_path(out, &p.file_name, &view.stem);
                        write_png(&path, w, h, &overlay(rgb, &mask), ExtendedColorType::Rgb8)?;
                    }
                }
                done += 1;
                progress(done, total);
                write_s += t_write.elapsed().as_secs_f64();
                t = Instant::now();
                Ok(())
            },
        )?;
        let prompts = self
            .prompts
            .iter()
            .zip(&selected_px)
            .map(|(p, &px)| PromptReport {
                prompt: p.name.clone(),
                selected: p.active.len(),
                valid: p.valid,
                threshold: decimal(p.active.threshold),
                selection: o.layout.selection_path(out, &p.file_name),
                views_written: done,
                mask_coverage: px as f64 / total_px.max(1) as f64,
            })
            .collect();
        Ok(Report {
            score: o.score,
            rule: rule_text(self.rule),
            gamma: decimal(o.gamma),
            k: o.k,
            layout: o.layout,
            views: self.views.clone(),
            prompts,
            unmatched_labels: self.unmatched_labels.clone(),
            score_s: self.score_s,
            render_s,
            write_s,
        })
    }

    /// Like [`Plan::run`], but the outputs appear at `out` whole: they are written into a
    /// temporary directory next to it (`.profuse-tmp-<name>-*`), which then *replaces*
    /// `out` ([`profuse_formats::output::StagedDir`]): files of an earlier run that this
    /// run does not write are gone, and a failure (a full disk) leaves `out` as it was and
    /// no temporary directory. An existing `out` must be empty or an earlier query output
    /// ([`is_query_output`]). The report names the final paths.
    pub fn run_replacing(
        &self,
        gaussians: &Gaussians,
        out: &Path,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<Report> {
        let staged = profuse_formats::output::StagedDir::new(
            out,
            is_query_output,
            "an earlier query output (it has no selection files)",
        )?;
        let mut report = self.run(gaussians, staged.path(), progress)?;
        for p in &mut report.prompts {
            if let Ok(rel) = p.selection.strip_prefix(staged.path()) {
                p.selection = out.join(rel);
            }
        }
        staged.commit()?;
        Ok(report)
    }

    /// The selection file of a planned prompt.
    pub fn selection_file(&self, p: &PlannedPrompt, num_gaussians: usize) -> Selection {
        let mut extra = p.extra.clone();
        extra.insert("score".to_string(), self.options.score.name().to_string());
        extra.insert("threshold".to_string(), format!("{:?}", p.active.threshold));
        extra.insert("rule".to_string(), rule_text(self.rule));
        extra.insert(
            "generator".to_string(),
            format!("profuse-query {}", env!("CARGO_PKG_VERSION")),
        );
        Selection {
            prompt: p.name.clone(),
            num_gaussians,
            gaussian_ids: p.active.ids.clone().into(),
            scores: p.active.scores.clone().into(),
            extra,
        }
    }

    fn create_dirs(&self, out: &Path) -> Result<()> {
        let o = &self.options;
        let mut dirs = BTreeSet::new();
        for p in &self.prompts {
            if let Some(d) = o.layout.selection_path(out, &p.file_name).parent() {
                dirs.insert(d.to_path_buf());
            }
            for v in &self.views {
                if let Some(d) = o.layout.mask_path(out, &p.file_name, &v.stem).parent() {
                    dirs.insert(d.to_path_buf());
                }
                if o.overlay {
                    if let Some(d) = o.layout.overlay_path(out, &p.file_name, &v.stem).parent() {
                        dirs.insert(d.to_path_buf());
                    }
                }
            }
        }
        dirs.iter().try_for_each(|d| create_dir(d))
    }
}

/// Whether `dir` holds a query's outputs (which [`Plan::run_replacing`] may replace): a
/// `selection/` folder (LERF layout) or a `<prompt>/selection.safetensors` (prompt layout).
pub fn is_query_output(dir: &Path) -> bool {
    dir.join("selection").is_dir()
        || std::fs::read_dir(dir).is_ok_and(|entries| {
            entries
                .flatten()
                .any(|e| e.path().join("selection.safetensors").is_file())
        })
}

/// `threshold=T` or `top_frac=F`, numbers in their shortest round-trip form.
pub fn rule_text(rule: Rule) -> String {
    match rule {
        Rule::Threshold(t) => format!("threshold={t:?}"),
        Rule::TopFraction(f) => format!("top_frac={}", format_float(f)),
    }
}

/// An f32 as the f64 of its shortest decimal form, for reports.
fn decimal(v: f32) -> f64 {
    format!("{v:?}").parse().unwrap_or(f64::from(v))
}

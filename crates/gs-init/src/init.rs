//! The pipeline: plan (references and their neighbours), check inputs, then per
//! reference sample, triangulate, gate and colour; finally assemble the Gaussians.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};

use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::SquaredEuclidean;
use profuse_formats::{camera, Cameras, Gaussians, Matches, SparseMatches, WarpCoords};
use rayon::prelude::*;

use crate::error::{InitError, Result};
use crate::geometry::{norm, sub, triangulate_normalised, Gates, Reason, Triangulation, View};
use crate::images::{ImageSource, ViewImage};
use crate::params::{Params, Scale};
use crate::report::{median, ReferenceReport, Rejected, Report};
use crate::rng::{keyed, purpose, sample, Rng};
use crate::select::{nearest_views, pose_features, select_references};

/// SH degree-0 constant: colour = C0 · dc + 0.5.
pub use profuse_formats::camera::SH_C0;
/// Smallest mean squared neighbour distance of the k-NN scale rule (3DGS's clamp).
pub const MIN_KNN_DIST2: f64 = 1e-7;

/// Names of the inputs for error messages.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Labels<'a> {
    pub cameras: &'a str,
    pub matches: &'a str,
}

/// The matches to triangulate.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Input<'a> {
    Dense(&'a Matches),
    Sparse(&'a SparseMatches),
}

impl Input<'_> {
    fn pairs(&self) -> &[[u32; 2]] {
        match self {
            Input::Dense(m) => &m.pairs,
            Input::Sparse(m) => &m.pairs,
        }
    }

    fn num_views(&self) -> usize {
        match self {
            Input::Dense(m) => m.num_views,
            Input::Sparse(m) => m.num_views,
        }
    }
}

/// A reference view and the (view, pair row) it is triangulated against.
#[derive(Debug, Clone)]
struct Job {
    reference: usize,
    partners: Vec<(usize, usize)>,
}

/// A kept point before it becomes a Gaussian.
#[derive(Debug, Clone, Copy)]
struct Point {
    mean: [f64; 3],
    colour: [f32; 3],
    ref_depth: f64,
    ref_distance: f64,
    reproj_px: f64,
    angle_deg: f64,
}

/// One neighbour's triangulation of a sample and its verdict.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    t: Triangulation,
    verdict: std::result::Result<(), Reason>,
    /// Targets the point agrees with (itself included; 0 when it fails a gate).
    support: usize,
}

impl Candidate {
    /// Passing beats failing; then more support; then the smaller larger-of-two
    /// reprojection error (NaN last); a tie keeps the earlier candidate.
    fn beats(&self, other: &Candidate) -> bool {
        let key = |c: &Candidate| {
            (
                c.verdict.is_err(),
                usize::MAX - c.support,
                c.t.max_reproj_px(),
            )
        };
        let (a, b) = (key(self), key(other));
        a.0.cmp(&b.0)
            .then(a.1.cmp(&b.1))
            .then(a.2.total_cmp(&b.2))
            .is_lt()
    }
}

/// One sample's fate.
#[derive(Debug, Clone, Copy)]
struct Outcome {
    result: std::result::Result<Point, Reason>,
    solves: u32,
}

/// One reference's results.
#[derive(Debug)]
struct RefOutput {
    report: ReferenceReport,
    points: Vec<Point>,
    rejected: Rejected,
    solves: u64,
}

/// Runs the whole initialisation. `progress(done, total)` is called after each reference.
pub(crate) fn initialise(
    cameras: &Cameras,
    images: &dyn ImageSource,
    input: Input<'_>,
    params: &Params,
    labels: Labels<'_>,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<(Gaussians, Report)> {
    params.validate()?;
    check_pairs(cameras, input, labels)?;
    let views: Vec<View> = (0..cameras.len())
        .map(|v| View::from_cameras(cameras, v))
        .collect();
    let jobs = match input {
        Input::Dense(_) => plan_dense(&views, input.pairs(), params),
        Input::Sparse(_) => plan_sparse(input.pairs()),
    };
    for job in &jobs {
        check_image(
            cameras,
            images,
            job.reference,
            images.dimensions(job.reference)?,
            labels,
        )?;
    }
    let done = AtomicUsize::new(0);
    let outputs: Vec<Result<RefOutput>> = jobs
        .par_iter()
        .map(|job| {
            let image = load_image(cameras, images, job.reference, labels)?;
            let ctx = RefContext {
                cameras,
                views: &views,
                image: &image,
                params,
                job,
            };
            let out = match input {
                Input::Dense(m) => ctx.dense(m),
                Input::Sparse(m) => ctx.sparse(m),
            };
            progress(done.fetch_add(1, Ordering::Relaxed) + 1, jobs.len());
            Ok(out)
        })
        .collect();
    // The first error in reference order, whatever the thread count.
    let outputs = outputs.into_iter().collect::<Result<Vec<_>>>()?;
    let mode = match input {
        Input::Dense(_) => "dense",
        Input::Sparse(_) => "sparse",
    };
    Ok(assemble(outputs, cameras, &views, input, params, mode))
}

/// Every pair's view ids exist in the cameras file, and the file was made for it.
fn check_pairs(cameras: &Cameras, input: Input<'_>, labels: Labels<'_>) -> Result<()> {
    for (p, pair) in input.pairs().iter().enumerate() {
        if let Some(&view) = pair.iter().find(|v| **v as usize >= cameras.len()) {
            return Err(InitError::PairOutOfRange {
                matches: labels.matches.to_string(),
                pair: p,
                view,
                cameras: labels.cameras.to_string(),
                views: cameras.len(),
            });
        }
    }
    if input.num_views() != cameras.len() {
        return Err(InitError::ViewCount {
            matches: labels.matches.to_string(),
            num_views: input.num_views(),
            cameras: labels.cameras.to_string(),
            views: cameras.len(),
        });
    }
    Ok(())
}

fn check_image(
    cameras: &Cameras,
    images: &dyn ImageSource,
    v: usize,
    found: [u32; 2],
    labels: Labels<'_>,
) -> Result<()> {
    let expected = cameras.image_size[v];
    if found == expected {
        Ok(())
    } else {
        Err(InitError::ImageSize {
            path: images.label(v),
            view: v,
            found_w: found[0],
            found_h: found[1],
            cameras: labels.cameras.to_string(),
            expected_w: expected[0],
            expected_h: expected[1],
        })
    }
}

/// Decodes view `v`'s image and checks it against the cameras file.
fn load_image(
    cameras: &Cameras,
    images: &dyn ImageSource,
    v: usize,
    labels: Labels<'_>,
) -> Result<ViewImage> {
    let image = images.load(v)?;
    check_image(cameras, images, v, [image.width, image.height], labels)?;
    let expected = image.width as usize * image.height as usize * 3;
    if image.rgb.len() != expected {
        return Err(InitError::ImageData {
            path: images.label(v),
            view: v,
            found: image.rgb.len(),
            expected,
            width: image.width,
            height: image.height,
        });
    }
    Ok(image)
}

/// Outgoing pairs per view: view -> [(partner, pair row)], in pair order.
fn outgoing(pairs: &[[u32; 2]]) -> BTreeMap<usize, Vec<(usize, usize)>> {
    let mut out: BTreeMap<usize, Vec<(usize, usize)>> = BTreeMap::new();
    for (p, [i, j]) in pairs.iter().enumerate() {
        out.entry(*i as usize).or_default().push((*j as usize, p));
    }
    out
}

/// Dense: references by k-means among the views with outgoing pairs; per reference its
/// `neighbours` nearest partners by pose distance.
fn plan_dense(views: &[View], pairs: &[[u32; 2]], params: &Params) -> Vec<Job> {
    let out = outgoing(pairs);
    let features = pose_features(views);
    let candidates: Vec<usize> = out.keys().copied().collect();
    select_references(&features, &candidates, params.references, params.seed)
        .into_iter()
        .map(|r| {
            let partners = &out[&r];
            let options: Vec<usize> = partners.iter().map(|(j, _)| *j).collect();
            let chosen = nearest_views(&features, r, &options, params.neighbours);
            Job {
                reference: r,
                partners: chosen
                    .into_iter()
                    .filter_map(|j| partners.iter().find(|(v, _)| *v == j).copied())
                    .collect(),
            }
        })
        .collect()
}

/// Sparse: every view with outgoing pairs is a reference, with all of its pairs.
fn plan_sparse(pairs: &[[u32; 2]]) -> Vec<Job> {
    outgoing(pairs)
        .into_iter()
        .map(|(reference, partners)| Job {
            reference,
            partners,
        })
        .collect()
}

/// What one reference's work needs.
struct RefContext<'a> {
    cameras: &'a Cameras,
    views: &'a [View],
    image: &'a ViewImage,
    params: &'a Params,
    job: &'a Job,
}

impl RefContext<'_> {
    fn rng(&self) -> Rng {
        keyed(&[self.params.seed, purpose::SAMPLE, self.job.reference as u64])
    }

    fn dense(&self, m: &Matches) -> RefOutput {
        let (gw, gh) = (m.width, m.height);
        let cells = gw * gh;
        let thr = self.params.certainty_threshold;
        let confident = |p: usize, c: usize| f64::from(m.certainty.get(p * cells + c)) > thr;
        let pool: Vec<usize> = (0..cells)
            .filter(|&c| self.job.partners.iter().any(|&(_, p)| confident(p, c)))
            .collect();
        let picks = sample(pool.len(), self.params.budget, &mut self.rng());
        let r = self.job.reference;
        let [w, h] = self.cameras.image_size[r];
        let (sx, sy) = (f64::from(w) / gw as f64, f64::from(h) / gh as f64);
        let outcomes: Vec<Outcome> = picks
            .par_iter()
            .map(|&k| {
                let cell = pool[k];
                let pixel = [
                    ((cell % gw) as f64 + 0.5) * sx,
                    ((cell / gw) as f64 + 0.5) * sy,
                ];
                let targets = self
                    .job
                    .partners
                    .iter()
                    .filter(|&&(_, p)| confident(p, cell))
                    .map(|&(j, p)| {
                        let at = (p * cells + cell) * 2;
                        let t = [f64::from(m.warp.get(at)), f64::from(m.warp.get(at + 1))];
                        (j, warp_to_pixels(t, m.coords, self.cameras.image_size[j]))
                    });
                self.triangulate_sample(pixel, targets)
            })
            .collect();
        self.tally(pool.len(), outcomes)
    }

    fn sparse(&self, m: &SparseMatches) -> RefOutput {
        let thr = self.params.certainty_threshold;
        let pool: Vec<(usize, usize)> = self
            .job
            .partners
            .iter()
            .flat_map(|&(j, p)| {
                m.range(p)
                    .filter(|&k| f64::from(m.certainty[k]) > thr)
                    .map(move |k| (j, k))
            })
            .collect();
        let picks = sample(pool.len(), self.params.budget, &mut self.rng());
        let outcomes: Vec<Outcome> = picks
            .par_iter()
            .map(|&s| {
                let (j, k) = pool[s];
                let pi = m.points_i[k].map(f64::from);
                let pj = m.points_j[k].map(f64::from);
                self.triangulate_sample(pi, std::iter::once((j, pj)))
            })
            .collect();
        self.tally(pool.len(), outcomes)
    }

    /// Triangulates the reference pixel against each target (view, pixel) and keeps one
    /// triangulation: among those that pass the gates, the one most other targets agree
    /// with (its point projects within the reprojection tolerance of their target), then
    /// the smallest larger-of-two reprojection error, then the earlier target. When none
    /// passes, the reason is that of the candidate with the smallest error.
    fn triangulate_sample(
        &self,
        pixel: [f64; 2],
        targets: impl Iterator<Item = (usize, [f64; 2])>,
    ) -> Outcome {
        let r = self.job.reference;
        let rv = &self.views[r];
        let nr = rv.normalise(pixel);
        let gates: Gates = self.params.gates();
        let targets: Vec<(usize, [f64; 2])> = targets.collect();
        let mut best: Option<Candidate> = None;
        for &(j, pj) in &targets {
            let vj = &self.views[j];
            let t = triangulate_normalised(rv, nr, vj, vj.normalise(pj));
            let verdict = t.check(&gates);
            let support = match (verdict, t.point) {
                (Ok(()), Some(x)) if targets.len() > 1 => targets
                    .iter()
                    .filter(|&&(k, pk)| {
                        let q = self.views[k].project(x);
                        let (dx, dy) = (q[0] - pk[0], q[1] - pk[1]);
                        q[2] > 0.0 && (dx * dx + dy * dy).sqrt() <= gates.max_reproj_px
                    })
                    .count(),
                _ => 0,
            };
            let c = Candidate {
                verdict,
                support,
                t,
            };
            if best.as_ref().is_none_or(|b| c.beats(b)) {
                best = Some(c);
            }
        }
        let result = match best {
            None => Err(Reason::NonFinite),
            Some(Candidate {
                verdict: Err(reason),
                ..
            }) => Err(reason),
            Some(Candidate {
                t, verdict: Ok(()), ..
            }) => match t.point {
                None => Err(Reason::NonFinite),
                Some(mean) => Ok(Point {
                    mean,
                    colour: self.image.sample(pixel[0], pixel[1]),
                    ref_depth: t.depths[0],
                    ref_distance: norm(sub(mean, rv.center())),
                    reproj_px: t.max_reproj_px(),
                    angle_deg: t.angle_deg,
                }),
            },
        };
        Outcome {
            result,
            solves: targets.len() as u32,
        }
    }

    fn tally(&self, confident: usize, outcomes: Vec<Outcome>) -> RefOutput {
        let mut rejected = Rejected::default();
        let mut points = Vec::new();
        let mut solves = 0u64;
        for o in &outcomes {
            solves += u64::from(o.solves);
            match o.result {
                Ok(p) => points.push(p),
                Err(reason) => rejected.add(reason),
            }
        }
        RefOutput {
            report: ReferenceReport {
                view: self.job.reference,
                neighbours: self.job.partners.iter().map(|(j, _)| *j).collect(),
                confident: confident as u64,
                sampled: outcomes.len() as u64,
                kept: points.len() as u64,
            },
            points,
            rejected,
            solves,
        }
    }
}

/// A warp target in pixels of an image of `size` (SPEC.md §4.4).
pub fn warp_to_pixels(t: [f64; 2], coords: WarpCoords, size: [u32; 2]) -> [f64; 2] {
    match coords {
        WarpCoords::Pixels => t,
        WarpCoords::Normalized => [
            (t[0] + 1.0) * 0.5 * f64::from(size[0]),
            (t[1] + 1.0) * 0.5 * f64::from(size[1]),
        ],
    }
}

/// Concatenates the references' points in reference order and makes the Gaussians.
fn assemble(
    outputs: Vec<RefOutput>,
    cameras: &Cameras,
    views: &[View],
    input: Input<'_>,
    params: &Params,
    mode: &'static str,
) -> (Gaussians, Report) {
    let mut rejected = Rejected::default();
    let mut references = Vec::with_capacity(outputs.len());
    let mut points = Vec::new();
    let mut scales_ref = Vec::new();
    let mut solves = 0;
    for out in outputs {
        rejected.merge(&out.rejected);
        solves += out.solves;
        let f = views[out.report.view].focal();
        scales_ref.extend(out.points.iter().map(|p| match params.scale {
            Scale::Pixels { pixels } => pixels * p.ref_depth / f,
            Scale::Distance { factor } => factor * p.ref_distance,
            Scale::Knn { .. } => 0.0,
        }));
        points.extend(out.points);
        references.push(out.report);
    }
    let means: Vec<[f64; 3]> = points.iter().map(|p| p.mean).collect();
    let mut scales = match params.scale {
        Scale::Knn { k } => knn_scales(&means, k),
        _ => scales_ref,
    };
    let g = Gaussians {
        means: means
            .iter()
            .map(|m| m.map(|c| c as f32))
            .collect::<Vec<_>>()
            .into(),
        log_scales: scales
            .iter()
            .map(|s| [s.ln() as f32; 3])
            .collect::<Vec<_>>()
            .into(),
        rotations: vec![[1.0, 0.0, 0.0, 0.0]; points.len()].into(),
        opacity_logits: vec![0.0; points.len()].into(),
        sh_dc: points
            .iter()
            .map(|p| {
                p.colour
                    .map(|c| camera::colour_to_sh_dc(f64::from(c)) as f32)
            })
            .collect::<Vec<_>>()
            .into(),
        sh_degree: 0,
        extra: BTreeMap::from([
            (
                "generator".to_string(),
                format!("gs-init {} {mode}", env!("CARGO_PKG_VERSION")),
            ),
            (
                "gs_init_params".to_string(),
                serde_json::to_string(params).unwrap_or_default(),
            ),
        ]),
        ..Default::default()
    };
    let sampled: u64 = references.iter().map(|r| r.sampled).sum();
    let report = Report {
        mode,
        views: cameras.len(),
        pairs: input.pairs().len(),
        pairs_used: references.iter().map(|r| r.neighbours.len()).sum(),
        confident: references.iter().map(|r| r.confident).sum(),
        sampled,
        triangulated: sampled - rejected.non_finite,
        dlt_solves: solves,
        kept: points.len() as u64,
        median_reproj_px: median(&mut points.iter().map(|p| p.reproj_px).collect::<Vec<_>>()),
        median_angle_deg: median(&mut points.iter().map(|p| p.angle_deg).collect::<Vec<_>>()),
        median_scale: median(&mut scales),
        rejected,
        references,
        params: *params,
    };
    (g, report)
}

/// Per point, sqrt of the mean squared distance to its `k` nearest other points (fewer
/// when there are fewer points), at least sqrt([`MIN_KNN_DIST2`]).
pub fn knn_scales(points: &[[f64; 3]], k: usize) -> Vec<f64> {
    let k = k.min(points.len().saturating_sub(1));
    if k == 0 {
        return vec![MIN_KNN_DIST2.sqrt(); points.len()];
    }
    let tree: ImmutableKdTree<f64, u64, 3, 32> = ImmutableKdTree::new_from_slice(points);
    let Some(query_len) = std::num::NonZero::new(k + 1) else {
        return vec![MIN_KNN_DIST2.sqrt(); points.len()];
    };
    points
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            let found = tree.nearest_n::<SquaredEuclidean>(p, query_len);
            let mut d2: Vec<f64> = found
                .iter()
                .filter(|nb| nb.item != i as u64)
                .map(|nb| nb.distance)
                .collect();
            // Ties at the k-th distance may leave self out of the list: keep k.
            d2.truncate(k);
            let mean = d2.iter().sum::<f64>() / d2.len().max(1) as f64;
            mean.max(MIN_KNN_DIST2).sqrt()
        })
        .collect()
}

//! The points of the consensus: the tracked Gaussians each view's masks see (interior pixels
//! only), gathered per mask, and each mask's votes for the clusters of the other views and its
//! share.

use super::*;

/// Pixels whose 3 × 3 neighbourhood (clipped at the image border) carries one label: only
/// they vote, because a mask's boundary is where segmentation is least certain (jitter,
/// a contributor straddling two regions), and small objects are mostly boundary.
pub(super) fn interior_pixels(plane: &[u32], width: usize) -> Vec<bool> {
    if width == 0 {
        return Vec::new();
    }
    let height = plane.len() / width;
    let mut out = vec![false; plane.len()];
    for y in 0..height {
        for x in 0..width {
            let l = plane[y * width + x];
            let (x0, x1) = (x.saturating_sub(1), (x + 1).min(width - 1));
            let (y0, y1) = (y.saturating_sub(1), (y + 1).min(height - 1));
            out[y * width + x] = (y0..=y1).all(|yy| {
                plane[yy * width + x0..=yy * width + x1]
                    .iter()
                    .all(|&m| m == l)
            });
        }
    }
    out
}
/// Which Gaussians are tracked as points: every `stride`-th, the smallest stride that
/// keeps at most `max_points`.
pub(crate) fn point_stride(gaussians: usize, max_points: usize) -> usize {
    gaussians.div_ceil(max_points.max(1)).max(1)
}

/// Every tracked point's label in one view, and how many of the label's pixels it won.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct ViewPoints {
    /// Per point: its label, or [`NONE`].
    pub labels: Vec<u32>,
    /// Per point: the interior pixels carrying its label that it wins (0 with [`NONE`]).
    pub pixels: Vec<u32>,
}

/// The label of every tracked point in one view, from the view's top-1 render on the mask
/// grid: `ids[p]` is the Gaussian contributing most to pixel p (or an id >= `gaussians`
/// for none), `plane[p]` the pixel's mask label. A point takes the label most of its
/// pixels carry (ties: the smaller label; "no mask" loses ties); a point that wins no
/// pixel, or whose pixels mostly carry no mask, gets [`NONE`].
pub(crate) fn view_point_labels(
    ids: &[u32],
    plane: &[u32],
    width: usize,
    gaussians: usize,
    stride: usize,
) -> ViewPoints {
    let points = gaussians.div_ceil(stride);
    let interior = interior_pixels(plane, width);
    let mut votes: Vec<(u32, u32)> = ids
        .iter()
        .zip(plane)
        .zip(&interior)
        .filter(|((&g, _), &inner)| {
            inner && (g as usize) < gaussians && (g as usize).is_multiple_of(stride)
        })
        .map(|((&g, &l), _)| (g / stride as u32, l))
        .collect();
    votes.sort_unstable();
    let mut labels = vec![NONE; points];
    let mut pixels = vec![0u32; points];
    for run in votes.chunk_by(|a, b| a.0 == b.0) {
        let mut best = (0usize, NONE);
        for same in run.chunk_by(|a, b| a.1 == b.1) {
            // Labels ascend within a run, so a later label wins only with more pixels.
            if same.len() > best.0 {
                best = (same.len(), same[0].1);
            }
        }
        if best.1 != NONE {
            labels[run[0].0 as usize] = best.1;
            pixels[run[0].0 as usize] = u32::try_from(best.0).unwrap_or(u32::MAX);
        }
    }
    ViewPoints { labels, pixels }
}

/// Every mask's points P_m and their weights, gathered view by view (so that only the
/// labels, not the pixel counts, of all views are kept).
#[derive(Debug, Clone)]
pub(crate) struct MaskPoints {
    pub(super) points: Vec<Vec<u32>>,
    pub(super) weights: Vec<Vec<u32>>,
    pub(super) weight: PointWeight,
}

impl MaskPoints {
    pub fn new(masks: usize, weight: PointWeight) -> Self {
        MaskPoints {
            points: vec![Vec::new(); masks],
            weights: vec![Vec::new(); masks],
            weight,
        }
    }

    /// Adds the points of the view whose first mask has global id `offset`.
    pub fn add_view(&mut self, offset: u32, view: &ViewPoints) {
        for (g, (&l, &px)) in view.labels.iter().zip(&view.pixels).enumerate() {
            if l == NONE {
                continue;
            }
            let m = (offset + l) as usize;
            self.points[m].push(g as u32);
            self.weights[m].push(match self.weight {
                PointWeight::Pixels => px,
                PointWeight::Points => 1,
            });
        }
    }
}

/// Per mask: the views that observe it with it contained (its visible views, as a bit
/// set) and the global ids of the masks that contain it; `None` when under-segmented.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct MaskVotes {
    pub(super) visible: Vec<u64>,
    pub(super) containers: Vec<u32>,
    pub(super) undersegmented: bool,
    pub(super) share: f32,
}

/// Observed/contained/split for mask `m` of view `own` with point ids `pts` of weights
/// `wts`.
pub(super) fn mask_votes(
    pts: &[u32],
    wts: &[u32],
    own: usize,
    global: u32,
    labels: &[Vec<u32>],
    offsets: &[u32],
    p: &ConsensusParams,
) -> MaskVotes {
    let views = labels.len();
    let mut visible = vec![0u64; views.div_ceil(64)];
    let mut containers = Vec::new();
    if pts.len() < MIN_MASK_POINTS {
        return MaskVotes {
            visible,
            containers,
            undersegmented: true,
            share: 1.0,
        };
    }
    // The other views that observe m, and those of them that split it.
    let (mut observed, mut split) = (0usize, 0usize);
    // Over the other views that observe m: the weight of its best container, and all
    // the weight they label (for the share).
    let (mut held, mut seen) = (0u64, 0u64);
    let total: u64 = wts.iter().map(|&w| u64::from(w)).sum();
    let mut counts: HashMap<u32, u64> = HashMap::new();
    for (k, lk) in labels.iter().enumerate() {
        if k == own {
            visible[k / 64] |= 1 << (k % 64);
            containers.push(global);
            continue;
        }
        counts.clear();
        let (mut labelled, mut labelled_points) = (0u64, 0usize);
        for (&g, &w) in pts.iter().zip(wts) {
            let l = lk[g as usize];
            if l != NONE {
                labelled += u64::from(w);
                labelled_points += 1;
                *counts.entry(l).or_insert(0) += u64::from(w);
            }
        }
        let too_few = labelled_points < p.observed_points.max(1);
        if too_few || (labelled as f64) < p.visible_ratio * total as f64 {
            continue;
        }
        observed += 1;
        let Some((best, n)) = most(&counts) else {
            continue;
        };
        held += n;
        seen += labelled;
        if n as f64 > p.contained_ratio * labelled as f64 {
            visible[k / 64] |= 1 << (k % 64);
            containers.push(offsets[k] + best);
        } else {
            split += 1;
        }
    }
    // The own view always contains the mask, so it votes only on request (step 4).
    let voters = observed + usize::from(p.own_view_votes);
    let undersegmented = split as f64 > p.undersegment_ratio * voters as f64;
    containers.sort_unstable();
    MaskVotes {
        visible,
        containers,
        undersegmented,
        share: mask_share(held, seen),
    }
}

/// A mask's share: the weight its best container holds over all the weight labelled, both
/// summed over the other views that observe it (in (0, 1]: the best label holds at least
/// its share of each view); 1 when no other view observes it.
pub(super) fn mask_share(held: u64, seen: u64) -> f32 {
    if seen == 0 {
        return 1.0;
    }
    // At least 2^-24, so that a share is never 0 in f32.
    ((held as f64 / seen as f64) as f32).clamp(f32::EPSILON / 2.0, 1.0)
}

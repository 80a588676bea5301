//! Scores of a predicted clustering (e.g. mask proposals grouped into objects) against
//! ground-truth labels: adjusted Rand index, purity and completeness.
//!
//! Conventions shared by every function here:
//!
//! * `u32::MAX` in `truth` means "no ground truth": the item is dropped before anything is
//!   counted, from every score.
//! * `u32::MAX` in `predicted` means "unassigned": for the adjusted Rand index and for
//!   completeness each unassigned item is its own singleton cluster (so leaving an item
//!   out never merges it with anything); purity counts only assigned items.
//! * Label values are arbitrary ids: every score is invariant under renaming them.

use std::collections::HashMap;

use serde::Serialize;

use crate::{MetricsError, Result};

/// The label meaning "unassigned" (in `predicted`) or "no ground truth" (in `truth`).
pub const NONE: u32 = u32::MAX;

/// Scores of a predicted clustering of items against ground-truth labels. `u32::MAX` in
/// `predicted` = unassigned (each unassigned item counts as its own singleton cluster);
/// `u32::MAX` in `truth` = no ground truth (item excluded from all scores).
#[derive(Debug, Clone, Serialize)]
pub struct ClusterScores {
    /// Adjusted Rand index (Hubert & Arabie 1985) over the evaluated items, unassigned
    /// items as singletons; 1 for identical partitions, about 0 for random ones, can be
    /// negative. 1 when both partitions are trivially equal (all items in one cluster, or
    /// all singletons, or fewer than two items).
    pub ari: f64,
    /// Σ over predicted clusters of the count of its majority truth label, divided by the
    /// number of assigned evaluated items: the share of assigned items whose cluster's
    /// majority label equals their own. 0 when no evaluated item is assigned.
    pub purity: f64,
    /// Σ over truth labels of the largest number of its items in one predicted cluster
    /// (an unassigned item is a singleton cluster), divided by the number of evaluated
    /// items: the per-label best-cluster share averaged with weights = label sizes.
    /// 0 when there are no evaluated items.
    pub completeness: f64,
    /// Evaluated items: those with ground truth.
    pub items: usize,
    /// Evaluated items with a predicted cluster.
    pub assigned: usize,
    /// Distinct predicted clusters among the evaluated items (unassigned items not counted).
    pub clusters: usize,
}

/// The contingency table of the evaluated items: counts per (predicted, truth) pair, with
/// one fresh predicted id per unassigned item.
struct Contingency {
    /// (predicted cluster, truth label) -> count; unassigned items have `Cluster::Single`.
    cells: HashMap<(Cluster, u32), u64>,
    items: u64,
    assigned: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Cluster {
    Assigned(u32),
    /// The singleton cluster of the unassigned item with this index.
    Single(usize),
}

fn contingency(predicted: &[u32], truth: &[u32]) -> Result<Contingency> {
    if predicted.len() != truth.len() {
        return Err(MetricsError::LengthMismatch {
            what: "cluster scores",
            left_name: "predicted",
            left: predicted.len(),
            right_name: "truth",
            right: truth.len(),
        });
    }
    let mut cells = HashMap::new();
    let (mut items, mut assigned) = (0, 0);
    for (i, (&p, &t)) in predicted.iter().zip(truth).enumerate() {
        if t == NONE {
            continue;
        }
        items += 1;
        let cluster = if p == NONE {
            Cluster::Single(i)
        } else {
            assigned += 1;
            Cluster::Assigned(p)
        };
        *cells.entry((cluster, t)).or_insert(0u64) += 1;
    }
    Ok(Contingency {
        cells,
        items,
        assigned,
    })
}

fn pairs(n: u64) -> u128 {
    let n = u128::from(n);
    n * n.saturating_sub(1) / 2
}

impl Contingency {
    fn row_sums(&self) -> HashMap<Cluster, u64> {
        let mut rows = HashMap::new();
        for (&(c, _), &n) in &self.cells {
            *rows.entry(c).or_insert(0) += n;
        }
        rows
    }

    fn column_sums(&self) -> HashMap<u32, u64> {
        let mut cols = HashMap::new();
        for (&(_, t), &n) in &self.cells {
            *cols.entry(t).or_insert(0) += n;
        }
        cols
    }

    /// ARI = (Σ C(n_ij,2) − E) / (½(Σ C(a_i,2) + Σ C(b_j,2)) − E),
    /// E = Σ C(a_i,2) · Σ C(b_j,2) / C(n,2). Pair counts are exact integers (u128).
    fn ari(&self) -> f64 {
        let index: u128 = self.cells.values().map(|&n| pairs(n)).sum();
        let rows: u128 = self.row_sums().values().map(|&n| pairs(n)).sum();
        let cols: u128 = self.column_sums().values().map(|&n| pairs(n)).sum();
        let total = pairs(self.items);
        // The denominator vanishes only when both partitions put every pair together or
        // every pair apart, i.e. when they are identical.
        if rows == cols && (rows == 0 || rows == total) {
            return 1.0;
        }
        let expected = rows as f64 * cols as f64 / total as f64;
        let max = 0.5 * (rows as f64 + cols as f64);
        (index as f64 - expected) / (max - expected)
    }

    fn purity(&self) -> f64 {
        let mut majority: HashMap<u32, u64> = HashMap::new();
        for (&(c, _), &n) in &self.cells {
            if let Cluster::Assigned(c) = c {
                let best = majority.entry(c).or_insert(0);
                *best = (*best).max(n);
            }
        }
        ratio(majority.values().sum(), self.assigned)
    }

    fn completeness(&self) -> f64 {
        let mut best: HashMap<u32, u64> = HashMap::new();
        for (&(_, t), &n) in &self.cells {
            let b = best.entry(t).or_insert(0);
            *b = (*b).max(n);
        }
        ratio(best.values().sum(), self.items)
    }

    fn clusters(&self) -> usize {
        let mut seen: Vec<u32> = self
            .cells
            .keys()
            .filter_map(|&(c, _)| match c {
                Cluster::Assigned(c) => Some(c),
                Cluster::Single(_) => None,
            })
            .collect();
        seen.sort_unstable();
        seen.dedup();
        seen.len()
    }
}

fn ratio(num: u64, den: u64) -> f64 {
    if den == 0 {
        0.0
    } else {
        num as f64 / den as f64
    }
}

/// ARI, purity and completeness of `predicted` against `truth` (same length; see the
/// module documentation for `u32::MAX`). All sums are over exact integer counts, so the
/// result does not depend on hash-map iteration order.
///
/// ```
/// use profuse_metrics::cluster::cluster_scores;
/// // Two objects (truth 7 and 9); the prediction merges item 2 into the wrong cluster.
/// let s = cluster_scores(&[0, 0, 0, 1, 1], &[7, 7, 9, 9, 9]).unwrap();
/// assert_eq!((s.items, s.assigned, s.clusters), (5, 5, 2));
/// assert!((s.purity - 0.8).abs() < 1e-12);
/// assert!((s.completeness - 0.8).abs() < 1e-12);
/// ```
pub fn cluster_scores(predicted: &[u32], truth: &[u32]) -> Result<ClusterScores> {
    let c = contingency(predicted, truth)?;
    Ok(ClusterScores {
        ari: c.ari(),
        purity: c.purity(),
        completeness: c.completeness(),
        items: c.items as usize,
        assigned: c.assigned as usize,
        clusters: c.clusters(),
    })
}

/// The adjusted Rand index alone (see [`ClusterScores::ari`]).
pub fn adjusted_rand_index(predicted: &[u32], truth: &[u32]) -> Result<f64> {
    Ok(contingency(predicted, truth)?.ari())
}

/// Reads `gt/mask_objects.json` (SPEC.md §6.1, through the typed reader of
/// `profuse-formats`) as the ground truth of each global mask: entry `i` is the object of
/// mask `i`, [`NONE`] where the mask lies on no object.
pub fn read_mask_objects(path: impl AsRef<std::path::Path>) -> Result<Vec<u32>> {
    let masks = profuse_formats::ground_truth::MaskObjects::read(path)?;
    Ok(masks.objects.iter().map(|o| o.unwrap_or(NONE)).collect())
}

/// The ground-truth ("oracle") proposals of a scene: masks on the same ground-truth
/// object form one proposal, masks on no object ([`NONE`]) none. Proposals are numbered
/// by ascending object id; `mask_view[m]` is the view of global mask `m` (for
/// `proposal_views`). Running the pipeline on these gives the ceiling of proposal pooling
/// for a perfect grouping (`profuse sweep --oracle`): what no grouping rule can beat with
/// the paper's registration.
pub fn oracle_proposals(truth: &[u32], mask_view: &[u32]) -> Result<profuse_formats::Proposals> {
    if truth.len() != mask_view.len() {
        return Err(MetricsError::LengthMismatch {
            what: "oracle proposals",
            left_name: "ground-truth masks",
            left: truth.len(),
            right_name: "mask views",
            right: mask_view.len(),
        });
    }
    let mut objects: Vec<u32> = truth.iter().copied().filter(|o| *o != NONE).collect();
    objects.sort_unstable();
    objects.dedup();
    let rank = |o: u32| objects.binary_search(&o).ok().map(|r| r as u32);
    let mask_proposal: Vec<u32> = truth.iter().map(|o| rank(*o).unwrap_or(NONE)).collect();
    let mut size = vec![0u32; objects.len()];
    let mut views: Vec<Vec<u32>> = vec![Vec::new(); objects.len()];
    for (p, v) in mask_proposal.iter().zip(mask_view) {
        if *p != NONE {
            size[*p as usize] += 1;
            views[*p as usize].push(*v);
        }
    }
    let proposal_views: Vec<u32> = views
        .iter_mut()
        .map(|v| {
            v.sort_unstable();
            v.dedup();
            v.len() as u32
        })
        .collect();
    Ok(profuse_formats::Proposals {
        mask_proposal: mask_proposal.into(),
        proposal_size: size.into(),
        proposal_views: proposal_views.into(),
        // Every member is on its object by construction: the mass alone.
        mask_share: None,
        mask_instance: None,
        extra: [("grouping".to_string(), "ground-truth".to_string())].into(),
    })
}

/// Scores a proposals file's object instances ([`Proposals::instances`]: `mask_instance`
/// when present, else `mask_proposal`; `u32::MAX` = none) against per-mask ground truth
/// (e.g. from [`read_mask_objects`]).
///
/// [`Proposals::instances`]: profuse_formats::Proposals::instances
pub fn proposal_scores(
    proposals: &profuse_formats::Proposals,
    truth: &[u32],
) -> Result<ClusterScores> {
    scores_of(proposals.instances(), "proposals.mask_instance", truth)
}

/// Scores the proposals' members alone (`mask_proposal`: the masks pooled into each
/// proposal's descriptor; attached masks unassigned) against per-mask ground truth.
pub fn member_scores(
    proposals: &profuse_formats::Proposals,
    truth: &[u32],
) -> Result<ClusterScores> {
    scores_of(&proposals.mask_proposal, "proposals.mask_proposal", truth)
}

fn scores_of(predicted: &[u32], name: &'static str, truth: &[u32]) -> Result<ClusterScores> {
    if predicted.len() != truth.len() {
        return Err(MetricsError::LengthMismatch {
            what: "proposal scores",
            left_name: name,
            left: predicted.len(),
            right_name: "ground-truth masks",
            right: truth.len(),
        });
    }
    cluster_scores(predicted, truth)
}

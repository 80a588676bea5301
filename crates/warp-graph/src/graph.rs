//! Mutual link test of the candidate mask pairs of one view pair, connected components of
//! the mask graph over all views (petgraph's union-find), the s_min / v_min filters and the
//! deterministic numbering of the proposals.

use std::collections::{BTreeMap, HashMap};

use petgraph::unionfind::UnionFind;
use profuse_formats::{Proposals, NO_PROPOSAL};
use serde::Serialize;

use crate::extent::{agreement, BinBox, Extent, MaskExtents};
use crate::overlap::DirectedOverlaps;
use crate::params::Params;

/// Why candidate links were rejected (a candidate may count under several reasons).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
pub struct Rejections {
    /// Mask IoU below τ_iou in at least one available direction.
    pub iou: u64,
    /// Box IoU below τ_box in at least one available direction.
    pub box_iou: u64,
    /// Passed both criteria in one direction and failed in the other (the mutual
    /// requirement at work).
    pub one_direction_only: u64,
    /// Overlapped in one direction's warp and not at all in the other's.
    pub no_reverse_overlap: u64,
}

impl Rejections {
    pub(crate) fn add(&mut self, o: &Rejections) {
        self.iou += o.iou;
        self.box_iou += o.box_iou;
        self.one_direction_only += o.one_direction_only;
        self.no_reverse_overlap += o.no_reverse_overlap;
    }
}

/// An accepted link between two masks of different views.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Link {
    /// Global mask ids, the lower view first.
    pub masks: [u32; 2],
    /// The smaller of the two directions' mask IoUs (the one available when only one
    /// warp exists).
    pub iou: f64,
    /// The smaller of the two directions' box IoUs.
    pub box_iou: f64,
}

/// The links of one unordered view pair {i, j}, i < j.
#[derive(Debug, Default)]
pub(crate) struct PairLinks {
    /// Accepted links.
    pub(crate) edges: Vec<Link>,
    /// Candidates: mask pairs with non-zero overlap in either direction.
    pub(crate) tested: u64,
    pub(crate) rejections: Rejections,
}

/// Tests every candidate (a in i, b in j): `forward` is the warp of pair (i, j) (IoU
/// O_{i,a;j,b} on view i's grid), `backward` the warp of pair (j, i). A candidate is
/// accepted when every available direction has IoU >= τ_iou and box IoU >= τ_box.
pub(crate) fn link_pair(
    forward: Option<&DirectedOverlaps>,
    backward: Option<&DirectedOverlaps>,
    offsets: [u32; 2],
    params: &Params,
) -> PairLinks {
    let mut candidates: Vec<(u32, u32)> = Vec::new();
    if let Some(f) = forward {
        candidates.extend(f.intersections.iter().map(|o| (o.src, o.dst)));
    }
    if let Some(b) = backward {
        candidates.extend(b.intersections.iter().map(|o| (o.dst, o.src)));
    }
    candidates.sort_unstable();
    candidates.dedup();
    let mut out = PairLinks {
        tested: candidates.len() as u64,
        ..PairLinks::default()
    };
    for (a, b) in candidates {
        let f = forward.map(|d| (d.iou(a, b), d.box_iou(a, b)));
        let g = backward.map(|d| (d.iou(b, a), d.box_iou(b, a)));
        let iou_ok = |s: Option<(f64, f64)>| s.is_none_or(|(iou, _)| iou >= params.tau_iou);
        let box_ok = |s: Option<(f64, f64)>| s.is_none_or(|(_, bx)| bx >= params.tau_box);
        let dir_ok = |s: Option<(f64, f64)>| iou_ok(s) && box_ok(s);
        if dir_ok(f) && dir_ok(g) {
            let min = |k: fn((f64, f64)) -> f64| {
                f.map(k)
                    .unwrap_or(f64::INFINITY)
                    .min(g.map(k).unwrap_or(f64::INFINITY))
            };
            out.edges.push(Link {
                masks: [offsets[0] + a, offsets[1] + b],
                iou: min(|s| s.0),
                box_iou: min(|s| s.1),
            });
            continue;
        }
        let r = &mut out.rejections;
        r.iou += u64::from(!(iou_ok(f) && iou_ok(g)));
        r.box_iou += u64::from(!(box_ok(f) && box_ok(g)));
        if let (Some(fs), Some(gs)) = (f, g) {
            r.one_direction_only += u64::from(dir_ok(Some(fs)) != dir_ok(Some(gs)));
            r.no_reverse_overlap += u64::from((fs.0 > 0.0) != (gs.0 > 0.0));
        }
    }
    out
}

/// How the components fared.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
pub struct ComponentStats {
    /// Connected components of the mask graph, singletons included.
    pub components: u64,
    /// Components with at least two members.
    pub linked_components: u64,
    /// Components dropped for fewer than s_min members.
    pub dropped_by_s_min: u64,
    /// Components with enough members dropped for fewer than v_min views.
    pub dropped_by_v_min: u64,
    /// Links not applied because the union would have put two masks of one view without
    /// enough common support together ([`Params::same_view_support`]).
    pub refused_links: u64,
    /// Links not applied because the two components' 3D extents disagree
    /// ([`Params::extent_agreement`]).
    pub extent_refused_links: u64,
    /// Unions of components made by the IoU of their 3D boxes
    /// ([`Params::extent_merge_iou`]).
    pub extent_merges: u64,
    /// Proposals kept.
    pub proposals: u64,
    /// Masks that belong to a kept proposal.
    pub masks_assigned: u64,
}

/// The extent rules in force for one run (see [`Params::extent_agreement`] and
/// [`Params::extent_merge_iou`]).
pub(crate) struct ExtentRules<'e> {
    pub(crate) masks: &'e MaskExtents,
    pub(crate) agreement: Option<f64>,
    pub(crate) merge_iou: Option<f64>,
    pub(crate) trim: f64,
}

/// The components and what the rules refused or added.
struct Roots {
    labels: Vec<u32>,
    refused: u64,
    extent_refused: u64,
    extent_merges: u64,
}

/// The state of the guarded union: per current root its members by view, member count and,
/// with the extent rules, its extent and box.
struct Groups<'r> {
    members: Vec<BTreeMap<u32, Vec<u32>>>,
    size: Vec<u32>,
    extents: Vec<Extent>,
    boxes: Vec<Option<BinBox>>,
    rules: Option<&'r ExtentRules<'r>>,
}

impl<'r> Groups<'r> {
    fn new(view_of: &[u32], rules: Option<&'r ExtentRules<'r>>) -> Self {
        let members = view_of
            .iter()
            .enumerate()
            .map(|(x, v)| BTreeMap::from([(*v, vec![x as u32])]))
            .collect();
        let (extents, boxes) = match rules {
            Some(r) => (
                r.masks.extents.clone(),
                r.masks
                    .extents
                    .iter()
                    .map(|e| e.padded_box(r.trim, r.masks.pad))
                    .collect(),
            ),
            None => (Vec::new(), Vec::new()),
        };
        Groups {
            members,
            size: vec![1; view_of.len()],
            extents,
            boxes,
            rules,
        }
    }

    /// The same-view guard: no two masks of one view end up together without support.
    fn compatible(&self, a: usize, b: usize, supported: &impl Fn(u32, u32) -> bool) -> bool {
        let (small, large) = if self.members[a].len() <= self.members[b].len() {
            (a, b)
        } else {
            (b, a)
        };
        self.members[small].iter().all(|(v, xs)| {
            self.members[large]
                .get(v)
                .is_none_or(|ys| xs.iter().all(|&x| ys.iter().all(|&y| supported(x, y))))
        })
    }

    /// The extent agreement test of a union of two components of at least two masks each;
    /// `true` when the rule is off or either has no box.
    fn extents_agree(&self, a: usize, b: usize) -> bool {
        let Some(threshold) = self.rules.and_then(|r| r.agreement) else {
            return true;
        };
        if self.size[a] < 2 || self.size[b] < 2 {
            return true;
        }
        match (&self.boxes[a], &self.boxes[b]) {
            (Some(ba), Some(bb)) => {
                agreement(&self.extents[a], ba, &self.extents[b], bb) >= threshold
            }
            _ => true,
        }
    }

    /// Unites the components of roots `a` and `b`; returns the new root.
    fn join(&mut self, uf: &mut UnionFind<u32>, a: usize, b: usize) -> usize {
        uf.union(a as u32, b as u32);
        let root = uf.find(a as u32) as usize;
        let from = if root == a { b } else { a };
        let moved = std::mem::take(&mut self.members[from]);
        for (v, xs) in moved {
            self.members[root].entry(v).or_default().extend(xs);
        }
        self.size[root] += self.size[from];
        if let Some(r) = self.rules {
            let e = std::mem::take(&mut self.extents[from]);
            self.extents[root].merge(&e);
            self.boxes[root] = self.extents[root].padded_box(r.trim, r.masks.pad);
            self.boxes[from] = None;
        }
        root
    }

    /// A component that the merge pass considers: two masks or more and a box.
    fn mergeable(&self, uf: &UnionFind<u32>, x: usize) -> bool {
        uf.find(x as u32) as usize == x && self.size[x] >= 2 && self.boxes[x].is_some()
    }

    fn box_iou(&self, a: usize, b: usize) -> f64 {
        match (&self.boxes[a], &self.boxes[b]) {
            (Some(p), Some(q)) => p.iou(q),
            _ => 0.0,
        }
    }
}

/// A pair of components for the merge pass, ordered by box IoU (largest first), then by
/// the smaller ids, so that the pass is deterministic.
#[derive(Debug, PartialEq)]
struct MergeCandidate {
    iou: f64,
    a: usize,
    b: usize,
    /// The sizes of a and b when the candidate was made (stale once either grew).
    sizes: (u32, u32),
}

impl Eq for MergeCandidate {}

impl Ord for MergeCandidate {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        self.iou
            .total_cmp(&o.iou)
            .then_with(|| (o.a, o.b).cmp(&(self.a, self.b)))
    }
}

impl PartialOrd for MergeCandidate {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}

/// The merge pass: components of two masks or more whose padded boxes have IoU >=
/// `threshold` are united, largest IoU first, unless the same-view guard objects; the box
/// of a merged component is recomputed and its candidates renewed. Initial candidates come
/// from a sweep over the boxes' x intervals (only pairs overlapping in x can reach the
/// threshold). Returns the number of merges.
fn merge_by_extent(
    uf: &mut UnionFind<u32>,
    groups: &mut Groups<'_>,
    threshold: f64,
    supported: &impl Fn(u32, u32) -> bool,
) -> u64 {
    let mut live: Vec<usize> = (0..groups.size.len())
        .filter(|&x| groups.mergeable(uf, x))
        .collect();
    let mut heap = std::collections::BinaryHeap::new();
    let candidate = |g: &Groups<'_>, a: usize, b: usize| {
        let (a, b) = (a.min(b), a.max(b));
        let iou = g.box_iou(a, b);
        (iou >= threshold && iou > 0.0).then_some(MergeCandidate {
            iou,
            a,
            b,
            sizes: (g.size[a], g.size[b]),
        })
    };
    let x_range = |g: &Groups<'_>, x: usize| g.boxes[x].map_or((0.0, 0.0), |b| b.x_range());
    let mut by_x = live.clone();
    by_x.sort_by(|&p, &q| {
        x_range(groups, p)
            .0
            .total_cmp(&x_range(groups, q).0)
            .then(p.cmp(&q))
    });
    for (k, &a) in by_x.iter().enumerate() {
        let hi = x_range(groups, a).1;
        for &b in &by_x[k + 1..] {
            if x_range(groups, b).0 >= hi {
                break;
            }
            heap.extend(candidate(groups, a, b));
        }
    }
    let mut merges = 0;
    while let Some(c) = heap.pop() {
        let fresh = |x: usize, s: u32| uf.find(x as u32) as usize == x && groups.size[x] == s;
        if !fresh(c.a, c.sizes.0) || !fresh(c.b, c.sizes.1) {
            continue;
        }
        if !groups.compatible(c.a, c.b, supported) {
            continue;
        }
        let root = groups.join(uf, c.a, c.b);
        merges += 1;
        live.retain(|&x| groups.mergeable(uf, x));
        if !groups.mergeable(uf, root) {
            continue;
        }
        for &x in &live {
            if x != root {
                heap.extend(candidate(groups, root, x));
            }
        }
    }
    merges
}

/// Component representative of every mask: plain connected components (paper), or, with
/// `same_view_support = Some(s)`, links taken strongest first (min IoU, then ids) and a
/// union refused when it would put two masks of one view together that fewer than `s`
/// masks of other views link to both. With extent rules (only with the guard): a union of
/// two components of two masks or more is also refused when their extents disagree, and
/// afterwards components are merged by the IoU of their boxes.
fn component_roots(
    view_of: &[u32],
    links: &[Link],
    same_view_support: Option<usize>,
    rules: Option<&ExtentRules<'_>>,
) -> Roots {
    let m = view_of.len();
    let mut uf = UnionFind::<u32>::new(m);
    let Some(min_support) = same_view_support else {
        for l in links {
            uf.union(l.masks[0], l.masks[1]);
        }
        return Roots {
            labels: uf.into_labeling(),
            refused: 0,
            extent_refused: 0,
            extent_merges: 0,
        };
    };
    let (mut refused, mut extent_refused) = (0u64, 0u64);
    let support = same_view_support_counts(view_of, links);
    let supported = |x: u32, y: u32| {
        support.get(&(x.min(y), x.max(y))).copied().unwrap_or(0) as usize >= min_support
    };
    let mut order: Vec<&Link> = links.iter().collect();
    order.sort_by(|p, q| q.iou.total_cmp(&p.iou).then(p.masks.cmp(&q.masks)));
    let mut groups = Groups::new(view_of, rules);
    for l in order {
        let (ra, rb) = (uf.find(l.masks[0]) as usize, uf.find(l.masks[1]) as usize);
        if ra == rb {
            continue;
        }
        if !groups.compatible(ra, rb, &supported) {
            refused += 1;
            continue;
        }
        if !groups.extents_agree(ra, rb) {
            extent_refused += 1;
            continue;
        }
        groups.join(&mut uf, ra, rb);
    }
    let extent_merges = match rules.and_then(|r| r.merge_iou) {
        Some(t) => merge_by_extent(&mut uf, &mut groups, t, &supported),
        None => 0,
    };
    Roots {
        labels: uf.into_labeling(),
        refused,
        extent_refused,
        extent_merges,
    }
}

/// For every pair of masks of one view (x < y): how many masks link to both.
fn same_view_support_counts(view_of: &[u32], links: &[Link]) -> HashMap<(u32, u32), u32> {
    let mut neighbours: Vec<Vec<u32>> = vec![Vec::new(); view_of.len()];
    for l in links {
        let [a, b] = l.masks;
        neighbours[a as usize].push(b);
        neighbours[b as usize].push(a);
    }
    let mut support = HashMap::new();
    for ns in &mut neighbours {
        ns.sort_unstable_by_key(|x| (view_of[*x as usize], *x));
        ns.dedup();
        for run in ns.chunk_by(|x, y| view_of[*x as usize] == view_of[*y as usize]) {
            for (k, &x) in run.iter().enumerate() {
                for &y in &run[k + 1..] {
                    *support.entry((x, y)).or_insert(0) += 1;
                }
            }
        }
    }
    support
}

/// The view of every global mask.
pub(crate) fn views_of_masks(offsets: &[u32]) -> Vec<u32> {
    let m = offsets.last().map_or(0, |v| *v as usize);
    let mut view_of = vec![0u32; m];
    for (v, w) in offsets.windows(2).enumerate() {
        view_of[w[0] as usize..w[1] as usize].fill(v as u32);
    }
    view_of
}

/// Connected components of the graph on all masks (global ids `0..offsets[V]`) with the
/// given links; components are numbered by their smallest member, filtered by
/// `s_min` / `v_min`, and the survivors renumbered 0..P in the same order.
pub(crate) fn proposals_from_links(
    offsets: &[u32],
    links: &[Link],
    params: &Params,
    extents: Option<&MaskExtents>,
    metadata: BTreeMap<String, String>,
) -> (Proposals, ComponentStats) {
    let view_of = views_of_masks(offsets);
    let rules = extents
        .filter(|_| params.extent_agreement.is_some() || params.extent_merge_iou.is_some())
        .map(|masks| ExtentRules {
            masks,
            agreement: params.extent_agreement,
            merge_iou: params.extent_merge_iou,
            trim: params.extent_trim,
        });
    let roots = component_roots(&view_of, links, params.same_view_support, rules.as_ref());
    let stats = ComponentStats {
        refused_links: roots.refused,
        extent_refused_links: roots.extent_refused,
        extent_merges: roots.extent_merges,
        ..ComponentStats::default()
    };
    let excluded = vec![false; view_of.len()];
    proposals_from_roots(&view_of, &roots.labels, &excluded, params, stats, metadata)
}

/// Numbers the components given by `roots` (a representative per mask) by their smallest
/// member, drops those with fewer than `s_min` members or `v_min` views and masks flagged
/// in `excluded` (which join no proposal), and renumbers the survivors 0..P in the same
/// order.
pub(crate) fn proposals_from_roots(
    view_of: &[u32],
    roots: &[u32],
    excluded: &[bool],
    params: &Params,
    mut stats: ComponentStats,
    metadata: BTreeMap<String, String>,
) -> (Proposals, ComponentStats) {
    let (s_min, v_min) = (params.s_min, params.v_min);
    let m = view_of.len();
    // Component ids in order of first (= smallest) member; views counted as the masks
    // are visited in view order.
    let mut comp_of_root: Vec<u32> = vec![u32::MAX; m];
    let mut comp = vec![0u32; m];
    let mut size: Vec<u32> = Vec::new();
    let mut views: Vec<u32> = Vec::new();
    let mut last_view: Vec<u32> = Vec::new();
    for mask in 0..m {
        let view = view_of[mask];
        let r = roots[mask] as usize;
        if comp_of_root[r] == u32::MAX {
            comp_of_root[r] = size.len() as u32;
            size.push(0);
            views.push(0);
            last_view.push(u32::MAX);
        }
        let c = comp_of_root[r] as usize;
        comp[mask] = c as u32;
        size[c] += 1;
        if last_view[c] != view {
            last_view[c] = view;
            views[c] += 1;
        }
    }
    stats.components = size.len() as u64;
    stats.linked_components = size.iter().filter(|s| **s >= 2).count() as u64;
    let mut new_id = vec![NO_PROPOSAL; size.len()];
    let (mut proposal_size, mut proposal_views) = (Vec::new(), Vec::new());
    let mut excluded_comp = vec![false; size.len()];
    for (mask, &c) in comp.iter().enumerate() {
        excluded_comp[c as usize] |= excluded[mask];
    }
    for c in 0..size.len() {
        if excluded_comp[c] {
            continue;
        }
        if (size[c] as usize) < s_min {
            stats.dropped_by_s_min += 1;
        } else if (views[c] as usize) < v_min {
            stats.dropped_by_v_min += 1;
        } else {
            new_id[c] = proposal_size.len() as u32;
            proposal_size.push(size[c]);
            proposal_views.push(views[c]);
            stats.masks_assigned += u64::from(size[c]);
        }
    }
    stats.proposals = proposal_size.len() as u64;
    let mask_proposal: Vec<u32> = comp.iter().map(|c| new_id[*c as usize]).collect();
    let proposals = Proposals {
        mask_proposal: mask_proposal.into(),
        proposal_size: proposal_size.into(),
        proposal_views: proposal_views.into(),
        mask_share: None,
        mask_instance: None,
        extra: metadata,
    };
    (proposals, stats)
}

/// Every mask's instance: its proposal for a member; for a mask attached to the cluster
/// of root mask r, r's proposal (none when that cluster was dropped); none otherwise.
pub(crate) fn instances(mask_proposal: &[u32], attached: &[u32]) -> Vec<u32> {
    mask_proposal
        .iter()
        .zip(attached)
        .map(|(&p, &r)| match (p, r) {
            (NO_PROPOSAL, NO_PROPOSAL) => NO_PROPOSAL,
            (NO_PROPOSAL, r) => mask_proposal[r as usize],
            (p, _) => p,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn links(pairs: &[[u32; 2]]) -> Vec<Link> {
        pairs
            .iter()
            .map(|&masks| Link {
                masks,
                iou: 0.5,
                box_iou: 0.5,
            })
            .collect()
    }

    fn run(
        offsets: &[u32],
        pairs: &[[u32; 2]],
        s_min: usize,
        v_min: usize,
    ) -> (Proposals, ComponentStats) {
        let params = Params {
            s_min,
            v_min,
            same_view_support: None,
            ..Params::default()
        };
        proposals_from_links(offsets, &links(pairs), &params, None, BTreeMap::new())
    }

    #[test]
    fn components_span_views_and_are_numbered_by_smallest_member() {
        // Views: 0 -> masks 0,1; 1 -> 2,3; 2 -> 4. Edges join 1-2-4 and 0-3.
        let offsets = [0, 2, 4, 5];
        let (p, s) = run(&offsets, &[[2, 4], [1, 2], [0, 3]], 2, 2);
        assert_eq!(&p.mask_proposal[..], &[0, 1, 1, 0, 1]);
        assert_eq!(&p.proposal_size[..], &[2, 3]);
        assert_eq!(&p.proposal_views[..], &[2, 3]);
        assert_eq!(
            (s.components, s.linked_components, s.masks_assigned),
            (2, 2, 5)
        );
        // v_min = 3 keeps only the three-view component, renumbered 0.
        let (p, s) = run(&offsets, &[[2, 4], [1, 2], [0, 3]], 2, 3);
        assert_eq!(&p.mask_proposal[..], &[NO_PROPOSAL, 0, 0, NO_PROPOSAL, 0]);
        assert_eq!((s.dropped_by_s_min, s.dropped_by_v_min), (0, 1));
        // No edges: every mask a singleton, all dropped by s_min = 2.
        let (p, s) = run(&offsets, &[], 2, 1);
        assert!(p.is_empty());
        assert_eq!((s.components, s.dropped_by_s_min), (5, 5));
    }

    #[test]
    fn same_view_support_keeps_a_merged_mask_from_gluing_two_objects() {
        // View 0: mask 0 = objects A+B merged. Views 1, 2, 3: A (1, 3, 5) and B (2, 4, 6).
        let offsets = [0, 1, 3, 5, 7];
        let mut l = links(&[[1, 3], [3, 5], [1, 5], [2, 4], [4, 6], [2, 6]]);
        // The merged mask links to A more strongly than to B in every view.
        for (b, iou) in [(1, 0.6), (3, 0.6), (5, 0.6), (2, 0.3), (4, 0.3), (6, 0.3)] {
            l.push(Link {
                masks: [0, b],
                iou,
                box_iou: 0.5,
            });
        }
        let plain = Params {
            same_view_support: None,
            ..Params::default()
        };
        let (p, _) = proposals_from_links(&offsets, &l, &plain, None, BTreeMap::new());
        assert_eq!(p.len(), 1, "plain components glue A and B");
        let guarded = Params {
            same_view_support: Some(2),
            ..Params::default()
        };
        let (p, _) = proposals_from_links(&offsets, &l, &guarded, None, BTreeMap::new());
        // A with the merged mask (its stronger side), B alone.
        assert_eq!(&p.mask_proposal[..], &[0, 0, 1, 0, 1, 0, 1]);
        // A split object (masks 1, 2 of view 1 both linked from views 0, 2, 3) stays whole.
        let split = links(&[[0, 1], [0, 2], [1, 3], [2, 3], [1, 5], [2, 5], [0, 3]]);
        let (p, _) = proposals_from_links(&offsets, &split, &guarded, None, BTreeMap::new());
        assert_eq!(p.len(), 1);
        assert_eq!(p.proposal_size[0], 5);
    }

    /// An extent of 30 points spread over x bins `x0..x0 + 10` (3 per bin) at y = z = 0.
    fn slab(x0: usize) -> Extent {
        let mut e = Extent::default();
        for k in 0..30 {
            e.add_bins([x0 + k / 3, 0, 0]);
        }
        e
    }

    fn with_extents(
        offsets: &[u32],
        l: &[Link],
        x0: &[usize],
        agreement: Option<f64>,
        merge_iou: Option<f64>,
    ) -> (Proposals, ComponentStats) {
        let extents = MaskExtents {
            extents: x0.iter().map(|&x| slab(x)).collect(),
            pad: [0.0; 3],
        };
        let params = Params {
            extent_agreement: agreement,
            extent_merge_iou: merge_iou,
            extent_trim: 0.0,
            ..Params::default()
        };
        proposals_from_links(offsets, l, &params, Some(&extents), BTreeMap::new())
    }

    #[test]
    fn extent_agreement_refuses_a_bridge_between_components_apart_in_3d() {
        // One mask per view; A = {0, 1} and B = {2, 3} linked strongly, a weak bridge 1-2.
        let offsets = [0, 1, 2, 3, 4];
        let mut l = links(&[[0, 1], [2, 3]]);
        l[0].iou = 0.9;
        l[1].iou = 0.9;
        l.push(Link {
            masks: [1, 2],
            iou: 0.3,
            box_iou: 0.5,
        });
        // B half inside A's box and A half inside B's: agreement 0.5.
        let near = [0, 0, 5, 5];
        let (p, s) = with_extents(&offsets, &l, &near, Some(0.5), None);
        assert_eq!(
            (p.len(), s.extent_refused_links),
            (1, 0),
            "0.5 >= 0.5 joins"
        );
        let (p, s) = with_extents(&offsets, &l, &near, Some(0.6), None);
        assert_eq!(
            (p.len(), s.extent_refused_links),
            (2, 1),
            "0.5 < 0.6 refuses"
        );
        assert_eq!(&p.mask_proposal[..], &[0, 0, 1, 1]);
        // Far apart in 3D: refused at the default; without the rule the bridge joins.
        let far = [0, 0, 100, 100];
        let (p, _) = with_extents(&offsets, &l, &far, Some(0.3), None);
        assert_eq!(p.len(), 2);
        let (p, _) = with_extents(&offsets, &l, &far, None, None);
        assert_eq!(p.len(), 1);
        // A singleton joining a component is never judged (its extent is one view's).
        let (p, s) = with_extents(&[0, 1, 2, 3], &l[..1], &[0, 0, 100], Some(0.3), None);
        assert_eq!((p.len(), s.extent_refused_links), (1, 0));
    }

    #[test]
    fn extent_merge_joins_unlinked_fragments_whose_boxes_overlap() {
        // A = {0, 1} and B = {2, 3}, no link between them; box IoU 5 / 15 = 1/3.
        let offsets = [0, 1, 2, 3, 4];
        let l = links(&[[0, 1], [2, 3]]);
        let near = [0, 0, 5, 5];
        let (p, s) = with_extents(&offsets, &l, &near, None, Some(0.3));
        assert_eq!((p.len(), s.extent_merges), (1, 1), "1/3 >= 0.3 merges");
        assert_eq!(p.proposal_views[0], 4);
        let (p, s) = with_extents(&offsets, &l, &near, None, Some(0.35));
        assert_eq!((p.len(), s.extent_merges), (2, 0), "1/3 < 0.35 does not");
        let (p, _) = with_extents(&offsets, &l, &[0, 0, 100, 100], None, Some(0.01));
        assert_eq!(p.len(), 2, "disjoint boxes never merge");
        // The same-view guard still holds: A = {0 (view 0), 2 (view 1)}, B = {1 (view 0),
        // 3 (view 2)}, and no mask links to both masks of view 0.
        let offsets = [0, 2, 3, 4];
        let l = links(&[[0, 2], [1, 3]]);
        let (p, s) = with_extents(&offsets, &l, &[0, 5, 0, 5], None, Some(0.3));
        assert_eq!((p.len(), s.extent_merges), (2, 0));
        // Without the guard (the paper's components) the extent rules do not run.
        let plain = Params {
            same_view_support: None,
            extent_merge_iou: Some(0.3),
            ..Params::default()
        };
        let extents = MaskExtents {
            extents: [0, 0, 5, 5].iter().map(|&x| slab(x)).collect(),
            pad: [0.0; 3],
        };
        let (p, _) = proposals_from_links(
            &[0, 1, 2, 3, 4],
            &links(&[[0, 1], [2, 3]]),
            &plain,
            Some(&extents),
            BTreeMap::new(),
        );
        assert_eq!(p.len(), 2);
    }

    #[test]
    fn extent_merges_take_the_largest_box_iou_first() {
        // Three two-mask components C0 = {0, 1}, C1 = {2, 3}, C2 = {4, 5} (one mask per
        // view). C1 overlaps C0 by 9/11 and C2 by 1/19, and the merged C0 + C1 box
        // overlaps C2 by 1/20; with threshold 0.051 C1 joins C0 (largest first) and the
        // stale C1-C2 candidate (1/19) is not used: C2 stays.
        let offsets: Vec<u32> = (0..=6).collect();
        let l = links(&[[0, 1], [2, 3], [4, 5]]);
        let (p, s) = with_extents(&offsets, &l, &[0, 0, 1, 1, 10, 10], None, Some(0.051));
        assert_eq!(&p.mask_proposal[..], &[0, 0, 0, 0, 1, 1]);
        assert_eq!(s.extent_merges, 1);
    }
}

//! Mutual link test of the candidate mask pairs of one view pair, connected components of
//! the mask graph over all views (petgraph's union-find), the s_min / v_min filters and the
//! deterministic numbering of the proposals.

use std::collections::{BTreeMap, HashMap};

use petgraph::unionfind::UnionFind;
use profuse_formats::{Proposals, NO_PROPOSAL};
use serde::Serialize;

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
    /// Proposals kept.
    pub proposals: u64,
    /// Masks that belong to a kept proposal.
    pub masks_assigned: u64,
}

/// Component representative of every mask: plain connected components (paper), or, with
/// `same_view_support = Some(s)`, links taken strongest first (min IoU, then ids) and a
/// union refused when it would put two masks of one view together that fewer than `s`
/// masks of other views link to both.
fn component_roots(
    view_of: &[u32],
    links: &[Link],
    same_view_support: Option<usize>,
) -> (Vec<u32>, u64) {
    let m = view_of.len();
    let mut uf = UnionFind::<u32>::new(m);
    let Some(min_support) = same_view_support else {
        for l in links {
            uf.union(l.masks[0], l.masks[1]);
        }
        return (uf.into_labeling(), 0);
    };
    let mut refused = 0u64;
    let support = same_view_support_counts(view_of, links);
    let supported = |x: u32, y: u32| {
        support.get(&(x.min(y), x.max(y))).copied().unwrap_or(0) as usize >= min_support
    };
    let mut order: Vec<&Link> = links.iter().collect();
    order.sort_by(|p, q| q.iou.total_cmp(&p.iou).then(p.masks.cmp(&q.masks)));
    // Members of each component by view, kept at its current root.
    let mut members: Vec<BTreeMap<u32, Vec<u32>>> = view_of
        .iter()
        .enumerate()
        .map(|(x, v)| BTreeMap::from([(*v, vec![x as u32])]))
        .collect();
    for l in order {
        let (ra, rb) = (uf.find(l.masks[0]), uf.find(l.masks[1]));
        if ra == rb {
            continue;
        }
        let (small, large) = if members[ra as usize].len() <= members[rb as usize].len() {
            (ra as usize, rb as usize)
        } else {
            (rb as usize, ra as usize)
        };
        let compatible = members[small].iter().all(|(v, xs)| {
            members[large]
                .get(v)
                .is_none_or(|ys| xs.iter().all(|&x| ys.iter().all(|&y| supported(x, y))))
        });
        if !compatible {
            refused += 1;
            continue;
        }
        uf.union(ra, rb);
        let root = uf.find(ra) as usize;
        let (from, into) = if root == small {
            (large, small)
        } else {
            (small, large)
        };
        let moved = std::mem::take(&mut members[from]);
        for (v, xs) in moved {
            members[into].entry(v).or_default().extend(xs);
        }
    }
    (uf.into_labeling(), refused)
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

/// Connected components of the graph on all masks (global ids `0..offsets[V]`) with the
/// given links; components are numbered by their smallest member, filtered by
/// `s_min` / `v_min`, and the survivors renumbered 0..P in the same order.
pub(crate) fn proposals_from_links(
    offsets: &[u32],
    links: &[Link],
    params: &Params,
    metadata: BTreeMap<String, String>,
) -> (Proposals, ComponentStats) {
    let (s_min, v_min) = (params.s_min, params.v_min);
    let m = offsets.last().map_or(0, |v| *v as usize);
    let mut view_of = vec![0u32; m];
    for (v, w) in offsets.windows(2).enumerate() {
        view_of[w[0] as usize..w[1] as usize].fill(v as u32);
    }
    let (roots, refused_links) = component_roots(&view_of, links, params.same_view_support);
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
    let mut stats = ComponentStats {
        refused_links,
        components: size.len() as u64,
        linked_components: size.iter().filter(|s| **s >= 2).count() as u64,
        ..ComponentStats::default()
    };
    let mut new_id = vec![NO_PROPOSAL; size.len()];
    let (mut proposal_size, mut proposal_views) = (Vec::new(), Vec::new());
    for c in 0..size.len() {
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
        extra: metadata,
    };
    (proposals, stats)
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
        proposals_from_links(offsets, &links(pairs), &params, BTreeMap::new())
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
        let (p, _) = proposals_from_links(&offsets, &l, &plain, BTreeMap::new());
        assert_eq!(p.len(), 1, "plain components glue A and B");
        let guarded = Params {
            same_view_support: Some(2),
            ..Params::default()
        };
        let (p, _) = proposals_from_links(&offsets, &l, &guarded, BTreeMap::new());
        // A with the merged mask (its stronger side), B alone.
        assert_eq!(&p.mask_proposal[..], &[0, 0, 1, 0, 1, 0, 1]);
        // A split object (masks 1, 2 of view 1 both linked from views 0, 2, 3) stays whole.
        let split = links(&[[0, 1], [0, 2], [1, 3], [2, 3], [1, 5], [2, 5], [0, 3]]);
        let (p, _) = proposals_from_links(&offsets, &split, &guarded, BTreeMap::new());
        assert_eq!(p.len(), 1);
        assert_eq!(p.proposal_size[0], 5);
    }
}

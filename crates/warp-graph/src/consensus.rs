//! View-consensus grouping ([`Grouping::Consensus`]): the masks are clustered by how the
//! *other* views see them, after MaskClustering (Yan et al., CVPR 2024), with the scene's
//! Gaussian centres as its point cloud.
//!
//! Why: connected components over pairwise links are single linkage, so one wrong link
//! (an under-segmented mask, a sliver that overlaps two objects) chains two objects, and
//! by chains of such links walls, floors and furniture. View consensus asks instead, for
//! two clusters A and B, in how many of the views that see *both* they fall into *one*
//! mask. An under-segmented mask is one view's vote against the many views that separate
//! the two objects, and it is recognised and removed as a voter.
//!
//! 1. **Points.** The Gaussians (every k-th when there are more than
//!    [`ConsensusParams::max_points`], k the smallest stride that fits). Every view is
//!    rendered on its mask grid with a top-1 list (splat-raster: the Gaussian with the
//!    largest blending weight T·α of each pixel, all Gaussians taking part). In view v a
//!    point is *seen* where it is some pixel's top contributor, and takes the label most of
//!    those pixels carry (ties: the smaller label). Visibility thus comes from the
//!    renderer's own occlusion, with no depth tolerance: a depth test with a relative
//!    tolerance lets a wall behind a bookshelf 5% nearer pass as seen, and then votes the
//!    wall into the bookshelf's mask.
//! 2. **A mask's points** P_m: the points seen in its own view with its label. Each point
//!    carries a weight w_m(p) ([`PointWeight`]): by default the number of m's interior
//!    pixels it wins, so that P_m measures the mask's *area*; `points` gives every point
//!    weight 1 (MaskClustering's count).
//! 3. **Observed and contained.** View k *observes* mask m when the points of P_m that
//!    carry a label in k hold at least `visible_ratio` of P_m's weight and are at least
//!    `observed_points` (3) in number. Among those, the label n with the most weight
//!    (ties: the smaller id) *contains* m when it holds more than `contained_ratio` of
//!    their weight; otherwise m is *split* in k. A mask observes and contains itself in
//!    its own view.
//!
//!    Why a number of points: with pixel weights one large Gaussian can hold a third of a
//!    small mask's weight, and a view that labels only that Gaussian then "observes" the
//!    mask and votes with one point. A 264-pixel table mask of a distant view, a third of
//!    whose weight one large Gaussian holds, was so contained in a mask of each of three
//!    views that labelled that Gaussian alone; with the floor mask of view 4 among its
//!    containers the table's cluster was consistent with that floor mask and took it, and
//!    the floor masks of two more views with it (seed 40, `default`: ScanNet19 −8.08
//!    against the baseline, −3.30 with the rule; measured in the crate README).
//!    MaskClustering's depth-map points are dense, so no single point weighs that much.
//!
//!    Why weights: MaskClustering's points come from depth maps at a uniform density, so
//!    counting points measures area. The Gaussians here come from triangulated matches,
//!    dense on texture and sparse on plain surfaces (a floor is covered by few large
//!    Gaussians, a sofa by many small ones). By count, a mask that is 64% floor and 36%
//!    sofa by area is mostly sofa points, is found contained in the sofa's masks, and
//!    joins the sofa's proposal, which then gives the sofa's class to the floor under it.
//!    By pixels it is split between the two wherever they are segmented apart, and is
//!    recognised as under-segmented (measured in the crate README).
//! 4. **Under-segmented masks**: split in more than `undersegment_ratio` of the *other*
//!    views that observe them (or with fewer than [`MIN_MASK_POINTS`] points). They join
//!    no proposal, and their votes are withdrawn: a mask contained in one loses that
//!    containment and the visibility of that view.
//!
//!    Why not its own view: a mask contains itself there whatever it covers, so that vote
//!    says nothing about whether it is whole, and counting it weighs most where the
//!    evidence is thinnest. A floor + bookshelf mask seen by three other views, split in two
//!    of them, was "split in 2 of 4" and kept; with its twin of the next view (each
//!    containing the other) it then made the floor and the bookshelf consistent, and the
//!    bookshelf's proposal took the floor (seed 15, `default`: 2,170 floor vertices
//!    labelled bookshelf; measured in the crate README). `own_view_votes` restores the
//!    count with the own view (MaskClustering's).
//! 5. **Nodes** start as the remaining masks, each with the set of views where it is
//!    contained (its *visible* views) and the set of masks that contain it. For two nodes,
//!    observers = |visible(A) ∩ visible(B)| and supporters = |containers(A) ∩
//!    containers(B)|; they are *consistent* when supporters >= `consensus` · observers
//!    (0.8; MaskClustering: 0.9).
//!
//!    Why 0.8: a view that splits one object into two masks holds two fragments of it
//!    apart, so fragments of one object carry "apart" votes that no merged object needs.
//!    Over the 32 `default` seeds 0-31, the cluster pairs left apart at 0.9 with a support
//!    rate in [0.8, 0.9) and three or more observers were one object 139 times and two
//!    objects 3 times (crate README, "Fragments and attached masks").
//! 6. **Iterations** over decreasing observer thresholds (the 95th, 90th, ..., 0th
//!    percentile of the observer counts of all node pairs with at least one observer,
//!    linear interpolation as numpy's default; a threshold of 1 or less ends the list
//!    below the 50th percentile and is raised to 1 above it): consistent pairs with at
//!    least that many observers are edges. The edges unite their nodes strongest first
//!    (more observers, then the higher rate supporters / observers, then the ids; petgraph's
//!    union-find), and a union is refused when the two clusters *as they stand by then*
//!    have observers and supporters < `union_ratio` · observers (0.6): fewer than three in
//!    five of the views that contain both hold them in one mask. Each resulting cluster
//!    becomes one node (visible views: union; containers: union). Pairs seen together by
//!    many views are decided first, when their evidence is strongest.
//!
//!    Why the check: consistency is a property of pairs, and uniting every consistent
//!    pair at once is single linkage again. A mask that merges a bookshelf with the wall
//!    behind it, seen merged in two views, is consistent with the bookshelf's cluster and
//!    with the wall's (two observers, two supporters each), and once both unions are made
//!    the bookshelf's descriptor is the wall's, though fifteen views hold the two apart.
//!    Checked cluster against cluster, the second union is refused (seed 5, `default`:
//!    measured in the crate README). The rate is about a majority, not `consensus`: an
//!    object that one view splits in two must still gather both halves through the whole
//!    masks of the other views, with that one view against (`union_ratio` = 0 unites every
//!    edge, the earlier rule).
//!
//!    Why 0.6, not 0.5: at 0.5 a tie passes, though half of the views that see both
//!    clusters hold them apart. On `harsh-segmentation` seed 9 a chair's cluster (17
//!    masks) and five south-wall masks, seen together by four views and held in one mask
//!    by two of them (merged chair + wall masks), were united, and
//!    the chair's vertices took *wall* (chair IoU 5.9 against the per-mask baseline's
//!    44.2; ScanNet19 −4.23 → +1.00 at 0.6). At 0.6 two of four, one of two and three of
//!    six are refused; two of three and three of five still unite (measured in the crate
//!    README).
//!
//! 7. **Link merge** (`link_merge`, on by default). The accepted warp links between
//!    clusters, strongest first, unite them where no view contradicts: no view contains
//!    both, or the consensus rate still holds. Points are sparse on textureless surfaces,
//!    so such masks are observed by few views, while the dense warps still see them
//!    overlap (`merge_along_links`).
//!
//! 8. **Attached masks** (`mask_instance`). An under-segmented mask belongs to no
//!    proposal, but it is still mostly one object: each of its points takes the cluster
//!    whose masks label it in the most other views (under-segmented masks not counted),
//!    and the mask is attached to the cluster whose points hold most of its weight w_m(p)
//!    (ties: the smaller root). It becomes an *instance* of that proposal, not a member:
//!    its pixels also cover the other object, so it registers its own feature, and the
//!    proposal's descriptor, membership and counts are unchanged.
//!
//!    Why per point: summed over the views, a label weighs as often as it is seen, and a
//!    small object that many views see (a cabinet) outvotes the floor that holds most of
//!    a floor + cabinet mask's area but is labelled in fewer views (its masks are often
//!    under-segmented themselves). Counted once per point, 21 of seed 12's 22 attached
//!    masks go to their own object's proposal, summed over the views 18.
//!
//! 9. **Shares.** Every mask's share s_m = (weight its best container holds) / (weight
//!    labelled), both summed over the other views that observe it (1 where none does),
//!    goes into the proposals file (`mask_share`); `fuse` weighs a member's mass by it,
//!    so that the part of a mask on a neighbouring object (a sofa mask merged with the
//!    cabinet beside it, not flagged because most views see only its sofa part) does not
//!    enter the proposal's descriptor in full.
//!
//! All counts are integers and every step runs in a fixed order, so the result does not
//! depend on the thread count. Memory: one label per (point, view) as u32 (V · N · 4
//! bytes; 160 MB for 200 views of 200,000 points) plus the masks' point lists and their
//! weights (a point is in at most one mask per view; the pixel counts of a view are
//! folded into the lists as the view is labelled and then dropped).
//!
//! [`Grouping::Consensus`]: crate::Grouping::Consensus

use std::collections::HashMap;

use petgraph::unionfind::UnionFind;
use rayon::prelude::*;
use serde::Serialize;

use crate::frame::NONE;
use crate::graph::{self, Link};

mod points;

pub(crate) use points::*;

/// A mask with fewer points than this cannot be judged; it counts as under-segmented.
pub const MIN_MASK_POINTS: usize = 5;

/// What a point of a mask weighs in the containment votes (module docs, steps 2-3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum PointWeight {
    /// The number of the mask's interior pixels the point wins in the mask's own view: the
    /// votes measure area, whatever the density of the Gaussians.
    #[default]
    Pixels,
    /// One per point (MaskClustering, whose depth-map points have a uniform density).
    Points,
}

impl PointWeight {
    /// Name used in metadata and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            PointWeight::Pixels => "pixels",
            PointWeight::Points => "points",
        }
    }
}

/// Parameters of the view-consensus grouping (MaskClustering's values are the defaults,
/// except `undersegment_ratio`, `own_view_votes`, `consensus` and `point_weight`: see the
/// module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ConsensusParams {
    /// A view observes a mask when the mask's points that carry a label there hold at
    /// least this share of their weight (MaskClustering: 0.3, by count).
    pub visible_ratio: f64,
    /// A view observes a mask only through at least this many of its points (1: any; see
    /// the module docs, step 3).
    pub observed_points: usize,
    /// A mask is contained in a mask of another view when more than this share of the
    /// weight of its labelled points there carries that mask's label (MaskClustering: 0.8,
    /// by count).
    pub contained_ratio: f64,
    /// A mask split in more than this share of the other views that observe it is
    /// under-segmented (MaskClustering: 0.3, counting the own view).
    pub undersegment_ratio: f64,
    /// Whether the mask's own view (which always contains it) counts among the views
    /// judging it under-segmented, as in MaskClustering; by default it does not (module
    /// docs, step 4).
    pub own_view_votes: bool,
    /// Two nodes are consistent when supporters >= this · observers (MaskClustering: 0.9;
    /// see the module docs, step 5).
    pub consensus: f64,
    /// Within an iteration, the union of two clusters is refused when their supporters <
    /// this · their observers (as the clusters stand when the union comes up; 0.6, so that
    /// a tie is refused: see the module docs, step 6); 0 unites every consistent pair
    /// (single linkage within an iteration).
    pub union_ratio: f64,
    /// Most Gaussians tracked as points (every k-th beyond; all of them are rendered).
    pub max_points: usize,
    /// After the iterations, unite clusters along the accepted warp links (strongest
    /// first) where the views hold no evidence against it: no view contains both, or the
    /// consensus rate still holds (see the module docs, step 7).
    pub link_merge: bool,
    /// What a mask's point weighs in the votes.
    pub point_weight: PointWeight,
}

impl Default for ConsensusParams {
    fn default() -> Self {
        ConsensusParams {
            visible_ratio: 0.3,
            observed_points: 3,
            contained_ratio: 0.8,
            undersegment_ratio: 0.5,
            own_view_votes: false,
            consensus: 0.8,
            union_ratio: 0.6,
            max_points: 200_000,
            link_merge: true,
            point_weight: PointWeight::Pixels,
        }
    }
}

/// What the consensus grouping did, for the report.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize)]
pub struct ConsensusStats {
    /// Points (Gaussian centres) used.
    pub points: u64,
    /// Masks found under-segmented (in no proposal).
    pub undersegmented: u64,
    /// Observer thresholds of the iterations, in order.
    pub thresholds: Vec<u32>,
    /// Consistent pairs per iteration (edges of that iteration's graph).
    pub edges: Vec<u64>,
    /// Unions refused per iteration because the clusters the edge would join had become
    /// inconsistent at `union_ratio` (step 6).
    pub refused: Vec<u64>,
    /// Unions made by the final pass along the warp links.
    pub link_merges: u64,
    /// Under-segmented masks attached to a cluster as its instance (step 8).
    pub attached: u64,
}

/// What [`cluster`] found.
pub(crate) struct Clustering {
    /// Per mask: the smallest mask of its cluster.
    pub root: Vec<u32>,
    /// Per mask: under-segmented (in no proposal).
    pub under: Vec<bool>,
    /// Per under-segmented mask: the root of the cluster it is attached to (step 8), NONE
    /// for the other masks and where none is found.
    pub attached: Vec<u32>,
    /// Per mask: its share (the proposals file's `mask_share`; see the module docs).
    pub share: Vec<f32>,
    /// For the report.
    pub stats: ConsensusStats,
}

/// A cluster of masks during the iterations.
#[derive(Debug, Clone)]
struct Node {
    masks: Vec<u32>,
    visible: Vec<u64>,
    containers: Vec<u32>,
}

impl Node {
    /// Takes `other`'s masks, visible views and containers (the union of two clusters);
    /// [`Node::tidy`] restores the sorted sets.
    fn absorb(&mut self, other: Node) {
        self.masks.extend(other.masks);
        self.visible
            .iter_mut()
            .zip(&other.visible)
            .for_each(|(p, q)| *p |= q);
        self.containers.extend(other.containers);
    }

    fn tidy(&mut self) {
        self.masks.sort_unstable();
        self.containers.sort_unstable();
        self.containers.dedup();
    }

    /// Views that contain both clusters (observers).
    fn observers(&self, other: &Node) -> u32 {
        popcount_and(&self.visible, &other.visible)
    }

    /// Whether the views containing both put them in one mask often enough: supporters >=
    /// `consensus` · `observers` (module docs, step 5).
    fn supported(&self, other: &Node, observers: u32, consensus: f64) -> bool {
        holds(
            common(&self.containers, &other.containers),
            observers,
            consensus,
        )
    }
}

/// The consensus rule: supporters >= `rate` · observers.
fn holds(supporters: u32, observers: u32, rate: f64) -> bool {
    f64::from(supporters) >= rate * f64::from(observers)
}

fn popcount_and(a: &[u64], b: &[u64]) -> u32 {
    a.iter().zip(b).map(|(x, y)| (x & y).count_ones()).sum()
}

/// numpy's default (linear) percentile of a histogram of integer values.
fn percentile(hist: &[u64], q: f64) -> f64 {
    let n: u64 = hist.iter().sum();
    if n == 0 {
        return 0.0;
    }
    let pos = q / 100.0 * (n - 1) as f64;
    let (lo, frac) = (pos.floor() as u64, pos - pos.floor());
    let at = |rank: u64| {
        let mut seen = 0u64;
        for (v, c) in hist.iter().enumerate() {
            seen += c;
            if seen > rank {
                return v as f64;
            }
        }
        (hist.len() - 1) as f64
    };
    let a = at(lo);
    if frac == 0.0 {
        return a;
    }
    a + frac * (at((lo + 1).min(n - 1)) - a)
}

/// The observer thresholds of the iterations (MaskClustering's rule, see the module docs).
fn observer_thresholds(nodes: &[Node], views: usize) -> Vec<u32> {
    let mut hist = (0..nodes.len())
        .into_par_iter()
        .map(|a| {
            let mut h = vec![0u64; views + 1];
            for b in a + 1..nodes.len() {
                h[popcount_and(&nodes[a].visible, &nodes[b].visible) as usize] += 1;
            }
            h
        })
        .reduce(
            || vec![0u64; views + 1],
            |mut x, y| {
                x.iter_mut().zip(&y).for_each(|(p, q)| *p += q);
                x
            },
        );
    hist[0] = 0;
    let mut out = Vec::new();
    for q in (0..=19).map(|k| 95 - 5 * k) {
        let mut t = percentile(&hist, f64::from(q));
        if t <= 1.0 {
            if q < 50 {
                break;
            }
            t = 1.0;
        }
        // Observer counts are integers: ">= 2.5" is ">= 3".
        out.push(t.ceil() as u32);
    }
    out
}

/// Sorted-set intersection size.
fn common(a: &[u32], b: &[u32]) -> u32 {
    let (mut i, mut j, mut n) = (0, 0, 0);
    while i < a.len() && j < b.len() {
        match a[i].cmp(&b[j]) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                n += 1;
                i += 1;
                j += 1;
            }
        }
    }
    n
}

/// Clusters of nodes being united: petgraph's union-find over the node indices, each
/// root holding the union of its nodes.
struct Clusters {
    uf: UnionFind<u32>,
    nodes: Vec<Option<Node>>,
}

impl Clusters {
    fn new(nodes: Vec<Node>) -> Self {
        Clusters {
            uf: UnionFind::new(nodes.len()),
            nodes: nodes.into_iter().map(Some).collect(),
        }
    }

    /// Unites the clusters of nodes `a` and `b` unless they are one already or `allow`
    /// refuses the two clusters as they stand; whether they were united.
    fn unite(&mut self, a: u32, b: u32, allow: impl FnOnce(&Node, &Node) -> bool) -> bool {
        let (ra, rb) = (self.uf.find(a) as usize, self.uf.find(b) as usize);
        if ra == rb {
            return false;
        }
        let (Some(na), Some(nb)) = (&self.nodes[ra], &self.nodes[rb]) else {
            return false;
        };
        if !allow(na, nb) {
            return false;
        }
        self.uf.union(ra as u32, rb as u32);
        let root = self.uf.find(ra as u32) as usize;
        let from = if root == ra { rb } else { ra };
        if let Some(n) = self.nodes[from].take() {
            if let Some(r) = self.nodes[root].as_mut() {
                r.absorb(n);
                r.tidy();
            }
        }
        true
    }

    /// The clusters in order of their smallest mask.
    fn into_nodes(self) -> Vec<Node> {
        let mut out: Vec<Node> = self.nodes.into_iter().flatten().collect();
        out.sort_unstable_by_key(|n| n.masks[0]);
        out
    }
}

/// What one iteration did: its edges and the unions it refused.
struct Iteration {
    nodes: Vec<Node>,
    edges: u64,
    refused: u64,
}

/// One iteration: the consistent pairs with at least `threshold` observers, and the
/// nodes merged along them, strongest first, each union checked at `union_ratio` (module
/// docs, step 6).
fn iterate(nodes: Vec<Node>, threshold: u32, p: &ConsensusParams, masks: usize) -> Iteration {
    // Nodes by container: pairs sharing none have no supporter and are never consistent.
    let mut by_container: Vec<Vec<u32>> = vec![Vec::new(); masks];
    for (x, n) in nodes.iter().enumerate() {
        for &c in &n.containers {
            by_container[c as usize].push(x as u32);
        }
    }
    let nodes_ref = &nodes;
    let by_container = &by_container;
    // (a, b, observers, supporters) of every consistent pair.
    let mut edges: Vec<(u32, u32, u32, u32)> = (0..nodes.len())
        .into_par_iter()
        .flat_map_iter(|a| {
            let na = &nodes_ref[a];
            let mut partners: Vec<u32> = na
                .containers
                .iter()
                .flat_map(|&c| by_container[c as usize].iter().copied())
                .filter(|&b| b as usize > a)
                .collect();
            partners.sort_unstable();
            partners.dedup();
            partners
                .into_iter()
                .filter_map(|b| {
                    let nb = &nodes_ref[b as usize];
                    let observers = na.observers(nb);
                    let supporters = common(&na.containers, &nb.containers);
                    let consistent =
                        observers >= threshold.max(1) && holds(supporters, observers, p.consensus);
                    consistent.then_some((a as u32, b, observers, supporters))
                })
                .collect::<Vec<_>>()
        })
        .collect();
    // More observers first, then the higher support rate (cross-multiplied: integers),
    // then the ids.
    edges.sort_unstable_by(|x, y| {
        y.2.cmp(&x.2)
            .then((u64::from(y.3) * u64::from(x.2)).cmp(&(u64::from(x.3) * u64::from(y.2))))
            .then((x.0, x.1).cmp(&(y.0, y.1)))
    });
    let mut clusters = Clusters::new(nodes);
    let mut refused = 0u64;
    for &(a, b, _, _) in &edges {
        let mut inconsistent = false;
        let united = clusters.unite(a, b, |na, nb| {
            let observers = na.observers(nb);
            inconsistent = observers > 0 && !na.supported(nb, observers, p.union_ratio);
            !inconsistent
        });
        refused += u64::from(!united && inconsistent);
    }
    Iteration {
        nodes: clusters.into_nodes(),
        edges: edges.len() as u64,
        refused,
    }
}

/// Step 7: the warp links between clusters, strongest first (the smaller IoU of the two
/// directions, ties by mask ids), unite them when no view contradicts: observers = 0, or
/// supporters >= `consensus` · observers with the clusters as they are at that moment.
/// Points are sparse where surfaces have little texture (a floor, a plain wall), so such
/// masks are observed by few views and the iterations leave them apart, while the dense
/// warps still see them overlap. Links of under-segmented masks take no part.
fn merge_along_links(
    nodes: Vec<Node>,
    links: &[Link],
    under: &[bool],
    consensus: f64,
) -> (Vec<Node>, u64) {
    let mut node_of = vec![u32::MAX; under.len()];
    for (x, n) in nodes.iter().enumerate() {
        for &m in &n.masks {
            node_of[m as usize] = x as u32;
        }
    }
    let mut order: Vec<&Link> = links
        .iter()
        .filter(|l| l.masks.iter().all(|&m| !under[m as usize]))
        .collect();
    order.sort_by(|p, q| q.iou.total_cmp(&p.iou).then(p.masks.cmp(&q.masks)));
    let mut clusters = Clusters::new(nodes);
    let mut merges = 0u64;
    for l in order {
        let (a, b) = (node_of[l.masks[0] as usize], node_of[l.masks[1] as usize]);
        let united = clusters.unite(a, b, |na, nb| {
            let observers = na.observers(nb);
            observers == 0 || na.supported(nb, observers, consensus)
        });
        merges += u64::from(united);
    }
    (clusters.into_nodes(), merges)
}

/// The consensus clustering of all masks: per global mask its cluster root (a global
/// mask id, the cluster's smallest member; under-segmented masks are their own roots and
/// flagged), plus statistics.
pub(crate) fn cluster(
    labels: &[Vec<u32>],
    mask_points: &MaskPoints,
    offsets: &[u32],
    points: usize,
    links: &[Link],
    p: &ConsensusParams,
) -> Clustering {
    let views = labels.len();
    let masks = offsets.last().map_or(0, |m| *m as usize);
    let view_of = graph::views_of_masks(offsets);
    let mut votes: Vec<MaskVotes> = (0..masks)
        .into_par_iter()
        .map(|m| {
            let (pts, wts) = (&mask_points.points[m], &mask_points.weights[m]);
            mask_votes(pts, wts, view_of[m] as usize, m as u32, labels, offsets, p)
        })
        .collect();
    let share: Vec<f32> = votes.iter().map(|v| v.share).collect();
    // Withdraw the votes of under-segmented masks.
    let under: Vec<bool> = votes.iter().map(|v| v.undersegmented).collect();
    for v in &mut votes {
        let visible = &mut v.visible;
        v.containers.retain(|&c| {
            let withdrawn = under[c as usize];
            if withdrawn {
                let view = view_of[c as usize] as usize;
                visible[view / 64] &= !(1 << (view % 64));
            }
            !withdrawn
        });
    }
    let mut nodes: Vec<Node> = votes
        .into_iter()
        .enumerate()
        .filter(|(m, _)| !under[*m])
        .map(|(m, v)| Node {
            masks: vec![m as u32],
            visible: v.visible,
            containers: v.containers,
        })
        .collect();
    let thresholds = observer_thresholds(&nodes, views);
    let mut stats = ConsensusStats {
        points: points as u64,
        undersegmented: under.iter().filter(|u| **u).count() as u64,
        thresholds: thresholds.clone(),
        edges: Vec::new(),
        refused: Vec::new(),
        link_merges: 0,
        attached: 0,
    };
    for t in thresholds {
        let it = iterate(nodes, t, p, masks);
        nodes = it.nodes;
        stats.edges.push(it.edges);
        stats.refused.push(it.refused);
    }
    if p.link_merge {
        let (next, merges) = merge_along_links(nodes, links, &under, p.consensus);
        nodes = next;
        stats.link_merges = merges;
    }
    let mut root: Vec<u32> = (0..masks as u32).collect();
    for n in &nodes {
        let r = n.masks[0];
        for &m in &n.masks {
            root[m as usize] = r;
        }
    }
    let attached = attach(labels, mask_points, offsets, &view_of, &root, &under);
    stats.attached = attached.iter().filter(|a| **a != NONE).count() as u64;
    Clustering {
        root,
        under,
        attached,
        share,
        stats,
    }
}

/// Step 8: the cluster each under-segmented mask is attached to (its root), or NONE for
/// the other masks and where none is found. Every point of the mask takes the cluster
/// whose masks label it in the most other views (under-segmented masks not counted; ties:
/// the smaller root) and adds its weight w_m(p) to it; the cluster with the most weight
/// wins (ties: the smaller root).
fn attach(
    labels: &[Vec<u32>],
    mask_points: &MaskPoints,
    offsets: &[u32],
    view_of: &[u32],
    root: &[u32],
    under: &[bool],
) -> Vec<u32> {
    (0..under.len())
        .into_par_iter()
        .map(|m| {
            if !under[m] {
                return NONE;
            }
            let own = view_of[m] as usize;
            let mut area: HashMap<u32, u64> = HashMap::new();
            let mut views: HashMap<u32, u32> = HashMap::new();
            for (&g, &w) in mask_points.points[m].iter().zip(&mask_points.weights[m]) {
                views.clear();
                for (k, lk) in labels.iter().enumerate() {
                    let l = lk[g as usize];
                    if k == own || l == NONE {
                        continue;
                    }
                    let n = (offsets[k] + l) as usize;
                    if !under[n] {
                        *views.entry(root[n]).or_insert(0) += 1;
                    }
                }
                if let Some((r, _)) = most(&views) {
                    *area.entry(r).or_insert(0) += u64::from(w);
                }
            }
            most(&area).map_or(NONE, |(r, _)| r)
        })
        .collect()
}

/// The key with the largest count and that count (ties: the smaller key).
fn most<C: Ord + Copy>(counts: &HashMap<u32, C>) -> Option<(u32, C)> {
    counts
        .iter()
        .max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0)))
        .map(|(k, c)| (*k, *c))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentile_matches_numpy_linear() {
        // np.percentile([1, 2, 2, 5], q) for q = 0, 50, 95, 100: 1, 2, 4.55, 5.
        let mut hist = vec![0u64; 6];
        for v in [1usize, 2, 2, 5] {
            hist[v] += 1;
        }
        assert_eq!(percentile(&hist, 0.0), 1.0);
        assert_eq!(percentile(&hist, 50.0), 2.0);
        assert!((percentile(&hist, 95.0) - 4.55).abs() < 1e-12);
        assert_eq!(percentile(&hist, 100.0), 5.0);
    }

    #[test]
    fn points_take_the_majority_label_of_the_pixels_they_win() {
        // Gaussians 0..6, every 2nd tracked (points 0, 1, 2 = Gaussians 0, 2, 4).
        assert_eq!(point_stride(6, 3), 2);
        let ids = [0, 0, 0, 2, 2, 4, 1, 1, 1, 9, 4, 4];
        let plane = [5, 5, 7, 3, NONE, NONE, 5, 5, 5, 5, 6, 6];
        // Width 12 and height 1: only pixels between two equal neighbours are interior
        // (0, 8 and 11 sit at the border with one neighbour).
        // Gaussian 0: pixels 0, 1 (label 5; pixel 2 is boundary) -> 5. Gaussian 2: pixel 3
        // is boundary, pixel 4 interior "none" -> NONE. Gaussian 4: pixels 5 (boundary),
        // 10 (boundary), 11 (6) -> 6. Gaussian 1 is not tracked, 9 is no Gaussian.
        // Only interior pixels count: Gaussian 0 wins pixel 0 (pixel 1 is boundary),
        // Gaussian 4 pixel 11.
        let seen = view_point_labels(&ids, &plane, 12, 6, 2);
        assert_eq!(seen.labels, vec![5, NONE, 6]);
        assert_eq!(seen.pixels, vec![1, 0, 1]);
        // Nothing tracked wins a pixel: every point unlabelled.
        let none = view_point_labels(&[1, 3], &[0, 0], 2, 6, 2);
        assert_eq!(none.labels, vec![NONE; 3]);
        assert_eq!(none.pixels, vec![0; 3]);
        // A 4 x 4 image of one label: every pixel is interior (neighbourhoods are clipped
        // at the border); Gaussian 0 wins 15 of them, Gaussian 2 one.
        let ids = [0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 2, 0, 0, 0, 0, 0];
        let seen = view_point_labels(&ids, &[3; 16], 4, 4, 2);
        assert_eq!(seen.labels, vec![3, 3]);
        assert_eq!(seen.pixels, vec![15, 1]);
    }

    /// Mask points from point labels (offsets as in `cluster`), every point winning
    /// `pixels[g]` pixels in every view.
    fn mask_points(
        labels: &[Vec<u32>],
        offsets: &[u32],
        pixels: &[u32],
        weight: PointWeight,
    ) -> MaskPoints {
        let masks = offsets.last().map_or(0, |m| *m as usize);
        let mut points = MaskPoints::new(masks, weight);
        for (v, l) in labels.iter().enumerate() {
            let view = ViewPoints {
                labels: l.clone(),
                pixels: pixels.to_vec(),
            };
            points.add_view(offsets[v], &view);
        }
        points
    }

    /// Mask points of one pixel each (so either weight mode gives the point counts).
    fn unit_points(labels: &[Vec<u32>], offsets: &[u32]) -> MaskPoints {
        let n = labels.first().map_or(0, Vec::len);
        mask_points(labels, offsets, &vec![1; n], PointWeight::Pixels)
    }

    /// A merged mask over a densely and a sparsely sampled object (a sofa of many small
    /// Gaussians, a floor of a few large ones): by count its points are 30 of 36 sofa, so
    /// the sofa's masks contain it and it joins the sofa; by the pixels each point wins
    /// (sofa 30, floor 60) the sofa holds a third of it, it is split wherever the two are
    /// segmented apart, and it is under-segmented.
    #[test]
    fn pixel_weights_find_a_merged_mask_that_point_counts_take_for_the_dense_object() {
        let sofa = |g: usize| g < 30;
        // Views 1-4 separate sofa (label 0) and floor (label 1); view 0 merges them.
        let mut labels = vec![vec![0u32; 36]];
        labels.extend((0..4).map(|_| (0..36).map(|g| u32::from(!sofa(g))).collect()));
        let offsets = [0, 1, 3, 5, 7, 9];
        let pixels: Vec<u32> = (0..36).map(|g| if sofa(g) { 1 } else { 10 }).collect();
        let build = |weight| mask_points(&labels, &offsets, &pixels, weight);
        let p = ConsensusParams {
            point_weight: PointWeight::Points,
            ..ConsensusParams::default()
        };
        let Clustering { root, under, .. } =
            cluster(&labels, &build(PointWeight::Points), &offsets, 36, &[], &p);
        assert_eq!(under, vec![false; 9]);
        // Mask 0 (the merged one) and the sofa masks 1, 3, 5, 7 form one cluster.
        assert_eq!(root, vec![0, 0, 2, 0, 2, 0, 2, 0, 2]);
        let p = ConsensusParams::default();
        assert_eq!(p.point_weight, PointWeight::Pixels);
        let Clustering {
            root,
            under,
            attached,
            share,
            stats,
        } = cluster(&labels, &build(PointWeight::Pixels), &offsets, 36, &[], &p);
        assert_eq!(
            under,
            vec![true, false, false, false, false, false, false, false, false]
        );
        assert_eq!(root, vec![0, 1, 2, 1, 2, 1, 2, 1, 2]);
        assert_eq!(stats.undersegmented, 1);
        // It is attached to the floor, which holds 60 of its 90 pixel-weights.
        assert_eq!(
            attached,
            [2, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE]
        );
        // The merged mask's share: the floor's 60 of the 90 pixel-weights each other view
        // labels; every other mask lies on one object in every view (the merged view
        // holds each whole).
        assert_eq!(share[0], (60.0f64 / 90.0) as f32);
        assert_eq!(share[1..], [1.0; 8]);
    }

    /// A small table mask (view 0: points 0-5 of one pixel each, and point 6, a large
    /// floor Gaussian seen through it that wins 4 of its 10 pixels) and a floor mask of
    /// view 1 (points 6-11; the table is hidden there). Each view labels only point 6 of
    /// the other's mask, which holds 0.3 of its weight or more: with any number of points
    /// each view observes and contains the other's mask through that one point, the two
    /// are consistent (two observers, two supporters) and unite; with three points
    /// needed, neither view observes the other's mask and they stay apart.
    #[test]
    fn one_large_gaussian_does_not_make_an_observation() {
        let labels = vec![
            vec![0, 0, 0, 0, 0, 0, 0, NONE, NONE, NONE, NONE, NONE],
            vec![NONE, NONE, NONE, NONE, NONE, NONE, 0, 0, 0, 0, 0, 0],
        ];
        let offsets = [0, 1, 2];
        let mut pixels = vec![1u32; 12];
        pixels[6] = 4;
        let points = mask_points(&labels, &offsets, &pixels, PointWeight::Pixels);
        let run = |observed_points| {
            let p = ConsensusParams {
                observed_points,
                ..ConsensusParams::default()
            };
            cluster(&labels, &points, &offsets, 12, &[], &p)
        };
        let any = run(1);
        assert_eq!(any.under, vec![false, false]);
        assert_eq!(any.root, vec![0, 0]);
        assert_eq!(ConsensusParams::default().observed_points, 3);
        let three = run(3);
        assert_eq!(three.under, vec![false, false]);
        assert_eq!(three.root, vec![0, 1]);
    }

    /// Five views see two objects (points 0-9 and 10-19). Views 0-3 separate them; view 4
    /// has one mask over both (under-segmented). Consensus keeps the objects apart and
    /// drops the merged mask, where plain components over "shares points" links would
    /// join everything.
    #[test]
    fn an_undersegmented_mask_does_not_bridge_two_objects() {
        let obj = |g: usize| u32::from(g >= 10);
        let mut labels: Vec<Vec<u32>> = (0..4)
            .map(|v| {
                (0..20)
                    .map(|g| if v % 2 == 0 { obj(g) } else { 1 - obj(g) })
                    .collect()
            })
            .collect();
        labels.push(vec![0; 20]);
        let offsets = [0, 2, 4, 6, 8, 9];
        // The merged mask links to every other mask (as a warp link would).
        let links: Vec<Link> = (0..8)
            .map(|m| Link {
                masks: [m, 8],
                iou: 0.5,
                box_iou: 0.5,
            })
            .collect();
        let points = unit_points(&labels, &offsets);
        let Clustering {
            root, under, stats, ..
        } = cluster(
            &labels,
            &points,
            &offsets,
            20,
            &links,
            &ConsensusParams::default(),
        );
        assert_eq!(
            under,
            vec![false, false, false, false, false, false, false, false, true]
        );
        // Object 0: masks 0 (v0), 3 (v1), 4 (v2), 7 (v3); object 1: 1, 2, 5, 6.
        assert_eq!(root, vec![0, 1, 1, 0, 0, 1, 1, 0, 8]);
        assert_eq!(stats.undersegmented, 1);
        assert_eq!(stats.link_merges, 0);
    }

    /// A bookshelf (points 40-49) against a wall (points 0-39), merged into one mask in
    /// views 0 and 1, and apart in views 2-7, which see only a corner of each (5 points
    /// of each, too little of the merged masks to observe them). Each merged mask is
    /// consistent with the wall's cluster and with the bookshelf's (two observers, two
    /// supporters), while the two clusters are seen together by eight views and held in
    /// one mask by two. Uniting every consistent pair (`union_ratio` 0) makes one cluster
    /// of all; checked cluster against cluster, the merged masks join the wall (first in
    /// id order) and the bookshelf stays apart.
    #[test]
    fn a_mask_consistent_with_two_clusters_does_not_unite_them() {
        let mut labels = vec![vec![0u32; 50], vec![0u32; 50]];
        labels.extend((0..6).map(|_| {
            (0..50)
                .map(|g| match g {
                    35..40 => 0,
                    45..50 => 1,
                    _ => NONE,
                })
                .collect::<Vec<u32>>()
        }));
        let offsets = [0, 1, 2, 4, 6, 8, 10, 12, 14];
        let points = unit_points(&labels, &offsets);
        let wall = [2, 4, 6, 8, 10, 12];
        let bookshelf = [3, 5, 7, 9, 11, 13];
        let run = |union_ratio| {
            let p = ConsensusParams {
                union_ratio,
                ..ConsensusParams::default()
            };
            cluster(&labels, &points, &offsets, 50, &[], &p)
        };

        let single = run(0.0);
        assert_eq!(single.under, vec![false; 14]);
        assert_eq!(single.root, vec![0; 14]);
        assert_eq!(single.stats.refused.iter().sum::<u64>(), 0);

        let guarded = run(ConsensusParams::default().union_ratio);
        assert_eq!(guarded.under, vec![false; 14]);
        for m in [0, 1].into_iter().chain(wall) {
            assert_eq!(guarded.root[m], 0, "mask {m}");
        }
        for m in bookshelf {
            assert_eq!(guarded.root[m], 3, "mask {m}");
        }
        assert!(guarded.stats.refused.iter().sum::<u64>() >= 1);
    }

    /// A floor (points 0-19) and a bookshelf (points 20-39) merged into one mask in views 0
    /// and 1 (each containing the other) and apart in views 2 and 3. A merged mask is
    /// split in two of the three other views that observe it: under-segmented, so the
    /// floor and the bookshelf stay apart. Counting its own view it is split in two of
    /// four, not more than half, and it makes the two objects consistent (each is seen
    /// together with it in views 0 and 1); the clusters then stand at two views together
    /// against two apart, a tie, which the union check refuses at its default 0.6 and
    /// passes at 0.5.
    #[test]
    fn a_merged_mask_split_by_most_other_views_is_undersegmented() {
        let floor_first: Vec<u32> = (0..40).map(|g| u32::from(g >= 20)).collect();
        let bookshelf_first: Vec<u32> = floor_first.iter().map(|&l| 1 - l).collect();
        let labels = vec![vec![0; 40], vec![0; 40], floor_first, bookshelf_first];
        // Masks: 0 (view 0, merged), 1 (view 1, merged), 2 floor and 3 bookshelf (view
        // 2), 4 bookshelf and 5 floor (view 3).
        let offsets = [0, 1, 2, 4, 6];
        let points = unit_points(&labels, &offsets);
        let run = |own_view_votes, union_ratio| {
            let p = ConsensusParams {
                own_view_votes,
                union_ratio,
                ..ConsensusParams::default()
            };
            cluster(&labels, &points, &offsets, 40, &[], &p)
        };
        let default_ratio = ConsensusParams::default().union_ratio;

        let judged_by_others = run(false, default_ratio);
        assert_eq!(
            judged_by_others.under,
            vec![true, true, false, false, false, false]
        );
        assert_eq!(judged_by_others.root, vec![0, 1, 2, 3, 3, 2]);

        let own_votes = run(true, 0.5);
        assert_eq!(own_votes.under, vec![false; 6]);
        assert_eq!(own_votes.root, vec![0; 6]);
        let tie_refused = run(true, default_ratio);
        assert_eq!(tie_refused.under, vec![false; 6]);
        // The merged masks join the floor (the first union in id order); the bookshelf,
        // two views together against two apart, stays out.
        assert_eq!(tie_refused.root, vec![0, 0, 0, 3, 3, 0]);
        assert!(tie_refused.stats.refused.iter().sum::<u64>() >= 1);
    }

    /// Two merged masks (views 0 and 1) over a floor of 24 points and a bookshelf of 16,
    /// split by views 2 and 3; views 4 and 5 see only ten bookshelf points. Summed over
    /// the views, the bookshelf's label weighs more (10 · 4 + 6 · 2 = 52 against 24 · 2):
    /// counted once per point, the floor holds most of each mask's area (24 of 40), and both
    /// are attached to it, as instances of the floor, not members.
    #[test]
    fn an_undersegmented_mask_is_attached_to_the_cluster_holding_most_of_its_area() {
        let floor = |g: usize| g < 24;
        let split: Vec<u32> = (0..40).map(|g| u32::from(!floor(g))).collect();
        let swapped: Vec<u32> = split.iter().map(|&l| 1 - l).collect();
        let part: Vec<u32> = (0..40)
            .map(|g| if (24..34).contains(&g) { 0 } else { NONE })
            .collect();
        let labels = vec![vec![0; 40], vec![0; 40], split, swapped, part.clone(), part];
        // Masks: 0, 1 merged; 2 floor and 3 bookshelf (view 2); 4 bookshelf and 5 floor
        // (view 3); 6, 7 part of the bookshelf (views 4, 5).
        let offsets = [0, 1, 2, 4, 6, 7, 8];
        let points = unit_points(&labels, &offsets);
        let found = cluster(
            &labels,
            &points,
            &offsets,
            40,
            &[],
            &ConsensusParams::default(),
        );

        assert_eq!(
            found.under,
            [true, true, false, false, false, false, false, false]
        );
        assert_eq!(found.root, [0, 1, 2, 3, 3, 2, 3, 3]);
        assert_eq!(found.attached, [2, 2, NONE, NONE, NONE, NONE, NONE, NONE]);
        assert_eq!(found.stats.attached, 2);
        // In the proposals: members keep their proposal, the merged masks take the
        // floor's as their instance only.
        let proposal = [NONE, NONE, 0, 1, 1, 0, 1, 1];
        assert_eq!(
            graph::instances(&proposal, &found.attached),
            [0, 0, 0, 1, 1, 0, 1, 1]
        );
        // A mask whose cluster was dropped (here: the floor's) is attached to nothing.
        let dropped = [NONE, NONE, NONE, 0, 0, NONE, 0, 0];
        assert_eq!(
            graph::instances(&dropped, &found.attached),
            [NONE, NONE, NONE, 0, 0, NONE, 0, 0]
        );
    }

    /// A split object: view 0 has two halves, views 1-4 the whole. The halves are each
    /// contained in the whole masks and end in one cluster; the whole masks are split in
    /// one view of five, a minority, so none is taken for under-segmented.
    #[test]
    fn split_halves_join_through_the_whole_masks() {
        let mut labels = vec![(0..20).map(|g| u32::from(g >= 10)).collect::<Vec<u32>>()];
        labels.extend((0..4).map(|_| vec![0; 20]));
        let offsets = [0, 2, 3, 4, 5, 6];
        let points = unit_points(&labels, &offsets);
        let p = ConsensusParams::default();
        let Clustering {
            root, under, share, ..
        } = cluster(&labels, &points, &offsets, 20, &[], &p);
        assert_eq!(under, vec![false; 6]);
        assert_eq!(root, vec![0; 6]);
        // A half lies on one mask everywhere; a whole mask is half in each of view 0's
        // halves and whole in the other three views: (10 + 3 · 20) / (4 · 20).
        assert_eq!(share[..2], [1.0, 1.0]);
        assert_eq!(share[2..], [(70.0f64 / 80.0) as f32; 4]);
    }

    /// Two masks that no view observes together (disjoint point sets, as on a floor seen
    /// in parts) are joined by a warp link only with `link_merge`.
    #[test]
    fn link_merge_joins_clusters_no_view_contradicts() {
        // Points 0-9 seen only in views 0 and 1, points 10-19 only in views 2 and 3.
        let part = |lo: usize, hi: usize| -> Vec<u32> {
            (0..20)
                .map(|g| if (lo..hi).contains(&g) { 0 } else { NONE })
                .collect()
        };
        let labels = vec![part(0, 10), part(0, 10), part(10, 20), part(10, 20)];
        let offsets = [0, 1, 2, 3, 4];
        let links = [Link {
            masks: [1, 2],
            iou: 0.3,
            box_iou: 0.3,
        }];
        let mut p = ConsensusParams::default();
        let points = unit_points(&labels, &offsets);
        let Clustering { root, stats, .. } = cluster(&labels, &points, &offsets, 20, &links, &p);
        assert_eq!(root, vec![0, 0, 0, 0]);
        assert_eq!(stats.link_merges, 1);
        p.link_merge = false;
        let Clustering { root, .. } = cluster(&labels, &points, &offsets, 20, &links, &p);
        assert_eq!(root, vec![0, 0, 2, 2]);
    }
}

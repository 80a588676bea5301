//! Warp-graph split over view pairs: the evidence of a range of view pairs (its accepted
//! links and counters), as a value and as a `profuse.warp_partial` file, and the merge of
//! shards back into the evidence of one run.
//!
//! Why a shard's links are all the grouping needs: a view pair's links come from its two
//! warps alone (the mutual test reads the overlaps of (i, j) and (j, i), nothing of other
//! pairs), and every float the grouping reads (the link scores) is computed inside its
//! pair. Counters are integers. So concatenating shards' links in view-pair order rebuilds
//! the very list of an unsharded run, whatever order the shards finished in. What the
//! grouping computes per view (mask extents, the consensus' top-1 renders) is not
//! evidence: the merge computes it as an unsharded run does.

use profuse_formats::{WarpPartial, WARP_COUNTERS};

use crate::graph::Link;
use crate::{CellCounts, PairResult, Rejections};

/// The evidence of consecutive view pairs `first_pair .. first_pair + pairs.len()`.
#[derive(Debug, Clone, PartialEq)]
pub struct Evidence {
    /// Index of the first pair in the run's list of view pairs.
    pub first_pair: usize,
    /// The view pairs (i < j), in the run's order.
    pub pairs: Vec<[u32; 2]>,
    /// Pair p's links are `edges[edge_offsets[p] .. edge_offsets[p + 1]]`.
    pub edge_offsets: Vec<u64>,
    /// Accepted links, in view-pair order.
    pub edges: Vec<Link>,
    /// The gate over the pairs' warps.
    pub cells: CellCounts,
    /// Rejected candidates.
    pub rejections: Rejections,
    /// Candidate links tested.
    pub tested: u64,
    /// Pairs skipped (a warp missing under `require_both_warps`).
    pub skipped: u64,
}

/// Why shards do not merge into the evidence of one run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ShardMismatch {
    /// A shard was computed from other inputs or parameters.
    Inputs {
        /// The shard file.
        shard: String,
        /// The differing metadata key.
        field: &'static str,
        /// This run's value.
        expected: String,
        /// The shard's value.
        found: String,
    },
    /// The shards leave view pairs out, or cover some twice.
    Coverage(String),
}

impl std::fmt::Display for ShardMismatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ShardMismatch::Inputs {
                shard,
                field,
                expected,
                found,
            } => write!(
                f,
                "{shard} was made from other inputs or parameters: metadata `{field}` is \
                 {found:?}, this run's is {expected:?}"
            ),
            ShardMismatch::Coverage(detail) => f.write_str(detail),
        }
    }
}

impl std::error::Error for ShardMismatch {}

impl Evidence {
    /// No pairs yet, starting at `first_pair`.
    pub(crate) fn empty(first_pair: usize) -> Evidence {
        Evidence {
            first_pair,
            pairs: Vec::new(),
            edge_offsets: vec![0],
            edges: Vec::new(),
            cells: CellCounts::default(),
            rejections: Rejections::default(),
            tested: 0,
            skipped: 0,
        }
    }

    /// Appends the next pair's result.
    pub(crate) fn push_pair(&mut self, pair: [u32; 2], r: &PairResult) {
        self.pairs.push(pair);
        self.edges.extend_from_slice(&r.links.edges);
        self.edge_offsets.push(self.edges.len() as u64);
        self.cells.add(&r.cells);
        self.rejections.add(&r.links.rejections);
        self.tested += r.links.tested;
        self.skipped += u64::from(r.skipped);
    }

    /// The counters in [`WARP_COUNTERS`] order.
    fn counters(&self) -> [u64; 10] {
        let (c, r) = (&self.cells, &self.rejections);
        [
            self.skipped,
            self.tested,
            c.total,
            c.low_certainty,
            c.occluded,
            c.gated,
            r.iou,
            r.box_iou,
            r.one_direction_only,
            r.no_reverse_overlap,
        ]
    }

    /// Merges the evidence of shards (`(name, evidence)`, any order) that together cover
    /// view pairs `0..total` exactly once, into the evidence of one run: links in
    /// view-pair order, counters summed.
    pub fn merge(
        mut shards: Vec<(String, Evidence)>,
        total: usize,
    ) -> Result<Evidence, ShardMismatch> {
        shards.sort_by_key(|(_, e)| (e.first_pair, e.pairs.len()));
        let mut merged = Evidence::empty(0);
        let mut prev = String::from("the start");
        for (name, e) in shards {
            let next = merged.pairs.len();
            if e.first_pair > next {
                return Err(ShardMismatch::Coverage(format!(
                    "view pairs {next}..{} of {total} are in no shard (between {prev} and {name})",
                    e.first_pair
                )));
            }
            if e.first_pair < next && !e.pairs.is_empty() {
                return Err(ShardMismatch::Coverage(format!(
                    "view pairs {}..{next} are in two shards ({prev} and {name})",
                    e.first_pair
                )));
            }
            merged.append(&e);
            prev = name;
        }
        if merged.pairs.len() != total {
            return Err(ShardMismatch::Coverage(format!(
                "view pairs {}..{total} of {total} are in no shard (after {prev})",
                merged.pairs.len()
            )));
        }
        Ok(merged)
    }

    /// Appends the pairs of the shard that starts where this evidence ends.
    fn append(&mut self, e: &Evidence) {
        let base = self.edges.len() as u64;
        self.pairs.extend_from_slice(&e.pairs);
        self.edges.extend_from_slice(&e.edges);
        self.edge_offsets
            .extend(e.edge_offsets.iter().skip(1).map(|o| base + o));
        self.cells.add(&e.cells);
        self.rejections.add(&e.rejections);
        self.tested += e.tested;
        self.skipped += e.skipped;
    }

    /// The evidence as a `profuse.warp_partial` file value.
    pub fn to_partial(
        &self,
        num_views: usize,
        num_masks: usize,
        num_view_pairs: usize,
        inputs: [String; 5],
    ) -> WarpPartial {
        WarpPartial {
            num_views,
            num_masks,
            num_view_pairs,
            first_pair: self.first_pair,
            counters: self.counters(),
            inputs,
            pairs: self.pairs.clone().into(),
            edge_offsets: self.edge_offsets.clone().into(),
            edge_masks: self
                .edges
                .iter()
                .map(|l| l.masks)
                .collect::<Vec<_>>()
                .into(),
            edge_scores: self
                .edges
                .iter()
                .map(|l| [l.iou, l.box_iou])
                .collect::<Vec<_>>()
                .into(),
            extra: [(
                "generator".to_string(),
                concat!("warp-graph ", env!("CARGO_PKG_VERSION")).to_string(),
            )]
            .into(),
        }
    }

    /// The evidence a (validated) `profuse.warp_partial` file holds.
    pub fn from_partial(p: &WarpPartial) -> Evidence {
        let c = p.counters;
        debug_assert_eq!(WARP_COUNTERS.len(), c.len());
        Evidence {
            first_pair: p.first_pair,
            pairs: p.pairs.to_vec(),
            edge_offsets: p.edge_offsets.to_vec(),
            edges: p
                .edge_masks
                .iter()
                .zip(p.edge_scores.iter())
                .map(|(m, s)| Link {
                    masks: *m,
                    iou: s[0],
                    box_iou: s[1],
                })
                .collect(),
            skipped: c[0],
            tested: c[1],
            cells: CellCounts {
                total: c[2],
                low_certainty: c[3],
                occluded: c[4],
                gated: c[5],
            },
            rejections: Rejections {
                iou: c[6],
                box_iou: c[7],
                one_direction_only: c[8],
                no_reverse_overlap: c[9],
            },
        }
    }
}

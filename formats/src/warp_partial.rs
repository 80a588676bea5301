//! `profuse.warp_partial`: the mask-pair evidence of a range of warp-graph's view pairs
//! (SPEC.md "warp_partial"), written by `profuse warp-shard` and merged by `profuse run
//! --warp-partials` into proposals identical to an unsharded warp-graph. The evidence is
//! the accepted links with the exact f64 scores the grouping reads, so shards merged in
//! view-pair order hand the grouping the very values of one run.

use std::collections::BTreeMap;

use crate::check::{check_finite, check_offsets, meta_err, out_of_range, TensorReader};
use crate::container::{Buffer, Container};
use crate::error::Result;
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// The integer counters of a shard (metadata keys, in [`WarpPartial::counters`] order):
/// they add up over shards into the warp-graph report's counts.
pub const WARP_COUNTERS: [&str; 10] = [
    "skipped_pairs",
    "edges_tested",
    "cells_total",
    "cells_low_certainty",
    "cells_occluded",
    "cells_gated",
    "rejected_iou",
    "rejected_box_iou",
    "rejected_one_direction_only",
    "rejected_no_reverse_overlap",
];

/// The identity of the inputs and parameters a shard was computed from (metadata keys
/// `input_*`): opaque strings that a merge compares with its own.
pub const WARP_INPUTS: [&str; 5] = [
    "input_masks",
    "input_matches",
    "input_cameras",
    "input_gaussians",
    "input_params",
];

/// The accepted mask links of view pairs `first_pair .. first_pair + P` of a warp-graph
/// run (its view pairs in ascending (i, j) order), with the shard's counters.
#[derive(Debug, Clone, PartialEq)]
pub struct WarpPartial {
    /// V (metadata `num_views`).
    pub num_views: usize,
    /// M, the masks of all views (metadata `num_masks`).
    pub num_masks: usize,
    /// T, the view pairs of the whole run (metadata `num_view_pairs`).
    pub num_view_pairs: usize,
    /// Index of the shard's first view pair in the run's list (metadata `first_pair`).
    pub first_pair: usize,
    /// The counters named by [`WARP_COUNTERS`], in that order.
    pub counters: [u64; 10],
    /// The values of the keys named by [`WARP_INPUTS`], in that order.
    pub inputs: [String; 5],
    /// `pairs` U32 [P, 2]: the view pairs (i < j < V), strictly ascending.
    pub pairs: Buffer<[u32; 2]>,
    /// `edge_offsets` U64 [P + 1]: pair p's links are `edge_offsets[p] .. [p + 1]`.
    pub edge_offsets: Buffer<u64>,
    /// `edge_masks` U32 [E, 2]: global mask ids of every link, first < second < M.
    pub edge_masks: Buffer<[u32; 2]>,
    /// `edge_scores` F64 [E, 2]: (mask IoU, box IoU) of every link, in [0, 1].
    pub edge_scores: Buffer<[f64; 2]>,
    /// Other metadata (`generator`), kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl WarpPartial {
    /// P, the view pairs of the shard.
    pub fn num_pairs(&self) -> usize {
        self.pairs.len()
    }

    /// E, the links of the shard.
    pub fn num_edges(&self) -> usize {
        self.edge_masks.len()
    }
}

const KNOWN_META: [&str; 4] = ["num_views", "num_masks", "num_view_pairs", "first_pair"];

impl FileKind for WarpPartial {
    const KIND: Kind = Kind::WarpPartial;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        let int = "a non-negative integer";
        let num_views = r.meta_parse("num_views", int)?;
        let num_masks = r.meta_parse("num_masks", int)?;
        let num_view_pairs = r.meta_parse("num_view_pairs", int)?;
        let first_pair = r.meta_parse("first_pair", int)?;
        let mut counters = [0u64; 10];
        for (value, key) in counters.iter_mut().zip(WARP_COUNTERS) {
            *value = r.meta_parse(key, "a decimal counter below 2^64")?;
        }
        let mut inputs: [String; 5] = Default::default();
        for (value, key) in inputs.iter_mut().zip(WARP_INPUTS) {
            *value = r.meta(key, "a string identifying the input")?.to_string();
        }
        let pairs = r.req("pairs", "P,2")?;
        let rows = r.dim("P").saturating_add(1);
        r.bind("P1", rows, "`pairs` rows + 1");
        let mut extra = r.extra_meta(&KNOWN_META);
        extra.retain(|k, _| {
            !WARP_COUNTERS.contains(&k.as_str()) && !WARP_INPUTS.contains(&k.as_str())
        });
        Ok(WarpPartial {
            num_views,
            num_masks,
            num_view_pairs,
            first_pair,
            counters,
            inputs,
            pairs,
            edge_offsets: r.req("edge_offsets", "P1")?,
            edge_masks: r.req("edge_masks", "E,2")?,
            edge_scores: r.req("edge_scores", "E,2")?,
            extra,
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        self.check_shapes(path)?;
        self.check_pairs(path)?;
        check_offsets(
            path,
            "edge_offsets",
            &self.edge_offsets,
            self.num_edges() as u64,
        )?;
        self.check_masks(path)?;
        self.check_scores(path)
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        w.meta("num_views", self.num_views.to_string())
            .meta("num_masks", self.num_masks.to_string())
            .meta("num_view_pairs", self.num_view_pairs.to_string())
            .meta("first_pair", self.first_pair.to_string());
        for (key, value) in WARP_COUNTERS.iter().zip(self.counters) {
            w.meta(key, value.to_string());
        }
        for (key, value) in WARP_INPUTS.iter().zip(&self.inputs) {
            w.meta(key, value.clone());
        }
        let (p, e) = (self.num_pairs(), self.num_edges());
        w.tensor("pairs", &[p, 2], &self.pairs)
            .tensor(
                "edge_offsets",
                &[self.edge_offsets.len()],
                &self.edge_offsets,
            )
            .tensor("edge_masks", &[e, 2], &self.edge_masks)
            .tensor("edge_scores", &[e, 2], &self.edge_scores);
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("views", self.num_views as u64),
            ("masks", self.num_masks as u64),
            ("view_pairs", self.num_view_pairs as u64),
            ("shard_pairs", self.num_pairs() as u64),
            ("edges", self.num_edges() as u64),
        ])
    }
}

impl WarpPartial {
    /// The named dimensions agree (a value built in memory has no header to check them),
    /// and the shard lies inside the run's pairs.
    fn check_shapes(&self, path: &str) -> Result<()> {
        let (p, e) = (self.num_pairs(), self.num_edges());
        if self.edge_offsets.len() != p + 1 {
            return Err(crate::check::shape_err(
                path,
                "edge_offsets",
                vec![self.edge_offsets.len()],
                format!("{} rows (P + 1, P from `pairs`)", p + 1),
            ));
        }
        if self.edge_scores.len() != e {
            return Err(crate::check::shape_err(
                path,
                "edge_scores",
                vec![self.edge_scores.len(), 2],
                format!("[{e}, 2] (E from `edge_masks`)"),
            ));
        }
        if self
            .first_pair
            .checked_add(p)
            .is_none_or(|end| end > self.num_view_pairs)
        {
            return Err(meta_err(
                path,
                "first_pair",
                &format!(
                    "first_pair + {p} (the shard's pairs) <= num_view_pairs {}",
                    self.num_view_pairs
                ),
            ));
        }
        Ok(())
    }

    /// Pairs (i < j < V), strictly ascending.
    fn check_pairs(&self, path: &str) -> Result<()> {
        let v = self.num_views;
        for (k, pair) in self.pairs.iter().enumerate() {
            let [i, j] = *pair;
            let ascending = k == 0 || self.pairs[k - 1] < *pair;
            if i >= j || j as usize >= v || !ascending {
                return Err(out_of_range(
                    path,
                    "pairs",
                    k,
                    format!("[{i}, {j}]"),
                    format!("view pairs (i < j < {v}), strictly ascending"),
                ));
            }
        }
        Ok(())
    }

    /// Links join two masks, first < second < M.
    fn check_masks(&self, path: &str) -> Result<()> {
        let m = self.num_masks;
        match self
            .edge_masks
            .iter()
            .position(|&[a, b]| a >= b || b as usize >= m)
        {
            Some(k) => {
                let [a, b] = self.edge_masks[k];
                Err(out_of_range(
                    path,
                    "edge_masks",
                    k,
                    format!("[{a}, {b}]"),
                    format!("global mask ids, first < second < {m}"),
                ))
            }
            None => Ok(()),
        }
    }

    /// Scores finite and in [0, 1].
    fn check_scores(&self, path: &str) -> Result<()> {
        let flat: Vec<f64> = self.edge_scores.iter().flatten().copied().collect();
        check_finite(path, "edge_scores", &flat)?;
        match flat.iter().position(|s| !(0.0..=1.0).contains(s)) {
            Some(k) => Err(out_of_range(
                path,
                "edge_scores",
                k,
                crate::check::format_float(flat[k]),
                "a value in [0, 1]",
            )),
            None => Ok(()),
        }
    }
}

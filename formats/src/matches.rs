//! `profuse.matches` (dense warps) and `profuse.sparse_matches` (pixel pairs)
//! (SPEC.md "matches", "sparse_matches").

use std::collections::{BTreeMap, BTreeSet};

use crate::check::{
    check_count, check_finite, check_finite_floats, check_len, check_offsets, check_unit_interval,
    invalid, meta_err, out_of_range, Floats, TensorReader,
};
use crate::container::{Buffer, Container};
use crate::error::Result;
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// How warp targets are expressed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WarpCoords {
    /// RoMa's convention: x and y in [-1, 1] over the target image, pixel centres at
    /// -1 + 1/W .. 1 - 1/W (`normalized`).
    Normalized,
    /// Pixels of the target image, origin at its top-left corner, centres at +0.5 (`pixels`).
    Pixels,
}

impl WarpCoords {
    /// Metadata spelling.
    pub fn name(self) -> &'static str {
        match self {
            WarpCoords::Normalized => "normalized",
            WarpCoords::Pixels => "pixels",
        }
    }

    fn parse(s: &str) -> Option<Self> {
        match s {
            "normalized" => Some(WarpCoords::Normalized),
            "pixels" => Some(WarpCoords::Pixels),
            _ => None,
        }
    }
}

/// Dense warps for ordered view pairs, all on one grid.
#[derive(Debug, Clone, PartialEq)]
pub struct Matches {
    /// Views in the matching cameras file (metadata `num_views`); pair ids must be below it.
    pub num_views: usize,
    /// `pairs` U32 [P, 2]: (i, j); warp `p` maps pixels of view i to positions in view j.
    pub pairs: Buffer<[u32; 2]>,
    /// Grid height (the warp is sampled on view i resized to this grid).
    pub height: usize,
    /// Grid width.
    pub width: usize,
    /// `warp` F16 or F32 [P, H, W, 2]: target (x, y) in view j, x first.
    pub warp: Floats,
    /// `certainty` F16 or F32 [P, H, W] in [0, 1]; 0 = no match.
    pub certainty: Floats,
    /// Metadata `coords`.
    pub coords: WarpCoords,
    /// Other metadata, kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl FileKind for Matches {
    const KIND: Kind = Kind::Matches;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        let num_views = r.meta_parse("num_views", "a non-negative integer")?;
        let coords = WarpCoords::parse(r.meta("coords", "\"normalized\" or \"pixels\"")?)
            .ok_or_else(|| meta_err(c.path(), "coords", "\"normalized\" or \"pixels\""))?;
        let pairs = r.req("pairs", "P,2")?;
        let warp = r.req_floats("warp", "P,H,W,2")?;
        let certainty = r.req_floats("certainty", "P,H,W")?;
        Ok(Matches {
            num_views,
            pairs,
            height: r.dim("H"),
            width: r.dim("W"),
            warp,
            certainty,
            coords,
            extra: r.extra_meta(&["num_views", "coords"]),
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        let cells = [self.pairs.len(), self.height, self.width];
        check_count(
            path,
            "warp",
            self.warp.len(),
            &[cells[0], cells[1], cells[2], 2],
            "values (P x H x W x 2)",
        )?;
        check_count(
            path,
            "certainty",
            self.certainty.len(),
            &cells,
            "values (P x H x W)",
        )?;
        check_pairs(path, &self.pairs, self.num_views)?;
        check_finite_floats(path, "warp", &self.warp)?;
        check_unit_interval(path, "certainty", &self.certainty)
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        let (p, h, wd) = (self.pairs.len(), self.height, self.width);
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        w.meta("num_views", self.num_views.to_string())
            .meta("coords", self.coords.name())
            .tensor("pairs", &[p, 2], &self.pairs);
        match &self.warp {
            Floats::F16(b) => w.tensor("warp", &[p, h, wd, 2], b),
            Floats::F32(b) => w.tensor("warp", &[p, h, wd, 2], b),
        };
        match &self.certainty {
            Floats::F16(b) => w.tensor("certainty", &[p, h, wd], b),
            Floats::F32(b) => w.tensor("certainty", &[p, h, wd], b),
        };
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("views", self.num_views as u64),
            ("pairs", self.pairs.len() as u64),
            ("height", self.height as u64),
            ("width", self.width as u64),
        ])
    }
}

/// Pixel-pair matches for ordered view pairs (sparse and semi-dense matchers).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SparseMatches {
    /// Views in the matching cameras file (metadata `num_views`).
    pub num_views: usize,
    /// `pairs` U32 [P, 2]: (i, j).
    pub pairs: Buffer<[u32; 2]>,
    /// `pair_offsets` U64 [P + 1]: pair p owns matches `offsets[p]..offsets[p+1]`.
    pub pair_offsets: Buffer<u64>,
    /// `points_i` F32 [N, 2]: pixel (x, y) in view i, centres at +0.5.
    pub points_i: Buffer<[f32; 2]>,
    /// `points_j` F32 [N, 2]: pixel (x, y) in view j.
    pub points_j: Buffer<[f32; 2]>,
    /// `certainty` F32 [N] in [0, 1].
    pub certainty: Buffer<f32>,
    /// Other metadata, kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl SparseMatches {
    /// The match index range of pair `p`.
    pub fn range(&self, p: usize) -> std::ops::Range<usize> {
        self.pair_offsets[p] as usize..self.pair_offsets[p + 1] as usize
    }

    /// The matches of `self` and `other` (of the same views) in one file: each ordered pair
    /// once, in the order pairs first appear (`self`'s, then `other`'s new ones), holding
    /// `self`'s matches of that pair followed by `other`'s. `extra` is `self`'s. Two
    /// matchers of one capture (COLMAP's tracks and XFeat) are combined this way.
    ///
    /// # Panics
    /// When `num_views` differ (a caller's mistake, not an input's).
    pub fn merged(&self, other: &SparseMatches) -> SparseMatches {
        assert_eq!(
            self.num_views, other.num_views,
            "merging matches of different cameras"
        );
        let mut order: Vec<[u32; 2]> = Vec::new();
        let mut parts: BTreeMap<[u32; 2], Vec<(&SparseMatches, usize)>> = BTreeMap::new();
        for m in [self, other] {
            for (p, pair) in m.pairs.iter().enumerate() {
                let e = parts.entry(*pair).or_default();
                if e.is_empty() {
                    order.push(*pair);
                }
                e.push((m, p));
            }
        }
        let mut offsets = vec![0u64];
        let (mut pi, mut pj, mut cert) = (Vec::new(), Vec::new(), Vec::new());
        for pair in &order {
            for (m, p) in parts.get(pair).map(Vec::as_slice).unwrap_or_default() {
                let r = m.range(*p);
                pi.extend_from_slice(&m.points_i[r.clone()]);
                pj.extend_from_slice(&m.points_j[r.clone()]);
                cert.extend_from_slice(&m.certainty[r]);
            }
            offsets.push(pi.len() as u64);
        }
        SparseMatches {
            num_views: self.num_views,
            pairs: order.into(),
            pair_offsets: offsets.into(),
            points_i: pi.into(),
            points_j: pj.into(),
            certainty: cert.into(),
            extra: self.extra.clone(),
        }
    }
}

impl FileKind for SparseMatches {
    const KIND: Kind = Kind::SparseMatches;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        let num_views = r.meta_parse("num_views", "a non-negative integer")?;
        let pairs: Buffer<[u32; 2]> = r.req("pairs", "P,2")?;
        r.bind("P+1", pairs.len() + 1, "tensor `pairs` rows + 1");
        Ok(SparseMatches {
            num_views,
            pairs,
            pair_offsets: r.req("pair_offsets", "P+1")?,
            points_i: r.req("points_i", "N,2")?,
            points_j: r.req("points_j", "N,2")?,
            certainty: r.req("certainty", "N")?,
            extra: r.extra_meta(&["num_views"]),
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        let n = self.points_i.len();
        check_len(
            path,
            "pair_offsets",
            self.pair_offsets.len(),
            self.pairs.len() + 1,
            "offsets (P + 1)",
        )?;
        check_len(
            path,
            "points_j",
            self.points_j.len(),
            n,
            "rows, one per row of points_i",
        )?;
        check_len(
            path,
            "certainty",
            self.certainty.len(),
            n,
            "values, one per row of points_i",
        )?;
        check_pairs(path, &self.pairs, self.num_views)?;
        check_offsets(path, "pair_offsets", &self.pair_offsets, n as u64)?;
        check_finite(
            path,
            "points_i",
            bytemuck::cast_slice::<_, f32>(&self.points_i),
        )?;
        check_finite(
            path,
            "points_j",
            bytemuck::cast_slice::<_, f32>(&self.points_j),
        )?;
        check_unit_interval(path, "certainty", &Floats::F32(self.certainty.clone()))
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        let (p, n) = (self.pairs.len(), self.points_i.len());
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        w.meta("num_views", self.num_views.to_string())
            .tensor("pairs", &[p, 2], &self.pairs)
            .tensor("pair_offsets", &[p + 1], &self.pair_offsets)
            .tensor("points_i", &[n, 2], &self.points_i)
            .tensor("points_j", &[n, 2], &self.points_j)
            .tensor("certainty", &[n], &self.certainty);
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("views", self.num_views as u64),
            ("pairs", self.pairs.len() as u64),
            ("matches", self.points_i.len() as u64),
        ])
    }
}

/// View ids inside the camera set, i != j, and each ordered pair at most once.
fn check_pairs(path: &str, pairs: &[[u32; 2]], num_views: usize) -> Result<()> {
    let mut seen = BTreeSet::new();
    for (p, [i, j]) in pairs.iter().enumerate() {
        for (k, v) in [i, j].into_iter().enumerate() {
            if *v as usize >= num_views {
                return Err(out_of_range(
                    path,
                    "pairs",
                    2 * p + k,
                    v,
                    format!("a view index < {num_views} (metadata num_views)"),
                ));
            }
        }
        if i == j {
            return Err(invalid(
                path,
                "pairs",
                format!("row {p} pairs view {i} with itself"),
            ));
        }
        if !seen.insert((*i, *j)) {
            return Err(invalid(
                path,
                "pairs",
                format!("row {p} repeats the ordered pair ({i}, {j})"),
            ));
        }
    }
    Ok(())
}

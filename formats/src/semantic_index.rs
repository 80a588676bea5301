//! `profuse.semantic_index`: per Gaussian the index of its dominant proposal and that
//! proposal's share of its weight, plus the proposal descriptor table (SPEC.md
//! "semantic_index"). A query scores the P table rows instead of N Gaussians.

use std::collections::BTreeMap;

use crate::check::{
    check_count, check_finite_floats, check_ids, check_len, check_unit_rows, invalid, shape_err,
    Floats, Labels, TensorReader,
};
use crate::container::{Buffer, Container, Dtype};
use crate::error::{FormatError, Result};
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// Units of `share` and `min_share`: a stored value q means a share of q / 255.
pub const SHARE_SCALE: f64 = 255.0;

/// Largest proposal count whose indices are stored as U16 (65535 stays the "none" value).
pub const MAX_U16_PROPOSALS: usize = 65535;

/// The stored form of a share in [0, 1]: round(255 · share), clamped (SPEC.md rounding).
pub fn quantise_share(share: f64) -> u8 {
    (share.clamp(0.0, 1.0) * SHARE_SCALE).round() as u8
}

/// The dtype of `index` for P proposals: U16 iff P <= 65535, else U32.
pub fn index_dtype(num_proposals: usize) -> Dtype {
    if num_proposals <= MAX_U16_PROPOSALS {
        Dtype::U16
    } else {
        Dtype::U32
    }
}

/// Dominant proposal per Gaussian plus the proposal descriptor table.
#[derive(Debug, Clone, PartialEq)]
pub struct SemanticIndex {
    /// `descriptors` F16 or F32 [P, D]: unit-norm rows, or all zero (no descriptor).
    pub descriptors: Floats,
    /// Feature dimension D.
    pub dim: usize,
    /// `index` U16 (P <= 65535) or U32 [N]: the dominant proposal, or the dtype's maximum
    /// for a Gaussian with no registration weight.
    pub index: Labels,
    /// `share` U8 [N]: the dominant proposal's share of the Gaussian's weight, in units of
    /// 1/255; 0 where `index` is none. Optional when `min_share` is 0 (every Gaussian with
    /// a proposal is then dominant, and the index alone is 2 bytes a Gaussian).
    pub share: Option<Buffer<u8>>,
    /// Metadata `min_share` (units of 1/255): a Gaussian has a dominant proposal iff its
    /// index is not none and `share >= min_share`.
    pub min_share: u8,
    /// Other metadata, kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl SemanticIndex {
    /// Gaussians N.
    pub fn num_gaussians(&self) -> usize {
        self.index.len()
    }

    /// Proposals P (rows of the table).
    pub fn num_proposals(&self) -> usize {
        self.descriptors.len().checked_div(self.dim).unwrap_or(0)
    }

    /// The proposal Gaussian `g` registered most weight to (`None`: no weight at all).
    pub fn proposal(&self, g: usize) -> Option<u32> {
        self.index.get(g)
    }

    /// Whether Gaussian `g` has a dominant proposal (share at least `min_share`); the
    /// others fall back to their PQ code where one exists.
    pub fn is_dominant(&self, g: usize) -> bool {
        self.index.get(g).is_some() && self.share_of(g) >= self.min_share
    }

    /// Gaussian `g`'s stored share (units of 1/255); without a `share` tensor (only
    /// allowed with `min_share` 0) 255 for a Gaussian with a proposal, else 0.
    pub fn share_of(&self, g: usize) -> u8 {
        match &self.share {
            Some(s) => s.get(g).copied().unwrap_or(0),
            None => u8::from(self.index.get(g).is_some()) * 255,
        }
    }

    /// Builds `index` in the dtype SPEC.md prescribes for `num_proposals`, from ids with
    /// `None` for "no weight".
    pub fn index_of(num_proposals: usize, ids: &[Option<u32>]) -> Labels {
        match index_dtype(num_proposals) {
            Dtype::U16 => Labels::U16(
                ids.iter()
                    .map(|i| i.map_or(u16::MAX, |v| v as u16))
                    .collect::<Vec<u16>>()
                    .into(),
            ),
            _ => Labels::U32(
                ids.iter()
                    .map(|i| i.unwrap_or(u32::MAX))
                    .collect::<Vec<u32>>()
                    .into(),
            ),
        }
    }
}

impl FileKind for SemanticIndex {
    const KIND: Kind = Kind::SemanticIndex;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        let expected = "an integer in 0..=255 (a share in units of 1/255)";
        let min_share: u8 = r.meta_parse("min_share", expected)?;
        let descriptors = r.req_floats("descriptors", "P,D")?;
        let p = r.dim("P");
        let index = r.req_labels("index", "N")?;
        let want = index_dtype(p);
        if index.dtype() != want {
            return Err(FormatError::Dtype {
                path: c.path().to_string(),
                tensor: "index".to_string(),
                found: index.dtype().to_string(),
                expected: format!("{want} for P = {p} proposals (U16 iff P <= 65535)"),
            });
        }
        Ok(SemanticIndex {
            descriptors,
            dim: r.dim("D"),
            index,
            // Required unless min_share is 0, where it cannot change which Gaussians are
            // dominant.
            share: match min_share {
                0 => r.opt("share", "N")?,
                _ => Some(r.req("share", "N")?),
            },
            min_share,
            extra: r.extra_meta(&["min_share"]),
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        let n = self.num_gaussians();
        let p = self.num_proposals();
        if self.dim == 0 {
            return Err(shape_err(
                path,
                "descriptors",
                vec![p, 0],
                "[P, D] with D >= 1".to_string(),
            ));
        }
        check_count(
            path,
            "descriptors",
            self.descriptors.len(),
            &[p, self.dim],
            "values (P x D)",
        )?;
        if self.index.dtype() != index_dtype(p) {
            return Err(FormatError::Dtype {
                path: path.to_string(),
                tensor: "index".to_string(),
                found: self.index.dtype().to_string(),
                expected: format!("{} for P = {p} proposals", index_dtype(p)),
            });
        }
        check_finite_floats(path, "descriptors", &self.descriptors)?;
        let d = self.dim;
        let zero = |r: usize| (0..d).all(|j| self.descriptors.get(r * d + j) == 0.0);
        check_unit_rows(path, "descriptors", &self.descriptors, d, &zero)?;
        let none = u64::from(self.index.none_value());
        match &self.index {
            Labels::U16(b) => check_ids(path, "index", b, p as u64, Some(none), "the table")?,
            Labels::U32(b) => check_ids(path, "index", b, p as u64, Some(none), "the table")?,
        }
        let Some(share) = &self.share else {
            if self.min_share == 0 {
                return Ok(());
            }
            return Err(FormatError::MissingTensor {
                path: path.to_string(),
                tensor: "share".to_string(),
                expected: format!("U8 [N] (required when min_share = {} > 0)", self.min_share),
            });
        };
        check_len(path, "share", share.len(), n, "shares, one per Gaussian")?;
        if let Some(g) = (0..n).find(|&g| self.index.get(g).is_none() && share[g] != 0) {
            return Err(invalid(
                path,
                "share",
                format!(
                    "Gaussian {g} has no proposal but share {} (expected 0)",
                    share[g]
                ),
            ));
        }
        Ok(())
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        let (n, p) = (self.num_gaussians(), self.num_proposals());
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        w.meta("min_share", self.min_share.to_string());
        match &self.descriptors {
            Floats::F16(b) => w.tensor("descriptors", &[p, self.dim], b),
            Floats::F32(b) => w.tensor("descriptors", &[p, self.dim], b),
        };
        match &self.index {
            Labels::U16(b) => w.tensor("index", &[n], b),
            Labels::U32(b) => w.tensor("index", &[n], b),
        };
        if let Some(share) = &self.share {
            w.tensor("share", &[n], share);
        }
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        let n = self.num_gaussians();
        let indexed = (0..n).filter(|&g| self.index.get(g).is_some()).count();
        let dominant = (0..n).filter(|&g| self.is_dominant(g)).count();
        BTreeMap::from([
            ("gaussians", n as u64),
            ("proposals", self.num_proposals() as u64),
            ("feature_dim", self.dim as u64),
            ("indexed", indexed as u64),
            ("dominant", dominant as u64),
        ])
    }
}

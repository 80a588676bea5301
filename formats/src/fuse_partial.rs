//! `profuse.fuse_partial`: the exact partial sums of a `fuse run --views a..b` shard
//! (SPEC.md "fuse_partial"), which `fuse merge` adds up into a features file identical to
//! an unsharded run. Sums are fixed-point integers (u128 stored as two u64 words) so that
//! shards added in any order give the same integers.

use std::collections::BTreeMap;

use crate::check::{
    check_finite_floats, check_offsets, invalid, meta_err, out_of_range, shape_err, Floats,
    TensorReader,
};
use crate::container::{Buffer, Container};
use crate::error::{FormatError, Result};
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// Group of a mask that registers into no group (an ignored orphan).
pub const NO_GROUP: u32 = u32::MAX;

/// What `fuse` does with masks that belong to no proposal.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FuseOrphans {
    /// Their pixels register nothing.
    Ignore,
    /// Each becomes a group of its own.
    Singleton,
}

/// How the masks were grouped (metadata `grouping` and `orphans`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FuseGrouping {
    /// Groups are proposals (plus singleton orphans).
    Proposals { orphans: FuseOrphans },
    /// Every mask is its own group (`--no-proposals`); `orphans = none`.
    Masks,
    /// One group per mask, blended with its proposal (`--registration blend`).
    Blend { orphans: FuseOrphans },
}

impl FuseGrouping {
    /// Metadata `grouping`.
    pub fn name(self) -> &'static str {
        match self {
            FuseGrouping::Proposals { .. } => "proposals",
            FuseGrouping::Masks => "masks",
            FuseGrouping::Blend { .. } => "blend",
        }
    }

    /// Metadata `orphans` (`none` for [`FuseGrouping::Masks`]).
    pub fn orphans_name(self) -> &'static str {
        match self {
            FuseGrouping::Proposals { orphans } | FuseGrouping::Blend { orphans } => {
                match orphans {
                    FuseOrphans::Ignore => "ignore",
                    FuseOrphans::Singleton => "singleton",
                }
            }
            FuseGrouping::Masks => "none",
        }
    }

    /// Parses `grouping` and `orphans`; the error names the key at fault.
    fn parse(path: &str, grouping: &str, orphans: &str) -> Result<FuseGrouping> {
        let policy = || match orphans {
            "ignore" => Ok(FuseOrphans::Ignore),
            "singleton" => Ok(FuseOrphans::Singleton),
            _ => Err(meta_err(path, "orphans", "`ignore` or `singleton`")),
        };
        match grouping {
            "masks" if orphans == "none" => Ok(FuseGrouping::Masks),
            "masks" => Err(meta_err(path, "orphans", "`none` for grouping `masks`")),
            "proposals" => Ok(FuseGrouping::Proposals { orphans: policy()? }),
            "blend" => Ok(FuseGrouping::Blend { orphans: policy()? }),
            _ => Err(meta_err(
                path,
                "grouping",
                "`proposals`, `masks` or `blend`",
            )),
        }
    }
}

/// A fixed-point sum stored as (low, high) 64-bit words.
pub fn fixed_point(words: [u64; 2]) -> u128 {
    u128::from(words[0]) | (u128::from(words[1]) << 64)
}

/// A fixed-point sum split into (low, high) 64-bit words.
pub fn fixed_point_words(value: u128) -> [u64; 2] {
    [value as u64, (value >> 64) as u64]
}

/// Partial sums of W (Gaussian x group) and of the mask masses over a set of views, plus
/// the grouping and mask features needed to finish the registration.
#[derive(Debug, Clone, PartialEq)]
pub struct FusePartial {
    /// N, the Gaussians of the run (metadata `num_gaussians`).
    pub num_gaussians: usize,
    /// V, the views of the cameras and masks (metadata `num_views`).
    pub num_views: usize,
    /// K of the top-K rendering (metadata `k`).
    pub k: usize,
    /// Metadata `grouping` and `orphans`.
    pub grouping: FuseGrouping,
    /// G (metadata `num_groups`).
    pub num_groups: usize,
    /// Grouped mask-grid pixels (metadata `pixels`).
    pub pixels: u64,
    /// Their top-K hits (metadata `hits`).
    pub hits: u64,
    /// `views` U32 [S]: the views summed, ascending, each `< V`.
    pub views: Buffer<u32>,
    /// `mask_group` U32 [M]: group of every mask (`< G`) or [`NO_GROUP`].
    pub mask_group: Buffer<u32>,
    /// `mask_proposal` U32 [M]: present exactly for grouping `blend`.
    pub mask_proposal: Option<Buffer<u32>>,
    /// Optional `mask_share` F32 [M], each in (0, 1]: the proposals file's `mask_share`,
    /// by which a member's mass is weighed in its proposal's descriptor; absent = every
    /// member weighs its mass (never present for grouping `masks`).
    pub mask_share: Option<Buffer<f32>>,
    /// `mask_features` F16 or F32 [M, D].
    pub mask_features: Floats,
    /// D >= 1.
    pub dim: usize,
    /// `mask_mass` U64 [M, 2]: μ of every mask, fixed point (see [`fixed_point`]).
    pub mask_mass: Buffer<[u64; 2]>,
    /// `w_offsets` U64 [N + 1]: row g of W is entries `w_offsets[g] .. w_offsets[g+1]`.
    pub w_offsets: Buffer<u64>,
    /// `w_groups` U32 [E]: group of every entry, strictly ascending within a row.
    pub w_groups: Buffer<u32>,
    /// `w_sums` U64 [E, 2]: Σ ω of every entry, fixed point, nonzero.
    pub w_sums: Buffer<[u64; 2]>,
    /// Other metadata (`generator`, `weight_scale`), kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl FusePartial {
    /// Number of masks M.
    pub fn num_masks(&self) -> usize {
        self.mask_group.len()
    }

    /// Number of nonzero entries E of W.
    pub fn num_entries(&self) -> usize {
        self.w_groups.len()
    }
}

const KNOWN_META: [&str; 8] = [
    "num_gaussians",
    "num_views",
    "k",
    "grouping",
    "orphans",
    "num_groups",
    "pixels",
    "hits",
];

impl FileKind for FusePartial {
    const KIND: Kind = Kind::FusePartial;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        let int = "a non-negative integer";
        let num_gaussians: usize = r.meta_parse("num_gaussians", int)?;
        let num_views = r.meta_parse("num_views", int)?;
        let k = r.meta_parse("k", int)?;
        let grouping = FuseGrouping::parse(
            r.path(),
            r.meta("grouping", "`proposals`, `masks` or `blend`")?,
            r.meta("orphans", "`ignore`, `singleton` or `none`")?,
        )?;
        let num_groups = r.meta_parse("num_groups", int)?;
        let pixels = r.meta_parse("pixels", int)?;
        let hits = r.meta_parse("hits", int)?;
        let rows = num_gaussians
            .checked_add(1)
            .ok_or_else(|| meta_err(r.path(), "num_gaussians", "an integer below 2^64 - 1"))?;
        r.bind("N1", rows, "metadata `num_gaussians` + 1");
        let views = r.req("views", "S")?;
        let mask_group = r.req("mask_group", "M")?;
        let mask_proposal = r.opt("mask_proposal", "M")?;
        let mask_share = r.opt("mask_share", "M")?;
        let mask_features = r.req_floats("mask_features", "M,D")?;
        Ok(FusePartial {
            num_gaussians,
            num_views,
            k,
            grouping,
            num_groups,
            pixels,
            hits,
            views,
            mask_group,
            mask_proposal,
            mask_share,
            mask_features,
            dim: r.dim("D"),
            mask_mass: r.req("mask_mass", "M,2")?,
            w_offsets: r.req("w_offsets", "N1")?,
            w_groups: r.req("w_groups", "E")?,
            w_sums: r.req("w_sums", "E,2")?,
            extra: r.extra_meta(&KNOWN_META),
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        self.check_shapes(path)?;
        self.check_views(path)?;
        self.check_groups(path)?;
        if let Some(share) = &self.mask_share {
            if self.grouping == FuseGrouping::Masks {
                return Err(invalid(
                    path,
                    "mask_share",
                    "present only for groupings `proposals` and `blend`, not `masks`".into(),
                ));
            }
            crate::proposals::check_share(path, "mask_share", share, self.num_masks())?;
        }
        check_finite_floats(path, "mask_features", &self.mask_features)?;
        self.check_weights(path)
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        let (m, e) = (self.num_masks(), self.num_entries());
        w.meta("num_gaussians", self.num_gaussians.to_string())
            .meta("num_views", self.num_views.to_string())
            .meta("k", self.k.to_string())
            .meta("grouping", self.grouping.name())
            .meta("orphans", self.grouping.orphans_name())
            .meta("num_groups", self.num_groups.to_string())
            .meta("pixels", self.pixels.to_string())
            .meta("hits", self.hits.to_string())
            .tensor("views", &[self.views.len()], &self.views)
            .tensor("mask_group", &[m], &self.mask_group)
            .tensor("mask_mass", &[m, 2], &self.mask_mass)
            .tensor("w_offsets", &[self.w_offsets.len()], &self.w_offsets)
            .tensor("w_groups", &[e], &self.w_groups)
            .tensor("w_sums", &[e, 2], &self.w_sums);
        if let Some(p) = &self.mask_proposal {
            w.tensor("mask_proposal", &[m], p);
        }
        if let Some(s) = &self.mask_share {
            w.tensor("mask_share", &[m], s);
        }
        match &self.mask_features {
            Floats::F16(b) => w.tensor("mask_features", &[m, self.dim], b),
            Floats::F32(b) => w.tensor("mask_features", &[m, self.dim], b),
        };
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("gaussians", self.num_gaussians as u64),
            ("views", self.num_views as u64),
            ("summed_views", self.views.len() as u64),
            ("masks", self.num_masks() as u64),
            ("groups", self.num_groups as u64),
            ("entries", self.num_entries() as u64),
            ("feature_dim", self.dim as u64),
        ])
    }
}

impl FusePartial {
    /// The named dimensions agree (a value built in memory has no header to check them).
    fn check_shapes(&self, path: &str) -> Result<()> {
        let (m, e) = (self.num_masks(), self.num_entries());
        let lengths = [
            (
                "mask_proposal",
                self.mask_proposal.as_ref().map(|p| p.len()),
                Some(m),
                "M",
            ),
            (
                "mask_features",
                Some(self.mask_features.len()),
                m.checked_mul(self.dim),
                "M x D",
            ),
            ("mask_mass", Some(self.mask_mass.len()), Some(m), "M"),
            (
                "w_offsets",
                Some(self.w_offsets.len()),
                self.num_gaussians.checked_add(1),
                "N + 1",
            ),
            ("w_sums", Some(self.w_sums.len()), Some(e), "E"),
        ];
        // Expected counts are checked sums and products of header values: one that
        // overflows matches no length (issue 20 item 1).
        for (tensor, len, expected, what) in lengths {
            if let Some(len) = len.filter(|l| Some(*l) != expected) {
                let expected =
                    expected.map_or_else(|| "more than 2^64".to_string(), |e| e.to_string());
                return Err(shape_err(
                    path,
                    tensor,
                    vec![len],
                    format!("{expected} rows ({what}, M from `mask_group`, E from `w_groups`)"),
                ));
            }
        }
        if self.dim == 0 {
            return Err(shape_err(
                path,
                "mask_features",
                vec![m, 0],
                "[M, D] with D >= 1".to_string(),
            ));
        }
        Ok(())
    }

    /// Views ascending, unique, `< V`.
    fn check_views(&self, path: &str) -> Result<()> {
        for (i, view) in self.views.iter().enumerate() {
            if *view as usize >= self.num_views || (i > 0 && self.views[i - 1] >= *view) {
                return Err(out_of_range(
                    path,
                    "views",
                    i,
                    view,
                    format!("ascending unique view ids < {}", self.num_views),
                ));
            }
        }
        Ok(())
    }

    /// Group ids in range, and the per-grouping rules of SPEC.md.
    fn check_groups(&self, path: &str) -> Result<()> {
        let g = self.num_groups;
        if let Some(i) = self
            .mask_group
            .iter()
            .position(|x| *x != NO_GROUP && *x as usize >= g)
        {
            return Err(out_of_range(
                path,
                "mask_group",
                i,
                self.mask_group[i],
                format!("a group < {g} or the reserved {NO_GROUP}"),
            ));
        }
        let m = self.num_masks();
        match (self.grouping, &self.mask_proposal) {
            (FuseGrouping::Blend { .. }, None) => Err(FormatError::MissingTensor {
                path: path.to_string(),
                tensor: "mask_proposal".to_string(),
                expected: "U32 [M] for grouping `blend`".to_string(),
            }),
            (FuseGrouping::Blend { orphans }, Some(proposals)) => {
                if g != m {
                    return Err(meta_err(
                        path,
                        "num_groups",
                        &format!("{m} (grouping `blend` has one group per mask)"),
                    ));
                }
                let expected = |i: usize| {
                    if proposals[i] == NO_GROUP && orphans == FuseOrphans::Ignore {
                        NO_GROUP
                    } else {
                        i as u32
                    }
                };
                match (0..m).find(|i| self.mask_group[*i] != expected(*i)) {
                    Some(i) => Err(invalid(
                        path,
                        "mask_group",
                        format!(
                            "mask {i}: grouping `blend` puts mask i in group i, or none when it \
                             has no proposal and orphans are ignored (`mask_proposal`)"
                        ),
                    )),
                    None => Ok(()),
                }
            }
            (other, Some(_)) => Err(invalid(
                path,
                "mask_proposal",
                format!("present only for grouping `blend`, not `{}`", other.name()),
            )),
            (FuseGrouping::Masks, None) => {
                if g != m
                    || self
                        .mask_group
                        .iter()
                        .enumerate()
                        .any(|(i, x)| *x as usize != i)
                {
                    return Err(invalid(
                        path,
                        "mask_group",
                        "grouping `masks` puts mask i in group i (and has G = M)".into(),
                    ));
                }
                Ok(())
            }
            (FuseGrouping::Proposals { .. }, None) => Ok(()),
        }
    }

    /// The sparse rows of W: offsets, sorted in-range groups, nonzero sums.
    fn check_weights(&self, path: &str) -> Result<()> {
        let e = self.num_entries();
        check_offsets(path, "w_offsets", &self.w_offsets, e as u64)?;
        let g = self.num_groups;
        for row in self.w_offsets.windows(2) {
            let (a, b) = (row[0] as usize, row[1] as usize);
            for j in a..b {
                let group = self.w_groups[j];
                if group as usize >= g || (j > a && self.w_groups[j - 1] >= group) {
                    return Err(out_of_range(
                        path,
                        "w_groups",
                        j,
                        group,
                        format!("groups < {g}, strictly ascending within a row"),
                    ));
                }
            }
        }
        match self.w_sums.iter().position(|s| fixed_point(*s) == 0) {
            Some(i) => Err(out_of_range(path, "w_sums", i, 0, "a nonzero sum")),
            None => Ok(()),
        }
    }
}

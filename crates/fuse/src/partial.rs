//! Partial sums of a view shard: what `fuse run --views a..b --partial-out F` writes and
//! `fuse merge` adds up. The layout (`profuse.fuse_partial`, a safetensors file) is
//! documented on [`PartialSums`].

use std::path::Path;

use profuse_formats::{Container, Dtype, FileWriter, Floats, FormatError, Kind};

use crate::accumulate::{Accumulator, HitCounts, WeightMatrix};
use crate::error::{FuseError, Result};
use crate::groups::{blend_group_mismatch, Grouping, Groups, Orphans, NO_GROUP};

/// `format` of a partial-sums file.
pub const PARTIAL_FORMAT: &str = "profuse.fuse_partial";
/// `format_version` of a partial-sums file this crate writes and reads.
pub const PARTIAL_VERSION: &str = "1.0";

/// Wall-clock seconds of the phases of an accumulation (not stored in files).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Timings {
    /// Rendering the top-K buffers of every view.
    pub raster_s: f64,
    /// Scattering the hits into W and the masses.
    pub accumulate_s: f64,
    /// Turning the accumulator into the sorted CSR matrix.
    pub compact_s: f64,
}

/// Exact partial sums over a set of views: W (Gaussian x group) and the mask masses μ, plus
/// what is needed to finish the registration without the input files (the grouping and
/// the mask features). Only [`crate::accumulate`], [`PartialSums::read`] and [`merge`] make
/// one, so its parts always agree with each other. Sums are fixed-point integers in units of 2^-62
/// ([`crate::WEIGHT_SCALE`]), so adding partial sums in any order and any split gives the
/// same integers as one pass over all views, and [`crate::finish`] the same bytes.
///
/// # File layout (`profuse.fuse_partial`, version 1.0)
///
/// A safetensors file written like every SPEC.md kind (atomic, deterministic bytes).
///
/// | metadata | value |
/// |---|---|
/// | `format`, `format_version` | `profuse.fuse_partial`, `1.0` |
/// | `num_gaussians` | N, the Gaussians of the run |
/// | `num_views` | V, the views of the cameras/masks |
/// | `k` | top-K used |
/// | `grouping` | `proposals`, `masks` (`--no-proposals`) or `blend` |
/// | `orphans` | `ignore`, `singleton`, or `none` for `masks` |
/// | `num_groups` | G |
/// | `pixels`, `hits` | counters: grouped mask-grid pixels and their top-K hits |
/// | `weight_scale` | `2^-62` (informational) |
///
/// | tensor | dtype | shape | meaning |
/// |---|---|---|---|
/// | `views` | U32 | `[S]` | the views summed, ascending, each `< V` |
/// | `mask_group` | U32 | `[M]` | group of every mask (`< G`) or 4294967295 |
/// | `mask_proposal` | U32 | `[M]` | only for `blend`: the proposal of every mask, or 4294967295 |
/// | `mask_features` | F16 or F32 | `[M, D]` | the masks' features, copied |
/// | `mask_mass` | U64 | `[M, 2]` | μ of every mask over these views, fixed point (low, high 64 bits) |
/// | `w_offsets` | U64 | `[N + 1]` | row g of W is entries `w_offsets[g] .. w_offsets[g+1]` |
/// | `w_groups` | U32 | `[E]` | group of every entry, strictly ascending within a row, `< G` |
/// | `w_sums` | U64 | `[E, 2]` | Σ ω of every entry, fixed point (low, high), nonzero |
#[derive(Debug, Clone, PartialEq)]
pub struct PartialSums {
    /// N.
    pub(crate) num_gaussians: usize,
    /// V.
    pub(crate) num_views: usize,
    /// K of the top-K rendering.
    pub(crate) k: usize,
    /// The views summed, ascending.
    pub(crate) views: Vec<u32>,
    /// The mask grouping.
    pub(crate) groups: Groups,
    /// The masks' features [M, D].
    pub(crate) mask_features: Floats,
    /// D.
    pub(crate) dim: usize,
    /// μ of every mask over `views`, fixed point.
    pub(crate) mask_mass: Vec<u128>,
    /// W over `views`.
    pub(crate) weights: WeightMatrix,
    /// Counters over `views`.
    pub(crate) counts: HitCounts,
    /// How long the accumulation took (zero when read from a file).
    pub(crate) timings: Timings,
}

impl PartialSums {
    /// N, the Gaussians.
    pub fn num_gaussians(&self) -> usize {
        self.num_gaussians
    }

    /// V, the views of the cameras and masks.
    pub fn num_views(&self) -> usize {
        self.num_views
    }

    /// K of the top-K rendering.
    pub fn k(&self) -> usize {
        self.k
    }

    /// The views summed, ascending.
    pub fn views(&self) -> &[u32] {
        &self.views
    }

    /// The mask grouping.
    pub fn groups(&self) -> &Groups {
        &self.groups
    }

    /// The masks' features [M, D].
    pub fn mask_features(&self) -> &Floats {
        &self.mask_features
    }

    /// D.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// μ of every mask over the views, fixed point ([`crate::WEIGHT_SCALE`]).
    pub fn mask_mass(&self) -> &[u128] {
        &self.mask_mass
    }

    /// W over the views.
    pub fn weights(&self) -> &WeightMatrix {
        &self.weights
    }

    /// Counters over the views.
    pub fn counts(&self) -> HitCounts {
        self.counts
    }

    /// How long the accumulation took (zero when read from a file or merged).
    pub fn timings(&self) -> Timings {
        self.timings
    }

    /// Number of masks M.
    pub fn num_masks(&self) -> usize {
        self.mask_mass.len()
    }

    /// Whether every view `0..V` is summed.
    pub fn is_complete(&self) -> bool {
        self.views.len() == self.num_views
    }

    /// The views not summed, as `a..b` ranges.
    pub fn missing_views(&self) -> String {
        let mut done = vec![false; self.num_views];
        for v in &self.views {
            done[*v as usize] = true;
        }
        let mut out = Vec::new();
        let mut v = 0;
        while v < done.len() {
            if done[v] {
                v += 1;
                continue;
            }
            let start = v;
            while v < done.len() && !done[v] {
                v += 1;
            }
            out.push(format!("{start}..{v}"));
        }
        out.join(", ")
    }

    /// Writes the file atomically (temp file + rename).
    pub fn write(&self, path: impl AsRef<Path>) -> Result<()> {
        let mass = split_u128(&self.mask_mass);
        let sums = split_u128(&self.weights.sums);
        let (m, e) = (self.num_masks(), self.weights.nnz());
        // The writer of a SPEC kind, with our own `format`: the writer keeps a `format`
        // value that was set explicitly.
        let mut w = FileWriter::new(Kind::Features);
        w.meta("format", PARTIAL_FORMAT)
            .meta("format_version", PARTIAL_VERSION)
            .meta(
                "generator",
                format!("profuse-fuse {}", env!("CARGO_PKG_VERSION")),
            )
            .meta("num_gaussians", self.num_gaussians.to_string())
            .meta("num_views", self.num_views.to_string())
            .meta("k", self.k.to_string())
            .meta("grouping", self.groups.grouping.name())
            .meta("orphans", self.groups.grouping.orphans_name())
            .meta("num_groups", self.groups.num_groups.to_string())
            .meta("pixels", self.counts.pixels.to_string())
            .meta("hits", self.counts.hits.to_string())
            .meta("weight_scale", "2^-62");
        w.tensor("views", &[self.views.len()], &self.views)
            .tensor("mask_group", &[m], &self.groups.mask_group)
            .tensor("mask_mass", &[m, 2], &mass)
            .tensor(
                "w_offsets",
                &[self.weights.offsets.len()],
                &self.weights.offsets,
            )
            .tensor("w_groups", &[e], &self.weights.groups)
            .tensor("w_sums", &[e, 2], &sums);
        if matches!(self.groups.grouping, Grouping::Blend { .. }) {
            // The blend forms each mask's descriptor from its proposal's members, which
            // `finish` after a merge must know without the proposals file.
            w.tensor("mask_proposal", &[m], &self.groups.mask_proposal);
        }
        match &self.mask_features {
            Floats::F16(b) => w.tensor("mask_features", &[m, self.dim], b),
            Floats::F32(b) => w.tensor("mask_features", &[m, self.dim], b),
        };
        w.commit(path)?;
        Ok(())
    }

    /// Reads and checks a partial-sums file: layout, index ranges, sorted rows, nonzero
    /// sums, finite features. Errors name the file and the tensor or key.
    pub fn read(path: impl AsRef<Path>) -> Result<PartialSums> {
        let c = Container::open(path)?;
        Ok(PartialReader { c: &c }.read()?)
    }
}

/// Adds partial sums of disjoint view sets. The grouping, the mask features, N, V and K
/// must agree; `names` label the parts in errors. The result's integers are the same
/// whatever the split and order of the parts.
pub fn merge(parts: &[PartialSums], names: &[String]) -> Result<PartialSums> {
    let first = parts.first().ok_or(FuseError::NothingToMerge)?;
    let name = |i: usize| names.get(i).cloned().unwrap_or_else(|| format!("part {i}"));
    let mut owner: Vec<Option<usize>> = vec![None; first.num_views];
    for (i, p) in parts.iter().enumerate() {
        check_same(first, p, &name(i))?;
        for v in &p.views {
            let slot = &mut owner[*v as usize];
            if let Some(j) = *slot {
                return Err(FuseError::ViewOverlap {
                    view: *v,
                    first: name(j),
                    second: name(i),
                });
            }
            *slot = Some(i);
        }
    }
    let mut acc = Accumulator::new(
        first.num_gaussians,
        first.num_masks(),
        first.groups.num_groups,
    );
    for p in parts {
        for (m, q) in p.mask_mass.iter().enumerate() {
            acc.add_mass(m, *q);
        }
        for g in 0..p.weights.rows() {
            let (groups, sums) = p.weights.row(g);
            for (group, q) in groups.iter().zip(sums) {
                acc.add_entry(g, *group, *q);
            }
        }
        acc.add_counts(p.counts);
    }
    let (weights, mask_mass) = acc.finish()?;
    let mut views: Vec<u32> = parts.iter().flat_map(|p| p.views.iter().copied()).collect();
    views.sort_unstable();
    Ok(PartialSums {
        views,
        mask_mass,
        weights,
        counts: parts.iter().fold(HitCounts::default(), |a, p| HitCounts {
            pixels: a.pixels + p.counts.pixels,
            hits: a.hits + p.counts.hits,
        }),
        timings: Timings::default(),
        ..first.clone()
    })
}

/// `p` was computed for the same inputs and parameters as `first`.
fn check_same(first: &PartialSums, p: &PartialSums, name: &str) -> Result<()> {
    let differ = |field: &'static str, expected: String, found: String| {
        Err(FuseError::PartialMismatch {
            path: name.to_string(),
            field,
            expected,
            found,
        })
    };
    let facts = |p: &PartialSums| {
        [
            ("num_gaussians", p.num_gaussians.to_string()),
            ("num_views", p.num_views.to_string()),
            ("k", p.k.to_string()),
            ("grouping", p.groups.grouping.name().to_string()),
            ("orphans", p.groups.grouping.orphans_name().to_string()),
            ("num_groups", p.groups.num_groups.to_string()),
            ("mask_features", format!("[{}, {}]", p.num_masks(), p.dim)),
        ]
    };
    for ((field, a), (_, b)) in facts(first).into_iter().zip(facts(p)) {
        if a != b {
            return differ(field, a, b);
        }
    }
    if first.groups.mask_group != p.groups.mask_group {
        return differ(
            "mask_group",
            "one grouping".into(),
            "a different one".into(),
        );
    }
    if first.groups.mask_proposal != p.groups.mask_proposal {
        return differ(
            "mask_proposal",
            "one set of proposals".into(),
            "a different one".into(),
        );
    }
    if first.mask_features != p.mask_features {
        return differ(
            "mask_features",
            "one feature table".into(),
            "different features".into(),
        );
    }
    Ok(())
}

/// u128 values as (low, high) u64 pairs, flattened.
fn split_u128(values: &[u128]) -> Vec<u64> {
    values
        .iter()
        .flat_map(|v| [*v as u64, (*v >> 64) as u64])
        .collect()
}

struct PartialReader<'c> {
    c: &'c Container,
}

impl PartialReader<'_> {
    fn path(&self) -> String {
        self.c.path().to_string()
    }

    fn meta_err(&self, key: &str, expected: &str) -> FormatError {
        FormatError::Metadata {
            path: self.path(),
            key: key.to_string(),
            expected: expected.to_string(),
        }
    }

    fn meta(&self, key: &str) -> std::result::Result<&str, FormatError> {
        self.c
            .metadata()
            .get(key)
            .map(String::as_str)
            .ok_or_else(|| self.meta_err(key, "present"))
    }

    fn meta_usize(&self, key: &str) -> std::result::Result<usize, FormatError> {
        let v = self.meta(key)?;
        if v.is_empty() || !v.bytes().all(|b| b.is_ascii_digit()) {
            return Err(self.meta_err(key, "a decimal integer"));
        }
        v.parse()
            .map_err(|_| self.meta_err(key, "a decimal integer"))
    }

    /// A tensor of dtype `T` with exactly `shape`.
    fn tensor<T: profuse_formats::Element>(
        &self,
        name: &str,
        shape: &[usize],
    ) -> std::result::Result<profuse_formats::Buffer<T>, FormatError> {
        let info = self.c.info(name, &format!("{shape:?}"))?;
        let b = self.c.buffer::<T>(name)?;
        if info.shape != shape {
            return Err(FormatError::Shape {
                path: self.path(),
                tensor: name.to_string(),
                found: info.shape.clone(),
                expected: format!("{shape:?}"),
            });
        }
        Ok(b)
    }

    /// A tensor of dtype `T` and rank `rank` (shape checked by the caller).
    fn any_shape<T: profuse_formats::Element>(
        &self,
        name: &str,
        rank: usize,
    ) -> std::result::Result<(profuse_formats::Buffer<T>, Vec<usize>), FormatError> {
        let info = self.c.info(name, &format!("a rank-{rank} tensor"))?;
        if info.shape.len() != rank {
            return Err(FormatError::Shape {
                path: self.path(),
                tensor: name.to_string(),
                found: info.shape.clone(),
                expected: format!("a rank-{rank} tensor"),
            });
        }
        let shape = info.shape.clone();
        Ok((self.c.buffer::<T>(name)?, shape))
    }

    fn invalid(&self, tensor: &str, detail: String) -> FormatError {
        FormatError::Invalid {
            path: self.path(),
            tensor: tensor.to_string(),
            detail,
        }
    }

    fn out_of_range(
        &self,
        tensor: &str,
        index: usize,
        value: u64,
        expected: String,
    ) -> FormatError {
        FormatError::OutOfRange {
            path: self.path(),
            tensor: tensor.to_string(),
            index,
            value: value.to_string(),
            expected,
        }
    }

    fn read(&self) -> std::result::Result<PartialSums, FormatError> {
        let format = self.c.metadata().get("format");
        if format.map(String::as_str) != Some(PARTIAL_FORMAT) {
            return Err(FormatError::WrongKind {
                path: self.path(),
                expected: PARTIAL_FORMAT.to_string(),
                found: format.map_or("absent".to_string(), |f| format!("{f:?}")),
            });
        }
        profuse_formats::check_version(self.c)?;
        let n = self.meta_usize("num_gaussians")?;
        let v = self.meta_usize("num_views")?;
        let k = self.meta_usize("k")?;
        let num_groups = self.meta_usize("num_groups")?;
        let grouping = match (self.meta("grouping")?, self.meta("orphans")?) {
            ("masks", "none") => Grouping::Masks,
            ("proposals", o) => Grouping::Proposals {
                orphans: Orphans::parse(o)
                    .ok_or_else(|| self.meta_err("orphans", "`ignore` or `singleton`"))?,
            },
            ("blend", o) => Grouping::Blend {
                orphans: Orphans::parse(o)
                    .ok_or_else(|| self.meta_err("orphans", "`ignore` or `singleton`"))?,
            },
            ("masks", _) => return Err(self.meta_err("orphans", "`none` for grouping `masks`")),
            _ => return Err(self.meta_err("grouping", "`proposals`, `masks` or `blend`")),
        };
        let counts = HitCounts {
            pixels: self.meta_usize("pixels")? as u64,
            hits: self.meta_usize("hits")? as u64,
        };

        let (views, _) = self.any_shape::<u32>("views", 1)?;
        let (mask_group, shape) = self.any_shape::<u32>("mask_group", 1)?;
        let m = shape[0];
        let info = self.c.info("mask_features", "F16 or F32 [M, D]")?.clone();
        let dim = match info.shape[..] {
            [rows, d] if rows == m && d >= 1 => d,
            _ => {
                return Err(FormatError::Shape {
                    path: self.path(),
                    tensor: "mask_features".into(),
                    found: info.shape,
                    expected: format!("[{m}, D] with D >= 1 (M from `mask_group`)"),
                })
            }
        };
        let mask_features = match info.dtype {
            Dtype::F16 => Floats::F16(self.c.buffer("mask_features")?),
            Dtype::F32 => Floats::F32(self.c.buffer("mask_features")?),
            other => {
                return Err(FormatError::Dtype {
                    path: self.path(),
                    tensor: "mask_features".into(),
                    found: other.to_string(),
                    expected: "F16 or F32".into(),
                })
            }
        };
        let mass = self.tensor::<u64>("mask_mass", &[m, 2])?;
        let offsets = self.tensor::<u64>("w_offsets", &[n + 1])?;
        let (w_groups, shape) = self.any_shape::<u32>("w_groups", 1)?;
        let e = shape[0];
        let sums = self.tensor::<u64>("w_sums", &[e, 2])?;

        // Value rules.
        for (i, view) in views.iter().enumerate() {
            if *view as usize >= v || (i > 0 && views[i - 1] >= *view) {
                return Err(self.out_of_range(
                    "views",
                    i,
                    u64::from(*view),
                    format!("ascending unique view ids < {v}"),
                ));
            }
        }
        for (i, g) in mask_group.iter().enumerate() {
            if *g != NO_GROUP && *g as usize >= num_groups {
                return Err(self.out_of_range(
                    "mask_group",
                    i,
                    u64::from(*g),
                    format!("a group < {num_groups} or 4294967295"),
                ));
            }
        }
        if grouping == Grouping::Masks
            && (num_groups != m || mask_group.iter().enumerate().any(|(i, g)| *g as usize != i))
        {
            return Err(self.invalid(
                "mask_group",
                "grouping `masks` puts mask i in group i".into(),
            ));
        }
        let mask_proposal = match grouping {
            Grouping::Blend { orphans } => {
                let proposals = self.tensor::<u32>("mask_proposal", &[m])?.to_vec();
                if num_groups != m {
                    return Err(self.meta_err(
                        "num_groups",
                        &format!("{m} (grouping `blend` has one group per mask)"),
                    ));
                }
                if let Some(i) = blend_group_mismatch(&proposals, &mask_group, orphans) {
                    return Err(self.invalid(
                        "mask_group",
                        format!(
                            "mask {i}: grouping `blend` puts mask i in group i, or none when \
                             it has no proposal and orphans are ignored (`mask_proposal`)"
                        ),
                    ));
                }
                proposals
            }
            _ => {
                if self.c.tensors().contains_key("mask_proposal") {
                    return Err(self.invalid(
                        "mask_proposal",
                        format!(
                            "present only for grouping `blend`, not `{}`",
                            grouping.name()
                        ),
                    ));
                }
                Vec::new()
            }
        };
        for (i, x) in mask_features.to_f32_vec().iter().enumerate() {
            if !x.is_finite() {
                return Err(FormatError::NonFinite {
                    path: self.path(),
                    tensor: "mask_features".into(),
                    index: i,
                    value: x.to_string(),
                });
            }
        }
        if offsets.first() != Some(&0) || offsets.last() != Some(&(e as u64)) {
            return Err(self.invalid(
                "w_offsets",
                format!("must start at 0 and end at {e} (the entries of `w_groups`)"),
            ));
        }
        for g in 0..n {
            let (a, b) = (offsets[g], offsets[g + 1]);
            if b < a || b > e as u64 {
                return Err(self.out_of_range(
                    "w_offsets",
                    g + 1,
                    b,
                    format!("non-decreasing offsets in {a}..={e}"),
                ));
            }
            let row = &w_groups[a as usize..b as usize];
            for (j, group) in row.iter().enumerate() {
                if *group as usize >= num_groups || (j > 0 && row[j - 1] >= *group) {
                    return Err(self.out_of_range(
                        "w_groups",
                        a as usize + j,
                        u64::from(*group),
                        format!("groups < {num_groups}, strictly ascending within a row"),
                    ));
                }
            }
        }
        let join = |pairs: &[u64]| -> Vec<u128> {
            pairs
                .chunks_exact(2)
                .map(|p| u128::from(p[0]) | (u128::from(p[1]) << 64))
                .collect()
        };
        let sums = join(&sums);
        if let Some(i) = sums.iter().position(|s| *s == 0) {
            return Err(self.out_of_range("w_sums", i, 0, "a nonzero sum".into()));
        }
        Ok(PartialSums {
            num_gaussians: n,
            num_views: v,
            k,
            views: views.to_vec(),
            groups: Groups {
                grouping,
                mask_group: mask_group.to_vec(),
                num_groups,
                mask_proposal,
            },
            mask_features,
            dim,
            mask_mass: join(&mass),
            weights: WeightMatrix {
                num_groups,
                offsets: offsets.to_vec(),
                groups: w_groups.to_vec(),
                sums,
            },
            counts,
            timings: Timings::default(),
        })
    }
}

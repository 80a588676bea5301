//! Partial sums of a view shard: what `fuse run --views a..b --partial-out F` writes and
//! `fuse merge` adds up. The file kind (`profuse.fuse_partial`, SPEC.md §4.15) belongs to
//! the formats crate ([`profuse_formats::FusePartial`]); this module converts to and from it.

use std::collections::BTreeMap;
use std::path::Path;

use profuse_formats::{
    fixed_point, fixed_point_words, FileKind, Floats, FuseGrouping, FuseOrphans, FusePartial,
};

use crate::accumulate::{Accumulator, HitCounts, WeightMatrix};
use crate::error::{FuseError, Result};
use crate::groups::{Grouping, Groups, Orphans};

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
/// # File layout
///
/// `profuse.fuse_partial`, version 1.0 (SPEC.md §4.15): read and written through
/// [`profuse_formats::FusePartial`], which validates every rule of the kind.
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

    /// Writes the file atomically (temp file + rename), validated as SPEC.md's
    /// `profuse.fuse_partial` kind.
    pub fn write(&self, path: impl AsRef<Path>) -> Result<()> {
        self.to_file().write(path)?;
        Ok(())
    }

    /// The file this value is written as.
    fn to_file(&self) -> FusePartial {
        let extra = BTreeMap::from([
            (
                "generator".to_string(),
                format!("profuse-fuse {}", env!("CARGO_PKG_VERSION")),
            ),
            ("weight_scale".to_string(), "2^-62".to_string()),
        ]);
        let mut extra = extra;
        if self.groups.pixel_share_power > 0.0 {
            extra.insert(
                PIXEL_SHARE_POWER_KEY.to_string(),
                self.groups.pixel_share_power.to_string(),
            );
        }
        let words = |values: &[u128]| -> Vec<[u64; 2]> {
            values.iter().map(|v| fixed_point_words(*v)).collect()
        };
        // The blend forms each mask's descriptor from its proposal's members, which
        // `finish` after a merge must know without the proposals file.
        let mask_proposal = matches!(self.groups.grouping, Grouping::Blend { .. })
            .then(|| self.groups.mask_proposal.clone().into());
        FusePartial {
            num_gaussians: self.num_gaussians,
            num_views: self.num_views,
            k: self.k,
            grouping: match self.groups.grouping {
                Grouping::Proposals { orphans } => FuseGrouping::Proposals {
                    orphans: file_orphans(orphans),
                },
                Grouping::Masks => FuseGrouping::Masks,
                Grouping::Blend { orphans } => FuseGrouping::Blend {
                    orphans: file_orphans(orphans),
                },
            },
            num_groups: self.groups.num_groups,
            pixels: self.counts.pixels,
            hits: self.counts.hits,
            views: self.views.clone().into(),
            mask_group: self.groups.mask_group.clone().into(),
            mask_proposal,
            mask_share: (!self.groups.mask_share.is_empty())
                .then(|| self.groups.mask_share.clone().into()),
            mask_features: self.mask_features.clone(),
            dim: self.dim,
            mask_mass: words(&self.mask_mass).into(),
            w_offsets: self.weights.offsets.clone().into(),
            w_groups: self.weights.groups.clone().into(),
            w_sums: words(&self.weights.sums).into(),
            extra,
        }
    }

    /// Reads and checks a partial-sums file (every rule of SPEC.md's `fuse_partial`:
    /// layout, index ranges, sorted rows, nonzero sums, finite features, the grouping's
    /// rules). Errors name the file and the tensor or key.
    pub fn read(path: impl AsRef<Path>) -> Result<PartialSums> {
        let path = path.as_ref();
        let f = FusePartial::read(path)?;
        let power = pixel_share_power(&f, path)?;
        Ok(PartialSums::from_file(f, power))
    }

    /// The sums of a validated file whose members' pixels weighed s^`power`.
    fn from_file(f: FusePartial, power: f64) -> PartialSums {
        let grouping = match f.grouping {
            FuseGrouping::Proposals { orphans } => Grouping::Proposals {
                orphans: fuse_orphans(orphans),
            },
            FuseGrouping::Masks => Grouping::Masks,
            FuseGrouping::Blend { orphans } => Grouping::Blend {
                orphans: fuse_orphans(orphans),
            },
        };
        let join =
            |words: &[[u64; 2]]| -> Vec<u128> { words.iter().map(|w| fixed_point(*w)).collect() };
        PartialSums {
            num_gaussians: f.num_gaussians,
            num_views: f.num_views,
            k: f.k,
            views: f.views.to_vec(),
            groups: Groups {
                grouping,
                mask_group: f.mask_group.to_vec(),
                num_groups: f.num_groups,
                mask_proposal: f.mask_proposal.map(|p| p.to_vec()).unwrap_or_default(),
                mask_share: f.mask_share.map(|s| s.to_vec()).unwrap_or_default(),
                // W already holds the weighed sums; only the exponent is kept.
                pixel_weight: Vec::new(),
                pixel_share_power: power,
            },
            mask_features: f.mask_features,
            dim: f.dim,
            mask_mass: join(&f.mask_mass),
            weights: WeightMatrix {
                num_groups: f.num_groups,
                offsets: f.w_offsets.to_vec(),
                groups: f.w_groups.to_vec(),
                sums: join(&f.w_sums),
            },
            counts: HitCounts {
                pixels: f.pixels,
                hits: f.hits,
            },
            timings: Timings::default(),
        }
    }
}

fn file_orphans(o: Orphans) -> FuseOrphans {
    match o {
        Orphans::Ignore => FuseOrphans::Ignore,
        Orphans::Singleton => FuseOrphans::Singleton,
    }
}

fn fuse_orphans(o: FuseOrphans) -> Orphans {
    match o {
        FuseOrphans::Ignore => Orphans::Ignore,
        FuseOrphans::Singleton => Orphans::Singleton,
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

/// The metadata key of [`crate::Groups::pixel_share_power`] in partial and features
/// files (absent: 0, the paper's pixel weights).
pub(crate) const PIXEL_SHARE_POWER_KEY: &str = "pixel_share_power";

/// The exponent of the members' pixel weights a partial file's W was summed with.
fn pixel_share_power(f: &FusePartial, path: &Path) -> Result<f64> {
    let Some(text) = f.extra.get(PIXEL_SHARE_POWER_KEY) else {
        return Ok(0.0);
    };
    match text.parse::<f64>() {
        Ok(e) if e.is_finite() && e > 0.0 => Ok(e),
        _ => Err(profuse_formats::FormatError::Metadata {
            path: path.display().to_string(),
            key: PIXEL_SHARE_POWER_KEY.to_string(),
            expected: format!(
                "a finite number > 0 (the exponent of the members' pixel weights), got `{text}`"
            ),
        }
        .into()),
    }
}

/// What every partial sum of one job shares: its inputs' sizes, K, the grouping of the
/// masks and the mask features.
pub(crate) struct JobFacts<'a> {
    pub num_gaussians: usize,
    pub num_views: usize,
    pub k: usize,
    pub groups: &'a Groups,
    pub mask_features: &'a Floats,
    pub num_masks: usize,
    pub dim: usize,
}

impl PartialSums {
    pub(crate) fn facts(&self) -> JobFacts<'_> {
        JobFacts {
            num_gaussians: self.num_gaussians,
            num_views: self.num_views,
            k: self.k,
            groups: &self.groups,
            mask_features: &self.mask_features,
            num_masks: self.num_masks(),
            dim: self.dim,
        }
    }
}

/// `p` was computed for the same inputs and parameters as `first`.
pub(crate) fn check_same(first: &PartialSums, p: &PartialSums, name: &str) -> Result<()> {
    compare_facts(&first.facts(), &p.facts()).map_err(|(field, expected, found)| {
        FuseError::PartialMismatch {
            path: name.to_string(),
            field,
            expected,
            found,
        }
    })
}

/// The first field in which `b` differs from `a`: (field, a's value, b's value).
pub(crate) fn compare_facts(
    a: &JobFacts<'_>,
    b: &JobFacts<'_>,
) -> std::result::Result<(), (&'static str, String, String)> {
    let facts = |p: &JobFacts<'_>| {
        [
            ("num_gaussians", p.num_gaussians.to_string()),
            ("num_views", p.num_views.to_string()),
            ("k", p.k.to_string()),
            ("grouping", p.groups.grouping.name().to_string()),
            ("orphans", p.groups.grouping.orphans_name().to_string()),
            ("num_groups", p.groups.num_groups.to_string()),
            ("pixel_share_power", p.groups.pixel_share_power.to_string()),
            ("mask_features", format!("[{}, {}]", p.num_masks, p.dim)),
        ]
    };
    for ((field, x), (_, y)) in facts(a).into_iter().zip(facts(b)) {
        if x != y {
            return Err((field, x, y));
        }
    }
    if a.groups.mask_group != b.groups.mask_group {
        return Err((
            "mask_group",
            "one grouping".into(),
            "a different one".into(),
        ));
    }
    if a.groups.mask_proposal != b.groups.mask_proposal {
        return Err((
            "mask_proposal",
            "one set of proposals".into(),
            "a different one".into(),
        ));
    }
    if a.groups.mask_share != b.groups.mask_share {
        return Err((
            "mask_share",
            "one set of member shares".into(),
            "a different one".into(),
        ));
    }
    if a.mask_features != b.mask_features {
        return Err((
            "mask_features",
            "one feature table".into(),
            "different features".into(),
        ));
    }
    Ok(())
}

//! Which descriptor each mask registers: its proposal's (paper), its own (Dr. Splat-style
//! baseline), or a blend of the two weighted by how well the mask agrees with its proposal.

use profuse_formats::{Masks, Proposals, NO_PROPOSAL};

use crate::error::Result;

/// "This mask registers nothing" in [`Groups::mask_group`] (the value of
/// [`NO_PROPOSAL`]).
pub const NO_GROUP: u32 = NO_PROPOSAL;

/// What to do with masks whose proposal was filtered out (`mask_proposal` = none).
///
/// The default is `Singleton`: the masks a grouping leaves out (under-segmented masks that
/// the consensus grouping drops, fragments below `s_min`) still carry evidence, and
/// ignoring them leaves their pixels without semantics, which the per-mask baseline never
/// does. On the synthetic demo with the consensus grouping, `singleton` raised the
/// ScanNet-protocol mIoU19 by 2-7 points over `ignore` and left LERF within ±0.2 (seeds
/// 0, 3, 4; harsh segmentation seed 0: +7.1, LERF +0.3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Orphans {
    /// Their pixels register nothing (the paper: pixels outside every proposal get the
    /// null label).
    Ignore,
    /// Each becomes a proposal of its own, with its own feature.
    #[default]
    Singleton,
}

impl Orphans {
    /// `ignore` or `singleton`.
    pub fn name(self) -> &'static str {
        match self {
            Orphans::Ignore => "ignore",
            Orphans::Singleton => "singleton",
        }
    }

    /// Parses [`Orphans::name`].
    pub fn parse(s: &str) -> Option<Orphans> {
        match s {
            "ignore" => Some(Orphans::Ignore),
            "singleton" => Some(Orphans::Singleton),
            _ => None,
        }
    }
}

/// What a member mask weighs in its proposal's descriptor.
///
/// The default is `Share`: a mask that the consensus grouping put into a proposal may
/// still cover a neighbouring object in part (a sofa mask merged with the cabinet beside
/// it), and by its mass alone its foreign part enters the proposal's descriptor in full,
/// so that the pooled sofa answers "cabinet" (seed 2, `default`: cabinet IoU 54.2 against
/// the per-mask baseline's 65.6). Weighing its mass by the share of its area that the
/// other views find on one object (the proposals file's `mask_share`) counts only the
/// part the grouping vouches for. Measured over seeds 0-15 in crates/warp-graph/README.md.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum MemberWeight {
    /// μ_m, the mask's mass (the paper's eq. proposal-desc).
    Mass,
    /// μ_m · s_m, with s_m the proposals file's `mask_share` (μ_m where the file has
    /// none).
    #[default]
    Share,
}

impl MemberWeight {
    /// `mass` or `share`.
    pub fn name(self) -> &'static str {
        match self {
            MemberWeight::Mass => "mass",
            MemberWeight::Share => "share",
        }
    }
}

/// Where the descriptors come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Grouping {
    /// 3D Context Proposals (paper eq. proposal-desc): a group's descriptor is the
    /// L2-normalised mass-weighted sum of its member masks' features.
    Proposals {
        /// Masks without a proposal.
        orphans: Orphans,
    },
    /// No proposals (the Dr. Splat-style baseline): every mask is its own group and
    /// registers its own feature, not mass-weighted.
    Masks,
    /// Proposals, blended per mask (a deviation from the paper, against impure proposals):
    /// mask m of proposal P registers d_m = normalise(α_m f̄_P + (1 − α_m) f̂_m), where
    /// f̄_P is the paper's descriptor, f̂_m the mask's own normalised feature,
    /// a_m = cos(f_m, f̄_P), c_P = Σ_{k∈P} μ_k a_k / Σ_{k∈P} μ_k and
    /// α_m = clamp(a_m / c_P, 0, 1) (0 when c_P <= 0). A mask at least as coherent with its
    /// proposal as the proposal's average member keeps f̄_P; a mask orthogonal to it keeps
    /// its own feature. d_m is per mask, so every mask is its own group of W; the proposals
    /// are kept in [`Groups::mask_proposal`].
    Blend {
        /// Masks without a proposal: ignored, or registering their own feature.
        orphans: Orphans,
    },
}

impl Grouping {
    /// `proposals`, `masks` or `blend`.
    pub fn name(self) -> &'static str {
        match self {
            Grouping::Proposals { .. } => "proposals",
            Grouping::Masks => "masks",
            Grouping::Blend { .. } => "blend",
        }
    }

    /// The orphan policy's name, `none` for [`Grouping::Masks`] (no mask is an orphan).
    pub fn orphans_name(self) -> &'static str {
        match self {
            Grouping::Proposals { orphans } | Grouping::Blend { orphans } => orphans.name(),
            Grouping::Masks => "none",
        }
    }
}

/// The group (proposal, or mask) every global mask registers into.
#[derive(Debug, Clone, PartialEq)]
pub struct Groups {
    /// How the groups were formed.
    pub grouping: Grouping,
    /// Group of every global mask, or [`NO_GROUP`].
    pub mask_group: Vec<u32>,
    /// Number of groups G; every entry of `mask_group` is `< G` or [`NO_GROUP`].
    pub num_groups: usize,
    /// For [`Grouping::Blend`]: the proposal of every global mask (the ids of the
    /// proposals file), or [`NO_PROPOSAL`]; empty for the other groupings, whose groups
    /// already are the proposals or need none. The blend needs it after the pass, when it
    /// forms each mask's descriptor from its proposal's members.
    pub mask_proposal: Vec<u32>,
    /// The share s_m of every global mask (the proposals file's `mask_share`) by which
    /// its mass is weighed in its proposal's descriptor ([`MemberWeight::Share`]); empty:
    /// every member weighs its mass. Always empty for [`Grouping::Masks`].
    pub mask_share: Vec<f32>,
    /// The factor of every global mask's pixel weights ω in W, in units of 2^-16
    /// ([`PIXEL_WEIGHT_ONE`] = 1): s_m^e for a member of a proposal, with s_m its share
    /// and e [`Groups::pixel_share_power`], 1 for an orphan ([`Groups::with_pixel_shares`]).
    /// Empty: every pixel weighs ω (the paper). Only the accumulation reads it; partial
    /// files keep e, not the factors, whose sums W already holds.
    pub pixel_weight: Vec<u32>,
    /// The exponent e of the members' pixel weights s_m^e in W; 0: the paper's ω.
    pub pixel_share_power: f64,
}

/// The pixel-weight factor 1 of [`Groups::pixel_weight`] (units of 2^-16).
pub const PIXEL_WEIGHT_ONE: u32 = 1 << 16;

/// One hit's fixed-point weight `q` times a pixel-weight factor (units of 2^-16),
/// truncated: exact integer arithmetic, so sums stay independent of order and split, and
/// a factor of [`PIXEL_WEIGHT_ONE`] returns `q` itself.
#[inline]
pub(crate) fn weigh_hit(q: u64, factor: u32) -> u64 {
    ((u128::from(q) * u128::from(factor)) >> 16) as u64
}

impl Groups {
    /// Groups = proposals `0..P`; with [`Orphans::Singleton`] every mask without a
    /// proposal becomes group `P + i`, `i` counting orphans in global mask order. Checks the
    /// proposals against the masks (SPEC.md §4.6); `proposals_name` names the file in
    /// errors.
    pub fn from_proposals(
        masks: &Masks,
        proposals: &Proposals,
        orphans: Orphans,
        weight: MemberWeight,
        proposals_name: &str,
    ) -> Result<Groups> {
        proposals.check_against(masks, proposals_name)?;
        let mut mask_group = proposals.mask_proposal.to_vec();
        let mut num_groups = proposals.len();
        if orphans == Orphans::Singleton {
            for g in mask_group.iter_mut().filter(|g| **g == NO_PROPOSAL) {
                *g = num_groups as u32;
                num_groups += 1;
            }
        }
        Ok(Groups {
            grouping: Grouping::Proposals { orphans },
            mask_group,
            num_groups,
            mask_proposal: Vec::new(),
            mask_share: member_shares(proposals, weight),
            pixel_weight: Vec::new(),
            pixel_share_power: 0.0,
        })
    }

    /// Weighs every member mask's pixels in W by s_m^`power`, s_m the proposals file's
    /// `mask_share` (a deviation from the paper, issue 16): a member the other views find
    /// only partly on its proposal's object (a chair mask that runs onto the floor) then
    /// registers its proposal's descriptor with less weight on every Gaussian it covers,
    /// so that where it overlaps the neighbour the neighbour's own masks decide. Orphans
    /// keep weight 1 (they register their own feature, as the baseline does). `power` 0,
    /// a file without shares or [`Grouping::Masks`] leave the paper's weights. The
    /// factors are quantised to 2^-16.
    pub fn with_pixel_shares(mut self, proposals: &Proposals, power: f64) -> Result<Groups> {
        check_pixel_share_power(power)?;
        let Some(shares) = &proposals.mask_share else {
            return Ok(self);
        };
        if power == 0.0 || self.grouping == Grouping::Masks {
            return Ok(self);
        }
        self.pixel_weight = proposals
            .mask_proposal
            .iter()
            .zip(shares.iter())
            .map(|(p, s)| {
                if *p == NO_PROPOSAL {
                    PIXEL_WEIGHT_ONE
                } else {
                    pixel_factor(f64::from(*s), power)
                }
            })
            .collect();
        self.pixel_share_power = power;
        Ok(self)
    }

    /// [`Grouping::Blend`]: every mask is its own group (orphans too with
    /// [`Orphans::Singleton`]; ignored orphans get [`NO_GROUP`]), and its proposal is kept
    /// for the blend. Checks the proposals against the masks like
    /// [`Groups::from_proposals`].
    pub fn blend(
        masks: &Masks,
        proposals: &Proposals,
        orphans: Orphans,
        weight: MemberWeight,
        proposals_name: &str,
    ) -> Result<Groups> {
        proposals.check_against(masks, proposals_name)?;
        let mask_proposal = proposals.mask_proposal.to_vec();
        Ok(Groups {
            grouping: Grouping::Blend { orphans },
            mask_group: blend_mask_groups(&mask_proposal, orphans),
            num_groups: mask_proposal.len(),
            mask_proposal,
            mask_share: member_shares(proposals, weight),
            pixel_weight: Vec::new(),
            pixel_share_power: 0.0,
        })
    }

    /// Every mask its own group (`--no-proposals`).
    pub fn per_mask(masks: &Masks) -> Groups {
        let m = masks.num_masks();
        Groups {
            grouping: Grouping::Masks,
            mask_group: (0..m as u32).collect(),
            num_groups: m,
            mask_proposal: Vec::new(),
            mask_share: Vec::new(),
            pixel_weight: Vec::new(),
            pixel_share_power: 0.0,
        }
    }

    /// One entry per mask (`num_masks`), each `< num_groups` or [`NO_GROUP`]; for
    /// [`Grouping::Blend`] also one proposal per mask, and the groups those imply.
    pub fn check(&self, num_masks: usize) -> Result<(), String> {
        if self.mask_group.len() != num_masks {
            return Err(format!(
                "{} entries for {num_masks} masks",
                self.mask_group.len()
            ));
        }
        match self.grouping {
            Grouping::Blend { orphans } => {
                if self.mask_proposal.len() != num_masks || self.num_groups != num_masks {
                    return Err(format!(
                        "{} proposal entries and {} groups for {num_masks} masks (grouping \
                         `blend` has one of each per mask)",
                        self.mask_proposal.len(),
                        self.num_groups
                    ));
                }
                if let Some(m) =
                    blend_group_mismatch(&self.mask_proposal, &self.mask_group, orphans)
                {
                    return Err(format!(
                        "mask {m} is in group {} but grouping `blend` puts it in its own \
                         group (or none for an ignored orphan)",
                        self.mask_group[m]
                    ));
                }
            }
            _ if !self.mask_proposal.is_empty() => {
                return Err(format!(
                    "grouping `{}` keeps no proposals, but {} are given",
                    self.grouping.name(),
                    self.mask_proposal.len()
                ));
            }
            _ => {}
        }
        if !self.mask_share.is_empty() {
            if self.grouping == Grouping::Masks {
                return Err("grouping `masks` weighs no members, but shares are given".into());
            }
            if self.mask_share.len() != num_masks {
                return Err(format!(
                    "{} shares for {num_masks} masks",
                    self.mask_share.len()
                ));
            }
        }
        if !self.pixel_weight.is_empty() && self.pixel_weight.len() != num_masks {
            return Err(format!(
                "{} pixel weights for {num_masks} masks",
                self.pixel_weight.len()
            ));
        }
        if let Some(m) = self.pixel_weight.iter().position(|w| *w > PIXEL_WEIGHT_ONE) {
            return Err(format!(
                "mask {m}'s pixel weight {} is above 1",
                f64::from(self.pixel_weight[m]) / f64::from(PIXEL_WEIGHT_ONE)
            ));
        }
        match self
            .mask_group
            .iter()
            .position(|g| *g != NO_GROUP && *g as usize >= self.num_groups)
        {
            Some(m) => Err(format!(
                "mask {m} is in group {} of {}",
                self.mask_group[m], self.num_groups
            )),
            None => Ok(()),
        }
    }

    /// Masks that register into some group.
    pub fn assigned_masks(&self) -> usize {
        self.mask_group.iter().filter(|g| **g != NO_GROUP).count()
    }

    /// What the members weigh: [`MemberWeight::Share`] when shares are kept.
    pub fn member_weight(&self) -> MemberWeight {
        if self.mask_share.is_empty() {
            MemberWeight::Mass
        } else {
            MemberWeight::Share
        }
    }

    /// The factor of mask m's mass in its proposal's descriptor: s_m, or 1.
    pub fn share(&self, m: usize) -> f64 {
        self.mask_share.get(m).map_or(1.0, |s| f64::from(*s))
    }
}

/// The exponent of the members' pixel weights must be a finite number >= 0.
pub(crate) fn check_pixel_share_power(power: f64) -> Result<()> {
    if power.is_finite() && power >= 0.0 {
        Ok(())
    } else {
        Err(crate::FuseError::PixelSharePower(power))
    }
}

/// s^e in units of 2^-16, rounded, with s clamped to [0, 1].
fn pixel_factor(share: f64, power: f64) -> u32 {
    let f = share.clamp(0.0, 1.0).powf(power) * f64::from(PIXEL_WEIGHT_ONE);
    (f.round() as u32).min(PIXEL_WEIGHT_ONE)
}

/// The proposals' shares under `weight` (none for [`MemberWeight::Mass`] or a file
/// without `mask_share`).
fn member_shares(proposals: &Proposals, weight: MemberWeight) -> Vec<f32> {
    match (&proposals.mask_share, weight) {
        (Some(s), MemberWeight::Share) => s.to_vec(),
        _ => Vec::new(),
    }
}

/// The groups of [`Grouping::Blend`]: mask m is group m, except an ignored orphan (no
/// group).
pub(crate) fn blend_mask_groups(mask_proposal: &[u32], orphans: Orphans) -> Vec<u32> {
    mask_proposal
        .iter()
        .enumerate()
        .map(|(m, p)| {
            if *p == NO_PROPOSAL && orphans == Orphans::Ignore {
                NO_GROUP
            } else {
                m as u32
            }
        })
        .collect()
}

/// The first mask whose group is not the one [`blend_mask_groups`] gives it.
pub(crate) fn blend_group_mismatch(
    mask_proposal: &[u32],
    mask_group: &[u32],
    orphans: Orphans,
) -> Option<usize> {
    let expected = blend_mask_groups(mask_proposal, orphans);
    (0..expected.len().max(mask_group.len())).find(|m| expected.get(*m) != mask_group.get(*m))
}

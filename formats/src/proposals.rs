//! `profuse.proposals`: 3D Context Proposals, the mask clusters of warp-graph
//! (SPEC.md "proposals").

use std::collections::BTreeMap;

use crate::check::{check_finite, check_ids, check_len, invalid, out_of_range, TensorReader};
use crate::container::{Buffer, Container};
use crate::error::Result;
use crate::kind::{FileKind, Kind};
use crate::masks::Masks;
use crate::writer::FileWriter;

/// "No proposal" in `mask_proposal`.
pub const NO_PROPOSAL: u32 = u32::MAX;

/// The proposal of every mask plus per-proposal member and view counts.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Proposals {
    /// `mask_proposal` U32 [M]: proposal id of each global mask, or 4294967295 (none).
    pub mask_proposal: Buffer<u32>,
    /// `proposal_size` U32 [P]: member masks of each proposal (>= 1).
    pub proposal_size: Buffer<u32>,
    /// `proposal_views` U32 [P]: distinct views among the members (1..=size).
    pub proposal_views: Buffer<u32>,
    /// Optional `mask_share` F32 [M], each in (0, 1]: the estimated share of every mask's
    /// area that lies on the one object its best container in the other views holds
    /// (written by the consensus grouping; `fuse` weighs a member's mass by it).
    pub mask_share: Option<Buffer<f32>>,
    /// Optional `mask_instance` U32 [M]: the object instance (a proposal id) of every
    /// mask: its proposal for a member; for a mask in no proposal (an under-segmented
    /// one), the proposal holding most of its area, or 4294967295 (none). Members pool
    /// into their proposal's descriptor; an attached mask only belongs to the instance and
    /// registers its own feature (written by the consensus grouping).
    pub mask_instance: Option<Buffer<u32>>,
    /// Other metadata (the thresholds used are recorded here), kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl Proposals {
    /// Number of proposals P.
    pub fn len(&self) -> usize {
        self.proposal_size.len()
    }

    /// Whether there are no proposals.
    pub fn is_empty(&self) -> bool {
        self.proposal_size.is_empty()
    }

    /// The object instance of every mask: `mask_instance` when present, otherwise the
    /// proposal (`mask_proposal`), [`NO_PROPOSAL`] for none.
    pub fn instances(&self) -> &[u32] {
        self.mask_instance.as_deref().unwrap_or(&self.mask_proposal)
    }

    /// Checks this file against the masks file it was built from: one entry per mask,
    /// and view counts that match the masks' views.
    pub fn check_against(&self, masks: &Masks, path: &str) -> Result<()> {
        check_len(
            path,
            "mask_proposal",
            self.mask_proposal.len(),
            masks.num_masks(),
            "entries, one per mask of the masks file",
        )?;
        let mut views: Vec<Vec<usize>> = vec![Vec::new(); self.len()];
        for (m, p) in self.mask_proposal.iter().enumerate() {
            if *p != NO_PROPOSAL {
                views[*p as usize].push(masks.view_of(m));
            }
        }
        for (p, mut v) in views.into_iter().enumerate() {
            v.dedup();
            if v.len() != self.proposal_views[p] as usize {
                return Err(invalid(
                    path,
                    "proposal_views",
                    format!(
                        "proposal {p} records {} views but its masks span {}",
                        self.proposal_views[p],
                        v.len()
                    ),
                ));
            }
        }
        Ok(())
    }
}

impl FileKind for Proposals {
    const KIND: Kind = Kind::Proposals;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        Ok(Proposals {
            mask_proposal: r.req("mask_proposal", "M")?,
            proposal_size: r.req("proposal_size", "P")?,
            proposal_views: r.req("proposal_views", "P")?,
            mask_share: r.opt("mask_share", "M")?,
            mask_instance: r.opt("mask_instance", "M")?,
            extra: r.extra_meta(&[]),
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        let p = self.len();
        check_len(
            path,
            "proposal_views",
            self.proposal_views.len(),
            p,
            "values, one per proposal",
        )?;
        check_ids(
            path,
            "mask_proposal",
            &self.mask_proposal,
            p as u64,
            Some(u64::from(NO_PROPOSAL)),
            "the proposals",
        )?;
        if let Some(s) = &self.mask_share {
            check_share(path, "mask_share", s, self.mask_proposal.len())?;
        }
        if let Some(inst) = &self.mask_instance {
            check_instances(path, inst, &self.mask_proposal, p)?;
        }
        let mut members = vec![0u64; p];
        for id in self.mask_proposal.iter().filter(|id| **id != NO_PROPOSAL) {
            members[*id as usize] += 1;
        }
        for (i, (size, views)) in self
            .proposal_size
            .iter()
            .zip(self.proposal_views.iter())
            .enumerate()
        {
            if u64::from(*size) != members[i] {
                return Err(invalid(
                    path,
                    "proposal_size",
                    format!(
                        "proposal {i} records {size} members but mask_proposal assigns {}",
                        members[i]
                    ),
                ));
            }
            if *size == 0 {
                return Err(invalid(
                    path,
                    "proposal_size",
                    format!("proposal {i} is empty"),
                ));
            }
            if *views == 0 || views > size {
                return Err(crate::check::out_of_range(
                    path,
                    "proposal_views",
                    i,
                    views,
                    format!("a view count in 1..={size} (its member count)"),
                ));
            }
        }
        Ok(())
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        w.tensor(
            "mask_proposal",
            &[self.mask_proposal.len()],
            &self.mask_proposal,
        )
        .tensor("proposal_size", &[self.len()], &self.proposal_size)
        .tensor("proposal_views", &[self.len()], &self.proposal_views);
        if let Some(s) = &self.mask_share {
            w.tensor("mask_share", &[s.len()], s);
        }
        if let Some(i) = &self.mask_instance {
            w.tensor("mask_instance", &[i.len()], i);
        }
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("masks", self.mask_proposal.len() as u64),
            ("proposals", self.len() as u64),
            (
                "assigned_masks",
                self.mask_proposal
                    .iter()
                    .filter(|p| **p != NO_PROPOSAL)
                    .count() as u64,
            ),
        ])
    }
}

/// `mask_instance`: one id per mask, each a proposal or none, and a member's instance is
/// its proposal.
fn check_instances(path: &str, inst: &[u32], proposal: &[u32], proposals: usize) -> Result<()> {
    check_len(
        path,
        "mask_instance",
        inst.len(),
        proposal.len(),
        "ids, one per mask",
    )?;
    check_ids(
        path,
        "mask_instance",
        inst,
        proposals as u64,
        Some(u64::from(NO_PROPOSAL)),
        "the proposals",
    )?;
    match inst
        .iter()
        .zip(proposal)
        .position(|(i, p)| *p != NO_PROPOSAL && i != p)
    {
        Some(m) => Err(invalid(
            path,
            "mask_instance",
            format!(
                "mask {m} is a member of proposal {} but its instance is {}",
                proposal[m], inst[m]
            ),
        )),
        None => Ok(()),
    }
}

/// A per-mask share tensor: `masks` values, each finite and in (0, 1].
pub(crate) fn check_share(path: &str, tensor: &str, s: &[f32], masks: usize) -> Result<()> {
    check_len(path, tensor, s.len(), masks, "values, one per mask")?;
    check_finite(path, tensor, s)?;
    match s.iter().position(|v| !(*v > 0.0 && *v <= 1.0)) {
        Some(i) => Err(out_of_range(path, tensor, i, s[i], "a share in (0, 1]")),
        None => Ok(()),
    }
}

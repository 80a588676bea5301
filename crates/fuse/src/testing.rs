//! Test and benchmark utilities (not part of the stable API): proposals from a synthetic
//! scene's ground truth, so registration can be tested without `warp-graph`.

use std::collections::BTreeMap;
use std::path::Path;

use profuse_formats::{Masks, Proposals, NO_PROPOSAL};

/// Boxed error of the utilities.
pub type BoxError = Box<dyn std::error::Error + Send + Sync + 'static>;

/// Proposals from `synth`'s `gt/mask_objects.json`: all masks whose dominant object is
/// the same form one proposal, numbered by ascending object id; objects with fewer than
/// `min_members` masks, and masks on no object, get no proposal (orphans).
pub fn proposals_from_mask_objects(
    path: impl AsRef<Path>,
    masks: &Masks,
    min_members: usize,
) -> Result<Proposals, BoxError> {
    let path = path.as_ref();
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
    let entries = json["masks"]
        .as_array()
        .ok_or_else(|| format!("{}: no `masks` array", path.display()))?;
    if entries.len() != masks.num_masks() {
        return Err(format!(
            "{}: {} masks, but the masks file has {}",
            path.display(),
            entries.len(),
            masks.num_masks()
        )
        .into());
    }
    let mut object_of = Vec::with_capacity(entries.len());
    for (i, e) in entries.iter().enumerate() {
        if e["id"].as_u64() != Some(i as u64) {
            return Err(format!("{}: entry {i} has id {}", path.display(), e["id"]).into());
        }
        object_of.push(e["object"].as_u64());
    }
    let mut members: BTreeMap<u64, Vec<usize>> = BTreeMap::new();
    for (m, o) in object_of.iter().enumerate() {
        if let Some(o) = o {
            members.entry(*o).or_default().push(m);
        }
    }
    let mut mask_proposal = vec![NO_PROPOSAL; masks.num_masks()];
    let mut sizes = Vec::new();
    let mut views = Vec::new();
    for list in members.values().filter(|l| l.len() >= min_members.max(1)) {
        let p = sizes.len() as u32;
        let mut seen: Vec<usize> = list.iter().map(|m| masks.view_of(*m)).collect();
        seen.dedup();
        for m in list {
            mask_proposal[*m] = p;
        }
        sizes.push(list.len() as u32);
        views.push(seen.len() as u32);
    }
    Ok(Proposals {
        mask_proposal: mask_proposal.into(),
        proposal_size: sizes.into(),
        proposal_views: views.into(),
        mask_share: None,
        mask_instance: None,
        extra: BTreeMap::from([("generator".into(), "synth ground truth".into())]),
    })
}

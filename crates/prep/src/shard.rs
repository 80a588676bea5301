//! `prep masks` and `prep features` over view shards: a shard is a masks file of all V views
//! in which only the views of its range carry masks (the others have an empty label map and
//! no feature rows), marked with the metadata key [`SHARD_VIEWS_KEY`] = `A..B`. Every view's
//! masks and descriptors come from that view's image alone (SAM's generator, the pooled
//! embedding and the CLIP crops read nothing of other views), so [`merge`] stitching shards
//! that cover every view once gives the file of one run, byte for byte.

use std::collections::BTreeMap;
use std::ops::Range;

use profuse_formats::{Floats, Labels, Masks};

use crate::error::{input, Result};

/// The metadata key naming a shard's views (`A..B`, half-open).
pub const SHARD_VIEWS_KEY: &str = "prep_shard_views";

/// The masks with only the views in `views` kept (the others: empty label map, no
/// masks), e.g. the input of a `prep features` shard.
pub fn restrict(masks: &Masks, views: Range<usize>) -> Result<Masks> {
    let v_all = masks.num_views();
    if views.start > views.end || views.end > v_all {
        return Err(input(
            "--shard",
            format!(
                "views {}..{} are not a range of the masks file's {v_all} views",
                views.start, views.end
            ),
        ));
    }
    let plane = masks.width * masks.height;
    let keep = |v: usize| views.contains(&v);
    let labels = match &masks.labels {
        Labels::U16(b) => Labels::U16(restrict_planes(b, plane, v_all, u16::MAX, keep).into()),
        Labels::U32(b) => Labels::U32(restrict_planes(b, plane, v_all, u32::MAX, keep).into()),
    };
    let mut offsets = vec![0u32];
    for v in 0..v_all {
        let count = if keep(v) { masks.masks_in_view(v) } else { 0 };
        offsets.push(offsets[v] + count as u32);
    }
    let rows = masks.mask_offsets[views.start] as usize..masks.mask_offsets[views.end] as usize;
    let features = feature_rows(&masks.features, masks.dim, rows);
    Ok(Masks {
        labels,
        mask_offsets: offsets.into(),
        features,
        ..masks.clone()
    })
}

/// Marks a masks file as the shard of `views`.
pub fn mark(masks: &mut Masks, views: &Range<usize>) {
    masks.extra.insert(
        SHARD_VIEWS_KEY.to_string(),
        format!("{}..{}", views.start, views.end),
    );
}

/// Stitches shards (`(name, masks)`, any order) that cover every view exactly once into
/// the masks file of one run (the shard key dropped). Shards must agree on everything but
/// their views' masks: view names, grid, label and feature types, dimension, metadata.
pub fn merge(shards: &[(String, Masks)]) -> Result<Masks> {
    let Some((first_name, first)) = shards.first() else {
        return Err(input("prep merge", "no shard files given"));
    };
    let mut ranged = Vec::with_capacity(shards.len());
    for (name, m) in shards {
        check_compatible(first_name, first, name, m)?;
        ranged.push((shard_views(name, m)?, name.as_str(), m));
    }
    ranged.sort_by_key(|(r, _, _)| (r.start, r.end));
    let mut next = 0;
    for (r, name, _) in &ranged {
        if r.start != next {
            let why = if r.start > next {
                format!("views {next}..{} are in no shard", r.start)
            } else {
                format!("views {}..{next} are in two shards", r.start)
            };
            return Err(input(format!("shard {name}"), why));
        }
        next = r.end;
    }
    if next != first.num_views() {
        return Err(input(
            "prep merge",
            format!("views {next}..{} are in no shard", first.num_views()),
        ));
    }
    Ok(stitch(first, &ranged))
}

/// The shards' views, in order, into one file.
fn stitch(first: &Masks, ranged: &[(Range<usize>, &str, &Masks)]) -> Masks {
    let plane = first.width * first.height;
    let mut offsets = vec![0u32];
    let mut u16s: Vec<u16> = Vec::new();
    let mut u32s: Vec<u32> = Vec::new();
    let mut f32s: Vec<f32> = Vec::new();
    let mut f16s = Vec::new();
    for (r, _, m) in ranged {
        for v in r.clone() {
            offsets.push(offsets[v] + m.masks_in_view(v) as u32);
        }
        let cells = r.start * plane..r.end * plane;
        match &m.labels {
            Labels::U16(b) => u16s.extend_from_slice(&b[cells]),
            Labels::U32(b) => u32s.extend_from_slice(&b[cells]),
        }
        let rows = m.mask_offsets[r.start] as usize * m.dim..m.mask_offsets[r.end] as usize * m.dim;
        match &m.features {
            Floats::F32(b) => f32s.extend_from_slice(&b[rows]),
            Floats::F16(b) => f16s.extend_from_slice(&b[rows]),
        }
    }
    let mut extra = first.extra.clone();
    extra.remove(SHARD_VIEWS_KEY);
    Masks {
        labels: match first.labels {
            Labels::U16(_) => Labels::U16(u16s.into()),
            Labels::U32(_) => Labels::U32(u32s.into()),
        },
        mask_offsets: offsets.into(),
        features: match first.features {
            Floats::F32(_) => Floats::F32(f32s.into()),
            Floats::F16(_) => Floats::F16(f16s.into()),
        },
        extra,
        ..first.clone()
    }
}

/// A shard's views from its metadata.
fn shard_views(name: &str, m: &Masks) -> Result<Range<usize>> {
    let bad = || {
        input(
            format!("shard {name}"),
            format!(
                "metadata `{SHARD_VIEWS_KEY}` must be `A..B` with A <= B <= {} (a file written \
                 by `prep masks --shard` or `prep features --shard`)",
                m.num_views()
            ),
        )
    };
    let text = m.extra.get(SHARD_VIEWS_KEY).ok_or_else(bad)?;
    let (a, b) = text.split_once("..").ok_or_else(bad)?;
    let (a, b): (usize, usize) = (a.parse().map_err(|_| bad())?, b.parse().map_err(|_| bad())?);
    if a > b || b > m.num_views() {
        return Err(bad());
    }
    Ok(a..b)
}

/// Shards of one run agree on everything but their views' masks.
fn check_compatible(first_name: &str, first: &Masks, name: &str, m: &Masks) -> Result<()> {
    let meta = |x: &Masks| -> BTreeMap<String, String> {
        let mut e = x.extra.clone();
        e.remove(SHARD_VIEWS_KEY);
        e
    };
    let differs = if m.view_names != first.view_names {
        Some("view names")
    } else if (m.width, m.height) != (first.width, first.height) {
        Some("label-map grid")
    } else if m.labels.dtype() != first.labels.dtype() {
        Some("label type")
    } else if (m.dim, m.features.dtype()) != (first.dim, first.features.dtype()) {
        Some("feature dimension or type")
    } else if meta(m) != meta(first) {
        Some("metadata (generator, parameters or feature kind)")
    } else {
        None
    };
    match differs {
        Some(what) => Err(input(
            format!("shard {name}"),
            format!("its {what} differ from shard {first_name}'s: shards of one run must agree"),
        )),
        None => Ok(()),
    }
}

fn restrict_planes<T: Copy + profuse_formats::Element>(
    labels: &[T],
    plane: usize,
    views: usize,
    none: T,
    keep: impl Fn(usize) -> bool,
) -> Vec<T> {
    let mut out = Vec::with_capacity(views * plane);
    for v in 0..views {
        if keep(v) {
            out.extend_from_slice(&labels[v * plane..(v + 1) * plane]);
        } else {
            out.extend(std::iter::repeat_n(none, plane));
        }
    }
    out
}

fn feature_rows(features: &Floats, dim: usize, rows: Range<usize>) -> Floats {
    let cells = rows.start * dim..rows.end * dim;
    match features {
        Floats::F32(b) => Floats::F32(b[cells].to_vec().into()),
        Floats::F16(b) => Floats::F16(b[cells].to_vec().into()),
    }
}

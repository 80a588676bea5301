//! From W and the masses to the descriptors: proposal descriptors (eq. proposal-desc),
//! A = W F (eq. accumulate, as one sparse-dense product) and f_g = A / max(S, ε),
//! L2-normalised (eq. gaussian-feature).

use std::collections::BTreeMap;
use std::time::Instant;

use half::slice::HalfFloatSliceExt;
use profuse_formats::{f16, Features, Floats};
use rayon::prelude::*;

use crate::accumulate::dequantise;
use crate::groups::{Grouping, NO_GROUP};
use crate::partial::PartialSums;

/// ε of eq. gaussian-feature. The division by max(S, ε) only rescales A, so it never
/// changes a normalised descriptor; it is kept for fidelity to the paper.
pub const EPS: f64 = 1e-12;

/// Storage precision of the written descriptors.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Precision {
    /// F16 (half the size; about 5e-4 relative rounding).
    F16,
    /// F32.
    F32,
}

impl Precision {
    /// `f16` or `f32`.
    pub fn name(self) -> &'static str {
        match self {
            Precision::F16 => "f16",
            Precision::F32 => "f32",
        }
    }

    /// The precision of a float table.
    pub fn of(floats: &Floats) -> Precision {
        match floats {
            Floats::F16(_) => Precision::F16,
            Floats::F32(_) => Precision::F32,
        }
    }
}

/// Statistics of a registration, for reports.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    /// Gaussians N.
    pub gaussians: usize,
    /// Gaussians with a descriptor.
    pub valid: usize,
    /// Nonzero (Gaussian, group) pairs of W.
    pub nnz: usize,
    /// Groups G (proposals, plus singleton orphans; or masks).
    pub groups: usize,
    /// Groups with a nonzero descriptor.
    pub groups_with_descriptor: usize,
    /// Views summed.
    pub views: usize,
    /// Masks M.
    pub masks: usize,
    /// Masks that register into a group.
    pub assigned_masks: usize,
    /// Masks with μ > 0.
    pub masks_with_mass: usize,
    /// Σ μ over all masks.
    pub mass_total: f64,
    /// Smallest, median and largest μ over the masks with μ > 0 (0 when none).
    pub mass_min: f64,
    /// See `mass_min`.
    pub mass_median: f64,
    /// See `mass_min`.
    pub mass_max: f64,
    /// Grouped mask-grid pixels.
    pub pixels: u64,
    /// Their top-K hits.
    pub hits: u64,
    /// Seconds spent in [`finish`].
    pub finish_s: f64,
}

/// The registered descriptors and their statistics.
#[derive(Debug, Clone)]
pub struct Registration {
    /// One descriptor per Gaussian (SPEC.md §4.7), with `weight_sum` = S.
    pub features: Features,
    /// Statistics.
    pub summary: Summary,
}

/// Finishes a registration from (complete or partial) sums: the group descriptors
/// (mass-weighted pools of the member features, or each mask's own feature), then per
/// Gaussian A = Σ_p W\[g,p\] f̄_p and S = Σ_p W\[g,p\] over its row of W in ascending group
/// order, all in f64; f_g = A / max(S, ε), normalised (with a single group that is the
/// group's descriptor, which is copied). A Gaussian with S = 0 (or a zero
/// A, possible only when member features cancel exactly) is invalid: zero row, valid 0,
/// weight_sum 0. Rows are independent, so the bytes do not depend on the thread count.
pub fn finish(p: &PartialSums, precision: Precision) -> Registration {
    let t0 = Instant::now();
    let d = p.dim;
    let desc = group_descriptors(p);
    let n = p.num_gaussians;
    let mut valid = vec![0u8; n];
    let mut weight_sum = vec![0f32; n];
    const ROWS: usize = 1024;
    let features = match precision {
        Precision::F32 => {
            let mut out = vec![0f32; n * d];
            fill_rows(
                p,
                &desc,
                &mut out,
                &mut valid,
                &mut weight_sum,
                ROWS,
                |src, dst, _| {
                    for (o, x) in dst.iter_mut().zip(src) {
                        *o = *x as f32;
                    }
                },
            );
            Floats::F32(out.into())
        }
        Precision::F16 => {
            // Zeroed pages from the allocator: invalid rows need no write.
            let mut out: Vec<f16> = bytemuck::zeroed_vec(n * d);
            fill_rows(
                p,
                &desc,
                &mut out,
                &mut valid,
                &mut weight_sum,
                ROWS,
                |src, dst, tmp| {
                    tmp.clear();
                    tmp.extend(src.iter().map(|x| *x as f32));
                    // Vectorised (F16C where the CPU has it).
                    dst.convert_from_f32_slice(tmp);
                },
            );
            Floats::F16(out.into())
        }
    };
    let summary = summarise(p, &desc, &valid, t0);
    let extra = BTreeMap::from([
        (
            "generator".to_string(),
            format!("profuse-fuse {}", env!("CARGO_PKG_VERSION")),
        ),
        ("k".to_string(), p.k.to_string()),
        ("grouping".to_string(), p.groups.grouping.name().to_string()),
        (
            "orphans".to_string(),
            p.groups.grouping.orphans_name().to_string(),
        ),
        ("views".to_string(), p.views.len().to_string()),
    ]);
    Registration {
        features: Features {
            features,
            dim: d,
            valid: valid.into(),
            weight_sum: Some(weight_sum.into()),
            extra,
        },
        summary,
    }
}

/// Computes rows `chunk` at a time in parallel; `store` writes one normalised f64 row
/// (with a scratch buffer).
fn fill_rows<T: Copy + Send>(
    p: &PartialSums,
    desc: &[f64],
    out: &mut [T],
    valid: &mut [u8],
    weight_sum: &mut [f32],
    chunk: usize,
    store: impl Fn(&[f64], &mut [T], &mut Vec<f32>) + Sync,
) {
    let d = p.dim;
    out.par_chunks_mut(chunk * d)
        .zip(valid.par_chunks_mut(chunk))
        .zip(weight_sum.par_chunks_mut(chunk))
        .enumerate()
        .for_each(|(c, ((rows, valid), sums))| {
            let mut a = vec![0f64; d];
            let mut tmp = Vec::with_capacity(d);
            for (i, ((row, v), slot)) in rows
                .chunks_exact_mut(d)
                .zip(valid.iter_mut())
                .zip(sums.iter_mut())
                .enumerate()
            {
                let (groups, qs) = p.weights.row(c * chunk + i);
                if let Some(s) = descriptor(desc, d, groups, qs, &mut a) {
                    store(&a, row, &mut tmp);
                    *v = 1;
                    *slot = s;
                }
            }
        });
}

/// f_g of one Gaussian into `a` (normalised, f64) and S as f32; `None` when invalid.
fn descriptor(desc: &[f64], d: usize, groups: &[u32], qs: &[u128], a: &mut [f64]) -> Option<f32> {
    if let ([group], [q]) = (groups, qs) {
        // One proposal: f_g is its descriptor (A / S = f̄).
        let f = &desc[*group as usize * d..][..d];
        a.copy_from_slice(f);
        return f.iter().any(|x| *x != 0.0).then(|| dequantise(*q) as f32);
    }
    a.fill(0.0);
    let mut total = 0u128;
    for (group, q) in groups.iter().zip(qs) {
        total += *q;
        let w = dequantise(*q);
        let f = &desc[*group as usize * d..][..d];
        for (ai, fi) in a.iter_mut().zip(f) {
            *ai += w * fi;
        }
    }
    let s = dequantise(total);
    let scale = 1.0 / s.max(EPS);
    let norm = a
        .iter()
        .map(|x| (x * scale) * (x * scale))
        .sum::<f64>()
        .sqrt();
    if !(norm > 0.0 && norm.is_finite()) || (s as f32) <= 0.0 {
        return None;
    }
    a.iter_mut().for_each(|x| *x = *x * scale / norm);
    Some(s as f32)
}

/// Descriptor of every group, [G, D] in f64: the L2-normalised mass-weighted sum of its
/// members' features (members in global mask order), or each mask's own normalised
/// feature for [`Grouping::Masks`]. A group whose sum is zero gets a zero descriptor
/// (it then has no W entries either, unless its members' features cancel exactly).
pub fn group_descriptors(p: &PartialSums) -> Vec<f64> {
    let d = p.dim;
    let mut desc = vec![0f64; p.groups.num_groups * d];
    let mut f = vec![0f32; d];
    for (m, group) in p.groups.mask_group.iter().enumerate() {
        if *group == NO_GROUP {
            continue;
        }
        let weight = match p.groups.grouping {
            Grouping::Proposals { .. } => dequantise(p.mask_mass[m]),
            Grouping::Masks => 1.0,
        };
        if weight == 0.0 {
            continue;
        }
        p.mask_features.read_into(m * d, &mut f);
        let row = &mut desc[*group as usize * d..][..d];
        for (r, x) in row.iter_mut().zip(&f) {
            *r += weight * f64::from(*x);
        }
    }
    for row in desc.chunks_exact_mut(d) {
        let norm = row.iter().map(|x| x * x).sum::<f64>().sqrt();
        if norm > 0.0 {
            row.iter_mut().for_each(|x| *x /= norm);
        }
    }
    desc
}

/// The descriptor each global mask's pixels register (eq. accumulate adds ω f̄_{L(p)} for
/// every pixel p of the mask): `desc[group(m)]` of [`group_descriptors`], as f32. With
/// proposals that is the mask's proposal's mass-weighted pool, with [`Grouping::Masks`]
/// (the `--no-proposals` baseline) the mask's own normalised feature. `None` for a mask
/// that registers nothing: no group ([`NO_GROUP`], an ignored orphan), or a group whose
/// descriptor is zero (no member with mass).
pub fn registered_mask_descriptors(p: &PartialSums) -> Vec<Option<Vec<f32>>> {
    let d = p.dim;
    let desc = group_descriptors(p);
    p.groups
        .mask_group
        .iter()
        .map(|group| {
            if *group == NO_GROUP {
                return None;
            }
            let row = desc.get(*group as usize * d..(*group as usize + 1) * d)?;
            row.iter()
                .any(|x| *x != 0.0)
                .then(|| row.iter().map(|x| *x as f32).collect())
        })
        .collect()
}

fn summarise(p: &PartialSums, desc: &[f64], valid: &[u8], t0: Instant) -> Summary {
    let mut masses: Vec<f64> = p
        .mask_mass
        .iter()
        .filter(|q| **q > 0)
        .map(|q| dequantise(*q))
        .collect();
    masses.sort_by(f64::total_cmp);
    let total: u128 = p.mask_mass.iter().sum();
    Summary {
        gaussians: p.num_gaussians,
        valid: valid.iter().filter(|v| **v == 1).count(),
        nnz: p.weights.nnz(),
        groups: p.groups.num_groups,
        groups_with_descriptor: desc
            .chunks_exact(p.dim)
            .filter(|r| r.iter().any(|x| *x != 0.0))
            .count(),
        views: p.views.len(),
        masks: p.num_masks(),
        assigned_masks: p.groups.assigned_masks(),
        masks_with_mass: masses.len(),
        mass_total: dequantise(total),
        mass_min: masses.first().copied().unwrap_or(0.0),
        mass_median: masses.get(masses.len() / 2).copied().unwrap_or(0.0),
        mass_max: masses.last().copied().unwrap_or(0.0),
        pixels: p.counts.pixels,
        hits: p.counts.hits,
        finish_s: t0.elapsed().as_secs_f64(),
    }
}

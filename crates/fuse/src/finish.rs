//! From W and the masses to the descriptors: proposal descriptors (eq. proposal-desc), or
//! for [`Grouping::Blend`] per-mask blends of them with the masks' own features,
//! A = W F (eq. accumulate, as one sparse-dense product) and f_g = A / max(S, ε),
//! L2-normalised (eq. gaussian-feature).

use std::collections::BTreeMap;
use std::time::Instant;

use half::slice::HalfFloatSliceExt;
use profuse_formats::{f16, Features, Floats};
use rayon::prelude::*;

use crate::accumulate::dequantise;
use crate::groups::{Grouping, MemberWeight, NO_GROUP};
use crate::partial::PartialSums;
use profuse_formats::NO_PROPOSAL;

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
    let desc = descriptor_table(p);
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
    Registration {
        features: Features {
            features,
            dim: d,
            valid: valid.into(),
            weight_sum: Some(weight_sum.into()),
            extra: run_metadata(p),
        },
        summary,
    }
}

/// Computes rows `chunk` at a time in parallel; `store` writes one normalised f64 row
/// (with a scratch buffer).
fn fill_rows<T: Copy + Send>(
    p: &PartialSums,
    desc: &Table,
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
            let mut columns = Columns::default();
            for (i, ((row, v), slot)) in rows
                .chunks_exact_mut(d)
                .zip(valid.iter_mut())
                .zip(sums.iter_mut())
                .enumerate()
            {
                let (groups, qs) = p.weights.row(c * chunk + i);
                let (groups, qs) = match &desc.column {
                    None => (groups, qs),
                    Some(column) => columns.gather(column, groups, qs),
                };
                if let Some(s) = descriptor(&desc.rows, d, groups, qs, &mut a) {
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

/// A row of W mapped to the descriptor table's rows, with the entries of groups that share
/// a row added up (exactly, in fixed point), in ascending row order.
#[derive(Default)]
pub(crate) struct Columns {
    pairs: Vec<(u32, u128)>,
    rows: Vec<u32>,
    sums: Vec<u128>,
}

impl Columns {
    pub(crate) fn gather(
        &mut self,
        column: &[u32],
        groups: &[u32],
        qs: &[u128],
    ) -> (&[u32], &[u128]) {
        self.pairs.clear();
        self.pairs.extend(
            groups
                .iter()
                .zip(qs)
                .map(|(g, q)| (column[*g as usize], *q)),
        );
        self.pairs.sort_unstable_by_key(|(row, _)| *row);
        self.rows.clear();
        self.sums.clear();
        for (row, q) in &self.pairs {
            if self.rows.last() == Some(row) {
                if let Some(s) = self.sums.last_mut() {
                    *s += *q;
                }
            } else {
                self.rows.push(*row);
                self.sums.push(*q);
            }
        }
        (&self.rows, &self.sums)
    }
}

/// The descriptors W is multiplied with: `rows` [R, D] in f64 and the row of every group
/// (`None`: group g is row g).
pub(crate) struct Table {
    pub(crate) rows: Vec<f64>,
    pub(crate) column: Option<Vec<u32>>,
}

impl Table {
    /// The descriptor of group `g` (all zero when it has none).
    fn group_row(&self, g: usize, d: usize) -> &[f64] {
        let r = self.column.as_ref().map_or(g, |c| c[g] as usize);
        &self.rows[r * d..][..d]
    }
}

/// Above this blend weight α a mask registers its proposal's descriptor itself. α is a
/// ratio of two f64 cosines that are equal in exact arithmetic when every member agrees
/// equally with its proposal; their rounding (~1e-16) must not turn the paper's
/// descriptor into a private copy that differs in the last bits (and costs a row of its
/// own). A weight this close to 1 moves a descriptor by < 1e-9, far below F32 rounding.
const FULL_BLEND: f64 = 1.0 - 1e-9;

pub(crate) fn descriptor_table(p: &PartialSums) -> Table {
    match p.groups.grouping {
        Grouping::Proposals { .. } | Grouping::Masks => Table {
            rows: pooled_groups(p),
            column: None,
        },
        Grouping::Blend { .. } => blend_table(p),
    }
}

/// Descriptor of every group, [G, D] in f64: the L2-normalised mass-weighted sum of its
/// members' features (members in global mask order), or each mask's own normalised
/// feature for [`Grouping::Masks`], or each mask's blend d_m for [`Grouping::Blend`]
/// (zero for ignored orphans). A group whose sum is zero gets a zero descriptor
/// (it then has no W entries either, unless its members' features cancel exactly).
pub fn group_descriptors(p: &PartialSums) -> Vec<f64> {
    match p.groups.grouping {
        Grouping::Proposals { .. } | Grouping::Masks => pooled_groups(p),
        Grouping::Blend { .. } => {
            let table = blend_table(p);
            (0..p.groups.num_groups)
                .flat_map(|g| table.group_row(g, p.dim).iter().copied())
                .collect()
        }
    }
}

/// Per global mask, the descriptor its pixels register (its group's: the proposal's
/// f̄_P, its own normalised feature, or its blend d_m), in f32; `None` when it registers
/// nothing (no group, e.g. an ignored orphan, or an all-zero descriptor).
pub fn registered_mask_descriptors(p: &PartialSums) -> Vec<Option<Vec<f32>>> {
    let d = p.dim;
    let table = descriptor_table(p);
    p.groups
        .mask_group
        .iter()
        .map(|g| {
            if *g == NO_GROUP {
                return None;
            }
            let row = table.group_row(*g as usize, d);
            row.iter()
                .any(|x| *x != 0.0)
                .then(|| row.iter().map(|x| *x as f32).collect())
        })
        .collect()
}

/// [G, D]: per group the normalised sum of `weight(m) f_m` over its members in global
/// mask order (μ for proposals, 1 for the per-mask baseline).
fn pooled_groups(p: &PartialSums) -> Vec<f64> {
    let weight = |m: usize| match p.groups.grouping {
        Grouping::Masks => 1.0,
        Grouping::Proposals { .. } | Grouping::Blend { .. } => member_mass(p, m),
    };
    let of = |m: usize| {
        let g = p.groups.mask_group[m];
        (g != NO_GROUP).then_some(g as usize)
    };
    pool(p, p.groups.num_groups, of, weight)
}

/// What mask m weighs in its proposal's descriptor: μ_m, times s_m when the groups keep
/// shares ([`crate::MemberWeight::Share`]).
fn member_mass(p: &PartialSums, m: usize) -> f64 {
    dequantise(p.mask_mass[m]) * p.groups.share(m)
}

/// [R, D]: row r is the normalised sum of `weight(m) f_m` over the masks with
/// `row_of(m) = r`, in global mask order (one routine, so the blend's f̄_P has the same
/// bits as the paper's).
fn pool(
    p: &PartialSums,
    rows: usize,
    row_of: impl Fn(usize) -> Option<usize>,
    weight: impl Fn(usize) -> f64,
) -> Vec<f64> {
    let d = p.dim;
    let mut desc = vec![0f64; rows * d];
    let mut f = vec![0f32; d];
    for m in 0..p.num_masks() {
        let Some(r) = row_of(m) else { continue };
        let w = weight(m);
        if w == 0.0 {
            continue;
        }
        p.mask_features.read_into(m * d, &mut f);
        let row = &mut desc[r * d..][..d];
        for (a, x) in row.iter_mut().zip(&f) {
            *a += w * f64::from(*x);
        }
    }
    for row in desc.chunks_exact_mut(d) {
        normalise(row);
    }
    desc
}

fn normalise(row: &mut [f64]) {
    let norm = row.iter().map(|x| x * x).sum::<f64>().sqrt();
    if norm > 0.0 {
        row.iter_mut().for_each(|x| *x /= norm);
    }
}

/// The blend of [`Grouping::Blend`] as a table: rows `0..P'` are the paper's f̄ of the P'
/// proposals that have members (ascending proposal id, so a Gaussian's row is summed in
/// the paper's order), then one row per mask. A mask with α = 1 (and the threshold
/// [`FULL_BLEND`]) maps to its proposal's row, so where every mask is that coherent W
/// collapses to the paper's W[g, P] = Σ_{m∈P} W[g, m] (exact integers) and the result
/// has the paper's bytes; any other mask maps to its own row, d_m.
fn blend_table(p: &PartialSums) -> Table {
    let d = p.dim;
    let m_count = p.num_masks();
    let proposal_of = &p.groups.mask_proposal;
    let mut ids: Vec<u32> = proposal_of
        .iter()
        .copied()
        .filter(|id| *id != NO_PROPOSAL)
        .collect();
    ids.sort_unstable();
    ids.dedup();
    // Dense ranks of the proposal ids: memory follows the masks, whatever the ids.
    let rank = |m: usize| -> Option<usize> {
        let id = *proposal_of.get(m)?;
        if id == NO_PROPOSAL {
            return None;
        }
        ids.binary_search(&id).ok()
    };
    let mass = |m: usize| member_mass(p, m);
    let num_proposals = ids.len();
    let bar = pool(p, num_proposals, rank, mass);

    // a_m = cos(f_m, f̄_P) (f̄_P is unit or zero) and f̂_m per mask, c_P per proposal.
    let mut own = vec![0f64; m_count * d];
    let mut agreement = vec![0f64; m_count];
    let mut f = vec![0f32; d];
    for m in 0..m_count {
        p.mask_features.read_into(m * d, &mut f);
        let row = &mut own[m * d..][..d];
        for (o, x) in row.iter_mut().zip(&f) {
            *o = f64::from(*x);
        }
        normalise(row);
        if let Some(r) = rank(m) {
            let fbar = &bar[r * d..][..d];
            agreement[m] = row.iter().zip(fbar).map(|(a, b)| a * b).sum::<f64>();
        }
    }
    let mut num = vec![0f64; num_proposals];
    let mut den = vec![0f64; num_proposals];
    for (m, a) in agreement.iter().enumerate() {
        if let Some(r) = rank(m) {
            num[r] += mass(m) * a;
            den[r] += mass(m);
        }
    }

    let mut rows = bar;
    rows.resize((num_proposals + m_count) * d, 0.0);
    let mut column = vec![0u32; m_count];
    for (m, slot) in column.iter_mut().enumerate() {
        let own_row = num_proposals + m;
        *slot = own_row as u32;
        if p.groups.mask_group[m] == NO_GROUP {
            continue;
        }
        let alpha = match rank(m) {
            Some(r) if den[r] > 0.0 && num[r] > 0.0 => {
                let c = num[r] / den[r];
                (agreement[m] / c).clamp(0.0, 1.0)
            }
            // c_P <= 0, no mass, or an orphan of `Orphans::Singleton`: its own feature.
            _ => 0.0,
        };
        let (head, tail) = rows.split_at_mut(num_proposals * d);
        let target = &mut tail[m * d..][..d];
        let f_hat = &own[m * d..][..d];
        match rank(m) {
            Some(r) if alpha >= FULL_BLEND => *slot = r as u32,
            Some(r) if alpha > 0.0 => {
                let fbar = &head[r * d..][..d];
                for ((t, b), o) in target.iter_mut().zip(fbar).zip(f_hat) {
                    *t = alpha * b + (1.0 - alpha) * o;
                }
                normalise(target);
            }
            _ => target.copy_from_slice(f_hat),
        }
    }
    Table {
        rows,
        column: Some(column),
    }
}

/// The metadata of a registration's outputs (features and semantic index): generator,
/// k, grouping, orphans, views, and `member_weight = share` when members were weighed by
/// their shares.
pub(crate) fn run_metadata(p: &PartialSums) -> BTreeMap<String, String> {
    let mut meta = BTreeMap::from([
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
    if p.groups.member_weight() == MemberWeight::Share {
        meta.insert(
            "member_weight".to_string(),
            MemberWeight::Share.name().into(),
        );
    }
    if p.groups.pixel_share_power > 0.0 {
        meta.insert(
            crate::partial::PIXEL_SHARE_POWER_KEY.to_string(),
            p.groups.pixel_share_power.to_string(),
        );
    }
    meta
}

fn summarise(p: &PartialSums, desc: &Table, valid: &[u8], t0: Instant) -> Summary {
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
        groups_with_descriptor: (0..p.groups.num_groups)
            .filter(|g| desc.group_row(*g, p.dim).iter().any(|x| *x != 0.0))
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

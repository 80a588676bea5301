//! One directed warp (a pair row (i, j) of the matches file) in one pass over its grid:
//! the gate, the warped labels of view j, and the sparse contingency table of
//! (label in i, label from j) from which every mask-pair IoU and box IoU of the pair follows.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use serde::Serialize;

use crate::frame::{Axis, NONE};
use crate::params::Sampling;
use crate::visibility::CellVisibility;

/// An axis-aligned box of grid cells, bounds inclusive; empty when `x0 > x1`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CellBox {
    /// Smallest column.
    pub x0: u32,
    /// Smallest row.
    pub y0: u32,
    /// Largest column.
    pub x1: u32,
    /// Largest row.
    pub y1: u32,
}

impl CellBox {
    /// The box that contains nothing.
    pub const EMPTY: CellBox = CellBox {
        x0: u32::MAX,
        y0: u32::MAX,
        x1: 0,
        y1: 0,
    };

    /// Whether the box contains no cell.
    pub fn is_empty(&self) -> bool {
        self.x0 > self.x1 || self.y0 > self.y1
    }

    /// Grows the box to contain cell (x, y).
    #[inline]
    pub fn add(&mut self, x: u32, y: u32) {
        self.x0 = self.x0.min(x);
        self.y0 = self.y0.min(y);
        self.x1 = self.x1.max(x);
        self.y1 = self.y1.max(y);
    }

    /// Number of cells in the box.
    pub fn area(&self) -> u64 {
        if self.is_empty() {
            0
        } else {
            u64::from(self.x1 - self.x0 + 1) * u64::from(self.y1 - self.y0 + 1)
        }
    }

    /// IoU of the two cell sets the boxes cover; 0 when either is empty.
    pub fn iou(&self, other: &CellBox) -> f64 {
        let inter = CellBox {
            x0: self.x0.max(other.x0),
            y0: self.y0.max(other.y0),
            x1: self.x1.min(other.x1),
            y1: self.y1.min(other.y1),
        };
        let i = inter.area();
        if i == 0 {
            return 0.0;
        }
        i as f64 / (self.area() + other.area() - i) as f64
    }
}

/// What the gate did with the cells of one or more directed warps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
pub struct CellCounts {
    /// Grid cells looked at.
    pub total: u64,
    /// Cells with certainty below τ_α.
    pub low_certainty: u64,
    /// Cells certain enough but rejected by vis_mask.
    pub occluded: u64,
    /// Cells inside the gate Γ.
    pub gated: u64,
}

impl CellCounts {
    /// Adds another count.
    pub fn add(&mut self, o: &CellCounts) {
        self.total += o.total;
        self.low_certainty += o.low_certainty;
        self.occluded += o.occluded;
        self.gated += o.gated;
    }
}

/// One non-zero entry of the contingency table: the gated warped weight of mask `dst` of
/// view j that lands on gated cells labelled `src` in view i (view-local indices).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Overlap {
    /// Local mask index in the source view i.
    pub src: u32,
    /// Local mask index in the target view j.
    pub dst: u32,
    /// |M_i^src ⊙ Γ ∩ M̃_j^dst ⊙ Γ|, in cells (fractional with bilinear sampling).
    pub weight: f64,
}

/// Everything Algorithm 1 needs from one directed warp of pair (i, j), all measured on
/// view i's warp grid over the gated cells Γ = [certainty >= τ_α] ∧ vis_mask:
///
/// * `src_area[a]` = |M_i^a ⊙ Γ|: gated cells whose centre lies in mask a of view i;
/// * `dst_area[b]` = |M̃_j^b ⊙ Γ|: the summed sampling weight of mask b of view j over
///   the gated cells (each cell's weights sum to at most 1);
/// * `intersections` (a, b) = Σ over gated cells labelled a of the weight of b: the fuzzy
///   intersection Σ min(M_i^a, M̃_j^b), since M_i^a is 0 or 1 per cell;
/// * IoU(a, b) = I / (`src_area[a]` + `dst_area[b]` − I) (the fuzzy union Σ max);
/// * `src_box[a]` = bounding box of a's gated cells; `dst_box[b]` = bounding box of the
///   gated cells where b's weight is > 0 (the support of the warped mask);
///   box IoU = IoU of the two boxes as cell sets.
#[derive(Debug, Clone, PartialEq)]
pub struct DirectedOverlaps {
    /// View i (the grid the warp is laid over).
    pub src_view: usize,
    /// View j (where the warp points).
    pub dst_view: usize,
    /// Per local mask of view i: gated cells.
    pub src_area: Vec<f64>,
    /// Per local mask of view i: box of its gated cells.
    pub src_box: Vec<CellBox>,
    /// Per local mask of view j: gated warped weight.
    pub dst_area: Vec<f64>,
    /// Per local mask of view j: box of the gated cells it reaches.
    pub dst_box: Vec<CellBox>,
    /// Non-zero intersections, sorted by (src, dst).
    pub intersections: Vec<Overlap>,
    /// What the gate did.
    pub cells: CellCounts,
}

impl DirectedOverlaps {
    /// Intersection weight of local masks (a in i, b in j); 0 when they do not overlap.
    pub fn intersection(&self, a: u32, b: u32) -> f64 {
        self.intersections
            .binary_search_by(|o| (o.src, o.dst).cmp(&(a, b)))
            .map_or(0.0, |k| self.intersections[k].weight)
    }

    /// Gated IoU of M_i^a and the warped M_j^b (paper eq. overlap).
    pub fn iou(&self, a: u32, b: u32) -> f64 {
        let i = self.intersection(a, b);
        if i <= 0.0 {
            return 0.0;
        }
        let union = self.src_area[a as usize] + self.dst_area[b as usize] - i;
        if union > 0.0 {
            (i / union).min(1.0)
        } else {
            0.0
        }
    }

    /// IoU of the boxes of M_i^a's gated cells and of the warped M_j^b's gated support.
    pub fn box_iou(&self, a: u32, b: u32) -> f64 {
        match (self.src_box.get(a as usize), self.dst_box.get(b as usize)) {
            (Some(p), Some(q)) => p.iou(q),
            _ => 0.0,
        }
    }
}

/// Inputs of one directed pass, already converted to plain slices.
pub(crate) struct DirectedInput<'p> {
    pub(crate) src_view: usize,
    pub(crate) dst_view: usize,
    /// Label plane of view i on the mask grid.
    pub(crate) src_labels: &'p [u32],
    /// Label plane of view j on the mask grid.
    pub(crate) dst_labels: &'p [u32],
    pub(crate) src_masks: usize,
    pub(crate) dst_masks: usize,
    /// Warp values (x, y) per grid cell.
    pub(crate) warp: &'p [f32],
    pub(crate) certainty: &'p [f32],
    /// Warp value -> continuous mask coordinates of view j.
    pub(crate) to_dst_mask: [Axis; 2],
}

/// Grid and mask geometry shared by all passes.
pub(crate) struct Grids<'f> {
    pub(crate) gw: usize,
    pub(crate) gh: usize,
    pub(crate) mw: usize,
    pub(crate) mh: usize,
    pub(crate) xmap: &'f [usize],
    pub(crate) ymap: &'f [usize],
}

/// Up to four (label, weight) samples of view j at one position, labels distinct.
#[derive(Clone, Copy)]
struct Samples {
    len: usize,
    items: [(u32, f64); 4],
}

impl Samples {
    const EMPTY: Samples = Samples {
        len: 0,
        items: [(NONE, 0.0); 4],
    };

    #[inline]
    fn push(&mut self, label: u32, w: f64) {
        if label == NONE || w <= 0.0 {
            return;
        }
        for item in &mut self.items[..self.len] {
            if item.0 == label {
                item.1 += w;
                return;
            }
        }
        self.items[self.len] = (label, w);
        self.len += 1;
    }

    fn as_slice(&self) -> &[(u32, f64)] {
        &self.items[..self.len]
    }
}

/// Bilinear fractions within this distance (in mask pixels) of 0 or 1 are snapped: a
/// target on a pixel centre, written as f32 normalised coordinates, comes back up to
/// ~1e-4 px off, and must not leak a 1e-7 weight (and a box cell) to the neighbours.
pub(crate) const SNAP: f64 = 1e-4;

/// `floor` for the finite, moderate values of grid coordinates, without the libm call
/// that `f64::floor` becomes on x86-64 without SSE4.1.
#[inline]
pub(crate) fn fast_floor(v: f64) -> f64 {
    let t = v as i64 as f64;
    if t > v {
        t - 1.0
    } else {
        t
    }
}

#[inline]
fn snap(f: f64) -> f64 {
    if f < SNAP {
        0.0
    } else if f > 1.0 - SNAP {
        1.0
    } else {
        f
    }
}

/// Samples view j's labels at continuous mask coordinates (mx, my) (corner origin, pixel
/// centres at +0.5). Outside the image [0, W] x [0, H] there is nothing. Bilinear: the
/// four pixels whose centres surround the position, indices clamped at the border (so
/// every position inside the image distributes a total weight of 1, "no mask" included),
/// fractions snapped to 0 or 1 within [`SNAP`].
/// The samples are written into `s` (cleared first) rather than returned: a returned
/// 72-byte struct per cell was the hottest instruction of the pass.
#[inline]
fn sample_labels(
    s: &mut Samples,
    labels: &[u32],
    mw: usize,
    mh: usize,
    mx: f64,
    my: f64,
    sampling: Sampling,
) {
    s.len = 0;
    let (wf, hf) = (mw as f64, mh as f64);
    if mw == 0 || mh == 0 {
        return;
    }
    // Written so that NaN fails every comparison and lands outside.
    if !(mx >= 0.0 && mx <= wf && my >= 0.0 && my <= hf) {
        return;
    }
    match sampling {
        Sampling::Nearest => {
            let px = (mx as usize).min(mw - 1);
            let py = (my as usize).min(mh - 1);
            s.push(labels[py * mw + px], 1.0);
        }
        Sampling::Bilinear => {
            let (sx, sy) = (mx - 0.5, my - 0.5);
            let (fx0, fy0) = (fast_floor(sx), fast_floor(sy));
            let (fx, fy) = (snap(sx - fx0), snap(sy - fy0));
            let clamp_x = |v: f64| (v.max(0.0) as usize).min(mw - 1);
            let clamp_y = |v: f64| (v.max(0.0) as usize).min(mh - 1);
            let (xa, xb) = (clamp_x(fx0), clamp_x(fx0 + 1.0));
            let (ya, yb) = (clamp_y(fy0), clamp_y(fy0 + 1.0));
            let (l00, l10) = (labels[ya * mw + xa], labels[ya * mw + xb]);
            let (l01, l11) = (labels[yb * mw + xa], labels[yb * mw + xb]);
            if l00 == l10 && l00 == l01 && l00 == l11 {
                // Inside a mask (the common case) the four weights sum to 1.
                s.push(l00, 1.0);
            } else {
                s.push(l00, (1.0 - fx) * (1.0 - fy));
                s.push(l10, fx * (1.0 - fy));
                s.push(l01, (1.0 - fx) * fy);
                s.push(l11, fx * fy);
            }
        }
    }
}

/// A multiplicative hasher for the (a, b) keys of the contingency table: the keys are
/// small dense integers, so SipHash's DoS resistance buys nothing and costs most of the
/// table's time.
#[derive(Default)]
struct KeyHasher(u64);

impl Hasher for KeyHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for b in bytes {
            self.write_u64(u64::from(*b));
        }
    }

    #[inline]
    fn write_u64(&mut self, n: u64) {
        self.0 = (self.0.rotate_left(5) ^ n).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }
}

type Table = HashMap<u64, f64, BuildHasherDefault<KeyHasher>>;

/// Views with at most this many (src mask, dst mask) combinations keep the contingency
/// table as a dense matrix (512 KiB at most): the same sparse result, without hashing.
const DENSE_LIMIT: usize = 1 << 16;

/// The contingency table of (label in i, label from j) -> summed weight.
enum Contingency {
    /// Row-major [src][dst] weights.
    Dense { dst_masks: usize, weights: Vec<f64> },
    /// Keyed by `src << 32 | dst`.
    Sparse(Table),
}

impl Contingency {
    fn new(src_masks: usize, dst_masks: usize) -> Self {
        match src_masks.checked_mul(dst_masks) {
            Some(n) if n <= DENSE_LIMIT => Contingency::Dense {
                dst_masks,
                weights: vec![0.0; n],
            },
            _ => Contingency::Sparse(Table::default()),
        }
    }

    #[inline]
    fn add(&mut self, a: u32, b: u32, w: f64) {
        match self {
            Contingency::Dense { dst_masks, weights } => {
                weights[a as usize * *dst_masks + b as usize] += w;
            }
            Contingency::Sparse(t) => {
                *t.entry(u64::from(a) << 32 | u64::from(b)).or_insert(0.0) += w;
            }
        }
    }

    /// The non-zero entries sorted by (src, dst).
    fn into_sorted(self) -> Vec<Overlap> {
        let mut out: Vec<Overlap> = match self {
            Contingency::Dense { dst_masks, weights } => weights
                .iter()
                .enumerate()
                .filter(|(_, w)| **w > 0.0)
                .map(|(k, &weight)| Overlap {
                    src: (k / dst_masks) as u32,
                    dst: (k % dst_masks) as u32,
                    weight,
                })
                .collect(),
            Contingency::Sparse(t) => t
                .into_iter()
                .map(|(k, weight)| Overlap {
                    src: (k >> 32) as u32,
                    dst: k as u32,
                    weight,
                })
                .collect(),
        };
        out.sort_unstable_by_key(|o| (o.src, o.dst));
        out
    }
}

/// The one pass over the grid of a directed warp.
pub(crate) fn directed_pass(
    grids: &Grids<'_>,
    input: &DirectedInput<'_>,
    tau_alpha: f32,
    sampling: Sampling,
    vis: &CellVisibility<'_>,
) -> DirectedOverlaps {
    let (gw, gh, mw, mh) = (grids.gw, grids.gh, grids.mw, grids.mh);
    let mut src_area = vec![0.0f64; input.src_masks];
    let mut src_box = vec![CellBox::EMPTY; input.src_masks];
    let mut dst_area = vec![0.0f64; input.dst_masks];
    let mut dst_box = vec![CellBox::EMPTY; input.dst_masks];
    let mut table = Contingency::new(input.src_masks, input.dst_masks);
    let mut cells = CellCounts::default();
    let [ax, ay] = input.to_dst_mask;
    let mut samples = Samples::EMPTY;
    for y in 0..gh {
        let src_row = &input.src_labels[grids.ymap[y] * mw..(grids.ymap[y] + 1) * mw];
        for x in 0..gw {
            let c = y * gw + x;
            cells.total += 1;
            // Spelled so that a NaN certainty (possible only in unvalidated in-memory
            // inputs) is not certain.
            let certain = input.certainty[c] >= tau_alpha;
            if !certain {
                cells.low_certainty += 1;
                continue;
            }
            let (wx, wy) = (
                f64::from(input.warp[2 * c]),
                f64::from(input.warp[2 * c + 1]),
            );
            if !vis.visible(x, y, c, wx, wy) {
                cells.occluded += 1;
                continue;
            }
            cells.gated += 1;
            let (xc, yc) = (x as u32, y as u32);
            let a = src_row[grids.xmap[x]];
            if a != NONE {
                src_area[a as usize] += 1.0;
                src_box[a as usize].add(xc, yc);
            }
            sample_labels(
                &mut samples,
                input.dst_labels,
                mw,
                mh,
                ax.apply(wx),
                ay.apply(wy),
                sampling,
            );
            for &(b, w) in samples.as_slice() {
                dst_area[b as usize] += w;
                dst_box[b as usize].add(xc, yc);
                if a != NONE {
                    table.add(a, b, w);
                }
            }
        }
    }
    let intersections = table.into_sorted();
    DirectedOverlaps {
        src_view: input.src_view,
        dst_view: input.dst_view,
        src_area,
        src_box,
        dst_area,
        dst_box,
        intersections,
        cells,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample_labels(
        labels: &[u32],
        mw: usize,
        mh: usize,
        mx: f64,
        my: f64,
        m: Sampling,
    ) -> Samples {
        let mut s = Samples::EMPTY;
        super::sample_labels(&mut s, labels, mw, mh, mx, my, m);
        s
    }

    #[test]
    fn bilinear_weights_split_between_the_pixels_whose_centres_surround_the_position() {
        // 2x1 labels [7, 9]: position x = 0.75 is a quarter of the way from centre 0.5 to 1.5.
        let s = sample_labels(&[7, 9], 2, 1, 0.75, 0.5, Sampling::Bilinear);
        assert_eq!(s.as_slice(), &[(7, 0.75), (9, 0.25)]);
        let s = sample_labels(&[7, 9], 2, 1, 0.75, 0.5, Sampling::Nearest);
        assert_eq!(s.as_slice(), &[(7, 1.0)]);
        // Border: clamped, the whole weight stays with the edge pixel.
        let s = sample_labels(&[7, 9], 2, 1, 0.1, 0.0, Sampling::Bilinear);
        assert_eq!(s.as_slice(), &[(7, 1.0)]);
        // Outside, or NaN: nothing.
        assert_eq!(
            sample_labels(&[7, 9], 2, 1, 2.01, 0.5, Sampling::Bilinear).len,
            0
        );
        assert_eq!(
            sample_labels(&[7, 9], 2, 1, f64::NAN, 0.5, Sampling::Nearest).len,
            0
        );
        // "No mask" takes weight but records nothing.
        let s = sample_labels(&[NONE, 9], 2, 1, 1.25, 0.5, Sampling::Bilinear);
        assert_eq!(s.as_slice(), &[(9, 0.75)]);
    }

    #[test]
    fn fast_floor_is_floor() {
        for v in [
            -2.5,
            -1.0,
            -0.5,
            -1e-9,
            0.0,
            1e-9,
            0.5,
            1.0,
            3.999_999,
            1e6 + 0.5,
        ] {
            assert_eq!(fast_floor(v), v.floor(), "{v}");
        }
    }

    #[test]
    fn dense_and_sparse_tables_agree() {
        let (na, nb) = (300, 250);
        assert!(matches!(Contingency::new(na, nb), Contingency::Sparse(_)));
        let mut dense = Contingency::Dense {
            dst_masks: nb,
            weights: vec![0.0; na * nb],
        };
        let mut sparse = Contingency::Sparse(Table::default());
        let mut z = 12345u64;
        for _ in 0..5000 {
            z = z.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
            let (a, b) = ((z >> 33) as u32 % 17 * 13, (z >> 17) as u32 % 250);
            let w = f64::from((z >> 40) as u32 % 4 + 1) * 0.25;
            dense.add(a, b, w);
            sparse.add(a, b, w);
        }
        let (d, s) = (dense.into_sorted(), sparse.into_sorted());
        assert!(d.len() > 100);
        assert_eq!(d, s);
    }

    #[test]
    fn box_iou_counts_cells() {
        let mut a = CellBox::EMPTY;
        assert!(a.is_empty());
        a.add(0, 0);
        a.add(1, 1);
        let mut b = CellBox::EMPTY;
        b.add(1, 1);
        b.add(2, 2);
        assert_eq!(a.area(), 4);
        assert!((a.iou(&b) - 1.0 / 7.0).abs() < 1e-12);
        assert_eq!(a.iou(&CellBox::EMPTY), 0.0);
    }
}

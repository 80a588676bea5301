//! 3D extents of masks and proposals (the extent rules of [`Params::extent_agreement`] and
//! [`Params::extent_merge_iou`]).
//!
//! Every grid cell of a mask that has a rendered depth (the depth test's map: Σωz/Σω where
//! the accumulated alpha reaches `depth_min_alpha`) is unprojected to a world point. A mask
//! keeps only three axis histograms of its points over the scene's bounds ([`BINS`] bins
//! per axis), so a proposal's extent is the sum of its masks' histograms: merging costs
//! O(BINS), memory is O(masks · BINS) whatever the image size, and every quantity is an
//! integer count (deterministic).
//!
//! * **Box** of an extent: per axis, the bins between the `trim` and `1 − trim` quantiles of
//!   its mass (inclusive), widened on both sides by the padding (a share of the scene
//!   diagonal, in bins of that axis), as a half-open interval [lo, hi) in bin units.
//! * **Share of A within B's box**: the product over the axes of the share of A's axis mass
//!   in the bins that lie wholly inside B's box (the marginals stand in for the joint
//!   distribution, which a histogram per axis does not keep).
//! * **Agreement** of A and B: the larger of the two shares.
//! * **Box IoU**: volume of the intersection of the two boxes over the volume of their union.
//!
//! [`Params::extent_agreement`]: crate::Params::extent_agreement
//! [`Params::extent_merge_iou`]: crate::Params::extent_merge_iou

use profuse_formats::camera;
use splat_raster::ViewCamera;

/// Histogram bins per axis over the scene bounds.
pub const BINS: usize = 128;

/// An extent needs at least this many cells with depth before it has a box; fewer are too
/// few to place an object.
pub const MIN_EXTENT_CELLS: u64 = 20;

/// Share of the Gaussian centres left out on each side when the scene bounds are taken, so
/// that a few stray Gaussians do not stretch the bins.
const BOUNDS_TRIM: f64 = 0.001;

/// The world box the histograms cover, split into [`BINS`] bins per axis; positions outside
/// fall into the border bins.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Bounds {
    lo: [f64; 3],
    bin: [f64; 3],
}

impl Bounds {
    /// The 0.1% / 99.9% quantiles of the points per axis; `None` without points or when an
    /// axis has no spread.
    pub(crate) fn from_points(points: &[[f32; 3]]) -> Option<Bounds> {
        let mut lo = [0.0; 3];
        let mut bin = [0.0; 3];
        for k in 0..3 {
            let mut v: Vec<f64> = points
                .iter()
                .map(|p| f64::from(p[k]))
                .filter(|v| v.is_finite())
                .collect();
            if v.is_empty() {
                return None;
            }
            // Two selections, O(n), instead of a sort of every Gaussian.
            let rank = |q: f64| ((v.len() - 1) as f64 * q).round() as usize;
            let (ra, rb) = (rank(BOUNDS_TRIM), rank(1.0 - BOUNDS_TRIM));
            let a = *v.select_nth_unstable_by(ra, f64::total_cmp).1;
            let b = *v.select_nth_unstable_by(rb, f64::total_cmp).1;
            // Finite values only, so `<=` is the complement of `>`.
            if b <= a {
                return None;
            }
            lo[k] = a;
            bin[k] = (b - a) / BINS as f64;
        }
        Some(Bounds { lo, bin })
    }

    /// The bin of a world position per axis, clamped to the border bins.
    #[inline]
    fn bins_of(&self, p: [f64; 3]) -> [usize; 3] {
        std::array::from_fn(|k| {
            let b = (p[k] - self.lo[k]) / self.bin[k];
            // NaN and negatives land in bin 0.
            (b.max(0.0) as usize).min(BINS - 1)
        })
    }

    /// `share` of the bounds' diagonal, in bins of each axis.
    pub(crate) fn padding(&self, share: f64) -> [f64; 3] {
        let diag = self
            .bin
            .iter()
            .map(|b| (b * BINS as f64).powi(2))
            .sum::<f64>()
            .sqrt();
        std::array::from_fn(|k| share * diag / self.bin[k])
    }
}

/// Axis histograms of the world points of a set of cells.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Extent {
    /// Three histograms of [`BINS`] counts (x, y, z).
    hist: Vec<u32>,
    /// Points counted (the sum of each histogram).
    mass: u64,
}

impl Default for Extent {
    fn default() -> Self {
        Extent {
            hist: vec![0; 3 * BINS],
            mass: 0,
        }
    }
}

/// An axis-aligned box in bin units, half-open per axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct BinBox {
    lo: [f64; 3],
    hi: [f64; 3],
}

impl Extent {
    /// Counts one point falling into the given bins.
    #[inline]
    pub(crate) fn add_bins(&mut self, bins: [usize; 3]) {
        for (k, b) in bins.into_iter().enumerate() {
            self.hist[k * BINS + b] += 1;
        }
        self.mass += 1;
    }

    /// Adds another extent (the union of the two point sets).
    pub(crate) fn merge(&mut self, other: &Extent) {
        for (a, b) in self.hist.iter_mut().zip(&other.hist) {
            *a += b;
        }
        self.mass += other.mass;
    }

    /// Points counted.
    pub fn mass(&self) -> u64 {
        self.mass
    }

    fn axis(&self, k: usize) -> &[u32] {
        &self.hist[k * BINS..(k + 1) * BINS]
    }

    /// The trimmed box widened by `pad` bins per axis; `None` below [`MIN_EXTENT_CELLS`].
    pub(crate) fn padded_box(&self, trim: f64, pad: [f64; 3]) -> Option<BinBox> {
        if self.mass < MIN_EXTENT_CELLS {
            return None;
        }
        let cut = trim * self.mass as f64;
        let first_above = |it: &mut dyn Iterator<Item = (usize, &u32)>| {
            let mut acc = 0u64;
            for (k, &c) in it {
                acc += u64::from(c);
                if acc as f64 > cut {
                    return k;
                }
            }
            0
        };
        let mut lo = [0.0; 3];
        let mut hi = [0.0; 3];
        for k in 0..3 {
            let h = self.axis(k);
            let a = first_above(&mut h.iter().enumerate());
            let b = first_above(&mut h.iter().enumerate().rev()).max(a);
            lo[k] = a as f64 - pad[k];
            hi[k] = (b + 1) as f64 + pad[k];
        }
        Some(BinBox { lo, hi })
    }

    /// The share of this extent's points inside `b`, per axis multiplied.
    pub(crate) fn share_within(&self, b: &BinBox) -> f64 {
        if self.mass == 0 {
            return 0.0;
        }
        (0..3)
            .map(|k| {
                let inside: u64 = self
                    .axis(k)
                    .iter()
                    .enumerate()
                    .filter(|(i, _)| *i as f64 >= b.lo[k] && (*i + 1) as f64 <= b.hi[k])
                    .map(|(_, &c)| u64::from(c))
                    .sum();
                inside as f64 / self.mass as f64
            })
            .product()
    }
}

impl BinBox {
    fn volume(&self) -> f64 {
        (0..3).map(|k| (self.hi[k] - self.lo[k]).max(0.0)).product()
    }

    /// Intersection volume over union volume.
    pub(crate) fn iou(&self, other: &BinBox) -> f64 {
        let inter: f64 = (0..3)
            .map(|k| (self.hi[k].min(other.hi[k]) - self.lo[k].max(other.lo[k])).max(0.0))
            .product();
        let union = self.volume() + other.volume() - inter;
        if union > 0.0 {
            inter / union
        } else {
            0.0
        }
    }

    /// Whether the x intervals overlap (the sweep of the merge pass).
    pub(crate) fn x_range(&self) -> (f64, f64) {
        (self.lo[0], self.hi[0])
    }
}

/// The larger of the shares of each extent within the other's box.
pub(crate) fn agreement(a: &Extent, a_box: &BinBox, b: &Extent, b_box: &BinBox) -> f64 {
    a.share_within(b_box).max(b.share_within(a_box))
}

/// The masks' extents and the padding, in bins, of their boxes.
#[derive(Debug, Clone)]
pub(crate) struct MaskExtents {
    /// Per global mask.
    pub(crate) extents: Vec<Extent>,
    /// Padding per axis in bins.
    pub(crate) pad: [f64; 3],
}

/// The extents of the `masks` masks of one view: every grid cell with depth `depth[c] > 0`
/// is unprojected with the grid camera `cam` (intrinsics scaled to the grid) and counted
/// for the label of the mask pixel containing the cell centre (`xmap`, `ymap`).
#[allow(clippy::too_many_arguments)]
pub(crate) fn view_extents(
    labels: &[u32],
    masks: usize,
    depth: &[f32],
    (gw, gh, mw): (usize, usize, usize),
    xmap: &[usize],
    ymap: &[usize],
    cam: &ViewCamera,
    bounds: &Bounds,
) -> Vec<Extent> {
    let mut out = vec![Extent::default(); masks];
    let (r, t) = (cam.rotation, cam.translation);
    for y in 0..gh {
        let row = &labels[ymap[y] * mw..(ymap[y] + 1) * mw];
        for x in 0..gw {
            let z = f64::from(depth[y * gw + x]);
            let label = row[xmap[x]];
            if z <= 0.0 || label as usize >= masks {
                continue;
            }
            // Camera point, then world = Rᵀ (p − t).
            let n = camera::pixel_to_normalised(&cam.intrinsics, camera::pixel_centre(x, y));
            let p = [n[0] * z - t[0], n[1] * z - t[1], z - t[2]];
            let w = camera::camera_to_world_direction(&r, p);
            out[label as usize].add_bins(bounds.bins_of(w));
        }
    }
    out
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn extent(points: &[[usize; 3]]) -> Extent {
        let mut e = Extent::default();
        for p in points {
            e.add_bins(*p);
        }
        e
    }

    #[test]
    fn trimmed_box_leaves_out_the_tails_of_the_mass() {
        // 100 points in x bins 10..=19 (10 each), one stray point at x bin 100.
        let mut pts: Vec<[usize; 3]> = (0..100).map(|i| [10 + i / 10, 5, 7]).collect();
        pts.push([100, 5, 7]);
        let e = extent(&pts);
        let exact = e.padded_box(0.0, [0.0; 3]).unwrap();
        assert_eq!((exact.lo, exact.hi), ([10.0, 5.0, 7.0], [101.0, 6.0, 8.0]));
        // 5% of 101 = 5.05 points: the first bin (10 points) survives, the stray one not.
        let trimmed = e.padded_box(0.05, [1.0, 0.5, 0.0]).unwrap();
        assert_eq!(
            (trimmed.lo, trimmed.hi),
            ([9.0, 4.5, 7.0], [21.0, 6.5, 8.0])
        );
        // Too few points: no box.
        assert!(extent(&[[1, 1, 1]; 19]).padded_box(0.0, [0.0; 3]).is_none());
    }

    #[test]
    fn share_within_and_box_iou_match_hand_counts() {
        // A: 10 points along x bins 0..10 at y = z = 0; B's box covers x [5, 20).
        let a = extent(&(0..10).map(|i| [i, 0, 0]).collect::<Vec<_>>());
        let b = BinBox {
            lo: [5.0, -1.0, -1.0],
            hi: [20.0, 1.0, 1.0],
        };
        assert!((a.share_within(&b) - 0.5).abs() < 1e-12);
        // A bin that sticks out of the box does not count.
        let b2 = BinBox {
            lo: [5.5, -1.0, -1.0],
            ..b
        };
        assert!((a.share_within(&b2) - 0.4).abs() < 1e-12);
        let c = BinBox {
            lo: [0.0; 3],
            hi: [2.0, 2.0, 2.0],
        };
        let d = BinBox {
            lo: [1.0, 0.0, 0.0],
            hi: [3.0, 2.0, 2.0],
        };
        // Intersection 1·2·2 = 4, union 8 + 8 − 4 = 12.
        assert!((c.iou(&d) - 4.0 / 12.0).abs() < 1e-12);
        assert_eq!(
            c.iou(&BinBox {
                lo: [5.0; 3],
                hi: [6.0; 3]
            }),
            0.0
        );
        let mut m = a.clone();
        m.merge(&a);
        assert_eq!(m.mass(), 20);
        // 10 points are too few for a box; doubled they span the same bins.
        assert_eq!(a.padded_box(0.0, [0.0; 3]), None);
        assert_eq!(
            m.padded_box(0.0, [0.0; 3]),
            Some(BinBox {
                lo: [0.0; 3],
                hi: [10.0, 1.0, 1.0]
            })
        );
    }

    #[test]
    fn bounds_bin_world_positions_and_pad_by_the_diagonal() {
        let pts: Vec<[f32; 3]> = (0..=1000)
            .map(|i| {
                let t = i as f32 / 1000.0;
                [12.8 * t, 6.4 * t, 3.2 * t]
            })
            .collect();
        let b = Bounds::from_points(&pts).unwrap();
        // 0.1% trimmed: from 0.0128 to 12.7872 in x.
        assert!((b.lo[0] - 0.0128).abs() < 1e-5);
        assert_eq!(b.bins_of([-5.0, 3.225, 1e9]), [0, 64, BINS - 1]);
        let pad = b.padding(0.01);
        let diag = ((12.7744f64).powi(2) + (6.3872f64).powi(2) + (3.1936f64).powi(2)).sqrt();
        assert!(
            (pad[0] - 0.01 * diag / (12.7744 / 128.0)).abs() < 1e-3,
            "{pad:?}"
        );
        assert!(Bounds::from_points(&[[1.0, 2.0, 3.0]; 5]).is_none());
        assert!(Bounds::from_points(&[]).is_none());
    }

    #[test]
    fn view_extents_unproject_cells_to_world_bins() {
        // World box [0, 12.8]^3 in bins of 0.1.
        let b = Bounds::from_points(&[[0.0; 3], [12.8; 3]]).unwrap();
        // World-to-camera swaps x and y and translates by −5.05 (off the bin edges):
        // world = Rᵀ (p − t).
        let cam = ViewCamera {
            rotation: [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
            translation: [-5.05; 3],
            intrinsics: [1.0, 1.0, 2.0, 1.0],
            width: 4,
            height: 2,
        };
        // 4 x 2 grid, depth 2 (one cell without depth); mask grid 2 x 1: mask 0 on the
        // left half, no mask on the right.
        let mut depth = vec![2.0f32; 8];
        depth[4] = 0.0;
        let labels = [0, u32::MAX];
        let e = view_extents(
            &labels,
            1,
            &depth,
            (4, 2, 2),
            &[0, 0, 1, 1],
            &[0, 0],
            &cam,
            &b,
        );
        assert_eq!(e.len(), 1);
        // Camera points of columns 0, 1: x = (c + 0.5 − 2)·2 = −3, −1; rows: y = −1, 1;
        // minus t: (2.05 | 4.05, 4.05 | 6.05, 7.05); axes swapped: world x in bins 40 | 60,
        // y in bins 20 | 40, z in bin 70. Cell (0, 1) has no depth.
        let nonzero = |k: usize| -> Vec<(usize, u32)> {
            e[0].axis(k)
                .iter()
                .enumerate()
                .filter(|(_, c)| **c > 0)
                .map(|(i, c)| (i, *c))
                .collect()
        };
        assert_eq!(e[0].mass(), 3);
        assert_eq!(nonzero(0), vec![(40, 2), (60, 1)]);
        assert_eq!(nonzero(1), vec![(20, 1), (40, 2)]);
        assert_eq!(nonzero(2), vec![(70, 3)]);
    }
}

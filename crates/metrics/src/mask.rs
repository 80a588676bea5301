//! Binary image masks: polygon rasterisation (the reference rule of the LERF-OVS evaluation,
//! and the pixel-centre rule), PNG reading, IoU.
//!
//! # The reference rule ([`rasterize_polygon`])
//!
//! The LERF-OVS evaluation of LangSplat (`eval/utils.py::polygon_to_mask`, reused by
//! OpenGaussian and Dr. Splat) turns a label polygon into a mask with
//! `points = np.asarray(segmentation, dtype=np.int32)` and
//! `cv2.fillPoly(mask, [points], 1)` (8-connected lines, `shift = 0`). So:
//!
//! 1. **int32 conversion**: each coordinate is truncated toward zero (`2.9 → 2`,
//!    `-0.5 → 0`, `-1.7 → -1`), as NumPy's float → int32 cast does ([`reference_vertices`]).
//! 2. **Outline**: every edge, the closing one included, is drawn as an 8-connected
//!    Bresenham line (OpenCV's `LineIterator`, left to right, clipped to the image with
//!    OpenCV's `clipLine`), so the boundary pixels are always in the mask.
//! 3. **Fill**: OpenCV's scan-line filler (`FillEdgeCollection`). Non-horizontal edges
//!    are kept as half-open row ranges `[y_top, y_bottom)` with x in 16.16 fixed point
//!    (slope truncated toward zero; edges partly outside the image take the slope of their
//!    clipped, integer end points). On each row the active edges' x are sorted and filled
//!    pairwise (1st–2nd, 3rd–4th, …: the even-odd rule) from `ceil(x_left)` to
//!    `floor(x_right)`, clipped to the image.
//!
//! [`fill_poly`] re-implements this for int32 vertices pixel for pixel (checked against
//! `cv2.fillPoly` of OpenCV 4.12 and 5.0 on thousands of random polygons by
//! `crates/metrics/python`, and of 4.7 with [`OpenCvFill::Legacy`]); it costs
//! O(edges · rows + outline pixels + filled pixels). OpenCV generations differ only for
//! polygons with vertices outside the image, except 4.8–4.10, whose fill rounded the right
//! end of each span (a regression fixed in 4.11, not reproduced here): see [`OpenCvFill`].
//!
//! # The pixel-centre rule ([`rasterize_polygon_centres`])
//!
//! Not the evaluation protocol; kept because it is the exact inverse of synth's label
//! polygons (pixel-edge tracings of its object-id maps). Pixel (x, y) covers
//! `[x, x+1) × [y, y+1)` and belongs to a polygon iff its centre `(x + 0.5, y + 0.5)` is
//! inside by the **even-odd** rule: a ray from the centre towards +x crosses the boundary
//! an odd number of times. An edge `a → b` is crossed when `(a.y > c.y) != (b.y > c.y)`
//! and the crossing lies strictly right of the centre, decided by an exact sign test on
//! cross products (exact for coordinates on a half-pixel grid). **Ties**: a centre exactly
//! on the boundary is classified like the point infinitesimally to its right and below
//! (inside on left and top edges, outside on right and bottom edges), so polygons sharing
//! an edge never share a pixel and doubled "bridge" edges cancel.

use std::path::Path;

use crate::{MetricsError, Result};

/// A binary mask of `width × height` pixels, row-major.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Mask {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `pixels[y * width + x]`: whether pixel (x, y) is selected.
    pub pixels: Vec<bool>,
}

impl Mask {
    /// An empty (all false) mask.
    pub fn empty(width: u32, height: u32) -> Mask {
        Mask {
            width,
            height,
            pixels: vec![false; width as usize * height as usize],
        }
    }

    /// Number of selected pixels.
    pub fn count(&self) -> u64 {
        self.pixels.iter().filter(|p| **p).count() as u64
    }

    /// Adds the pixels of `other` (same size; smaller overlaps are cut).
    pub fn union_with(&mut self, other: &Mask) {
        for (a, b) in self.pixels.iter_mut().zip(&other.pixels) {
            *a |= *b;
        }
    }

    /// Number of pixels selected in both masks.
    pub fn intersection(&self, other: &Mask) -> u64 {
        self.pixels
            .iter()
            .zip(&other.pixels)
            .filter(|(a, b)| **a && **b)
            .count() as u64
    }
}

/// Fixed-point fraction bits of OpenCV's polygon filler (`XY_SHIFT`).
const XY_SHIFT: u32 = 16;
/// One pixel in fixed point.
const XY_ONE: i64 = 1 << XY_SHIFT;

/// The vertices the reference evaluation rasterises: each coordinate cast to int32 the way
/// `np.asarray(points, dtype=np.int32)` does, i.e. truncated toward zero (`2.9 → 2`,
/// `-0.5 → 0`, `-1.5 → -1`). NumPy raises on values outside int32 (and on NaN); here they
/// saturate, and [`crate::lerf::read_label_file`] rejects them first.
pub fn reference_vertices(points: &[[f64; 2]]) -> Vec<[i32; 2]> {
    // `as` truncates toward zero and saturates (NaN → 0).
    points.iter().map(|p| [p[0] as i32, p[1] as i32]).collect()
}

/// Whether `v` survives the int32 conversion of [`reference_vertices`] unchanged in
/// meaning: finite and inside the int32 range after truncation (NumPy raises otherwise).
pub fn fits_int32(v: f64) -> bool {
    v.is_finite() && v.trunc() >= f64::from(i32::MIN) && v.trunc() <= f64::from(i32::MAX)
}

/// Rasterises a closed polygon given in (possibly fractional) pixel coordinates exactly as
/// the LERF-OVS reference evaluation does: [`reference_vertices`] (truncation to int32),
/// then [`fill_poly`] (`cv2.fillPoly` semantics, boundary included). Fewer than three
/// vertices still draw their outline (a point, a segment), as OpenCV does.
///
/// ```
/// use profuse_metrics::mask::rasterize_polygon;
/// // The square with corners (1, 1) and (3, 3) covers pixels 1..=3 x 1..=3: the outline is
/// // part of the mask.
/// let m = rasterize_polygon(&[[1.0, 1.0], [3.0, 1.0], [3.0, 3.0], [1.0, 3.0]], 5, 5);
/// assert_eq!(m.count(), 9);
/// assert!(m.pixels[1 * 5 + 1] && m.pixels[3 * 5 + 3] && !m.pixels[4 * 5 + 4]);
/// // 3.9 truncates to 3: the same mask.
/// let t = rasterize_polygon(&[[1.2, 1.0], [3.9, 1.0], [3.9, 3.5], [1.0, 3.0]], 5, 5);
/// assert_eq!(t, m);
/// ```
pub fn rasterize_polygon(points: &[[f64; 2]], width: u32, height: u32) -> Mask {
    fill_poly(&reference_vertices(points), width, height)
}

/// One non-horizontal edge of the scan-line filler (OpenCV's `PolyEdge`): the rows
/// `y0 ≤ y < y1` it spans, its x at row `y0` and its x step per row, both in 16.16 fixed
/// point.
#[derive(Debug, Clone, Copy)]
struct Edge {
    y0: i32,
    y1: i32,
    x: i64,
    dx: i64,
}

/// Cohen–Sutherland outcode of OpenCV's `clipLine`: 1 left, 2 right, 4 above, 8 below.
fn outcode(p: [i64; 2], right: i64, bottom: i64) -> u8 {
    u8::from(p[0] < 0)
        + u8::from(p[0] > right) * 2
        + u8::from(p[1] < 0) * 4
        + u8::from(p[1] > bottom) * 8
}

/// OpenCV's `clipLine(Size2l, Point2l&, Point2l&)` step for step: each end point outside
/// is moved along the segment, first onto the top/bottom border, then onto the left/right
/// one, with the offset computed in double precision and truncated toward zero. The second
/// end point uses the already moved first one, so the result depends on the order, and the
/// points can be moved even when the segment turns out to miss the image (the caller of
/// [`collect_edges`] relies on those moved points, as OpenCV does). Returns whether the
/// segment touches the `width × height` image.
fn clip_line(width: i64, height: i64, p1: &mut [i64; 2], p2: &mut [i64; 2]) -> bool {
    if width <= 0 || height <= 0 {
        return false;
    }
    let (right, bottom) = (width - 1, height - 1);
    let mut c1 = outcode(*p1, right, bottom);
    let mut c2 = outcode(*p2, right, bottom);
    // `(double)(a - y1) * (x2 - x1) / (y2 - y1)` then a cast that truncates; the
    // denominators are non-zero whenever the branches run (both ends outside on the same
    // side would have `c1 & c2 != 0`), and a non-finite quotient saturates instead of
    // panicking.
    let offset = |num: i64, mul: i64, den: i64| (num as f64 * mul as f64 / den as f64) as i64;
    if c1 & c2 == 0 && c1 | c2 != 0 {
        if c1 & 12 != 0 {
            let a = if c1 < 8 { 0 } else { bottom };
            p1[0] = p1[0].wrapping_add(offset(a - p1[1], p2[0] - p1[0], p2[1] - p1[1]));
            p1[1] = a;
            c1 = u8::from(p1[0] < 0) + u8::from(p1[0] > right) * 2;
        }
        if c2 & 12 != 0 {
            let a = if c2 < 8 { 0 } else { bottom };
            p2[0] = p2[0].wrapping_add(offset(a - p2[1], p2[0] - p1[0], p2[1] - p1[1]));
            p2[1] = a;
            c2 = u8::from(p2[0] < 0) + u8::from(p2[0] > right) * 2;
        }
        if c1 & c2 == 0 && c1 | c2 != 0 {
            if c1 != 0 {
                let a = if c1 == 1 { 0 } else { right };
                p1[1] = p1[1].wrapping_add(offset(a - p1[0], p2[1] - p1[1], p2[0] - p1[0]));
                p1[0] = a;
                c1 = 0;
            }
            if c2 != 0 {
                let a = if c2 == 1 { 0 } else { right };
                p2[1] = p2[1].wrapping_add(offset(a - p2[0], p2[1] - p1[1], p2[0] - p1[0]));
                p2[0] = a;
                c2 = 0;
            }
        }
    }
    c1 | c2 == 0
}

/// Sets pixel (x, y) when it is inside the mask (the line and span code only produce
/// inside pixels; the check keeps a logic slip from becoming a panic).
fn set(mask: &mut Mask, x: i64, y: i64) {
    if (0..i64::from(mask.width)).contains(&x) && (0..i64::from(mask.height)).contains(&y) {
        mask.pixels[y as usize * mask.width as usize + x as usize] = true;
    }
}

/// An 8-connected line as OpenCV's `Line` draws it (`LineIterator` with
/// `leftToRight = true`): end points outside the image are first clipped with
/// [`clip_line`] (nothing is drawn when the segment misses the image), then a Bresenham
/// walk from the left end point (the first one when both have the same x) along the
/// major axis, stepping the minor axis while the error term is negative. Both end points
/// are drawn. The walk direction matters: at an exact tie the minor step happens late.
fn draw_line(mask: &mut Mask, mut p1: [i64; 2], mut p2: [i64; 2]) {
    let (w, h) = (i64::from(mask.width), i64::from(mask.height));
    let inside = |p: [i64; 2]| (0..w).contains(&p[0]) && (0..h).contains(&p[1]);
    // Clip only when an end point is outside (OpenCV's condition): clipping moves points.
    let outside = !(inside(p1) && inside(p2));
    if outside && !clip_line(w, h, &mut p1, &mut p2) {
        return;
    }
    let (mut dx, mut dy) = (p2[0] - p1[0], p2[1] - p1[1]);
    let mut start = p1;
    if dx < 0 {
        // Left to right: start from the second point and walk the negated vector.
        dx = -dx;
        dy = -dy;
        start = p2;
    }
    let sy = if dy < 0 { -1 } else { 1 };
    let dy = dy.abs();
    let vertical = dy > dx;
    let (major, minor) = if vertical { (dy, dx) } else { (dx, dy) };
    let mut err = major - 2 * minor;
    let [mut x, mut y] = start;
    for _ in 0..=major {
        set(mask, x, y);
        let minor_step = err < 0;
        if minor_step {
            err += 2 * major - 2 * minor;
        } else {
            err -= 2 * minor;
        }
        if vertical {
            y += sy;
            if minor_step {
                x += 1;
            }
        } else {
            x += 1;
            if minor_step {
                y += sy;
            }
        }
    }
}

/// OpenCV's `CollectPolyEdges` for `shift = 0` and 8-connected lines: draws every edge
/// (the closing one first: OpenCV starts from the last vertex) with [`draw_line`] and
/// returns the non-horizontal ones. An edge with an end point outside the image takes
/// its x (and, unless the clipped segment is horizontal, its y) reference and its slope
/// from the clipped integer end points, then extrapolates that line to its original end
/// rows (OpenCV ≥ 4.8, "use clipped endpoints to create a more accurate PolyEdge");
/// [`OpenCvFill::Legacy`] builds every edge from its unclipped vertices.
/// Arithmetic wraps like OpenCV's on overflow (only reachable with coordinates near the
/// int32 limits).
fn collect_edges(mask: &mut Mask, points: &[[i32; 2]], variant: OpenCvFill) -> Vec<Edge> {
    let (w, h) = (i64::from(mask.width), i64::from(mask.height));
    let mut edges = Vec::with_capacity(points.len());
    let Some(&last) = points.last() else {
        return edges;
    };
    let mut p0 = [i64::from(last[0]), i64::from(last[1])];
    for v in points {
        let p1 = [i64::from(v[0]), i64::from(v[1])];
        draw_line(mask, p0, p1);
        let (mut t0, mut t1) = (p0, p1);
        // (fixed-point x, row) of the two end points the edge is built from.
        let (mut c0y, mut c1y) = (p0[1], p1[1]);
        let inside = |p: [i64; 2]| (0..w).contains(&p[0]) && (0..h).contains(&p[1]);
        if variant == OpenCvFill::Current && !(inside(t0) && inside(t1)) {
            // The result is ignored on purpose: OpenCV uses the moved points either way.
            clip_line(w, h, &mut t0, &mut t1);
            if t0[1] != t1[1] {
                (c0y, c1y) = (t0[1], t1[1]);
            }
        }
        let (c0x, c1x) = (t0[0].wrapping_mul(XY_ONE), t1[0].wrapping_mul(XY_ONE));
        if p0[1] != p1[1] {
            // C integer division truncates toward zero, as Rust's does.
            let dx = c1x.wrapping_sub(c0x).wrapping_div(c1y - c0y);
            let (y0, y1, x) = if p0[1] < p1[1] {
                (
                    p0[1],
                    p1[1],
                    c0x.wrapping_add((p0[1] - c0y).wrapping_mul(dx)),
                )
            } else {
                (
                    p1[1],
                    p0[1],
                    c1x.wrapping_add((p1[1] - c1y).wrapping_mul(dx)),
                )
            };
            // Rows came from i32 vertices, so they fit.
            edges.push(Edge {
                y0: y0 as i32,
                y1: y1 as i32,
                x,
                dx,
            });
        }
        p0 = p1;
    }
    edges
}

/// OpenCV's `FillEdgeCollection`: on every image row `y`, the edges with `y0 ≤ y < y1`
/// are active; their x at the row (`x + (y − y0)·dx`: OpenCV adds `dx` once per row from
/// `y0` on, rows above the image included, which is the same sum) are sorted and taken in
/// pairs, and each pair fills `ceil(x_left) ..= floor(x_right)`, clipped to the image. The
/// pairs are what OpenCV's active-edge list pairs, because its list is kept sorted by x
/// (new edges merged in order, a bubble sort after every row), so the spans depend only on
/// the sorted x values. Fewer than two edges, or edges all left, right, above or below
/// the image, fill nothing (OpenCV's early return).
fn fill_edges(mask: &mut Mask, mut edges: Vec<Edge>) {
    if edges.len() < 2 {
        return;
    }
    let (w, h) = (i64::from(mask.width), i64::from(mask.height));
    let (mut y_min, mut y_max) = (i32::MAX, i32::MIN);
    // OpenCV starts x_max at -1 (an all-ones literal), which changes nothing below.
    let (mut x_min, mut x_max) = (i64::MAX, -1i64);
    for e in &edges {
        // OpenCV multiplies `int` (y1 − y0) by the int64 step.
        let x1 =
            e.x.wrapping_add(i64::from(e.y1.wrapping_sub(e.y0)).wrapping_mul(e.dx));
        y_min = y_min.min(e.y0);
        y_max = y_max.max(e.y1);
        x_min = x_min.min(e.x).min(x1);
        x_max = x_max.max(e.x).max(x1);
    }
    if y_max < 0 || i64::from(y_min) >= h || x_max < 0 || x_min >= w << XY_SHIFT {
        return;
    }
    edges.sort_by_key(|e| e.y0);
    let first = i64::from(y_min).max(0);
    let end = i64::from(y_max).min(h);
    let mut next = 0; // first edge not yet activated
    let mut active: Vec<Edge> = Vec::new();
    let mut xs: Vec<i64> = Vec::new();
    let w_px = mask.width as usize;
    for y in first..end {
        while next < edges.len() && i64::from(edges[next].y0) <= y {
            active.push(edges[next]);
            next += 1;
        }
        active.retain(|e| i64::from(e.y1) > y);
        xs.clear();
        xs.extend(
            active
                .iter()
                .map(|e| e.x.wrapping_add((y - i64::from(e.y0)).wrapping_mul(e.dx))),
        );
        xs.sort_unstable();
        let row = y as usize * w_px;
        for pair in xs.chunks_exact(2) {
            // `(int)` casts of the shifted values, as OpenCV's.
            let x1 = i64::from((pair[0].wrapping_add(XY_ONE - 1) >> XY_SHIFT) as i32);
            let x2 = i64::from((pair[1] >> XY_SHIFT) as i32);
            if x1 < w && x2 >= 0 {
                let (x1, x2) = (x1.max(0) as usize, x2.min(w - 1) as usize);
                if x1 <= x2 {
                    mask.pixels[row + x1..=row + x2].fill(true);
                }
            }
        }
    }
}

/// Which OpenCV's `fillPoly` [`fill_poly_as`] reproduces. The two agree on every polygon
/// whose vertices all lie inside the image (the LERF-OVS labels); they differ only in
/// how an edge with an end point outside the image is extrapolated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum OpenCvFill {
    /// OpenCV ≥ 4.11 (checked against 4.12 and 5.0): edges partly outside the image are
    /// rebuilt from their clipped end points (PR #23076), spans are `ceil ..= floor`
    /// (PR #26187 restored this after 4.8–4.10 rounded the right end, a regression that
    /// neither variant reproduces).
    #[default]
    Current,
    /// OpenCV ≤ 4.7 (checked against 4.7.0), the generation LangSplat's published
    /// environment (Python 3.7, conda-forge `opencv` unpinned) resolves to: every edge
    /// from its unclipped vertices.
    Legacy,
}

/// `cv2.fillPoly(mask, [points], 1)` on a `width × height` mask (8-connected, no
/// sub-pixel shift, one contour) as current OpenCV does ([`OpenCvFill::Current`]): the
/// outline is drawn with 8-connected lines and the interior filled by OpenCV's scan-line
/// rule (module documentation). Any int32 vertices are accepted: outside the image the
/// polygon is clipped; a single vertex draws one pixel, two draw a segment; an empty
/// slice draws nothing.
///
/// ```
/// use profuse_metrics::mask::fill_poly;
/// // A right triangle with legs of 4 pixels: rows 0..=4 hold 5, 4, 3, 2, 1 pixels.
/// let m = fill_poly(&[[0, 0], [4, 0], [0, 4]], 6, 6);
/// assert_eq!(m.count(), 15);
/// ```
pub fn fill_poly(points: &[[i32; 2]], width: u32, height: u32) -> Mask {
    fill_poly_as(points, width, height, OpenCvFill::Current)
}

/// [`fill_poly`] as the given OpenCV generation does it.
pub fn fill_poly_as(points: &[[i32; 2]], width: u32, height: u32, variant: OpenCvFill) -> Mask {
    let mut mask = Mask::empty(width, height);
    if width == 0 || height == 0 {
        return mask;
    }
    let edges = collect_edges(&mut mask, points, variant);
    fill_edges(&mut mask, edges);
    mask
}

/// Whether the crossing of edge `a → b` (which straddles the row `y = py`) lies strictly
/// right of `px`: sign of `((a.x − px)·dy + (py − a.y)·dx) · dy`, no division.
fn crossing_right_of(a: [f64; 2], b: [f64; 2], px: f64, py: f64) -> bool {
    let dy = b[1] - a[1];
    let num = (a[0] - px) * dy + (py - a[1]) * (b[0] - a[0]);
    (num > 0.0 && dy > 0.0) || (num < 0.0 && dy < 0.0)
}

/// Rasterises a closed polygon (vertices in pixel coordinates; the last vertex connects
/// to the first) with the pixel-centre even-odd rule of the module documentation (not the
/// LERF-OVS protocol, see [`rasterize_polygon`]).
/// Fewer than three vertices give an empty mask; non-finite vertices are skipped by the
/// crossing test (callers validate them, see [`crate::lerf::read_label_file`]).
///
/// ```
/// use profuse_metrics::mask::rasterize_polygon_centres;
/// // The square [1, 3] x [1, 3] covers pixels 1..3 x 1..3.
/// let m = rasterize_polygon_centres(&[[1.0, 1.0], [3.0, 1.0], [3.0, 3.0], [1.0, 3.0]], 4, 4);
/// assert_eq!(m.count(), 4);
/// assert!(m.pixels[1 * 4 + 1] && m.pixels[2 * 4 + 2] && !m.pixels[3 * 4 + 3]);
/// ```
pub fn rasterize_polygon_centres(points: &[[f64; 2]], width: u32, height: u32) -> Mask {
    let mut mask = Mask::empty(width, height);
    if points.len() < 3 || width == 0 {
        return mask;
    }
    let w = width as usize;
    let (lo, hi) = points
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), p| {
            (l.min(p[1]), h.max(p[1]))
        });
    if !(lo.is_finite() && hi.is_finite()) {
        return mask;
    }
    // Rows whose centre can lie in [lo, hi].
    let first = (lo - 0.5).ceil().max(0.0) as usize;
    let last = ((hi - 0.5).floor().min(f64::from(height) - 1.0)).max(-1.0);
    if last < 0.0 {
        return mask;
    }
    // toggles[k]: crossings whose first pixel not left of them is k; pixel x is inside iff
    // the crossings with k > x are odd in number.
    let mut toggles = vec![0u32; w + 1];
    for y in first..=last as usize {
        let py = y as f64 + 0.5;
        toggles.iter_mut().for_each(|t| *t = 0);
        let mut any = false;
        for (i, &a) in points.iter().enumerate() {
            let b = points[(i + 1) % points.len()];
            if (a[1] > py) == (b[1] > py) {
                continue;
            }
            let xx = a[0] + (py - a[1]) * (b[0] - a[0]) / (b[1] - a[1]);
            if !xx.is_finite() {
                continue;
            }
            // Guess k = #{x : x + 0.5 < xx}, then settle it with the exact test.
            let mut k = (xx - 0.5).ceil().clamp(0.0, w as f64) as usize;
            while k > 0 && !crossing_right_of(a, b, k as f64 - 0.5, py) {
                k -= 1;
            }
            while k < w && crossing_right_of(a, b, k as f64 + 0.5, py) {
                k += 1;
            }
            toggles[k] += 1;
            any = true;
        }
        if !any {
            continue;
        }
        let row = &mut mask.pixels[y * w..(y + 1) * w];
        let mut parity = 0u32;
        for x in (0..w).rev() {
            parity += toggles[x + 1];
            row[x] = parity % 2 == 1;
        }
    }
    mask
}

/// Reads a PNG (or any format the `image` crate decodes) as a mask: a pixel is selected
/// when any colour channel is non-zero (alpha is ignored). The size must be
/// `width × height`, else [`MetricsError::MaskSize`].
pub fn read_mask_png(path: &Path, width: u32, height: u32) -> Result<Mask> {
    let shown = || path.display().to_string();
    let img = image::ImageReader::open(path)
        .map_err(crate::error::io_err(path, "cannot open mask"))?
        .with_guessed_format()
        .map_err(crate::error::io_err(path, "cannot read mask"))?
        .decode()
        .map_err(|source| MetricsError::Image {
            path: shown(),
            source,
        })?;
    if img.width() != width || img.height() != height {
        return Err(MetricsError::MaskSize {
            path: shown(),
            width,
            height,
            found_width: img.width(),
            found_height: img.height(),
        });
    }
    let pixels = match img {
        image::DynamicImage::ImageLuma8(b) => b.into_raw().into_iter().map(|v| v != 0).collect(),
        other => other
            .to_rgb16()
            .pixels()
            .map(|p| p.0 != [0, 0, 0])
            .collect(),
    };
    Ok(Mask {
        width,
        height,
        pixels,
    })
}

//! LERF-style label files (LangSplat's `lerf_ovs` schema) for evaluation frames:
//! one polygon per 4-connected component of each visible non-room object, traced along
//! pixel edges.

use std::collections::HashMap;

use profuse_formats::NO_OBJECT;
use serde::Serialize;

use crate::scene::Scene;

/// Components smaller than this (pixels) get no entry.
pub const MIN_COMPONENT_PX: usize = 20;

/// A label file.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct LabelFile {
    pub info: Info,
    pub objects: Vec<LabelObject>,
}

/// The `info` block.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct Info {
    pub name: String,
    pub width: u32,
    pub height: u32,
}

/// One object entry.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct LabelObject {
    pub category: String,
    /// Polygon vertices (x, y) at pixel corners, pixels, origin top-left corner.
    pub segmentation: Vec<[i64; 2]>,
    /// [x1, y1, x2, y2] of the component's pixels (corner coordinates).
    pub bbox: [i64; 4],
    /// The object index (extension; LangSplat readers ignore it).
    pub object: u32,
    /// Pixels of the component (extension).
    pub area: usize,
}

/// Builds the label file of one frame from its object-id map.
pub(crate) fn frame_labels(scene: &Scene, ids: &[u32], width: usize, name: String) -> LabelFile {
    let height = ids.len() / width.max(1);
    let mut comp = vec![u32::MAX; ids.len()];
    let mut objects = Vec::new();
    let mut stack = Vec::new();
    let mut pixels = Vec::new();
    let mut next = 0u32;
    for start in 0..ids.len() {
        let o = ids[start];
        if comp[start] != u32::MAX
            || o == NO_OBJECT
            || scene.objects.get(o as usize).is_none_or(|s| s.room)
        {
            continue;
        }
        // Flood fill (4-connected) from the raster-first pixel of the component.
        pixels.clear();
        comp[start] = next;
        stack.push(start);
        while let Some(i) = stack.pop() {
            pixels.push(i);
            let (x, y) = (i % width, i / width);
            let mut visit = |j: usize| {
                if comp[j] == u32::MAX && ids[j] == o {
                    comp[j] = next;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < width {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - width);
            }
            if y + 1 < height {
                visit(i + width);
            }
        }
        if pixels.len() >= MIN_COMPONENT_PX {
            let (segmentation, bbox) = trace(&comp, width, height, next, start);
            objects.push(LabelObject {
                category: scene.objects[o as usize].class_name.clone(),
                segmentation,
                bbox,
                object: o,
                area: pixels.len(),
            });
        }
        next += 1;
    }
    LabelFile {
        info: Info {
            name,
            width: width as u32,
            height: height as u32,
        },
        objects,
    }
}

/// Directions: 0 = +x, 1 = +y (down), 2 = −x, 3 = −y.
const STEP: [[i64; 2]; 4] = [[1, 0], [0, 1], [-1, 0], [0, -1]];

/// Traces the boundary of component `c` (whose raster-first pixel is `first`) along pixel
/// edges, interior on the right (screen coordinates), hugging the component at saddle
/// corners (4-connectivity). Returns one polygon: the outer loop, then each hole joined
/// by a doubled "bridge" path from the outer loop's first vertex. Doubled paths cancel in
/// even-odd and non-zero winding tests, so the pixel-centre rasterisation of the polygon
/// is exactly the component. Also returns the bbox.
fn trace(
    comp: &[u32],
    width: usize,
    height: usize,
    c: u32,
    first: usize,
) -> (Vec<[i64; 2]>, [i64; 4]) {
    let (fx, fy) = ((first % width) as i64, (first / width) as i64);
    let (out, edges, bbox) = boundary_edges(comp, width, height, c, [fx, fy]);
    let mut used = vec![false; edges.len()];
    // Outer loop: starts with the top edge of the raster-first pixel.
    let start = out
        .get(&[fx, fy])
        .and_then(|v| v.iter().copied().find(|k| edges[*k].1 == 0))
        .unwrap_or(0);
    let mut poly = follow(&out, &edges, start, &mut used);
    let o0 = poly.first().copied().unwrap_or([fx, fy]);
    // Holes, in order of their first edge (raster order of the pixels that own them).
    for k in 0..edges.len() {
        if used[k] {
            continue;
        }
        let hole = follow(&out, &edges, k, &mut used);
        let Some(&h0) = hole.first() else { continue };
        let bend = [h0[0], o0[1]];
        let mut path = vec![o0, bend, h0];
        path.extend(hole.iter().skip(1).copied());
        path.extend([h0, bend, o0]);
        for p in path {
            if poly.last() != Some(&p) {
                poly.push(p);
            }
        }
    }
    if poly.len() > 1 && poly.last() == poly.first() {
        poly.pop();
    }
    (poly, bbox)
}

/// A boundary edge: its start vertex and its direction (see [`STEP`]).
type Edge = ([i64; 2], usize);
/// Outgoing boundary edges of a component, per start vertex (at most two).
type EdgesFrom = HashMap<[i64; 2], Vec<usize>>;

/// The boundary edges of component `c` (start vertex, direction), in raster order of their
/// pixels from the component's raster-first pixel `[fx, fy]`, the edges leaving each
/// vertex, and the component's bbox. A step of [`trace`].
fn boundary_edges(
    comp: &[u32],
    width: usize,
    height: usize,
    c: u32,
    [fx, fy]: [i64; 2],
) -> (EdgesFrom, Vec<Edge>, [i64; 4]) {
    let inside = |x: i64, y: i64| {
        x >= 0
            && y >= 0
            && (x as usize) < width
            && (y as usize) < height
            && comp[y as usize * width + x as usize] == c
    };
    let mut out: EdgesFrom = HashMap::new();
    let mut edges: Vec<Edge> = Vec::new();
    let (mut bx0, mut by0, mut bx1, mut by1) = (fx, fy, fx + 1, fy + 1);
    for y in fy..height as i64 {
        for x in 0..width as i64 {
            if !inside(x, y) {
                continue;
            }
            bx0 = bx0.min(x);
            bx1 = bx1.max(x + 1);
            by1 = by1.max(y + 1);
            by0 = by0.min(y);
            let mut add = |v: [i64; 2], d: usize| {
                out.entry(v).or_default().push(edges.len());
                edges.push((v, d));
            };
            if !inside(x, y - 1) {
                add([x, y], 0);
            }
            if !inside(x + 1, y) {
                add([x + 1, y], 1);
            }
            if !inside(x, y + 1) {
                add([x + 1, y + 1], 2);
            }
            if !inside(x - 1, y) {
                add([x, y + 1], 3);
            }
        }
    }
    (out, edges, [bx0, by0, bx1, by1])
}

/// Walks the unused edges from `start` around their loop (marking them used) and returns
/// its corners: the vertices where the direction changes, starting at the first corner.
/// A step of [`trace`].
fn follow(out: &EdgesFrom, edges: &[Edge], start: usize, used: &mut [bool]) -> Vec<[i64; 2]> {
    // Walk edges; collect the direction of each.
    let mut loop_edges = Vec::new();
    let mut e = start;
    loop {
        used[e] = true;
        loop_edges.push(e);
        let (v, d) = edges[e];
        let end = [v[0] + STEP[d][0], v[1] + STEP[d][1]];
        let cands = out.get(&end).map(Vec::as_slice).unwrap_or(&[]);
        let free: Vec<usize> = cands.iter().copied().filter(|k| !used[*k]).collect();
        let next = match free.as_slice() {
            [] => None,
            [only] => Some(*only),
            many => many
                .iter()
                .copied()
                .find(|k| edges[*k].1 == (d + 1) % 4)
                .or(Some(many[0])),
        };
        match next {
            Some(n) => e = n,
            None => break,
        }
    }
    // Corners: vertices where the direction changes, starting at the first corner.
    let n = loop_edges.len();
    let dirs: Vec<usize> = loop_edges.iter().map(|e| edges[*e].1).collect();
    let mut corners = Vec::new();
    for k in 0..n {
        if dirs[k] != dirs[(k + n - 1) % n] {
            corners.push(edges[loop_edges[k]].0);
        }
    }
    corners
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Even-odd pixel-centre rasterisation.
    fn raster(poly: &[[i64; 2]], w: usize, h: usize) -> Vec<bool> {
        let mut m = vec![false; w * h];
        for y in 0..h {
            let py = y as f64 + 0.5;
            for x in 0..w {
                let px = x as f64 + 0.5;
                let mut inside = false;
                for k in 0..poly.len() {
                    let (a, b) = (poly[k], poly[(k + 1) % poly.len()]);
                    let (ay, by) = (a[1] as f64, b[1] as f64);
                    if (ay > py) != (by > py) {
                        let t = (py - ay) / (by - ay);
                        let xx = a[0] as f64 + t * (b[0] - a[0]) as f64;
                        if xx > px {
                            inside = !inside;
                        }
                    }
                }
                m[y * w + x] = inside;
            }
        }
        m
    }

    #[test]
    fn traces_holes_saddles_and_borders() {
        // A ring with a hole, a diagonal saddle inside the component, touching the border.
        let art = [
            "#######.", //
            "#.....#.", //
            "#.##..#.", //
            "#.##..##", //
            "#....#.#", //
            "######.#", //
            "#......#", //
            "########", //
        ];
        let (w, h) = (8, 8);
        let comp: Vec<u32> = art
            .iter()
            .flat_map(|r| r.bytes().map(|b| if b == b'#' { 0 } else { u32::MAX }))
            .collect();
        let (poly, bbox) = trace(&comp, w, h, 0, 0);
        let m = raster(&poly, w, h);
        for i in 0..w * h {
            assert_eq!(m[i], comp[i] == 0, "pixel {i} polygon {poly:?}");
        }
        assert_eq!(bbox, [0, 0, 8, 8]);
        // Axis-aligned, vertices at corners.
        for k in 0..poly.len() {
            let (a, b) = (poly[k], poly[(k + 1) % poly.len()]);
            assert!(a[0] == b[0] || a[1] == b[1], "{a:?} {b:?}");
        }
    }
}

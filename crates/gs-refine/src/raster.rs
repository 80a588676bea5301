//! The differentiable tile rasterizer: splat-raster's colour forward (the same per-pixel
//! f32 operations in the same order, so the same image), keeping per pixel its final
//! transmittance and how far down its tile's list it blended, and the backward pass that
//! walks each pixel's contributors back to front over those same lists.
//!
//! Parallel over tile rows with rayon. The backward pass accumulates each tile's gradients
//! in a buffer with one slot per (tile, Gaussian) list entry (no atomics: every tile row
//! owns its slots); one sequential pass then sums the slots of each Gaussian in list
//! order, so the bytes do not depend on the thread count.

use rayon::prelude::*;
use splat_raster::math::exp;
use splat_raster::{ViewCamera, ALPHA_MAX, ALPHA_MIN, TILE, T_MIN};

use crate::params::{rest_coeffs, Grads, Params};
use crate::project::{self, ScreenGrad};

/// Margin added to ln(255 · opacity) when bounding a footprint (splat-raster's TAU_MARGIN).
const TAU_MARGIN: f64 = 0.05;

/// One projected Gaussian in the single-precision form of the per-pixel loop.
#[derive(Debug, Clone, Copy)]
struct Splat {
    x: f32,
    y: f32,
    conic: [f32; 3],
    opacity: f32,
    color: [f32; 3],
    depth: f32,
    id: u32,
    /// Inclusive pixel rectangle outside which alpha < 1/255: x0, x1, y0, y1.
    rect: [u32; 4],
}

/// One view's forward state, reused between iterations (buffers keep their capacity).
#[derive(Debug, Default)]
pub struct ViewState {
    width: usize,
    height: usize,
    tiles_x: usize,
    splats: Vec<Splat>,
    /// Start of each tile's list in `entries` (tiles row-major), plus the end.
    tile_start: Vec<usize>,
    /// Indices into `splats`, per tile front to back.
    entries: Vec<u32>,
    /// Final transmittance per pixel.
    t_final: Vec<f32>,
    /// Per pixel, the number of list entries up to and including its last contributor.
    last: Vec<u32>,
    /// Rendered colour `[H, W, 3]`.
    color: Vec<f32>,
    /// Per list entry, the screen gradient summed over the tile's pixels.
    entry_grads: Vec<[f32; 9]>,
    /// Per splat, the screen gradient summed over tiles.
    splat_grads: Vec<ScreenGrad>,
}

impl ViewState {
    /// The rendered colour `[H, W, 3]` of the last [`forward`].
    pub fn color(&self) -> &[f32] {
        &self.color
    }

    /// Final transmittance per pixel.
    pub fn transmittance(&self) -> &[f32] {
        &self.t_final
    }

    /// (tile, Gaussian) pairs of the last forward.
    pub fn pairs(&self) -> usize {
        self.entries.len()
    }

    /// Gaussians drawn by the last forward.
    pub fn visible(&self) -> usize {
        self.splats.len()
    }
}

/// Projects every Gaussian in parallel and keeps the drawable ones in (depth, id) order.
fn project_all(p: &Params, cam: &ViewCamera, campos: [f64; 3], out: &mut Vec<Splat>) {
    let (w, h) = (cam.width, cam.height);
    let mut splats: Vec<Splat> = (0..p.len())
        .into_par_iter()
        .filter_map(|i| to_splat(&project::project(p, cam, campos, i)?, i, w, h))
        .collect();
    splats.par_sort_unstable_by_key(|s| (s.depth.to_bits(), s.id));
    *out = splats;
}

/// splat-raster's `Splat::new` culls (opacity below 1/255, non-finite f32 parameters) and
/// the pixel rectangle of its α >= 1/255 ellipse (with a whole pixel of slack, a superset
/// of splat-raster's, so the same pixels are blended).
fn to_splat(pr: &project::Proj, i: usize, width: u32, height: u32) -> Option<Splat> {
    let opacity = pr.opacity as f32;
    if opacity.is_nan() || opacity < ALPHA_MIN {
        return None;
    }
    let [u, v] = pr.center;
    let conic = pr.conic.map(|x| x as f32);
    let (x, y) = (u as f32, v as f32);
    if ![x, y, conic[0], conic[1], conic[2]]
        .iter()
        .all(|v| v.is_finite())
    {
        return None;
    }
    let tau = (255.0 * pr.opacity).ln() + TAU_MARGIN;
    let ex = (2.0 * tau * pr.cov2d[0]).sqrt();
    let ey = (2.0 * tau * pr.cov2d[2]).sqrt();
    let span = |c: f64, e: f64, t0: u32, t1: u32, size: u32| -> Option<[u32; 2]> {
        let lo = (c - e - 1.5).ceil();
        let hi = (c + e + 0.5).floor();
        let lo = lo.max(f64::from(t0) * TILE as f64).max(0.0);
        let hi = hi
            .min(f64::from(t1) * TILE as f64 + (TILE - 1) as f64)
            .min(f64::from(size) - 1.0);
        (lo <= hi).then_some([lo as u32, hi as u32])
    };
    let [x0, x1] = span(u, ex, pr.tiles[0], pr.tiles[1], width)?;
    let [y0, y1] = span(v, ey, pr.tiles[2], pr.tiles[3], height)?;
    Some(Splat {
        x,
        y,
        conic,
        opacity,
        color: pr.color.map(|c| c as f32),
        depth: pr.depth as f32,
        id: i as u32,
        rect: [x0, x1, y0, y1],
    })
}

/// Buckets the depth-ordered splats into tiles (a stable counting sort: each tile's list
/// stays front to back).
fn bin(s: &mut ViewState) {
    let tiles_y = s.height.div_ceil(TILE);
    let n_tiles = s.tiles_x * tiles_y;
    let mut count = vec![0usize; n_tiles + 1];
    for sp in &s.splats {
        let [x0, x1, y0, y1] = sp.rect.map(|v| v as usize / TILE);
        for ty in y0..=y1 {
            for tx in x0..=x1 {
                count[ty * s.tiles_x + tx + 1] += 1;
            }
        }
    }
    for t in 0..n_tiles {
        count[t + 1] += count[t];
    }
    s.entries.clear();
    s.entries.resize(count[n_tiles], 0);
    let mut fill = count.clone();
    for (k, sp) in s.splats.iter().enumerate() {
        let [x0, x1, y0, y1] = sp.rect.map(|v| v as usize / TILE);
        for ty in y0..=y1 {
            for tx in x0..=x1 {
                let t = ty * s.tiles_x + tx;
                s.entries[fill[t]] = k as u32;
                fill[t] += 1;
            }
        }
    }
    s.tile_start = count;
}

/// Per-pixel power and alpha of a splat exactly as splat-raster computes them; `None` when
/// the pixel is skipped (power > 0 or alpha < 1/255).
#[inline(always)]
fn alpha_at(sp: &Splat, px: f32, py: f32) -> Option<(f32, f32, f32, f32)> {
    let dx = sp.x - px;
    let dy = sp.y - py;
    let cdy = sp.conic[2] * dy * dy;
    let power = -0.5 * (sp.conic[0] * dx * dx + cdy) - sp.conic[1] * dx * dy;
    let g = exp(power);
    let alpha = (sp.opacity * g).min(ALPHA_MAX);
    (power <= 0.0 && alpha >= ALPHA_MIN).then_some((alpha, g, dx, dy))
}

#[inline(always)]
fn inside(sp: &Splat, x: u32, y: u32) -> bool {
    x >= sp.rect[0] && x <= sp.rect[1] && y >= sp.rect[2] && y <= sp.rect[3]
}

/// Renders `cam` into `state`: colour over background `bg`, and what [`backward`] needs.
pub fn forward(p: &Params, cam: &ViewCamera, bg: [f32; 3], state: &mut ViewState) {
    let (w, h) = (cam.width as usize, cam.height as usize);
    state.width = w;
    state.height = h;
    state.tiles_x = w.div_ceil(TILE);
    project_all(p, cam, cam.center(), &mut state.splats);
    bin(state);
    state.t_final.resize(w * h, 0.0);
    state.last.resize(w * h, 0);
    state.color.resize(w * h * 3, 0.0);
    let rows = TILE * w;
    let (splats, entries, starts, tiles_x) = (
        &state.splats,
        &state.entries,
        &state.tile_start,
        state.tiles_x,
    );
    state
        .t_final
        .par_chunks_mut(rows)
        .zip(state.last.par_chunks_mut(rows))
        .zip(state.color.par_chunks_mut(rows * 3))
        .enumerate()
        .for_each(|(ty, ((tf, la), co))| {
            for (i, ((t_out, l_out), c_out)) in tf
                .iter_mut()
                .zip(la.iter_mut())
                .zip(co.chunks_exact_mut(3))
                .enumerate()
            {
                let (x, y) = (i % w, ty * TILE + i / w);
                let tile = ty * tiles_x + x / TILE;
                let list = &entries[starts[tile]..starts[tile + 1]];
                let (t, n, c) = blend_pixel(splats, list, x as u32, y as u32);
                *t_out = t;
                *l_out = n;
                for ch in 0..3 {
                    c_out[ch] = c[ch] + t * bg[ch];
                }
            }
        });
}

/// Front-to-back blend of one pixel: (final T, list entries up to the last contributor,
/// colour without background).
#[inline]
fn blend_pixel(splats: &[Splat], list: &[u32], x: u32, y: u32) -> (f32, u32, [f32; 3]) {
    let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
    let mut t = 1.0f32;
    let mut c = [0.0f32; 3];
    let mut last = 0;
    for (k, &e) in list.iter().enumerate() {
        let sp = &splats[e as usize];
        if !inside(sp, x, y) {
            continue;
        }
        let Some((alpha, _, _, _)) = alpha_at(sp, px, py) else {
            continue;
        };
        let test_t = t * (1.0 - alpha);
        if test_t < T_MIN {
            break;
        }
        let w = alpha * t;
        for (c, col) in c.iter_mut().zip(sp.color) {
            *c += col * w;
        }
        t = test_t;
        last = k as u32 + 1;
    }
    (t, last, c)
}

/// Adds the gradient of a loss to `grads`, given `dl_dcolor` (`[H, W, 3]`, the loss's
/// gradient with respect to the colour of the last [`forward`] of `state`, which must
/// have rendered `p` from `cam` over `bg`).
pub fn backward(
    p: &Params,
    cam: &ViewCamera,
    bg: [f32; 3],
    state: &mut ViewState,
    dl_dcolor: &[f32],
    grads: &mut Grads,
) {
    pixel_backward(state, bg, dl_dcolor);
    reduce(state);
    let campos = cam.center();
    let per = rest_coeffs(p.sh_degree) * 3;
    let s = &*state;
    let param: Vec<(u32, project::ParamGrad, Vec<f64>)> = s
        .splats
        .par_iter()
        .zip(&s.splat_grads)
        .filter(|(_, g)| g.iter().any(|v| *v != 0.0))
        .map(|(sp, g)| {
            let mut rest = vec![0.0; if p.sh_degree > 0 { per } else { 0 }];
            let pg = project::backward(p, cam, campos, sp.id as usize, g, &mut rest);
            (sp.id, pg, rest)
        })
        .collect();
    for (id, pg, rest) in param {
        let i = id as usize;
        let add = |a: &mut [f64], b: &[f64]| a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
        add(&mut grads.means[i], &pg.mean);
        add(&mut grads.log_scales[i], &pg.log_scale);
        add(&mut grads.rotations[i], &pg.rotation);
        grads.opacity_logits[i] += pg.opacity_logit;
        add(&mut grads.sh_dc[i], &pg.sh_dc);
        if per > 0 {
            add(&mut grads.sh_rest[i * per..(i + 1) * per], &rest);
        }
    }
}

/// Per tile row in parallel: every pixel walks its contributors back to front and adds its
/// share to the entry slots of its tile.
fn pixel_backward(state: &mut ViewState, bg: [f32; 3], dl_dcolor: &[f32]) {
    let (w, tiles_x) = (state.width, state.tiles_x);
    state.entry_grads.clear();
    state.entry_grads.resize(state.entries.len(), [0.0; 9]);
    let starts = &state.tile_start;
    // Split the entry slots at tile-row boundaries.
    let mut rows_slots = Vec::new();
    let mut rest = &mut state.entry_grads[..];
    let tiles_y = state.height.div_ceil(TILE);
    for ty in 0..tiles_y {
        let len = starts[(ty + 1) * tiles_x] - starts[ty * tiles_x];
        let (a, b) = rest.split_at_mut(len);
        rows_slots.push(a);
        rest = b;
    }
    let (splats, entries) = (&state.splats, &state.entries);
    let (t_final, last) = (&state.t_final, &state.last);
    rows_slots
        .into_par_iter()
        .enumerate()
        .for_each(|(ty, slots)| {
            let base = starts[ty * tiles_x];
            let y0 = ty * TILE;
            let y1 = (y0 + TILE).min(state.height);
            for y in y0..y1 {
                for x in 0..w {
                    let pix = y * w + x;
                    let tile = ty * tiles_x + x / TILE;
                    let (s0, s1) = (starts[tile], starts[tile + 1]);
                    let n = last[pix] as usize;
                    let dc = [
                        dl_dcolor[pix * 3],
                        dl_dcolor[pix * 3 + 1],
                        dl_dcolor[pix * 3 + 2],
                    ];
                    if n == 0 || dc == [0.0; 3] {
                        continue;
                    }
                    let list = &entries[s0..s1][..n];
                    let slot = &mut slots[s0 - base..s1 - base];
                    pixel_grad(splats, list, slot, x as u32, y as u32, t_final[pix], bg, dc);
                }
            }
        });
}

/// One pixel's back-to-front pass (INRIA's `renderCUDA` backward): with R the colour
/// behind contributor j (later contributors plus T_final · bg), dC/dα_j = T_j c_j −
/// R / (1 − α_j) and dC/dc_j = T_j α_j; T_j is recovered as T_{j+1} / (1 − α_j).
#[allow(clippy::too_many_arguments)]
#[inline]
fn pixel_grad(
    splats: &[Splat],
    list: &[u32],
    slot: &mut [[f32; 9]],
    x: u32,
    y: u32,
    t_final: f32,
    bg: [f32; 3],
    dc: [f32; 3],
) {
    let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
    let mut t = t_final;
    let mut behind = [bg[0] * t, bg[1] * t, bg[2] * t];
    for k in (0..list.len()).rev() {
        let sp = &splats[list[k] as usize];
        if !inside(sp, x, y) {
            continue;
        }
        let Some((alpha, g, dx, dy)) = alpha_at(sp, px, py) else {
            continue;
        };
        let one_minus = 1.0 - alpha;
        let tj = t / one_minus;
        let w = alpha * tj;
        let mut d_alpha = 0.0;
        for ch in 0..3 {
            d_alpha += dc[ch] * (tj * sp.color[ch] - behind[ch] / one_minus);
            behind[ch] += w * sp.color[ch];
        }
        t = tj;
        let e = &mut slot[k];
        e[6] += w * dc[0];
        e[7] += w * dc[1];
        e[8] += w * dc[2];
        // alpha = min(0.99, o·G): the clamp passes no gradient.
        if sp.opacity * g >= ALPHA_MAX {
            continue;
        }
        e[5] += g * d_alpha;
        let d_power = alpha * d_alpha;
        let [a, b, c] = sp.conic;
        // power = −½(a dx² + c dy²) − b dx dy with dx = u − px, dy = v − py.
        e[0] += d_power * -(a * dx + b * dy);
        e[1] += d_power * -(c * dy + b * dx);
        e[2] += d_power * -0.5 * dx * dx;
        e[3] += d_power * -(dx * dy);
        e[4] += d_power * -0.5 * dy * dy;
    }
}

/// Sums each splat's entry slots in list order (tile-major), in f64.
fn reduce(state: &mut ViewState) {
    state.splat_grads.clear();
    state.splat_grads.resize(state.splats.len(), [0.0; 9]);
    for (e, g) in state.entries.iter().zip(&state.entry_grads) {
        let dst = &mut state.splat_grads[*e as usize];
        for (d, v) in dst.iter_mut().zip(g) {
            *d += f64::from(*v);
        }
    }
}

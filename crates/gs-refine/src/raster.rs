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
    /// splat-raster's per-row span terms: 2 a tau, a c − b², 1 / a (0: no spans, visit
    /// whole rectangle rows).
    two_a_tau: f32,
    det: f32,
    inv_a: f32,
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

    /// For every Gaussian drawn by the last forward, its id and the gradient of the loss
    /// with respect to its pixel centre (u, v) from the last [`backward`] (zero before).
    pub fn drawn_center_grads(&self) -> impl Iterator<Item = (u32, [f64; 2])> + '_ {
        self.splats.iter().enumerate().map(|(k, s)| {
            let g = self.splat_grads.get(k).map_or([0.0; 2], |g| [g[0], g[1]]);
            (s.id, g)
        })
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
    let [a, b, c] = conic;
    let det = a * c - b * b;
    let two_a_tau = 2.0 * a * tau as f32;
    let inv_a = 1.0 / a;
    let spans =
        a > 0.0 && det > 0.0 && det.is_finite() && two_a_tau.is_finite() && inv_a.is_finite();
    Some(Splat {
        two_a_tau,
        det,
        inv_a: if spans { inv_a } else { 0.0 },
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
            let mut tile = TileBuf::default();
            let y0 = ty * TILE;
            let y1 = (y0 + TILE).min(h);
            for tx in 0..tiles_x {
                let t = ty * tiles_x + tx;
                let x0 = tx * TILE;
                let r = [x0, (x0 + TILE).min(w), y0, y1];
                blend_tile(splats, &entries[starts[t]..starts[t + 1]], r, &mut tile);
                for y in y0..y1 {
                    for x in r[0]..r[1] {
                        let (i, o) = ((y - y0) * TILE + x - x0, (y - y0) * w + x);
                        tf[o] = tile.t[i];
                        la[o] = tile.last[i];
                        for ch in 0..3 {
                            co[o * 3 + ch] = tile.c[i][ch] + tile.t[i] * bg[ch];
                        }
                    }
                }
            }
        });
}

/// One tile's per-pixel state (tile-local, row-major 16 x 16).
#[derive(Debug)]
struct TileBuf {
    t: [f32; TILE * TILE],
    last: [u32; TILE * TILE],
    done: [bool; TILE * TILE],
    c: [[f32; 3]; TILE * TILE],
}

impl Default for TileBuf {
    fn default() -> Self {
        TileBuf {
            t: [1.0; TILE * TILE],
            last: [0; TILE * TILE],
            done: [false; TILE * TILE],
            c: [[0.0; 3]; TILE * TILE],
        }
    }
}

/// The pixels of `sp`'s rectangle inside the tile `[x0, x1) x [y0, y1)`, as inclusive
/// image ranges, or `None`.
#[inline(always)]
fn clip(sp: &Splat, [x0, x1, y0, y1]: [usize; 4]) -> Option<[usize; 4]> {
    let [rx0, rx1, ry0, ry1] = sp.rect.map(|v| v as usize);
    let (cx0, cx1) = (rx0.max(x0), rx1.min(x1 - 1));
    let (cy0, cy1) = (ry0.max(y0), ry1.min(y1 - 1));
    (cx0 <= cx1 && cy0 <= cy1).then_some([cx0, cx1, cy0, cy1])
}

/// Extra width, in pixels, of a row span beyond the solved ellipse bounds (splat-raster's
/// SPAN_SLACK): far above the f32 rounding of the bounds.
const SPAN_SLACK: f32 = 1.0 / 64.0;

/// The columns `cx0..=cx1` of row `y` that can have alpha >= 1/255 (splat-raster's
/// per-row span of the ellipse ½ dᵀ C d <= ln(255 o) + margin, a superset of those pixels).
#[inline(always)]
fn row_span(sp: &Splat, y: usize, cx0: usize, cx1: usize) -> Option<(usize, usize)> {
    if sp.inv_a <= 0.0 {
        return Some((cx0, cx1));
    }
    let dy = sp.y - (y as f32 + 0.5);
    let disc = sp.two_a_tau - sp.det * dy * dy;
    if disc.is_nan() || disc < 0.0 {
        return None;
    }
    let half = disc.sqrt() * sp.inv_a;
    let mid = sp.x - 0.5 + sp.conic[1] * dy * sp.inv_a;
    let (lo, hi) = (mid - half - SPAN_SLACK, mid + half + SPAN_SLACK);
    if hi < cx0 as f32 || lo > cx1 as f32 {
        return None;
    }
    let lo = if lo > cx0 as f32 {
        lo.ceil() as usize
    } else {
        cx0
    };
    let hi = (hi.floor() as usize).min(cx1);
    (lo <= hi).then_some((lo, hi))
}

/// Front-to-back blend of one tile, splat by splat over each splat's pixels (every pixel
/// still sees its contributors in list order, so the sums are splat-raster's).
fn blend_tile(splats: &[Splat], list: &[u32], r: [usize; 4], tb: &mut TileBuf) {
    *tb = TileBuf::default();
    let live = (r[1] - r[0]) * (r[3] - r[2]);
    let mut stopped = 0;
    for (k, &e) in list.iter().enumerate() {
        let sp = &splats[e as usize];
        let Some([cx0, cx1, cy0, cy1]) = clip(sp, r) else {
            continue;
        };
        for y in cy0..=cy1 {
            let py = y as f32 + 0.5;
            let Some((lo, hi)) = row_span(sp, y, cx0, cx1) else {
                continue;
            };
            for x in lo..=hi {
                let i = (y - r[2]) * TILE + x - r[0];
                if tb.done[i] {
                    continue;
                }
                let Some((alpha, _, _, _)) = alpha_at(sp, x as f32 + 0.5, py) else {
                    continue;
                };
                let t = tb.t[i];
                let test_t = t * (1.0 - alpha);
                if test_t < T_MIN {
                    tb.done[i] = true;
                    stopped += 1;
                    continue;
                }
                let w = alpha * t;
                for (c, col) in tb.c[i].iter_mut().zip(sp.color) {
                    *c += col * w;
                }
                tb.t[i] = test_t;
                tb.last[i] = k as u32 + 1;
            }
        }
        if stopped == live {
            break;
        }
    }
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

/// Per tile row in parallel: every tile walks its list back to front, each splat over its
/// pixels (those whose last contributor is at or after it), and writes the splat's summed
/// screen gradient into its entry slot.
fn pixel_backward(state: &mut ViewState, bg: [f32; 3], dl_dcolor: &[f32]) {
    let (w, h, tiles_x) = (state.width, state.height, state.tiles_x);
    state.entry_grads.clear();
    state.entry_grads.resize(state.entries.len(), [0.0; 9]);
    let starts = &state.tile_start;
    let mut rows_slots = Vec::new();
    let mut rest = &mut state.entry_grads[..];
    for ty in 0..h.div_ceil(TILE) {
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
            let mut tb = BackBuf::default();
            let y0 = ty * TILE;
            let y1 = (y0 + TILE).min(h);
            for tx in 0..tiles_x {
                let t = ty * tiles_x + tx;
                let x0 = tx * TILE;
                let r = [x0, (x0 + TILE).min(w), y0, y1];
                for y in y0..y1 {
                    for x in r[0]..r[1] {
                        let (i, o) = ((y - y0) * TILE + x - x0, y * w + x);
                        tb.t[i] = t_final[o];
                        tb.last[i] = last[o];
                        tb.dc[i] = [dl_dcolor[o * 3], dl_dcolor[o * 3 + 1], dl_dcolor[o * 3 + 2]];
                        tb.behind[i] = bg.map(|b| b * t_final[o]);
                    }
                }
                let (s0, s1) = (starts[t], starts[t + 1]);
                tile_grad(
                    splats,
                    &entries[s0..s1],
                    r,
                    &mut tb,
                    &mut slots[s0 - base..s1 - base],
                );
            }
        });
}

/// One tile's backward state per pixel.
#[derive(Debug)]
struct BackBuf {
    t: [f32; TILE * TILE],
    last: [u32; TILE * TILE],
    dc: [[f32; 3]; TILE * TILE],
    behind: [[f32; 3]; TILE * TILE],
}

impl Default for BackBuf {
    fn default() -> Self {
        BackBuf {
            t: [0.0; TILE * TILE],
            last: [0; TILE * TILE],
            dc: [[0.0; 3]; TILE * TILE],
            behind: [[0.0; 3]; TILE * TILE],
        }
    }
}

/// The back-to-front pass of one tile (INRIA's `renderCUDA` backward): with R the colour
/// behind contributor j (later contributors plus T_final · bg), dC/dα_j = T_j c_j −
/// R / (1 − α_j) and dC/dc_j = T_j α_j; T_j is recovered as T_{j+1} / (1 − α_j).
fn tile_grad(
    splats: &[Splat],
    list: &[u32],
    r: [usize; 4],
    tb: &mut BackBuf,
    slots: &mut [[f32; 9]],
) {
    for k in (0..list.len()).rev() {
        let sp = &splats[list[k] as usize];
        let Some([cx0, cx1, cy0, cy1]) = clip(sp, r) else {
            continue;
        };
        let mut e = [0.0f32; 9];
        let [a, b, c] = sp.conic;
        for y in cy0..=cy1 {
            let py = y as f32 + 0.5;
            let Some((lo, hi)) = row_span(sp, y, cx0, cx1) else {
                continue;
            };
            for x in lo..=hi {
                let i = (y - r[2]) * TILE + x - r[0];
                if k as u32 >= tb.last[i] {
                    continue;
                }
                let Some((alpha, g, dx, dy)) = alpha_at(sp, x as f32 + 0.5, py) else {
                    continue;
                };
                let one_minus = 1.0 - alpha;
                let tj = tb.t[i] / one_minus;
                let w = alpha * tj;
                let dc = tb.dc[i];
                let behind = &mut tb.behind[i];
                let mut d_alpha = 0.0;
                for ch in 0..3 {
                    d_alpha += dc[ch] * (tj * sp.color[ch] - behind[ch] / one_minus);
                    behind[ch] += w * sp.color[ch];
                }
                tb.t[i] = tj;
                e[6] += w * dc[0];
                e[7] += w * dc[1];
                e[8] += w * dc[2];
                // alpha = min(0.99, o·G): the clamp passes no gradient.
                if sp.opacity * g >= ALPHA_MAX {
                    continue;
                }
                e[5] += g * d_alpha;
                let d_power = alpha * d_alpha;
                // power = −½(a dx² + c dy²) − b dx dy with dx = u − px, dy = v − py.
                e[0] += d_power * -(a * dx + b * dy);
                e[1] += d_power * -(c * dy + b * dx);
                e[2] += d_power * -0.5 * dx * dx;
                e[3] += d_power * -(dx * dy);
                e[4] += d_power * -0.5 * dy * dy;
            }
        }
        slots[k] = e;
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

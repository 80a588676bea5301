//! Synthetic inputs with exact ground truth, for tests, examples and the benchmark: a plane
//! tiled by random Voronoi cells (jittered-lattice seeds), seen by views that slide along x
//! by `shift_frac` of the image width each. Every cell a view shows is one mask of that view,
//! so the true proposal of a mask is its world cell ([`Scene::truth`]). The warp of pair
//! (i, j) is the exact shift (plus optional uniform noise), in normalised coordinates, with
//! certainty in [0.6, 1] where the target lies inside view j and 0 elsewhere.

use profuse_formats::rng::{splitmix64 as mix, unit_from_bits};
use profuse_formats::{Floats, Labels, Masks, Matches, WarpCoords};

/// What to generate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Config {
    /// Number of views.
    pub views: usize,
    /// Image and mask width.
    pub width: usize,
    /// Image and mask height.
    pub height: usize,
    /// The warp grid is the image subsampled by this step (1 = one cell per pixel).
    pub grid_step: usize,
    /// Mean number of Voronoi cells (masks) per view.
    pub masks_per_view: usize,
    /// Horizontal shift between neighbouring views, as a fraction of the width.
    pub shift_frac: f64,
    /// Views i and j are paired (both directions) when 1 <= |i − j| <= neighbours.
    pub neighbours: usize,
    /// Amplitude (pixels) of uniform noise added to each warp target.
    pub warp_noise: f64,
    /// Seed of every random choice.
    pub seed: u64,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            views: 4,
            width: 64,
            height: 48,
            grid_step: 1,
            masks_per_view: 12,
            shift_frac: 1.0 / 6.0,
            neighbours: 1,
            warp_noise: 0.0,
            seed: 0,
        }
    }
}

/// Generated inputs and the truth.
#[derive(Debug, Clone)]
pub struct Scene {
    /// Label maps (U16 when every view has fewer than 65535 masks) and unit features [M, 1].
    pub masks: Masks,
    /// Warps of every neighbour pair in both directions, `coords = normalized`.
    pub matches: Matches,
    /// Per global mask: the id of the world cell it shows.
    pub truth: Vec<u32>,
}

/// A uniform number in [0, 1) hashed from a key by chained SplitMix64 steps, so that
/// every value is independent of evaluation order.
fn unit(seed: u64, a: u64, b: u64, c: u64) -> f64 {
    unit_from_bits(mix(mix(mix(mix(seed) ^ a) ^ b) ^ c))
}

/// The world: a jittered lattice of Voronoi seeds with spacing `s`.
struct World {
    seed: u64,
    s: f64,
    cols: i64,
}

impl World {
    fn seed_of(&self, cx: i64, cy: i64) -> (f64, f64) {
        let jx = 0.15 + 0.7 * unit(self.seed, 1, cx as u64, cy as u64);
        let jy = 0.15 + 0.7 * unit(self.seed, 2, cx as u64, cy as u64);
        ((cx as f64 + jx) * self.s, (cy as f64 + jy) * self.s)
    }

    /// Id of the Voronoi cell containing world point (x, y), x, y >= 0.
    fn cell(&self, x: f64, y: f64) -> u32 {
        let (cx, cy) = ((x / self.s).floor() as i64, (y / self.s).floor() as i64);
        let mut best = (f64::INFINITY, 0i64, 0i64);
        for dy in -1..=1 {
            for dx in -1..=1 {
                let (sx, sy) = self.seed_of(cx + dx, cy + dy);
                let d = (sx - x).powi(2) + (sy - y).powi(2);
                if d < best.0 {
                    best = (d, cx + dx, cy + dy);
                }
            }
        }
        ((best.2 + 1) * self.cols + best.1 + 1) as u32
    }
}

/// Generates a scene.
pub fn scene(cfg: &Config) -> Scene {
    let (w, h) = (cfg.width.max(1), cfg.height.max(1));
    let shift = cfg.shift_frac * w as f64;
    // Lattice spacing s such that the cells a view shows, about W·H/s² inside plus
    // (W + H)/s cut by the border, number `masks_per_view`.
    let (wf, hf, n) = (w as f64, h as f64, cfg.masks_per_view.max(1) as f64);
    let u = (-(wf + hf) + ((wf + hf).powi(2) + 4.0 * wf * hf * n).sqrt()) / (2.0 * wf * hf);
    let s = 1.0 / u;
    let world_width = w as f64 + shift * cfg.views.saturating_sub(1) as f64;
    let world = World {
        seed: cfg.seed,
        s,
        cols: (world_width / s).ceil() as i64 + 3,
    };
    let mut labels: Vec<u32> = Vec::with_capacity(cfg.views * w * h);
    let mut offsets = vec![0u32];
    let mut truth = Vec::new();
    for v in 0..cfg.views {
        let mut local: Vec<u32> = Vec::new();
        let mut cache: std::collections::HashMap<u32, u32> = std::collections::HashMap::new();
        for y in 0..h {
            for x in 0..w {
                let id = world.cell(x as f64 + 0.5 + v as f64 * shift, y as f64 + 0.5);
                let l = *cache.entry(id).or_insert_with(|| {
                    local.push(id);
                    (local.len() - 1) as u32
                });
                labels.push(l);
            }
        }
        truth.extend_from_slice(&local);
        offsets.push(truth.len() as u32);
    }
    let wide = offsets
        .windows(2)
        .any(|o| o[1] - o[0] >= u32::from(u16::MAX));
    let labels = if wide {
        Labels::U32(labels.into())
    } else {
        Labels::U16(
            labels
                .iter()
                .map(|l| *l as u16)
                .collect::<Vec<u16>>()
                .into(),
        )
    };
    let masks = Masks {
        view_names: (0..cfg.views).map(|v| format!("view_{v:04}.png")).collect(),
        width: w,
        height: h,
        labels,
        mask_offsets: offsets.into(),
        features: Floats::F32(vec![1.0f32; truth.len()].into()),
        dim: 1,
        extra: Default::default(),
    };
    Scene {
        matches: matches(cfg, w, h, shift),
        masks,
        truth,
    }
}

fn matches(cfg: &Config, w: usize, h: usize, shift: f64) -> Matches {
    let step = cfg.grid_step.max(1);
    let (gw, gh) = (w.div_ceil(step), h.div_ceil(step));
    let mut pairs = Vec::new();
    for i in 0..cfg.views {
        for j in 0..cfg.views {
            if i != j && i.abs_diff(j) <= cfg.neighbours {
                pairs.push([i as u32, j as u32]);
            }
        }
    }
    let mut warp = Vec::with_capacity(pairs.len() * gw * gh * 2);
    let mut certainty = Vec::with_capacity(pairs.len() * gw * gh);
    for (p, &[i, j]) in pairs.iter().enumerate() {
        let dx = (f64::from(i) - f64::from(j)) * shift;
        for y in 0..gh {
            for x in 0..gw {
                let key = ((p * gh + y) * gw + x) as u64;
                let u = (x as f64 + 0.5) * w as f64 / gw as f64;
                let v = (y as f64 + 0.5) * h as f64 / gh as f64;
                let nx = cfg.warp_noise * (2.0 * unit(cfg.seed, 3, key, 0) - 1.0);
                let ny = cfg.warp_noise * (2.0 * unit(cfg.seed, 3, key, 1) - 1.0);
                let (tu, tv) = (u + dx + nx, v + ny);
                warp.push((2.0 * tu / w as f64 - 1.0) as f32);
                warp.push((2.0 * tv / h as f64 - 1.0) as f32);
                let inside = (0.0..=w as f64).contains(&tu) && (0.0..=h as f64).contains(&tv);
                certainty.push(if inside {
                    (0.6 + 0.4 * unit(cfg.seed, 4, key, 0)) as f32
                } else {
                    0.0
                });
            }
        }
    }
    Matches {
        num_views: cfg.views,
        pairs: pairs.into(),
        height: gh,
        width: gw,
        warp: Floats::F32(warp.into()),
        certainty: Floats::F32(certainty.into()),
        coords: WarpCoords::Normalized,
        extra: Default::default(),
    }
}

//! Per-view activation maps A_i(p) = Σ_t ω_{i,p,t} · 1[g_{i,p,t} active] over the top-K
//! contributors of each pixel (paper §4.2), for many prompts in one pass.

use rayon::prelude::*;
use splat_raster::NO_GAUSSIAN;

use crate::error::{QueryError, Result};
use crate::select::ActiveSet;

/// Which prompts each Gaussian is active for: one bit per prompt, ⌈Q/8⌉ bytes per
/// Gaussian (one byte for up to 8 prompts, so a million Gaussians take 1 MB and the
/// random lookups of a top-K pass stay in cache), so one pass over a view's top-K buffer
/// serves every prompt.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Membership {
    gaussians: usize,
    prompts: usize,
    bytes: usize,
    bits: Vec<u8>,
}

impl Membership {
    /// The membership of `gaussians` Gaussians in each of `sets` (prompt q = `sets[q]`).
    /// Ids outside the Gaussian set are ignored.
    pub fn new(gaussians: usize, sets: &[&ActiveSet]) -> Membership {
        let prompts = sets.len();
        let bytes = prompts.div_ceil(8).max(1);
        let mut bits = vec![0u8; gaussians * bytes];
        for (q, set) in sets.iter().enumerate() {
            for &g in &set.ids {
                if let Some(b) = bits.get_mut(g as usize * bytes + q / 8) {
                    *b |= 1 << (q % 8);
                }
            }
        }
        Membership {
            gaussians,
            prompts,
            bytes,
            bits,
        }
    }

    /// Number of prompts.
    pub fn prompts(&self) -> usize {
        self.prompts
    }

    /// Number of Gaussians.
    pub fn gaussians(&self) -> usize {
        self.gaussians
    }

    /// Whether Gaussian `g` is active for prompt `q`.
    pub fn is_active(&self, g: usize, q: usize) -> bool {
        q < self.prompts
            && self
                .bits
                .get(g * self.bytes + q / 8)
                .is_some_and(|b| b >> (q % 8) & 1 == 1)
    }

    fn bytes_of(&self, g: u32) -> Option<&[u8]> {
        let start = (g as usize).checked_mul(self.bytes)?;
        self.bits.get(start..start + self.bytes)
    }
}

/// The activation of every pixel of one view for every prompt.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Activation {
    width: usize,
    height: usize,
    prompts: usize,
    /// [H·W, Q]: pixel-major, prompt-minor.
    values: Vec<f32>,
}

impl Activation {
    /// Image width.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Image height.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Number of prompts.
    pub fn prompts(&self) -> usize {
        self.prompts
    }

    /// A(p) of prompt `q` at pixel (`x`, `y`).
    pub fn get(&self, q: usize, x: usize, y: usize) -> f32 {
        self.values[(y * self.width + x) * self.prompts + q]
    }

    /// The activation map of prompt `q`, row-major [H, W].
    pub fn map(&self, q: usize) -> Vec<f32> {
        self.values
            .iter()
            .skip(q)
            .step_by(self.prompts.max(1))
            .copied()
            .collect()
    }

    /// The binary mask 1[A >= γ] of prompt `q` as 8-bit grey values (255 = selected),
    /// row-major [H, W].
    pub fn mask(&self, q: usize, gamma: f32) -> Vec<u8> {
        self.values
            .iter()
            .skip(q)
            .step_by(self.prompts.max(1))
            .map(|a| if *a >= gamma { 255 } else { 0 })
            .collect()
    }
}

/// Computes the activation of every prompt of `membership` from a view's top-K buffers
/// (`ids`, `weights`: [H, W, K] as `splat_raster::ViewRender` holds them). Each pixel's
/// sum runs over its slots in order (f32), so it equals a plain loop over the slots.
/// Padding slots ([`NO_GAUSSIAN`]) and ids outside the Gaussian set contribute nothing.
pub fn activation(
    ids: &[u32],
    weights: &[f32],
    width: usize,
    height: usize,
    k: usize,
    membership: &Membership,
) -> Result<Activation> {
    let pixels = width * height;
    if k == 0 || ids.len() != pixels * k || weights.len() != pixels * k {
        return Err(QueryError::BadParameter {
            name: "k",
            value: format!(
                "{k} (ids {}, weights {} values for {width}x{height} pixels)",
                ids.len(),
                weights.len()
            ),
            expected: "K >= 1 and top-K buffers of H x W x K values",
        });
    }
    let q = membership.prompts;
    let mut values = vec![0.0f32; pixels * q];
    if q > 0 && width > 0 {
        values
            .par_chunks_mut(width * q)
            .zip(ids.par_chunks(width * k).zip(weights.par_chunks(width * k)))
            .for_each(|(row, (row_ids, row_weights))| {
                accumulate_row(row, row_ids, row_weights, k, membership);
            });
    }
    Ok(Activation {
        width,
        height,
        prompts: q,
        values,
    })
}

fn accumulate_row(out: &mut [f32], ids: &[u32], weights: &[f32], k: usize, m: &Membership) {
    let q = m.prompts;
    for ((acc, pid), pw) in out
        .chunks_exact_mut(q)
        .zip(ids.chunks_exact(k))
        .zip(weights.chunks_exact(k))
    {
        for (&g, &w) in pid.iter().zip(pw) {
            if g == NO_GAUSSIAN {
                continue;
            }
            let Some(bytes) = m.bytes_of(g) else {
                continue;
            };
            for (bi, &byte) in bytes.iter().enumerate() {
                let mut bits = byte;
                while bits != 0 {
                    let b = bits.trailing_zeros() as usize;
                    acc[bi * 8 + b] += w;
                    bits &= bits - 1;
                }
            }
        }
    }
}

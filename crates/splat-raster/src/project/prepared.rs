//! View-independent per-Gaussian data (3D covariance, opacity, footprint threshold), stored in
//! the Morton order of the means, with the bounds of the group pre-cull.

use super::*;

/// View-independent data of every Gaussian, stored by *slot*: the Gaussians in the Morton
/// order of their means ([`spatial_order`]), not in id order.
///
/// Why: a tile's splats are the Gaussians near one line of sight, and the blend reads each
/// of them from the view's splat buffer, which projection fills in slot order. In id order
/// (whatever order the file has: a synthetic scene's or a densified one's is spatially
/// random) those reads are scattered over the whole buffer and stall on memory; in Morton
/// order a tile's splats lie in a few runs. Depth ties are still broken by id
/// (`sort_by_depth`), so the slot order changes no output bit.
#[derive(Debug, Clone)]
pub(crate) struct Prepared {
    /// The key of each slot in the spatial order: Morton code above the Gaussian id (see
    /// [`Prepared::id`]). Kept whole rather than narrowed to the ids: freeing the sort's
    /// key buffer raised glibc's dynamic mmap threshold, and fuse bench's peak RSS by
    /// ~100 MB (later mid-size buffers came from the heap and stayed).
    pub order: Vec<u64>,
    /// The mean of each slot's Gaussian.
    pub means: Vec<[f32; 3]>,
    /// Upper triangle of Σ = R S Sᵀ Rᵀ: xx, xy, xz, yy, yz, zz.
    pub cov3d: Vec<[f64; 6]>,
    /// sigmoid(opacity logit).
    pub opacity: Vec<f64>,
    /// ln(255 · opacity) + [`TAU_MARGIN`]: the footprint bound of [`Splat::new`], view
    /// independent, so computed once here rather than once per view.
    pub tau: Vec<f64>,
    /// An upper bound on the largest eigenvalue of Σ (the largest scale², with a margin,
    /// see [`var_bound`]) for the off-image pre-cull of [`project_chunk`], or
    /// [`NEVER_DRAWN`] where the single-precision opacity is NaN or below 1/255 (such a
    /// Gaussian never becomes a [`Splat`] in any view).
    pub var_max: Vec<f32>,
    /// The colour as a [`Splat`] holds it when it is view independent (SH degree 0): what
    /// [`eval_sh`] returns, in single precision. Empty for SH degree > 0.
    pub color0: Vec<[f32; 3]>,
    /// The bounds of each run of [`CULL_GROUP`] slots (the last one may be shorter) for
    /// the per-view group cull of [`project_chunk`].
    pub groups: Vec<CullGroup>,
}

/// Slots per [`CullGroup`]: 8 projection batches. The slots are in Morton order, so a
/// group's Gaussians lie close together and a view often sees all or none of them.
pub(crate) const CULL_GROUP: usize = 64;

/// A bounding sphere of the means of a run of slots and the largest variance bound of
/// those that may be drawn, from which one test per view tells that no Gaussian of the run
/// can become a [`Splat`] ([`ViewConsts::group_culled`]).
#[derive(Debug, Clone, Copy)]
pub(crate) struct CullGroup {
    pub(super) center: [f64; 3],
    /// At least the distance of every mean from `center`.
    pub(super) radius: f64,
    /// The largest [`Prepared::var_max`] of the run's Gaussians that may be drawn (NaN
    /// if one is NaN, -1 if none may be drawn).
    pub(super) var_max: f64,
}

impl CullGroup {
    pub(super) fn new(means: &[[f32; 3]], var_max: &[f32]) -> Self {
        let (lo, hi) = means.iter().fold(
            ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]),
            |(lo, hi), m| {
                let m = m.map(f64::from);
                (
                    std::array::from_fn(|a| lo[a].min(m[a])),
                    std::array::from_fn(|a| hi[a].max(m[a])),
                )
            },
        );
        let center: [f64; 3] = std::array::from_fn(|a| 0.5 * (lo[a] + hi[a]));
        let radius = means
            .iter()
            .map(|m| {
                let d: [f64; 3] = std::array::from_fn(|a| f64::from(m[a]) - center[a]);
                (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
            })
            .fold(0.0, f64::max);
        let var_max = var_max
            .iter()
            .filter(|&&v| may_be_drawn(v))
            .map(|&v| f64::from(v))
            .fold(f64::from(NEVER_DRAWN), |a, v| {
                if a.is_nan() || v.is_nan() {
                    f64::NAN
                } else {
                    a.max(v)
                }
            });
        CullGroup {
            center,
            // The rounding of the distances is ~1e-16 relative; the test's margin is far
            // wider, and this one keeps the bound a bound by itself.
            radius: radius * (1.0 + 1e-12),
            var_max,
        }
    }
}

/// [`Prepared::var_max`] of a Gaussian that is never drawn.
pub(super) const NEVER_DRAWN: f32 = -1.0;

/// Whether a [`Prepared::var_max`] is not [`NEVER_DRAWN`] (not negative).
#[inline(always)]
pub(super) fn may_be_drawn(var_max: f32) -> bool {
    (var_max >= 0.0) | var_max.is_nan()
}

/// Checks what `prepare` (and so `Rasterizer::new`) requires of the Gaussians, without
/// preparing anything: consistent lengths, SH degree <= 3, finite means, log-scales,
/// rotations and SH, no zero quaternion, no NaN opacity logit (±inf is allowed).
pub fn check_gaussians(g: &Gaussians) -> Result<()> {
    let n = g.len();
    let check_len = |field: &'static str, got: usize, expected: usize| {
        if got == expected {
            Ok(())
        } else {
            Err(RasterError::InconsistentGaussians {
                field,
                got,
                expected,
            })
        }
    };
    check_len("log_scales", g.log_scales.len(), n)?;
    check_len("rotations", g.rotations.len(), n)?;
    check_len("opacity_logits", g.opacity_logits.len(), n)?;
    check_len("sh_dc", g.sh_dc.len(), n)?;
    if g.sh_degree > 3 {
        return Err(RasterError::InconsistentGaussians {
            field: "sh_degree",
            got: g.sh_degree,
            expected: 3,
        });
    }
    let rest_len = g.sh_rest.as_ref().map_or(0, |r| r.len());
    check_len("sh_rest", rest_len, n * g.sh_rest_coeffs() * 3)?;

    let non_finite = |index: usize, field: &'static str, value: String| {
        Err(RasterError::NonFiniteGaussian {
            index,
            field,
            value,
        })
    };
    for i in 0..n {
        if !g.means[i].iter().all(|v| v.is_finite()) {
            return non_finite(i, "means", format!("{:?}", g.means[i]));
        }
        if !g.log_scales[i].iter().all(|v| v.is_finite()) {
            return non_finite(i, "log_scales", format!("{:?}", g.log_scales[i]));
        }
        if !g.rotations[i].iter().all(|v| v.is_finite()) {
            return non_finite(i, "rotations", format!("{:?}", g.rotations[i]));
        }
        if g.rotations[i].iter().all(|v| *v == 0.0) {
            return Err(RasterError::ZeroRotation { index: i });
        }
        if g.opacity_logits[i].is_nan() {
            return non_finite(i, "opacity_logits", "NaN".into());
        }
        if !g.sh_dc[i].iter().all(|v| v.is_finite()) {
            return non_finite(i, "sh_dc", format!("{:?}", g.sh_dc[i]));
        }
    }
    if let Some(rest) = &g.sh_rest {
        let per = g.sh_rest_coeffs() * 3;
        if let Some(pos) = rest.iter().position(|v| !v.is_finite()) {
            return non_finite(pos / per, "sh_rest", format!("{}", rest[pos]));
        }
    }
    Ok(())
}

pub(crate) fn prepare(g: &Gaussians) -> Result<Prepared> {
    check_gaussians(g)?;
    let order = spatial_order(&g.means);
    let by_slot = || order.iter().map(|&k| key_id(k) as usize);
    let cov3d = by_slot()
        .map(|i| covariance_3d(g.log_scales[i], g.rotations[i]))
        .collect();
    let opacity: Vec<f64> = by_slot().map(|i| opacity_of(g.opacity_logits[i])).collect();
    let tau = opacity.iter().map(|&o| footprint_tau(o)).collect();
    let var_max: Vec<f32> = by_slot()
        .zip(&opacity)
        .map(|(i, &o)| {
            let o = o as f32;
            if o.is_nan() || o < ALPHA_MIN {
                NEVER_DRAWN
            } else {
                var_bound(g.log_scales[i])
            }
        })
        .collect();
    let color0 = if g.sh_degree == 0 {
        // Degree 0 ignores the direction (see `eval_sh`); any unit vector will do.
        by_slot()
            .map(|i| eval_sh(0, g.sh_dc[i], &[], [0.0, 0.0, 1.0]).map(|x| x as f32))
            .collect()
    } else {
        Vec::new()
    };
    let means: Vec<[f32; 3]> = by_slot().map(|i| g.means[i]).collect();
    let groups = means
        .chunks(CULL_GROUP)
        .zip(var_max.chunks(CULL_GROUP))
        .map(|(m, v)| CullGroup::new(m, v))
        .collect();
    Ok(Prepared {
        means,
        order,
        cov3d,
        opacity,
        tau,
        var_max,
        color0,
        groups,
    })
}

/// Bits per axis of the Morton code of [`spatial_order`]: 1024 cells per axis of the
/// scene's bounding box, far finer than a tile's share of a scene.
pub(super) const MORTON_BITS: u32 = 10;

/// The keys (Morton code << 32 | id) of the Gaussians in ascending order, i.e. the ids in
/// the Morton (Z-curve) order of their means, quantised to [`MORTON_BITS`] per axis over the
/// means' bounding box, equal codes by id. The means are finite ([`prepare`] checked them).
/// Deterministic: every key is unique.
pub(crate) fn spatial_order(means: &[[f32; 3]]) -> Vec<u64> {
    let (lo, hi) = means.iter().fold(
        ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]),
        |(lo, hi), m| {
            (
                std::array::from_fn(|a| lo[a].min(m[a])),
                std::array::from_fn(|a| hi[a].max(m[a])),
            )
        },
    );
    let cells = (1u32 << MORTON_BITS) as f64;
    let quantise = |a: usize, x: f32| -> u64 {
        let extent = f64::from(hi[a]) - f64::from(lo[a]);
        if extent > 0.0 {
            // In [0, cells) up to the rounding at the top end, which the min catches.
            ((f64::from(x) - f64::from(lo[a])) / extent * cells).min(cells - 1.0) as u64
        } else {
            0
        }
    };
    let mut keys: Vec<u64> = means
        .iter()
        .enumerate()
        .map(|(i, m)| {
            let code = (0..3).fold(0u64, |c, a| c | (spread_bits(quantise(a, m[a])) << a));
            (code << 32) | i as u64
        })
        .collect();
    keys.sort_unstable();
    keys
}

/// The Gaussian id of a [`spatial_order`] key.
pub(crate) fn key_id(key: u64) -> u32 {
    key as u32
}

impl Prepared {
    /// The Gaussian id of slot `slot`.
    #[inline(always)]
    pub fn id(&self, slot: usize) -> u32 {
        key_id(self.order[slot])
    }
}

/// The low [`MORTON_BITS`] bits of `x` moved to every third bit (bit j to bit 3j).
pub(super) fn spread_bits(x: u64) -> u64 {
    (0..MORTON_BITS).fold(0, |s, j| s | (((x >> j) & 1) << (3 * j)))
}

/// sigmoid(logit) in double precision: the opacity of [`Prepared`] and [`project`].
pub(super) fn opacity_of(logit: f32) -> f64 {
    1.0 / (1.0 + (-f64::from(logit)).exp())
}

/// An upper bound on the largest eigenvalue of the Σ that [`covariance_3d`] computes from
/// these log-scales: exp(2 max log s). Σ = R S² Rᵀ with R orthonormal up to rounding, so
/// its eigenvalues are the s_j² up to a relative error of a few 1e-16; rounding the bound
/// to f32 loses at most 6e-8 relative. Both are covered by the 1e-6 margin of
/// [`ViewConsts::cull_gain`]. Huge scales give +inf: never pre-culled.
pub(super) fn var_bound(log_scales: [f32; 3]) -> f32 {
    let l = log_scales
        .iter()
        .fold(f64::NEG_INFINITY, |m, &l| m.max(f64::from(l)));
    (2.0 * l).exp() as f32
}

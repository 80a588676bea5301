//! The batched projection of a chunk of slots: vector-width batches (AVX-512 or portable) of
//! lanes, their prefetches, and each kept lane emitted as a splat.

use super::*;

/// Projects the Gaussians in [`Prepared`] slots `slots` into the camera of `view` and
/// appends, in slot order, the [`Splat`] of each one that [`project`] followed by
/// [`Splat::new`] keeps: bit for bit the same values (the same operations in the same
/// order; the unit tests compare the two paths), for less work: per-view constants are
/// computed once ([`ViewConsts`]), runs of [`CULL_GROUP`] slots wholly behind the camera or
/// beside the image are skipped after one test per run ([`ViewConsts::group_culled`]),
/// Gaussians far off the image are rejected by a conservative bound before the EWA
/// projection (see [`ViewConsts::surely_off_grid`]),
/// degree-0 colours come from [`Prepared::color0`], no colour at all is evaluated when the
/// view is not shaded (the splats then carry black: a render without a colour output never
/// reads it, and spherical harmonics of degree 3 cost several times the rest of the
/// projection), no [`Projected`] is built, and the Gaussians go through the arithmetic
/// [`BATCH`] at a time, lane by lane without branches (see [`ViewConsts::project_lanes`]),
/// which the compiler turns into vector instructions: 8 lanes with AVX-512 where `level`
/// has it, 2 with SSE2 otherwise. Every lane performs the IEEE double-precision operations
/// of the scalar formula, so the width changes no bit.
pub(crate) fn project_chunk(
    view: &ViewConsts,
    g: &Gaussians,
    prep: &Prepared,
    slots: Range<usize>,
    level: Level,
    out: &mut impl SplatSink,
) {
    let tail = match level {
        Level::Portable => project_batches(view, g, prep, slots.clone(), out),
        // SAFETY: `Level::Avx512` is only made after `Level::detect` found AVX-512 F and DQ
        // on this CPU, which is all `project_batches_avx512` needs.
        #[cfg(target_arch = "x86_64")]
        #[allow(unsafe_code)]
        Level::Avx512 => unsafe { project_batches_avx512(view, g, prep, slots.clone(), out) },
    };
    for i in tail..slots.end {
        let mut lane = ProjectedLanes::<1>::default();
        view.project_lanes(prep, i, &mut lane);
        lane.emit(view, g, prep, i, out);
    }
}

/// Gaussians per batch of [`project_chunk`]: one AVX-512 vector of f64.
pub(super) const BATCH: usize = 8;

/// [`project_batches`] compiled for AVX-512, where its lane loops become 8-lane vectors.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq")]
pub(super) fn project_batches_avx512(
    view: &ViewConsts,
    g: &Gaussians,
    prep: &Prepared,
    slots: Range<usize>,
    out: &mut impl SplatSink,
) -> usize {
    project_batches(view, g, prep, slots, out)
}

/// Projects the whole batches of `slots`; returns where the remainder (fewer than [`BATCH`]
/// Gaussians) starts.
#[inline(always)]
pub(super) fn project_batches(
    view: &ViewConsts,
    g: &Gaussians,
    prep: &Prepared,
    slots: Range<usize>,
    out: &mut impl SplatSink,
) -> usize {
    let mut first = slots.start;
    let mut lanes = ProjectedLanes::<BATCH>::default();
    let harmonics = view.shade && prep.color0.is_empty();
    // The group of the last batch tested and whether the view culls it.
    let mut culled = (usize::MAX, false);
    while first + BATCH <= slots.end {
        if harmonics {
            prefetch_harmonics(
                g,
                prep,
                first + SH_PREFETCH_AHEAD..first + SH_PREFETCH_AHEAD + BATCH,
            );
        }
        let group = first / CULL_GROUP;
        if group == (first + BATCH - 1) / CULL_GROUP {
            if culled.0 != group {
                culled = (
                    group,
                    prep.groups.get(group).is_some_and(|c| view.group_culled(c)),
                );
            }
            if culled.1 {
                first += BATCH;
                continue;
            }
        }
        // A batch of Gaussians that are never drawn (zero opacity) costs nothing.
        if prep.var_max[first..first + BATCH]
            .iter()
            .any(|&v| may_be_drawn(v))
        {
            view.project_lanes(prep, first, &mut lanes);
            lanes.emit(view, g, prep, first, out);
        }
        first += BATCH;
    }
    first
}

/// Slots ahead of the batch being projected whose spherical harmonics are prefetched.
pub(super) const SH_PREFETCH_AHEAD: usize = 8 * BATCH;

/// Asks for the colour coefficients of the Gaussians in `slots` (those beyond the slots
/// are ignored). They are stored in id order, which the slot order scatters over the whole
/// file: without the hint each Gaussian's colour waited on a few cache misses, and the
/// colour took most of a shaded projection's time.
#[inline(always)]
pub(super) fn prefetch_harmonics(g: &Gaussians, prep: &Prepared, slots: Range<usize>) {
    let per = g.sh_rest_coeffs() * 3;
    let rest = g.sh_rest.as_deref().unwrap_or(&[]);
    for slot in slots.take_while(|&s| s < prep.order.len()) {
        let id = prep.id(slot) as usize;
        if let Some(dc) = g.sh_dc.get(id) {
            prefetch(dc);
        }
        if let Some(row) = rest.get(id * per..(id + 1) * per) {
            // One hint per 64-byte line the row touches (16 floats), and its last one.
            for c in row.iter().step_by(16).chain(row.last()) {
                prefetch(c);
            }
        }
    }
}

/// What [`ViewConsts::project_lanes`] computes for `L` consecutive Gaussians, lane l for
/// the l-th: whether [`project`] + [`Splat::new`] keep it, and the values of its
/// [`Splat`] (meaningless in lanes that are not kept).
#[derive(Debug, Clone, Copy)]
pub(super) struct ProjectedLanes<const L: usize> {
    pub(super) keep: [bool; L],
    /// The f64 intermediates: centre, depth, 2D covariance, conic, radius.
    pub(super) u: [f64; L],
    pub(super) v: [f64; L],
    pub(super) z: [f64; L],
    pub(super) cov2d: [[f64; L]; 3],
    pub(super) conic: [[f64; L]; 3],
    pub(super) radius: [f64; L],
    /// Tile range tx0, tx1, ty0, ty1.
    pub(super) tiles: [[u32; L]; 4],
    /// The single-precision conic a, b, c, its det, 2 a tau and the inverse of a (0 when
    /// the spans cannot be trusted).
    pub(super) abc: [[f32; L]; 3],
    pub(super) det: [f32; L],
    pub(super) two_a_tau: [f32; L],
    pub(super) inv_a: [f32; L],
    /// Pixel rectangle x0, x1, y0, y1.
    pub(super) rect: [[u16; L]; 4],
}

impl<const L: usize> Default for ProjectedLanes<L> {
    fn default() -> Self {
        ProjectedLanes {
            keep: [false; L],
            u: [0.0; L],
            v: [0.0; L],
            z: [0.0; L],
            cov2d: [[0.0; L]; 3],
            conic: [[0.0; L]; 3],
            radius: [0.0; L],
            tiles: [[0; L]; 4],
            abc: [[0.0; L]; 3],
            det: [0.0; L],
            two_a_tau: [0.0; L],
            inv_a: [0.0; L],
            rect: [[0; L]; 4],
        }
    }
}

impl<const L: usize> ProjectedLanes<L> {
    /// Appends the [`Splat`] of every kept lane (Gaussian `first + l`), in lane order;
    /// black unless `view` is shaded.
    #[inline(always)]
    pub(super) fn emit(
        &self,
        view: &ViewConsts,
        g: &Gaussians,
        prep: &Prepared,
        first: usize,
        out: &mut impl SplatSink,
    ) {
        for l in 0..L {
            if !self.keep[l] {
                continue;
            }
            let i = first + l;
            let id = prep.id(i);
            let color = match prep.color0.get(i) {
                _ if !view.shade => [0.0; 3],
                Some(c) => *c,
                None => {
                    let mean = prep.means[i].map(f64::from);
                    sh_color(g, view.campos, id as usize, mean).map(|x| x as f32)
                }
            };
            #[cfg(test)]
            tests::trace(Projected {
                id,
                center: [self.u[l], self.v[l]],
                depth: self.z[l],
                cov2d: self.cov2d.map(|c| c[l]),
                conic: self.conic.map(|c| c[l]),
                radius: self.radius[l],
                tiles: self.tiles.map(|t| t[l]),
                color: [0.0; 3], // compared as the splat's f32 colour
                opacity: prep.opacity[i],
            });
            let [a, b, c] = self.abc.map(|v| v[l]);
            out.push(
                i,
                Splat {
                    x: self.u[l] as f32,
                    y: self.v[l] as f32,
                    a,
                    b,
                    c,
                    opacity: prep.opacity[i] as f32,
                    color,
                    depth: self.z[l] as f32,
                    id,
                    two_a_tau: self.two_a_tau[l],
                    det: self.det[l],
                    inv_a: self.inv_a[l],
                    rect: self.rect.map(|r| r[l]),
                },
            );
        }
    }
}

//! Step 1 for one tile: its hits summed per (Gaussian, group) and its masks' masses, through
//! the dense (position, group) array where the rasterizer hands out list positions, else
//! through the tile's hash table.

use super::*;

impl ViewContext<'_> {
    /// Step 1 for one tile: adds the masses of its pixels' masks to `out.mass` and its
    /// hits summed per (Gaussian, group) to `out.records`. A problem is recorded in
    /// `out.error` (the row then stops adding).
    pub(crate) fn sum_tile(&self, tile: &TileHits<'_>, out: &mut RowOutput) {
        match self.labels {
            LabelPlane::U16(labels) => self.sum_tile_with(labels, tile, out),
            LabelPlane::U32(labels) => self.sum_tile_with(labels, tile, out),
        }
    }

    fn sum_tile_with<L: Label>(&self, labels: &[L], tile: &TileHits<'_>, out: &mut RowOutput) {
        let groups = self.groups;
        if out.error.is_some() {
            return;
        }
        if out.mass.len() != groups.len() {
            out.mass.clear();
            out.mass.resize(groups.len(), 0);
        }
        let (k, width) = (self.k, self.width);
        if tile.x0 + tile.width > width || tile.y0 + tile.height > self.height {
            out.error = Some(format!(
                "tile at ({}, {}) of {}x{} pixels is outside the {width}x{} mask grid",
                tile.x0, tile.y0, tile.width, tile.height, self.height
            ));
            return;
        }
        if let Some(positions) = tile.positions {
            if self.sum_tile_dense(labels, tile, positions, out) {
                return;
            }
        }
        let table = &mut out.table;
        for row in 0..tile.height {
            let y = tile.y0 + row;
            for col in 0..tile.width {
                let Some(local) = labels
                    .get(y * width + tile.x0 + col)
                    .and_then(|l| l.local())
                else {
                    continue;
                };
                let Some(&group) = groups.get(local) else {
                    out.error = Some(format!(
                        "label {local} is beyond the view's {} masks",
                        groups.len()
                    ));
                    table.flush(&mut out.records);
                    return;
                };
                let first = (row * tile.row_stride + col) * k;
                let (Some(ids), Some(ws)) = (
                    tile.ids.get(first..first + k),
                    tile.weights.get(first..first + k),
                ) else {
                    out.error = Some(format!(
                        "the lists of pixel ({}, {y}) are missing",
                        tile.x0 + col
                    ));
                    table.flush(&mut out.records);
                    return;
                };
                let records = &mut out.records;
                let factor = self.pixel_factor(local);
                let summed = self.pixel_hits(ids, ws, |_, g, q| {
                    // A factor can floor a weight to 0: W keeps nonzero sums only.
                    let q = weigh_hit(q, factor);
                    if group != NO_GROUP && q != 0 {
                        table.add(g, group, q, records);
                    }
                    Ok(())
                });
                let (pixel, n) = match summed {
                    Ok(sums) => sums,
                    Err(e) => {
                        out.error = Some(e);
                        table.flush(&mut out.records);
                        return;
                    }
                };
                out.mass[local] += pixel;
                if group != NO_GROUP {
                    out.counts.pixels += 1;
                    out.counts.hits += n;
                }
            }
        }
        table.flush(&mut out.records);
    }

    /// The pixel-weight factor of the view's mask `local` (1 without factors).
    #[inline]
    fn pixel_factor(&self, local: usize) -> u32 {
        self.pixel_weight
            .get(local)
            .copied()
            .unwrap_or(PIXEL_WEIGHT_ONE)
    }

    /// One pixel's list (`ids`, `ws`, up to the first padding entry): its summed fixed-point
    /// weight and its hit count, calling `add(rank, g, q)` for every hit of nonzero weight
    /// q; an error for a Gaussian past the scene's, or from `add`.
    #[inline(always)]
    fn pixel_hits(
        &self,
        ids: &[u32],
        ws: &[f32],
        mut add: impl FnMut(usize, u32, u64) -> Result<(), String>,
    ) -> Result<(u128, u64), String> {
        let mut pixel = 0u128;
        let mut n = 0u64;
        for (rank, (&g, &w)) in ids.iter().zip(ws).enumerate() {
            if g == NO_GAUSSIAN {
                break;
            }
            if g as usize >= self.num_gaussians {
                return Err(format!(
                    "the rasterizer returned Gaussian {g} of {}",
                    self.num_gaussians
                ));
            }
            let q = quantise(w);
            pixel += u128::from(q);
            n += 1;
            if q != 0 {
                add(rank, g, q)?;
            }
        }
        Ok((pixel, n))
    }

    /// [`ViewContext::sum_tile`] with the rasterizer's list positions: the tile's sums per
    /// (Gaussian, group) in a dense array indexed by (position in the tile's splat list,
    /// the group's rank among the tile's groups), an add per hit where the table probes
    /// a hash. The same records (in another order, which step 2 does not see: the sums
    /// are exact integers) and the same masses and counts. Returns false, having changed
    /// nothing, where the tile has more than [`DENSE_GROUPS`] groups or more than
    /// [`DENSE_CELLS`] (position, group) cells, or a label names no mask (the table path
    /// then sums it, or reports the label).
    fn sum_tile_dense<L: Label>(
        &self,
        labels: &[L],
        tile: &TileHits<'_>,
        positions: &[u32],
        out: &mut RowOutput,
    ) -> bool {
        let mut tile_groups = [NO_GROUP; DENSE_GROUPS];
        let Some(count) = self.code_pixels(labels, tile, &mut tile_groups, &mut out.dense) else {
            return false;
        };
        let cells = tile.splat_ids.len() * count;
        if cells > DENSE_CELLS {
            return false;
        }
        out.dense.sums.clear();
        out.dense.sums.resize(cells, (0, 0));
        let summed = self
            .sum_dense_pixels(tile, positions, count, out)
            .and_then(|()| self.dense_records(tile, &tile_groups[..count], out));
        if let Err(e) = summed {
            out.error = Some(e);
        }
        true
    }

    /// Step one of [`ViewContext::sum_tile_dense`]: each pixel's mask and code (its group's
    /// rank among the tile's groups, which it fills, or [`UNGROUPED`]; none where
    /// unlabelled) into `dense.pixels`. Returns the number of the tile's groups; `None`
    /// where they are more than [`DENSE_GROUPS`] or a label names no mask.
    #[inline(always)]
    fn code_pixels<L: Label>(
        &self,
        labels: &[L],
        tile: &TileHits<'_>,
        tile_groups: &mut [u32; DENSE_GROUPS],
        dense: &mut DenseSums,
    ) -> Option<usize> {
        let mut count = 0;
        dense.pixels.clear();
        for row in 0..tile.height {
            let first = (tile.y0 + row) * self.width + tile.x0;
            let row_labels = labels.get(first..first + tile.width)?;
            for label in row_labels {
                let Some(mask) = label.local() else {
                    dense.pixels.push(None);
                    continue;
                };
                let &group = self.groups.get(mask)?;
                let code = if group == NO_GROUP {
                    UNGROUPED
                } else if let Some(j) = tile_groups[..count].iter().position(|&g| g == group) {
                    j as u8
                } else if count < DENSE_GROUPS {
                    tile_groups[count] = group;
                    count += 1;
                    (count - 1) as u8
                } else {
                    return None;
                };
                dense.pixels.push(Some((mask, code)));
            }
        }
        Some(count)
    }

    /// Step two of [`ViewContext::sum_tile_dense`]: every coded pixel's hits added into its
    /// (position, group) cells of `out.dense.sums` (`count` groups per position), its mass
    /// into `out.mass` and its hits into `out.counts`. An error stops it (a pixel's lists
    /// missing, or a position past the tile's splats).
    #[inline(always)]
    fn sum_dense_pixels(
        &self,
        tile: &TileHits<'_>,
        positions: &[u32],
        count: usize,
        out: &mut RowOutput,
    ) -> Result<(), String> {
        let k = self.k;
        let dense = &mut out.dense;
        for row in 0..tile.height {
            for col in 0..tile.width {
                let Some((mask, code)) = dense.pixels[row * tile.width + col] else {
                    continue;
                };
                let x = tile.x0 + col;
                let y = tile.y0 + row;
                let first = (row * tile.row_stride + col) * k;
                let (Some(ids), Some(ws), Some(ats)) = (
                    tile.ids.get(first..first + k),
                    tile.weights.get(first..first + k),
                    positions.get(first..first + k),
                ) else {
                    return Err(format!("the lists of pixel ({x}, {y}) are missing"));
                };
                let sums = &mut dense.sums;
                let factor = self.pixel_factor(mask);
                let (pixel, n) = self.pixel_hits(ids, ws, |rank, g, q| {
                    let q = weigh_hit(q, factor);
                    if code == UNGROUPED || q == 0 {
                        return Ok(());
                    }
                    let at = ats[rank];
                    let cell = at as usize * count + usize::from(code);
                    let Some(sum) = sums.get_mut(cell) else {
                        return Err(format!(
                            "the rasterizer placed Gaussian {g} at {at} of the {} splats of \
                             the tile at ({}, {})",
                            tile.splat_ids.len(),
                            tile.x0,
                            tile.y0
                        ));
                    };
                    let (lo, carry) = sum.0.overflowing_add(q);
                    *sum = (lo, sum.1 + u64::from(carry));
                    Ok(())
                })?;
                out.mass[mask] += pixel;
                if code != UNGROUPED {
                    out.counts.pixels += 1;
                    out.counts.hits += n;
                }
            }
        }
        Ok(())
    }

    /// Step three of [`ViewContext::sum_tile_dense`]: the nonzero (position, group) sums as
    /// records of (the Gaussian at that position, the group); an error for a Gaussian past
    /// the scene's.
    #[inline(always)]
    fn dense_records(
        &self,
        tile: &TileHits<'_>,
        tile_groups: &[u32],
        out: &mut RowOutput,
    ) -> Result<(), String> {
        let count = tile_groups.len();
        if count == 0 {
            return Ok(());
        }
        for (&g, sums) in tile
            .splat_ids
            .iter()
            .zip(out.dense.sums.chunks_exact(count))
        {
            for (&group, &(lo, hi)) in tile_groups.iter().zip(sums) {
                if (lo, hi) == (0, 0) {
                    continue;
                }
                if g as usize >= self.num_gaussians {
                    return Err(format!(
                        "the rasterizer listed Gaussian {g} of {} in the tile at ({}, {})",
                        self.num_gaussians, tile.x0, tile.y0
                    ));
                }
                out.records.push(Record { g, group, lo, hi });
            }
        }
        Ok(())
    }
}

/// The dense sums of [`ViewContext::sum_tile_dense`], reused from tile to tile: per pixel
/// of the tile its mask and code (none where unlabelled), and the (low, high) halves of
/// each (position, group) sum.
#[derive(Debug, Default)]
pub(crate) struct DenseSums {
    pub(super) pixels: Vec<Option<(usize, u8)>>,
    pub(super) sums: Vec<(u64, u64)>,
}

/// Groups of one tile that the dense sum handles (a tile of a real view has a few).
pub(super) const DENSE_GROUPS: usize = 8;
/// (position, group) cells of one tile that the dense sum handles: at most 256 KiB of sums
/// per tile row's output (two views' rows are alive at once, ~90 of them at 1000x730; a
/// cap of 4,096 cells held the same peak RSS and sent more tiles to the slower table).
pub(super) const DENSE_CELLS: usize = 1 << 14;
/// The pixel code of the dense sum beside the group ranks (< [`DENSE_GROUPS`]): a mask in
/// no group.
pub(super) const UNGROUPED: u8 = u8::MAX;

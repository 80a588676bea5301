//! `profuse.topk`: the per-pixel top-K contributors of one rendered view (SPEC.md "topk"),
//! as `splat-raster topk` dumps them for inspection and for other tools.

use std::collections::BTreeMap;

use crate::check::{
    check_count, check_finite, check_ids, invalid, out_of_range, shape_err, TensorReader,
};
use crate::container::{Buffer, Container};
use crate::error::Result;
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// Padding id of an unused top-K slot (its weight is 0).
pub const NO_GAUSSIAN: u32 = u32::MAX;

/// Slack allowed on `Σ weights + T <= 1` for float accumulation.
pub const WEIGHT_SUM_TOLERANCE: f64 = 1e-4;

/// Top-K (id, weight) per pixel plus the final transmittance.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TopK {
    /// Gaussians in the scene the ids index (metadata `num_gaussians`).
    pub num_gaussians: usize,
    /// Image width.
    pub width: usize,
    /// Image height.
    pub height: usize,
    /// Slots per pixel K >= 1.
    pub k: usize,
    /// `ids` U32 [H, W, K]: Gaussian ids by decreasing weight, padded with 4294967295.
    pub ids: Buffer<u32>,
    /// `weights` F32 [H, W, K]: ω = T·α in [0, 1], non-increasing, 0 exactly on padding.
    pub weights: Buffer<f32>,
    /// `transmittance` F32 [H, W]: T after the last blended Gaussian, in [0, 1].
    pub transmittance: Buffer<f32>,
    /// Other metadata (`view`, camera, renderer parameters), kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl FileKind for TopK {
    const KIND: Kind = Kind::TopK;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        let num_gaussians = r.meta_parse("num_gaussians", "a non-negative integer")?;
        let ids = r.req("ids", "H,W,K")?;
        Ok(TopK {
            num_gaussians,
            ids,
            weights: r.req("weights", "H,W,K")?,
            transmittance: r.req("transmittance", "H,W")?,
            width: r.dim("W"),
            height: r.dim("H"),
            k: r.dim("K"),
            extra: r.extra_meta(&["num_gaussians"]),
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        let cells = [self.height, self.width, self.k];
        if self.k == 0 {
            return Err(shape_err(
                path,
                "ids",
                cells.to_vec(),
                "[H, W, K] with K >= 1".to_string(),
            ));
        }
        check_count(path, "ids", self.ids.len(), &cells, "values (H x W x K)")?;
        check_count(
            path,
            "weights",
            self.weights.len(),
            &cells,
            "values (H x W x K)",
        )?;
        check_count(
            path,
            "transmittance",
            self.transmittance.len(),
            &cells[..2],
            "values (H x W)",
        )?;
        check_ids(
            path,
            "ids",
            &self.ids,
            self.num_gaussians as u64,
            Some(u64::from(NO_GAUSSIAN)),
            "the Gaussians",
        )?;
        check_finite(path, "weights", &self.weights)?;
        if let Some(i) = self.weights.iter().position(|w| !(0.0..=1.0).contains(w)) {
            return Err(out_of_range(
                path,
                "weights",
                i,
                self.weights[i],
                "a weight in [0, 1]",
            ));
        }
        for (p, (ids, ws)) in self
            .ids
            .chunks_exact(self.k)
            .zip(self.weights.chunks_exact(self.k))
            .enumerate()
        {
            check_pixel(path, p, ids, ws)?;
        }
        check_finite(path, "transmittance", &self.transmittance)?;
        if let Some(i) = self
            .transmittance
            .iter()
            .position(|t| !(0.0..=1.0).contains(t))
        {
            return Err(out_of_range(
                path,
                "transmittance",
                i,
                self.transmittance[i],
                "a transmittance in [0, 1]",
            ));
        }
        for (p, ws) in self.weights.chunks_exact(self.k).enumerate() {
            let total =
                ws.iter().map(|w| f64::from(*w)).sum::<f64>() + f64::from(self.transmittance[p]);
            if total > 1.0 + WEIGHT_SUM_TOLERANCE {
                return Err(invalid(
                    path,
                    "weights",
                    format!("pixel {p}: weights plus transmittance sum to {total}, more than 1"),
                ));
            }
        }
        Ok(())
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        let (h, wd) = (self.height, self.width);
        w.meta("num_gaussians", self.num_gaussians.to_string())
            .tensor("ids", &[h, wd, self.k], &self.ids)
            .tensor("weights", &[h, wd, self.k], &self.weights)
            .tensor("transmittance", &[h, wd], &self.transmittance);
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("height", self.height as u64),
            ("width", self.width as u64),
            ("k", self.k as u64),
            (
                "hits",
                self.ids.iter().filter(|i| **i != NO_GAUSSIAN).count() as u64,
            ),
        ])
    }
}

/// Padding carries weight 0 and real hits weight > 0; weights never increase.
fn check_pixel(path: &str, p: usize, ids: &[u32], ws: &[f32]) -> Result<()> {
    for (s, (id, w)) in ids.iter().zip(ws).enumerate() {
        if (*id == NO_GAUSSIAN) != (*w == 0.0) {
            return Err(invalid(path, "weights", format!("pixel {p} slot {s}: id {id} with weight {w} (padding must have weight 0, hits weight > 0)")));
        }
        if s > 0 && *w > ws[s - 1] {
            return Err(invalid(
                path,
                "weights",
                format!(
                    "pixel {p} slot {s}: weight {w} exceeds the previous slot's {}",
                    ws[s - 1]
                ),
            ));
        }
    }
    Ok(())
}

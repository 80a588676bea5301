//! `profuse.masks`: per-view mask label maps plus one feature row per mask (SPEC.md "masks").

use std::collections::BTreeMap;

use crate::check::{
    check_count, check_finite_floats, check_len, check_offsets, check_unit_rows, out_of_range,
    Floats, Labels, TensorReader,
};
use crate::container::{Buffer, Container};
use crate::error::Result;
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// Per-view label maps of non-overlapping masks and their language features.
#[derive(Debug, Clone, PartialEq)]
pub struct Masks {
    /// View names (metadata `view_names`), the image names of the matching cameras file.
    pub view_names: Vec<String>,
    /// Label-map width in pixels.
    pub width: usize,
    /// Label-map height in pixels.
    pub height: usize,
    /// `labels` U16 or U32 [V, H, W]: per pixel the view-local mask index, or the dtype's
    /// maximum (65535 or 4294967295) for "no mask".
    pub labels: Labels,
    /// `mask_offsets` U32 [V + 1]: view v owns global masks `offsets[v]..offsets[v+1]`;
    /// global id = offsets[v] + local index.
    pub mask_offsets: Buffer<u32>,
    /// `features` F16 or F32 [M, D]: one L2-normalised row per global mask.
    pub features: Floats,
    /// Feature dimension D.
    pub dim: usize,
    /// Other metadata, kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl Masks {
    /// Number of views.
    pub fn num_views(&self) -> usize {
        self.view_names.len()
    }

    /// Total number of masks M.
    pub fn num_masks(&self) -> usize {
        self.mask_offsets.last().map_or(0, |m| *m as usize)
    }

    /// Number of masks of view `v`.
    pub fn masks_in_view(&self, v: usize) -> usize {
        (self.mask_offsets[v + 1] - self.mask_offsets[v]) as usize
    }

    /// The view owning global mask `m`.
    pub fn view_of(&self, m: usize) -> usize {
        self.mask_offsets.partition_point(|o| (*o as usize) <= m) - 1
    }

    /// Global mask id at pixel (x, y) of view `v`, `None` for no mask.
    pub fn mask_at(&self, v: usize, x: usize, y: usize) -> Option<u32> {
        let i = (v * self.height + y) * self.width + x;
        self.labels.get(i).map(|local| self.mask_offsets[v] + local)
    }
}

impl FileKind for Masks {
    const KIND: Kind = Kind::Masks;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        let view_names = r.meta_strings("view_names")?;
        r.bind("V", view_names.len(), "metadata `view_names`");
        let labels = r.req_labels("labels", "V,H,W")?;
        r.bind("V+1", view_names.len() + 1, "metadata `view_names` + 1");
        let mask_offsets = r.req("mask_offsets", "V+1")?;
        let features = r.req_floats("features", "M,D")?;
        Ok(Masks {
            width: r.dim("W"),
            height: r.dim("H"),
            dim: r.dim("D"),
            extra: r.extra_meta(&["view_names"]),
            view_names,
            labels,
            mask_offsets,
            features,
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        let v = self.view_names.len();
        check_count(
            path,
            "labels",
            self.labels.len(),
            &[v, self.height, self.width],
            "pixels (V x H x W)",
        )?;
        check_len(
            path,
            "mask_offsets",
            self.mask_offsets.len(),
            v + 1,
            "offsets (V + 1)",
        )?;
        if self.dim == 0 {
            return Err(crate::check::shape_err(
                path,
                "features",
                vec![0, 0],
                "[M, D] with D >= 1".to_string(),
            ));
        }
        let m = self.features.len() / self.dim;
        check_len(
            path,
            "features",
            self.features.len(),
            m * self.dim,
            "values (M x D)",
        )?;
        check_offsets(path, "mask_offsets", &self.mask_offsets, m as u64)?;
        let none = self.labels.none_value();
        // H x W only matters when there is a view; with none it may overflow (a header
        // value), and then no plane is ever indexed.
        let plane = if v == 0 { 0 } else { self.height * self.width };
        for view in 0..v {
            let count = self.masks_in_view(view) as u64;
            if count > u64::from(none) {
                return Err(out_of_range(
                    path,
                    "mask_offsets",
                    view + 1,
                    self.mask_offsets[view + 1],
                    format!(
                        "at most {none} masks per view for {} labels",
                        self.labels.dtype()
                    ),
                ));
            }
            check_plane(path, &self.labels, view * plane, plane, count)?;
        }
        check_finite_floats(path, "features", &self.features)?;
        check_unit_rows(path, "features", &self.features, self.dim, &|_| false)
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        let (v, h, wd) = (self.view_names.len(), self.height, self.width);
        let m = self.features.len().checked_div(self.dim).unwrap_or(0);
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        w.meta_strings("view_names", &self.view_names);
        match &self.labels {
            Labels::U16(b) => w.tensor("labels", &[v, h, wd], b),
            Labels::U32(b) => w.tensor("labels", &[v, h, wd], b),
        };
        w.tensor("mask_offsets", &[v + 1], &self.mask_offsets);
        match &self.features {
            Floats::F16(b) => w.tensor("features", &[m, self.dim], b),
            Floats::F32(b) => w.tensor("features", &[m, self.dim], b),
        };
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("views", self.num_views() as u64),
            ("masks", self.num_masks() as u64),
            ("height", self.height as u64),
            ("width", self.width as u64),
            ("feature_dim", self.dim as u64),
        ])
    }
}

/// Every label of one view's plane is a local mask index `< count` or "no mask".
fn check_plane(path: &str, labels: &Labels, start: usize, len: usize, count: u64) -> Result<()> {
    let bad = |i: usize, value: u64| {
        out_of_range(
            path,
            "labels",
            i,
            value,
            format!(
                "a mask index < {count} of this view or the reserved {}",
                labels.none_value()
            ),
        )
    };
    match labels {
        Labels::U16(b) => {
            let none = u16::MAX;
            if let Some(i) = b[start..start + len]
                .iter()
                .position(|l| *l != none && u64::from(*l) >= count)
            {
                return Err(bad(start + i, u64::from(b[start + i])));
            }
        }
        Labels::U32(b) => {
            let none = u32::MAX;
            if let Some(i) = b[start..start + len]
                .iter()
                .position(|l| *l != none && u64::from(*l) >= count)
            {
                return Err(bad(start + i, u64::from(b[start + i])));
            }
        }
    }
    Ok(())
}

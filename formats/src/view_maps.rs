//! `profuse.view_maps`: dense per-view depth and object-id maps, the ground truth of
//! synthetic scenes and the depth renders used for visibility (SPEC.md "view_maps").

use std::collections::BTreeMap;

use crate::check::{check_count, check_finite, check_ids, meta_err, out_of_range, TensorReader};
use crate::container::{Buffer, Container};
use crate::error::Result;
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// "No object" in `object_ids`.
pub const NO_OBJECT: u32 = u32::MAX;

/// Per-view depth and object ids on one grid.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ViewMaps {
    /// View names (metadata `view_names`), as in the cameras file.
    pub view_names: Vec<String>,
    /// Objects the ids index (metadata `num_objects`).
    pub num_objects: usize,
    /// Grid width.
    pub width: usize,
    /// Grid height.
    pub height: usize,
    /// `depth` F32 [V, H, W]: camera-space z of the surface seen at the pixel centre,
    /// 0 where no surface is seen; finite and >= 0.
    pub depth: Buffer<f32>,
    /// Optional `object_ids` U32 [V, H, W]: object seen at the pixel centre, or 4294967295.
    pub object_ids: Option<Buffer<u32>>,
    /// Other metadata, kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl ViewMaps {
    /// Index of pixel (x, y) of view `v` in the flat maps.
    pub fn index(&self, v: usize, x: usize, y: usize) -> usize {
        (v * self.height + y) * self.width + x
    }
}

impl FileKind for ViewMaps {
    const KIND: Kind = Kind::ViewMaps;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        let view_names = r.meta_strings("view_names")?;
        let num_objects = r.meta_parse("num_objects", "a non-negative integer")?;
        r.bind("V", view_names.len(), "metadata `view_names`");
        let depth = r.req("depth", "V,H,W")?;
        Ok(ViewMaps {
            object_ids: r.opt("object_ids", "V,H,W")?,
            width: r.dim("W"),
            height: r.dim("H"),
            extra: r.extra_meta(&["view_names", "num_objects"]),
            view_names,
            num_objects,
            depth,
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        let cells = [self.view_names.len(), self.height, self.width];
        if let Some(i) = self.view_names.iter().position(String::is_empty) {
            return Err(meta_err(
                path,
                "view_names",
                &format!("non-empty names (entry {i} is empty)"),
            ));
        }
        check_count(
            path,
            "depth",
            self.depth.len(),
            &cells,
            "values (V x H x W)",
        )?;
        check_finite(path, "depth", &self.depth)?;
        if let Some(i) = self.depth.iter().position(|d| *d < 0.0) {
            return Err(out_of_range(
                path,
                "depth",
                i,
                self.depth[i],
                "a depth >= 0",
            ));
        }
        if let Some(ids) = &self.object_ids {
            check_count(path, "object_ids", ids.len(), &cells, "values (V x H x W)")?;
            check_ids(
                path,
                "object_ids",
                ids,
                self.num_objects as u64,
                Some(u64::from(NO_OBJECT)),
                "the objects",
            )?;
        }
        Ok(())
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        let shape = [self.view_names.len(), self.height, self.width];
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        w.meta_strings("view_names", &self.view_names)
            .meta("num_objects", self.num_objects.to_string())
            .tensor("depth", &shape, &self.depth);
        if let Some(ids) = &self.object_ids {
            w.tensor("object_ids", &shape, ids);
        }
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("views", self.view_names.len() as u64),
            ("height", self.height as u64),
            ("width", self.width as u64),
            ("objects", self.num_objects as u64),
        ])
    }
}

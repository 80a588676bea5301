//! `profuse.mesh`: a triangle mesh or point cloud with optional per-vertex ground-truth
//! labels, ScanNet style (SPEC.md "mesh").

use std::collections::BTreeMap;

use crate::check::{check_finite, check_ids, check_len, TensorReader};
use crate::container::{Buffer, Container};
use crate::error::Result;
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// Vertices, optional colours, faces and labels.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Mesh {
    /// `vertices` F32 [V, 3].
    pub vertices: Buffer<[f32; 3]>,
    /// Optional `colors` U8 [V, 3] RGB.
    pub colors: Option<Buffer<[u8; 3]>>,
    /// Optional `faces` U32 [F, 3]: vertex indices < V, counter-clockwise seen from outside.
    pub faces: Option<Buffer<[u32; 3]>>,
    /// Optional `labels` U32 [V]: semantic class (metadata `label_space`, e.g. `nyu40`),
    /// 0 = unannotated.
    pub labels: Option<Buffer<u32>>,
    /// Optional `instances` U32 [V]: object instance id, 0 = none.
    pub instances: Option<Buffer<u32>>,
    /// Other metadata (`label_space`, provenance), kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl FileKind for Mesh {
    const KIND: Kind = Kind::Mesh;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        Ok(Mesh {
            vertices: r.req("vertices", "V,3")?,
            colors: r.opt("colors", "V,3")?,
            faces: r.opt("faces", "F,3")?,
            labels: r.opt("labels", "V")?,
            instances: r.opt("instances", "V")?,
            extra: r.extra_meta(&[]),
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        let v = self.vertices.len();
        check_finite(
            path,
            "vertices",
            bytemuck::cast_slice::<_, f32>(&self.vertices),
        )?;
        if let Some(c) = &self.colors {
            check_len(path, "colors", c.len(), v, "rows, one per vertex")?;
        }
        if let Some(l) = &self.labels {
            check_len(path, "labels", l.len(), v, "values, one per vertex")?;
        }
        if let Some(l) = &self.instances {
            check_len(path, "instances", l.len(), v, "values, one per vertex")?;
        }
        if let Some(f) = &self.faces {
            check_ids(
                path,
                "faces",
                bytemuck::cast_slice::<_, u32>(f),
                v as u64,
                None,
                "the vertices",
            )?;
        }
        Ok(())
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        let v = self.vertices.len();
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        w.tensor("vertices", &[v, 3], &self.vertices);
        if let Some(c) = &self.colors {
            w.tensor("colors", &[v, 3], c);
        }
        if let Some(f) = &self.faces {
            w.tensor("faces", &[f.len(), 3], f);
        }
        if let Some(l) = &self.labels {
            w.tensor("labels", &[v], l);
        }
        if let Some(l) = &self.instances {
            w.tensor("instances", &[v], l);
        }
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("vertices", self.vertices.len() as u64),
            ("faces", self.faces.as_ref().map_or(0, |f| f.len()) as u64),
            (
                "labelled",
                self.labels
                    .as_ref()
                    .map_or(0, |l| l.iter().filter(|x| **x != 0).count()) as u64,
            ),
        ])
    }
}

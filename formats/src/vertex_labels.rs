//! `profuse.vertex_labels`: a predicted class per mesh vertex (SPEC.md "vertex_labels").

use std::collections::BTreeMap;

use crate::check::{check_class_ids, check_finite, check_len, out_of_range, TensorReader};
use crate::container::{Buffer, Container};
use crate::error::Result;
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// Per-vertex predicted labels.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct VertexLabels {
    /// `labels` I32 [V]: class id (in metadata `label_space`), −1 = no label.
    pub labels: Buffer<i32>,
    /// Optional `confidence` F32 [V] in [0, 1].
    pub confidence: Option<Buffer<f32>>,
    /// Other metadata (`label_space`, parameters), kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl FileKind for VertexLabels {
    const KIND: Kind = Kind::VertexLabels;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        Ok(VertexLabels {
            labels: r.req("labels", "V")?,
            confidence: r.opt("confidence", "V")?,
            extra: r.extra_meta(&[]),
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        check_class_ids(path, "labels", &self.labels, "no label")?;
        if let Some(c) = &self.confidence {
            check_len(
                path,
                "confidence",
                c.len(),
                self.labels.len(),
                "values, one per vertex",
            )?;
            check_finite(path, "confidence", c)?;
            if let Some(i) = c.iter().position(|v| !(0.0..=1.0).contains(v)) {
                return Err(out_of_range(
                    path,
                    "confidence",
                    i,
                    c[i],
                    "a value in [0, 1]",
                ));
            }
        }
        Ok(())
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        let v = self.labels.len();
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        w.tensor("labels", &[v], &self.labels);
        if let Some(c) = &self.confidence {
            w.tensor("confidence", &[v], c);
        }
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("vertices", self.labels.len() as u64),
            (
                "labelled",
                self.labels.iter().filter(|l| **l >= 0).count() as u64,
            ),
        ])
    }
}

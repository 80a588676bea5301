//! `profuse.prompts`: named text embeddings (SPEC.md "prompts").

use std::collections::{BTreeMap, BTreeSet};

use crate::check::{
    check_class_ids, check_count, check_finite, check_len, invalid, meta_err, TensorReader,
};
use crate::container::{Buffer, Container};
use crate::error::Result;
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// Text prompts with their embeddings (any CLIP; normalised on use).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Prompts {
    /// Prompt texts (metadata `names`): unique and non-empty.
    pub names: Vec<String>,
    /// Embedding dimension D.
    pub dim: usize,
    /// `embeddings` F32 [Q, D]: finite, non-zero rows.
    pub embeddings: Buffer<f32>,
    /// Optional `class_ids` I32 [Q]: the class each prompt names, −1 for none
    /// (distractors, canonical negatives).
    pub class_ids: Option<Buffer<i32>>,
    /// Other metadata, kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl Prompts {
    /// Number of prompts.
    pub fn len(&self) -> usize {
        self.names.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }

    /// Index of a prompt by name.
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// Embedding row `q`.
    pub fn embedding(&self, q: usize) -> &[f32] {
        &self.embeddings[q * self.dim..(q + 1) * self.dim]
    }
}

impl FileKind for Prompts {
    const KIND: Kind = Kind::Prompts;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        let names = r.meta_strings("names")?;
        r.bind("Q", names.len(), "metadata `names`");
        let embeddings = r.req("embeddings", "Q,D")?;
        Ok(Prompts {
            dim: r.dim("D"),
            embeddings,
            class_ids: r.opt("class_ids", "Q")?,
            extra: r.extra_meta(&["names"]),
            names,
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        let q = self.len();
        if self.dim == 0 {
            return Err(crate::check::shape_err(
                path,
                "embeddings",
                vec![q, 0],
                "[Q, D] with D >= 1".to_string(),
            ));
        }
        check_count(
            path,
            "embeddings",
            self.embeddings.len(),
            &[q, self.dim],
            "values (Q x D, Q from metadata `names`)",
        )?;
        let mut seen = BTreeSet::new();
        for (i, n) in self.names.iter().enumerate() {
            if n.is_empty() || !seen.insert(n.as_str()) {
                return Err(meta_err(
                    path,
                    "names",
                    &format!("unique non-empty names (entry {i} {n:?} is empty or repeated)"),
                ));
            }
        }
        check_finite(path, "embeddings", &self.embeddings)?;
        if let Some(i) = (0..q).find(|&i| self.embedding(i).iter().all(|v| *v == 0.0)) {
            return Err(invalid(
                path,
                "embeddings",
                format!("row {i} ({:?}) is all zero", self.names[i]),
            ));
        }
        if let Some(ids) = &self.class_ids {
            check_len(path, "class_ids", ids.len(), q, "values, one per prompt")?;
            check_class_ids(path, "class_ids", ids, "none")?;
        }
        Ok(())
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        let q = self.len();
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        w.meta_strings("names", &self.names)
            .tensor("embeddings", &[q, self.dim], &self.embeddings);
        if let Some(ids) = &self.class_ids {
            w.tensor("class_ids", &[q], ids);
        }
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([("prompts", self.len() as u64), ("dim", self.dim as u64)])
    }
}

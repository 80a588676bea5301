//! `profuse.selection`: the Gaussians a text query selected (SPEC.md "selection").

use std::collections::BTreeMap;

use crate::check::{check_finite, check_len, meta_err, out_of_range, TensorReader};
use crate::container::{Buffer, Container};
use crate::error::Result;
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// Selected Gaussian ids with their scores.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Selection {
    /// The prompt text (metadata `prompt`).
    pub prompt: String,
    /// Gaussians in the scene the ids index (metadata `num_gaussians`).
    pub num_gaussians: usize,
    /// `gaussian_ids` U32 [S]: strictly increasing, < num_gaussians.
    pub gaussian_ids: Buffer<u32>,
    /// `scores` F32 [S]: the score that selected each Gaussian.
    pub scores: Buffer<f32>,
    /// Other metadata (score kind, threshold), kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl FileKind for Selection {
    const KIND: Kind = Kind::Selection;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        let prompt = r.meta("prompt", "the prompt text")?.to_string();
        let num_gaussians = r.meta_parse("num_gaussians", "a non-negative integer")?;
        Ok(Selection {
            prompt,
            num_gaussians,
            gaussian_ids: r.req("gaussian_ids", "S")?,
            scores: r.req("scores", "S")?,
            extra: r.extra_meta(&["prompt", "num_gaussians"]),
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        if self.prompt.is_empty() {
            return Err(meta_err(path, "prompt", "a non-empty prompt text"));
        }
        check_len(
            path,
            "scores",
            self.scores.len(),
            self.gaussian_ids.len(),
            "values, one per id",
        )?;
        let mut prev: Option<u32> = None;
        for (i, id) in self.gaussian_ids.iter().enumerate() {
            if *id as usize >= self.num_gaussians {
                return Err(out_of_range(
                    path,
                    "gaussian_ids",
                    i,
                    id,
                    format!(
                        "a Gaussian id < {} (metadata num_gaussians)",
                        self.num_gaussians
                    ),
                ));
            }
            if prev.is_some_and(|p| p >= *id) {
                return Err(out_of_range(
                    path,
                    "gaussian_ids",
                    i,
                    id,
                    "ids in strictly increasing order",
                ));
            }
            prev = Some(*id);
        }
        check_finite(path, "scores", &self.scores)
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        let s = self.gaussian_ids.len();
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        w.meta("prompt", self.prompt.clone())
            .meta("num_gaussians", self.num_gaussians.to_string())
            .tensor("gaussian_ids", &[s], &self.gaussian_ids)
            .tensor("scores", &[s], &self.scores);
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("selected", self.gaussian_ids.len() as u64),
            ("gaussians", self.num_gaussians as u64),
        ])
    }
}

//! `profuse.features`: one language descriptor per Gaussian (SPEC.md "features").

use std::collections::BTreeMap;

use crate::check::{
    check_count, check_finite, check_finite_floats, check_flags, check_len, check_unit_rows,
    invalid, out_of_range, Floats, TensorReader,
};
use crate::container::{Buffer, Container};
use crate::error::Result;
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// Registered descriptors; a Gaussian no view ever hit has none.
#[derive(Debug, Clone, PartialEq)]
pub struct Features {
    /// `features` F16 or F32 [N, D]: L2-normalised where valid, all zero where not.
    pub features: Floats,
    /// Feature dimension D.
    pub dim: usize,
    /// `valid` U8 [N]: 1 where the descriptor exists, 0 otherwise.
    pub valid: Buffer<u8>,
    /// Optional `weight_sum` F32 [N]: the registration weight S[g] (> 0 exactly where valid).
    pub weight_sum: Option<Buffer<f32>>,
    /// Other metadata, kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl Features {
    /// Number of Gaussians N.
    pub fn len(&self) -> usize {
        self.valid.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.valid.is_empty()
    }
}

impl FileKind for Features {
    const KIND: Kind = Kind::Features;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        let features = r.req_floats("features", "N,D")?;
        Ok(Features {
            features,
            dim: r.dim("D"),
            valid: r.req("valid", "N")?,
            weight_sum: r.opt("weight_sum", "N")?,
            extra: r.extra_meta(&[]),
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        let n = self.len();
        if self.dim == 0 {
            return Err(crate::check::shape_err(
                path,
                "features",
                vec![n, 0],
                "[N, D] with D >= 1".to_string(),
            ));
        }
        check_count(
            path,
            "features",
            self.features.len(),
            &[n, self.dim],
            "values (N x D, N from `valid`)",
        )?;
        check_flags(path, "valid", &self.valid)?;
        check_finite_floats(path, "features", &self.features)?;
        check_unit_rows(path, "features", &self.features, self.dim, &|r| {
            self.valid[r] == 0
        })?;
        if let Some(s) = &self.weight_sum {
            check_len(path, "weight_sum", s.len(), n, "values, one per Gaussian")?;
            check_finite(path, "weight_sum", s)?;
            if let Some(i) = s.iter().position(|w| *w < 0.0) {
                return Err(out_of_range(path, "weight_sum", i, s[i], "a weight >= 0"));
            }
            if let Some(i) = (0..n).find(|&i| (s[i] > 0.0) != (self.valid[i] == 1)) {
                return Err(invalid(
                    path,
                    "weight_sum",
                    format!(
                        "Gaussian {i} has weight {} but valid = {}",
                        s[i], self.valid[i]
                    ),
                ));
            }
        }
        Ok(())
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        let n = self.len();
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        match &self.features {
            Floats::F16(b) => w.tensor("features", &[n, self.dim], b),
            Floats::F32(b) => w.tensor("features", &[n, self.dim], b),
        };
        w.tensor("valid", &[n], &self.valid);
        if let Some(s) = &self.weight_sum {
            w.tensor("weight_sum", &[n], s);
        }
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("gaussians", self.len() as u64),
            ("feature_dim", self.dim as u64),
            (
                "valid",
                self.valid.iter().filter(|v| **v == 1).count() as u64,
            ),
        ])
    }
}

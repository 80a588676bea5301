//! `profuse.pq`: a product-quantisation codebook and the codes of N descriptors
//! (SPEC.md "pq"), centroids laid out as faiss's `ProductQuantizer.centroids`.

use std::collections::BTreeMap;

use crate::check::{
    check_count, check_finite, check_flags, check_len, invalid, meta_err, out_of_range, shape_err,
    TensorReader,
};
use crate::container::{Buffer, Container};
use crate::error::Result;
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// Centroids per sub-quantiser (8-bit codes).
pub const KSUB: usize = 256;

/// PQ codebook plus codes.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Pq {
    /// Sub-quantisers M.
    pub m: usize,
    /// Sub-vector dimension d/M.
    pub dsub: usize,
    /// `centroids` F32 [M, 256, dsub].
    pub centroids: Buffer<f32>,
    /// `codes` U8 [N, M].
    pub codes: Buffer<u8>,
    /// `norms` F32 [N]: L2 norm of each decoded vector (0 where invalid).
    pub norms: Buffer<f32>,
    /// `valid` U8 [N]: 1 where the encoded descriptor exists.
    pub valid: Buffer<u8>,
    /// Other metadata, kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl Pq {
    /// Number of encoded vectors N.
    pub fn len(&self) -> usize {
        self.valid.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.valid.is_empty()
    }

    /// Full dimension d = M x dsub.
    pub fn dim(&self) -> usize {
        self.m * self.dsub
    }
}

impl FileKind for Pq {
    const KIND: Kind = Kind::Pq;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        let metric = r.meta("metric", "\"inner_product\"")?;
        if metric != "inner_product" {
            return Err(meta_err(c.path(), "metric", "\"inner_product\""));
        }
        let nbits: usize = r.meta_parse("nbits", "8")?;
        if nbits != 8 {
            return Err(meta_err(c.path(), "nbits", "8"));
        }
        let centroids = r.req("centroids", "M,256,S")?;
        Ok(Pq {
            m: r.dim("M"),
            dsub: r.dim("S"),
            centroids,
            codes: r.req("codes", "N,M")?,
            norms: r.req("norms", "N")?,
            valid: r.req("valid", "N")?,
            extra: r.extra_meta(&["metric", "nbits"]),
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        let n = self.len();
        if self.m == 0 || self.dsub == 0 {
            return Err(shape_err(
                path,
                "centroids",
                vec![self.m, KSUB, self.dsub],
                "[M, 256, dsub] with M, dsub >= 1".to_string(),
            ));
        }
        check_count(
            path,
            "centroids",
            self.centroids.len(),
            &[self.m, KSUB, self.dsub],
            "values (M x 256 x dsub)",
        )?;
        check_count(
            path,
            "codes",
            self.codes.len(),
            &[n, self.m],
            "values (N x M, N from `valid`)",
        )?;
        check_len(path, "norms", self.norms.len(), n, "values, one per vector")?;
        check_finite(path, "centroids", &self.centroids)?;
        check_flags(path, "valid", &self.valid)?;
        check_finite(path, "norms", &self.norms)?;
        if let Some(i) = self.norms.iter().position(|v| *v < 0.0) {
            return Err(out_of_range(path, "norms", i, self.norms[i], "a norm >= 0"));
        }
        if let Some(i) = (0..n).find(|&i| self.valid[i] == 0 && self.norms[i] != 0.0) {
            return Err(invalid(
                path,
                "norms",
                format!("vector {i} is invalid but has norm {}", self.norms[i]),
            ));
        }
        Ok(())
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        let n = self.len();
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        w.meta("metric", "inner_product")
            .meta("nbits", "8")
            .tensor("centroids", &[self.m, KSUB, self.dsub], &self.centroids)
            .tensor("codes", &[n, self.m], &self.codes)
            .tensor("norms", &[n], &self.norms)
            .tensor("valid", &[n], &self.valid);
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("vectors", self.len() as u64),
            ("dim", self.dim() as u64),
            ("m", self.m as u64),
            ("ksub", KSUB as u64),
            (
                "valid",
                self.valid.iter().filter(|v| **v == 1).count() as u64,
            ),
        ])
    }
}

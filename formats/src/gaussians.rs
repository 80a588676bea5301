//! `profuse.gaussians`: 3D Gaussians with the INRIA 3DGS parameterisation (SPEC.md "gaussians").

use std::collections::BTreeMap;

use crate::check::{
    check_class_ids, check_finite, check_len, invalid, meta_err, product, shape_err, TensorReader,
};
use crate::container::{Buffer, Container};
use crate::error::Result;
use crate::kind::{FileKind, Kind};
use crate::writer::FileWriter;

/// SH coefficients per channel beyond DC for degrees 0..=3.
pub const SH_REST_COEFFS: [usize; 4] = [0, 3, 8, 15];

/// A set of Gaussians.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Gaussians {
    /// `means` F32 [N, 3]: centres in world coordinates.
    pub means: Buffer<[f32; 3]>,
    /// `log_scales` F32 [N, 3]: natural log of the per-axis standard deviations.
    pub log_scales: Buffer<[f32; 3]>,
    /// `rotations` F32 [N, 4]: quaternion (w, x, y, z), normalised on use, never zero.
    pub rotations: Buffer<[f32; 4]>,
    /// `opacity_logits` F32 [N]: opacity = sigmoid(logit).
    pub opacity_logits: Buffer<f32>,
    /// `sh_dc` F32 [N, 3]: degree-0 SH coefficient per RGB channel.
    pub sh_dc: Buffer<[f32; 3]>,
    /// SH degree 0..=3 (metadata `sh_degree`); `sh_rest` is present exactly when it is > 0.
    pub sh_degree: usize,
    /// Optional `sh_rest` F32 [N, R, 3], R = 3, 8 or 15 for degree 1, 2, 3: higher SH
    /// bands, coefficient-major (index `[n, k, channel]`).
    pub sh_rest: Option<Buffer<f32>>,
    /// Optional `class_ids` I32 [N]: ground-truth class per Gaussian, −1 = none.
    pub class_ids: Option<Buffer<i32>>,
    /// Other metadata, kept on round trips.
    pub extra: BTreeMap<String, String>,
}

impl Gaussians {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.means.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// Coefficients per channel in `sh_rest` (0 for degree 0).
    pub fn sh_rest_coeffs(&self) -> usize {
        SH_REST_COEFFS.get(self.sh_degree).copied().unwrap_or(0)
    }

    /// Opacity in (0, 1) of Gaussian `i`.
    pub fn opacity(&self, i: usize) -> f32 {
        1.0 / (1.0 + (-self.opacity_logits[i]).exp())
    }
}

impl FileKind for Gaussians {
    const KIND: Kind = Kind::Gaussians;

    fn from_container(c: &Container) -> Result<Self> {
        let mut r = TensorReader::new(c);
        let degree: usize = r.meta_parse("sh_degree", "an integer 0, 1, 2 or 3")?;
        if degree > 3 {
            return Err(meta_err(c.path(), "sh_degree", "an integer 0, 1, 2 or 3"));
        }
        let means = r.req("means", "N,3")?;
        let sh_rest = if degree > 0 {
            let coeffs = SH_REST_COEFFS[degree];
            Some(r.req("sh_rest", &format!("N,{coeffs},3"))?)
        } else if c.tensors().contains_key("sh_rest") {
            return Err(meta_err(
                c.path(),
                "sh_degree",
                "a degree >= 1 when tensor `sh_rest` is present",
            ));
        } else {
            None
        };
        Ok(Gaussians {
            means,
            log_scales: r.req("log_scales", "N,3")?,
            rotations: r.req("rotations", "N,4")?,
            opacity_logits: r.req("opacity_logits", "N")?,
            sh_dc: r.req("sh_dc", "N,3")?,
            sh_degree: degree,
            sh_rest,
            class_ids: r.opt("class_ids", "N")?,
            extra: r.extra_meta(&["sh_degree"]),
        })
    }

    fn validate(&self, path: &str) -> Result<()> {
        let n = self.len();
        check_len(
            path,
            "log_scales",
            self.log_scales.len(),
            n,
            "rows, one per mean",
        )?;
        check_len(
            path,
            "rotations",
            self.rotations.len(),
            n,
            "rows, one per mean",
        )?;
        check_len(
            path,
            "opacity_logits",
            self.opacity_logits.len(),
            n,
            "values, one per mean",
        )?;
        check_len(path, "sh_dc", self.sh_dc.len(), n, "rows, one per mean")?;
        if self.sh_degree > 3 {
            return Err(meta_err(path, "sh_degree", "an integer 0, 1, 2 or 3"));
        }
        match &self.sh_rest {
            None if self.sh_degree > 0 => {
                return Err(crate::error::FormatError::MissingTensor {
                    path: path.to_string(),
                    tensor: "sh_rest".to_string(),
                    expected: format!(
                        "[N, {}, 3] for sh_degree {}",
                        self.sh_rest_coeffs(),
                        self.sh_degree
                    ),
                })
            }
            Some(_) if self.sh_degree == 0 => {
                return Err(meta_err(
                    path,
                    "sh_degree",
                    "a degree >= 1 when tensor `sh_rest` is present",
                ));
            }
            Some(rest) => {
                let coeffs = self.sh_rest_coeffs();
                if product(&[n, coeffs, 3]) != Some(rest.len()) {
                    return Err(shape_err(
                        path,
                        "sh_rest",
                        vec![rest.len()],
                        format!("{n} x {coeffs} x 3 values"),
                    ));
                }
                check_finite(path, "sh_rest", rest)?;
            }
            None => {}
        }
        check_finite(path, "means", bytemuck::cast_slice::<_, f32>(&self.means))?;
        check_finite(
            path,
            "log_scales",
            bytemuck::cast_slice::<_, f32>(&self.log_scales),
        )?;
        check_finite(
            path,
            "rotations",
            bytemuck::cast_slice::<_, f32>(&self.rotations),
        )?;
        check_finite(path, "opacity_logits", &self.opacity_logits)?;
        check_finite(path, "sh_dc", bytemuck::cast_slice::<_, f32>(&self.sh_dc))?;
        if let Some(i) = self
            .rotations
            .iter()
            .position(|q| q.iter().all(|c| *c == 0.0))
        {
            return Err(invalid(
                path,
                "rotations",
                format!("row {i} is the zero quaternion"),
            ));
        }
        if let Some(ids) = &self.class_ids {
            check_len(path, "class_ids", ids.len(), n, "values, one per mean")?;
            check_class_ids(path, "class_ids", ids, "none")?;
        }
        Ok(())
    }

    fn fill<'a>(&'a self, w: &mut FileWriter<'a>) {
        let n = self.len();
        for (k, val) in &self.extra {
            w.meta(k, val.clone());
        }
        w.meta("sh_degree", self.sh_degree.to_string())
            .tensor("means", &[n, 3], &self.means)
            .tensor("log_scales", &[n, 3], &self.log_scales)
            .tensor("rotations", &[n, 4], &self.rotations)
            .tensor("opacity_logits", &[n], &self.opacity_logits)
            .tensor("sh_dc", &[n, 3], &self.sh_dc);
        if let Some(rest) = &self.sh_rest {
            w.tensor("sh_rest", &[n, self.sh_rest_coeffs(), 3], rest);
        }
        if let Some(ids) = &self.class_ids {
            w.tensor("class_ids", &[n], ids);
        }
    }

    fn counts(&self) -> BTreeMap<&'static str, u64> {
        BTreeMap::from([
            ("gaussians", self.len() as u64),
            ("sh_degree", self.sh_degree as u64),
        ])
    }
}

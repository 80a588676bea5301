//! The trainable parameters (one flat array per tensor, as the optimiser sees them) and
//! their gradients, with the conversions to and from the `profuse.gaussians` format type.

use profuse_formats::Gaussians;

use crate::error::{RefineError, Result};

/// Trainable Gaussian parameters, the tensors of SPEC.md's `profuse.gaussians` in owned,
/// mutable form.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Params {
    /// World-space means.
    pub means: Vec<[f32; 3]>,
    /// Natural-log scales.
    pub log_scales: Vec<[f32; 3]>,
    /// Quaternions (w, x, y, z), not necessarily normalised.
    pub rotations: Vec<[f32; 4]>,
    /// Opacity logits.
    pub opacity_logits: Vec<f32>,
    /// Degree-0 SH coefficients.
    pub sh_dc: Vec<[f32; 3]>,
    /// Higher SH coefficients, `[n, coeffs, 3]` flattened (empty for degree 0).
    pub sh_rest: Vec<f32>,
    /// SH degree 0..=3.
    pub sh_degree: usize,
}

/// SH coefficients beyond DC per channel for a degree.
pub fn rest_coeffs(degree: usize) -> usize {
    (degree + 1) * (degree + 1) - 1
}

impl Params {
    /// Copies the trainable tensors of `g` after splat-raster's validation (class ids and
    /// metadata are not trained; the writer takes them from the input again, see
    /// [`Params::to_gaussians`]).
    pub fn from_gaussians(g: &Gaussians) -> Result<Params> {
        let n = g.len();
        let check = |field: &'static str, got: usize, expected: usize| {
            if got == expected {
                Ok(())
            } else {
                Err(RefineError::Inconsistent {
                    field,
                    got,
                    expected,
                })
            }
        };
        check("log_scales", g.log_scales.len(), n)?;
        check("rotations", g.rotations.len(), n)?;
        check("opacity_logits", g.opacity_logits.len(), n)?;
        check("sh_dc", g.sh_dc.len(), n)?;
        if g.sh_degree > 3 {
            return Err(RefineError::Config {
                name: "sh_degree",
                value: g.sh_degree.to_string(),
                expected: "0..=3",
            });
        }
        // Non-finite means, scales, rotations or SH, zero quaternions: splat-raster's
        // checks, with its typed error naming the Gaussian and tensor.
        splat_raster::check_gaussians(g)?;
        let rest = g.sh_rest.as_ref().map(|r| r.to_vec()).unwrap_or_default();
        check("sh_rest", rest.len(), n * rest_coeffs(g.sh_degree) * 3)?;
        Ok(Params {
            means: g.means.to_vec(),
            log_scales: g.log_scales.to_vec(),
            rotations: g.rotations.to_vec(),
            opacity_logits: g.opacity_logits.to_vec(),
            sh_dc: g.sh_dc.to_vec(),
            sh_rest: rest,
            sh_degree: g.sh_degree,
        })
    }

    /// The parameters as a `Gaussians` value, with class ids and metadata of `template`
    /// (kept only where `keep` maps every output Gaussian to its input index).
    pub fn to_gaussians(&self, template: &Gaussians, keep: Option<&[u32]>) -> Gaussians {
        let class_ids = template.class_ids.as_ref().map(|c| match keep {
            Some(k) => k.iter().map(|&i| c[i as usize]).collect::<Vec<_>>().into(),
            None => c.clone(),
        });
        Gaussians {
            means: self.means.clone().into(),
            log_scales: self.log_scales.clone().into(),
            rotations: self.rotations.clone().into(),
            opacity_logits: self.opacity_logits.clone().into(),
            sh_dc: self.sh_dc.clone().into(),
            sh_degree: self.sh_degree,
            sh_rest: (self.sh_degree > 0).then(|| self.sh_rest.clone().into()),
            class_ids,
            extra: template.extra.clone(),
        }
    }

    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.means.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// Higher SH coefficients of Gaussian `i` (`3 * rest_coeffs` values).
    pub fn rest(&self, i: usize) -> &[f32] {
        let per = rest_coeffs(self.sh_degree) * 3;
        &self.sh_rest[i * per..(i + 1) * per]
    }

    /// Raises the SH degree to `degree` (never lowers it): the new higher coefficients
    /// start at zero, so every Gaussian's colour is unchanged until they are trained
    /// (3DGS trains up to degree 3 from SH-0 initialisations the same way).
    pub fn raise_sh_degree(&mut self, degree: usize) -> Result<()> {
        if degree > 3 {
            return Err(RefineError::Config {
                name: "sh_degree",
                value: degree.to_string(),
                expected: "0..=3",
            });
        }
        if degree <= self.sh_degree {
            return Ok(());
        }
        let (old, new) = (rest_coeffs(self.sh_degree) * 3, rest_coeffs(degree) * 3);
        let mut rest = Vec::with_capacity(self.len() * new);
        for i in 0..self.len() {
            rest.extend_from_slice(&self.sh_rest[i * old..(i + 1) * old]);
            rest.resize((i + 1) * new, 0.0);
        }
        self.sh_rest = rest;
        self.sh_degree = degree;
        Ok(())
    }

    /// Opacity of Gaussian `i`: the sigmoid of its logit.
    pub fn opacity(&self, i: usize) -> f64 {
        1.0 / (1.0 + (-f64::from(self.opacity_logits[i])).exp())
    }

    /// Keeps the Gaussians whose index is in `keep` (ascending).
    pub fn retain(&mut self, keep: &[u32]) {
        *self = self.subset(keep);
    }

    /// The Gaussians whose index is in `keep`, in that order.
    pub fn subset(&self, keep: &[u32]) -> Params {
        let per = rest_coeffs(self.sh_degree) * 3;
        let pick = |v: &[[f32; 3]]| keep.iter().map(|&i| v[i as usize]).collect();
        Params {
            means: pick(&self.means),
            log_scales: pick(&self.log_scales),
            sh_dc: pick(&self.sh_dc),
            rotations: keep.iter().map(|&i| self.rotations[i as usize]).collect(),
            opacity_logits: keep
                .iter()
                .map(|&i| self.opacity_logits[i as usize])
                .collect(),
            sh_rest: keep
                .iter()
                .flat_map(|&i| &self.sh_rest[i as usize * per..(i as usize + 1) * per])
                .copied()
                .collect(),
            sh_degree: self.sh_degree,
        }
    }
}

/// Gradients of a scalar loss with respect to every parameter, in the layout of
/// [`Params`] (f64: they are sums over many pixels and views).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Grads {
    /// d/d means.
    pub means: Vec<[f64; 3]>,
    /// d/d log-scales.
    pub log_scales: Vec<[f64; 3]>,
    /// d/d quaternions (through the normalisation).
    pub rotations: Vec<[f64; 4]>,
    /// d/d opacity logits.
    pub opacity_logits: Vec<f64>,
    /// d/d degree-0 SH.
    pub sh_dc: Vec<[f64; 3]>,
    /// d/d higher SH, layout of [`Params::sh_rest`].
    pub sh_rest: Vec<f64>,
}

impl Grads {
    /// All-zero gradients for `p`'s shapes.
    pub fn zeros(p: &Params) -> Grads {
        let n = p.len();
        Grads {
            means: vec![[0.0; 3]; n],
            log_scales: vec![[0.0; 3]; n],
            rotations: vec![[0.0; 4]; n],
            opacity_logits: vec![0.0; n],
            sh_dc: vec![[0.0; 3]; n],
            sh_rest: vec![0.0; p.sh_rest.len()],
        }
    }

    /// Sets every entry to zero, keeping the shapes.
    pub fn clear(&mut self) {
        self.means.fill([0.0; 3]);
        self.log_scales.fill([0.0; 3]);
        self.rotations.fill([0.0; 4]);
        self.opacity_logits.fill(0.0);
        self.sh_dc.fill([0.0; 3]);
        self.sh_rest.fill(0.0);
    }
}

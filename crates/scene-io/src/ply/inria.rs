//! INRIA 3DGS PLY ↔ [`Gaussians`].
//!
//! The INRIA layout (`GaussianModel.save_ply` of graphdeco-inria/gaussian-splatting) is
//! one `vertex` element with float properties `x y z nx ny nz f_dc_0..2 f_rest_0..
//! opacity scale_0..2 rot_0..3`. Our parameterisation is the same (log scales, opacity
//! logits, quaternion w first), so conversion is a relayout:
//!
//! * `f_rest_*` is channel-major in the PLY (`f_rest_{c*R + k}` = channel c, coefficient k)
//!   and coefficient-major in `sh_rest[n, k, c]`;
//! * normals are ignored on import and written as zeros on export, as INRIA does;
//! * non-finite opacity logits (trained scenes can store +inf for opacity 1) are clamped
//!   to ±[`OPACITY_LOGIT_CLAMP`] and counted; any other non-finite value is an error.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::Path;

use profuse_formats::{format_float, FileKind, Gaussians, SH_REST_COEFFS};
use serde::Serialize;

use super::parser::{read_ply, Element, PlyData, Values};
use crate::error::{invalid, missing, Result, SceneError};
use crate::fsutil::{show, write_atomically};

/// Magnitude that non-finite opacity logits are clamped to: +inf becomes +20 (opacity
/// 1 − 2e-9, indistinguishable from 1 in f32), NaN and −inf become −20 (invisible; a NaN
/// carries no opacity, so the safe reading is "not there").
pub const OPACITY_LOGIT_CLAMP: f32 = 20.0;

/// What [`read_inria_ply`] found besides the Gaussians.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct PlyReport {
    /// `ascii` or `binary_little_endian`.
    pub format: String,
    /// Number of Gaussians (vertices).
    pub gaussians: usize,
    /// SH degree implied by the number of `f_rest_*` properties.
    pub sh_degree: usize,
    /// Opacity logits that were NaN or ±inf and were clamped to ±[`OPACITY_LOGIT_CLAMP`].
    pub clamped_opacity: usize,
    /// Vertex properties that were read but not used (`nx ny nz`, extras of other trainers).
    pub ignored_properties: Vec<String>,
    /// Elements other than `vertex` (skipped).
    pub ignored_elements: Vec<String>,
}

/// Reads an INRIA 3DGS PLY file (`binary_little_endian` or `ascii`).
pub fn read_inria_ply(path: impl AsRef<Path>) -> Result<(Gaussians, PlyReport)> {
    let path = path.as_ref();
    let ply = read_ply(path)?;
    gaussians_from_ply(&ply, &show(path))
}

/// Converts a parsed PLY in the INRIA layout; `label` names the file in errors.
pub fn gaussians_from_ply(ply: &PlyData, label: &str) -> Result<(Gaussians, PlyReport)> {
    let vertex = ply.element("vertex").ok_or_else(|| {
        missing(
            label,
            "element `vertex`",
            "one vertex per Gaussian (INRIA 3DGS layout)",
        )
    })?;
    let columns = VertexColumns { vertex, label };
    let sh_degree = sh_degree_of(vertex, label)?;
    let coeffs = SH_REST_COEFFS.get(sh_degree).copied().unwrap_or(0);

    let means = columns.rows3(["x", "y", "z"])?;
    let sh_dc = columns.rows3(["f_dc_0", "f_dc_1", "f_dc_2"])?;
    let log_scales = columns.rows3(["scale_0", "scale_1", "scale_2"])?;
    let rotations = columns.rows4(["rot_0", "rot_1", "rot_2", "rot_3"])?;
    if let Some(i) = rotations.iter().position(|q| q.iter().all(|c| *c == 0.0)) {
        return Err(invalid(
            label,
            "vertex properties `rot_0..3`",
            format!("vertex {i} has the zero quaternion"),
        ));
    }
    let (opacity_logits, clamped_opacity) = columns.opacity()?;
    let sh_rest = if coeffs > 0 {
        Some(columns.sh_rest(coeffs)?)
    } else {
        None
    };

    let known = known_properties(coeffs);
    let ignored_properties = vertex
        .def
        .properties
        .iter()
        .filter(|p| !known.contains(&p.name))
        .map(|p| p.name.clone())
        .collect();
    let ignored_elements = ply
        .elements
        .iter()
        .filter(|e| e.def.name != "vertex")
        .map(|e| e.def.name.clone())
        .collect();
    let gaussians = Gaussians {
        means: means.into(),
        log_scales: log_scales.into(),
        rotations: rotations.into(),
        opacity_logits: opacity_logits.into(),
        sh_dc: sh_dc.into(),
        sh_degree,
        sh_rest: sh_rest.map(Into::into),
        class_ids: None,
        extra: BTreeMap::from([("source".to_string(), "inria_ply".to_string())]),
    };
    let report = PlyReport {
        format: ply.header.format.name().to_string(),
        gaussians: gaussians.len(),
        sh_degree,
        clamped_opacity,
        ignored_properties,
        ignored_elements,
    };
    Ok((gaussians, report))
}

/// The degree from the `f_rest_*` count (0, 9, 24, 45 → 0..3); the names must be
/// exactly `f_rest_0 .. f_rest_{count-1}`.
fn sh_degree_of(vertex: &Element, label: &str) -> Result<usize> {
    let count = vertex
        .def
        .properties
        .iter()
        .filter(|p| p.name.starts_with("f_rest_"))
        .count();
    let degree = SH_REST_COEFFS
        .iter()
        .position(|c| c * 3 == count)
        .ok_or_else(|| {
            invalid(
                label,
                "vertex properties `f_rest_*`",
                format!("found {count}, expected 0, 9, 24 or 45 (SH degree 0, 1, 2 or 3)"),
            )
        })?;
    if let Some(i) = (0..count).find(|i| vertex.column(&format!("f_rest_{i}")).is_none()) {
        return Err(missing(
            label,
            format!("vertex property `f_rest_{i}`"),
            format!(
                "f_rest_0 .. f_rest_{} for {count} SH coefficients",
                count - 1
            ),
        ));
    }
    Ok(degree)
}

fn known_properties(coeffs: usize) -> Vec<String> {
    let fixed = [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3",
    ];
    fixed
        .iter()
        .map(|s| (*s).to_string())
        .chain((0..coeffs * 3).map(|i| format!("f_rest_{i}")))
        .collect()
}

/// Typed access to the vertex columns with errors that name the property and vertex.
struct VertexColumns<'a> {
    vertex: &'a Element,
    label: &'a str,
}

impl VertexColumns<'_> {
    fn values(&self, name: &str) -> Result<&Values> {
        match self.vertex.column(name) {
            None => Err(missing(
                self.label,
                format!("vertex property `{name}`"),
                "a scalar property of element `vertex` (INRIA 3DGS layout)",
            )),
            Some(_) => self.vertex.scalar(name).ok_or_else(|| {
                invalid(
                    self.label,
                    format!("vertex property `{name}`"),
                    "is a list, expected a scalar",
                )
            }),
        }
    }

    /// A column as f32 that must be finite.
    fn finite(&self, name: &str) -> Result<Vec<f32>> {
        let values = self.values(name)?;
        (0..values.len())
            .map(|i| {
                let v = values.get_f32(i).unwrap_or(f32::NAN);
                if v.is_finite() {
                    Ok(v)
                } else {
                    Err(SceneError::NonFinite {
                        path: self.label.to_string(),
                        field: format!("vertex property `{name}`"),
                        index: i,
                        value: format_float(values.get(i).unwrap_or(f64::NAN)),
                    })
                }
            })
            .collect()
    }

    fn rows3(&self, names: [&str; 3]) -> Result<Vec<[f32; 3]>> {
        let [a, b, c] = names.map(|n| self.finite(n));
        let (a, b, c) = (a?, b?, c?);
        Ok(a.into_iter()
            .zip(b)
            .zip(c)
            .map(|((a, b), c)| [a, b, c])
            .collect())
    }

    fn rows4(&self, names: [&str; 4]) -> Result<Vec<[f32; 4]>> {
        let [a, b, c, d] = names.map(|n| self.finite(n));
        let (a, b, c, d) = (a?, b?, c?, d?);
        Ok(a.into_iter()
            .zip(b)
            .zip(c)
            .zip(d)
            .map(|(((a, b), c), d)| [a, b, c, d])
            .collect())
    }

    /// Opacity logits with non-finite values clamped, and how many were.
    fn opacity(&self) -> Result<(Vec<f32>, usize)> {
        let values = self.values("opacity")?;
        let mut clamped = 0;
        let logits = (0..values.len())
            .map(|i| {
                let v = values.get_f32(i).unwrap_or(f32::NAN);
                if v.is_finite() {
                    v
                } else {
                    clamped += 1;
                    clamp_logit(v)
                }
            })
            .collect();
        Ok((logits, clamped))
    }

    /// `sh_rest[n, k, c]` from channel-major `f_rest_{c*R + k}`.
    fn sh_rest(&self, coeffs: usize) -> Result<Vec<f32>> {
        let n = self.vertex.len();
        let mut rest = vec![0.0f32; n * coeffs * 3];
        for j in 0..coeffs * 3 {
            let (channel, k) = (j / coeffs, j % coeffs);
            for (i, v) in self.finite(&format!("f_rest_{j}"))?.into_iter().enumerate() {
                if let Some(slot) = rest.get_mut((i * coeffs + k) * 3 + channel) {
                    *slot = v;
                }
            }
        }
        Ok(rest)
    }
}

/// +inf → +[`OPACITY_LOGIT_CLAMP`]; NaN and −inf → −[`OPACITY_LOGIT_CLAMP`].
fn clamp_logit(v: f32) -> f32 {
    if v == f32::INFINITY {
        OPACITY_LOGIT_CLAMP
    } else {
        -OPACITY_LOGIT_CLAMP
    }
}

/// The property names of an INRIA PLY of this SH degree, in `save_ply` order.
pub fn inria_property_names(sh_degree: usize) -> Vec<String> {
    let coeffs = SH_REST_COEFFS.get(sh_degree).copied().unwrap_or(0);
    let mut names: Vec<String> = [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    ]
    .iter()
    .map(|s| (*s).to_string())
    .collect();
    names.extend((0..coeffs * 3).map(|i| format!("f_rest_{i}")));
    names.push("opacity".to_string());
    names.extend((0..3).map(|i| format!("scale_{i}")));
    names.extend((0..4).map(|i| format!("rot_{i}")));
    names
}

/// Writes Gaussians as an INRIA 3DGS binary little-endian PLY (the property order of
/// INRIA's `save_ply`; normals are zero). Validates first; the write is atomic.
pub fn write_inria_ply(path: impl AsRef<Path>, gaussians: &Gaussians) -> Result<()> {
    let path = path.as_ref();
    gaussians.validate(&show(path))?;
    write_atomically(path, |out| write_inria_body(out, gaussians))
}

/// The bytes [`write_inria_ply`] writes (after validating).
pub fn inria_ply_bytes(gaussians: &Gaussians) -> Result<Vec<u8>> {
    gaussians.validate("<memory>")?;
    let mut bytes = Vec::new();
    write_inria_body(&mut bytes, gaussians)
        .map_err(|e| crate::error::io_err("<memory>", "cannot write", e))?;
    Ok(bytes)
}

fn write_inria_body(out: &mut dyn Write, g: &Gaussians) -> std::io::Result<()> {
    let names = inria_property_names(g.sh_degree);
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\n",
        g.len()
    );
    for name in &names {
        header.push_str(&format!("property float {name}\n"));
    }
    header.push_str("end_header\n");
    out.write_all(header.as_bytes())?;

    let coeffs = g.sh_rest_coeffs();
    let mut row: Vec<u8> = Vec::with_capacity(names.len() * 4);
    for i in 0..g.len() {
        row.clear();
        let mut put = |v: f32| row.extend_from_slice(&v.to_le_bytes());
        g.means[i].iter().for_each(|v| put(*v));
        (0..3).for_each(|_| put(0.0));
        g.sh_dc[i].iter().for_each(|v| put(*v));
        if let Some(rest) = &g.sh_rest {
            // Channel-major on disk: all coefficients of red, then green, then blue.
            for channel in 0..3 {
                for k in 0..coeffs {
                    put(rest[(i * coeffs + k) * 3 + channel]);
                }
            }
        }
        put(g.opacity_logits[i]);
        g.log_scales[i].iter().for_each(|v| put(*v));
        g.rotations[i].iter().for_each(|v| put(*v));
        out.write_all(&row)?;
    }
    Ok(())
}

//! Shared validation: shape patterns with named dimensions that must agree across
//! tensors, and element checks (finite, ranges, monotone offsets, unit norms).

use std::collections::BTreeMap;

use half::f16;

use crate::container::{Buffer, Container, Dtype, Element};
use crate::error::{FormatError, Result};

/// A float tensor that the spec allows as F16 or F32.
#[derive(Debug, Clone, PartialEq)]
pub enum Floats {
    F16(Buffer<f16>),
    F32(Buffer<f32>),
}

impl Floats {
    /// Number of scalars.
    pub fn len(&self) -> usize {
        match self {
            Floats::F16(b) => b.len(),
            Floats::F32(b) => b.len(),
        }
    }

    /// Whether there are no scalars.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The stored dtype.
    pub fn dtype(&self) -> Dtype {
        match self {
            Floats::F16(_) => Dtype::F16,
            Floats::F32(_) => Dtype::F32,
        }
    }

    /// Scalar `i` widened to f32.
    pub fn get(&self, i: usize) -> f32 {
        match self {
            Floats::F16(b) => b[i].to_f32(),
            Floats::F32(b) => b[i],
        }
    }

    /// Copies scalars `start..start + out.len()` into `out` as f32.
    pub fn read_into(&self, start: usize, out: &mut [f32]) {
        match self {
            Floats::F16(b) => {
                let n = out.len();
                for (o, v) in out.iter_mut().zip(&b[start..start + n]) {
                    *o = v.to_f32();
                }
            }
            Floats::F32(b) => out.copy_from_slice(&b[start..start + out.len()]),
        }
    }

    /// All scalars as f32 (a copy).
    pub fn to_f32_vec(&self) -> Vec<f32> {
        let mut v = vec![0.0; self.len()];
        self.read_into(0, &mut v);
        v
    }

    /// The tolerance on unit norms that this precision can honour.
    pub fn unit_norm_tolerance(&self) -> f32 {
        match self {
            Floats::F16(_) => 1e-2,
            Floats::F32(_) => 1e-4,
        }
    }
}

impl From<Vec<f32>> for Floats {
    fn from(v: Vec<f32>) -> Self {
        Floats::F32(v.into())
    }
}

impl From<Vec<f16>> for Floats {
    fn from(v: Vec<f16>) -> Self {
        Floats::F16(v.into())
    }
}

/// A label tensor that the spec allows as U16 or U32, with the dtype's maximum reserved.
#[derive(Debug, Clone, PartialEq)]
pub enum Labels {
    U16(Buffer<u16>),
    U32(Buffer<u32>),
}

impl Labels {
    /// Number of labels.
    pub fn len(&self) -> usize {
        match self {
            Labels::U16(b) => b.len(),
            Labels::U32(b) => b.len(),
        }
    }

    /// Whether there are no labels.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The stored dtype.
    pub fn dtype(&self) -> Dtype {
        match self {
            Labels::U16(_) => Dtype::U16,
            Labels::U32(_) => Dtype::U32,
        }
    }

    /// Label `i`, `None` for the reserved "no mask" value.
    pub fn get(&self, i: usize) -> Option<u32> {
        match self {
            Labels::U16(b) => (b[i] != u16::MAX).then_some(u32::from(b[i])),
            Labels::U32(b) => (b[i] != u32::MAX).then_some(b[i]),
        }
    }

    /// The reserved "no mask" value of this dtype.
    pub fn none_value(&self) -> u32 {
        match self {
            Labels::U16(_) => u32::from(u16::MAX),
            Labels::U32(_) => u32::MAX,
        }
    }
}

/// Reads tensors of one container, binding named dimensions on first use and checking
/// every later use against the binding.
pub(crate) struct TensorReader<'c> {
    pub(crate) c: &'c Container,
    dims: BTreeMap<String, (usize, String)>,
}

impl<'c> TensorReader<'c> {
    pub(crate) fn new(c: &'c Container) -> Self {
        TensorReader {
            c,
            dims: BTreeMap::new(),
        }
    }

    pub(crate) fn path(&self) -> &str {
        self.c.path()
    }

    /// Binds a dimension from metadata or another source before tensors use it.
    pub(crate) fn bind(&mut self, sym: &str, value: usize, source: &str) {
        self.dims
            .insert(sym.to_string(), (value, source.to_string()));
    }

    pub(crate) fn dim(&self, sym: &str) -> usize {
        self.dims.get(sym).map_or(0, |d| d.0)
    }

    /// Checks a tensor's shape against a pattern like `"N,3"` (upper-case names bind,
    /// digits are fixed) and binds new names.
    pub(crate) fn check_shape(&mut self, name: &str, pattern: &str) -> Result<()> {
        let info = self.c.info(name, &format!("shape [{pattern}]"))?;
        let parts: Vec<&str> = pattern.split(',').map(str::trim).collect();
        let expected = || self.describe(&parts);
        if info.shape.len() != parts.len() {
            return Err(self.shape_err(name, &info.shape, expected()));
        }
        let mut fresh: Vec<(String, usize)> = Vec::new();
        for (part, &d) in parts.iter().zip(&info.shape) {
            if let Ok(fixed) = part.parse::<usize>() {
                if fixed != d {
                    return Err(self.shape_err(name, &info.shape, expected()));
                }
            } else if let Some((bound, _)) = self.dims.get(*part) {
                if *bound != d {
                    return Err(self.shape_err(name, &info.shape, expected()));
                }
            } else if let Some((_, v)) = fresh.iter().find(|(s, _)| s == part) {
                if *v != d {
                    return Err(self.shape_err(name, &info.shape, expected()));
                }
            } else {
                fresh.push((part.to_string(), d));
            }
        }
        for (sym, d) in fresh {
            self.dims.insert(sym, (d, name.to_string()));
        }
        Ok(())
    }

    fn describe(&self, parts: &[&str]) -> String {
        let dims: Vec<String> = parts
            .iter()
            .map(|p| match self.dims.get(*p) {
                Some((v, src)) => format!("{p}={v} (from {src})"),
                None => (*p).to_string(),
            })
            .collect();
        format!("[{}]", dims.join(", "))
    }

    fn shape_err(&self, name: &str, found: &[usize], expected: String) -> FormatError {
        FormatError::Shape {
            path: self.path().to_string(),
            tensor: name.to_string(),
            found: found.to_vec(),
            expected,
        }
    }

    /// A required tensor of a fixed dtype and shape pattern.
    pub(crate) fn req<T: Element>(&mut self, name: &str, pattern: &str) -> Result<Buffer<T>> {
        let buf = self.c.buffer::<T>(name)?;
        self.check_shape(name, pattern)?;
        Ok(buf)
    }

    /// An optional tensor: absent is fine, present must be right.
    pub(crate) fn opt<T: Element>(
        &mut self,
        name: &str,
        pattern: &str,
    ) -> Result<Option<Buffer<T>>> {
        if self.c.tensors().contains_key(name) {
            self.req(name, pattern).map(Some)
        } else {
            Ok(None)
        }
    }

    /// A required F16-or-F32 tensor.
    pub(crate) fn req_floats(&mut self, name: &str, pattern: &str) -> Result<Floats> {
        let info = self.c.info(name, "dtype F16 or F32")?;
        let floats = match info.dtype {
            Dtype::F16 => Floats::F16(self.c.buffer(name)?),
            Dtype::F32 => Floats::F32(self.c.buffer(name)?),
            other => return Err(self.dtype_err(name, other, "F16 or F32")),
        };
        self.check_shape(name, pattern)?;
        Ok(floats)
    }

    /// A required U16-or-U32 label tensor.
    pub(crate) fn req_labels(&mut self, name: &str, pattern: &str) -> Result<Labels> {
        let info = self.c.info(name, "dtype U16 or U32")?;
        let labels = match info.dtype {
            Dtype::U16 => Labels::U16(self.c.buffer(name)?),
            Dtype::U32 => Labels::U32(self.c.buffer(name)?),
            other => return Err(self.dtype_err(name, other, "U16 or U32")),
        };
        self.check_shape(name, pattern)?;
        Ok(labels)
    }

    fn dtype_err(&self, name: &str, found: Dtype, expected: &str) -> FormatError {
        FormatError::Dtype {
            path: self.path().to_string(),
            tensor: name.to_string(),
            found: found.to_string(),
            expected: expected.to_string(),
        }
    }

    /// A required metadata string.
    pub(crate) fn meta(&self, key: &str, expected: &str) -> Result<&'c str> {
        self.c
            .metadata()
            .get(key)
            .map(String::as_str)
            .ok_or_else(|| meta_err(self.path(), key, expected))
    }

    /// A metadata value parsed as `T`.
    pub(crate) fn meta_parse<T: std::str::FromStr>(&self, key: &str, expected: &str) -> Result<T> {
        self.meta(key, expected)?
            .parse()
            .map_err(|_| meta_err(self.path(), key, expected))
    }

    /// A metadata value holding a JSON array of strings.
    pub(crate) fn meta_strings(&self, key: &str) -> Result<Vec<String>> {
        let expected = "a JSON array of strings";
        serde_json::from_str(self.meta(key, expected)?)
            .map_err(|_| meta_err(self.path(), key, expected))
    }

    /// Metadata keys that are not part of the kind's fixed set, kept for round trips.
    pub(crate) fn extra_meta(&self, known: &[&str]) -> BTreeMap<String, String> {
        self.c
            .metadata()
            .iter()
            .filter(|(k, _)| {
                !known.contains(&k.as_str())
                    && k.as_str() != "format"
                    && k.as_str() != "format_version"
            })
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect()
    }
}

pub(crate) fn meta_err(path: &str, key: &str, expected: &str) -> FormatError {
    FormatError::Metadata {
        path: path.to_string(),
        key: key.to_string(),
        expected: expected.to_string(),
    }
}

pub(crate) fn shape_err(
    path: &str,
    tensor: &str,
    found: Vec<usize>,
    expected: String,
) -> FormatError {
    FormatError::Shape {
        path: path.to_string(),
        tensor: tensor.to_string(),
        found,
        expected,
    }
}

pub(crate) fn invalid(path: &str, tensor: &str, detail: String) -> FormatError {
    FormatError::Invalid {
        path: path.to_string(),
        tensor: tensor.to_string(),
        detail,
    }
}

pub(crate) fn out_of_range(
    path: &str,
    tensor: &str,
    index: usize,
    value: impl ToString,
    expected: impl Into<String>,
) -> FormatError {
    FormatError::OutOfRange {
        path: path.to_string(),
        tensor: tensor.to_string(),
        index,
        value: value.to_string(),
        expected: expected.into(),
    }
}

/// Checks that a length matches `expected`, naming the tensor and its role.
pub(crate) fn check_len(
    path: &str,
    tensor: &str,
    len: usize,
    expected: usize,
    what: &str,
) -> Result<()> {
    if len == expected {
        Ok(())
    } else {
        Err(shape_err(
            path,
            tensor,
            vec![len],
            format!("{expected} {what}"),
        ))
    }
}

/// The product of dimensions in checked arithmetic, left to right as SPEC.md 2 step 7
/// multiplies them; `None` when it overflows.
pub(crate) fn product(dims: &[usize]) -> Option<usize> {
    dims.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d))
}

/// Checks that a length equals the product of `dims` (a count such as V x H x W built
/// from header dimensions). The product is computed in checked arithmetic: a product that
/// overflows is a `shape` error, never a panic or a wrapped value (issue 20 item 1).
pub(crate) fn check_count(
    path: &str,
    tensor: &str,
    len: usize,
    dims: &[usize],
    what: &str,
) -> Result<()> {
    match product(dims) {
        Some(expected) => check_len(path, tensor, len, expected, what),
        None => Err(shape_err(
            path,
            tensor,
            vec![len],
            format!("{what}, a product of {dims:?} that overflows"),
        )),
    }
}

/// Every value finite.
pub(crate) fn check_finite<T: Copy + Into<f64>>(
    path: &str,
    tensor: &str,
    values: &[T],
) -> Result<()> {
    match values.iter().position(|v| !(*v).into().is_finite()) {
        None => Ok(()),
        Some(index) => Err(FormatError::NonFinite {
            path: path.to_string(),
            tensor: tensor.to_string(),
            index,
            value: format_float(values[index].into()),
        }),
    }
}

/// Every value finite, for a F16/F32 tensor.
pub(crate) fn check_finite_floats(path: &str, tensor: &str, values: &Floats) -> Result<()> {
    match values {
        Floats::F16(b) => check_finite(path, tensor, b),
        Floats::F32(b) => check_finite(path, tensor, b),
    }
}

/// Every value finite and within `[lo, hi]`.
pub(crate) fn check_unit_interval(path: &str, tensor: &str, values: &Floats) -> Result<()> {
    check_finite_floats(path, tensor, values)?;
    for i in 0..values.len() {
        let v = values.get(i);
        if !(0.0..=1.0).contains(&v) {
            return Err(out_of_range(
                path,
                tensor,
                i,
                format_float(f64::from(v)),
                "a value in [0, 1]",
            ));
        }
    }
    Ok(())
}

/// Every value a class id (>= 0) or -1, which stands for `none` ("none", "no label").
pub(crate) fn check_class_ids(path: &str, tensor: &str, values: &[i32], none: &str) -> Result<()> {
    match values.iter().position(|c| *c < -1) {
        Some(i) => Err(out_of_range(
            path,
            tensor,
            i,
            values[i],
            format!("a class id >= 0 or -1 for {none}"),
        )),
        None => Ok(()),
    }
}

/// Every index `< limit`, except the reserved `none` value when given.
pub(crate) fn check_ids<T: Copy + Into<u64>>(
    path: &str,
    tensor: &str,
    values: &[T],
    limit: u64,
    none: Option<u64>,
    what: &str,
) -> Result<()> {
    for (i, v) in values.iter().enumerate() {
        let v: u64 = (*v).into();
        if Some(v) != none && v >= limit {
            let expected = match none {
                Some(n) => format!("an index < {limit} into {what} or the reserved {n}"),
                None => format!("an index < {limit} into {what}"),
            };
            return Err(out_of_range(path, tensor, i, v, expected));
        }
    }
    Ok(())
}

/// CSR offsets: start at 0, never decrease, end at `total`.
pub(crate) fn check_offsets<T: Copy + Into<u64>>(
    path: &str,
    tensor: &str,
    offsets: &[T],
    total: u64,
) -> Result<()> {
    let mut prev = 0u64;
    for (i, v) in offsets.iter().enumerate() {
        let v: u64 = (*v).into();
        let ok = if i == 0 { v == 0 } else { v >= prev };
        if !ok {
            let expected = if i == 0 {
                "0".to_string()
            } else {
                format!("a value >= {prev} (offsets never decrease)")
            };
            return Err(out_of_range(path, tensor, i, v, expected));
        }
        prev = v;
    }
    if prev != total {
        return Err(out_of_range(
            path,
            tensor,
            offsets.len().saturating_sub(1),
            prev,
            format!("the last offset to equal {total}"),
        ));
    }
    Ok(())
}

/// Flags that are 0 or 1.
pub(crate) fn check_flags(path: &str, tensor: &str, values: &[u8]) -> Result<()> {
    match values.iter().position(|v| *v > 1) {
        None => Ok(()),
        Some(i) => Err(out_of_range(path, tensor, i, values[i], "0 or 1")),
    }
}

/// Each row of `values` ([rows, dim]) has unit L2 norm within the dtype's tolerance;
/// rows where `zero_row(row)` holds must instead be all zero.
///
/// Rows are visited in place (`chunks_exact` over the data): nothing is allocated from
/// `dim`, which comes from a header, so a file with zero rows and a huge D costs nothing
/// (issue 20 item 1: a `vec![0; dim]` row buffer aborted on D = 2^40 and reserved 16 GB
/// for D = 2^32).
pub(crate) fn check_unit_rows(
    path: &str,
    tensor: &str,
    values: &Floats,
    dim: usize,
    zero_row: &dyn Fn(usize) -> bool,
) -> Result<()> {
    if dim == 0 {
        return Ok(());
    }
    let tol = values.unit_norm_tolerance();
    let norms: Box<dyn Iterator<Item = f64> + '_> = match values {
        Floats::F16(b) => Box::new(
            b.chunks_exact(dim)
                .map(|row| l2_norm(row.iter().map(|v| v.to_f32()))),
        ),
        Floats::F32(b) => Box::new(b.chunks_exact(dim).map(|row| l2_norm(row.iter().copied()))),
    };
    for (r, norm) in norms.enumerate() {
        if zero_row(r) {
            if norm != 0.0 {
                return Err(invalid(
                    path,
                    tensor,
                    format!(
                        "row {r} is marked invalid but is not all zero (norm {})",
                        format_float(norm)
                    ),
                ));
            }
        } else if (norm - 1.0).abs() > f64::from(tol) {
            return Err(invalid(
                path,
                tensor,
                format!(
                    "row {r} has L2 norm {}, expected 1 within {tol}",
                    format_float(norm)
                ),
            ));
        }
    }
    Ok(())
}

/// L2 norm with the squares summed in f64 in index order (SPEC.md 3.5).
fn l2_norm(values: impl Iterator<Item = f32>) -> f64 {
    values
        .map(|v| f64::from(v) * f64::from(v))
        .sum::<f64>()
        .sqrt()
}

/// Shortest round-trip text of a float, with `nan`/`inf` spelled as in Python.
pub fn format_float(v: f64) -> String {
    if v.is_nan() {
        "nan".to_string()
    } else if v.is_infinite() {
        if v > 0.0 {
            "inf".to_string()
        } else {
            "-inf".to_string()
        }
    } else {
        format!("{v:?}")
    }
}

//! NumPy `.npy` (format versions 1.0, 2.0, 3.0) and `.npz` (a zip of `.npy` members,
//! stored or deflated).
//!
//! Read: little-endian (`<`) or byte-order-free (`|`) dtypes `b1 i1 i2 i4 i8 u1 u2 u4 u8
//! f2 f4 f8`, C order. Big-endian data, Fortran order, structured or object dtypes are
//! [`SceneError::Unsupported`]; a short file is [`SceneError::Truncated`]; a bad magic or
//! header dictionary is [`SceneError::Header`]; a data size that disagrees with the shape
//! is [`SceneError::Invalid`]. Write: version 1.0 (2.0 when the header needs it).

use std::collections::BTreeMap;

use std::io::Read;
use std::path::Path;

use half::f16;

use crate::error::{header_err, invalid, io_err, truncated, unsupported, Result, SceneError};
use crate::fsutil::{open_regular, read_bytes, show, write_atomically};

const MAGIC: &[u8; 6] = b"\x93NUMPY";

/// Longest header dictionary read, in bytes: NumPy's own `np.load` default
/// (`max_header_size=10000`, numpy/lib/format.py, "large headers may not be safe to load
/// securely"). A plain array's header is under 200 bytes even with 32 dimensions.
pub const MAX_HEADER_LEN: usize = 10_000;

/// Deepest nesting of tuples and lists in a header (`shape` is depth 1 inside the
/// dictionary; a structured `descr` a few more). The parser recurses once per level.
pub const MAX_HEADER_DEPTH: usize = 16;

/// Default cap on the bytes inflated from one `.npz` archive (all members together),
/// [`read_npz_capped`]: 256 MiB, far above a keypoint-pair file (~16 bytes per match).
pub const MAX_NPZ_BYTES: u64 = 256 << 20;

/// Element types read and written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NpyDtype {
    Bool,
    I8,
    I16,
    I32,
    I64,
    U8,
    U16,
    U32,
    U64,
    F16,
    F32,
    F64,
}

impl NpyDtype {
    /// NumPy's kind letter and size (`f4`).
    pub fn code(self) -> &'static str {
        match self {
            NpyDtype::Bool => "b1",
            NpyDtype::I8 => "i1",
            NpyDtype::I16 => "i2",
            NpyDtype::I32 => "i4",
            NpyDtype::I64 => "i8",
            NpyDtype::U8 => "u1",
            NpyDtype::U16 => "u2",
            NpyDtype::U32 => "u4",
            NpyDtype::U64 => "u8",
            NpyDtype::F16 => "f2",
            NpyDtype::F32 => "f4",
            NpyDtype::F64 => "f8",
        }
    }

    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            NpyDtype::Bool | NpyDtype::I8 | NpyDtype::U8 => 1,
            NpyDtype::I16 | NpyDtype::U16 | NpyDtype::F16 => 2,
            NpyDtype::I32 | NpyDtype::U32 | NpyDtype::F32 => 4,
            NpyDtype::I64 | NpyDtype::U64 | NpyDtype::F64 => 8,
        }
    }

    fn from_code(code: &str) -> Option<NpyDtype> {
        [
            NpyDtype::Bool,
            NpyDtype::I8,
            NpyDtype::I16,
            NpyDtype::I32,
            NpyDtype::I64,
            NpyDtype::U8,
            NpyDtype::U16,
            NpyDtype::U32,
            NpyDtype::U64,
            NpyDtype::F16,
            NpyDtype::F32,
            NpyDtype::F64,
        ]
        .into_iter()
        .find(|d| d.code() == code)
    }

    /// The `descr` NumPy writes (`<f4`, `|u1`).
    pub fn descr(self) -> String {
        let order = if self.size() == 1 { '|' } else { '<' };
        format!("{order}{}", self.code())
    }

    /// Whether the type is a float type.
    pub fn is_float(self) -> bool {
        matches!(self, NpyDtype::F16 | NpyDtype::F32 | NpyDtype::F64)
    }
}

/// The elements of an array, in C order.
#[derive(Debug, Clone, PartialEq)]
pub enum NpyData {
    Bool(Vec<bool>),
    I8(Vec<i8>),
    I16(Vec<i16>),
    I32(Vec<i32>),
    I64(Vec<i64>),
    U8(Vec<u8>),
    U16(Vec<u16>),
    U32(Vec<u32>),
    U64(Vec<u64>),
    F16(Vec<f16>),
    F32(Vec<f32>),
    F64(Vec<f64>),
}

/// Applies `$body` to the vector inside any variant.
macro_rules! each_variant {
    ($data:expr, $v:ident => $body:expr) => {
        match $data {
            NpyData::Bool($v) => $body,
            NpyData::I8($v) => $body,
            NpyData::I16($v) => $body,
            NpyData::I32($v) => $body,
            NpyData::I64($v) => $body,
            NpyData::U8($v) => $body,
            NpyData::U16($v) => $body,
            NpyData::U32($v) => $body,
            NpyData::U64($v) => $body,
            NpyData::F16($v) => $body,
            NpyData::F32($v) => $body,
            NpyData::F64($v) => $body,
        }
    };
}

/// A value that a conversion helper could not represent in the target type.
#[derive(Debug, Clone, PartialEq)]
pub struct ConversionError {
    /// Flat (C-order) index of the value.
    pub index: usize,
    /// The value as text.
    pub value: String,
    /// What the target needed (`an integer in 0..=4294967295`).
    pub expected: &'static str,
}

impl std::fmt::Display for ConversionError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "element {} is {}, expected {}",
            self.index, self.value, self.expected
        )
    }
}

/// An n-dimensional array.
#[derive(Debug, Clone, PartialEq)]
pub struct NpyArray {
    /// Dimensions (empty for a scalar).
    pub shape: Vec<usize>,
    /// Elements in C order; `len` = product of `shape`.
    pub data: NpyData,
}

impl NpyArray {
    /// An array, or `None` when the data length is not the product of the shape.
    pub fn new(shape: Vec<usize>, data: NpyData) -> Option<NpyArray> {
        let n = shape
            .iter()
            .try_fold(1usize, |acc, d| acc.checked_mul(*d))?;
        let len = each_variant!(&data, v => v.len());
        (n == len).then_some(NpyArray { shape, data })
    }

    /// The element type.
    pub fn dtype(&self) -> NpyDtype {
        match &self.data {
            NpyData::Bool(_) => NpyDtype::Bool,
            NpyData::I8(_) => NpyDtype::I8,
            NpyData::I16(_) => NpyDtype::I16,
            NpyData::I32(_) => NpyDtype::I32,
            NpyData::I64(_) => NpyDtype::I64,
            NpyData::U8(_) => NpyDtype::U8,
            NpyData::U16(_) => NpyDtype::U16,
            NpyData::U32(_) => NpyDtype::U32,
            NpyData::U64(_) => NpyDtype::U64,
            NpyData::F16(_) => NpyDtype::F16,
            NpyData::F32(_) => NpyDtype::F32,
            NpyData::F64(_) => NpyDtype::F64,
        }
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        each_variant!(&self.data, v => v.len())
    }

    /// Whether there are no elements.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Element `i` widened to f64 (exact except 64-bit integers beyond 2^53).
    pub fn get_f64(&self, i: usize) -> Option<f64> {
        match &self.data {
            NpyData::Bool(v) => v.get(i).map(|b| f64::from(u8::from(*b))),
            NpyData::I8(v) => v.get(i).map(|x| f64::from(*x)),
            NpyData::I16(v) => v.get(i).map(|x| f64::from(*x)),
            NpyData::I32(v) => v.get(i).map(|x| f64::from(*x)),
            NpyData::I64(v) => v.get(i).map(|x| *x as f64),
            NpyData::U8(v) => v.get(i).map(|x| f64::from(*x)),
            NpyData::U16(v) => v.get(i).map(|x| f64::from(*x)),
            NpyData::U32(v) => v.get(i).map(|x| f64::from(*x)),
            NpyData::U64(v) => v.get(i).map(|x| *x as f64),
            NpyData::F16(v) => v.get(i).map(|x| x.to_f64()),
            NpyData::F32(v) => v.get(i).map(|x| f64::from(*x)),
            NpyData::F64(v) => v.get(i).copied(),
        }
    }

    /// All elements as f64.
    pub fn to_f64_vec(&self) -> Vec<f64> {
        (0..self.len()).filter_map(|i| self.get_f64(i)).collect()
    }

    /// All elements as f32 (f32 data is copied exactly; others round to nearest).
    pub fn to_f32_vec(&self) -> Vec<f32> {
        match &self.data {
            NpyData::F32(v) => v.clone(),
            NpyData::F16(v) => v.iter().map(|x| x.to_f32()).collect(),
            _ => (0..self.len())
                .filter_map(|i| self.get_f64(i))
                .map(|x| x as f32)
                .collect(),
        }
    }

    /// All elements as i64: integers exactly, floats only when they are whole numbers
    /// (NumPy label maps are often stored as float).
    pub fn to_i64_vec(&self) -> Result<Vec<i64>, ConversionError> {
        let expected = "a whole number in the i64 range";
        match &self.data {
            NpyData::I64(v) => Ok(v.clone()),
            NpyData::U64(v) => v
                .iter()
                .enumerate()
                .map(|(i, x)| {
                    i64::try_from(*x).map_err(|_| ConversionError {
                        index: i,
                        value: x.to_string(),
                        expected,
                    })
                })
                .collect(),
            _ => (0..self.len())
                .map(|i| {
                    let x = self.get_f64(i).unwrap_or(f64::NAN);
                    if x.fract() == 0.0 && x >= -(2f64.powi(63)) && x < 2f64.powi(63) {
                        Ok(x as i64)
                    } else {
                        Err(ConversionError {
                            index: i,
                            value: x.to_string(),
                            expected,
                        })
                    }
                })
                .collect(),
        }
    }

    /// All elements as u32 (whole numbers in 0..=4294967295 only).
    pub fn to_u32_vec(&self) -> Result<Vec<u32>, ConversionError> {
        if let NpyData::U32(v) = &self.data {
            return Ok(v.clone());
        }
        let expected = "a whole number in 0..=4294967295";
        self.to_i64_vec()
            .map_err(|e| ConversionError { expected, ..e })?
            .into_iter()
            .enumerate()
            .map(|(i, x)| {
                u32::try_from(x).map_err(|_| ConversionError {
                    index: i,
                    value: x.to_string(),
                    expected,
                })
            })
            .collect()
    }

    /// The f32 elements, when the dtype is f4.
    pub fn as_f32(&self) -> Option<&[f32]> {
        match &self.data {
            NpyData::F32(v) => Some(v),
            _ => None,
        }
    }

    /// The f16 elements, when the dtype is f2.
    pub fn as_f16(&self) -> Option<&[f16]> {
        match &self.data {
            NpyData::F16(v) => Some(v),
            _ => None,
        }
    }

    /// The `.npy` bytes (format 1.0, or 2.0 when the header exceeds 65535 bytes).
    pub fn to_bytes(&self) -> Vec<u8> {
        let shape = match self.shape.as_slice() {
            [one] => format!("({one},)"),
            dims => format!(
                "({})",
                dims.iter()
                    .map(ToString::to_string)
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        };
        let dict = format!(
            "{{'descr': '{}', 'fortran_order': False, 'shape': {shape}, }}",
            self.dtype().descr()
        );
        // Pad with spaces so the data starts on a 64-byte boundary, ending with '\n'.
        let fixed_v1 = MAGIC.len() + 2 + 2;
        let padded = |fixed: usize| (fixed + dict.len() + 1).div_ceil(64) * 64 - fixed;
        let (version, fixed) = if padded(fixed_v1) <= usize::from(u16::MAX) {
            (1u8, fixed_v1)
        } else {
            (2u8, fixed_v1 + 2)
        };
        let header_len = padded(fixed);
        let mut out = Vec::with_capacity(fixed + header_len + self.len() * self.dtype().size());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&[version, 0]);
        if version == 1 {
            out.extend_from_slice(&(header_len as u16).to_le_bytes());
        } else {
            out.extend_from_slice(&(header_len as u32).to_le_bytes());
        }
        out.extend_from_slice(dict.as_bytes());
        out.resize(fixed + header_len - 1, b' ');
        out.push(b'\n');
        match &self.data {
            NpyData::Bool(v) => out.extend(v.iter().map(|b| u8::from(*b))),
            NpyData::I8(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
            NpyData::I16(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
            NpyData::I32(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
            NpyData::I64(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
            NpyData::U8(v) => out.extend_from_slice(v),
            NpyData::U16(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
            NpyData::U32(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
            NpyData::U64(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
            NpyData::F16(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
            NpyData::F32(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
            NpyData::F64(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
        }
        out
    }
}

/// Reads a `.npy` file.
pub fn read_npy(path: impl AsRef<Path>) -> Result<NpyArray> {
    let path = path.as_ref();
    parse_npy(&read_bytes(path)?, &show(path))
}

/// Writes a `.npy` file atomically.
pub fn write_npy(path: impl AsRef<Path>, array: &NpyArray) -> Result<()> {
    let bytes = array.to_bytes();
    write_atomically(path.as_ref(), |out| out.write_all(&bytes))
}

/// The `.npz` bytes of `arrays` (member `<name>.npy` each, in the given order), stored
/// uncompressed as `np.savez` writes them; every time stamp is the zip epoch (1980-01-01),
/// so the same arrays always give the same bytes. `label` names the file in errors.
pub fn npz_bytes(arrays: &[(&str, &NpyArray)], label: &str) -> Result<Vec<u8>> {
    use std::io::Write;
    let zip_err = |source| SceneError::Zip {
        path: label.to_string(),
        source,
    };
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    for (name, array) in arrays {
        let bytes = array.to_bytes();
        let options = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored)
            .large_file(bytes.len() as u64 >= u64::from(u32::MAX));
        zip.start_file(format!("{name}.npy"), options)
            .map_err(zip_err)?;
        zip.write_all(&bytes)
            .map_err(|e| io_err(label, "cannot add a member", e))?;
    }
    Ok(zip.finish().map_err(zip_err)?.into_inner())
}

/// Writes a `.npz` file (see [`npz_bytes`]) atomically: a temporary file in the same
/// folder, renamed over `path` once complete.
pub fn write_npz(path: impl AsRef<Path>, arrays: &[(&str, &NpyArray)]) -> Result<()> {
    let path = path.as_ref();
    let bytes = npz_bytes(arrays, &show(path))?;
    write_atomically(path, |out| out.write_all(&bytes))
}

/// Reads every `.npy` member of a `.npz` archive, keyed by member name without `.npy`,
/// inflating at most [`MAX_NPZ_BYTES`] in all.
pub fn read_npz(path: impl AsRef<Path>) -> Result<BTreeMap<String, NpyArray>> {
    read_npz_capped(path, MAX_NPZ_BYTES)
}

/// [`read_npz`] inflating at most `max_bytes` in all. Each member is inflated through a
/// bounded reader: first its `.npy` header, which fixes the member's exact size; that
/// size must equal the size the zip declares and fit in what is left of `max_bytes`;
/// then at most that many bytes + 1 are inflated, and a member that inflates to more or
/// less is an error. The zip's declared size alone is never trusted.
pub fn read_npz_capped(
    path: impl AsRef<Path>,
    max_bytes: u64,
) -> Result<BTreeMap<String, NpyArray>> {
    let path = path.as_ref();
    let label = show(path);
    let (file, _) = open_regular(path)?;
    let zip_err = |source| SceneError::Zip {
        path: label.clone(),
        source,
    };
    // numpy writes the archive from byte 0. With the offset known, each candidate end
    // record is checked in constant time; left to detect it, zip searches the whole file
    // for the central directory once per candidate, so a file of end-record signatures
    // took time quadratic in its size (16,000 of them, 350 KB: 2 s; issue 20).
    let config = zip::read::Config {
        archive_offset: zip::read::ArchiveOffset::Known(0),
    };
    let mut archive =
        zip::ZipArchive::with_config(config, std::io::BufReader::new(file)).map_err(zip_err)?;
    let mut arrays = BTreeMap::new();
    let mut budget = max_bytes;
    for i in 0..archive.len() {
        let mut member = archive.by_index(i).map_err(zip_err)?;
        let Some(key) = member.name().strip_suffix(".npy").map(str::to_string) else {
            continue;
        };
        let member_label = format!("{label}[{key}.npy]");
        let declared = member.size();
        let bytes = inflate_member(&mut member, declared, budget, &member_label)?;
        budget -= bytes.len() as u64;
        let array = parse_npy(&bytes, &member_label)?;
        arrays.insert(key, array);
    }
    Ok(arrays)
}

/// Inflates one `.npy` member: header first, then exactly the bytes it announces.
fn inflate_member(
    member: &mut impl Read,
    declared: u64,
    budget: u64,
    label: &str,
) -> Result<Vec<u8>> {
    let read_err = |e| io_err(label, "cannot decompress the member", e);
    // Preamble: magic, version, and a 2-byte (v1) or 4-byte (v2, v3) header length.
    let mut head = Vec::new();
    member
        .by_ref()
        .take(10)
        .read_to_end(&mut head)
        .map_err(read_err)?;
    if head.get(6).is_some_and(|major| *major >= 2) {
        member
            .by_ref()
            .take(2)
            .read_to_end(&mut head)
            .map_err(read_err)?;
    }
    let header_len = preamble(&head, label)?.1;
    check_header_len(header_len, label)?;
    member
        .by_ref()
        .take(header_len as u64)
        .read_to_end(&mut head)
        .map_err(read_err)?;
    let header = read_header(&head, label)?;
    let expected = (header.data_start as u64).saturating_add(header.nbytes as u64);
    if declared != expected {
        return Err(invalid(
            label,
            "zip uncompressed size",
            format!(
                "the zip declares {declared} bytes, but the .npy header (shape {:?} of {}) makes the member {expected} bytes",
                header.shape,
                header.dtype.descr()
            ),
        ));
    }
    if expected > budget {
        return Err(invalid(
            label,
            "size",
            format!(
                "the member inflates to {expected} bytes, above the {budget} bytes left of the archive's inflate cap"
            ),
        ));
    }
    let mut bytes = head;
    let rest = expected - bytes.len() as u64;
    bytes
        .try_reserve_exact(usize::try_from(rest).unwrap_or(usize::MAX))
        .map_err(|_| {
            invalid(
                label,
                "size",
                format!("{expected} bytes do not fit in memory"),
            )
        })?;
    member
        .by_ref()
        .take(rest.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(read_err)?;
    if bytes.len() as u64 != expected {
        return Err(invalid(
            label,
            "size",
            format!(
                "the member inflates to {} bytes, its header and the zip say {expected}",
                if bytes.len() as u64 > expected {
                    format!("more than {expected}")
                } else {
                    bytes.len().to_string()
                }
            ),
        ));
    }
    Ok(bytes)
}

/// Parses `.npy` bytes; `label` names the file in errors.
pub fn parse_npy(bytes: &[u8], label: &str) -> Result<NpyArray> {
    let NpyHeader {
        dtype,
        shape,
        data_start,
        nbytes,
    } = read_header(bytes, label)?;
    let data = bytes.get(data_start..).unwrap_or_default();
    if data.len() < nbytes {
        return Err(truncated(
            label,
            format!(
                "shape {shape:?} of {} needs {nbytes} data bytes, the file has {}",
                dtype.descr(),
                data.len()
            ),
        ));
    }
    if data.len() > nbytes {
        return Err(invalid(
            label,
            "shape",
            format!(
                "{shape:?} of {} is {nbytes} bytes but the file holds {} data bytes",
                dtype.descr(),
                data.len()
            ),
        ));
    }
    let values = decode(dtype, data).map_err(|i| {
        invalid(
            label,
            "data",
            format!("element {i} is not a valid bool (0 or 1)"),
        )
    })?;
    Ok(NpyArray {
        shape,
        data: values,
    })
}

/// What a `.npy` header says.
struct NpyHeader {
    dtype: NpyDtype,
    shape: Vec<usize>,
    /// Offset of the first data byte.
    data_start: usize,
    /// Data bytes the shape and dtype need.
    nbytes: usize,
}

/// Parses the preamble and header dictionary at the start of `bytes`.
fn read_header(bytes: &[u8], label: &str) -> Result<NpyHeader> {
    let (header, data_start) = split_header(bytes, label)?;
    let dict = parse_dict(&header)
        .map_err(|e| header_err(label, format!("header dictionary {header:?}: {e}")))?;
    let (dtype, shape) = interpret_dict(&dict, label)?;
    let nbytes = shape
        .iter()
        .try_fold(1usize, |acc, d| acc.checked_mul(*d))
        .and_then(|n| n.checked_mul(dtype.size()))
        .ok_or_else(|| {
            invalid(
                label,
                "shape",
                format!("{shape:?} has more elements than memory can hold"),
            )
        })?;
    Ok(NpyHeader {
        dtype,
        shape,
        data_start,
        nbytes,
    })
}

/// Checks magic and version; returns (offset of the header dictionary, its length).
fn preamble(bytes: &[u8], label: &str) -> Result<(usize, usize)> {
    if bytes.len() < MAGIC.len() + 2 {
        return Err(truncated(
            label,
            format!("{} bytes, shorter than the .npy preamble", bytes.len()),
        ));
    }
    if bytes.get(..MAGIC.len()) != Some(MAGIC.as_slice()) {
        return Err(header_err(
            label,
            "bad magic: not a NumPy .npy file (expected \\x93NUMPY)",
        ));
    }
    let major = bytes.get(6).copied().unwrap_or(0);
    let minor = bytes.get(7).copied().unwrap_or(0);
    let (len_bytes, start) = match major {
        1 => (2, 10),
        2 | 3 => (4, 12),
        _ => {
            return Err(unsupported(
                label,
                "npy format version",
                format!("{major}.{minor} (1.0, 2.0 and 3.0 are read)"),
            ))
        }
    };
    let raw_len = bytes
        .get(8..8 + len_bytes)
        .ok_or_else(|| truncated(label, "the file ends inside the header length"))?;
    let header_len = raw_len
        .iter()
        .rev()
        .fold(0usize, |acc, b| (acc << 8) | usize::from(*b));
    Ok((start, header_len))
}

/// Refuses a header dictionary longer than [`MAX_HEADER_LEN`].
fn check_header_len(header_len: usize, label: &str) -> Result<()> {
    if header_len > MAX_HEADER_LEN {
        return Err(header_err(
            label,
            format!(
                "the header is {header_len} bytes, above the {MAX_HEADER_LEN}-byte limit of NumPy's own reader (np.load max_header_size)"
            ),
        ));
    }
    Ok(())
}

/// Checks magic, version and header length (present, and at most [`MAX_HEADER_LEN`]);
/// returns the header text and where the data starts.
fn split_header(bytes: &[u8], label: &str) -> Result<(String, usize)> {
    let (start, header_len) = preamble(bytes, label)?;
    let major = bytes.get(6).copied().unwrap_or(0);
    let end = start + header_len;
    let raw = bytes.get(start..end).ok_or_else(|| {
        truncated(
            label,
            format!(
                "the header announces {header_len} bytes, the file has {}",
                bytes.len().saturating_sub(start)
            ),
        )
    })?;
    check_header_len(header_len, label)?;
    // Versions 1 and 2 use latin-1 headers, version 3 UTF-8; a valid header is ASCII.
    let text = if major == 3 {
        String::from_utf8(raw.to_vec())
            .map_err(|_| header_err(label, "version 3 header is not UTF-8"))?
    } else {
        raw.iter().map(|b| char::from(*b)).collect()
    };
    Ok((text, end))
}

/// The parts of a Python literal that `.npy` headers use.
#[derive(Debug, Clone, PartialEq)]
enum PyValue {
    Str(String),
    Bool(bool),
    Int(u64),
    Tuple(Vec<PyValue>),
    List(Vec<PyValue>),
}

fn parse_dict(text: &str) -> Result<BTreeMap<String, PyValue>, String> {
    let mut p = PyParser {
        chars: text.chars().collect(),
        pos: 0,
        depth: 0,
    };
    p.expect('{')?;
    let mut dict = BTreeMap::new();
    loop {
        p.skip_ws();
        if p.eat('}') {
            break;
        }
        let PyValue::Str(key) = p.value()? else {
            return Err("dictionary keys must be strings".to_string());
        };
        p.expect(':')?;
        let value = p.value()?;
        dict.insert(key, value);
        p.skip_ws();
        if !p.eat(',') {
            p.expect('}')?;
            break;
        }
    }
    p.skip_ws();
    if p.pos != p.chars.len() {
        return Err(format!(
            "unexpected text after the dictionary at character {}",
            p.pos
        ));
    }
    Ok(dict)
}

struct PyParser {
    chars: Vec<char>,
    pos: usize,
    /// Open tuples and lists around the current position (at most [`MAX_HEADER_DEPTH`]).
    depth: usize,
}

impl PyParser {
    fn skip_ws(&mut self) {
        while self.chars.get(self.pos).is_some_and(|c| c.is_whitespace()) {
            self.pos += 1;
        }
    }

    fn eat(&mut self, c: char) -> bool {
        self.skip_ws();
        if self.chars.get(self.pos) == Some(&c) {
            self.pos += 1;
            true
        } else {
            false
        }
    }

    fn expect(&mut self, c: char) -> Result<(), String> {
        if self.eat(c) {
            Ok(())
        } else {
            Err(format!("expected {c:?} at character {}", self.pos))
        }
    }

    fn value(&mut self) -> Result<PyValue, String> {
        self.skip_ws();
        match self.chars.get(self.pos).copied() {
            Some(q @ ('\'' | '"')) => {
                self.pos += 1;
                let start = self.pos;
                while self.chars.get(self.pos).is_some_and(|c| *c != q) {
                    self.pos += 1;
                }
                let s: String = self
                    .chars
                    .get(start..self.pos)
                    .unwrap_or_default()
                    .iter()
                    .collect();
                if !self.eat(q) {
                    return Err("unterminated string".to_string());
                }
                Ok(PyValue::Str(s))
            }
            Some('(') => self.sequence(')').map(PyValue::Tuple),
            Some('[') => self.sequence(']').map(PyValue::List),
            Some(c) if c.is_ascii_digit() => {
                let start = self.pos;
                while self.chars.get(self.pos).is_some_and(|c| c.is_ascii_digit()) {
                    self.pos += 1;
                }
                let digits: String = self
                    .chars
                    .get(start..self.pos)
                    .unwrap_or_default()
                    .iter()
                    .collect();
                // Python 2 headers may write long integers as `3L`.
                self.eat('L');
                digits
                    .parse()
                    .map(PyValue::Int)
                    .map_err(|_| format!("integer {digits} is too large"))
            }
            Some(_) => {
                let start = self.pos;
                while self
                    .chars
                    .get(self.pos)
                    .is_some_and(|c| c.is_ascii_alphabetic())
                {
                    self.pos += 1;
                }
                let word: String = self
                    .chars
                    .get(start..self.pos)
                    .unwrap_or_default()
                    .iter()
                    .collect();
                match word.as_str() {
                    "True" => Ok(PyValue::Bool(true)),
                    "False" => Ok(PyValue::Bool(false)),
                    _ => Err(format!("unexpected value at character {start}")),
                }
            }
            None => Err("unexpected end of header".to_string()),
        }
    }

    fn sequence(&mut self, close: char) -> Result<Vec<PyValue>, String> {
        if self.depth >= MAX_HEADER_DEPTH {
            return Err(format!(
                "tuples and lists nested deeper than {MAX_HEADER_DEPTH} levels at character {}",
                self.pos
            ));
        }
        self.depth += 1;
        self.pos += 1;
        let mut items = Vec::new();
        let result = loop {
            if self.eat(close) {
                break Ok(items);
            }
            match self.value() {
                Ok(v) => items.push(v),
                Err(e) => break Err(e),
            }
            if !self.eat(',') {
                break self.expect(close).map(|()| items);
            }
        };
        self.depth -= 1;
        result
    }
}

fn interpret_dict(dict: &BTreeMap<String, PyValue>, label: &str) -> Result<(NpyDtype, Vec<usize>)> {
    let descr = match dict.get("descr") {
        Some(PyValue::Str(s)) => s.as_str(),
        Some(_) => {
            return Err(unsupported(
                label,
                "dtype",
                "a structured dtype (only plain numeric dtypes are read)",
            ))
        }
        None => return Err(header_err(label, "the header has no 'descr' key")),
    };
    match dict.get("fortran_order") {
        Some(PyValue::Bool(false)) => {}
        Some(PyValue::Bool(true)) => {
            return Err(unsupported(
                label,
                "memory order",
                "fortran_order is True (save a C-ordered array, e.g. np.ascontiguousarray)",
            ))
        }
        _ => {
            return Err(header_err(
                label,
                "the header has no boolean 'fortran_order' key",
            ))
        }
    }
    let shape = match dict.get("shape") {
        Some(PyValue::Tuple(dims)) => dims
            .iter()
            .map(|d| match d {
                PyValue::Int(n) => usize::try_from(*n)
                    .map_err(|_| header_err(label, format!("dimension {n} is too large"))),
                _ => Err(header_err(label, "'shape' must be a tuple of integers")),
            })
            .collect::<Result<Vec<_>>>()?,
        _ => return Err(header_err(label, "the header has no 'shape' tuple")),
    };
    let dtype = parse_descr(descr).ok_or_else(|| {
        let detail = if descr.starts_with('>') {
            format!("{descr:?} is big-endian (only little-endian data is read)")
        } else {
            format!("{descr:?} (readable: b1 i1 i2 i4 i8 u1 u2 u4 u8 f2 f4 f8, little-endian)")
        };
        unsupported(label, "dtype", detail)
    })?;
    Ok((dtype, shape))
}

/// `<f4`, `|u1`, and `=`/`<` for single bytes; never `>` (big-endian) for wider types.
fn parse_descr(descr: &str) -> Option<NpyDtype> {
    let mut chars = descr.chars();
    let order = chars.next()?;
    let dtype = NpyDtype::from_code(chars.as_str())?;
    match order {
        '<' => Some(dtype),
        '|' | '>' | '=' if dtype.size() == 1 => Some(dtype),
        _ => None,
    }
}

/// Decodes little-endian elements; `Err(i)` for a bool byte other than 0 or 1.
fn decode(dtype: NpyDtype, data: &[u8]) -> Result<NpyData, usize> {
    macro_rules! le {
        ($t:ty, $n:literal, $var:ident) => {
            NpyData::$var(
                data.chunks_exact($n)
                    .map(|c| {
                        let mut a = [0u8; $n];
                        a.copy_from_slice(c);
                        <$t>::from_le_bytes(a)
                    })
                    .collect(),
            )
        };
    }
    Ok(match dtype {
        NpyDtype::Bool => NpyData::Bool(
            data.iter()
                .enumerate()
                .map(|(i, b)| match b {
                    0 => Ok(false),
                    1 => Ok(true),
                    _ => Err(i),
                })
                .collect::<Result<_, _>>()?,
        ),
        NpyDtype::I8 => NpyData::I8(data.iter().map(|b| i8::from_le_bytes([*b])).collect()),
        NpyDtype::U8 => NpyData::U8(data.to_vec()),
        NpyDtype::I16 => le!(i16, 2, I16),
        NpyDtype::U16 => le!(u16, 2, U16),
        NpyDtype::F16 => NpyData::F16(
            data.chunks_exact(2)
                .map(|c| {
                    f16::from_bits(u16::from_le_bytes([
                        c.first().copied().unwrap_or(0),
                        c.get(1).copied().unwrap_or(0),
                    ]))
                })
                .collect(),
        ),
        NpyDtype::I32 => le!(i32, 4, I32),
        NpyDtype::U32 => le!(u32, 4, U32),
        NpyDtype::F32 => le!(f32, 4, F32),
        NpyDtype::I64 => le!(i64, 8, I64),
        NpyDtype::U64 => le!(u64, 8, U64),
        NpyDtype::F64 => le!(f64, 8, F64),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_dictionary_variants() {
        let d = parse_dict("{'descr': '<f4', 'fortran_order': False, 'shape': (3, 4), }")
            .unwrap_or_default();
        assert_eq!(
            d.get("shape"),
            Some(&PyValue::Tuple(vec![PyValue::Int(3), PyValue::Int(4)]))
        );
        let d = parse_dict("{\"descr\":\"|u1\",\"fortran_order\":False,\"shape\":()}")
            .unwrap_or_default();
        assert_eq!(d.get("shape"), Some(&PyValue::Tuple(vec![])));
        assert!(parse_dict("{'descr': '<f4'").is_err());
        assert!(parse_dict("{'descr': <f4}").is_err());
    }

    #[test]
    fn npz_round_trip_is_deterministic() {
        let a = NpyArray::new(
            vec![3, 2],
            NpyData::F32(vec![0.5, 1.0, 2.0, -3.0, 4.25, 5.0]),
        );
        let b = NpyArray::new(vec![0, 2], NpyData::F32(Vec::new()));
        let (Some(a), Some(b)) = (a, b) else {
            panic!("shapes")
        };
        let dir = tempfile::tempdir().map_err(|e| e.to_string());
        let Ok(dir) = dir else { panic!("tempdir") };
        let path = dir.path().join("x.npz");
        assert!(write_npz(&path, &[("kpts_i", &a), ("kpts_j", &b)]).is_ok());
        let read = read_npz(&path).unwrap_or_default();
        assert_eq!(read.get("kpts_i"), Some(&a));
        assert_eq!(read.get("kpts_j"), Some(&b));
        let once = npz_bytes(&[("kpts_i", &a)], "x").unwrap_or_default();
        assert!(!once.is_empty());
        assert_eq!(npz_bytes(&[("kpts_i", &a)], "x").unwrap_or_default(), once);
    }

    #[test]
    fn descr_orders() {
        assert_eq!(parse_descr("<f4"), Some(NpyDtype::F32));
        assert_eq!(parse_descr("|b1"), Some(NpyDtype::Bool));
        assert_eq!(parse_descr(">f4"), None);
        assert_eq!(parse_descr("<U4"), None);
    }
}

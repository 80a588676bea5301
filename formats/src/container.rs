//! The safetensors container: header parsing with full structural validation,
//! memory mapping, and zero-copy typed views of tensor data.
//!
//! The header is parsed here rather than by the `safetensors` crate so that every
//! structural defect maps to a precise [`FormatError`] (truncation versus a lying header),
//! and so that the Python reader can mirror the exact same checks (SPEC.md "Container").

use std::collections::BTreeMap;
use std::fmt;
use std::ops::Deref;
use std::path::Path;
use std::sync::Arc;

use bytemuck::Pod;
use half::f16;

use crate::error::{FormatError, Result};

#[cfg(target_endian = "big")]
compile_error!("profuse-formats reads little-endian safetensors data by casting; big-endian hosts are not supported");

/// Largest header accepted, as in the reference safetensors implementation.
pub const MAX_HEADER_BYTES: u64 = 100_000_000;

/// Element types of the safetensors container.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Dtype {
    Bool,
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    U64,
    I64,
    F16,
    BF16,
    F32,
    F64,
}

impl Dtype {
    /// Name as written in the safetensors header.
    pub fn name(self) -> &'static str {
        match self {
            Dtype::Bool => "BOOL",
            Dtype::U8 => "U8",
            Dtype::I8 => "I8",
            Dtype::U16 => "U16",
            Dtype::I16 => "I16",
            Dtype::U32 => "U32",
            Dtype::I32 => "I32",
            Dtype::U64 => "U64",
            Dtype::I64 => "I64",
            Dtype::F16 => "F16",
            Dtype::BF16 => "BF16",
            Dtype::F32 => "F32",
            Dtype::F64 => "F64",
        }
    }

    /// Parses a header dtype name; `None` for names outside the container spec.
    pub fn parse(name: &str) -> Option<Dtype> {
        Some(match name {
            "BOOL" => Dtype::Bool,
            "U8" => Dtype::U8,
            "I8" => Dtype::I8,
            "U16" => Dtype::U16,
            "I16" => Dtype::I16,
            "U32" => Dtype::U32,
            "I32" => Dtype::I32,
            "U64" => Dtype::U64,
            "I64" => Dtype::I64,
            "F16" => Dtype::F16,
            "BF16" => Dtype::BF16,
            "F32" => Dtype::F32,
            "F64" => Dtype::F64,
            _ => return None,
        })
    }

    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            Dtype::Bool | Dtype::U8 | Dtype::I8 => 1,
            Dtype::U16 | Dtype::I16 | Dtype::F16 | Dtype::BF16 => 2,
            Dtype::U32 | Dtype::I32 | Dtype::F32 => 4,
            Dtype::U64 | Dtype::I64 | Dtype::F64 => 8,
        }
    }
}

impl fmt::Display for Dtype {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A scalar type that can be viewed directly in a little-endian tensor buffer.
pub trait Scalar: Pod + Send + Sync + fmt::Debug + 'static {
    const DTYPE: Dtype;
}

macro_rules! scalar {
    ($($t:ty => $d:ident),* $(,)?) => { $(impl Scalar for $t { const DTYPE: Dtype = Dtype::$d; })* };
}
scalar!(u8 => U8, i8 => I8, u16 => U16, i16 => I16, u32 => U32, i32 => I32, u64 => U64, i64 => I64,
        f16 => F16, f32 => F32, f64 => F64);

/// An element of a typed buffer: a scalar, or a fixed-size row of scalars (`[f32; 3]`
/// for a point), so that `Buffer<[f32; 3]>` indexes points rather than coordinates.
pub trait Element: Pod + Send + Sync + fmt::Debug + 'static {
    type Scalar: Scalar;
    /// Scalars per element.
    const LANES: usize;
}

impl<T: Scalar> Element for T {
    type Scalar = T;
    const LANES: usize = 1;
}

/// Fixed-size rows of a scalar, the row lengths the file kinds use.
macro_rules! row_element {
    ($($n:literal),*) => { $(
        impl Element for [f32; $n] { type Scalar = f32; const LANES: usize = $n; }
        impl Element for [f64; $n] { type Scalar = f64; const LANES: usize = $n; }
        impl Element for [u32; $n] { type Scalar = u32; const LANES: usize = $n; }
        impl Element for [u8; $n] { type Scalar = u8; const LANES: usize = $n; }
    )* };
}
row_element!(2, 3, 4, 12);
// Fixed-point u128 sums stored as (low, high) words (`fuse_partial`).
impl Element for [u64; 2] {
    type Scalar = u64;
    const LANES: usize = 2;
}

/// The bytes behind a container: a read-only memory map, or an in-memory copy.
#[derive(Debug)]
pub(crate) enum Bytes {
    Mapped(memmap2::Mmap),
    Owned(Vec<u8>),
}

impl Deref for Bytes {
    type Target = [u8];
    fn deref(&self) -> &[u8] {
        match self {
            Bytes::Mapped(m) => m,
            Bytes::Owned(v) => v,
        }
    }
}

/// Tensor data typed as `T`: borrowed from the memory map when the file's bytes are
/// aligned for `T` (the normal case: safetensors pads its header to 8 bytes and our
/// writer orders tensors by alignment), copied otherwise. Cheap to clone.
pub struct Buffer<T: Element> {
    repr: Repr<T>,
}

enum Repr<T> {
    Owned(Arc<Vec<T>>),
    Mapped {
        bytes: Arc<Bytes>,
        start: usize,
        len: usize,
    },
}

impl<T: Element> Buffer<T> {
    /// Whether the data is viewed in place in the mapped file (no copy was made).
    pub fn is_zero_copy(&self) -> bool {
        matches!(self.repr, Repr::Mapped { .. })
    }

    /// Copies the data out into a vector.
    pub fn to_vec(&self) -> Vec<T> {
        self.deref().to_vec()
    }

    fn from_bytes(bytes: &Arc<Bytes>, start: usize, len: usize) -> Self {
        let raw = &bytes[start..start + len * std::mem::size_of::<T>()];
        if bytemuck::try_cast_slice::<u8, T>(raw).is_ok() {
            Buffer {
                repr: Repr::Mapped {
                    bytes: Arc::clone(bytes),
                    start,
                    len,
                },
            }
        } else {
            Buffer {
                repr: Repr::Owned(Arc::new(bytemuck::pod_collect_to_vec(raw))),
            }
        }
    }
}

impl<T: Element> Deref for Buffer<T> {
    type Target = [T];
    fn deref(&self) -> &[T] {
        match &self.repr {
            Repr::Owned(v) => v,
            Repr::Mapped { bytes, start, len } => {
                // Alignment and length were checked when the buffer was made.
                bytemuck::cast_slice(&bytes[*start..*start + *len * std::mem::size_of::<T>()])
            }
        }
    }
}

impl<T: Element> Clone for Buffer<T> {
    fn clone(&self) -> Self {
        let repr = match &self.repr {
            Repr::Owned(v) => Repr::Owned(Arc::clone(v)),
            Repr::Mapped { bytes, start, len } => Repr::Mapped {
                bytes: Arc::clone(bytes),
                start: *start,
                len: *len,
            },
        };
        Buffer { repr }
    }
}

impl<T: Element> From<Vec<T>> for Buffer<T> {
    fn from(v: Vec<T>) -> Self {
        Buffer {
            repr: Repr::Owned(Arc::new(v)),
        }
    }
}

impl<T: Element> Default for Buffer<T> {
    fn default() -> Self {
        Vec::new().into()
    }
}

impl<T: Element> fmt::Debug for Buffer<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "Buffer<{}>(len {}, {})",
            std::any::type_name::<T>(),
            self.len(),
            if self.is_zero_copy() {
                "mapped"
            } else {
                "owned"
            }
        )
    }
}

impl<T: Element + PartialEq> PartialEq for Buffer<T> {
    fn eq(&self, other: &Self) -> bool {
        self.deref() == other.deref()
    }
}

/// One tensor's entry in the header.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TensorInfo {
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    /// Byte range relative to the start of the data section.
    pub data_offsets: (usize, usize),
}

impl TensorInfo {
    /// Number of scalars.
    pub fn numel(&self) -> usize {
        self.shape.iter().product()
    }
}

/// A parsed, structurally valid safetensors file. Kind-specific validation lives in
/// the kind modules; this type only guarantees that every tensor's bytes exist and agree
/// with its dtype and shape.
#[derive(Debug, Clone)]
pub struct Container {
    path: String,
    bytes: Arc<Bytes>,
    data_start: usize,
    tensors: BTreeMap<String, TensorInfo>,
    metadata: BTreeMap<String, String>,
}

/// Whether [`Container::open`] reads files into memory instead of mapping them
/// ([`read_files_into_memory`]).
static READ_INTO_MEMORY: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// From now on, every file this process opens is read into memory instead of mapped.
/// For long-running processes (the viewer): a mapped file that another program truncates or
/// rewrites in place (a plain `cp` over it) raises SIGBUS on the next access, which kills
/// the process; a copy in memory cannot be changed under it. Costs the files' size in RAM.
pub fn read_files_into_memory() {
    READ_INTO_MEMORY.store(true, std::sync::atomic::Ordering::Relaxed);
}

impl Container {
    /// Memory-maps (or, after [`read_files_into_memory`], reads) and parses a file.
    pub fn open(path: impl AsRef<Path>) -> Result<Container> {
        let path = path.as_ref();
        let label = path.display().to_string();
        let io = |action, source| FormatError::Io {
            path: label.clone(),
            action,
            source,
        };
        // A FIFO (or device) would block the open itself, or never end: refuse it first.
        let kind = std::fs::metadata(path).map_err(|e| io("cannot open", e))?;
        if !kind.is_file() {
            return Err(io(
                "cannot open",
                std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a regular file"),
            ));
        }
        let file = std::fs::File::open(path).map_err(|e| io("cannot open", e))?;
        let len = file.metadata().map_err(|e| io("cannot stat", e))?.len();
        let bytes = if len == 0 {
            Bytes::Owned(Vec::new())
        } else if READ_INTO_MEMORY.load(std::sync::atomic::Ordering::Relaxed) {
            let mut buf = Vec::new();
            std::io::Read::read_to_end(&mut std::io::BufReader::new(file), &mut buf)
                .map_err(|e| io("cannot read", e))?;
            Bytes::Owned(buf)
        } else {
            // SAFETY: the map is read-only; a file truncated by another process while
            // mapped can raise SIGBUS, which is the documented limit of memory mapping
            // (SPEC.md: writers never modify a published file, they rename a new one over it).
            #[allow(unsafe_code)]
            let map = unsafe { memmap2::Mmap::map(&file) }.map_err(|e| io("cannot map", e))?;
            Bytes::Mapped(map)
        };
        Self::parse(label, bytes)
    }

    /// Parses an in-memory file; `label` stands for the path in errors.
    pub fn from_vec(label: impl Into<String>, bytes: Vec<u8>) -> Result<Container> {
        Self::parse(label.into(), Bytes::Owned(bytes))
    }

    fn parse(path: String, bytes: Bytes) -> Result<Container> {
        let (data_start, tensors, metadata) = parse_header(&path, &bytes)?;
        Ok(Container {
            path,
            bytes: Arc::new(bytes),
            data_start,
            tensors,
            metadata,
        })
    }

    /// The path (or label) errors name.
    pub fn path(&self) -> &str {
        &self.path
    }

    /// `__metadata__`, sorted by key.
    pub fn metadata(&self) -> &BTreeMap<String, String> {
        &self.metadata
    }

    /// Header entries, sorted by name.
    pub fn tensors(&self) -> &BTreeMap<String, TensorInfo> {
        &self.tensors
    }

    /// Size of the file in bytes.
    pub fn file_size(&self) -> usize {
        self.bytes.len()
    }

    /// The tensor's header entry, or `MissingTensor`.
    pub fn info(&self, name: &str, expected: &str) -> Result<&TensorInfo> {
        self.tensors
            .get(name)
            .ok_or_else(|| FormatError::MissingTensor {
                path: self.path.clone(),
                tensor: name.to_string(),
                expected: expected.to_string(),
            })
    }

    /// A typed view of a tensor whose dtype must be `T::Scalar`'s. Shape is not checked
    /// here (see [`crate::shape::Dims`]); the element count must be a multiple of the lanes.
    pub fn buffer<T: Element>(&self, name: &str) -> Result<Buffer<T>> {
        let info = self.info(name, T::Scalar::DTYPE.name())?;
        if info.dtype != T::Scalar::DTYPE {
            return Err(FormatError::Dtype {
                path: self.path.clone(),
                tensor: name.to_string(),
                found: info.dtype.to_string(),
                expected: T::Scalar::DTYPE.to_string(),
            });
        }
        let numel = info.numel();
        if numel % T::LANES != 0 {
            return Err(FormatError::Shape {
                path: self.path.clone(),
                tensor: name.to_string(),
                found: info.shape.clone(),
                expected: format!("a last dimension of {}", T::LANES),
            });
        }
        Ok(Buffer::from_bytes(
            &self.bytes,
            self.data_start + info.data_offsets.0,
            numel / T::LANES,
        ))
    }

    /// Raw little-endian bytes of a tensor.
    pub fn raw(&self, name: &str) -> Option<&[u8]> {
        let info = self.tensors.get(name)?;
        Some(
            &self.bytes
                [self.data_start + info.data_offsets.0..self.data_start + info.data_offsets.1],
        )
    }
}

/// What a file given in place of a container is, from its first bytes, with what to do
/// (only asked once the header length has failed, so a container never matches).
/// Mirrored by `_foreign_format` of the Python reader.
fn foreign_format(bytes: &[u8]) -> Option<&'static str> {
    if bytes.starts_with(b"ply\n") || bytes.starts_with(b"ply\r\n") {
        Some("it is a PLY file; convert an INRIA 3DGS PLY with `scene-io ply-import FILE --out gaussians.safetensors`")
    } else if bytes.starts_with(b"\x93NUMPY") {
        Some("it is a NumPy .npy array (scene-io reads NumPy inputs: see `scene-io --help`)")
    } else if bytes.starts_with(b"PK\x03\x04") {
        Some("it is a zip archive such as a NumPy .npz (scene-io reads those: see `scene-io --help`)")
    } else {
        None
    }
}

type ParsedHeader = (
    usize,
    BTreeMap<String, TensorInfo>,
    BTreeMap<String, String>,
);

fn parse_header(path: &str, bytes: &[u8]) -> Result<ParsedHeader> {
    let header_err = |detail: String| FormatError::Header {
        path: path.to_string(),
        detail,
    };
    let truncated = |detail: String| FormatError::Truncated {
        path: path.to_string(),
        detail,
    };
    let file_len = bytes.len() as u64;
    if file_len < 8 {
        return Err(truncated(format!(
            "{file_len} bytes, shorter than the 8-byte header length"
        )));
    }
    let mut len_bytes = [0u8; 8];
    len_bytes.copy_from_slice(&bytes[..8]);
    let header_len = u64::from_le_bytes(len_bytes);
    if header_len > MAX_HEADER_BYTES {
        if let Some(kind) = foreign_format(bytes) {
            return Err(header_err(format!("not a safetensors file: {kind}")));
        }
        return Err(header_err(format!(
            "header length {header_len} exceeds the {MAX_HEADER_BYTES}-byte limit"
        )));
    }
    if 8 + header_len > file_len {
        return Err(truncated(format!(
            "header announces {header_len} bytes but the file has {} after the length",
            file_len - 8
        )));
    }
    let data_start = 8 + header_len as usize;
    let text = std::str::from_utf8(&bytes[8..data_start])
        .map_err(|e| header_err(format!("header is not UTF-8: {e}")))?;
    let json: serde_json::Value =
        serde_json::from_str(text).map_err(|e| header_err(format!("header is not JSON: {e}")))?;
    let object = json
        .as_object()
        .ok_or_else(|| header_err("header is not a JSON object".to_string()))?;

    let mut metadata = BTreeMap::new();
    let mut tensors = BTreeMap::new();
    for (name, entry) in object {
        if name == "__metadata__" {
            let map = entry
                .as_object()
                .ok_or_else(|| header_err("`__metadata__` is not an object".to_string()))?;
            for (k, v) in map {
                let v = v
                    .as_str()
                    .ok_or_else(|| header_err(format!("`__metadata__.{k}` is not a string")))?;
                metadata.insert(k.clone(), v.to_string());
            }
            continue;
        }
        let info = parse_entry(name, entry).map_err(header_err)?;
        tensors.insert(name.clone(), info);
    }

    let data_len = (file_len - 8 - header_len) as usize;
    check_data_layout(&tensors, data_len, &header_err, &truncated)?;
    Ok((data_start, tensors, metadata))
}

fn parse_entry(name: &str, entry: &serde_json::Value) -> std::result::Result<TensorInfo, String> {
    let obj = entry
        .as_object()
        .ok_or_else(|| format!("entry `{name}` is not an object"))?;
    let dtype_name = obj
        .get("dtype")
        .and_then(|d| d.as_str())
        .ok_or_else(|| format!("entry `{name}` has no string `dtype`"))?;
    let dtype = Dtype::parse(dtype_name)
        .ok_or_else(|| format!("entry `{name}` has unknown dtype {dtype_name:?}"))?;
    let shape = obj
        .get("shape")
        .and_then(|s| s.as_array())
        .ok_or_else(|| format!("entry `{name}` has no array `shape`"))?
        .iter()
        .map(|d| d.as_u64().and_then(|d| usize::try_from(d).ok()))
        .collect::<Option<Vec<usize>>>()
        .ok_or_else(|| {
            format!("entry `{name}` has a shape that is not a list of non-negative integers")
        })?;
    let offsets = obj
        .get("data_offsets")
        .and_then(|s| s.as_array())
        .filter(|a| a.len() == 2)
        .and_then(|a| Some((a[0].as_u64()?, a[1].as_u64()?)))
        .ok_or_else(|| {
            format!("entry `{name}` has no `data_offsets` pair of non-negative integers")
        })?;
    let (begin, end) = (
        usize::try_from(offsets.0).map_err(|_| format!("entry `{name}` offset too large"))?,
        usize::try_from(offsets.1).map_err(|_| format!("entry `{name}` offset too large"))?,
    );
    if begin > end {
        return Err(format!(
            "entry `{name}` has data_offsets [{begin}, {end}] that decrease"
        ));
    }
    let numel = shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| format!("entry `{name}` has a shape whose size overflows"))?;
    let nbytes = numel
        .checked_mul(dtype.size())
        .ok_or_else(|| format!("entry `{name}` has a shape whose size overflows"))?;
    if end - begin != nbytes {
        return Err(format!(
            "entry `{name}` spans {} bytes but dtype {dtype} and shape {shape:?} need {nbytes}",
            end - begin
        ));
    }
    Ok(TensorInfo {
        dtype,
        shape,
        data_offsets: (begin, end),
    })
}

/// Tensors must tile the data section exactly: sorted by offset, no gap, no overlap,
/// nothing after the last one. A claim past the end of the file is truncation.
fn check_data_layout(
    tensors: &BTreeMap<String, TensorInfo>,
    data_len: usize,
    header_err: &dyn Fn(String) -> FormatError,
    truncated: &dyn Fn(String) -> FormatError,
) -> Result<()> {
    let mut spans: Vec<(usize, usize, &str)> = tensors
        .iter()
        .map(|(n, t)| (t.data_offsets.0, t.data_offsets.1, n.as_str()))
        .collect();
    spans.sort_unstable();
    let mut cursor = 0usize;
    for (begin, end, name) in &spans {
        if *begin != cursor {
            return Err(header_err(format!(
                "tensor `{name}` starts at byte {begin} of the data, expected {cursor} (gap or overlap)"
            )));
        }
        cursor = *end;
    }
    if cursor > data_len {
        return Err(truncated(format!(
            "header announces {cursor} bytes of tensor data but the file has {data_len}"
        )));
    }
    if cursor < data_len {
        return Err(header_err(format!(
            "{} bytes after the last tensor are not described by the header",
            data_len - cursor
        )));
    }
    Ok(())
}

//! Atomic writers: the file is serialised into a temporary file in the target
//! directory, flushed to disk, and renamed over the target, so a reader sees either
//! the old file or the complete new one, never a partial write.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use crate::container::{Dtype, Element, Scalar};
use crate::error::{FormatError, Result};
use crate::kind::Kind;

/// One tensor to write: borrowed bytes plus header facts.
#[derive(Debug)]
struct Pending<'a> {
    dtype: Dtype,
    shape: Vec<usize>,
    bytes: Cow<'a, [u8]>,
}

impl safetensors::View for &Pending<'_> {
    fn dtype(&self) -> safetensors::Dtype {
        self.dtype.to_safetensors()
    }
    fn shape(&self) -> &[usize] {
        &self.shape
    }
    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Borrowed(&self.bytes)
    }
    fn data_len(&self) -> usize {
        self.bytes.len()
    }
}

/// Collects tensors and metadata of one file, then writes it atomically.
#[derive(Debug)]
pub struct FileWriter<'a> {
    kind: Kind,
    metadata: BTreeMap<String, String>,
    tensors: BTreeMap<String, Pending<'a>>,
}

impl<'a> FileWriter<'a> {
    /// A writer for a file of `kind`; `format` and `format_version` are set for you.
    pub fn new(kind: Kind) -> Self {
        FileWriter {
            kind,
            metadata: BTreeMap::new(),
            tensors: BTreeMap::new(),
        }
    }

    /// Sets a metadata string.
    pub fn meta(&mut self, key: &str, value: impl Into<String>) -> &mut Self {
        self.metadata.insert(key.to_string(), value.into());
        self
    }

    /// Sets a metadata value as a JSON array of strings.
    pub fn meta_strings(&mut self, key: &str, values: &[String]) -> &mut Self {
        let json = serde_json::to_string(values).unwrap_or_else(|_| "[]".to_string());
        self.meta(key, json)
    }

    /// Adds a tensor; `shape`'s product must equal the scalar count of `data`.
    pub fn tensor<T: Element>(&mut self, name: &str, shape: &[usize], data: &'a [T]) -> &mut Self {
        self.tensors.insert(
            name.to_string(),
            Pending {
                dtype: T::Scalar::DTYPE,
                shape: shape.to_vec(),
                bytes: Cow::Borrowed(bytemuck::cast_slice(data)),
            },
        );
        self
    }

    /// Adds a tensor of any dtype from raw little-endian bytes (used to build test files).
    pub fn raw_tensor(&mut self, name: &str, dtype: Dtype, shape: &[usize], bytes: Vec<u8>) -> &mut Self {
        self.tensors.insert(
            name.to_string(),
            Pending {
                dtype,
                shape: shape.to_vec(),
                bytes: Cow::Owned(bytes),
            },
        );
        self
    }

    /// Removes a metadata key (used to build invalid test files).
    pub fn remove_meta(&mut self, key: &str) -> &mut Self {
        self.metadata.remove(key);
        self
    }

    /// Serialises to bytes (the header and tensor order are deterministic).
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        let meta = self.header_metadata();
        safetensors::serialize(self.tensors.iter().map(|(n, t)| (n.as_str(), t)), Some(meta))
            .map_err(|e| FormatError::Header {
                path: "<memory>".to_string(),
                detail: format!("cannot serialise: {e}"),
            })
    }

    fn header_metadata(&self) -> HashMap<String, String> {
        let mut meta: HashMap<String, String> = self.metadata.clone().into_iter().collect();
        meta.entry("format".to_string())
            .or_insert_with(|| self.kind.format_name().to_string());
        meta.entry("format_version".to_string())
            .or_insert_with(|| self.kind.version().to_string());
        meta
    }

    /// Writes the file atomically: temp file in the same directory, fsync, rename.
    pub fn commit(&self, path: impl AsRef<Path>) -> Result<()> {
        let path = path.as_ref();
        let label = path.display().to_string();
        let io = |action, source| FormatError::Io {
            path: label.clone(),
            action,
            source,
        };
        let dir = match path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p,
            _ => Path::new("."),
        };
        let tmp = tempfile::Builder::new()
            .prefix(".profuse-tmp-")
            .tempfile_in(dir)
            .map_err(|e| io("cannot create a temporary file next to it", e))?;
        safetensors::serialize_to_file(
            self.tensors.iter().map(|(n, t)| (n.as_str(), t)),
            Some(self.header_metadata()),
            tmp.path(),
        )
        .map_err(|e| FormatError::Io {
            path: label.clone(),
            action: "cannot write",
            source: std::io::Error::other(e.to_string()),
        })?;
        tmp.as_file().sync_all().map_err(|e| io("cannot flush", e))?;
        tmp.persist(path).map_err(|e| io("cannot rename into place", e.error))?;
        Ok(())
    }
}

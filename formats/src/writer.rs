//! Atomic writers: the file is serialised into a temporary file in the target
//! directory, flushed to disk, and renamed over the target, so a reader sees either
//! the old file or the complete new one, never a partial write.

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::io::Write;
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
    pub fn raw_tensor(
        &mut self,
        name: &str,
        dtype: Dtype,
        shape: &[usize],
        bytes: Vec<u8>,
    ) -> &mut Self {
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

    /// Serialises to bytes (deterministic: sorted metadata keys, tensors ordered by
    /// decreasing alignment then name, header padded to 8 bytes).
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        let mut out = Vec::new();
        self.serialise(&mut out).map_err(|e| FormatError::Io {
            path: "<memory>".to_string(),
            action: "cannot serialise",
            source: e,
        })?;
        Ok(out)
    }

    fn metadata_with_kind(&self) -> BTreeMap<String, String> {
        let mut meta = self.metadata.clone();
        meta.entry("format".to_string())
            .or_insert_with(|| self.kind.format_name().to_string());
        meta.entry("format_version".to_string())
            .or_insert_with(|| self.kind.version().to_string());
        meta
    }

    /// Tensors in the order the safetensors reference writer uses, which keeps every
    /// tensor aligned to its dtype when the data section is 8-aligned.
    fn ordered(&self) -> Vec<(&String, &Pending<'a>)> {
        let mut order: Vec<_> = self.tensors.iter().collect();
        order.sort_by(|a, b| {
            b.1.dtype
                .size()
                .cmp(&a.1.dtype.size())
                .then_with(|| a.0.cmp(b.0))
        });
        order
    }

    fn header(&self) -> std::io::Result<Vec<u8>> {
        let mut header = serde_json::Map::new();
        header.insert(
            "__metadata__".to_string(),
            serde_json::to_value(self.metadata_with_kind())?,
        );
        let mut offset = 0usize;
        for (name, t) in self.ordered() {
            let numel: usize = t.shape.iter().product();
            if numel * t.dtype.size() != t.bytes.len() {
                return Err(std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    format!(
                        "tensor `{name}`: shape {:?} of {} does not match {} bytes",
                        t.shape,
                        t.dtype,
                        t.bytes.len()
                    ),
                ));
            }
            header.insert(
                name.clone(),
                serde_json::json!({"dtype": t.dtype.name(), "shape": t.shape, "data_offsets": [offset, offset + t.bytes.len()]}),
            );
            offset += t.bytes.len();
        }
        let mut text = serde_json::to_vec(&serde_json::Value::Object(header))?;
        while (8 + text.len()) % 8 != 0 {
            text.push(b' ');
        }
        Ok(text)
    }

    fn serialise(&self, out: &mut impl Write) -> std::io::Result<()> {
        let header = self.header()?;
        out.write_all(&(header.len() as u64).to_le_bytes())?;
        out.write_all(&header)?;
        for (_, t) in self.ordered() {
            out.write_all(&t.bytes)?;
        }
        out.flush()
    }

    /// Writes the file atomically: temp file in the same directory, fsync, rename.
    pub fn commit(&self, path: impl AsRef<Path>) -> Result<()> {
        let path = path.as_ref();
        write_atomically(path, |out| {
            let mut w = std::io::BufWriter::with_capacity(1 << 20, out);
            self.serialise(&mut w)
        })
        .map_err(|(action, source)| FormatError::Io {
            path: path.display().to_string(),
            action,
            source,
        })
    }
}

/// Writes any file atomically, the way every ProFuse writer does: `fill` writes into a
/// temporary file `.profuse-tmp-*` in the target's directory (mode 0666 minus the umask,
/// like `File::create`; locked while it is written, see [`crate::output`]), which is
/// flushed to disk and renamed over `path`, so readers never see a partial file and a
/// failure leaves nothing behind. Only a regular file (or nothing) is replaced: a device,
/// FIFO, socket or directory at `path` fails before anything is written
/// ([`crate::output::check_output_file`]). The error names the step that failed (`will not
/// replace it`, `cannot create a temporary file next to it`, `cannot write`, `cannot
/// flush`, `cannot rename into place`). Crates use it for their PNG and JSON outputs.
pub fn write_atomically(
    path: &Path,
    fill: impl FnOnce(&std::fs::File) -> std::io::Result<()>,
) -> std::result::Result<(), (&'static str, std::io::Error)> {
    if let Err(e) = crate::output::check_output_file(path) {
        let source = match e {
            crate::output::OutputError::Io { source, .. } => source,
            crate::output::OutputError::NotAFile { found, .. } => std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!("it is a {found}; an output may only replace a regular file"),
            ),
            other => std::io::Error::new(std::io::ErrorKind::InvalidInput, other.to_string()),
        };
        return Err(("will not replace it", source));
    }
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let mut builder = tempfile::Builder::new();
    builder.prefix(".profuse-tmp-");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        builder.permissions(std::fs::Permissions::from_mode(0o666));
    }
    let tmp = builder
        .tempfile_in(dir)
        .map_err(|e| ("cannot create a temporary file next to it", e))?;
    crate::output::claim(tmp.as_file());
    fill(tmp.as_file()).map_err(|e| ("cannot write", e))?;
    tmp.as_file().sync_all().map_err(|e| ("cannot flush", e))?;
    tmp.persist(path)
        .map_err(|e| ("cannot rename into place", e.error))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    /// Issue 20 item 5: a FIFO, socket or directory at the output path is refused before
    /// anything is written, and stays what it was (on the old code the FIFO was replaced
    /// by a regular file).
    #[cfg(unix)]
    #[test]
    fn non_regular_targets_are_refused_and_left_alone() {
        use std::os::unix::fs::FileTypeExt;
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("fifo");
        let ok = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success();
        assert!(ok, "mkfifo failed");
        let sock = dir.path().join("sock");
        let _listener = std::os::unix::net::UnixListener::bind(&sock).unwrap();
        let sub = dir.path().join("sub");
        std::fs::create_dir(&sub).unwrap();
        for (path, found) in [(&fifo, "FIFO"), (&sock, "socket"), (&sub, "directory")] {
            let mut w = FileWriter::new(Kind::Prompts);
            w.meta("names", "[]");
            let e = w.commit(path).unwrap_err();
            let text = e.to_string();
            assert!(
                text.contains("will not replace it") && text.contains(found),
                "{text}"
            );
            assert_eq!(e.code(), "io");
        }
        assert!(std::fs::metadata(&fifo).unwrap().file_type().is_fifo());
        assert!(std::fs::metadata(&sock).unwrap().file_type().is_socket());
        assert!(sub.is_dir());
        // Nothing else was created next to them (no temporary file left behind).
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 3);
        // A regular file is still replaced.
        let file = dir.path().join("file");
        std::fs::write(&file, b"old").unwrap();
        write_atomically(&file, |mut f| std::io::Write::write_all(&mut f, b"new")).unwrap();
        assert_eq!(std::fs::read(&file).unwrap(), b"new");
    }
}

//! The file kinds of SPEC.md and the trait every kind implements.

use std::collections::BTreeMap;
use std::path::Path;

use crate::container::Container;
use crate::error::{FormatError, Result};
use crate::writer::FileWriter;

/// Major version every reader of this crate accepts (SPEC.md "Versioning").
pub const MAJOR_VERSION: u32 = 1;

/// Every file kind of SPEC.md.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Kind {
    Cameras,
    Gaussians,
    Masks,
    Matches,
    SparseMatches,
    Proposals,
    Features,
    Pq,
    Prompts,
    Selection,
    VertexLabels,
    Mesh,
    ViewMaps,
    TopK,
    FusePartial,
    WarpPartial,
    SemanticIndex,
}

impl Kind {
    /// All kinds, in SPEC.md order.
    pub const ALL: [Kind; 17] = [
        Kind::Cameras,
        Kind::Gaussians,
        Kind::Masks,
        Kind::Matches,
        Kind::SparseMatches,
        Kind::Proposals,
        Kind::Features,
        Kind::Pq,
        Kind::Prompts,
        Kind::Selection,
        Kind::VertexLabels,
        Kind::Mesh,
        Kind::ViewMaps,
        Kind::TopK,
        Kind::FusePartial,
        Kind::WarpPartial,
        Kind::SemanticIndex,
    ];

    /// Short name (`cameras`, `sparse_matches`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Kind::Cameras => "cameras",
            Kind::Gaussians => "gaussians",
            Kind::Masks => "masks",
            Kind::Matches => "matches",
            Kind::SparseMatches => "sparse_matches",
            Kind::Proposals => "proposals",
            Kind::Features => "features",
            Kind::Pq => "pq",
            Kind::Prompts => "prompts",
            Kind::Selection => "selection",
            Kind::VertexLabels => "vertex_labels",
            Kind::Mesh => "mesh",
            Kind::ViewMaps => "view_maps",
            Kind::TopK => "topk",
            Kind::FusePartial => "fuse_partial",
            Kind::WarpPartial => "warp_partial",
            Kind::SemanticIndex => "semantic_index",
        }
    }

    /// Value of `__metadata__.format`.
    pub fn format_name(self) -> &'static str {
        match self {
            Kind::Cameras => "profuse.cameras",
            Kind::Gaussians => "profuse.gaussians",
            Kind::Masks => "profuse.masks",
            Kind::Matches => "profuse.matches",
            Kind::SparseMatches => "profuse.sparse_matches",
            Kind::Proposals => "profuse.proposals",
            Kind::Features => "profuse.features",
            Kind::Pq => "profuse.pq",
            Kind::Prompts => "profuse.prompts",
            Kind::Selection => "profuse.selection",
            Kind::VertexLabels => "profuse.vertex_labels",
            Kind::Mesh => "profuse.mesh",
            Kind::ViewMaps => "profuse.view_maps",
            Kind::TopK => "profuse.topk",
            Kind::FusePartial => "profuse.fuse_partial",
            Kind::WarpPartial => "profuse.warp_partial",
            Kind::SemanticIndex => "profuse.semantic_index",
        }
    }

    /// The version this crate writes.
    pub fn version(self) -> &'static str {
        "1.0"
    }

    /// The kind named by a `format` value.
    pub fn from_format_name(s: &str) -> Option<Kind> {
        Kind::ALL.into_iter().find(|k| k.format_name() == s)
    }

    /// Checks `format` and `format_version` of a container against this kind.
    pub fn check(self, c: &Container) -> Result<()> {
        let found = c.metadata().get("format");
        if found.map(String::as_str) != Some(self.format_name()) {
            return Err(FormatError::WrongKind {
                path: c.path().to_string(),
                expected: self.format_name().to_string(),
                found: found.map_or("absent".to_string(), |f| format!("{f:?}")),
            });
        }
        check_version(c)
    }
}

/// `format_version` must read `MAJOR.MINOR` with MAJOR = [`MAJOR_VERSION`].
pub fn check_version(c: &Container) -> Result<()> {
    let found = c.metadata().get("format_version");
    let ok = found.is_some_and(|v| {
        let mut parts = v.split('.');
        let major = parts.next().and_then(parse_decimal);
        let minor = parts.next().and_then(parse_decimal);
        major == Some(MAJOR_VERSION) && minor.is_some() && parts.next().is_none()
    });
    if ok {
        Ok(())
    } else {
        Err(FormatError::WrongVersion {
            path: c.path().to_string(),
            found: found.map_or("absent".to_string(), |f| format!("{f:?}")),
            supported: MAJOR_VERSION,
        })
    }
}

fn parse_decimal(s: &str) -> Option<u32> {
    if s.is_empty() || !s.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    s.parse().ok()
}

/// A file kind: how to read it from a container, validate it, write it, and count it.
pub trait FileKind: Sized {
    /// The kind this type reads and writes.
    const KIND: Kind;

    /// Builds the value from a container whose kind and version were checked
    /// (dtypes and shapes are checked here).
    fn from_container(c: &Container) -> Result<Self>;

    /// Checks every rule of SPEC.md that the value's own data can show; `path` names
    /// the file in errors.
    fn validate(&self, path: &str) -> Result<()>;

    /// Adds the tensors and kind-specific metadata to a writer.
    fn fill<'a>(&'a self, w: &mut FileWriter<'a>);

    /// Counts reported by `profuse inspect` (SPEC.md lists them per kind).
    fn counts(&self) -> BTreeMap<&'static str, u64>;

    /// Reads and fully validates a file.
    fn read(path: impl AsRef<Path>) -> Result<Self> {
        let c = Container::open(path)?;
        Self::from_checked_container(&c)
    }

    /// Validates a parsed container as this kind.
    fn from_checked_container(c: &Container) -> Result<Self> {
        Self::KIND.check(c)?;
        let value = Self::from_container(c)?;
        value.validate(c.path())?;
        Ok(value)
    }

    /// Validates and writes the file atomically.
    fn write(&self, path: impl AsRef<Path>) -> Result<()> {
        let path = path.as_ref();
        self.validate(&path.display().to_string())?;
        let mut w = FileWriter::new(Self::KIND);
        self.fill(&mut w);
        w.commit(path)
    }

    /// Validates and serialises to bytes.
    fn to_bytes(&self) -> Result<Vec<u8>> {
        self.validate("<memory>")?;
        let mut w = FileWriter::new(Self::KIND);
        self.fill(&mut w);
        w.to_bytes()
    }
}

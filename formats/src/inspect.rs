//! `profuse inspect`: a JSON report of any file (SPEC.md "Inspect report"). The Python
//! reader prints the identical JSON, so the two implementations can be diffed.

use std::collections::BTreeMap;
use std::path::Path;

use serde_json::{json, Value};

use crate::container::Container;
use crate::error::{FormatError, Result};
use crate::kind::{FileKind, Kind};
use crate::{
    Cameras, Features, FusePartial, Gaussians, Masks, Matches, Mesh, Pq, Prompts, Proposals,
    Selection, SemanticIndex, SparseMatches, TopK, VertexLabels, ViewMaps, WarpPartial,
};

/// The outcome of inspecting one file.
#[derive(Debug)]
pub struct Report {
    /// The JSON object printed on stdout.
    pub json: Value,
    /// The validation error, if the file is invalid.
    pub error: Option<FormatError>,
}

/// Reads `path` as whatever kind its metadata names and validates it fully.
pub fn inspect(path: impl AsRef<Path>) -> Report {
    let path = path.as_ref();
    let label = path.display().to_string();
    let container = Container::open(path);
    let (c, result) = match container {
        Ok(c) => {
            let r = validate_any(&c);
            (Some(c), r)
        }
        Err(e) => (None, Err(e)),
    };
    let metadata: BTreeMap<String, String> =
        c.as_ref().map(|c| c.metadata().clone()).unwrap_or_default();
    let tensors: serde_json::Map<String, Value> = c
        .as_ref()
        .map(|c| {
            c.tensors()
                .iter()
                .map(|(n, t)| {
                    (
                        n.clone(),
                        json!({"dtype": t.dtype.name(), "shape": t.shape}),
                    )
                })
                .collect()
        })
        .unwrap_or_default();
    let kind = metadata
        .get("format")
        .and_then(|f| Kind::from_format_name(f))
        .map(|k| k.name());
    let (counts, error) = match result {
        Ok(counts) => (counts, None),
        Err(e) => (BTreeMap::new(), Some(e)),
    };
    let json = json!({
        "file": label,
        "size_bytes": c.as_ref().map(|c| c.file_size()),
        "kind": kind,
        "format": metadata.get("format"),
        "format_version": metadata.get("format_version"),
        "metadata": metadata,
        "tensors": tensors,
        "counts": counts,
        "valid": error.is_none(),
        "error": error.as_ref().map(|e| json!({"code": e.code(), "field": e.field()})),
    });
    Report { json, error }
}

/// Validates a container as the kind its `format` names; returns the kind's counts.
pub fn validate_any(c: &Container) -> Result<BTreeMap<&'static str, u64>> {
    let format = c.metadata().get("format");
    let Some(kind) = format.and_then(|f| Kind::from_format_name(f)) else {
        return Err(FormatError::WrongKind {
            path: c.path().to_string(),
            expected: "profuse.<kind> for a known kind".to_string(),
            found: format.map_or("absent".to_string(), |f| format!("{f:?}")),
        });
    };
    fn counts<K: FileKind>(c: &Container) -> Result<BTreeMap<&'static str, u64>> {
        K::from_checked_container(c).map(|k| k.counts())
    }
    match kind {
        Kind::Cameras => counts::<Cameras>(c),
        Kind::Gaussians => counts::<Gaussians>(c),
        Kind::Masks => counts::<Masks>(c),
        Kind::Matches => counts::<Matches>(c),
        Kind::SparseMatches => counts::<SparseMatches>(c),
        Kind::Proposals => counts::<Proposals>(c),
        Kind::Features => counts::<Features>(c),
        Kind::Pq => counts::<Pq>(c),
        Kind::Prompts => counts::<Prompts>(c),
        Kind::Selection => counts::<Selection>(c),
        Kind::VertexLabels => counts::<VertexLabels>(c),
        Kind::Mesh => counts::<Mesh>(c),
        Kind::ViewMaps => counts::<ViewMaps>(c),
        Kind::TopK => counts::<TopK>(c),
        Kind::FusePartial => counts::<FusePartial>(c),
        Kind::WarpPartial => counts::<WarpPartial>(c),
        Kind::SemanticIndex => counts::<SemanticIndex>(c),
    }
}

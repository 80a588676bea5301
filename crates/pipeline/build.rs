//! Computes the *code identity* of every workspace crate the pipeline runs, so that a
//! stage's completion record can say which code produced its outputs (README "Up-to-date
//! rules"): a crate's identity hashes its `Cargo.toml`, every file beneath its `src/`, the
//! identities of the workspace crates it depends on (not its dev-dependencies) and the
//! workspace's `Cargo.lock` (the versions of everything else). A change to any of them
//! changes the identity, and the stages that run the crate run again.
//!
//! Outside the workspace (a packaged crate) the sibling sources are not there: every
//! crate's identity is then the pipeline's own sources and version.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// FNV-1a 64: not cryptographic; it tells edits apart, nobody forges them.
#[derive(Clone, Copy)]
struct Fnv(u64);

impl Fnv {
    fn new() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }
    fn bytes(mut self, bytes: &[u8]) -> Self {
        for &b in bytes {
            self.0 ^= u64::from(b);
            self.0 = self.0.wrapping_mul(0x0100_0000_01b3);
        }
        // The length too, so that concatenations of different pieces differ.
        for &b in &(bytes.len() as u64).to_le_bytes() {
            self.0 ^= u64::from(b);
            self.0 = self.0.wrapping_mul(0x0100_0000_01b3);
        }
        self
    }
}

/// Every file beneath `dir`, as (path relative to `dir` with `/` separators, path), sorted.
fn files_beneath(dir: &Path) -> Vec<(String, PathBuf)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for entry in entries.flatten() {
            let path = entry.path();
            if path.is_dir() {
                stack.push(path);
            } else if let Ok(rel) = path.strip_prefix(dir) {
                let rel: Vec<String> = rel
                    .components()
                    .map(|c| c.as_os_str().to_string_lossy().into_owned())
                    .collect();
                out.push((rel.join("/"), path));
            }
        }
    }
    out.sort();
    out
}

/// The hash of a crate's own `Cargo.toml` and `src/` (and asks cargo to rebuild when they
/// change).
fn own_sources(dir: &Path) -> Fnv {
    let manifest = dir.join("Cargo.toml");
    let src = dir.join("src");
    println!("cargo:rerun-if-changed={}", manifest.display());
    println!("cargo:rerun-if-changed={}", src.display());
    let mut h = Fnv::new().bytes(&std::fs::read(&manifest).unwrap_or_default());
    for (rel, path) in files_beneath(&src) {
        h = h
            .bytes(rel.as_bytes())
            .bytes(&std::fs::read(&path).unwrap_or_default());
    }
    h
}

/// The workspace's path crates (`[workspace.dependencies]` entries with a `path`), by name.
fn workspace_crates(root_manifest: &toml::Table) -> BTreeMap<String, String> {
    let Some(deps) = root_manifest
        .get("workspace")
        .and_then(|w| w.get("dependencies"))
        .and_then(|d| d.as_table())
    else {
        return BTreeMap::new();
    };
    deps.iter()
        .filter_map(|(name, spec)| {
            let path = spec.get("path")?.as_str()?;
            Some((name.clone(), path.to_string()))
        })
        .collect()
}

/// The workspace crates among a crate's `[dependencies]`.
fn workspace_dependencies(dir: &Path, crates: &BTreeMap<String, String>) -> BTreeSet<String> {
    let text = std::fs::read_to_string(dir.join("Cargo.toml")).unwrap_or_default();
    let Ok(manifest) = text.parse::<toml::Table>() else {
        return BTreeSet::new();
    };
    manifest
        .get("dependencies")
        .and_then(|d| d.as_table())
        .map(|d| {
            d.keys()
                .filter(|k| crates.contains_key(*k))
                .cloned()
                .collect()
        })
        .unwrap_or_default()
}

/// The identity of `name` and, on the way, of every workspace crate it depends on.
fn identity(
    name: &str,
    root: &Path,
    crates: &BTreeMap<String, String>,
    lock: Fnv,
    done: &mut BTreeMap<String, u64>,
) -> u64 {
    if let Some(&id) = done.get(name) {
        return id;
    }
    // Stops a dependency cycle (cargo forbids them; a broken manifest must not hang).
    done.insert(name.to_string(), 0);
    let dir = root.join(&crates[name]);
    let mut h = own_sources(&dir).bytes(&lock.0.to_le_bytes());
    for dep in workspace_dependencies(&dir, crates) {
        let id = identity(&dep, root, crates, lock, done);
        h = h.bytes(dep.as_bytes()).bytes(&id.to_le_bytes());
    }
    done.insert(name.to_string(), h.0);
    h.0
}

fn main() {
    let here = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").unwrap_or_default());
    let own = std::env::var("CARGO_PKG_NAME").unwrap_or_default();
    let root = here.join("..").join("..");
    let root_manifest = std::fs::read_to_string(root.join("Cargo.toml"))
        .ok()
        .and_then(|t| t.parse::<toml::Table>().ok());
    let crates = root_manifest
        .as_ref()
        .map(workspace_crates)
        .unwrap_or_default();
    let in_workspace = crates
        .get(&own)
        .is_some_and(|p| root.join(p).join("Cargo.toml").is_file() && root.join(p) != root);

    let mut table = BTreeMap::new();
    if in_workspace {
        println!(
            "cargo:rerun-if-changed={}",
            root.join("Cargo.lock").display()
        );
        println!(
            "cargo:rerun-if-changed={}",
            root.join("Cargo.toml").display()
        );
        let lock = Fnv::new().bytes(&std::fs::read(root.join("Cargo.lock")).unwrap_or_default());
        identity(&own, &root, &crates, lock, &mut table);
    } else {
        let version = std::env::var("CARGO_PKG_VERSION").unwrap_or_default();
        let id = own_sources(&here).bytes(version.as_bytes()).0;
        table.insert(own.clone(), id);
    }

    let glue = own_sources(&here).0;
    let mut code = format!(
        "/// Identity of the pipeline crate's own sources (the glue that calls each stage).\n\
         pub(crate) const GLUE_CODE: &str = \"{glue:016x}\";\n"
    );
    code.push_str(
        "/// Code identity (FNV-1a 64, hex) of each workspace crate the pipeline runs, by\n\
         /// package name; written by `build.rs`.\n\
         pub(crate) const CRATE_CODE: &[(&str, &str)] = &[\n",
    );
    for (name, id) in &table {
        let _ = writeln!(code, "    ({name:?}, \"{id:016x}\"),");
    }
    code.push_str("];\n");
    let out = PathBuf::from(std::env::var_os("OUT_DIR").unwrap_or_default());
    if let Err(e) = std::fs::write(out.join("code_identity.rs"), code) {
        panic!("cannot write code_identity.rs into OUT_DIR: {e}");
    }
}

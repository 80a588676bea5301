//! Code identities of workspace crates (README "Up-to-date rules"). Compiled twice: into
//! `build.rs` (`#[path]`), which writes the table the stages compare, and into the
//! library's unit tests, which check it on synthetic workspaces.
//!
//! A crate's identity hashes its `Cargo.toml`, every file beneath its `src/`, the
//! identities of the workspace crates among its `[dependencies]` (not dev-dependencies)
//! and the workspace's `Cargo.lock`.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use crate::fnv::{files_beneath, Fnv};

/// Hashes `bytes` and then their length (8 bytes, little-endian), so that concatenations
/// of different pieces differ.
fn piece(h: Fnv, bytes: &[u8]) -> Fnv {
    h.bytes(bytes).bytes(&(bytes.len() as u64).to_le_bytes())
}

/// The hash of a crate's own `Cargo.toml` and `src/`; `watch` is told both paths (cargo's
/// `rerun-if-changed`).
pub fn own_sources(dir: &Path, watch: &mut dyn FnMut(&Path)) -> Fnv {
    let manifest = dir.join("Cargo.toml");
    let src = dir.join("src");
    watch(&manifest);
    watch(&src);
    let mut h = piece(Fnv::new(), &std::fs::read(&manifest).unwrap_or_default());
    for (rel, path) in files_beneath(&src).unwrap_or_default() {
        h = piece(h, rel.as_os_str().as_encoded_bytes());
        h = piece(h, &std::fs::read(&path).unwrap_or_default());
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

struct Workspace<'a> {
    root: &'a Path,
    crates: BTreeMap<String, String>,
    lock: Fnv,
    done: BTreeMap<String, u64>,
}

impl Workspace<'_> {
    /// The identity of `name` and, on the way, of every workspace crate it depends on.
    fn identity(&mut self, name: &str, watch: &mut dyn FnMut(&Path)) -> u64 {
        if let Some(&id) = self.done.get(name) {
            return id;
        }
        // Stops a dependency cycle (cargo forbids them; a broken manifest must not hang).
        self.done.insert(name.to_string(), 0);
        let Some(rel) = self.crates.get(name) else {
            return 0;
        };
        let dir = self.root.join(rel);
        let mut h = piece(own_sources(&dir, watch), &self.lock.0.to_le_bytes());
        for dep in workspace_dependencies(&dir, &self.crates) {
            let id = self.identity(&dep, watch);
            h = piece(piece(h, dep.as_bytes()), &id.to_le_bytes());
        }
        self.done.insert(name.to_string(), h.0);
        h.0
    }
}

/// The identities of `package` and of every workspace crate it depends on, by name, for
/// the workspace at `root`; `None` when `root` is not a workspace listing `package` at a
/// directory with a manifest (a packaged crate). `watch` is told every file and directory
/// read.
pub fn workspace_identities(
    root: &Path,
    package: &str,
    watch: &mut dyn FnMut(&Path),
) -> Option<BTreeMap<String, u64>> {
    let manifest = std::fs::read_to_string(root.join("Cargo.toml")).ok()?;
    let crates = workspace_crates(&manifest.parse::<toml::Table>().ok()?);
    let dir = root.join(crates.get(package)?);
    if dir == root || !dir.join("Cargo.toml").is_file() {
        return None;
    }
    watch(&root.join("Cargo.toml"));
    watch(&root.join("Cargo.lock"));
    let lock = piece(
        Fnv::new(),
        &std::fs::read(root.join("Cargo.lock")).unwrap_or_default(),
    );
    let mut ws = Workspace {
        root,
        crates,
        lock,
        done: BTreeMap::new(),
    };
    ws.identity(package, watch);
    Some(ws.done)
}

/// The `CRATE_CODE` table a build script generates: one `(package, identity)` row per crate
/// of `table`; `runner` completes the doc line ("the pipeline", "the experiments").
pub fn crate_code_table(table: &BTreeMap<String, u64>, runner: &str) -> String {
    let mut code = format!(
        "/// Code identity (FNV-1a 64, hex) of each workspace crate {runner} runs, by\n\
         /// package name; written by `build.rs`.\n\
         pub(crate) const CRATE_CODE: &[(&str, &str)] = &[\n"
    );
    for (name, id) in table {
        code.push_str(&format!("    ({name:?}, \"{id:016x}\"),\n"));
    }
    code.push_str("];\n");
    code
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn the_crate_code_table_is_rust_with_one_row_per_crate() {
        let table = BTreeMap::from([("a-b".to_string(), 0xab_u64), ("c".to_string(), 1)]);
        let code = crate_code_table(&table, "the pipeline");
        assert!(
            code.contains("each workspace crate the pipeline runs, by\n"),
            "{code}"
        );
        assert!(
            code.contains("    (\"a-b\", \"00000000000000ab\"),\n"),
            "{code}"
        );
        assert!(
            code.contains("    (\"c\", \"0000000000000001\"),\n];\n"),
            "{code}"
        );
    }

    /// A workspace of three crates: `app` depends on `mid`, `mid` on `leaf`; `leaf` has
    /// `app` as a dev-dependency (which must not count).
    fn workspace(root: &Path) {
        let write = |rel: &str, text: &str| {
            let path = root.join(rel);
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::write(path, text).unwrap();
        };
        write(
            "Cargo.toml",
            "[workspace]\nmembers = [\"crates/*\"]\n[workspace.dependencies]\n\
             leaf = { path = \"crates/leaf\" }\nmid = { path = \"crates/mid\" }\n\
             app = { path = \"crates/app\" }\nserde = \"1\"\n",
        );
        write("Cargo.lock", "# lock v1\n");
        write(
            "crates/leaf/Cargo.toml",
            "[package]\nname = \"leaf\"\n[dev-dependencies]\napp.workspace = true\n",
        );
        write("crates/leaf/src/lib.rs", "pub fn leaf() {}\n");
        write(
            "crates/mid/Cargo.toml",
            "[package]\nname = \"mid\"\n[dependencies]\nleaf.workspace = true\nserde.workspace = true\n",
        );
        write("crates/mid/src/lib.rs", "pub fn mid() {}\n");
        write("crates/mid/src/deep/inner.rs", "pub fn inner() {}\n");
        write(
            "crates/app/Cargo.toml",
            "[package]\nname = \"app\"\n[dependencies]\nmid = { workspace = true }\n",
        );
        write("crates/app/src/main.rs", "fn main() {}\n");
    }

    fn ids(root: &Path) -> BTreeMap<String, u64> {
        workspace_identities(root, "app", &mut |_| {}).unwrap()
    }

    #[test]
    fn an_edit_changes_its_crate_and_the_crates_that_depend_on_it_only() {
        let dir = tempfile::tempdir().unwrap();
        workspace(dir.path());
        let before = ids(dir.path());
        assert_eq!(
            before.keys().collect::<Vec<_>>(),
            ["app", "leaf", "mid"],
            "{before:?}"
        );
        assert_eq!(ids(dir.path()), before, "deterministic");

        // The leaf's identity by hand: manifest, its one source file, the lock.
        let lock = piece(Fnv::new(), b"# lock v1\n");
        let mut leaf = piece(
            Fnv::new(),
            b"[package]\nname = \"leaf\"\n[dev-dependencies]\napp.workspace = true\n",
        );
        leaf = piece(piece(leaf, b"lib.rs"), b"pub fn leaf() {}\n");
        leaf = piece(leaf, &lock.0.to_le_bytes());
        assert_eq!(before["leaf"], leaf.0);

        // A file deep in mid's src/: mid and app change, leaf does not.
        std::fs::write(
            dir.path().join("crates/mid/src/deep/inner.rs"),
            "pub fn inner() { }\n",
        )
        .unwrap();
        let after = ids(dir.path());
        assert_eq!(after["leaf"], before["leaf"]);
        assert_ne!(after["mid"], before["mid"]);
        assert_ne!(after["app"], before["app"]);

        // Tests and READMEs are not the product: no change.
        let now = ids(dir.path());
        std::fs::create_dir_all(dir.path().join("crates/leaf/tests")).unwrap();
        std::fs::write(
            dir.path().join("crates/leaf/tests/t.rs"),
            "#[test] fn t() {}",
        )
        .unwrap();
        std::fs::write(dir.path().join("crates/leaf/README.md"), "# leaf").unwrap();
        assert_eq!(ids(dir.path()), now);

        // The leaf's source reaches everything; so does the lock.
        std::fs::write(
            dir.path().join("crates/leaf/src/lib.rs"),
            "pub fn leaf2() {}\n",
        )
        .unwrap();
        let edited = ids(dir.path());
        assert!(edited.iter().all(|(k, v)| now[k] != *v), "{edited:?}");
        std::fs::write(dir.path().join("Cargo.lock"), "# lock v2\n").unwrap();
        let relocked = ids(dir.path());
        assert!(
            relocked.iter().all(|(k, v)| edited[k] != *v),
            "{relocked:?}"
        );

        // A new file in src/ counts, and so does a renamed one.
        std::fs::write(dir.path().join("crates/leaf/src/extra.rs"), "").unwrap();
        let added = ids(dir.path());
        assert_ne!(added["leaf"], relocked["leaf"]);
        std::fs::rename(
            dir.path().join("crates/leaf/src/extra.rs"),
            dir.path().join("crates/leaf/src/other.rs"),
        )
        .unwrap();
        assert_ne!(ids(dir.path())["leaf"], added["leaf"]);
    }

    #[test]
    fn every_file_read_is_watched_and_a_non_workspace_is_none() {
        let dir = tempfile::tempdir().unwrap();
        workspace(dir.path());
        let mut watched = Vec::new();
        workspace_identities(dir.path(), "app", &mut |p| watched.push(p.to_path_buf()));
        for rel in [
            "Cargo.toml",
            "Cargo.lock",
            "crates/app/Cargo.toml",
            "crates/app/src",
            "crates/mid/src",
            "crates/leaf/src",
        ] {
            assert!(
                watched.contains(&dir.path().join(rel)),
                "{rel}: {watched:?}"
            );
        }
        assert!(workspace_identities(dir.path(), "absent", &mut |_| {}).is_none());
        let empty = tempfile::tempdir().unwrap();
        assert!(workspace_identities(empty.path(), "app", &mut |_| {}).is_none());
    }
}

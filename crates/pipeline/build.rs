//! Writes the *code identity* of every workspace crate the pipeline runs into
//! `OUT_DIR/code_identity.rs`, so that a stage's completion record can say which code
//! produced its outputs (README "Up-to-date rules"; the hashing is `src/identity.rs`).
//! Outside the workspace (a packaged crate) the sibling sources are not there: the
//! pipeline's own sources and version then stand for every crate.

use std::path::{Path, PathBuf};

#[path = "src/fnv.rs"]
mod fnv;
#[path = "src/identity.rs"]
mod identity;

fn main() {
    let here = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").unwrap_or_default());
    let own = std::env::var("CARGO_PKG_NAME").unwrap_or_default();
    let mut watch = |p: &Path| println!("cargo:rerun-if-changed={}", p.display());
    let table = identity::workspace_identities(&here.join("..").join(".."), &own, &mut watch)
        .unwrap_or_else(|| {
            let version = std::env::var("CARGO_PKG_VERSION").unwrap_or_default();
            let id = identity::own_sources(&here, &mut watch)
                .bytes(version.as_bytes())
                .0;
            [(own.clone(), id)].into()
        });
    let glue = identity::own_sources(&here, &mut watch).0;

    let mut code = format!(
        "/// Identity of the pipeline crate's own sources (the glue that calls each stage).\n\
         pub(crate) const GLUE_CODE: &str = \"{glue:016x}\";\n"
    );
    code.push_str(&identity::crate_code_table(&table, "the pipeline"));
    let out = PathBuf::from(std::env::var_os("OUT_DIR").unwrap_or_default());
    if let Err(e) = std::fs::write(out.join("code_identity.rs"), code) {
        panic!("cannot write code_identity.rs into OUT_DIR: {e}");
    }
}

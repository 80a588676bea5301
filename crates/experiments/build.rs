//! Writes the code identity of synth (and of every workspace crate the experiments run)
//! into `OUT_DIR/code_identity.rs`, with the pipeline's own hashing (`#[path]` below), so
//! that `profuse demo` regenerates its scene when the generator's code changed. This crate
//! is not published: the sibling sources are always there.

use std::path::{Path, PathBuf};

#[path = "../pipeline/src/fnv.rs"]
#[allow(dead_code)]
mod fnv;
#[path = "../pipeline/src/identity.rs"]
#[allow(dead_code)]
mod identity;

fn main() {
    let here = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").unwrap_or_default());
    let own = std::env::var("CARGO_PKG_NAME").unwrap_or_default();
    let mut watch = |p: &Path| println!("cargo:rerun-if-changed={}", p.display());
    let table = identity::workspace_identities(&here.join("..").join(".."), &own, &mut watch)
        .unwrap_or_default();
    let code = identity::crate_code_table(&table, "the experiments");
    let out = PathBuf::from(std::env::var_os("OUT_DIR").unwrap_or_default());
    if let Err(e) = std::fs::write(out.join("code_identity.rs"), code) {
        panic!("cannot write code_identity.rs into OUT_DIR: {e}");
    }
}

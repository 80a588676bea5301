//! `vertex-transfer` tool (under construction).
fn main() {}

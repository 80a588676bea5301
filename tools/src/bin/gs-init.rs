//! `gs-init` tool (under construction).
fn main() {}

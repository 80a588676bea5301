//! `fuse` tool (under construction).
fn main() {}

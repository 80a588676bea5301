//! `metrics` tool (under construction).
fn main() {}

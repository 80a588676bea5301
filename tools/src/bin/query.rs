//! `query` tool (under construction).
fn main() {}

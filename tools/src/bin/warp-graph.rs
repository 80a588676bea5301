//! `warp-graph` tool (under construction).
fn main() {}

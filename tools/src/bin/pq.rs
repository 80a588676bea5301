//! `pq` tool (under construction).
fn main() {}

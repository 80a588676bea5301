//! End-to-end tests of the `warp-graph` tool.

//! End-to-end tests of the `fuse` tool.

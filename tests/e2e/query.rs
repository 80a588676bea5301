//! End-to-end tests of the `query` tool.

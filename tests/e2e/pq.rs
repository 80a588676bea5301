//! End-to-end tests of the `pq` tool.

//! End-to-end tests of the `vertex-transfer` tool.

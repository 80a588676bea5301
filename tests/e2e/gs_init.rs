//! End-to-end tests of the `gs-init` tool.

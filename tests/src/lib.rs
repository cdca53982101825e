//! End-to-end tests across the skyherd crates live in `tests/`.

//! The `trainer` integration tests: one binary, a module per feature.

mod libtorch;
mod scheduler;
mod vae;

//! The `trainer` integration tests: one binary, a module per feature.

mod data;
mod eval_cli;
mod forward_cli;
mod libtorch;
mod parity;
mod pretrain;
mod scheduler;
mod transformer;
mod vae;

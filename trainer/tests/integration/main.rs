//! The `trainer` integration tests: one binary, a module per feature.

mod checkpointing;
mod data;
mod eval_cli;
mod forward_cli;
mod hostile_inputs;
mod libtorch;
mod lora;
mod parity;
mod pretrain;
mod scheduler;
mod transformer;
mod vae;

//! The `trainer` integration tests: one binary, a module per feature.

mod benchmark;
mod checkpointing;
mod data;
mod distributed;
mod eval_benchmark;
mod eval_cli;
mod eval_parity;
mod eval_protocol;
mod forward_cli;
mod hostile_inputs;
mod libtorch;
mod long_runs;
mod lora;
mod nvs;
mod parity;
mod plan;
mod pretrain;
mod sampling;
mod scheduler;
mod tensorboard;
mod text_embedding;
mod transformer;
mod vae;
mod validation;
mod wan;
mod wan_training;

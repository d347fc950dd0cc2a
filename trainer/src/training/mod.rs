//! Pretraining the CogNVS transformer on shard pairs: the objective, AdamW, the
//! learning-rate schedule, gradient clipping and accumulation, checkpoints that resume exactly,
//! and the `trainer pretrain` loop.
//!
//! Objective (the public CogNVS code): the target clip is VAE-encoded (a posterior sample ×
//! `scaling_factor`); the conditioning clip is noise-augmented with σ = exp(N(μ, s)) per sample
//! (μ = −3, s = 0.5) before encoding; the noisy target latent at a uniform timestep t and the
//! condition latent are concatenated on channels; the transformer predicts v, from which
//! x̂₀ = √ᾱ_t·x_t − √(1−ᾱ_t)·v̂; the loss is mean((x̂₀ − x₀)² / (1−ᾱ_t)). The VAE is frozen.
//! The text input is a fixed embedding of the empty prompt: loaded from a safetensors file
//! (`encoder_hidden_states` `[S, D]`, e.g. T5-XXL's encoding of "" for the real model) or zeros.
//!
//! Determinism: every random draw of step k comes from tch's generator seeded with
//! (seed, k), and batches are a pure function of the data position, so a run resumed from a
//! checkpoint reproduces the uninterrupted run's losses exactly (fp32, same machine and threads).
//!
//! Checkpoints: `RUN_DIR/checkpoints/step-NNNNNNNN/` holds `transformer/` (diffusers layout,
//! loadable by `from_pretrained`), `optimizer.safetensors` (AdamW moments) and `state.json`
//! (step, data position, every other file's size and digest); written under a temporary name
//! and renamed, the oldest intact ones beyond `keep_last` removed. With `validate_every`,
//! validation samples go to `RUN_DIR/samples/`. The frozen VAE is saved once as `RUN_DIR/vae/`
//! and the run's config as `RUN_DIR/config.json`. `RUN_DIR/metrics.jsonl` has one line per step
//! and one per validation.
//!
//! Long runs: rank 0 holds the folder's lock for the whole run (`run_lock`), preemption signals
//! end the run after a step with a complete checkpoint (`preempt`), `--resume` takes the newest
//! checkpoint whose files match their digests (`checkpoint`), and held-out pairs are measured
//! while training (`validation`); what the ranks decide together goes through `consensus`.
//!
//! One file per part: `config` (the TOML), `adamw` (optimizer), `lr_schedule`,
//! `objective` (models and loss), `latent_cache`, `checkpoint`, `pretrain` (the loop),
//! `finetune`, `run_lock`, `preempt`, `consensus`, `validation` and `comm_cost` (the exchange's
//! share of a data-parallel step).

mod adamw;
pub mod checkpoint;
mod comm_cost;
mod config;
pub mod consensus;
pub mod data;
mod finetune;
mod latent_cache;
mod lr_schedule;
mod objective;
mod parallel;
pub mod plan;
pub mod preempt;
mod pretrain;
pub mod run_lock;
pub mod tensorboard;
pub mod validation;

pub use adamw::AdamW;
pub(crate) use adamw::trainable_parameters;
pub use checkpoint::{CheckpointLayout, FileRecord, TrainState, list_checkpoints};
pub use comm_cost::{CommCost, VariantTiming, comm_cost};
pub use config::{
    CheckpointEvery, ConfigSource, DistributedConfig, LoopConfig, ModelConfig, OptimConfig, Precision, PretrainConfig,
    ValidationConfig, timeout_seconds,
};
pub use finetune::{
    FinetuneRequest, ReadSequence, finetune, finetune_config, finetune_launched, finetune_on, finetune_pairs_config,
};
pub use latent_cache::LatentCache;
pub use lr_schedule::learning_rate;
pub use objective::{
    Backward, CogNvsModel, Draws, FlowSchedule, TrainingSchedule, flow_matching_loss, flow_noisy_and_target,
};
pub use pretrain::{
    RunEvent, RunSummary, StepMetrics, pretrain, pretrain_launched, pretrain_on, read_metrics, read_validation,
};
pub use run_lock::RunLock;

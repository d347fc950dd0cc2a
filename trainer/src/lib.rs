//! `trainer`: the CogNVS video-to-video diffusion model (a diffusers `CogVideoXTransformer3DModel`
//! with the CogVideoX 3D causal VAE and schedulers) in tch, weight-compatible with diffusers.
//!
//! Modules are named after the diffusers files they mirror.

pub mod attention;
pub mod autoencoder_kl_cogvideox;
pub mod benchmark;
pub mod cogvideox_transformer_3d;
pub mod data;
pub mod diffusers_config;
pub mod distributed;
pub mod embeddings;
pub mod error;
pub mod eval;
pub mod forward;
pub mod loaders;
pub mod lora;
pub mod metrics;
pub mod normalization;
pub mod nvs;
pub mod plan;
pub mod precision;
pub mod sampling;
pub mod scheduling_ddim_cogvideox;
pub mod scheduling_dpm_cogvideox;
pub mod tensorboard;
pub mod training;
pub mod vars;
pub mod video_processor;
pub mod weights;

pub use error::{Error, Result};
pub use tch;

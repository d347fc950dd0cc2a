//! `trainer`: the CogNVS video-to-video diffusion model (a diffusers `CogVideoXTransformer3DModel`
//! with the CogVideoX 3D causal VAE and schedulers) in tch, weight-compatible with diffusers.
//!
//! Modules are named after the diffusers files they mirror.

pub mod autoencoder_kl_cogvideox;
pub mod diffusers_config;
pub mod error;
pub mod scheduling_cogvideox_dpm;
pub mod scheduling_ddim;

pub use error::{Error, Result};
pub use tch;

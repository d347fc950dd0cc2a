//! `trainer`: the CogNVS video-to-video diffusion model (a diffusers `CogVideoXTransformer3DModel`
//! with the CogVideoX 3D causal VAE and schedulers) in tch, weight-compatible with diffusers.
//!
//! Modules are named after the diffusers files they mirror.

pub mod diffusers_config;
pub mod distributed;
pub mod error;
pub mod eval;
pub mod loaders;
pub mod models;
pub mod pipelines;
pub mod precision;
pub mod schedulers;
pub mod training;

pub use error::{Error, Result};
pub use tch;

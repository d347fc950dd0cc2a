//! `trainer`: the CogNVS video-to-video diffusion model (a diffusers `CogVideoXTransformer3DModel`
//! with the CogVideoX 3D causal VAE and schedulers) in tch, weight-compatible with diffusers.

pub use tch;

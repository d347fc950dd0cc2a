//! The CogVideoX family: its transformer (`cogvideox_transformer_3d`) and its 3D causal VAE
//! (`autoencoder_kl_cogvideox`), named after the diffusers files they mirror.

pub mod autoencoder_kl_cogvideox;
pub mod cogvideox_transformer_3d;

//! The Wan family (2.1 and 2.2): its transformer (`transformer_wan`) and its VAE
//! (`autoencoder_kl_wan`), named after the diffusers files they mirror, and the CogNVS
//! conditioning's mask channels (`cognvs`).

pub mod autoencoder_kl_wan;
pub mod cognvs;
pub mod transformer_wan;

//! The model components, named after the diffusers files they mirror (`diffusers/models/`): the
//! CogVideoX transformer and its parts (`embeddings`, `attention`, `normalization`), the 3D causal
//! VAE, the Wan transformer and VAE (`transformer_wan`, `autoencoder_kl_wan`), the LoRA layer, and
//! the variables and weight files they are made of (`vars` creates variables at diffusers'
//! state-dict paths; `weights` reads and writes diffusers model folders, as diffusers'
//! `modeling_utils` does). Each family is a folder (`cogvideox/`, `wan/`); `family` tells the
//! families apart from a config's `_class_name`, once for every job, and `backbone` is the one
//! interface the pipelines and training loops reach either family through.

pub mod attention;
pub mod backbone;
pub mod cogvideox;
pub mod embeddings;
pub mod family;
pub mod lora;
pub mod normalization;
pub mod vars;
pub mod wan;
pub mod weights;

//! `trainer`: the CogNVS video-to-video diffusion model (a diffusers `CogVideoXTransformer3DModel`
//! with the CogVideoX 3D causal VAE and schedulers) in tch, weight-compatible with diffusers.
//!
//! Laid out as diffusers is, from the bottom: the foundations ([`error`], [`precision`],
//! [`diffusers_config`]); [`models`]; [`schedulers`]; [`loaders`] (where models come from);
//! [`distributed`] (c10d); [`eval`]; [`pipelines`] (sampling and its video processor);
//! [`training`]; the jobs ([`pipelines::nvs`], [`benchmark`]); and [`cli`], every command's
//! flags and their conversion into the requests above (the `trainer` binary only dispatches to
//! it). Files are named after the diffusers files they mirror; a module uses its own layer and
//! those below (`docs/ARCHITECTURE.md` states the layers, `scripts/check_module_cycles.py`
//! checks them).

pub mod benchmark;
pub mod cli;
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

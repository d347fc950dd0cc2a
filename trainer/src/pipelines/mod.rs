//! From a model to videos, as diffusers' `pipelines/`: `sampling` (the CogNVS pipeline, draw for
//! draw the public one), `video_processor` (its pre- and post-processing), `nvs` (the user's whole
//! novel-view job: finetune, render, sample) and `forward` (one forward pass of a component, for
//! checking a port against another implementation), `pipeline_wan` (Wan text-to-video sampling,
//! draw for draw diffusers' `WanPipeline`).

pub mod forward;
pub mod nvs;
pub mod pipeline_wan;
pub mod sampling;
pub mod video_processor;

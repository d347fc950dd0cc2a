//! From a model to videos, as diffusers' `pipelines/`: `sampling` (the CogNVS pipeline, draw for
//! draw the public one, and the family dispatch of every sampling job; `sampling_wan` its Wan
//! models), `video_processor` (its pre- and post-processing), `nvs` (the user's whole
//! novel-view job: finetune, render, sample), `forward` (one forward pass of a component, for
//! checking a port against another implementation) and `pipeline_wan` (Wan sampling, draw for
//! draw diffusers' `WanPipeline` and `WanImageToVideoPipeline`, and the CogNVS conditioning on Wan).

pub mod forward;
pub mod nvs;
pub mod pipeline_wan;
pub mod sampling;
pub mod sampling_wan;
pub mod video_processor;

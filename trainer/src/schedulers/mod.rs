//! The noise schedulers, named after diffusers' `schedulers/` files: the shared core of the
//! CogVideoX schedulers (`scheduling_utils`: the config, the noise schedule, [`Scheduler`]) and
//! the two CogVideoX samplers built on it, DDIM and the DPM-Solver++ the 5B pipelines sample with;
//! and Wan's flow-matching schedulers, the Euler sampler (with the shared sigma shifting) and
//! UniPC on flow sigmas.

pub mod scheduling_ddim_cogvideox;
pub mod scheduling_dpm_cogvideox;
pub mod scheduling_flow_match_euler_discrete;
pub mod scheduling_unipc_multistep;
pub mod scheduling_utils;

pub use scheduling_ddim_cogvideox::CogVideoXDDIMScheduler;
pub use scheduling_dpm_cogvideox::CogVideoXDPMScheduler;
pub use scheduling_utils::{
    CLASS_NAMES, CogVideoXSchedulerConfig, MAX_TRAIN_TIMESTEPS, NoiseSchedule, PredictionType, Scheduler,
    SchedulerState, SchedulerStepOutput, TimestepSpacing,
};

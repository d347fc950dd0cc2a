//! CogVideoX's DDIM scheduler: diffusers' `CogVideoXDDIMScheduler`
//! (`diffusers/schedulers/scheduling_ddim_cogvideox.py`), deterministic DDIM (η = 0). What it
//! shares with the DPM scheduler is in [`super::scheduling_utils`].

use tch::Tensor;

use super::scheduling_utils::{Scheduler, SchedulerState, SchedulerStepOutput, same_shape};
use crate::error::{Error, Result};

/// diffusers' `CogVideoXDDIMScheduler` (deterministic DDIM, η = 0).
#[derive(Debug)]
pub struct CogVideoXDDIMScheduler {
    state: SchedulerState,
}

impl Scheduler for CogVideoXDDIMScheduler {
    fn from_state(state: SchedulerState) -> Self {
        Self { state }
    }

    fn state(&self) -> &SchedulerState {
        &self.state
    }

    fn state_mut(&mut self) -> &mut SchedulerState {
        &mut self.state
    }
}

impl CogVideoXDDIMScheduler {
    /// One DDIM step from `timestep` to `timestep − T/n`.
    pub fn step(&self, model_output: &Tensor, timestep: i64, sample: &Tensor) -> Result<SchedulerStepOutput> {
        same_shape(sample, model_output, "model_output")?;
        let prev_timestep = timestep - self.state.step_ratio("CogVideoXDDIMScheduler")?;
        if timestep < 0 {
            return Err(Error::InvalidArgument { name: "timestep".to_string(), reason: format!("{timestep} < 0") });
        }
        let schedule = self.schedule();
        let alpha_t = schedule.alpha_cumprod_at(timestep)?;
        let alpha_prev = schedule.alpha_cumprod_at(prev_timestep)?;
        let pred = schedule.pred_original_sample(model_output, sample, alpha_t)?;
        let a = ((1.0 - alpha_prev) / (1.0 - alpha_t)).sqrt();
        let b = alpha_prev.sqrt() - alpha_t.sqrt() * a;
        let prev_sample = sample.f_mul_scalar(a)?.f_add(&pred.f_mul_scalar(b)?)?;
        Ok(SchedulerStepOutput { prev_sample, pred_original_sample: pred })
    }
}

//! CogVideoX's sampler: diffusers' `CogVideoXDPMScheduler`
//! (`diffusers/schedulers/scheduling_dpm_cogvideox.py`), a stochastic DPM-Solver++(2M) in the
//! log-SNR λ = log √(ᾱ/(1−ᾱ)): a first-order step from x̂₀, then second-order steps that
//! extrapolate x̂₀ with the previous step's x̂₀. Every step injects fresh Gaussian noise scaled by
//! √(1−ᾱ_prev)·√(1−e^{−2h}). The 5B pipelines sample with it for 50 steps.
//!
//! Noise: diffusers draws one noise tensor on a first-order step and two on a second-order step
//! (keeping the second). [`CogVideoXDPMScheduler::step`] draws the same way from tch's global
//! generator, so a run seeded like a PyTorch run replays it; [`CogVideoXDPMScheduler::step_with_noise`]
//! takes the noise that ends up in the update explicitly (tests, reproducible sampling).

use tch::Tensor;

use super::scheduling_utils::{Scheduler, SchedulerState, SchedulerStepOutput, same_shape};
use crate::error::Result;

/// diffusers' `CogVideoXDPMScheduler`.
#[derive(Debug)]
pub struct CogVideoXDPMScheduler {
    state: SchedulerState,
}

impl Scheduler for CogVideoXDPMScheduler {
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

/// Log-SNR λ = log √(ᾱ / (1 − ᾱ)) (−∞ at ᾱ = 0, +∞ at ᾱ = 1).
fn lambda(alpha_cumprod: f64) -> f64 {
    (alpha_cumprod / (1.0 - alpha_cumprod)).sqrt().ln()
}

/// The float64 coefficients of one step (diffusers' `get_variables` / `get_mult`).
#[derive(Debug, Clone, Copy)]
struct StepCoefficients {
    /// Multiplies x_t.
    sample: f64,
    /// Multiplies x̂₀ (or the extrapolated x̂₀), subtracted.
    denoised: f64,
    /// Multiplies the injected noise.
    noise: f64,
    /// Second order only: x̂₀ extrapolation weights `1 + 1/(2r)` and `1/(2r)`.
    extrapolation: Option<(f64, f64)>,
}

impl CogVideoXDPMScheduler {
    /// Whether a step at `timestep` with a previous x̂₀ is second order (draws noise twice).
    pub fn is_second_order(&self, timestep: i64, has_old_pred: bool) -> Result<bool> {
        Ok(has_old_pred && self.prev_timestep(timestep)? >= 0)
    }

    fn prev_timestep(&self, timestep: i64) -> Result<i64> {
        Ok(timestep - self.state.step_ratio("CogVideoXDPMScheduler")?)
    }

    fn coefficients(&self, timestep: i64, timestep_back: Option<i64>, second_order: bool) -> Result<StepCoefficients> {
        let alpha_t = self.schedule().alpha_cumprod_at(timestep.max(0))?;
        let alpha_prev = self.schedule().alpha_cumprod_at(self.prev_timestep(timestep)?)?;
        let lamb = lambda(alpha_t);
        let h = lambda(alpha_prev) - lamb;
        let extrapolation = match (second_order, timestep_back) {
            (true, Some(back)) => {
                let h_last = lamb - lambda(self.schedule().alpha_cumprod_at(back)?);
                let r = h_last / h;
                Some((1.0 + 1.0 / (2.0 * r), 1.0 / (2.0 * r)))
            }
            (true, None) => {
                return Err(crate::error::Error::InvalidArgument {
                    name: "timestep_back".to_string(),
                    reason: "a second-order step (old_pred_original_sample given) needs the previous timestep"
                        .to_string(),
                });
            }
            (false, _) => None,
        };
        Ok(StepCoefficients {
            sample: ((1.0 - alpha_prev) / (1.0 - alpha_t)).sqrt() * (-h).exp(),
            denoised: (-2.0 * h).exp_m1() * alpha_prev.sqrt(),
            noise: (1.0 - alpha_prev).sqrt() * (1.0 - (-2.0 * h).exp()).sqrt(),
            extrapolation,
        })
    }

    /// One step from `timestep` (noise drawn from tch's global generator exactly as diffusers
    /// draws it). `old_pred_original_sample` is the previous step's x̂₀ (None on the first step)
    /// and `timestep_back` the previous step's timestep.
    pub fn step(
        &self,
        model_output: &Tensor,
        old_pred_original_sample: Option<&Tensor>,
        timestep: i64,
        timestep_back: Option<i64>,
        sample: &Tensor,
    ) -> Result<SchedulerStepOutput> {
        let mut noise = sample.f_randn_like()?;
        if self.is_second_order(timestep, old_pred_original_sample.is_some())? {
            noise = sample.f_randn_like()?;
        }
        self.step_with_noise(model_output, old_pred_original_sample, timestep, timestep_back, sample, &noise)
    }

    /// [`Self::step`] with the noise that enters the update given explicitly.
    pub fn step_with_noise(
        &self,
        model_output: &Tensor,
        old_pred_original_sample: Option<&Tensor>,
        timestep: i64,
        timestep_back: Option<i64>,
        sample: &Tensor,
        noise: &Tensor,
    ) -> Result<SchedulerStepOutput> {
        same_shape(sample, model_output, "model_output")?;
        same_shape(sample, noise, "noise")?;
        if let Some(old) = old_pred_original_sample {
            same_shape(sample, old, "old_pred_original_sample")?;
        }
        if timestep < 0 {
            return Err(crate::error::Error::InvalidArgument {
                name: "timestep".to_string(),
                reason: format!("{timestep} < 0"),
            });
        }
        let second_order = self.is_second_order(timestep, old_pred_original_sample.is_some())?;
        let c = self.coefficients(timestep, timestep_back, second_order)?;
        let alpha_t = self.schedule().alpha_cumprod_at(timestep)?;
        let pred = self.schedule().pred_original_sample(model_output, sample, alpha_t)?;
        let denoised = match (c.extrapolation, old_pred_original_sample) {
            (Some((m3, m4)), Some(old)) => pred.f_mul_scalar(m3)?.f_sub(&old.f_mul_scalar(m4)?)?,
            _ => pred.shallow_clone(),
        };
        let prev_sample = sample
            .f_mul_scalar(c.sample)?
            .f_sub(&denoised.f_mul_scalar(c.denoised)?)?
            .f_add(&noise.f_mul_scalar(c.noise)?)?;
        Ok(SchedulerStepOutput { prev_sample, pred_original_sample: pred })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::schedulers::CogVideoXSchedulerConfig;
    use tch::{Device, Kind};

    #[test]
    fn last_step_returns_the_prediction() {
        // At the final step ᾱ_prev = 1: no noise, x_{t-1} = x̂₀ (a property of the update rule).
        let mut s = CogVideoXDPMScheduler::new(&CogVideoXSchedulerConfig::cogvideox_5b()).unwrap();
        s.set_timesteps(50).unwrap();
        let x = Tensor::randn([2, 3], (Kind::Float, Device::Cpu));
        let v = Tensor::randn([2, 3], (Kind::Float, Device::Cpu));
        let noise = Tensor::randn([2, 3], (Kind::Float, Device::Cpu)) * 100.0;
        let out = s.step_with_noise(&v, Some(&x), 19, Some(39), &x, &noise).unwrap();
        let diff = (&out.prev_sample - &out.pred_original_sample).abs().max().double_value(&[]);
        assert!(diff < 1e-6, "{diff}");
    }

    #[test]
    fn step_before_set_timesteps_is_an_error() {
        let s = CogVideoXDPMScheduler::new(&CogVideoXSchedulerConfig::cogvideox_5b()).unwrap();
        let x = Tensor::zeros([1], (Kind::Float, Device::Cpu));
        assert!(s.step(&x, None, 999, None, &x).unwrap_err().to_string().contains("set_timesteps"));
    }
}

//! The flow-matching Euler sampler: diffusers' `FlowMatchEulerDiscreteScheduler`
//! (`diffusers/schedulers/scheduling_flow_match_euler_discrete.py`), the scheduler Wan is trained
//! with and one of the two it samples with.
//!
//! A flow-matching model sees `x_σ = (1 − σ)·x₀ + σ·ε` and predicts the velocity `ε − x₀`; sampling
//! walks σ from 1 down to 0 with Euler steps `x ← x + (σ_next − σ)·v`. The σ schedule is shifted
//! towards the noisy end (`shift`, or a resolution-dependent `mu` with `use_dynamic_shifting`), and
//! may be stretched to end at `shift_terminal` or respaced as Karras or exponential sigmas. Like
//! diffusers, the schedule is built in fp64 and stored in fp32, and the training-time sigmas that
//! bound the inference schedule are the shifted training schedule's (so a static shift applies
//! twice to the ends: diffusers' behaviour, kept for equal timesteps).
//!
//! The shared shifting functions (also used by `scheduling_unipc_multistep`) live here, as
//! diffusers' UniPC copies them from this file.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor};

use crate::diffusers_config::{self, DiffusersConfig};
use crate::error::{Error, Result};

/// The class name of this scheduler's `scheduler_config.json`.
pub const CLASS_NAME: &str = "FlowMatchEulerDiscreteScheduler";
/// Karras et al.'s ρ (diffusers' `_convert_to_karras`: "the value used in the paper").
const KARRAS_RHO: f64 = 7.0;
/// Largest `num_train_timesteps` (the discrete training grid is allocated).
pub const MAX_TRAIN_TIMESTEPS: i64 = 1 << 20;

/// How `mu` shifts the sigmas with `use_dynamic_shifting` (diffusers' `time_shift_type`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TimeShiftType {
    /// `e^μ / (e^μ + (1/σ − 1))`.
    Exponential,
    /// `μ / (μ + (1/σ − 1))`.
    Linear,
}

/// diffusers' `time_shift(mu, 1.0, σ)` of one sigma.
pub fn time_shift(kind: TimeShiftType, mu: f64, sigma: f64) -> f64 {
    match kind {
        TimeShiftType::Exponential => mu.exp() / (mu.exp() + (1.0 / sigma - 1.0)),
        TimeShiftType::Linear => mu / (mu + (1.0 / sigma - 1.0)),
    }
}

/// The static shift `s·σ / (1 + (s − 1)·σ)` (Wan's `flow_shift`, SD3's `shift`).
pub fn static_shift(shift: f64, sigma: f64) -> f64 {
    shift * sigma / (1.0 + (shift - 1.0) * sigma)
}

/// diffusers' `stretch_shift_to_terminal`: rescales `1 − σ` so the last sigma becomes `terminal`.
pub fn stretch_shift_to_terminal(sigmas: &mut [f64], terminal: f64) {
    let Some(&last) = sigmas.last() else { return };
    let scale = (1.0 - last) / (1.0 - terminal);
    for s in sigmas.iter_mut() {
        *s = 1.0 - (1.0 - *s) / scale;
    }
}

/// How a flow schedule's sigmas are shifted towards the noisy end: the part of
/// `set_timesteps` that `FlowMatchEulerDiscreteScheduler` and the UniPC scheduler on flow sigmas
/// share (diffusers copies it between them).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlowShift {
    /// Shift by the `mu` given to `set_timesteps` (`use_dynamic_shifting`) instead of `shift`.
    pub dynamic: bool,
    /// The dynamic shift's form.
    pub time_shift_type: TimeShiftType,
    /// The static shift (`shift`, UniPC's `flow_shift`).
    pub shift: f64,
    /// Stretch the shifted schedule to end at this sigma; null or 0 for no stretch.
    pub shift_terminal: Option<f64>,
}

impl FlowShift {
    /// Shifts `sigmas` in place (fp64, as diffusers computes them in numpy); `mu` is required
    /// exactly when the shift is dynamic.
    pub fn apply(&self, sigmas: &mut [f64], mu: Option<f64>) -> Result<()> {
        match (self.dynamic, mu) {
            (true, Some(mu)) => sigmas.iter_mut().for_each(|s| *s = time_shift(self.time_shift_type, mu, *s)),
            (true, None) => {
                return Err(Error::InvalidArgument {
                    name: "mu".to_string(),
                    reason: "required when use_dynamic_shifting is set".to_string(),
                });
            }
            (false, _) => sigmas.iter_mut().for_each(|s| *s = static_shift(self.shift, *s)),
        }
        if let Some(terminal) = self.shift_terminal.filter(|&t| t != 0.0) {
            stretch_shift_to_terminal(sigmas, terminal);
        }
        Ok(())
    }
}

/// Refuses a schedule of no steps (both flow schedulers' `set_timesteps`).
pub fn check_steps(num_inference_steps: usize) -> Result<()> {
    if num_inference_steps == 0 {
        return Err(Error::InvalidArgument {
            name: "num_inference_steps".to_string(),
            reason: "must be at least 1".to_string(),
        });
    }
    Ok(())
}

/// The training schedule's sigmas, `num_train_timesteps` of them from the noisiest down, as
/// diffusers' constructor builds them (in fp32 torch arithmetic): `t/N` for t = N … 1, statically
/// shifted unless the shift is dynamic. Flow-matching training draws its sigmas from this grid.
pub fn training_sigmas(config: &FlowMatchEulerDiscreteSchedulerConfig) -> Vec<f32> {
    let n = config.num_train_timesteps;
    (1..=n)
        .rev()
        .map(|t| {
            let s = t as f32 / n as f32;
            if config.use_dynamic_shifting {
                s
            } else {
                let shift = config.shift as f32;
                shift * s / (1.0 + (shift - 1.0) * s)
            }
        })
        .collect()
}

/// `n` evenly spaced values from `start` to `end` inclusive, as `np.linspace` computes them.
pub fn linspace(start: f64, end: f64, n: usize) -> Vec<f64> {
    match n {
        0 => Vec::new(),
        1 => vec![start],
        _ => {
            let step = (end - start) / (n - 1) as f64;
            let mut v: Vec<f64> = (0..n).map(|i| start + i as f64 * step).collect();
            v[n - 1] = end;
            v
        }
    }
}

/// The scheduler's `scheduler_config.json`, field names verbatim, defaults of diffusers'
/// `__init__`; other keys are kept in `extra` and reported.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FlowMatchEulerDiscreteSchedulerConfig {
    /// Training timesteps (σ = t / N).
    pub num_train_timesteps: i64,
    /// Static shift of the sigmas (ignored with `use_dynamic_shifting`).
    pub shift: f64,
    /// Shift by `mu` given to `set_timesteps` instead of `shift`.
    pub use_dynamic_shifting: bool,
    /// Kept for the pipelines that compute `mu` from the resolution.
    pub base_shift: Option<f64>,
    /// Kept for the pipelines that compute `mu` from the resolution.
    pub max_shift: Option<f64>,
    /// Kept for the pipelines that compute `mu` from the resolution.
    pub base_image_seq_len: i64,
    /// Kept for the pipelines that compute `mu` from the resolution.
    pub max_image_seq_len: i64,
    /// Use `1 − σ` (Mochi).
    pub invert_sigmas: bool,
    /// Stretch the shifted schedule to end at this sigma; null or 0 for no stretch.
    pub shift_terminal: Option<f64>,
    /// Respace the sigmas as Karras et al. do.
    pub use_karras_sigmas: bool,
    /// Respace the sigmas exponentially.
    pub use_exponential_sigmas: bool,
    /// Beta-distributed sigmas (needs scipy's beta quantiles; refused).
    pub use_beta_sigmas: bool,
    /// The dynamic shift's form.
    pub time_shift_type: TimeShiftType,
    /// Re-noise each step from the predicted sample instead of the Euler step.
    pub stochastic_sampling: bool,
    /// Every other key: `_class_name`, `_diffusers_version`, … and unknown keys.
    #[serde(flatten)]
    pub extra: BTreeMap<String, serde_json::Value>,
}

impl Default for FlowMatchEulerDiscreteSchedulerConfig {
    fn default() -> Self {
        Self {
            num_train_timesteps: 1000,
            shift: 1.0,
            use_dynamic_shifting: false,
            base_shift: Some(0.5),
            max_shift: Some(1.15),
            base_image_seq_len: 256,
            max_image_seq_len: 4096,
            invert_sigmas: false,
            shift_terminal: None,
            use_karras_sigmas: false,
            use_exponential_sigmas: false,
            use_beta_sigmas: false,
            time_shift_type: TimeShiftType::Exponential,
            stochastic_sampling: false,
            extra: BTreeMap::new(),
        }
    }
}

impl DiffusersConfig for FlowMatchEulerDiscreteSchedulerConfig {
    const KIND: &'static str = "scheduler";
    const CLASS_NAMES: &'static [&'static str] = &[CLASS_NAME];
    const FILE_NAME: &'static str = "scheduler_config.json";

    fn validate_fields(&self, source_name: &str) -> Result<()> {
        let err = diffusers_config::field_error(source_name);
        if !(1..=MAX_TRAIN_TIMESTEPS).contains(&self.num_train_timesteps) {
            return Err(err(
                "num_train_timesteps",
                format!("must be in [1, {MAX_TRAIN_TIMESTEPS}], got {}", self.num_train_timesteps),
            ));
        }
        if !(self.shift > 0.0 && self.shift.is_finite()) {
            return Err(err("shift", format!("must be positive and finite, got {}", self.shift)));
        }
        if let Some(t) = self.shift_terminal.filter(|&t| !(0.0..1.0).contains(&t)) {
            return Err(err("shift_terminal", format!("must be in [0, 1) or null, got {t}")));
        }
        let respacings = [self.use_karras_sigmas, self.use_exponential_sigmas, self.use_beta_sigmas];
        if respacings.iter().filter(|&&b| b).count() > 1 {
            return Err(err(
                "use_karras_sigmas",
                "only one of use_beta_sigmas, use_exponential_sigmas, use_karras_sigmas can be set".to_string(),
            ));
        }
        if self.use_beta_sigmas {
            return Err(err(
                "use_beta_sigmas",
                "beta-distributed sigmas are not supported (no Wan configuration uses them)".to_string(),
            ));
        }
        Ok(())
    }

    fn extra(&self) -> &BTreeMap<String, serde_json::Value> {
        &self.extra
    }
}

/// diffusers' `FlowMatchEulerDiscreteScheduler`: the σ schedule, `scale_noise` and `step`.
#[derive(Debug, Clone)]
pub struct FlowMatchEulerDiscreteScheduler {
    config: FlowMatchEulerDiscreteSchedulerConfig,
    /// The ends of the (shifted) training schedule, as fp32 values.
    sigma_min: f32,
    sigma_max: f32,
    timesteps: Vec<f32>,
    /// One more than `timesteps`: the terminal sigma last.
    sigmas: Vec<f32>,
    step_index: Option<usize>,
    begin_index: Option<usize>,
}

impl FlowMatchEulerDiscreteScheduler {
    /// A scheduler for `config`, holding the training schedule until
    /// [`set_timesteps`](Self::set_timesteps) is called.
    pub fn new(config: &FlowMatchEulerDiscreteSchedulerConfig) -> Result<Self> {
        config.validate("scheduler config")?;
        let n = config.num_train_timesteps;
        let sigmas = training_sigmas(config);
        let timesteps = sigmas.iter().map(|s| s * n as f32).collect();
        Ok(Self {
            config: config.clone(),
            sigma_min: *sigmas.last().expect("num_train_timesteps ≥ 1"),
            sigma_max: sigmas[0],
            timesteps,
            sigmas,
            step_index: None,
            begin_index: None,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &FlowMatchEulerDiscreteSchedulerConfig {
        &self.config
    }

    /// Chooses `num_inference_steps` sigmas between the training schedule's ends; `mu` is the
    /// dynamic shift, required exactly when `use_dynamic_shifting` is set.
    pub fn set_timesteps(&mut self, num_inference_steps: usize, mu: Option<f64>) -> Result<()> {
        let c = &self.config;
        check_steps(num_inference_steps)?;
        let n = c.num_train_timesteps as f64;
        let ends = (f64::from(self.sigma_max) * n, f64::from(self.sigma_min) * n);
        let mut sigmas: Vec<f64> = linspace(ends.0, ends.1, num_inference_steps).into_iter().map(|t| t / n).collect();
        let shift = FlowShift {
            dynamic: c.use_dynamic_shifting,
            time_shift_type: c.time_shift_type,
            shift: c.shift,
            shift_terminal: c.shift_terminal,
        };
        shift.apply(&mut sigmas, mu)?;
        if c.use_karras_sigmas {
            sigmas = karras(&sigmas);
        } else if c.use_exponential_sigmas {
            sigmas = exponential(&sigmas);
        }
        let mut sigmas: Vec<f32> = sigmas.into_iter().map(|s| s as f32).collect();
        let terminal = if c.invert_sigmas {
            sigmas.iter_mut().for_each(|s| *s = 1.0 - *s);
            1.0
        } else {
            0.0
        };
        self.timesteps = sigmas.iter().map(|s| s * c.num_train_timesteps as f32).collect();
        sigmas.push(terminal);
        self.sigmas = sigmas;
        self.step_index = None;
        self.begin_index = None;
        Ok(())
    }

    /// The timesteps the model is called with, descending (fp32, fractional).
    pub fn timesteps(&self) -> &[f32] {
        &self.timesteps
    }

    /// The sigmas, one more than the timesteps (the terminal sigma last).
    pub fn sigmas(&self) -> &[f32] {
        &self.sigmas
    }

    /// The step the next [`step`](Self::step) takes, once stepping has started.
    pub fn step_index(&self) -> Option<usize> {
        self.step_index
    }

    /// Starts stepping at index `begin_index` (pipelines that start mid-schedule).
    pub fn set_begin_index(&mut self, begin_index: usize) {
        self.begin_index = Some(begin_index);
    }

    /// diffusers' `index_for_timestep`: the position of `timestep` in the schedule (the second
    /// one if it occurs twice, so a schedule entered mid-way does not skip a sigma).
    pub fn index_for_timestep(&self, timestep: f32) -> Result<usize> {
        let hits: Vec<usize> =
            self.timesteps.iter().enumerate().filter(|&(_, &t)| t == timestep).map(|(i, _)| i).collect();
        match hits.as_slice() {
            [] => Err(Error::InvalidArgument {
                name: "timestep".to_string(),
                reason: format!("{timestep} is not one of the scheduler's timesteps"),
            }),
            [only] => Ok(*only),
            [_, second, ..] => Ok(*second),
        }
    }

    /// diffusers' `scale_noise`: `σ·noise + (1 − σ)·sample` with each sample's σ looked up from
    /// its timestep in `timesteps` `[B]` (the flow-matching forward process).
    pub fn scale_noise(&self, sample: &Tensor, timesteps: &Tensor, noise: &Tensor) -> Result<Tensor> {
        let values = Vec::<f32>::try_from(timesteps.f_to_kind(Kind::Float)?.f_flatten(0, -1)?)?;
        let sigmas = values
            .iter()
            .map(|&t| {
                let index = match (self.begin_index, self.step_index) {
                    (None, _) => self.index_for_timestep(t)?,
                    (Some(_), Some(step)) => step,
                    (Some(begin), None) => begin,
                };
                Ok(self.sigmas[index])
            })
            .collect::<Result<Vec<f32>>>()?;
        let mut shape = vec![values.len() as i64];
        shape.resize(sample.dim(), 1);
        let sigma = Tensor::from_slice(&sigmas)
            .f_to_device(sample.device())?
            .f_to_kind(sample.kind())?
            .f_view(shape.as_slice())?;
        Ok(sigma.f_mul(noise)?.f_add(&sigma.f_neg()?.f_add_scalar(1.0)?.f_mul(sample)?)?)
    }

    /// One Euler step from `timestep` (one of [`timesteps`](Self::timesteps)) with the model's
    /// velocity `model_output`; `noise` (drawn by the caller, the sample's shape) is required
    /// exactly with `stochastic_sampling`. Computed in fp32, returned in `model_output`'s dtype.
    pub fn step(
        &mut self,
        model_output: &Tensor,
        timestep: f32,
        sample: &Tensor,
        noise: Option<&Tensor>,
    ) -> Result<Tensor> {
        let index = match self.step_index {
            Some(i) => i,
            None => self.begin_index.map_or_else(|| self.index_for_timestep(timestep), Ok)?,
        };
        if index + 1 >= self.sigmas.len() {
            return Err(Error::InvalidArgument {
                name: "timestep".to_string(),
                reason: format!("the schedule of {} steps is finished", self.timesteps.len()),
            });
        }
        let (sigma, sigma_next) = (self.sigmas[index], self.sigmas[index + 1]);
        let sample = sample.f_to_kind(Kind::Float)?;
        let prev = if self.config.stochastic_sampling {
            let noise = noise.ok_or_else(|| Error::InvalidArgument {
                name: "noise".to_string(),
                reason: "required with stochastic_sampling".to_string(),
            })?;
            let x0 = sample.f_sub(&model_output.f_mul_scalar(f64::from(sigma))?)?;
            x0.f_mul_scalar(f64::from(1.0 - sigma_next))?.f_add(&noise.f_mul_scalar(f64::from(sigma_next))?)?
        } else {
            sample.f_add(&model_output.f_mul_scalar(f64::from(sigma_next - sigma))?)?
        };
        self.step_index = Some(index + 1);
        Ok(prev.f_to_kind(model_output.kind())?)
    }
}

/// diffusers' `_convert_to_karras` over the schedule's ends.
fn karras(sigmas: &[f64]) -> Vec<f64> {
    let (max, min) = (sigmas[0], sigmas[sigmas.len() - 1]);
    let (max_inv, min_inv) = (max.powf(1.0 / KARRAS_RHO), min.powf(1.0 / KARRAS_RHO));
    linspace(0.0, 1.0, sigmas.len()).into_iter().map(|r| (max_inv + r * (min_inv - max_inv)).powf(KARRAS_RHO)).collect()
}

/// diffusers' `_convert_to_exponential` over the schedule's ends.
fn exponential(sigmas: &[f64]) -> Vec<f64> {
    let (max, min) = (sigmas[0], sigmas[sigmas.len() - 1]);
    linspace(max.ln(), min.ln(), sigmas.len()).into_iter().map(f64::exp).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linspace_hits_both_ends() {
        assert_eq!(linspace(1.0, 0.0, 3), vec![1.0, 0.5, 0.0]);
        assert_eq!(linspace(2.0, 9.0, 1), vec![2.0]);
    }

    #[test]
    fn config_errors_name_the_field() {
        let err =
            |json: &str| FlowMatchEulerDiscreteSchedulerConfig::from_json_str(json, "s.json").unwrap_err().to_string();
        assert!(err(r#"{"shift": 0}"#).contains("`shift`"));
        assert!(err(r#"{"use_beta_sigmas": true}"#).contains("use_beta_sigmas"));
        assert!(err(r#"{"use_karras_sigmas": true, "use_exponential_sigmas": true}"#).contains("only one"));
        assert!(err(r#"{"time_shift_type": "cubic"}"#).contains("time_shift_type"));
    }

    #[test]
    fn dynamic_shifting_needs_mu() {
        let config = FlowMatchEulerDiscreteSchedulerConfig { use_dynamic_shifting: true, ..Default::default() };
        let mut s = FlowMatchEulerDiscreteScheduler::new(&config).unwrap();
        assert!(s.set_timesteps(4, None).unwrap_err().to_string().contains("mu"));
        s.set_timesteps(4, Some(0.5)).unwrap();
        assert_eq!(s.sigmas().len(), 5);
    }
}

//! What CogVideoX's two schedulers share, as diffusers' `scheduling_utils.py` and `SchedulerMixin`
//! hold it: the `scheduler_config.json` both read, the noise schedule ᾱ_t (with CogVideoX's SNR
//! shift and the zero-terminal-SNR rescale), the inference timesteps, `add_noise` and
//! `get_velocity` (the training side: noising latents and the v-prediction target), and
//! [`Scheduler`], the one implementation of construction, `set_timesteps` and the accessors that
//! each scheduler adds its `step` to.
//!
//! The schedule is computed with the same tensor ops and dtypes as diffusers (float64 for
//! `scaled_linear`), so ᾱ_t agrees to the last bit; step coefficients are float64 scalars.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor};

use crate::diffusers_config::{self, DiffusersConfig};
use crate::error::{Error, Result};

/// Scheduler class names a CogVideoX `scheduler_config.json` may carry (`_class_name`): the
/// released checkpoints ship the DDIM one and pipelines build either scheduler from it.
pub const CLASS_NAMES: [&str; 2] = ["CogVideoXDDIMScheduler", "CogVideoXDPMScheduler"];

/// Most training timesteps a scheduler config may ask for: every released diffusion scheduler
/// uses 1000; a million keeps the schedule's tables (ᾱ in float64, the DPM solver's timestep
/// list) under 10 MB each, where a file's 1e12 would ask libtorch for terabytes.
pub const MAX_TRAIN_TIMESTEPS: i64 = 1_000_000;

/// A CogVideoX `scheduler_config.json`, field names verbatim; missing fields take diffusers'
/// `__init__` defaults (which are *not* the 5B values: use [`Self::cogvideox_5b`] or the file).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CogVideoXSchedulerConfig {
    /// Training diffusion steps (1000).
    pub num_train_timesteps: i64,
    /// First β of the schedule.
    pub beta_start: f64,
    /// Last β of the schedule.
    pub beta_end: f64,
    /// `linear`, `scaled_linear` (CogVideoX) or `squaredcos_cap_v2`.
    pub beta_schedule: String,
    /// Explicit βs, overriding the three fields above.
    pub trained_betas: Option<Vec<f64>>,
    /// Read but unused by both CogVideoX schedulers' `step` (as in diffusers).
    pub clip_sample: bool,
    /// Whether ᾱ after the last step is 1 (else ᾱ_0).
    pub set_alpha_to_one: bool,
    /// Added to `leading` timesteps.
    pub steps_offset: i64,
    /// What the model predicts: `epsilon`, `sample` or `v_prediction` (CogVideoX).
    pub prediction_type: String,
    /// Read but unused (as in diffusers).
    pub clip_sample_range: f64,
    /// Read but unused (as in diffusers).
    pub sample_max_value: f64,
    /// Inference timestep placement: `linspace`, `leading` or `trailing` (CogVideoX).
    pub timestep_spacing: String,
    /// Rescale ᾱ to zero terminal SNR (Lin et al. 2023, Algorithm 1).
    pub rescale_betas_zero_snr: bool,
    /// CogVideoX's SNR shift: ᾱ ← ᾱ / (s + (1 − s)·ᾱ), i.e. SNR divided by s (1.0 for 5B).
    pub snr_shift_scale: f64,
    /// Every other key: `_class_name`, `_diffusers_version`, … and unknown keys.
    #[serde(flatten)]
    pub extra: BTreeMap<String, serde_json::Value>,
}

impl Default for CogVideoXSchedulerConfig {
    /// diffusers' `CogVideoXDDIMScheduler.__init__` defaults.
    fn default() -> Self {
        Self {
            num_train_timesteps: 1000,
            beta_start: 0.00085,
            beta_end: 0.012,
            beta_schedule: "scaled_linear".to_string(),
            trained_betas: None,
            clip_sample: true,
            set_alpha_to_one: true,
            steps_offset: 0,
            prediction_type: "epsilon".to_string(),
            clip_sample_range: 1.0,
            sample_max_value: 1.0,
            timestep_spacing: "leading".to_string(),
            rescale_betas_zero_snr: false,
            snr_shift_scale: 3.0,
            extra: BTreeMap::new(),
        }
    }
}

/// What the denoiser predicts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PredictionType {
    /// The added noise ε.
    Epsilon,
    /// The clean sample x₀.
    Sample,
    /// The velocity v = √ᾱ·ε − √(1−ᾱ)·x₀ (CogVideoX).
    VPrediction,
}

/// How inference timesteps are spread over the training range.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TimestepSpacing {
    /// Evenly from 0 to T−1, rounded.
    Linspace,
    /// Multiples of T/n from 0, plus `steps_offset`.
    Leading,
    /// Multiples of T/n counted down from T, minus 1 (CogVideoX).
    Trailing,
}

impl DiffusersConfig for CogVideoXSchedulerConfig {
    const KIND: &'static str = "scheduler";
    const CLASS_NAMES: &'static [&'static str] = &CLASS_NAMES;
    const FILE_NAME: &'static str = "scheduler_config.json";

    /// Rejects values the schedulers cannot use, naming the field.
    fn validate_fields(&self, source_name: &str) -> Result<()> {
        let err = diffusers_config::field_error(source_name);
        let t = self.num_train_timesteps;
        // The zero-terminal-SNR rescale divides by √ᾱ_0 − √ᾱ_{T−1}, which one step makes 0.
        let fewest = if self.rescale_betas_zero_snr { 2 } else { 1 };
        if !(fewest..=MAX_TRAIN_TIMESTEPS).contains(&t) {
            return Err(err(
                "num_train_timesteps",
                format!(
                    "must be in {fewest}..={MAX_TRAIN_TIMESTEPS}{}, got {t}",
                    if fewest > 1 { " (rescale_betas_zero_snr needs two)" } else { "" }
                ),
            ));
        }
        // A β outside (0, 1) makes 1 − β, and so ᾱ, zero, negative or above 1.
        let in_unit = |beta: f64| beta > 0.0 && beta < 1.0;
        for (field, beta) in [("beta_start", self.beta_start), ("beta_end", self.beta_end)] {
            if !in_unit(beta) {
                return Err(err(field, format!("must be a number in (0, 1), got {beta}")));
            }
        }
        if self.beta_start > self.beta_end {
            return Err(err(
                "beta_end",
                format!("{} is below beta_start {}: the βs must not decrease", self.beta_end, self.beta_start),
            ));
        }
        match (&self.trained_betas, self.beta_schedule.as_str()) {
            (Some(b), _) if b.len() as i64 != t => {
                return Err(err("trained_betas", format!("has {} values, num_train_timesteps is {t}", b.len())));
            }
            (Some(b), _) => {
                if let Some((i, beta)) = b.iter().enumerate().find(|(_, beta)| !in_unit(**beta)) {
                    return Err(err("trained_betas", format!("value {i} must be in (0, 1), got {beta}")));
                }
            }
            (None, "linear" | "scaled_linear" | "squaredcos_cap_v2") => {}
            (None, other) => {
                return Err(err(
                    "beta_schedule",
                    format!("`{other}` is not linear, scaled_linear or squaredcos_cap_v2"),
                ));
            }
        }
        if !(self.snr_shift_scale.is_finite() && self.snr_shift_scale > 0.0) {
            return Err(err("snr_shift_scale", format!("must be a finite number > 0, got {}", self.snr_shift_scale)));
        }
        if !(0..t).contains(&self.steps_offset) {
            return Err(err(
                "steps_offset",
                format!("must be in 0..{t} (num_train_timesteps), got {}", self.steps_offset),
            ));
        }
        for (field, value) in
            [("clip_sample_range", self.clip_sample_range), ("sample_max_value", self.sample_max_value)]
        {
            if !(value.is_finite() && value > 0.0) {
                return Err(err(field, format!("must be a finite number > 0, got {value}")));
            }
        }
        self.prediction().map_err(|_| {
            err("prediction_type", format!("`{}` is not epsilon, sample or v_prediction", self.prediction_type))
        })?;
        self.spacing().map_err(|_| {
            err("timestep_spacing", format!("`{}` is not linspace, leading or trailing", self.timestep_spacing))
        })?;
        Ok(())
    }

    fn extra(&self) -> &BTreeMap<String, serde_json::Value> {
        &self.extra
    }
}

impl CogVideoXSchedulerConfig {
    /// `THUDM/CogVideoX-5b-I2V` `scheduler/scheduler_config.json`: scaled-linear
    /// βs 0.00085→0.012, 1000 steps, v-prediction, zero terminal SNR, SNR shift 1.0, trailing.
    pub fn cogvideox_5b() -> Self {
        Self {
            clip_sample: false,
            prediction_type: "v_prediction".to_string(),
            timestep_spacing: "trailing".to_string(),
            rescale_betas_zero_snr: true,
            snr_shift_scale: 1.0,
            ..Self::default()
        }
    }

    /// `THUDM/CogVideoX-2b` `scheduler/scheduler_config.json`: as 5B with SNR shift 3.0.
    pub fn cogvideox_2b() -> Self {
        Self { snr_shift_scale: 3.0, ..Self::cogvideox_5b() }
    }

    /// The parsed `prediction_type`.
    pub fn prediction(&self) -> Result<PredictionType> {
        match self.prediction_type.as_str() {
            "epsilon" => Ok(PredictionType::Epsilon),
            "sample" => Ok(PredictionType::Sample),
            "v_prediction" => Ok(PredictionType::VPrediction),
            other => {
                Err(self.field_error("prediction_type", format!("`{other}` is not epsilon, sample or v_prediction")))
            }
        }
    }

    /// The parsed `timestep_spacing`.
    pub fn spacing(&self) -> Result<TimestepSpacing> {
        match self.timestep_spacing.as_str() {
            "linspace" => Ok(TimestepSpacing::Linspace),
            "leading" => Ok(TimestepSpacing::Leading),
            "trailing" => Ok(TimestepSpacing::Trailing),
            other => {
                Err(self.field_error("timestep_spacing", format!("`{other}` is not linspace, leading or trailing")))
            }
        }
    }

    fn field_error(&self, field: &str, reason: String) -> Error {
        Error::InvalidConfig { source_name: "scheduler config".to_string(), field: field.to_string(), reason }
    }
}

/// diffusers' `betas_for_alpha_bar` with the cosine transform (`squaredcos_cap_v2`), float32.
fn cosine_betas(n: i64) -> Tensor {
    const MAX_BETA: f64 = 0.999; // diffusers' default `max_beta`
    let alpha_bar = |t: f64| ((t + 0.008) / 1.008 * std::f64::consts::PI / 2.0).cos().powi(2);
    let betas: Vec<f64> = (0..n)
        .map(|i| {
            let (t1, t2) = (i as f64 / n as f64, (i + 1) as f64 / n as f64);
            (1.0 - alpha_bar(t2) / alpha_bar(t1)).min(MAX_BETA)
        })
        .collect();
    Tensor::from_slice(&betas).to_kind(Kind::Float)
}

/// The noise schedule ᾱ_t of a CogVideoX scheduler and the training-side operations on it.
#[derive(Debug)]
pub struct NoiseSchedule {
    config: CogVideoXSchedulerConfig,
    prediction: PredictionType,
    spacing: TimestepSpacing,
    /// ᾱ_t in the dtype diffusers keeps it in (float64 for scaled_linear), on the CPU.
    alphas_cumprod_tensor: Tensor,
    alphas_cumprod: Vec<f64>,
    final_alpha_cumprod: f64,
}

impl NoiseSchedule {
    /// Builds ᾱ_t as diffusers' scheduler `__init__` does.
    pub fn new(config: &CogVideoXSchedulerConfig) -> Result<Self> {
        config.validate("NoiseSchedule::new")?;
        let n = config.num_train_timesteps;
        let cpu = Device::Cpu;
        let betas = match (&config.trained_betas, config.beta_schedule.as_str()) {
            (Some(b), _) => Tensor::from_slice(b).to_kind(Kind::Float),
            (None, "linear") => Tensor::linspace(config.beta_start, config.beta_end, n, (Kind::Float, cpu)),
            (None, "scaled_linear") => {
                Tensor::linspace(config.beta_start.sqrt(), config.beta_end.sqrt(), n, (Kind::Double, cpu))
                    .pow_tensor_scalar(2)
            }
            (None, _) => cosine_betas(n),
        };
        let alphas = betas.neg() + 1.0;
        let mut ac = alphas.cumprod(0, None::<Kind>);
        let s = config.snr_shift_scale;
        ac = &ac / ((&ac * (1.0 - s)) + s);
        if config.rescale_betas_zero_snr {
            let sqrt = ac.sqrt();
            let first = sqrt.get(0);
            let last = sqrt.get(n - 1);
            let shifted = &sqrt - &last;
            let rescaled = shifted * (&first / (&first - &last));
            ac = rescaled.pow_tensor_scalar(2);
        }
        let alphas_cumprod: Vec<f64> = Vec::<f64>::try_from(ac.to_kind(Kind::Double).contiguous())?;
        let final_alpha_cumprod = if config.set_alpha_to_one { 1.0 } else { alphas_cumprod[0] };
        Ok(Self {
            config: config.clone(),
            prediction: config.prediction()?,
            spacing: config.spacing()?,
            alphas_cumprod_tensor: ac,
            alphas_cumprod,
            final_alpha_cumprod,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &CogVideoXSchedulerConfig {
        &self.config
    }

    /// The parsed prediction type.
    pub fn prediction(&self) -> PredictionType {
        self.prediction
    }

    /// ᾱ_t for t = 0..num_train_timesteps (as float64).
    pub fn alphas_cumprod(&self) -> &[f64] {
        &self.alphas_cumprod
    }

    /// ᾱ at `timestep`, or the final ᾱ (1 with `set_alpha_to_one`) for a negative one.
    pub fn alpha_cumprod_at(&self, timestep: i64) -> Result<f64> {
        if timestep < 0 {
            return Ok(self.final_alpha_cumprod);
        }
        self.alphas_cumprod.get(timestep as usize).copied().ok_or_else(|| Error::InvalidArgument {
            name: "timestep".to_string(),
            reason: format!("{timestep} is outside 0..{}", self.config.num_train_timesteps),
        })
    }

    /// Inference timesteps for `num_inference_steps` (diffusers' `set_timesteps`), descending.
    pub fn timesteps(&self, num_inference_steps: usize) -> Result<Vec<i64>> {
        let t = self.config.num_train_timesteps;
        let n = num_inference_steps as i64;
        if n == 0 || n > t {
            return Err(Error::InvalidArgument {
                name: "num_inference_steps".to_string(),
                reason: format!("{n} must be in 1..={t} (num_train_timesteps)"),
            });
        }
        Ok(match self.spacing {
            TimestepSpacing::Linspace => {
                // np.linspace(0, T-1, n).round(), reversed; numpy rounds half to even and puts
                // the endpoint exactly (a single step gives [0]).
                let step = if n > 1 { (t - 1) as f64 / (n - 1) as f64 } else { 0.0 };
                (0..n)
                    .rev()
                    .map(|i| {
                        if n > 1 && i == n - 1 { (t - 1) as f64 } else { i as f64 * step }.round_ties_even() as i64
                    })
                    .collect()
            }
            TimestepSpacing::Leading => {
                let ratio = t / n;
                (0..n).rev().map(|i| i * ratio + self.config.steps_offset).collect()
            }
            TimestepSpacing::Trailing => {
                // np.round(np.arange(T, 0, -T/n)) - 1; numpy's arange has ceil(T / (T/n)) values.
                let ratio = t as f64 / n as f64;
                let len = (t as f64 / ratio).ceil() as i64;
                (0..len).map(|k| (t as f64 - k as f64 * ratio).round_ties_even() as i64 - 1).collect()
            }
        })
    }

    /// √ᾱ_t and √(1 − ᾱ_t) for each timestep, in `like`'s dtype (diffusers casts ᾱ first), shaped
    /// to broadcast over `like`'s trailing dimensions.
    fn coefficients(&self, like: &Tensor, timesteps: &Tensor, name: &str) -> Result<(Tensor, Tensor)> {
        let batch = like.size().first().copied().unwrap_or(1);
        let count = timesteps.numel() as i64;
        if !(count == batch || count == 1) || timesteps.kind() != Kind::Int64 && timesteps.kind() != Kind::Int {
            return Err(Error::Shape {
                tensor: format!("{name}.timesteps"),
                expected: format!("[{batch}] integer timesteps (one per sample)"),
                actual: timesteps.size(),
            });
        }
        let t = timesteps.f_to_kind(Kind::Int64)?.f_flatten(0, -1)?.f_to_device(Device::Cpu)?;
        let (lo, hi) = (t.f_min()?.int64_value(&[]), t.f_max()?.int64_value(&[]));
        if lo < 0 || hi >= self.config.num_train_timesteps {
            return Err(Error::InvalidArgument {
                name: format!("{name}.timesteps"),
                reason: format!("values {lo}..={hi} outside 0..{}", self.config.num_train_timesteps),
            });
        }
        let ac = self.alphas_cumprod_tensor.f_to_kind(like.kind())?.f_index_select(0, &t)?;
        let mut shape = vec![count];
        shape.extend(std::iter::repeat_n(1, like.dim().saturating_sub(1)));
        let sqrt_alpha = ac.f_sqrt()?.f_reshape(&shape)?.f_to_device(like.device())?;
        let sqrt_one_minus = ac.f_neg()?.f_add_scalar(1.0)?.f_sqrt()?.f_reshape(&shape)?.f_to_device(like.device())?;
        Ok((sqrt_alpha, sqrt_one_minus))
    }

    /// Forward diffusion `√ᾱ_t·x₀ + √(1−ᾱ_t)·ε` (diffusers' `add_noise`); `timesteps` `[B]`.
    pub fn add_noise(&self, original_samples: &Tensor, noise: &Tensor, timesteps: &Tensor) -> Result<Tensor> {
        same_shape(original_samples, noise, "add_noise.noise")?;
        let (a, b) = self.coefficients(original_samples, timesteps, "add_noise")?;
        Ok(a.f_mul(original_samples)?.f_add(&b.f_mul(noise)?)?)
    }

    /// The v-prediction target `√ᾱ_t·ε − √(1−ᾱ_t)·x₀` (diffusers' `get_velocity`).
    pub fn get_velocity(&self, sample: &Tensor, noise: &Tensor, timesteps: &Tensor) -> Result<Tensor> {
        same_shape(sample, noise, "get_velocity.noise")?;
        let (a, b) = self.coefficients(sample, timesteps, "get_velocity")?;
        Ok(a.f_mul(noise)?.f_sub(&b.f_mul(sample)?)?)
    }

    /// x̂₀ from the model output at `timestep` (ᾱ = `alpha_prod_t`), per the prediction type.
    pub(crate) fn pred_original_sample(
        &self,
        model_output: &Tensor,
        sample: &Tensor,
        alpha_prod_t: f64,
    ) -> Result<Tensor> {
        let beta_prod_t = 1.0 - alpha_prod_t;
        Ok(match self.prediction {
            PredictionType::Epsilon => {
                sample.f_sub(&model_output.f_mul_scalar(beta_prod_t.sqrt())?)?.f_div_scalar(alpha_prod_t.sqrt())?
            }
            PredictionType::Sample => model_output.shallow_clone(),
            PredictionType::VPrediction => {
                sample.f_mul_scalar(alpha_prod_t.sqrt())?.f_sub(&model_output.f_mul_scalar(beta_prod_t.sqrt())?)?
            }
        })
    }
}

pub(crate) fn same_shape(reference: &Tensor, other: &Tensor, name: &str) -> Result<()> {
    if reference.size() != other.size() {
        return Err(Error::Shape {
            tensor: name.to_string(),
            expected: format!("{:?} (the sample's shape)", reference.size()),
            actual: other.size(),
        });
    }
    Ok(())
}

/// The result of one denoising step.
#[derive(Debug)]
pub struct SchedulerStepOutput {
    /// x_{t−1}, the next model input.
    pub prev_sample: Tensor,
    /// x̂₀ predicted at this step (the DPM scheduler needs it back on the next step).
    pub pred_original_sample: Tensor,
}

/// The state every scheduler keeps: the schedule and the timesteps chosen by `set_timesteps`.
#[derive(Debug)]
pub struct SchedulerState {
    schedule: NoiseSchedule,
    num_inference_steps: Option<usize>,
    timesteps: Vec<i64>,
}

impl SchedulerState {
    /// The state for `config`, before `set_timesteps` (every training timestep, descending).
    pub fn new(config: &CogVideoXSchedulerConfig) -> Result<Self> {
        let schedule = NoiseSchedule::new(config)?;
        let timesteps = (0..config.num_train_timesteps).rev().collect();
        Ok(Self { schedule, num_inference_steps: None, timesteps })
    }

    /// The distance between two inference timesteps, T / n; an error naming `scheduler` before
    /// `set_timesteps`.
    pub(crate) fn step_ratio(&self, scheduler: &str) -> Result<i64> {
        let n = self.num_inference_steps.ok_or_else(|| Error::InvalidArgument {
            name: "num_inference_steps".to_string(),
            reason: format!("{scheduler}: call set_timesteps before step"),
        })?;
        Ok(self.schedule.config.num_train_timesteps / n as i64)
    }
}

/// A CogVideoX scheduler: construction, `set_timesteps`, the accessors and the training-side
/// operations, written once over its [`SchedulerState`] (diffusers' `SchedulerMixin`); each
/// scheduler adds its own `step`.
pub trait Scheduler: Sized {
    /// Wraps a state (the scheduler's only field besides what its `step` needs).
    fn from_state(state: SchedulerState) -> Self;

    /// Its state.
    fn state(&self) -> &SchedulerState;

    /// Its state, to change.
    fn state_mut(&mut self) -> &mut SchedulerState;

    /// A scheduler for `config` (call [`Self::set_timesteps`] before stepping).
    fn new(config: &CogVideoXSchedulerConfig) -> Result<Self> {
        Ok(Self::from_state(SchedulerState::new(config)?))
    }

    /// The noise schedule (ᾱ, `add_noise`, `get_velocity`).
    fn schedule(&self) -> &NoiseSchedule {
        &self.state().schedule
    }

    /// Chooses `num_inference_steps` timesteps per the configured spacing (50 for CogVideoX).
    fn set_timesteps(&mut self, num_inference_steps: usize) -> Result<()> {
        let state = self.state_mut();
        state.timesteps = state.schedule.timesteps(num_inference_steps)?;
        state.num_inference_steps = Some(num_inference_steps);
        Ok(())
    }

    /// The current timesteps, descending.
    fn timesteps(&self) -> &[i64] {
        &self.state().timesteps
    }

    /// See [`NoiseSchedule::add_noise`].
    fn add_noise(&self, original_samples: &Tensor, noise: &Tensor, timesteps: &Tensor) -> Result<Tensor> {
        self.schedule().add_noise(original_samples, noise, timesteps)
    }

    /// See [`NoiseSchedule::get_velocity`].
    fn get_velocity(&self, sample: &Tensor, noise: &Tensor, timesteps: &Tensor) -> Result<Tensor> {
        self.schedule().get_velocity(sample, noise, timesteps)
    }
}

/// A sampling run's step count (flag `flag`): 1 to the scheduler's `num_train_timesteps`
/// training timesteps, the range every scheduler's `set_timesteps` can spread.
pub fn check_inference_steps(flag: &str, steps: usize, num_train_timesteps: u64) -> Result<()> {
    if steps == 0 || steps as u64 > num_train_timesteps {
        return Err(Error::InvalidArgument {
            name: flag.to_string(),
            reason: format!(
                "{steps} denoising steps: must be in 1..={num_train_timesteps} (the scheduler's training timesteps)"
            ),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trailing_timesteps_of_the_5b_sampler() {
        let s = NoiseSchedule::new(&CogVideoXSchedulerConfig::cogvideox_5b()).unwrap();
        let t = s.timesteps(50).unwrap();
        assert_eq!(t.len(), 50);
        assert_eq!((t[0], t[1], t[49]), (999, 979, 19));
    }

    #[test]
    fn zero_terminal_snr() {
        let s = NoiseSchedule::new(&CogVideoXSchedulerConfig::cogvideox_5b()).unwrap();
        let ac = s.alphas_cumprod();
        assert_eq!(ac[999], 0.0);
        assert!(ac.windows(2).all(|w| w[1] < w[0]));
        // The rescale keeps ᾱ_0 = 1 − β_0 = 1 − 0.00085.
        assert!((ac[0] - (1.0 - 0.00085)).abs() < 1e-12);
    }

    #[test]
    fn config_errors_name_the_field() {
        let e = CogVideoXSchedulerConfig::from_json_str(r#"{"prediction_type": "x"}"#, "s.json").unwrap_err();
        assert!(e.to_string().contains("prediction_type"), "{e}");
        let c =
            CogVideoXSchedulerConfig::from_json_str(r#"{"foo": 1, "_class_name": "CogVideoXDDIMScheduler"}"#, "s.json")
                .unwrap();
        assert_eq!(c.unknown_keys(), vec!["foo"]);
    }
}

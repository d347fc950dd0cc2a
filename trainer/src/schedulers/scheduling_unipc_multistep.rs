//! The UniPC multistep sampler with flow-matching sigmas: diffusers' `UniPCMultistepScheduler`
//! (`diffusers/schedulers/scheduling_unipc_multistep.py`) as Wan's pipelines ship it
//! (`use_flow_sigmas`, `prediction_type = "flow_prediction"`, `flow_shift` 3 for 480p and 5 for
//! 720p, second order, B(h) = e^h − 1).
//!
//! UniPC (Zhao et al., 2023) is a predictor-corrector solver of the diffusion ODE in
//! λ = log(α/σ): each step first corrects the sample it was given with the model output just
//! computed there (UniC), then predicts the next sample from the last `order` outputs (UniP). With
//! flow sigmas, α = 1 − σ. The σ schedule is `linspace(1, 1/N)` shifted as
//! `scheduling_flow_match_euler_discrete` shifts, built in fp64, stored in fp32; the coefficients
//! are computed in fp32 as diffusers computes them on 0-dim tensors. The variance-preserving
//! (non-flow) schedules, Karras/exponential/beta respacing, thresholding and `solver_p` are not
//! ported: no Wan configuration uses them, and a config asking for them is refused, naming the
//! field.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor};

use crate::diffusers_config::{self, DiffusersConfig};
use crate::error::{Error, Result};
use crate::schedulers::scheduling_flow_match_euler_discrete::{
    FlowShift, MAX_TRAIN_TIMESTEPS, TimeShiftType, check_steps, linspace,
};

/// The class name of this scheduler's `scheduler_config.json`.
pub const CLASS_NAME: &str = "UniPCMultistepScheduler";
/// How far diffusers moves a first sigma of 1 down, so `log σ − log(1 − σ)` stays finite.
const FIRST_SIGMA_EPS: f64 = 1e-6;
/// Highest solver order accepted (diffusers allows any; UniPC's paper uses up to 3, Wan 2).
pub const MAX_SOLVER_ORDER: i64 = 8;

/// What the model predicts (diffusers' `prediction_type`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PredictionType {
    /// The noise ε.
    Epsilon,
    /// The clean sample x₀.
    Sample,
    /// v = α·ε − σ·x₀.
    VPrediction,
    /// The flow velocity ε − x₀ (Wan).
    FlowPrediction,
}

/// The B(h) of UniPC's update (diffusers' `solver_type`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SolverType {
    /// B(h) = h.
    Bh1,
    /// B(h) = e^h − 1.
    Bh2,
}

/// The last sigma of the schedule (diffusers' `final_sigmas_type`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FinalSigmasType {
    /// 0: the last step lands on the clean sample.
    Zero,
    /// The schedule's last sigma repeated.
    SigmaMin,
}

/// The scheduler's `scheduler_config.json`, field names verbatim, defaults of diffusers'
/// `__init__`; other keys are kept in `extra` and reported. Fields that only the
/// variance-preserving schedule reads (`beta_*`, `trained_betas`, `timestep_spacing`, …) are kept
/// so a file round-trips.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct UniPCMultistepSchedulerConfig {
    /// Training timesteps.
    pub num_train_timesteps: i64,
    /// Variance-preserving schedule only.
    pub beta_start: f64,
    /// Variance-preserving schedule only.
    pub beta_end: f64,
    /// Variance-preserving schedule only.
    pub beta_schedule: String,
    /// Variance-preserving schedule only.
    pub trained_betas: Option<Vec<f64>>,
    /// Model outputs the predictor uses (Wan: 2).
    pub solver_order: i64,
    /// What the model predicts (Wan: `flow_prediction`).
    pub prediction_type: PredictionType,
    /// Dynamic thresholding of x₀ (not supported).
    pub thresholding: bool,
    /// Dynamic thresholding only.
    pub dynamic_thresholding_ratio: f64,
    /// Dynamic thresholding only.
    pub sample_max_value: f64,
    /// Solve for x₀ (data prediction) rather than ε.
    pub predict_x0: bool,
    /// B(h) of the update.
    pub solver_type: SolverType,
    /// Lower the order on the last steps.
    pub lower_order_final: bool,
    /// Step indices whose corrector is skipped.
    pub disable_corrector: Vec<i64>,
    /// Another scheduler as predictor (not supported: must be null).
    pub solver_p: Option<serde_json::Value>,
    /// Karras respacing (not supported).
    pub use_karras_sigmas: bool,
    /// Exponential respacing (not supported).
    pub use_exponential_sigmas: bool,
    /// Beta respacing (not supported).
    pub use_beta_sigmas: bool,
    /// Flow-matching sigmas, α = 1 − σ (required: Wan's).
    pub use_flow_sigmas: bool,
    /// The static shift of the flow sigmas.
    pub flow_shift: f64,
    /// Variance-preserving schedule only.
    pub timestep_spacing: String,
    /// Variance-preserving schedule only.
    pub steps_offset: i64,
    /// The last sigma.
    pub final_sigmas_type: FinalSigmasType,
    /// Variance-preserving schedule only.
    pub rescale_betas_zero_snr: bool,
    /// Shift by `mu` given to `set_timesteps` instead of `flow_shift`.
    pub use_dynamic_shifting: bool,
    /// The dynamic shift's form.
    pub time_shift_type: TimeShiftType,
    /// Respacing only.
    pub sigma_min: Option<f64>,
    /// Respacing only.
    pub sigma_max: Option<f64>,
    /// Stretch the shifted schedule to end at this sigma; null or 0 for no stretch.
    pub shift_terminal: Option<f64>,
    /// Every other key: `_class_name`, `_diffusers_version`, … and unknown keys.
    #[serde(flatten)]
    pub extra: BTreeMap<String, serde_json::Value>,
}

impl Default for UniPCMultistepSchedulerConfig {
    fn default() -> Self {
        Self {
            num_train_timesteps: 1000,
            beta_start: 0.0001,
            beta_end: 0.02,
            beta_schedule: "linear".to_string(),
            trained_betas: None,
            solver_order: 2,
            prediction_type: PredictionType::Epsilon,
            thresholding: false,
            dynamic_thresholding_ratio: 0.995,
            sample_max_value: 1.0,
            predict_x0: true,
            solver_type: SolverType::Bh2,
            lower_order_final: true,
            disable_corrector: Vec::new(),
            solver_p: None,
            use_karras_sigmas: false,
            use_exponential_sigmas: false,
            use_beta_sigmas: false,
            use_flow_sigmas: false,
            flow_shift: 1.0,
            timestep_spacing: "linspace".to_string(),
            steps_offset: 0,
            final_sigmas_type: FinalSigmasType::Zero,
            rescale_betas_zero_snr: false,
            use_dynamic_shifting: false,
            time_shift_type: TimeShiftType::Exponential,
            sigma_min: None,
            sigma_max: None,
            shift_terminal: None,
            extra: BTreeMap::new(),
        }
    }
}

impl UniPCMultistepSchedulerConfig {
    /// The `scheduler/scheduler_config.json` of `Wan-AI/Wan2.1-T2V-1.3B-Diffusers` (and the other
    /// Wan2.1/2.2 480p checkpoints): flow sigmas shifted by 3, flow prediction, second order bh2.
    pub fn wan_480p() -> Self {
        Self {
            prediction_type: PredictionType::FlowPrediction,
            use_flow_sigmas: true,
            flow_shift: 3.0,
            ..Self::default()
        }
    }

    /// [`wan_480p`](Self::wan_480p) with the 720p checkpoints' `flow_shift` of 5.
    pub fn wan_720p() -> Self {
        Self { flow_shift: 5.0, ..Self::wan_480p() }
    }
}

impl DiffusersConfig for UniPCMultistepSchedulerConfig {
    const KIND: &'static str = "scheduler";
    const CLASS_NAMES: &'static [&'static str] = &[CLASS_NAME];
    const FILE_NAME: &'static str = "scheduler_config.json";

    fn validate_fields(&self, source_name: &str) -> Result<()> {
        let err = diffusers_config::field_error(source_name);
        let unsupported =
            |field: &str, what: &str| err(field, format!("{what} is not supported (no Wan configuration uses it)"));
        if !(1..=MAX_TRAIN_TIMESTEPS).contains(&self.num_train_timesteps) {
            return Err(err(
                "num_train_timesteps",
                format!("must be in [1, {MAX_TRAIN_TIMESTEPS}], got {}", self.num_train_timesteps),
            ));
        }
        if !(1..=MAX_SOLVER_ORDER).contains(&self.solver_order) {
            return Err(err("solver_order", format!("must be in [1, {MAX_SOLVER_ORDER}], got {}", self.solver_order)));
        }
        if !self.use_flow_sigmas {
            return Err(unsupported("use_flow_sigmas", "false (the variance-preserving schedule)"));
        }
        if !(self.flow_shift > 0.0 && self.flow_shift.is_finite()) {
            return Err(err("flow_shift", format!("must be positive and finite, got {}", self.flow_shift)));
        }
        if let Some(t) = self.shift_terminal.filter(|&t| !(0.0..1.0).contains(&t)) {
            return Err(err("shift_terminal", format!("must be in [0, 1) or null, got {t}")));
        }
        for (field, set) in [
            ("use_karras_sigmas", self.use_karras_sigmas),
            ("use_exponential_sigmas", self.use_exponential_sigmas),
            ("use_beta_sigmas", self.use_beta_sigmas),
            ("thresholding", self.thresholding),
        ] {
            if set {
                return Err(unsupported(field, "true"));
            }
        }
        if self.solver_p.as_ref().is_some_and(|v| !v.is_null()) {
            return Err(unsupported("solver_p", "a separate predictor scheduler"));
        }
        if self.prediction_type == PredictionType::FlowPrediction && !self.predict_x0 {
            return Err(err(
                "predict_x0",
                "must be true with prediction_type flow_prediction (diffusers refuses the pair too)".to_string(),
            ));
        }
        if !["linspace", "leading", "trailing"].contains(&self.timestep_spacing.as_str()) {
            return Err(err(
                "timestep_spacing",
                format!("`{}` is not one of linspace, leading, trailing", self.timestep_spacing),
            ));
        }
        Ok(())
    }

    fn extra(&self) -> &BTreeMap<String, serde_json::Value> {
        &self.extra
    }
}

/// diffusers' `UniPCMultistepScheduler` on flow sigmas.
#[derive(Debug)]
pub struct UniPCMultistepScheduler {
    config: UniPCMultistepSchedulerConfig,
    timesteps: Vec<i64>,
    /// One more than `timesteps`: the final sigma last.
    sigmas: Vec<f32>,
    /// The last `solver_order` converted model outputs, oldest first.
    model_outputs: Vec<Option<Tensor>>,
    lower_order_nums: usize,
    this_order: usize,
    last_sample: Option<Tensor>,
    step_index: Option<usize>,
    begin_index: Option<usize>,
}

impl UniPCMultistepScheduler {
    /// A scheduler for `config` (call [`set_timesteps`](Self::set_timesteps) before stepping).
    pub fn new(config: &UniPCMultistepSchedulerConfig) -> Result<Self> {
        config.validate("scheduler config")?;
        Ok(Self {
            config: config.clone(),
            timesteps: Vec::new(),
            sigmas: Vec::new(),
            model_outputs: (0..config.solver_order).map(|_| None).collect(),
            lower_order_nums: 0,
            this_order: 0,
            last_sample: None,
            step_index: None,
            begin_index: None,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &UniPCMultistepSchedulerConfig {
        &self.config
    }

    /// Chooses `num_inference_steps` flow sigmas (`linspace(1, 1/N)`, shifted) and resets the
    /// solver's history; `mu` is the dynamic shift, required exactly with `use_dynamic_shifting`.
    pub fn set_timesteps(&mut self, num_inference_steps: usize, mu: Option<f64>) -> Result<()> {
        let c = &self.config;
        check_steps(num_inference_steps)?;
        let n = c.num_train_timesteps as f64;
        let mut sigmas = linspace(1.0, 1.0 / n, num_inference_steps + 1);
        sigmas.pop();
        let shift = FlowShift {
            dynamic: c.use_dynamic_shifting,
            time_shift_type: c.time_shift_type,
            shift: c.flow_shift,
            shift_terminal: c.shift_terminal,
        };
        shift.apply(&mut sigmas, mu)?;
        if (sigmas[0] - 1.0).abs() < FIRST_SIGMA_EPS {
            sigmas[0] -= FIRST_SIGMA_EPS;
        }
        // fp64 → int64 truncates, as torch's `.to(torch.int64)` does.
        self.timesteps = sigmas.iter().map(|s| (s * n) as i64).collect();
        let last = match c.final_sigmas_type {
            FinalSigmasType::Zero => 0.0,
            FinalSigmasType::SigmaMin => *sigmas.last().expect("at least one step"),
        };
        sigmas.push(last);
        self.sigmas = sigmas.into_iter().map(|s| s as f32).collect();
        self.model_outputs = (0..c.solver_order).map(|_| None).collect();
        self.lower_order_nums = 0;
        self.last_sample = None;
        self.step_index = None;
        self.begin_index = None;
        Ok(())
    }

    /// The timesteps the model is called with, descending.
    pub fn timesteps(&self) -> &[i64] {
        &self.timesteps
    }

    /// The sigmas, one more than the timesteps.
    pub fn sigmas(&self) -> &[f32] {
        &self.sigmas
    }

    /// Starts stepping at index `begin_index` (pipelines that start mid-schedule).
    pub fn set_begin_index(&mut self, begin_index: usize) {
        self.begin_index = Some(begin_index);
    }

    /// diffusers' `index_for_timestep`: the position of `timestep` in the schedule (the second
    /// if it occurs twice; the last step if it does not occur).
    pub fn index_for_timestep(&self, timestep: i64) -> usize {
        let hits: Vec<usize> =
            self.timesteps.iter().enumerate().filter(|&(_, &t)| t == timestep).map(|(i, _)| i).collect();
        match hits.as_slice() {
            [] => self.timesteps.len().saturating_sub(1),
            [only] => *only,
            [_, second, ..] => *second,
        }
    }

    /// diffusers' `add_noise` on flow sigmas: `(1 − σ)·x₀ + σ·noise`, σ looked up per sample from
    /// `timesteps` `[B]`.
    pub fn add_noise(&self, original_samples: &Tensor, noise: &Tensor, timesteps: &Tensor) -> Result<Tensor> {
        let values = Vec::<i64>::try_from(timesteps.f_to_kind(Kind::Int64)?.f_flatten(0, -1)?)?;
        let sigmas: Vec<f32> = values
            .iter()
            .map(|&t| {
                let index = match (self.begin_index, self.step_index) {
                    (None, _) => self.index_for_timestep(t),
                    (Some(_), Some(step)) => step,
                    (Some(begin), None) => begin,
                };
                self.sigmas.get(index).copied().ok_or_else(|| Error::InvalidArgument {
                    name: "timesteps".to_string(),
                    reason: "set_timesteps must be called first".to_string(),
                })
            })
            .collect::<Result<_>>()?;
        let mut shape = vec![values.len() as i64];
        shape.resize(original_samples.dim(), 1);
        let kind = original_samples.kind();
        let sigma = Tensor::from_slice(&sigmas)
            .f_to_device(original_samples.device())?
            .f_to_kind(kind)?
            .f_view(shape.as_slice())?;
        let alpha = sigma.f_neg()?.f_add_scalar(1.0)?;
        Ok(alpha.f_mul(original_samples)?.f_add(&sigma.f_mul(noise)?)?)
    }

    /// One UniPC step from `timestep` (one of [`timesteps`](Self::timesteps)): corrects `sample`
    /// with `model_output` (after the first step), then predicts the sample at the next sigma.
    pub fn step(&mut self, model_output: &Tensor, timestep: i64, sample: &Tensor) -> Result<Tensor> {
        if self.sigmas.is_empty() {
            return Err(Error::InvalidArgument {
                name: "timestep".to_string(),
                reason: "set_timesteps must be called before step".to_string(),
            });
        }
        let index = match self.step_index {
            Some(i) => i,
            None => self.begin_index.unwrap_or_else(|| self.index_for_timestep(timestep)),
        };
        if index + 1 >= self.sigmas.len() {
            return Err(Error::InvalidArgument {
                name: "timestep".to_string(),
                reason: format!("the schedule of {} steps is finished", self.timesteps.len()),
            });
        }
        self.step_index = Some(index);
        let disabled = index > 0 && self.config.disable_corrector.contains(&(index as i64 - 1));
        let converted = self.convert_model_output(model_output, sample, index)?;
        let sample = match self.last_sample.take() {
            Some(last) if index > 0 && !disabled => self.corrector(&converted, &last, sample, index)?,
            _ => sample.shallow_clone(),
        };
        self.model_outputs.rotate_left(1);
        *self.model_outputs.last_mut().expect("solver_order ≥ 1") = Some(converted);

        let order = self.config.solver_order as usize;
        let this_order = if self.config.lower_order_final { order.min(self.timesteps.len() - index) } else { order };
        self.this_order = this_order.min(self.lower_order_nums + 1);
        let prev = self.predictor(&sample, index)?;
        self.last_sample = Some(sample);
        if self.lower_order_nums < order {
            self.lower_order_nums += 1;
        }
        self.step_index = Some(index + 1);
        Ok(prev)
    }

    /// (α, σ) of a flow sigma, in fp32.
    fn alpha_sigma(&self, index: usize) -> (f32, f32) {
        let sigma = self.sigmas[index];
        (1.0 - sigma, sigma)
    }

    /// λ = log α − log σ at a sigma index, in fp32.
    fn lambda(&self, index: usize) -> f32 {
        let (alpha, sigma) = self.alpha_sigma(index);
        alpha.ln() - sigma.ln()
    }

    /// diffusers' `convert_model_output`: x₀ (data prediction) or ε from the model's output.
    fn convert_model_output(&self, model_output: &Tensor, sample: &Tensor, index: usize) -> Result<Tensor> {
        let (alpha, sigma) = self.alpha_sigma(index);
        let (alpha, sigma) = (f64::from(alpha), f64::from(sigma));
        let out = match (self.config.predict_x0, self.config.prediction_type) {
            (true, PredictionType::Epsilon) => sample.f_sub(&model_output.f_mul_scalar(sigma)?)?.f_div_scalar(alpha)?,
            (true, PredictionType::Sample) | (false, PredictionType::Epsilon) => model_output.shallow_clone(),
            (true, PredictionType::VPrediction) => {
                sample.f_mul_scalar(alpha)?.f_sub(&model_output.f_mul_scalar(sigma)?)?
            }
            (true, PredictionType::FlowPrediction) => sample.f_sub(&model_output.f_mul_scalar(sigma)?)?,
            (false, PredictionType::Sample) => sample.f_sub(&model_output.f_mul_scalar(alpha)?)?.f_div_scalar(sigma)?,
            (false, PredictionType::VPrediction) => {
                model_output.f_mul_scalar(alpha)?.f_add(&sample.f_mul_scalar(sigma)?)?
            }
            (false, PredictionType::FlowPrediction) => unreachable!("refused by the config check"),
        };
        Ok(out)
    }

    /// The coefficients shared by UniP and UniC for a step from sigma index `s0` to `t` using
    /// the earlier outputs at `earlier` (most recent first): the ratios r_k, the right-hand sides
    /// b of the order conditions, φ₁ and B(h), all fp32 as diffusers computes them.
    fn coefficients(&self, t: usize, s0: usize, earlier: &[usize], order: usize) -> Coefficients {
        let lambda_s0 = self.lambda(s0);
        let h = self.lambda(t) - lambda_s0;
        let rks: Vec<f32> = earlier.iter().map(|&si| (self.lambda(si) - lambda_s0) / h).chain([1.0]).collect();
        let hh = if self.config.predict_x0 { -h } else { h };
        let h_phi_1 = hh.exp_m1();
        let b_h = match self.config.solver_type {
            SolverType::Bh1 => hh,
            SolverType::Bh2 => hh.exp_m1(),
        };
        let mut h_phi_k = h_phi_1 / hh - 1.0;
        let mut factorial = 1u64;
        let mut b = Vec::with_capacity(order);
        for i in 1..=order as u64 {
            b.push(h_phi_k * factorial as f32 / b_h);
            factorial *= i + 1;
            h_phi_k = h_phi_k / hh - (1.0 / factorial as f64) as f32;
        }
        Coefficients { rks, b, h_phi_1, b_h }
    }

    /// The sample's update `x ↦ c_x·x − c_m·m0`, before the residual term, and the residual's
    /// factor, for a step from `s0` to `t`.
    fn base_update(&self, t: usize, s0: usize, c: &Coefficients) -> (f32, f32, f32) {
        let (alpha_t, sigma_t) = self.alpha_sigma(t);
        let (alpha_s0, sigma_s0) = self.alpha_sigma(s0);
        if self.config.predict_x0 {
            (sigma_t / sigma_s0, alpha_t * c.h_phi_1, alpha_t * c.b_h)
        } else {
            (alpha_t / alpha_s0, sigma_t * c.h_phi_1, sigma_t * c.b_h)
        }
    }

    /// UniP (diffusers' `multistep_uni_p_bh_update`) from the current index to the next.
    fn predictor(&self, sample: &Tensor, index: usize) -> Result<Tensor> {
        let order = self.this_order;
        let outputs = self.history();
        let m0 = outputs[0];
        let earlier: Vec<usize> = (1..order).map(|i| index - i).collect();
        let c = self.coefficients(index + 1, index, &earlier, order);
        let (cx, cm, cr) = self.base_update(index + 1, index, &c);
        let mut x_t = sample.f_mul_scalar(f64::from(cx))?.f_sub(&m0.f_mul_scalar(f64::from(cm))?)?;
        if order > 1 {
            let rhos: Vec<f32> = if order == 2 {
                vec![0.5]
            } else {
                let k = order - 1;
                let r: Vec<Vec<f64>> =
                    (0..k).map(|i| (0..k).map(|j| f64::from(c.rks[j].powi(i as i32))).collect()).collect();
                solve(r, c.b[..k].iter().map(|&v| f64::from(v)).collect()).into_iter().map(|v| v as f32).collect()
            };
            let residual = self.residual(&rhos, &c.rks, &outputs)?;
            // Without earlier outputs diffusers multiplies a zero residual by B(h), which is −∞
            // on a bh1 step to σ = 0 (NaN); there is no residual term to add, so none is.
            x_t = x_t.f_sub(&residual.f_mul_scalar(f64::from(cr))?)?;
        }
        Ok(x_t.f_to_kind(sample.kind())?)
    }

    /// UniC (diffusers' `multistep_uni_c_bh_update`): corrects `this_sample`, predicted from
    /// `last_sample` at the previous index, with `this_output` computed at `index`.
    fn corrector(
        &self,
        this_output: &Tensor,
        last_sample: &Tensor,
        this_sample: &Tensor,
        index: usize,
    ) -> Result<Tensor> {
        let order = self.this_order;
        let outputs = self.history();
        let m0 = outputs[0];
        let earlier: Vec<usize> = (1..order).map(|i| index - (i + 1)).collect();
        let c = self.coefficients(index, index - 1, &earlier, order);
        let (cx, cm, cr) = self.base_update(index, index - 1, &c);
        let rhos: Vec<f32> = if order == 1 {
            vec![0.5]
        } else {
            let r: Vec<Vec<f64>> =
                (0..order).map(|i| (0..order).map(|j| f64::from(c.rks[j].powi(i as i32))).collect()).collect();
            solve(r, c.b.iter().map(|&v| f64::from(v)).collect()).into_iter().map(|v| v as f32).collect()
        };
        let x_t = last_sample.f_mul_scalar(f64::from(cx))?.f_sub(&m0.f_mul_scalar(f64::from(cm))?)?;
        let d1_t = this_output.f_sub(m0)?;
        let (last_rho, earlier_rhos) = rhos.split_last().expect("order ≥ 1");
        let mut correction = d1_t.f_mul_scalar(f64::from(*last_rho))?;
        if order > 1 {
            correction = self.residual(earlier_rhos, &c.rks, &outputs)?.f_add(&correction)?;
        }
        Ok(x_t.f_sub(&correction.f_mul_scalar(f64::from(cr))?)?.f_to_kind(this_sample.kind())?)
    }

    /// Σ_k ρ_k · (m_k − m0) / r_k over the earlier outputs.
    fn residual(&self, rhos: &[f32], rks: &[f32], outputs: &[&Tensor]) -> Result<Tensor> {
        let m0 = outputs[0];
        let mut sum: Option<Tensor> = None;
        for (k, rho) in rhos.iter().enumerate() {
            let d1 = outputs[k + 1].f_sub(m0)?.f_div_scalar(f64::from(rks[k]))?;
            let term = d1.f_mul_scalar(f64::from(*rho))?;
            sum = Some(match sum {
                Some(s) => s.f_add(&term)?,
                None => term,
            });
        }
        Ok(sum.expect("at least one earlier output"))
    }

    /// The stored converted outputs, most recent first.
    fn history(&self) -> Vec<&Tensor> {
        self.model_outputs.iter().rev().map_while(Option::as_ref).collect()
    }
}

/// The per-step coefficients of UniP/UniC.
struct Coefficients {
    /// (λ_si − λ_s0) / h for the earlier outputs, then 1.
    rks: Vec<f32>,
    /// The order conditions' right-hand sides.
    b: Vec<f32>,
    /// e^{hh} − 1.
    h_phi_1: f32,
    /// B(h).
    b_h: f32,
}

/// Solves the small dense system `a·x = b` by Gaussian elimination with partial pivoting
/// (`torch.linalg.solve` for UniPC's order conditions, at most [`MAX_SOLVER_ORDER`] unknowns).
fn solve(mut a: Vec<Vec<f64>>, mut b: Vec<f64>) -> Vec<f64> {
    let n = b.len();
    for col in 0..n {
        let pivot = (col..n).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs())).expect("non-empty");
        a.swap(col, pivot);
        b.swap(col, pivot);
        for row in col + 1..n {
            let f = a[row][col] / a[col][col];
            let (above, below) = a.split_at_mut(row);
            for (x, pivot_x) in below[0][col..].iter_mut().zip(&above[col][col..]) {
                *x -= f * pivot_x;
            }
            b[row] -= f * b[col];
        }
    }
    let mut x = vec![0.0; n];
    for row in (0..n).rev() {
        let s: f64 = (row + 1..n).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - s) / a[row][row];
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn solve_inverts_a_small_system() {
        let x = solve(vec![vec![2.0, 1.0], vec![1.0, 3.0]], vec![3.0, 5.0]);
        assert!((x[0] - 0.8).abs() < 1e-12 && (x[1] - 1.4).abs() < 1e-12, "{x:?}");
    }

    #[test]
    fn config_refuses_what_is_not_ported() {
        let err = |json: &str| UniPCMultistepSchedulerConfig::from_json_str(json, "s.json").unwrap_err().to_string();
        assert!(err("{}").contains("use_flow_sigmas"));
        let e = err(r#"{"use_flow_sigmas": true, "use_karras_sigmas": true}"#);
        assert!(e.contains("s.json") && e.contains("use_karras_sigmas"), "{e}");
        let e = err(r#"{"use_flow_sigmas": true, "prediction_type": "flow_prediction", "predict_x0": false}"#);
        assert!(e.contains("predict_x0"), "{e}");
        let e = err(r#"{"use_flow_sigmas": true, "solver_type": "midpoint"}"#);
        assert!(e.contains("solver_type"), "{e}");
    }

    #[test]
    fn wan_schedule_starts_just_below_one() {
        let mut s = UniPCMultistepScheduler::new(&UniPCMultistepSchedulerConfig::wan_480p()).unwrap();
        s.set_timesteps(50, None).unwrap();
        assert_eq!(s.timesteps().len(), 50);
        assert_eq!(s.timesteps()[0], 999);
        assert_eq!(s.sigmas().len(), 51);
        assert_eq!(*s.sigmas().last().unwrap(), 0.0);
    }
}

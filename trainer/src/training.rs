//! Pretraining the CogNVS transformer on shard pairs (DESIGN §6): the objective, AdamW, the
//! learning-rate schedule, gradient clipping and accumulation, checkpoints that resume exactly,
//! and the `trainer pretrain` loop.
//!
//! Objective (the public CogNVS code): the target clip is VAE-encoded (a posterior sample ×
//! `scaling_factor`); the conditioning clip is noise-augmented with σ = exp(N(μ, s)) per sample
//! (μ = −3, s = 0.5) before encoding; the noisy target latent at a uniform timestep t and the
//! condition latent are concatenated on channels; the transformer predicts v, from which
//! x̂₀ = √ᾱ_t·x_t − √(1−ᾱ_t)·v̂; the loss is mean((x̂₀ − x₀)² / (1−ᾱ_t)). The VAE is frozen.
//! The text input is a fixed embedding of the empty prompt: loaded from a safetensors file
//! (`encoder_hidden_states` `[S, D]`, e.g. T5-XXL's encoding of "" for the real model) or zeros.
//!
//! Determinism: every random draw of step k comes from tch's generator seeded with
//! (seed, k), and batches are a pure function of the data position, so a run resumed from a
//! checkpoint reproduces the uninterrupted run's losses exactly (fp32, same machine and threads).
//!
//! Checkpoints: `RUN_DIR/checkpoints/step-NNNNNNNN/` holds `transformer/` (diffusers layout,
//! loadable by `from_pretrained`), `optimizer.safetensors` (AdamW moments) and `state.json`
//! (step, data position); written under a temporary name and renamed, the oldest beyond
//! `keep_last` removed. With `validate_every`, validation samples go to `RUN_DIR/samples/`. The frozen VAE is saved once as `RUN_DIR/vae/` and the run's config as
//! `RUN_DIR/config.json`. `RUN_DIR/metrics.jsonl` has one line per step.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor, nn};

use crate::autoencoder_kl_cogvideox::{self as vae, AutoencoderKLCogVideoX, AutoencoderKLCogVideoXConfig};
use crate::cogvideox_transformer_3d::{
    self as transformer, CogVideoXTransformer3DModel, CogVideoXTransformer3DModelConfig, TransformerInput,
};
use crate::data::{Batch, DataConfig, DataPosition, ShardLoader};
use crate::diffusers_config::DiffusersConfig;
use crate::error::{Error, Result};
use crate::scheduling_ddim::{CogVideoXSchedulerConfig, NoiseSchedule};
use crate::weights;

/// Which models to train and with what.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelConfig {
    /// Transformer: a preset (`tiny`, `cognvs-5b`, `cogvideox-2b`) or a `config.json` file, both
    /// random init, or a diffusers model folder (config.json + weights) to start from.
    pub transformer: String,
    /// VAE: a preset (`tiny` random init with `seed`, `cogvideox-5b`) or a diffusers model folder.
    pub vae: String,
    /// Optional safetensors file with `encoder_hidden_states` `[S, D]`: the empty prompt's text
    /// embedding. Zeros when unset.
    #[serde(default)]
    pub text_embedding: Option<PathBuf>,
}

/// AdamW and its schedule (paper: lr 2e-5, β = (0.9, 0.95)).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OptimConfig {
    /// Peak learning rate.
    pub lr: f64,
    /// First-moment decay.
    pub beta1: f64,
    /// Second-moment decay.
    pub beta2: f64,
    /// Decoupled weight decay.
    pub weight_decay: f64,
    /// Denominator epsilon.
    pub eps: f64,
    /// Linear warm-up steps from 0 to `lr`.
    pub warmup_steps: u64,
    /// After warm-up: `constant` or `cosine` (to 0 at the last step).
    pub schedule: String,
    /// Gradient-norm clip (0: none).
    pub max_grad_norm: f64,
    /// Micro-batches accumulated per optimizer step.
    pub grad_accumulation: u64,
}

impl Default for OptimConfig {
    fn default() -> Self {
        Self {
            lr: 2e-5,
            beta1: 0.9,
            beta2: 0.95,
            weight_decay: 1e-4,
            eps: 1e-8,
            warmup_steps: 0,
            schedule: "constant".to_string(),
            max_grad_norm: 1.0,
            grad_accumulation: 1,
        }
    }
}

/// The loop.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LoopConfig {
    /// Optimizer steps in all (a resumed run continues up to this).
    pub steps: u64,
    /// Seed of model init and of every per-step draw.
    pub seed: u64,
    /// Steps between checkpoints (and one at the end).
    pub checkpoint_every: u64,
    /// Checkpoints kept.
    pub keep_last: usize,
    /// Mean of log σ of the condition noise augmentation.
    pub condition_noise_log_mean: f64,
    /// Standard deviation of log σ.
    pub condition_noise_log_std: f64,
    /// Steps between validation samples (0: none): the first pair of the data is sampled from
    /// its conditioning into `RUN/samples/step-N/` (`sample.mp4`, `contact_sheet.png` with
    /// target | conditioning | sample rows).
    pub validate_every: u64,
    /// Denoising steps of a validation sample.
    pub validation_steps: usize,
    /// A folder caching VAE latents per pair (see [`LatentCache`]); none when unset.
    pub latent_cache: Option<PathBuf>,
    /// Arithmetic of the transformer and the VAE.
    pub precision: Precision,
}

/// Training arithmetic.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Precision {
    /// bf16 on CUDA, fp32 elsewhere (CPUs have no fast bf16 kernels).
    #[default]
    Auto,
    /// Weights, activations and gradients in fp32.
    Fp32,
    /// Mixed precision: weights, activations and gradients in bf16 (half the memory, tensor-core
    /// speed); fp32 master weights, optimizer moments, noise schedule and loss. Checkpoints hold
    /// the fp32 master weights. bf16 keeps fp32's exponent range, so no loss scaling is needed
    /// (fp16's overflows are what turn into NaN losses).
    Bf16,
}

impl Precision {
    /// The element type of the models' weights on `device`.
    pub fn kind(self, device: Device) -> Kind {
        match self {
            Self::Auto if device.is_cuda() => Kind::BFloat16,
            Self::Auto | Self::Fp32 => Kind::Float,
            Self::Bf16 => Kind::BFloat16,
        }
    }
}

impl Default for LoopConfig {
    fn default() -> Self {
        Self {
            steps: 12_000,
            seed: 0,
            checkpoint_every: 500,
            keep_last: 3,
            condition_noise_log_mean: -3.0,
            condition_noise_log_std: 0.5,
            validate_every: 0,
            validation_steps: 20,
            latent_cache: None,
            precision: Precision::Auto,
        }
    }
}

/// `trainer pretrain --config` TOML.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PretrainConfig {
    /// Models.
    pub model: ModelConfig,
    /// Batches.
    pub data: DataConfig,
    /// Optimizer.
    #[serde(default)]
    pub optim: OptimConfig,
    /// Loop.
    #[serde(default, rename = "loop")]
    pub train: LoopConfig,
}

impl PretrainConfig {
    /// Reads and checks a TOML config, naming the file and field on error.
    pub fn from_toml_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io { path: path.to_path_buf(), source })?;
        let config: Self = toml::from_str(&text).map_err(|e| Error::InvalidConfig {
            source_name: path.display().to_string(),
            field: "(toml)".to_string(),
            reason: e.to_string(),
        })?;
        let bad = |field: &str, reason: &str| Error::InvalidConfig {
            source_name: path.display().to_string(),
            field: field.to_string(),
            reason: reason.to_string(),
        };
        if !["constant", "cosine"].contains(&config.optim.schedule.as_str()) {
            return Err(bad("optim.schedule", "must be `constant` or `cosine`"));
        }
        if config.optim.grad_accumulation == 0 || config.train.checkpoint_every == 0 || config.train.keep_last == 0 {
            return Err(bad(
                "optim.grad_accumulation",
                "grad_accumulation, checkpoint_every and keep_last must be ≥ 1",
            ));
        }
        if config.data.frames == 0 || !(config.data.frames - 1).is_multiple_of(4) {
            return Err(bad("data.frames", "must be 4k + 1 (the VAE compresses time by 4 after the first frame)"));
        }
        Ok(config)
    }
}

// ------------------------------------------------------------------------------------------------
// AdamW with saveable state
// ------------------------------------------------------------------------------------------------

/// PyTorch's `torch.optim.AdamW` (decoupled weight decay, bias correction), with its moments in
/// tensors that checkpoints save and load. For mixed precision it keeps fp32 master weights:
/// updates apply to them (with fp32 gradients and moments) and are copied, rounded, into the
/// low-precision parameters.
pub struct AdamW {
    config: OptimConfig,
    params: Vec<(String, Tensor)>,
    exp_avg: Vec<Tensor>,
    exp_avg_sq: Vec<Tensor>,
    step: u64,
    /// fp32 master copies of `params` when those are kept in lower precision.
    master: Option<Vec<Tensor>>,
}

impl AdamW {
    /// Optimizes every trainable variable of `vs`.
    pub fn new(vs: &nn::VarStore, config: OptimConfig) -> Self {
        let mut params: Vec<(String, Tensor)> = vs.variables().into_iter().filter(|(_, t)| t.requires_grad()).collect();
        params.sort_by(|a, b| a.0.cmp(&b.0));
        let zeros = |p: &Tensor| p.zeros_like();
        let exp_avg = params.iter().map(|(_, p)| zeros(p)).collect();
        let exp_avg_sq = params.iter().map(|(_, p)| zeros(p)).collect();
        Self { config, params, exp_avg, exp_avg_sq, step: 0, master: None }
    }

    /// Keeps fp32 master copies of the parameters, which must still be fp32: call before the
    /// model is cast to a lower precision.
    pub fn keep_master_weights(&mut self) -> Result<()> {
        if let Some((name, p)) = self.params.iter().find(|(_, p)| p.kind() != Kind::Float) {
            return Err(Error::InvalidArgument {
                name: "precision".to_string(),
                reason: format!("master weights are taken from fp32 parameters; {name} is {:?}", p.kind()),
            });
        }
        self.master = Some(tch::no_grad(|| self.params.iter().map(|(_, p)| p.detach().copy()).collect()));
        Ok(())
    }

    /// The fp32 master weights by variable name, when kept.
    pub fn master_weights(&self) -> Option<Vec<(String, Tensor)>> {
        let master = self.master.as_ref()?;
        Some(self.params.iter().zip(master).map(|((name, _), m)| (name.clone(), m.shallow_clone())).collect())
    }

    /// Zeroes every gradient.
    pub fn zero_grad(&self) {
        for (_, p) in &self.params {
            let mut grad = p.grad();
            if grad.defined() {
                let _ = grad.zero_();
            }
        }
    }

    /// Scales gradients so their global L2 norm is at most `max_norm` (PyTorch's
    /// `clip_grad_norm_`); returns the norm before clipping.
    pub fn clip_grad_norm(&self, max_norm: f64) -> Result<f64> {
        let mut total = 0.0;
        for (_, p) in &self.params {
            let grad = p.grad();
            if grad.defined() {
                total += grad.f_square()?.f_sum(Kind::Double)?.double_value(&[]);
            }
        }
        let norm = total.sqrt();
        if max_norm > 0.0 {
            let coef = (max_norm / (norm + 1e-6)).min(1.0);
            if coef < 1.0 {
                for (_, p) in &self.params {
                    let mut grad = p.grad();
                    if grad.defined() {
                        let _ = grad.f_mul_scalar_(coef)?;
                    }
                }
            }
        }
        Ok(norm)
    }

    /// One update with learning rate `lr`.
    pub fn step(&mut self, lr: f64) -> Result<()> {
        self.step += 1;
        let c = &self.config;
        let bias1 = 1.0 - c.beta1.powi(self.step as i32);
        let bias2 = 1.0 - c.beta2.powi(self.step as i32);
        tch::no_grad(|| -> Result<()> {
            for (i, (_, param)) in self.params.iter().enumerate() {
                let grad = param.grad();
                if !grad.defined() {
                    continue;
                }
                let (mut p, grad) = match &self.master {
                    Some(master) => (master[i].shallow_clone(), grad.f_to_kind(Kind::Float)?),
                    None => (param.shallow_clone(), grad),
                };
                let _ = p.f_mul_scalar_(1.0 - lr * c.weight_decay)?;
                let _ = self.exp_avg[i].f_mul_scalar_(c.beta1)?.f_add_(&grad.f_mul_scalar(1.0 - c.beta1)?)?;
                let _ = self.exp_avg_sq[i]
                    .f_mul_scalar_(c.beta2)?
                    .f_add_(&grad.f_square()?.f_mul_scalar(1.0 - c.beta2)?)?;
                let denom = self.exp_avg_sq[i].f_sqrt()?.f_div_scalar(bias2.sqrt())?.f_add_scalar(c.eps)?;
                let _ = p.f_sub_(&self.exp_avg[i].f_div(&denom)?.f_mul_scalar(lr / bias1)?)?;
                if self.master.is_some() {
                    param.shallow_clone().f_copy_(&p)?;
                }
            }
            Ok(())
        })
    }

    /// Optimizer steps taken.
    pub fn steps(&self) -> u64 {
        self.step
    }

    fn save(&self, path: &Path) -> Result<()> {
        let mut named: Vec<(String, &Tensor)> = Vec::new();
        for (i, (name, _)) in self.params.iter().enumerate() {
            named.push((format!("exp_avg.{name}"), &self.exp_avg[i]));
            named.push((format!("exp_avg_sq.{name}"), &self.exp_avg_sq[i]));
        }
        let step = Tensor::from_slice(&[self.step as i64]);
        named.push(("step".to_string(), &step));
        Tensor::write_safetensors(&named, path)
            .map_err(|e| Error::Safetensors { path: path.to_path_buf(), reason: e.to_string() })
    }

    fn load(&mut self, path: &Path) -> Result<()> {
        let tensors: BTreeMap<String, Tensor> = Tensor::read_safetensors(path)
            .map_err(|e| Error::Safetensors { path: path.to_path_buf(), reason: e.to_string() })?
            .into_iter()
            .collect();
        let get = |name: &str, like: &Tensor| -> Result<Tensor> {
            let t = tensors.get(name).ok_or_else(|| Error::MissingTensor {
                path: path.to_path_buf(),
                tensor: name.to_string(),
                expected: like.size(),
            })?;
            weights::check_shape(name, t, &like.size())?;
            Ok(t.f_to_kind(like.kind())?.f_to_device(like.device())?)
        };
        for (i, (name, p)) in self.params.iter().enumerate() {
            self.exp_avg[i] = get(&format!("exp_avg.{name}"), p)?;
            self.exp_avg_sq[i] = get(&format!("exp_avg_sq.{name}"), p)?;
        }
        self.step = tensors.get("step").map(|t| t.int64_value(&[0]) as u64).unwrap_or(0);
        Ok(())
    }
}

/// The learning rate at optimizer step `step` (0-based).
pub fn learning_rate(config: &OptimConfig, step: u64, total_steps: u64) -> f64 {
    if step < config.warmup_steps {
        return config.lr * (step + 1) as f64 / config.warmup_steps as f64;
    }
    match config.schedule.as_str() {
        "cosine" => {
            let span = total_steps.saturating_sub(config.warmup_steps).max(1) as f64;
            let progress = (step - config.warmup_steps) as f64 / span;
            config.lr * 0.5 * (1.0 + (std::f64::consts::PI * progress.min(1.0)).cos())
        }
        _ => config.lr,
    }
}

// ------------------------------------------------------------------------------------------------
// Models and the objective
// ------------------------------------------------------------------------------------------------

/// The trained transformer, the frozen VAE, the noise schedule and the text input.
pub struct CogNvsModel {
    /// The transformer's variables.
    pub vs: nn::VarStore,
    /// The transformer.
    pub transformer: CogVideoXTransformer3DModel,
    /// The VAE's variables (frozen).
    pub vae_vs: nn::VarStore,
    /// The VAE.
    pub vae: AutoencoderKLCogVideoX,
    /// The training noise schedule (CogVideoX-5B scheduler).
    pub schedule: NoiseSchedule,
    /// `[1, S, D]` text embedding of the empty prompt (fp32).
    pub text: Tensor,
    /// Element type of both models' weights and of their inputs.
    kind: Kind,
}

impl CogNvsModel {
    /// Builds (preset names, random init from `seed`) or loads (model folders) the models.
    pub fn load(config: &ModelConfig, seed: u64, device: Device) -> Result<Self> {
        tch::manual_seed(seed as i64);
        let transformer_config = match Path::new(&config.transformer) {
            p if p.is_dir() || p.is_file() => CogVideoXTransformer3DModelConfig::from_json_file(p)?,
            _ => CogVideoXTransformer3DModelConfig::preset(&config.transformer)?,
        };
        let (vs, transformer) = transformer::build(&transformer_config, device, Kind::Float)?;
        if Path::new(&config.transformer).is_dir() {
            weights::load(&vs, Path::new(&config.transformer))?;
        }
        let vae_config = match Path::new(&config.vae) {
            p if p.is_dir() => AutoencoderKLCogVideoXConfig::from_json_file(p)?,
            _ => AutoencoderKLCogVideoXConfig::preset(&config.vae)?,
        };
        let (mut vae_vs, vae) = vae::build(&vae_config, device, Kind::Float)?;
        if Path::new(&config.vae).is_dir() {
            weights::load(&vae_vs, Path::new(&config.vae))?;
        }
        vae_vs.freeze();
        let text = crate::sampling::load_text_embedding(config.text_embedding.as_deref(), &transformer_config, device)?;
        let schedule = NoiseSchedule::new(&CogVideoXSchedulerConfig::cogvideox_5b())?;
        Ok(Self { vs, transformer, vae_vs, vae, schedule, text, kind: Kind::Float })
    }

    /// Casts both models' weights to `kind` (fp32 as loaded; bf16 for mixed precision, after the
    /// optimizer has taken its master copies).
    pub fn set_kind(&mut self, kind: Kind) {
        self.vs.set_kind(kind);
        self.vae_vs.set_kind(kind);
        self.kind = kind;
    }

    /// Element type of the models' weights.
    pub fn kind(&self) -> Kind {
        self.kind
    }

    /// Scaled fp32 latents `[B, F', C, h, w]` of a video batch `[B, 3, F, H, W]` (a posterior
    /// sample).
    pub fn encode(&self, video: &Tensor) -> Result<Tensor> {
        let latent = tch::no_grad(|| -> Result<Tensor> {
            Ok(self.vae.encode_posterior(&video.f_to_kind(self.kind)?)?.sample()?.f_to_kind(Kind::Float)?)
        })?;
        self.scale_latent(&latent)
    }

    /// A VAE latent `[B, C, F', h, w]` scaled and laid out for the transformer `[B, F', C, h, w]`.
    fn scale_latent(&self, latent: &Tensor) -> Result<Tensor> {
        Ok(latent.f_mul_scalar(self.vae.config().scaling_factor)?.f_permute([0, 2, 1, 3, 4])?.f_contiguous()?)
    }

    /// The training loss of one batch (see the module docs); draws from tch's generator. With a
    /// latent cache, the VAE runs only for samples not cached yet (see [`LatentCache`]).
    pub fn loss(
        &self,
        batch: &Batch,
        noise_log_mean: f64,
        noise_log_std: f64,
        cache: Option<&LatentCache>,
    ) -> Result<Tensor> {
        let device = self.text.device();
        let b = batch.target.size()[0];
        let (x0, cond) = match cache {
            None => {
                let target = batch.target.f_to_device(device)?;
                let condition = batch.condition.f_to_device(device)?;
                let sigma = (Tensor::f_randn([b, 1, 1, 1, 1], (Kind::Float, device))? * noise_log_std + noise_log_mean)
                    .f_exp()?;
                let noisy_condition = condition.f_add(&condition.f_randn_like()?.f_mul(&sigma)?)?;
                (self.encode(&target)?, self.encode(&noisy_condition)?)
            }
            Some(cache) => {
                // Cache look-ups and fills draw from their own seeds; the step's generator state is
                // saved around them by reseeding with a draw taken before.
                let resume_seed = Tensor::f_randint(i64::MAX, [1], (Kind::Int64, Device::Cpu))?.int64_value(&[0]);
                let mut x0 = Vec::new();
                let mut cond = Vec::new();
                let mut posteriors = Vec::new();
                for i in 0..b {
                    let entry = cache.get_or_encode(self, batch, i, noise_log_mean, noise_log_std)?;
                    posteriors.push(entry);
                }
                tch::manual_seed(resume_seed);
                for (mean, logvar, condition) in posteriors {
                    let (mean, logvar) = (mean.f_to_kind(Kind::Float)?, logvar.f_to_kind(Kind::Float)?);
                    let std = logvar.f_mul_scalar(0.5)?.f_exp()?;
                    let sample = mean.f_add(&std.f_mul(&mean.f_randn_like()?)?)?;
                    x0.push(self.scale_latent(&sample)?);
                    cond.push(condition.f_to_kind(Kind::Float)?);
                }
                (Tensor::f_cat(&x0, 0)?, Tensor::f_cat(&cond, 0)?)
            }
        };
        let steps = self.schedule.alphas_cumprod().len() as i64;
        let t = Tensor::f_randint(steps, [b], (Kind::Int64, device))?;
        let noise = x0.f_randn_like()?;
        let xt = self.schedule.add_noise(&x0, &noise, &t)?;
        let input = Tensor::f_cat(&[&xt, &cond], 2)?.f_to_kind(self.kind)?;
        let text = self.text.f_to_kind(self.kind)?.f_expand([b, -1, -1], false)?;
        let v = self
            .transformer
            .forward(
                &TransformerInput {
                    hidden_states: &input,
                    encoder_hidden_states: &text,
                    timestep: &t,
                    ofs: None,
                    image_rotary_emb: None,
                },
                true,
            )?
            .f_to_kind(Kind::Float)?;
        let alphas: Vec<f64> =
            (0..b).map(|i| self.schedule.alpha_cumprod_at(t.int64_value(&[i]))).collect::<Result<_>>()?;
        let per_sample = |f: fn(f64) -> f64| -> Result<Tensor> {
            let values: Vec<f32> = alphas.iter().map(|&a| f(a) as f32).collect();
            Ok(Tensor::from_slice(&values).f_view([b, 1, 1, 1, 1])?.f_to_device(device)?)
        };
        let sqrt_alpha = per_sample(f64::sqrt)?;
        let sqrt_one_minus = per_sample(|a| (1.0 - a).sqrt())?;
        let weight = per_sample(|a| 1.0 / (1.0 - a).max(1e-12))?;
        let x0_hat = xt.f_mul(&sqrt_alpha)?.f_sub(&v.f_mul(&sqrt_one_minus)?)?;
        Ok(x0_hat.f_sub(&x0)?.f_square()?.f_mul(&weight)?.f_mean(Kind::Float)?)
    }
}

// ------------------------------------------------------------------------------------------------
// Checkpoints
// ------------------------------------------------------------------------------------------------

/// Precomputed VAE latents, so that small runs encode each pair once and train many epochs:
/// per sample (clip, trajectory, window — the batch's provenance — at the configured size) the
/// target's posterior (mean, log-variance; a fresh sample is drawn at every use, as without the
/// cache) and the conditioning latent. The conditioning's noise augmentation is then drawn once
/// per sample (seeded by the sample) instead of at every use: the cache trades augmentation
/// variety for speed. Entries are keyed by the sample, the data size and the VAE's weights, and
/// written atomically, so runs and resumed runs share them; a cached entry equals a fresh one
/// bit for bit.
pub struct LatentCache {
    dir: PathBuf,
    prefix: String,
}

impl LatentCache {
    /// A cache in `dir` for `model`'s VAE and the data size.
    pub fn open(dir: &Path, model: &CogNvsModel, data: &DataConfig) -> Result<Self> {
        std::fs::create_dir_all(dir).map_err(|source| Error::Io { path: dir.to_path_buf(), source })?;
        let mut hasher = blake3::Hasher::new();
        hasher.update(b"cognvs latent cache v1");
        hasher.update(serde_json::to_string(model.vae.config()).expect("config serialises").as_bytes());
        let mut variables: Vec<(String, Tensor)> = model.vae_vs.variables().into_iter().collect();
        variables.sort_by(|a, b| a.0.cmp(&b.0));
        for (name, tensor) in variables {
            hasher.update(name.as_bytes());
            let t = tensor.f_to_kind(Kind::Float)?.f_to_device(Device::Cpu)?.f_contiguous()?;
            let values = Vec::<f32>::try_from(t.f_flatten(0, -1)?)?;
            for v in values {
                hasher.update(&v.to_le_bytes());
            }
        }
        hasher.update(format!("{}x{}x{}", data.frames, data.height, data.width).as_bytes());
        Ok(Self { dir: dir.to_path_buf(), prefix: hasher.finalize().to_hex()[..16].to_string() })
    }

    fn key(&self, provenance: &str) -> (PathBuf, i64) {
        let hash = blake3::hash(format!("{}/{provenance}", self.prefix).as_bytes());
        let seed = i64::from_le_bytes(hash.as_bytes()[..8].try_into().expect("8 bytes")) & i64::MAX;
        (self.dir.join(format!("{}.safetensors", &hash.to_hex()[..32])), seed)
    }

    /// Sample `i` of `batch`: (posterior mean, log-variance, scaled conditioning latent), from the
    /// cache or encoded and stored.
    fn get_or_encode(
        &self,
        model: &CogNvsModel,
        batch: &Batch,
        i: i64,
        noise_log_mean: f64,
        noise_log_std: f64,
    ) -> Result<(Tensor, Tensor, Tensor)> {
        let device = model.text.device();
        let (path, seed) = self.key(&batch.provenance[i as usize]);
        if let Ok(entries) = Tensor::read_safetensors(&path) {
            let map: BTreeMap<String, Tensor> = entries.into_iter().collect();
            if let (Some(m), Some(l), Some(c)) = (map.get("mean"), map.get("logvar"), map.get("condition")) {
                return Ok((m.f_to_device(device)?, l.f_to_device(device)?, c.f_to_device(device)?));
            }
        }
        tch::manual_seed(seed);
        let target = batch.target.f_narrow(0, i, 1)?.f_to_device(device)?;
        let condition = batch.condition.f_narrow(0, i, 1)?.f_to_device(device)?;
        let sigma = (Tensor::f_randn([1], (Kind::Float, Device::Cpu))?.double_value(&[0]) * noise_log_std
            + noise_log_mean)
            .exp();
        let noisy = condition.f_add(&condition.f_randn_like()?.f_mul_scalar(sigma)?)?.f_to_kind(model.kind)?;
        let target = target.f_to_kind(model.kind)?;
        let (posterior, cond) = tch::no_grad(|| -> Result<_> {
            let posterior = model.vae.encode_posterior(&target)?;
            let cond = model.vae.encode(&noisy)?;
            Ok((posterior, cond))
        })?;
        let cond = model.scale_latent(&cond)?;
        let temp = path.with_extension(format!("tmp-{}", std::process::id()));
        Tensor::write_safetensors(
            &[("mean", &posterior.mean), ("logvar", &posterior.logvar), ("condition", &cond)],
            &temp,
        )
        .map_err(|e| Error::Safetensors { path: temp.clone(), reason: e.to_string() })?;
        std::fs::rename(&temp, &path).map_err(|source| Error::Io { path: path.clone(), source })?;
        Ok((posterior.mean, posterior.logvar, cond))
    }
}

/// `state.json` of a checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainState {
    /// Optimizer steps done.
    pub step: u64,
    /// The data position of the next batch.
    pub data_position: DataPosition,
    /// The run seed.
    pub seed: u64,
}

fn checkpoints_dir(run: &Path) -> PathBuf {
    run.join("checkpoints")
}

/// The checkpoints of a run, oldest first.
pub fn list_checkpoints(run: &Path) -> Vec<(u64, PathBuf)> {
    let mut found: Vec<(u64, PathBuf)> = std::fs::read_dir(checkpoints_dir(run))
        .into_iter()
        .flatten()
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let step = name.strip_prefix("step-")?.parse().ok()?;
            e.path().join("state.json").is_file().then(|| (step, e.path()))
        })
        .collect();
    found.sort();
    found
}

fn save_checkpoint(
    run: &Path,
    model: &CogNvsModel,
    optimizer: &AdamW,
    state: &TrainState,
    keep: usize,
) -> Result<PathBuf> {
    let dir = checkpoints_dir(run);
    let final_dir = dir.join(format!("step-{:08}", state.step));
    let temp = dir.join(format!(".tmp-step-{:08}", state.step));
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| Error::Io { path, source }
    };
    let _ = std::fs::remove_dir_all(&temp);
    std::fs::create_dir_all(&temp).map_err(io(&temp))?;
    // fp32 throughout: a mixed-precision run's master weights replace its bf16 parameters.
    let mut variables: BTreeMap<String, Tensor> = model.vs.variables().into_iter().collect();
    variables.extend(optimizer.master_weights().into_iter().flatten());
    let variables = variables
        .into_iter()
        .map(|(name, t)| Ok((name, if t.is_floating_point() { t.f_to_kind(Kind::Float)? } else { t })))
        .collect::<Result<_>>()?;
    weights::save_tensors(
        variables,
        model.transformer.config(),
        transformer::CLASS_NAME,
        &temp.join("transformer"),
        weights::DEFAULT_MAX_SHARD_BYTES,
    )?;
    optimizer.save(&temp.join("optimizer.safetensors"))?;
    let json = serde_json::to_vec_pretty(state).expect("state serialises");
    std::fs::write(temp.join("state.json"), json).map_err(io(&temp))?;
    let _ = std::fs::remove_dir_all(&final_dir);
    std::fs::rename(&temp, &final_dir).map_err(io(&final_dir))?;
    let all = list_checkpoints(run);
    for (_, old) in all.iter().take(all.len().saturating_sub(keep)) {
        let _ = std::fs::remove_dir_all(old);
    }
    Ok(final_dir)
}

// ------------------------------------------------------------------------------------------------
// The loop
// ------------------------------------------------------------------------------------------------

/// One line of `metrics.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StepMetrics {
    /// Optimizer step (1-based).
    pub step: u64,
    /// Mean loss over the step's micro-batches.
    pub loss: f64,
    /// Learning rate used.
    pub lr: f64,
    /// Gradient norm before clipping.
    pub grad_norm: f64,
    /// Wall seconds of the step.
    pub seconds: f64,
}

/// What a pretraining run did.
#[derive(Debug, Clone)]
pub struct RunSummary {
    /// The step the run started from (0, or a resumed checkpoint's).
    pub resumed_from: u64,
    /// Steps done at the end.
    pub steps: u64,
    /// The last checkpoint.
    pub last_checkpoint: Option<PathBuf>,
}

/// `trainer pretrain`: trains up to `config.train.steps`, resuming from the run's latest
/// checkpoint when `resume` is set. `progress(step, metrics)` is called after every step.
pub fn pretrain(
    config: &PretrainConfig,
    shards: &[PathBuf],
    run: &Path,
    resume: bool,
    device: Device,
    mut progress: impl FnMut(&StepMetrics),
) -> Result<RunSummary> {
    // Bad shard folders fail before the run folder is touched.
    crate::data::describe(shards, &config.data)?;
    std::fs::create_dir_all(run).map_err(|source| Error::Io { path: run.to_path_buf(), source })?;
    let run_config = run.join("config.json");
    let text = serde_json::to_vec_pretty(config).expect("config serialises");
    let latest = if resume { list_checkpoints(run).pop() } else { None };
    if !resume && run_config.exists() {
        return Err(Error::InvalidArgument {
            name: "out".to_string(),
            reason: format!(
                "{} already holds a run; pass --resume to continue it or choose another folder",
                run.display()
            ),
        });
    }
    std::fs::write(&run_config, text).map_err(|source| Error::Io { path: run_config.clone(), source })?;

    let mut model = CogNvsModel::load(&config.model, config.train.seed, device)?;
    // The frozen VAE goes with the run once (sampling and finetuning find it there).
    let vae_dir = run.join("vae");
    if !vae_dir.join("config.json").exists() {
        weights::save(&model.vae_vs, model.vae.config(), vae::CLASS_NAME, &vae_dir, weights::DEFAULT_MAX_SHARD_BYTES)?;
    }
    let mut optimizer = AdamW::new(&model.vs, config.optim.clone());
    let mut state = TrainState { step: 0, data_position: DataPosition::default(), seed: config.train.seed };
    if let Some((_, dir)) = &latest {
        weights::load(&model.vs, &dir.join("transformer"))?;
        optimizer.load(&dir.join("optimizer.safetensors"))?;
        let path = dir.join("state.json");
        let text = std::fs::read_to_string(&path).map_err(|source| Error::Io { path: path.clone(), source })?;
        state = serde_json::from_str(&text).map_err(|e| Error::InvalidConfig {
            source_name: path.display().to_string(),
            field: "(json)".to_string(),
            reason: e.to_string(),
        })?;
    }
    let kind = config.train.precision.kind(device);
    if kind != Kind::Float {
        // Mixed precision: the optimizer keeps the fp32 weights (as initialised or resumed).
        optimizer.keep_master_weights()?;
        model.set_kind(kind);
    }
    let resumed_from = state.step;
    rewrite_metrics(run, resumed_from)?;
    let mut metrics_file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(run.join("metrics.jsonl"))
        .map_err(|source| Error::Io { path: run.join("metrics.jsonl"), source })?;
    let mut loader = ShardLoader::open(shards, config.data.clone(), state.data_position)?;
    let mut last_checkpoint = latest.map(|(_, d)| d);
    let accumulation = config.optim.grad_accumulation;
    let cache = match &config.train.latent_cache {
        Some(dir) => Some(LatentCache::open(dir, &model, &config.data)?),
        None => None,
    };
    let mut validation: Option<Result<Batch>> = None;
    while state.step < config.train.steps {
        let started = Instant::now();
        // Every draw of this step comes from (seed, step): resumed runs repeat them exactly.
        tch::manual_seed(step_seed(config.train.seed, state.step));
        optimizer.zero_grad();
        let mut loss_sum = 0.0;
        for _ in 0..accumulation {
            let batch = loader.next_batch()?;
            let loss = model.loss(
                &batch,
                config.train.condition_noise_log_mean,
                config.train.condition_noise_log_std,
                cache.as_ref(),
            )?;
            let value = loss.double_value(&[]);
            if !value.is_finite() {
                return Err(Error::InvalidArgument {
                    name: "loss".to_string(),
                    reason: format!(
                        "non-finite loss {value} at step {} on batch {:?}; last good checkpoint: {}",
                        state.step + 1,
                        batch.provenance,
                        last_checkpoint.as_ref().map_or("none".to_string(), |p| p.display().to_string())
                    ),
                });
            }
            loss_sum += value;
            (loss / accumulation as f64).f_backward()?;
        }
        let grad_norm = optimizer.clip_grad_norm(config.optim.max_grad_norm)?;
        let lr = learning_rate(&config.optim, state.step, config.train.steps);
        optimizer.step(lr)?;
        state.step += 1;
        state.data_position = loader.position();
        let metrics = StepMetrics {
            step: state.step,
            loss: loss_sum / accumulation as f64,
            lr,
            grad_norm,
            seconds: started.elapsed().as_secs_f64(),
        };
        writeln!(metrics_file, "{}", serde_json::to_string(&metrics).expect("metrics serialise"))
            .map_err(|source| Error::Io { path: run.join("metrics.jsonl"), source })?;
        progress(&metrics);
        if config.train.validate_every > 0 && state.step.is_multiple_of(config.train.validate_every) {
            let batch = validation.get_or_insert_with(|| {
                ShardLoader::open(shards, DataConfig { batch_size: 1, ..config.data.clone() }, DataPosition::default())
                    .and_then(|mut l| l.next_batch())
            });
            let batch = batch
                .as_ref()
                .map_err(|e| Error::InvalidArgument { name: "validation".to_string(), reason: e.to_string() })?;
            write_validation_sample(run, state.step, &model, batch, config)?;
        }
        if state.step.is_multiple_of(config.train.checkpoint_every) || state.step == config.train.steps {
            last_checkpoint = Some(save_checkpoint(run, &model, &optimizer, &state, config.train.keep_last)?);
        }
    }
    Ok(RunSummary { resumed_from, steps: state.step, last_checkpoint })
}

/// Samples the validation pair's conditioning and writes the video and a contact sheet. Its
/// random draws come from (seed, step) too, and every training step reseeds, so validation does
/// not change the training run.
fn write_validation_sample(
    run: &Path,
    step: u64,
    model: &CogNvsModel,
    batch: &Batch,
    config: &PretrainConfig,
) -> Result<()> {
    let dir = run.join("samples").join(format!("step-{step:08}"));
    std::fs::create_dir_all(&dir).map_err(|source| Error::Io { path: dir.clone(), source })?;
    let device = model.text.device();
    let condition = batch.condition.f_narrow(0, 0, 1)?.f_to_device(device)?;
    tch::manual_seed(step_seed(config.train.seed ^ VALIDATION_SEED, step));
    let video = crate::sampling::generate(
        &model.transformer,
        &model.vae,
        &condition,
        &model.text,
        None,
        config.train.validation_steps,
        1.0,
    )?;
    let sample = crate::sampling::to_frames(&video)?;
    let target = crate::sampling::to_frames(&batch.target.f_narrow(0, 0, 1)?)?;
    let cond = crate::sampling::to_frames(&condition)?;
    datagen::video::encode_video(&dir.join("sample.mp4"), &sample, VALIDATION_FPS)?;
    let picked: Vec<usize> = (0..SHEET_ROWS).map(|k| k * (sample.len() - 1) / (SHEET_ROWS - 1)).collect();
    let rows: Vec<Vec<image::RgbImage>> =
        picked.iter().map(|&i| vec![target[i].clone(), cond[i].clone(), sample[i].clone()]).collect();
    datagen::contact_sheet::write_contact_sheet(&dir.join("contact_sheet.png"), &rows)?;
    let provenance = serde_json::json!({ "step": step, "pair": batch.provenance[0] });
    std::fs::write(dir.join("pair.json"), provenance.to_string()).map_err(|source| Error::Io { path: dir, source })?;
    Ok(())
}

/// Mixed into the seed of validation sampling (so it differs from the training draws).
const VALIDATION_SEED: u64 = 0x5eed_0f5a_3b1e;
/// Frame rate of validation videos (CogVideoX's 8 fps).
const VALIDATION_FPS: f64 = 8.0;
/// Frames shown on a validation contact sheet.
const SHEET_ROWS: usize = 4;

fn step_seed(seed: u64, step: u64) -> i64 {
    let mut hasher = blake3::Hasher::new();
    hasher.update(b"cognvs train step v1");
    hasher.update(&seed.to_le_bytes());
    hasher.update(&step.to_le_bytes());
    let bytes = hasher.finalize();
    i64::from_le_bytes(bytes.as_bytes()[..8].try_into().expect("8 bytes")) & i64::MAX
}

/// Keeps the metrics lines of steps up to `step` (a resumed run rewrites what followed).
fn rewrite_metrics(run: &Path, step: u64) -> Result<()> {
    let path = run.join("metrics.jsonl");
    let Ok(text) = std::fs::read_to_string(&path) else { return Ok(()) };
    let kept: String = text
        .lines()
        .filter(|line| serde_json::from_str::<StepMetrics>(line).is_ok_and(|m| m.step <= step))
        .map(|line| format!("{line}\n"))
        .collect();
    schemas::write_atomic(&path, kept.as_bytes())?;
    Ok(())
}

/// Reads a run's `metrics.jsonl`.
pub fn read_metrics(run: &Path) -> Result<Vec<StepMetrics>> {
    let path = run.join("metrics.jsonl");
    let text = std::fs::read_to_string(&path).map_err(|source| Error::Io { path: path.clone(), source })?;
    text.lines()
        .map(|line| {
            serde_json::from_str(line).map_err(|e| Error::InvalidConfig {
                source_name: path.display().to_string(),
                field: "(jsonl)".to_string(),
                reason: e.to_string(),
            })
        })
        .collect()
}

/// What `trainer finetune` trains.
#[derive(Debug, Clone)]
pub struct FinetuneRequest {
    /// Checkpoint to start from.
    pub init: PathBuf,
    /// The test video's sequence folder.
    pub sequence: PathBuf,
    /// Run folder.
    pub out: PathBuf,
    /// Optimizer steps.
    pub steps: u64,
    /// Sampled trajectories per clip.
    pub trajectories: u32,
    /// Training TOML overriding the init run's settings.
    pub config: Option<PathBuf>,
}

/// `trainer finetune`: test-time finetuning on one video (DESIGN §1). Its self-supervised pairs
/// are built in-process with the `datagen` library (clips of the training length, back to back,
/// `trajectories` sampled paths each) into `RUN/pairs/`, then the transformer of checkpoint
/// `init` is trained on them for `steps` steps with the init run's settings (its `config.json`,
/// or `config` when given) and the init run's VAE. Checkpoints and metrics go to `run`.
pub fn finetune(request: &FinetuneRequest, device: Device, progress: impl FnMut(&StepMetrics)) -> Result<RunSummary> {
    let FinetuneRequest { init, sequence: sequence_dir, out: run, steps, trajectories, config } = request;
    let (steps, trajectories) = (*steps, *trajectories);
    let mut config = match config {
        Some(path) => PretrainConfig::from_toml_file(path)?,
        None => {
            let path = init.join("../../config.json");
            let text = std::fs::read_to_string(&path).map_err(|source| Error::Io { path: path.clone(), source })?;
            serde_json::from_str(&text).map_err(|e| Error::InvalidConfig {
                source_name: path.display().to_string(),
                field: "(json)".to_string(),
                reason: e.to_string(),
            })?
        }
    };
    if run.join("config.json").exists() {
        return Err(Error::InvalidArgument {
            name: "out".to_string(),
            reason: format!("{} already holds a run; choose another folder", run.display()),
        });
    }
    config.model.transformer = crate::sampling::transformer_dir(init).display().to_string();
    config.model.vae = crate::sampling::find_vae(init, None)?.display().to_string();
    config.train.steps = steps;
    config.train.checkpoint_every = config.train.checkpoint_every.min(steps.max(1));

    let sequence = datagen::sequence::read_sequence(sequence_dir)?;
    let frames = config.data.frames as u32;
    let pairs_config = datagen::pairs::PairsConfig {
        clip: datagen::pairs::ClipConfig { length: frames, stride: frames, max_clips: 0 },
        ..Default::default()
    };
    let request = datagen::pairs::TrajectoryRequest { sampled: trajectories, explicit: Vec::new() };
    let records = datagen::pairs::generate_clips(&sequence, "finetune", &pairs_config, &request, config.data.seed)?;
    let digest = schemas::InputDigest {
        source_path: sequence_dir.display().to_string(),
        content_hash: datagen::corpus::build::hash_tree(sequence_dir)?,
    };
    let pairs_dir = run.join("pairs");
    datagen::pairs::write_shard(&pairs_dir, &sequence.source_id, &records, digest)?;
    // Small test videos have few clips: never ask for more per batch than there are.
    config.data.batch_size = config.data.batch_size.min(records.len()).max(1);
    pretrain(&config, &[pairs_dir], run, false, device, progress)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A var store with one trainable `[4, 3]` variable holding `values`, and that variable.
    fn store(values: &Tensor) -> (nn::VarStore, Tensor) {
        let vs = nn::VarStore::new(Device::Cpu);
        let w = vs.root().var_copy("w", values);
        (vs, w)
    }

    /// Mixed precision updates the fp32 master exactly as fp32 AdamW would with the same
    /// (bf16-rounded) gradients, and the bf16 parameter is the master rounded.
    #[test]
    fn adamw_master_weights_follow_the_fp32_update() {
        tch::manual_seed(3);
        let init = Tensor::randn([4, 3], (Kind::Float, Device::Cpu));
        let config = OptimConfig { weight_decay: 0.01, ..OptimConfig::default() };
        let (reference_vs, reference) = store(&init);
        let mut reference_optimizer = AdamW::new(&reference_vs, config.clone());
        let (mut mixed_vs, mixed) = store(&init);
        let mut mixed_optimizer = AdamW::new(&mixed_vs, config);
        mixed_optimizer.keep_master_weights().unwrap();
        mixed_vs.set_kind(Kind::BFloat16);
        assert_eq!(mixed.kind(), Kind::BFloat16);
        for step in 0..3 {
            let target = Tensor::randn([4, 3], (Kind::Float, Device::Cpu));
            reference_optimizer.zero_grad();
            mixed_optimizer.zero_grad();
            // The same loss; the reference sees the gradient the bf16 parameter receives.
            let loss = |w: &Tensor| w.to_kind(Kind::Float).f_sub(&target).unwrap().square().sum(Kind::Float);
            loss(&mixed).backward();
            // d/dw Σ w·g = g: the reference's gradient is the mixed one, exactly.
            let gradient = mixed.grad().to_kind(Kind::Float);
            reference.f_mul(&gradient).unwrap().sum(Kind::Float).backward();
            reference_optimizer.step(1e-2).unwrap();
            mixed_optimizer.step(1e-2).unwrap();
            let master = &mixed_optimizer.master_weights().unwrap()[0].1;
            assert!(master.equal(&reference), "step {step}: master differs from the fp32 update");
            assert!(
                mixed.equal(&reference.to_kind(Kind::BFloat16)),
                "step {step}: parameter is not the rounded master"
            );
        }
    }

    #[test]
    fn master_weights_must_come_from_fp32_parameters() {
        let (mut vs, _) = store(&Tensor::zeros([4, 3], (Kind::Float, Device::Cpu)));
        vs.set_kind(Kind::BFloat16);
        let mut optimizer = AdamW::new(&vs, OptimConfig::default());
        assert!(optimizer.keep_master_weights().is_err());
    }

    #[test]
    fn auto_precision_is_bf16_on_cuda_only() {
        assert_eq!(Precision::Auto.kind(Device::Cpu), Kind::Float);
        assert_eq!(Precision::Auto.kind(Device::Cuda(0)), Kind::BFloat16);
        assert_eq!(Precision::Bf16.kind(Device::Cpu), Kind::BFloat16);
        assert_eq!(Precision::Fp32.kind(Device::Cuda(0)), Kind::Float);
    }
}

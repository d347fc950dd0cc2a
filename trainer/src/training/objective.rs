//! The trained and frozen models and the CogNVS objective (the public CogNVS training code):
//! noise-augmented condition and, per the family's [`Objective`], CogVideoX's v-prediction with
//! the x̂₀ loss weighted by 1/(1−ᾱ_t), or Wan's rectified flow (the velocity `ε − x₀` at σ drawn
//! uniformly from the shifted flow-matching training schedule, as diffusers-based trainers such as
//! finetrainers train Wan). The models are reached through [`crate::models::backbone`] only.

use std::path::Path;

use tch::{Device, Kind, Tensor, nn};

use super::{LatentCache, ModelConfig};
use crate::error::Result;
use crate::loaders::lora::LoraFile;
use crate::models::backbone::{ModelInput, Tape, Transformer, Vae};
use crate::models::family::Objective;
use crate::models::lora::LoraConfig;
use crate::models::weights;
use crate::schedulers::NoiseSchedule;
use crate::schedulers::scheduling_flow_match_euler_discrete::{FlowMatchEulerDiscreteSchedulerConfig, training_sigmas};
use crate::training::data::Batch;

/// The noise schedule a run trains on, per the family's objective.
pub enum TrainingSchedule {
    /// CogVideoX's DDPM schedule (v-prediction; boxed, its tables are large beside the sigmas).
    Ddpm(Box<NoiseSchedule>),
    /// The flow-matching training sigmas (rectified flow).
    Flow(FlowSchedule),
}

/// The rectified-flow training schedule: diffusers' `FlowMatchEulerDiscreteScheduler` training
/// sigmas (`num_train_timesteps` of them, shifted), from which a step draws one per sample.
#[derive(Debug, Clone, PartialEq)]
pub struct FlowSchedule {
    sigmas: Vec<f32>,
}

impl FlowSchedule {
    /// The schedule of a flow-matching scheduler config.
    pub fn new(config: &FlowMatchEulerDiscreteSchedulerConfig) -> Result<Self> {
        use crate::diffusers_config::DiffusersConfig;
        config.validate("flow-matching scheduler config")?;
        Ok(Self { sigmas: training_sigmas(config) })
    }

    /// The sigmas `[B]` and the model's timesteps `[B]` (int64) for uniform draws `u` in [0, 1):
    /// index ⌊u·N⌋ of the training sigmas (noisiest first), timestep ⌊σ·N⌋, as finetrainers'
    /// `prepare_sigmas` with the uniform weighting and its `(σ · 1000).long()` timesteps.
    pub fn draw(&self, u: &Tensor) -> Result<(Tensor, Tensor)> {
        let n = self.sigmas.len() as i64;
        let table = Tensor::from_slice(&self.sigmas).f_to_device(u.device())?;
        let index = u.f_mul_scalar(n as f64)?.f_to_kind(Kind::Int64)?.f_clamp(0, n - 1)?;
        let sigmas = table.f_index_select(0, &index)?;
        let timesteps = sigmas.f_mul_scalar(n as f64)?.f_to_kind(Kind::Int64)?;
        Ok((sigmas, timesteps))
    }
}

/// The rectified-flow pieces for clean latents `x0`, noise and per-sample sigmas `[B]`:
/// `(x_σ, target)` with `x_σ = (1 − σ)·x0 + σ·noise` and the velocity target `noise − x0`.
pub fn flow_noisy_and_target(x0: &Tensor, noise: &Tensor, sigmas: &Tensor) -> Result<(Tensor, Tensor)> {
    let mut shape = vec![-1];
    shape.extend(std::iter::repeat_n(1, x0.dim() - 1));
    let sigma = sigmas.f_to_kind(Kind::Float)?.f_view(shape.as_slice())?;
    let noisy = x0.f_mul(&sigma.f_neg()?.f_add_scalar(1.0)?)?.f_add(&noise.f_mul(&sigma)?)?;
    Ok((noisy, noise.f_sub(x0)?))
}

/// The trained transformer, the frozen VAE, the noise schedule and the text input.
pub struct CogNvsModel {
    /// The transformer's variables.
    pub vs: nn::VarStore,
    /// The transformer.
    pub transformer: Transformer,
    /// The VAE's variables (frozen).
    pub vae_vs: nn::VarStore,
    /// The VAE.
    pub vae: Vae,
    /// The training noise schedule (the family's objective's).
    pub schedule: TrainingSchedule,
    /// `[1, S, D]` text embedding of the empty prompt (fp32).
    pub text: Tensor,
    /// The LoRA adapters' variables when only adapters train (the base `vs` is then frozen).
    pub lora_vs: Option<nn::VarStore>,
    /// The adapters' settings, with `lora_vs`.
    pub lora: Option<LoraConfig>,
    /// Element type of both models' weights and of their inputs.
    pub(super) kind: Kind,
    /// Seconds spent in VAE encodes since [`Self::take_encode_seconds`] last read them.
    encode_seconds: std::cell::Cell<f64>,
}

impl CogNvsModel {
    /// Builds (preset names, random init from `seed`) or loads (model folders) the models; with
    /// `lora`, adds fresh adapters (drawn after the base's initialisation) and freezes the base.
    pub fn load(config: &ModelConfig, lora: Option<&LoraConfig>, seed: u64, device: Device) -> Result<Self> {
        tch::manual_seed(seed as i64);
        let (transformer_config, vae_config) = config.model_configs(true)?;
        // The transformer checkpoint's headers are checked before its 5B variables are allocated.
        let transformer_dir = Path::new(&config.transformer);
        if transformer_dir.is_dir() {
            let found = weights::read_checkpoint_info(transformer_dir)?;
            weights::check_against(&transformer_config.variable_shapes()?, &found, transformer_dir)?;
        }
        let (mut vs, lora_vs, transformer) = Transformer::build(&transformer_config, lora, device, Kind::Float)?;
        if transformer_dir.is_dir() {
            transformer.load(&vs, transformer_dir)?;
        }
        if let Some(file) = &config.transformer_lora {
            LoraFile::read(file)?.merge_into(&vs, file)?;
        }
        if lora_vs.is_some() {
            vs.freeze();
        }
        let (mut vae_vs, vae) = Vae::build(&vae_config, device, Kind::Float)?;
        if Path::new(&config.vae).is_dir() {
            weights::load(&vae_vs, Path::new(&config.vae))?;
        }
        vae_vs.freeze();
        let text = crate::loaders::load_text_embedding(config.text_embedding.as_deref(), &transformer_config, device)?;
        let schedule = match transformer.family().objective() {
            Objective::VPrediction => {
                TrainingSchedule::Ddpm(Box::new(NoiseSchedule::new(&config.scheduler_config()?)?))
            }
            Objective::RectifiedFlow => TrainingSchedule::Flow(FlowSchedule::new(&config.flow_schedule_config()?)?),
        };
        Ok(Self {
            vs,
            transformer,
            vae_vs,
            vae,
            schedule,
            text,
            lora_vs,
            lora: lora.cloned(),
            kind: Kind::Float,
            encode_seconds: std::cell::Cell::new(0.0),
        })
    }

    /// Casts both models' weights to `kind` (fp32 as loaded; bf16 for mixed precision, after the
    /// optimizer has taken its master copies).
    pub fn set_kind(&mut self, kind: Kind) {
        self.vs.set_kind(kind);
        if let Some(lora_vs) = &mut self.lora_vs {
            lora_vs.set_kind(kind);
        }
        self.vae_vs.set_kind(kind);
        self.kind = kind;
    }

    /// The variables that train: the adapters in a LoRA run, else the whole transformer.
    pub fn trainable(&self) -> &nn::VarStore {
        self.lora_vs.as_ref().unwrap_or(&self.vs)
    }

    /// Element type of the models' weights.
    pub fn kind(&self) -> Kind {
        self.kind
    }

    /// Latents of a video batch `[B, 3, F, H, W]` as the transformer sees them (a posterior
    /// sample, scaled and laid out by the family: [`Vae::to_model_latent`]), fp32.
    pub fn encode(&self, video: &Tensor) -> Result<Tensor> {
        let latent = self.timed_encode(|| {
            tch::no_grad(|| -> Result<Tensor> {
                Ok(self.vae.encode_posterior(&video.f_to_kind(self.kind)?)?.sample()?.f_to_kind(Kind::Float)?)
            })
        })?;
        self.scale_latent(&latent)
    }

    /// Seconds of VAE encoding since the last call (synchronised with the device on CUDA, so
    /// they are the encode's own), and restarts the count.
    pub fn take_encode_seconds(&self) -> f64 {
        self.encode_seconds.replace(0.0)
    }

    fn timed_encode<T>(&self, encode: impl FnOnce() -> Result<T>) -> Result<T> {
        let synchronize = || {
            if let Device::Cuda(index) = self.text.device() {
                tch::Cuda::synchronize(index as i64);
            }
        };
        synchronize();
        let started = std::time::Instant::now();
        let out = encode();
        synchronize();
        self.encode_seconds.set(self.encode_seconds.get() + started.elapsed().as_secs_f64());
        out
    }

    /// [`Self::encode`] with the posterior's noise drawn by `pick` (for the global batch); for
    /// the conditioning (`condition`), the family's conditioning latent
    /// ([`Vae::condition_latent`]).
    fn encode_with(&self, video: &Tensor, pick: &Picker, condition: bool) -> Result<Tensor> {
        let latent = self.timed_encode(|| {
            tch::no_grad(|| -> Result<Tensor> {
                let posterior = self.vae.encode_posterior(&video.f_to_kind(self.kind)?)?;
                let eps = pick.randn(&posterior.mean.size(), posterior.mean.kind())?;
                let latent = if condition {
                    self.vae.condition_latent(&posterior, &eps)?
                } else {
                    let std = posterior.logvar.f_mul_scalar(0.5)?.f_exp()?;
                    posterior.mean.f_add(&std.f_mul(&eps)?)?
                };
                Ok(latent.f_to_kind(Kind::Float)?)
            })
        })?;
        self.scale_latent(&latent)
    }

    /// A VAE latent `[B, C, F', h, w]` as the transformer sees it ([`Vae::to_model_latent`]).
    pub(super) fn scale_latent(&self, latent: &Tensor) -> Result<Tensor> {
        self.vae.to_model_latent(latent)
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
        Ok(self.loss_graph(batch, noise_log_mean, noise_log_std, cache, None, Draws::SINGLE)?.0)
    }

    /// The loss of one batch, as [`loss`](Self::loss), back-propagated with the gradient divided
    /// by `divisor` (the micro-batches per step) block by block as `backward` says; returns the
    /// unscaled loss value. `condition_noise` is (mean, std) of log σ; `draws` says which
    /// samples of the global batch this process holds. A non-finite loss is not
    /// back-propagated, but `backward.on_stage` still sees every stage, so every rank starts
    /// the same collectives.
    pub fn loss_backward(
        &self,
        batch: &Batch,
        condition_noise: (f64, f64),
        cache: Option<&LatentCache>,
        divisor: f64,
        backward: Backward<'_>,
        draws: Draws,
    ) -> Result<f64> {
        let (noise_log_mean, noise_log_std) = condition_noise;
        let Backward { checkpointing, on_stage } = backward;
        let mut no_hook = |_: usize| -> Result<()> { Ok(()) };
        let on_stage: &mut dyn FnMut(usize) -> Result<()> = match on_stage {
            Some(hook) => hook,
            None => &mut no_hook,
        };
        let (loss, tape) = self.loss_graph(batch, noise_log_mean, noise_log_std, cache, Some(checkpointing), draws)?;
        let tape = tape.expect("a training graph has a tape");
        let value = loss.double_value(&[]);
        if value.is_finite() {
            loss.f_div_scalar(divisor)?.f_backward()?;
            tape.backward(on_stage)?;
        } else {
            for stage in 0..self.transformer.backward_stages() {
                on_stage(stage)?;
            }
        }
        Ok(value)
    }

    /// The loss and, for training (`taped`: with or without checkpointing), the transformer's
    /// tape for [`Tape::backward`]; without `taped` the plain forward's graph.
    fn loss_graph(
        &self,
        batch: &Batch,
        noise_log_mean: f64,
        noise_log_std: f64,
        cache: Option<&LatentCache>,
        taped: Option<bool>,
        draws: Draws,
    ) -> Result<(Tensor, Option<Tape<'_>>)> {
        let device = self.text.device();
        let b = batch.target.size()[0];
        let pick = draws.picker(b, device)?;
        let (x0, cond) = match cache {
            None => {
                let target = batch.target.f_to_device(device)?;
                let condition = batch.condition.f_to_device(device)?;
                let sigma = (pick.randn(&[b, 1, 1, 1, 1], Kind::Float)? * noise_log_std + noise_log_mean).f_exp()?;
                let noise = pick.randn(&condition.size(), condition.kind())?;
                let noisy_condition = condition.f_add(&noise.f_mul(&sigma)?)?;
                let x0 = self.encode_with(&target, &pick, false)?;
                let cond = self.encode_with(&noisy_condition, &pick, true)?;
                (x0, self.vae.condition_input(&cond, &batch.mask)?)
            }
            Some(cache) => {
                // Cache look-ups and fills draw from their own seeds; the step's generator state is
                // saved around them by reseeding with a draw taken before.
                let resume_seed = Tensor::f_randint(i64::MAX, [1], (Kind::Int64, Device::Cpu))?.int64_value(&[0]);
                let mut x0 = Vec::new();
                let mut cond = Vec::new();
                let mut posteriors = Vec::new();
                for i in 0..b {
                    let entry = cache.get_or_encode(&self.vae, device, batch, (i, noise_log_mean, noise_log_std))?;
                    posteriors.push(entry);
                }
                tch::manual_seed(resume_seed);
                // One posterior draw per sample of the global batch, in its order; this rank's
                // samples keep theirs.
                let (shape, posterior_device) =
                    posteriors.first().map(|(mean, _, _)| (mean.size(), mean.device())).expect("a batch has samples");
                let mut posteriors = posteriors.into_iter();
                for global in 0..b * draws.world {
                    let Some(local) = draws.local_index(global) else {
                        let _ = Tensor::f_randn(shape.as_slice(), (Kind::Float, posterior_device))?;
                        continue;
                    };
                    debug_assert_eq!(local, x0.len() as i64);
                    let (mean, logvar, condition) = posteriors.next().expect("one posterior per local sample");
                    let (mean, logvar) = (mean.f_to_kind(Kind::Float)?, logvar.f_to_kind(Kind::Float)?);
                    let std = logvar.f_mul_scalar(0.5)?.f_exp()?;
                    let sample = mean.f_add(&std.f_mul(&mean.f_randn_like()?)?)?;
                    x0.push(self.scale_latent(&sample)?);
                    cond.push(condition.f_to_kind(Kind::Float)?);
                }
                (Tensor::f_cat(&x0, 0)?, Tensor::f_cat(&cond, 0)?)
            }
        };
        let text = self.text.f_to_kind(self.kind)?.f_expand([b, -1, -1], false)?;
        match &self.schedule {
            TrainingSchedule::Ddpm(schedule) => {
                let steps = schedule.alphas_cumprod().len() as i64;
                let t = pick.randint(steps, b)?;
                let noise = pick.randn(&x0.size(), x0.kind())?;
                let xt = schedule.add_noise(&x0, &noise, &t)?;
                let (v, tape) = self.predict(&xt, &cond, &text, &t, taped)?;
                let alphas: Vec<f64> =
                    (0..b).map(|i| schedule.alpha_cumprod_at(t.int64_value(&[i]))).collect::<Result<_>>()?;
                let per_sample = |f: fn(f64) -> f64| -> Result<Tensor> {
                    let values: Vec<f32> = alphas.iter().map(|&a| f(a) as f32).collect();
                    Ok(Tensor::from_slice(&values).f_view([b, 1, 1, 1, 1])?.f_to_device(device)?)
                };
                let sqrt_alpha = per_sample(f64::sqrt)?;
                let sqrt_one_minus = per_sample(|a| (1.0 - a).sqrt())?;
                let weight = per_sample(|a| 1.0 / (1.0 - a).max(1e-12))?;
                let x0_hat = xt.f_mul(&sqrt_alpha)?.f_sub(&v.f_mul(&sqrt_one_minus)?)?;
                Ok((x0_hat.f_sub(&x0)?.f_square()?.f_mul(&weight)?.f_mean(Kind::Float)?, tape))
            }
            TrainingSchedule::Flow(schedule) => {
                let u = pick.rand(b)?;
                let noise = pick.randn(&x0.size(), x0.kind())?;
                flow_matching_loss(self, schedule, (&x0, &cond, &text), &u, &noise, taped)
            }
        }
    }

    /// The transformer's prediction (fp32) for noisy latents, the condition channels, text and
    /// timesteps, in the models' element type.
    fn predict(
        &self,
        latents: &Tensor,
        condition: &Tensor,
        text: &Tensor,
        timestep: &Tensor,
        taped: Option<bool>,
    ) -> Result<(Tensor, Option<Tape<'_>>)> {
        let (latents, condition) = (latents.f_to_kind(self.kind)?, condition.f_to_kind(self.kind)?);
        let input = ModelInput { latents: &latents, condition: &condition, text, timestep };
        let (out, tape) = self.transformer.forward_taped(&input, true, taped)?;
        Ok((out.f_to_kind(Kind::Float)?, tape))
    }
}

/// The rectified-flow loss of clean latents `x0` with the condition channels and text (in the
/// model's layout), for uniform draws `u` `[B]` and `noise` like `x0`: σ and the timestep from
/// [`FlowSchedule::draw`], `x_σ` and the target from [`flow_noisy_and_target`], and
/// `mean((v̂ − (noise − x0))²)` (finetrainers' uniform loss weighting; every sample has the same
/// size, so its per-sample means averaged are this mean).
pub fn flow_matching_loss<'a>(
    model: &'a CogNvsModel,
    schedule: &FlowSchedule,
    (x0, condition, text): (&Tensor, &Tensor, &Tensor),
    u: &Tensor,
    noise: &Tensor,
    taped: Option<bool>,
) -> Result<(Tensor, Option<Tape<'a>>)> {
    let (sigmas, timesteps) = schedule.draw(u)?;
    let (noisy, target) = flow_noisy_and_target(x0, noise, &sigmas)?;
    let (v, tape) = model.predict(&noisy, condition, text, &timesteps, taped)?;
    Ok((v.f_sub(&target)?.f_square()?.f_mean(Kind::Float)?, tape))
}

/// How [`CogNvsModel::loss_backward`] runs the transformer's backward: block by block where the
/// family has a tape ([`Tape`]), reporting each finished stage.
pub struct Backward<'a> {
    /// Keep only each block's input and recompute the blocks during the backward (gradient
    /// checkpointing): the same gradients for a fraction of the activation memory.
    pub checkpointing: bool,
    /// Called with each stage of the backward once the gradients of its parameters are final
    /// ([`Transformer::backward_stage_of`]), in order; a data-parallel step
    /// starts reducing them there.
    pub on_stage: Option<&'a mut dyn FnMut(usize) -> Result<()>>,
}

/// Which samples of the step's global batch this process computes: with `world` ranks of `b`
/// samples each, rank r holds global samples `k·world + r` (the data loader's interleaving).
/// Every random draw of the objective is made for the whole global batch, in the order a single
/// process makes it, and each rank keeps its samples' values: a run's draws, and so its losses
/// and gradients, do not depend on the world size. With one rank this is exactly the
/// single-process draw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Draws {
    /// This rank.
    pub rank: i64,
    /// Number of ranks.
    pub world: i64,
}

impl Draws {
    /// One process.
    pub const SINGLE: Self = Self { rank: 0, world: 1 };

    /// The local index of global sample `global`, when this rank holds it.
    fn local_index(&self, global: i64) -> Option<i64> {
        (global % self.world == self.rank).then_some(global / self.world)
    }

    fn picker(self, b: i64, device: Device) -> Result<Picker> {
        let index = if self.world == 1 {
            None
        } else {
            let rows: Vec<i64> = (0..b).map(|k| k * self.world + self.rank).collect();
            Some(Tensor::from_slice(&rows).f_to_device(device)?)
        };
        Ok(Picker { world: self.world, device, index })
    }
}

/// Draws for the global batch, keeping this rank's rows.
struct Picker {
    world: i64,
    device: Device,
    index: Option<Tensor>,
}

impl Picker {
    fn keep(&self, global: Tensor) -> Result<Tensor> {
        Ok(match &self.index {
            None => global,
            Some(index) => global.f_index_select(0, index)?,
        })
    }

    fn global(&self, local: &[i64]) -> Vec<i64> {
        let mut shape = local.to_vec();
        shape[0] *= self.world;
        shape
    }

    /// Standard normal values of `local` shape (batch first).
    fn randn(&self, local: &[i64], kind: Kind) -> Result<Tensor> {
        self.keep(Tensor::f_randn(self.global(local).as_slice(), (kind, self.device))?)
    }

    /// Uniform values in [0, 1), one per local sample.
    fn rand(&self, b: i64) -> Result<Tensor> {
        self.keep(Tensor::f_rand([b * self.world], (Kind::Float, self.device))?)
    }

    /// Integers in `0..high`, one per local sample.
    fn randint(&self, high: i64, b: i64) -> Result<Tensor> {
        self.keep(Tensor::f_randint(high, [b * self.world], (Kind::Int64, self.device))?)
    }
}

/// The seed of tch's generator for step `step` of a run seeded `seed` (also the validation
/// pairs' sampling seeds, with `step` their index).
pub(super) fn step_seed(seed: u64, step: u64) -> i64 {
    let mut hasher = blake3::Hasher::new();
    hasher.update(b"cognvs train step v1");
    hasher.update(&seed.to_le_bytes());
    hasher.update(&step.to_le_bytes());
    let bytes = hasher.finalize();
    i64::from_le_bytes(bytes.as_bytes()[..8].try_into().expect("8 bytes")) & i64::MAX
}

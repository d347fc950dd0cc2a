//! The `trainer pretrain --config` TOML: models, data, optimizer and loop settings, with their
//! defaults (the paper's and the public CogNVS code's) and the checks run when a file is read.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::diffusers_config;
use crate::error::{Error, Result};
use crate::models::backbone::{TransformerConfig, VaeConfig};
use crate::models::cogvideox::autoencoder_kl_cogvideox::AutoencoderKLCogVideoXConfig;
use crate::models::cogvideox::cogvideox_transformer_3d::CogVideoXTransformer3DModelConfig;
use crate::models::family::{Job, ModelFamily, Objective};
use crate::models::wan::autoencoder_kl_wan::AutoencoderKLWanConfig;
use crate::schedulers::scheduling_flow_match_euler_discrete::FlowMatchEulerDiscreteSchedulerConfig;

/// The static flow shift a Wan run trains with when no scheduler is configured: diffusers' Wan
/// documentation's setting for 480p (`flow_shift = 3.0`; 5.0 for 720p), the clip size Wan runs
/// default to.
pub const WAN_FLOW_SHIFT: f64 = 3.0;
use crate::models::lora::LoraConfig;
use crate::models::wan::transformer_wan::WanTransformer3DModelConfig;
pub use crate::precision::Precision;
use crate::training::data::DataConfig;

/// Which models to train and with what.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelConfig {
    /// Transformer: a preset (CogVideoX: `tiny`, `cognvs-5b`, `cogvideox-2b`; Wan:
    /// `tiny-cognvs`, `wan2.1-t2v-1.3b`, …) or a `config.json` file, both random init, or a
    /// diffusers model folder (config.json + weights) to start from; the family is the config's
    /// `_class_name`'s. Valid: a preset name or an existing file/folder; `in_channels` the VAE's
    /// `latent_channels` plus the conditioning's channels, `out_channels` the `latent_channels`.
    pub transformer: String,
    /// VAE: a preset (`tiny` random init with `seed`, `cogvideox-5b`; Wan: `tiny-wan`,
    /// `wan2.1`) or a diffusers model folder, of the transformer's family.
    /// Valid: a preset name or an existing folder.
    pub vae: String,
    /// Optional safetensors file with `encoder_hidden_states` `[S, D]`: the empty prompt's text
    /// embedding (`scripts/encode_prompt.py` makes it). Zeros when unset, which a transformer of
    /// the released models' T5-XXL text shape (226 × 4096) refuses unless `zero_text_embedding`.
    /// Valid: an existing file (its shape is checked at load).
    #[serde(default)]
    pub text_embedding: Option<PathBuf>,
    /// Train with zeros as the text embedding even where the transformer takes T5-XXL text (it
    /// then sees text tokens it never saw in pretraining). Valid: any.
    #[serde(default)]
    pub zero_text_embedding: bool,
    /// Optional diffusers scheduler folder (or its `scheduler_config.json`) whose noise schedule
    /// training uses; CogVideoX-5B's when unset. A Wan run reads a flow-matching scheduler
    /// (`FlowMatchEulerDiscreteScheduler`, or `UniPCMultistepScheduler`'s `flow_shift`); unset,
    /// the shift is [`WAN_FLOW_SHIFT`]. Valid: an existing folder or file.
    #[serde(default)]
    pub scheduler: Option<PathBuf>,
    /// Optional LoRA file (`pytorch_lora_weights.safetensors`, ours or another diffusers/peft
    /// trainer's) merged into the transformer's weights once they are loaded: training starts
    /// from base + adapter. Valid: an existing file whose adapters fit the transformer (checked
    /// at load, naming the key and both shapes).
    #[serde(default)]
    pub transformer_lora: Option<PathBuf>,
}

/// AdamW and its schedule (paper: lr 2e-5, β = (0.9, 0.95)).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OptimConfig {
    /// Peak learning rate. Valid: finite, in (0, 1].
    pub lr: f64,
    /// First-moment decay. Valid: [0, 1).
    pub beta1: f64,
    /// Second-moment decay. Valid: [0, 1).
    pub beta2: f64,
    /// Decoupled weight decay. Valid: finite, in [0, 1].
    pub weight_decay: f64,
    /// Denominator epsilon. Valid: finite, > 0.
    pub eps: f64,
    /// Linear warm-up steps from 0 to `lr`. Valid: any (0: none).
    pub warmup_steps: u64,
    /// After warm-up: `constant` or `cosine` (to 0 at the last step). Valid: those two.
    pub schedule: String,
    /// Gradient-norm clip (0: none). Valid: finite, ≥ 0.
    pub max_grad_norm: f64,
    /// Micro-batches accumulated per optimizer step. Valid: ≥ 1.
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
    /// Optimizer steps in all (a resumed run continues up to this). Valid: ≥ 1.
    pub steps: u64,
    /// Seed of model init and of every per-step draw. Valid: any.
    pub seed: u64,
    /// How often a checkpoint is written (and one at the end): every N optimizer steps
    /// (`checkpoint_every = 500`) or every so many minutes of the run (`checkpoint_every =
    /// "30min"`, timed on rank 0 from the last checkpoint or the start, and written after the
    /// step that crosses it). Valid: ≥ 1 step, or a finite number of minutes > 0.
    pub checkpoint_every: CheckpointEvery,
    /// Checkpoints kept: the newest this many intact ones (damaged ones never count).
    /// Valid: ≥ 1.
    pub keep_last: usize,
    /// Signals that preempt the run: the step in progress finishes, a checkpoint is written and
    /// the process exits with status 75 (see `trainer::training::preempt`). Valid: names among
    /// `SIGTERM`, `SIGUSR1`, `SIGUSR2`, `SIGINT`, `SIGHUP`; empty: none (the signals' default
    /// actions).
    pub preempt_signals: Vec<String>,
    /// Seconds after a preemption signal after which the process ends at once, without
    /// finishing its checkpoint, whatever it is doing (keep it below the time the scheduler
    /// leaves before SIGKILL, so the job script still gets to requeue). Valid: finite, ≥ 0
    /// (0: no deadline).
    pub preempt_grace_seconds: f64,
    /// Mean of log σ of the condition noise augmentation. Valid: finite, in
    /// [−[`MAX_ABS_LOG_SIGMA`], [`MAX_ABS_LOG_SIGMA`]].
    pub condition_noise_log_mean: f64,
    /// Standard deviation of log σ. Valid: finite, in [0, [`MAX_ABS_LOG_SIGMA`]].
    pub condition_noise_log_std: f64,
    /// Steps between validations (0: none). With a `[validation]` section, its held-out pairs
    /// are sampled and measured (see [`ValidationConfig`]); without one, only the first training
    /// pair is sampled. Either way the first pair's sample goes to `RUN/samples/step-N/`
    /// (`sample.mp4`, `contact_sheet.png` with target | conditioning | sample rows). Valid: any.
    pub validate_every: u64,
    /// Denoising steps of a validation sample. Valid: 1 to the scheduler's 1000 training
    /// timesteps.
    pub validation_steps: usize,
    /// A folder caching VAE latents per pair (see [`LatentCache`]); none when unset.
    /// Valid: any path (created when missing).
    pub latent_cache: Option<PathBuf>,
    /// Arithmetic of the transformer and the VAE. Valid: `auto`, `fp32`, `bf16`.
    pub precision: Precision,
    /// Activation checkpointing per transformer block: the forward keeps only each block's
    /// input and the backward recomputes one block at a time, so activation memory is one
    /// block's instead of all of them, for about one more forward of compute. Same gradients.
    pub gradient_checkpointing: bool,
    /// Write model files: the run's VAE and LoRA base copies and the checkpoints. `false` is for
    /// measurement runs (`scripts/gpu_check.sh`, benchmarks): nothing but `config.json` and the
    /// metrics is written, so a 5B run needs no disk for its 20–70 GB of weights. Valid: any.
    pub save_checkpoints: bool,
}

impl Default for LoopConfig {
    fn default() -> Self {
        Self {
            steps: 12_000,
            seed: 0,
            checkpoint_every: CheckpointEvery::Steps(500),
            keep_last: 3,
            preempt_signals: vec!["SIGTERM".to_string(), "SIGUSR1".to_string()],
            preempt_grace_seconds: 0.0,
            condition_noise_log_mean: -3.0,
            condition_noise_log_std: 0.5,
            validate_every: 0,
            validation_steps: 20,
            latent_cache: None,
            precision: Precision::Auto,
            gradient_checkpointing: false,
            save_checkpoints: true,
        }
    }
}

/// How often checkpoints are written: `checkpoint_every = 500` (steps) or `"30min"` (minutes).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CheckpointEvery {
    /// Every this many optimizer steps.
    Steps(u64),
    /// After the first step that ends this many minutes after the last checkpoint (or the start).
    Minutes(f64),
}

impl CheckpointEvery {
    /// Parses `"30min"`, `"30 min"`, `"1.5 minutes"` (minutes) or `"500"` (steps).
    pub fn parse(text: &str) -> Option<Self> {
        let text = text.trim();
        if let Ok(steps) = text.parse::<u64>() {
            return Some(Self::Steps(steps));
        }
        let number = ["minutes", "minute", "min"].iter().find_map(|unit| text.strip_suffix(unit))?;
        number.trim().parse::<f64>().ok().map(Self::Minutes)
    }
}

impl Serialize for CheckpointEvery {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> std::result::Result<S::Ok, S::Error> {
        match self {
            Self::Steps(steps) => serializer.serialize_u64(*steps),
            Self::Minutes(minutes) => serializer.serialize_str(&format!("{minutes}min")),
        }
    }
}

impl<'de> Deserialize<'de> for CheckpointEvery {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> std::result::Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Written {
            Steps(u64),
            Text(String),
        }
        match Written::deserialize(deserializer)? {
            Written::Steps(steps) => Ok(Self::Steps(steps)),
            Written::Text(text) => Self::parse(&text).ok_or_else(|| {
                serde::de::Error::custom(format!(
                    "`{text}` is neither a number of steps (500) nor of minutes (\"30min\")"
                ))
            }),
        }
    }
}

/// `[validation]`: held-out pairs sampled and measured every `[loop] validate_every` steps.
/// The set is fixed for the run: up to `pairs` held-out clips, each with its trajectory and
/// window drawn from `seed` and its sampling noise from `seed` and its index, so values at
/// different steps compare the model alone. PSNR and SSIM (and LPIPS with `lpips_weights`),
/// over whole frames and over the co-visible pixels, go to `metrics.jsonl` and TensorBoard.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ValidationConfig {
    /// Shard folders of held-out pairs (never trained on). Valid: folders of finished shards.
    pub shards: Vec<PathBuf>,
    /// Fraction of the training shards' videos held out, with all their clips, and never trained
    /// on (a hash of `{dataset}/{source_id}`, so the same videos whatever the seed, the shard order
    /// or the world size).
    /// Valid: in [0, 1); at least one of `shards` and `holdout_fraction` given.
    pub holdout_fraction: f64,
    /// Held-out pairs sampled at each validation (fewer when fewer clips are held out); with
    /// several ranks each samples its share. Valid: 1 to [`MAX_VALIDATION_PAIRS`].
    pub pairs: usize,
    /// Seed of the pairs' trajectories, windows and sampling noise. Valid: any.
    pub seed: u64,
    /// LPIPS weights (`scripts/convert_eval_weights.py lpips`): adds LPIPS and LPIPS over the
    /// co-visible pixels. Valid: an existing file (its tensors are checked at the start).
    pub lpips_weights: Option<PathBuf>,
    /// LPIPS backbone. Valid: `alex` or `vgg`.
    pub lpips_net: crate::eval::lpips::LpipsNet,
}

impl Default for ValidationConfig {
    fn default() -> Self {
        Self {
            shards: Vec::new(),
            holdout_fraction: 0.0,
            pairs: 8,
            seed: 0,
            lpips_weights: None,
            lpips_net: crate::eval::lpips::LpipsNet::Alex,
        }
    }
}

/// Most validation pairs: each is a full sampling run of `[loop] validation_steps` steps.
pub const MAX_VALIDATION_PAIRS: usize = 4096;

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
    /// LoRA adapters: when the section is present, only adapters on the targeted linear layers
    /// of the transformer train (the base stays frozen) and checkpoints hold
    /// `pytorch_lora_weights.safetensors` instead of `transformer/`.
    #[serde(default)]
    pub lora: Option<LoraConfig>,
    /// Multi-process training (ignored at world size 1).
    #[serde(default)]
    pub distributed: DistributedConfig,
    /// Held-out validation (none when the section is absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub validation: Option<ValidationConfig>,
    /// The file the config was read from, for messages (not a key of the file).
    #[serde(skip)]
    pub source: ConfigSource,
}

/// Where a config was read from, named by the errors of checks made after loading (the
/// held-out split against the data, the batch against the world size). Not part of the
/// config's value: two configs with the same settings are equal wherever they came from.
#[derive(Debug, Clone, Default)]
pub struct ConfigSource(pub Option<String>);

impl PartialEq for ConfigSource {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

/// How errors name a config built in code rather than read from a file.
const UNNAMED_CONFIG: &str = "training config";

/// The collectives' timeout of the run `config` names (its `[distributed] timeout_seconds`), or
/// the default without one: what joining a job needs before the rest of the config is read.
pub fn timeout_seconds(config: Option<&Path>) -> Result<f64> {
    Ok(match config {
        Some(path) => PretrainConfig::from_toml_file(path)?.distributed.timeout_seconds,
        None => DistributedConfig::default().timeout_seconds,
    })
}

/// `[distributed]`: how ranks share the work when the launcher starts several processes
/// (torchrun, Slurm `srun`, or RANK/WORLD_SIZE by hand; see `trainer::distributed`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DistributedConfig {
    /// 0: plain data parallel (every rank keeps all gradients and optimizer state); 2: ZeRO-2
    /// (each rank keeps the reduced gradients and the AdamW moments and master weights of its
    /// 1/N of the parameters only, and the updated weights are all-gathered). Same results.
    /// Valid: 0 or 2.
    pub zero_stage: u8,
    /// Seconds any collective may wait for the other ranks before the job fails naming the
    /// collective and the ranks that did not arrive. Valid: finite, > 0.
    pub timeout_seconds: f64,
    /// Gradient bucket size in MiB: gradients are flattened into buckets of about this size and
    /// each bucket is reduced in one collective (PyTorch DDP's default is 25). Valid: finite, > 0.
    pub bucket_mib: f64,
    /// Benchmarking only: the gradient and weight collectives of each step become local no-ops
    /// (each rank keeps its own gradient sums and its own weights; everything computed around
    /// them is unchanged), so a run's step time without communication can be set against the
    /// real one (`trainer comm-cost`). The ranks' weights drift apart: never for training. The
    /// loss and gradient-norm sums stay real collectives.
    pub noop_collectives: bool,
}

impl Default for DistributedConfig {
    fn default() -> Self {
        Self { zero_stage: 0, timeout_seconds: 300.0, bucket_mib: 25.0, noop_collectives: false }
    }
}

/// Largest |log σ| of the condition noise augmentation: σ = e^±30 is already far outside any
/// useful noise level for videos in [−1, 1] (the paper uses log σ ~ N(−3, 0.5)), and larger
/// values overflow to 0 or inf in fp32.
pub const MAX_ABS_LOG_SIGMA: f64 = 30.0;
/// Largest peak learning rate accepted: AdamW steps are ~`lr` per parameter, so above 1 every
/// weight jumps by more than its own scale in one step (the paper uses 2e-5).
pub const MAX_LR: f64 = 1.0;

impl PretrainConfig {
    /// Reads and checks a TOML config (see [`Self::validate`]). Errors name the file and the key
    /// as written in it (`optim.lr`, `data.height`), with the value or the parser's complaint.
    pub fn from_toml_file(path: &Path) -> Result<Self> {
        let text =
            std::fs::read_to_string(path).map_err(|source| Error::Io { path: path.to_path_buf(), error: source })?;
        let source_name = path.display().to_string();
        let mut config: Self = toml::from_str(&text).map_err(|e| toml_error(&text, &source_name, &e))?;
        config.validate(&source_name)?;
        config.source = ConfigSource(Some(source_name));
        Ok(config)
    }

    /// The file the config was read from, or "training config" for one built in code.
    pub fn source_name(&self) -> String {
        self.source.0.clone().unwrap_or_else(|| UNNAMED_CONFIG.to_string())
    }

    /// Checks every field against its documented range and the combinations the models need
    /// (frames, height and width multiples of the VAE's compression and the transformer's patch,
    /// the learned positional table's size, latent channels), resolving the model configs
    /// (presets or `config.json` files; no weights are read). `source_name` names the config in
    /// errors; fields are named as in the TOML (`loop.steps`). Called by
    /// [`Self::from_toml_file`] and by [`super::pretrain`] before anything is written.
    pub fn validate(&self, source_name: &str) -> Result<()> {
        let bad = |field: &str, reason: String| Error::InvalidConfig {
            source_name: source_name.to_string(),
            field: field.to_string(),
            reason,
        };
        if let Some(lora) = &self.lora {
            lora.validate(source_name)?;
        }
        self.model.validate(source_name)?;
        let o = &self.optim;
        if !(o.lr.is_finite() && o.lr > 0.0 && o.lr <= MAX_LR) {
            return Err(bad("optim.lr", format!("{} must be finite and in (0, {MAX_LR}]", o.lr)));
        }
        for (field, value) in [("optim.beta1", o.beta1), ("optim.beta2", o.beta2)] {
            if !(0.0..1.0).contains(&value) {
                return Err(bad(field, format!("{value} must be in [0, 1)")));
            }
        }
        if !(o.eps.is_finite() && o.eps > 0.0) {
            return Err(bad("optim.eps", format!("{} must be finite and > 0", o.eps)));
        }
        if !(0.0..=1.0).contains(&o.weight_decay) {
            return Err(bad("optim.weight_decay", format!("{} must be in [0, 1]", o.weight_decay)));
        }
        if !["constant", "cosine"].contains(&o.schedule.as_str()) {
            return Err(bad("optim.schedule", format!("`{}` must be `constant` or `cosine`", o.schedule)));
        }
        if !(o.max_grad_norm.is_finite() && o.max_grad_norm >= 0.0) {
            return Err(bad(
                "optim.max_grad_norm",
                format!("{} must be finite and ≥ 0 (0: no clipping)", o.max_grad_norm),
            ));
        }
        let t = &self.train;
        for (field, value) in [
            ("optim.grad_accumulation", o.grad_accumulation),
            ("loop.steps", t.steps),
            ("loop.keep_last", t.keep_last as u64),
        ] {
            if value == 0 {
                return Err(bad(field, "0 must be ≥ 1".to_string()));
            }
        }
        match t.checkpoint_every {
            CheckpointEvery::Steps(0) => return Err(bad("loop.checkpoint_every", "0 steps must be ≥ 1".to_string())),
            CheckpointEvery::Minutes(m) if !(m.is_finite() && m > 0.0) => {
                return Err(bad("loop.checkpoint_every", format!("{m} minutes must be finite and > 0")));
            }
            _ => {}
        }
        for name in &t.preempt_signals {
            if super::preempt::signal_number(name).is_none() {
                let known: Vec<&str> = super::preempt::SIGNALS.iter().map(|(n, _)| *n).collect();
                return Err(bad("loop.preempt_signals", format!("`{name}` is not one of {}", known.join(", "))));
            }
        }
        if !(t.preempt_grace_seconds.is_finite() && t.preempt_grace_seconds >= 0.0) {
            return Err(bad(
                "loop.preempt_grace_seconds",
                format!("{} must be finite and ≥ 0 (0: no deadline)", t.preempt_grace_seconds),
            ));
        }
        if let Some(v) = &self.validation {
            if !(0.0..1.0).contains(&v.holdout_fraction) {
                return Err(bad("validation.holdout_fraction", format!("{} must be in [0, 1)", v.holdout_fraction)));
            }
            if v.shards.is_empty() && v.holdout_fraction == 0.0 {
                return Err(bad(
                    "validation",
                    "give held-out `shards`, a `holdout_fraction` of the training clips, or both".to_string(),
                ));
            }
            if !(1..=MAX_VALIDATION_PAIRS).contains(&v.pairs) {
                return Err(bad("validation.pairs", format!("{} must be in 1..={MAX_VALIDATION_PAIRS}", v.pairs)));
            }
            if let Some(path) = v.lpips_weights.as_ref().filter(|p| !p.is_file()) {
                return Err(bad("validation.lpips_weights", format!("{} is not a file", path.display())));
            }
        }
        if !(t.condition_noise_log_mean.is_finite() && t.condition_noise_log_mean.abs() <= MAX_ABS_LOG_SIGMA) {
            return Err(bad(
                "loop.condition_noise_log_mean",
                format!(
                    "{} must be finite and in [-{MAX_ABS_LOG_SIGMA}, {MAX_ABS_LOG_SIGMA}]",
                    t.condition_noise_log_mean
                ),
            ));
        }
        if !(0.0..=MAX_ABS_LOG_SIGMA).contains(&t.condition_noise_log_std) {
            return Err(bad(
                "loop.condition_noise_log_std",
                format!("{} must be in [0, {MAX_ABS_LOG_SIGMA}]", t.condition_noise_log_std),
            ));
        }
        let timesteps = crate::schedulers::CogVideoXSchedulerConfig::cogvideox_5b().num_train_timesteps;
        if t.validation_steps == 0 || t.validation_steps as i64 > timesteps {
            return Err(bad(
                "loop.validation_steps",
                format!("{} must be in 1..={timesteps} (the scheduler's training timesteps)", t.validation_steps),
            ));
        }
        let d = &self.distributed;
        if ![0, 2].contains(&d.zero_stage) {
            return Err(bad("distributed.zero_stage", format!("{} must be 0 or 2", d.zero_stage)));
        }
        for (field, value) in
            [("distributed.timeout_seconds", d.timeout_seconds), ("distributed.bucket_mib", d.bucket_mib)]
        {
            if !(value.is_finite() && value > 0.0) {
                return Err(bad(field, format!("{value} must be finite and > 0")));
            }
        }
        self.data.validate(source_name)?;
        self.check_models(source_name)
    }

    /// The data sizes and channel counts against the models they feed.
    fn check_models(&self, source_name: &str) -> Result<()> {
        let bad = |field: &str, reason: String| Error::InvalidConfig {
            source_name: source_name.to_string(),
            field: field.to_string(),
            reason,
        };
        let (transformer, vae) = self.model.model_configs(false)?;
        // The scheduler's file too: its ranges are checked as it is read. And the text embedding
        // (small: its shape against the transformer, every value finite), so that a bad one
        // stops the run before its folder is written.
        match transformer.family().objective() {
            Objective::VPrediction => drop(self.model.scheduler_config()?),
            Objective::RectifiedFlow => drop(self.model.flow_schedule_config()?),
        }
        if let Some(path) = &self.model.text_embedding {
            let _ = crate::loaders::load_text_embedding(Some(path), &transformer, tch::Device::Cpu)?;
        }
        if let Some(lora) = &self.lora {
            // Targets and rank against the transformer's layers, before any run folder exists.
            transformer.check_lora(lora).map_err(|e| match e {
                Error::InvalidConfig { field, reason, .. } => {
                    Error::InvalidConfig { source_name: source_name.to_string(), field, reason }
                }
                other => other,
            })?;
        }
        if transformer.family() != ModelFamily::CogVideoX && self.train.validate_every > 0 {
            return Err(bad(
                "loop.validate_every",
                format!(
                    "validation samples CogVideoX models only so far; set it to 0 for a {} run",
                    transformer.family().name()
                ),
            ));
        }
        let d = &self.data;
        let temporal = vae.temporal_factor() as usize;
        if !(d.frames - 1).is_multiple_of(temporal) {
            return Err(bad(
                "data.frames",
                format!(
                    "{} must be {temporal}k + 1 (the VAE compresses time by {temporal} after the first frame)",
                    d.frames
                ),
            ));
        }
        let spatial = vae.spatial_factor();
        let [patch, _] = transformer.spatial_patch();
        let multiple = spatial * patch;
        for (field, value) in [("data.height", d.height), ("data.width", d.width)] {
            if i64::from(value) % multiple != 0 {
                return Err(bad(
                    field,
                    format!(
                        "{value} must be a multiple of {multiple} (the VAE's {spatial}x spatial compression \
                         times the transformer's patch size {patch})"
                    ),
                ));
            }
        }
        if let TransformerConfig::CogVideoX(transformer) = &transformer {
            for (field, value, sample) in [
                ("data.height", d.height, transformer.sample_height),
                ("data.width", d.width, transformer.sample_width),
            ] {
                if transformer.use_learned_positional_embeddings && i64::from(value) != sample * spatial {
                    return Err(bad(
                        field,
                        format!(
                            "{value} must be {} pixels: the transformer's learned positional table covers {sample} \
                             latents of {spatial} pixels",
                            sample * spatial
                        ),
                    ));
                }
            }
        }
        let (latent, condition) = (vae.latent_channels(), vae.condition_channels());
        if transformer.in_channels() != latent + condition {
            return Err(bad(
                "model.transformer",
                format!(
                    "in_channels {} must be the VAE's latent_channels {latent} plus the {condition} channels of \
                     the conditioning (noisy latents, then the condition)",
                    transformer.in_channels()
                ),
            ));
        }
        if transformer.output_channels() != latent {
            return Err(bad(
                "model.transformer",
                format!("out_channels {} must equal the VAE's latent_channels {latent}", transformer.output_channels()),
            ));
        }
        Ok(())
    }
}

impl ModelConfig {
    /// The transformer's and the VAE's configs: presets, or read from their `config.json` (no
    /// weights are read). Errors name the preset or file; with `warn`, the files' warnings
    /// (unknown keys, inconsistent values) go to stderr.
    pub fn model_configs(&self, warn: bool) -> Result<(TransformerConfig, VaeConfig)> {
        let mut warnings = Vec::new();
        let transformer = match Path::new(&self.transformer) {
            p if p.is_dir() || p.is_file() => {
                let (config, w) = TransformerConfig::read_quiet(p)?;
                config.family().require(Job::Training, p)?;
                warnings.extend(w);
                config
            }
            _ => TransformerConfig::preset(&self.transformer)?,
        };
        let vae = match Path::new(&self.vae) {
            p if p.is_dir() => {
                let (config, w) = VaeConfig::read_quiet(p)?;
                config.family().require(Job::Training, p)?;
                warnings.extend(w);
                config
            }
            _ => VaeConfig::preset_of(transformer.family(), &self.vae)?,
        };
        if transformer.family() != vae.family() {
            return Err(Error::InvalidConfig {
                source_name: self.vae.clone(),
                field: "_class_name".to_string(),
                reason: format!(
                    "is a {} VAE but the transformer {} is a {} model: both must be of one family",
                    vae.family().name(),
                    self.transformer,
                    transformer.family().name()
                ),
            });
        }
        if warn {
            for warning in warnings {
                eprintln!("warning: {warning}");
            }
        }
        Ok((transformer, vae))
    }

    /// The Wan transformer's and VAE's configs when `transformer` names a Wan model (a Wan preset
    /// such as `wan2.1-t2v-1.3b`, or a config file or folder whose `_class_name` is Wan's), else
    /// None. `vae` must then be a Wan VAE: a preset (`wan2.1`, `wan2.2`) or a folder.
    pub fn wan_configs(&self) -> Result<Option<(WanTransformer3DModelConfig, AutoencoderKLWanConfig)>> {
        Ok(match self.model_configs(false)? {
            (TransformerConfig::Wan(transformer), VaeConfig::Wan(vae)) => Some((transformer, vae)),
            _ => None,
        })
    }

    /// [`Self::model_configs`] for the jobs that run CogVideoX only so far (the memory plan):
    /// a Wan model is refused by name.
    pub fn configs(&self, warn: bool) -> Result<(CogVideoXTransformer3DModelConfig, AutoencoderKLCogVideoXConfig)> {
        match self.model_configs(warn)? {
            (TransformerConfig::CogVideoX(transformer), VaeConfig::CogVideoX(vae)) => Ok((transformer, vae)),
            (transformer, _) => Err(Error::InvalidConfig {
                source_name: self.transformer.clone(),
                field: "_class_name".to_string(),
                reason: format!(
                    "is a {} model; this job runs CogVideoX models only so far",
                    transformer.family().name()
                ),
            }),
        }
    }

    /// The rectified-flow training schedule of a Wan run: the `scheduler` folder's (a
    /// `FlowMatchEulerDiscreteScheduler` config, or Wan's `UniPCMultistepScheduler` whose
    /// `flow_shift` it takes), else diffusers' defaults with [`WAN_FLOW_SHIFT`].
    pub fn flow_schedule_config(&self) -> Result<FlowMatchEulerDiscreteSchedulerConfig> {
        use crate::diffusers_config::DiffusersConfig;
        use crate::schedulers::scheduling_unipc_multistep as unipc;
        let Some(path) = &self.scheduler else {
            return Ok(FlowMatchEulerDiscreteSchedulerConfig { shift: WAN_FLOW_SHIFT, ..Default::default() });
        };
        match diffusers_config::class_name(path, "scheduler_config.json")?.as_deref() {
            Some(unipc::CLASS_NAME) => {
                let unipc: unipc::UniPCMultistepSchedulerConfig = diffusers_config::read(path)?;
                Ok(FlowMatchEulerDiscreteSchedulerConfig {
                    num_train_timesteps: unipc.num_train_timesteps,
                    shift: unipc.flow_shift,
                    ..Default::default()
                })
            }
            _ => FlowMatchEulerDiscreteSchedulerConfig::from_json_file(path),
        }
    }

    fn validate(&self, source_name: &str) -> Result<()> {
        let bad = |field: &str, reason: String| Error::InvalidConfig {
            source_name: source_name.to_string(),
            field: field.to_string(),
            reason,
        };
        let transformer = Path::new(&self.transformer);
        if !(transformer.is_dir() || transformer.is_file())
            && let Err(e) = TransformerConfig::preset(&self.transformer)
        {
            return Err(bad("model.transformer", format!("neither a config file, a model folder nor a preset: {e}")));
        }
        if !Path::new(&self.vae).is_dir()
            && let Err(e) = VaeConfig::preset(&self.vae)
        {
            return Err(bad("model.vae", format!("neither a model folder nor a preset: {e}")));
        }
        if let Some(path) = &self.text_embedding
            && !path.is_file()
        {
            return Err(bad("model.text_embedding", format!("{} is not a file", path.display())));
        }
        if let Some(path) = &self.scheduler
            && !path.exists()
        {
            return Err(bad("model.scheduler", format!("{} does not exist", path.display())));
        }
        Ok(())
    }

    /// Refuses zeros as the text embedding of a transformer that takes T5-XXL text unless
    /// `zero_text_embedding` says so (see [`crate::loaders::require_text_embedding`]).
    pub fn check_text_embedding(&self) -> Result<()> {
        let (transformer, _) = self.model_configs(false)?;
        crate::loaders::require_text_embedding(
            &transformer,
            self.text_embedding.as_deref(),
            self.zero_text_embedding,
            Path::new(&self.transformer),
        )
    }

    /// The noise schedule's config: the `scheduler` folder's, else CogVideoX-5B's.
    pub fn scheduler_config(&self) -> Result<crate::schedulers::CogVideoXSchedulerConfig> {
        use crate::diffusers_config::DiffusersConfig;
        match &self.scheduler {
            Some(path) => crate::schedulers::CogVideoXSchedulerConfig::from_json_file(path),
            None => Ok(crate::schedulers::CogVideoXSchedulerConfig::cogvideox_5b()),
        }
    }
}

impl PretrainConfig {
    /// Reads a run's `config.json` (the config a run was trained with, as `trainer pretrain`
    /// writes it). Parse errors name the file and the key path (`optim.lr`). Not validated here:
    /// `trainer finetune` replaces its model paths first, and [`super::pretrain`] validates.
    pub fn from_json_file(path: &Path) -> Result<Self> {
        let text =
            std::fs::read_to_string(path).map_err(|source| Error::Io { path: path.to_path_buf(), error: source })?;
        let source_name = path.display().to_string();
        let mut config: Self = serde_json::from_str(&text).map_err(|e| {
            let offset = offset_of(&text, e.line(), e.column());
            let key = json_key_at(&text, offset);
            Error::InvalidConfig {
                source_name: source_name.clone(),
                field: if key.is_empty() { "(json)".to_string() } else { key },
                reason: e.to_string(),
            }
        })?;
        config.source = ConfigSource(Some(source_name));
        Ok(config)
    }
}

/// Byte offset of a 1-based line and column (serde_json's error position).
fn offset_of(text: &str, line: usize, column: usize) -> usize {
    let start: usize = text.split_inclusive('\n').take(line.saturating_sub(1)).map(str::len).sum();
    (start + column).min(text.len())
}

/// The dotted path of object keys open at byte `offset` of a JSON text (`optim.lr`): the keys
/// of the enclosing objects and the last key read in the innermost one.
fn json_key_at(text: &str, offset: usize) -> String {
    // One entry per open object: the last key seen in it.
    let mut stack: Vec<Option<String>> = Vec::new();
    let mut chars = text[..offset.min(text.len())].char_indices().peekable();
    let mut last_string: Option<String> = None;
    while let Some((_, c)) = chars.next() {
        match c {
            '"' => {
                let mut value = String::new();
                while let Some((_, c)) = chars.next() {
                    match c {
                        '\\' => {
                            chars.next();
                        }
                        '"' => break,
                        other => value.push(other),
                    }
                }
                last_string = Some(value);
            }
            ':' => {
                if let Some(top) = stack.last_mut() {
                    *top = last_string.take();
                }
            }
            '{' => stack.push(None),
            '}' => {
                stack.pop();
            }
            _ => {}
        }
    }
    stack.into_iter().flatten().collect::<Vec<_>>().join(".")
}

/// A TOML parse error as an [`Error::InvalidConfig`] whose field is the key at the error's
/// position (`optim.lr`; the table for a missing key, `data.frames`), and whose reason starts
/// with the line and column, so the first line of the message names file and key.
fn toml_error(text: &str, source_name: &str, error: &toml::de::Error) -> Error {
    let message = error.message().trim().replace('\n', " ");
    let (field, place) = match error.span() {
        Some(span) => {
            let (line, column) = line_column(text, span.start);
            let (table, line_key) = toml_key_at(text, span.start, span.end);
            let key = match message.strip_prefix("missing field `").and_then(|m| m.split('`').next()) {
                Some(missing) => [table, missing.to_string()].into_iter().filter(|k| !k.is_empty()).collect::<Vec<_>>(),
                None => [table, line_key].into_iter().filter(|k| !k.is_empty()).collect(),
            }
            .join(".");
            (key, format!("line {line}, column {column}: "))
        }
        None => (String::new(), String::new()),
    };
    Error::InvalidConfig {
        source_name: source_name.to_string(),
        field: if field.is_empty() { "(toml)".to_string() } else { field },
        reason: format!("{place}{message}"),
    }
}

/// 1-based line and column of byte `offset`.
fn line_column(text: &str, offset: usize) -> (usize, usize) {
    let before = &text[..offset.min(text.len())];
    let line = before.matches('\n').count() + 1;
    let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
    (line, column)
}

/// The table header in force at byte `start` of a TOML text (`optim` under `[optim]`; empty
/// for the root table or a span covering the whole text) and the key of that line (`lr` for
/// `lr = …`; empty on a header, comment or blank line).
fn toml_key_at(text: &str, start: usize, end: usize) -> (String, String) {
    if start == 0 && end >= text.len() {
        return (String::new(), String::new());
    }
    let clean = |s: &str| s.replace(['"', '\'', ' '], "");
    let mut table = String::new();
    let mut offset = 0;
    for line in text.split_inclusive('\n') {
        let trimmed = line.trim();
        let is_here = start < offset + line.len();
        if let Some(header) = trimmed.strip_prefix('[') {
            table = clean(header.trim_start_matches('[').split(']').next().unwrap_or(""));
            if is_here {
                return (table, String::new());
            }
        } else if is_here {
            let key = if trimmed.starts_with('#') || !trimmed.contains('=') {
                String::new()
            } else {
                clean(trimmed.split('=').next().unwrap_or(""))
            };
            return (table, key);
        }
        offset += line.len();
    }
    (table, String::new())
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    #[test]
    fn toml_and_json_error_positions_map_to_dotted_keys() {
        let toml = "# comment\n[model]\nvae = \"tiny\"\n\n[optim]\nlr = \"x\"  # peak\n";
        let at = |needle: &str| toml.find(needle).unwrap();
        assert_eq!(toml_key_at(toml, at("\"x\""), at("\"x\"") + 3), ("optim".to_string(), "lr".to_string()));
        assert_eq!(toml_key_at(toml, at("[optim]"), at("[optim]") + 7), ("optim".to_string(), String::new()));
        assert_eq!(toml_key_at(toml, 0, toml.len()), (String::new(), String::new()));
        let json = "{\n  \"data\": {\"frames\": 9},\n  \"optim\": {\n    \"beta1\": 0.9,\n    \"lr\": \"fast\"\n  }\n}";
        assert_eq!(json_key_at(json, json.find("fast").unwrap()), "optim.lr");
        assert_eq!(json_key_at(json, json.find("9}").unwrap()), "data.frames");
        assert_eq!(offset_of("ab\ncd", 2, 1), 4);
    }

    #[test]
    fn auto_precision_is_bf16_on_cuda_only() {
        assert_eq!(Precision::Auto.kind(Device::Cpu), Kind::Float);
        assert_eq!(Precision::Auto.kind(Device::Cuda(0)), Kind::BFloat16);
        assert_eq!(Precision::Bf16.kind(Device::Cpu), Kind::BFloat16);
        assert_eq!(Precision::Fp32.kind(Device::Cuda(0)), Kind::Float);
    }
}

//! The `trainer pretrain --config` TOML: models, data, optimizer and loop settings, with their
//! defaults (the paper's and the public CogNVS code's) and the checks run when a file is read.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use tch::{Device, Kind};

use crate::data::DataConfig;
use crate::error::{Error, Result};

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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_precision_is_bf16_on_cuda_only() {
        assert_eq!(Precision::Auto.kind(Device::Cpu), Kind::Float);
        assert_eq!(Precision::Auto.kind(Device::Cuda(0)), Kind::BFloat16);
        assert_eq!(Precision::Bf16.kind(Device::Cpu), Kind::BFloat16);
        assert_eq!(Precision::Fp32.kind(Device::Cuda(0)), Kind::Float);
    }
}

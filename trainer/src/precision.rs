//! The arithmetic the models run in (`[loop] precision`, `--dtype`): bf16 on GPUs, f32 on CPUs by
//! default. Shared by training, sampling and the memory plan.

use serde::{Deserialize, Serialize};
use tch::{Device, Kind};

/// The arithmetic of the models' weights and activations.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Precision {
    /// bf16 on CUDA, fp32 elsewhere (CPUs have no fast bf16 kernels).
    #[default]
    Auto,
    /// Weights, activations and gradients in fp32.
    Fp32,
    /// Mixed precision: weights, activations and gradients in bf16 (half the memory, tensor-core
    /// speed); in training, fp32 master weights, optimizer moments, noise schedule and loss, and
    /// checkpoints hold the fp32 master weights. bf16 keeps fp32's exponent range, so no loss scaling is needed
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

//! The arithmetic the models run in (`[loop] precision`, `--dtype`): bf16 on GPUs, f32 on CPUs by
//! default, and the device they run on (`--device`). Shared by training, sampling and the memory
//! plan.

use serde::{Deserialize, Serialize};
use tch::{Device, Kind};

use crate::error::{Error, Result};

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

/// Parses `cpu`, `cuda` or `cuda:N` without touching a device (a plan can be made for a GPU this
/// machine lacks); [`usable_device`] also checks that libtorch sees it.
pub fn parse_device(name: &str) -> Result<Device> {
    match name {
        "cpu" => Ok(Device::Cpu),
        "cuda" => Ok(Device::Cuda(0)),
        other => match other.strip_prefix("cuda:").and_then(|i| i.parse().ok()) {
            Some(i) => Ok(Device::Cuda(i)),
            None => Err(Error::InvalidArgument {
                name: "device".to_string(),
                reason: format!("`{other}` is not cpu, cuda or cuda:N"),
            }),
        },
    }
}

/// [`parse_device`], refusing a CUDA device libtorch does not see.
pub fn usable_device(name: &str) -> Result<Device> {
    let device = parse_device(name)?;
    if let Device::Cuda(i) = device
        && i >= tch::Cuda::device_count() as usize
    {
        return Err(Error::InvalidArgument {
            name: "device".to_string(),
            reason: format!("`{name}`: libtorch sees {} CUDA devices", tch::Cuda::device_count()),
        });
    }
    Ok(device)
}

/// Parses `f32` / `fp32` / `float32` or `bf16` / `bfloat16`.
pub fn parse_dtype(name: &str) -> Result<Kind> {
    match name {
        "f32" | "fp32" | "float32" => Ok(Kind::Float),
        "bf16" | "bfloat16" => Ok(Kind::BFloat16),
        other => {
            Err(Error::InvalidArgument { name: "dtype".to_string(), reason: format!("`{other}` is not f32 or bf16") })
        }
    }
}

//! Model variables at diffusers' state-dict paths: [`Vars`] creates a module's variables
//! (`transformer_blocks.0.attn1.to_q.weight`), either allocated and initialised like PyTorch's
//! defaults or as shape-only placeholders (one element, broadcast), so the full 5B module tree can be
//! listed and checked against a checkpoint without allocating its 22 GB; with LoRA settings, the
//! targeted linear layers get their adapters in a second store. [`Linear`], [`LayerNorm`] and
//! [`RmsNorm`] are the layers built this way.

use tch::{Device, Kind, Tensor, nn};

use crate::error::Result;
use crate::models::lora::{LoraAdapter, LoraConfig};
use crate::models::weights::check_shape;

/// How a parameter starts before any checkpoint is loaded.
#[derive(Debug, Clone, Copy)]
pub enum ParamInit {
    /// PyTorch's `nn.Linear` / `nn.Conv2d` default: uniform in ±1/√fan_in (weights and biases).
    FanInUniform(i64),
    /// A constant (LayerNorm weights 1, biases 0).
    Const(f64),
    /// Normal with mean 0 and this standard deviation (Wan's modulation tables,
    /// `torch.randn(…) / dim**0.5`).
    Normal(f64),
}

/// Where a module's variables go: a path in a [`nn::VarStore`] and whether to allocate them,
/// and, for LoRA training, the same path in the adapters' store with the adapter settings.
#[derive(Clone)]
pub struct Vars<'a> {
    path: nn::Path<'a>,
    shapes_only: bool,
    lora: Option<(nn::Path<'a>, &'a LoraConfig)>,
}

impl<'a> Vars<'a> {
    /// Variables allocated and initialised in `path`'s store.
    pub fn new(path: nn::Path<'a>) -> Self {
        Self { path, shapes_only: false, lora: None }
    }

    /// These variables, with LoRA adapters (`{module}.lora_A.weight`, `lora_B.weight`) created in
    /// `adapters` for every linear layer `config` targets.
    pub fn with_lora(self, adapters: nn::Path<'a>, config: &'a LoraConfig) -> Self {
        Self { lora: Some((adapters, config)), ..self }
    }

    /// Shape-only placeholders: every variable is one element broadcast to its shape, so a module
    /// tree of any size costs a few bytes per variable. Such a module lists names and shapes
    /// ([`nn::VarStore::variables`]) but must not be run.
    pub fn shapes_only(path: nn::Path<'a>) -> Self {
        Self { path, shapes_only: true, lora: None }
    }

    /// The variables of a sub-module (`vars.sub("attn1")`).
    pub fn sub<T: std::string::ToString>(&self, name: T) -> Vars<'a> {
        let name = name.to_string();
        let lora = self.lora.as_ref().map(|(path, config)| (path.sub(&name), *config));
        Vars { path: self.path.sub(&name), shapes_only: self.shapes_only, lora }
    }

    /// The device variables live on.
    pub fn device(&self) -> Device {
        self.path.device()
    }

    /// A trainable parameter.
    pub fn param(&self, name: &str, dims: &[i64], init: ParamInit) -> Result<Tensor> {
        if self.shapes_only {
            return Ok(self.path.add(name, Self::placeholder(dims, self.device())?, true));
        }
        let options = (Kind::Float, self.device());
        let value = match init {
            ParamInit::FanInUniform(fan_in) => {
                let bound = 1.0 / (fan_in.max(1) as f64).sqrt();
                Tensor::f_empty(dims, options)?.f_uniform_(-bound, bound)?
            }
            ParamInit::Const(c) => Tensor::f_full(dims, c, options)?,
            ParamInit::Normal(std) => Tensor::f_randn(dims, options)?.f_mul_scalar(std)?,
        };
        Ok(self.path.add(name, value, true))
    }

    /// A non-trainable variable saved with the weights (a persistent buffer in PyTorch terms),
    /// starting at `value()`.
    pub fn buffer(&self, name: &str, dims: &[i64], value: impl FnOnce() -> Result<Tensor>) -> Result<Tensor> {
        let tensor = if self.shapes_only {
            Self::placeholder(dims, self.device())?
        } else {
            let t = value()?.f_to_kind(Kind::Float)?.f_to_device(self.device())?;
            check_shape(&self.path.path(name), &t, dims)?;
            t
        };
        Ok(self.path.add(name, tensor, false))
    }

    /// `nn.Linear(in_dim, out_dim, bias)`: `weight` [out, in] and `bias` [out].
    pub fn linear(&self, in_dim: i64, out_dim: i64, bias: bool) -> Result<Linear> {
        let weight = self.param("weight", &[out_dim, in_dim], ParamInit::FanInUniform(in_dim))?;
        let bias = if bias { Some(self.param("bias", &[out_dim], ParamInit::FanInUniform(in_dim))?) } else { None };
        let module = self.path.path("weight");
        let module = module.strip_suffix(".weight").unwrap_or(&module);
        let lora = match &self.lora {
            Some((adapters, config)) if config.targets(module) => {
                Some(LoraAdapter::new(adapters, config, in_dim, out_dim, self.shapes_only)?)
            }
            _ => None,
        };
        Ok(Linear { weight, bias, lora })
    }

    /// `nn.LayerNorm(dim, eps, elementwise_affine)`.
    pub fn layer_norm(&self, dim: i64, eps: f64, elementwise_affine: bool) -> Result<LayerNorm> {
        let (weight, bias) = if elementwise_affine {
            (
                Some(self.param("weight", &[dim], ParamInit::Const(1.0))?),
                Some(self.param("bias", &[dim], ParamInit::Const(0.0))?),
            )
        } else {
            (None, None)
        };
        Ok(LayerNorm { weight, bias, dim, eps })
    }

    /// `torch.nn.RMSNorm(dim, eps, elementwise_affine)`.
    pub fn rms_norm(&self, dim: i64, eps: f64, elementwise_affine: bool) -> Result<RmsNorm> {
        let weight = if elementwise_affine { Some(self.param("weight", &[dim], ParamInit::Const(1.0))?) } else { None };
        Ok(RmsNorm { weight, eps })
    }

    fn placeholder(dims: &[i64], device: Device) -> Result<Tensor> {
        Ok(Tensor::f_zeros([1], (Kind::Float, device))?.f_expand(dims, true)?)
    }
}

/// `nn.Linear`.
#[derive(Debug)]
pub struct Linear {
    weight: Tensor,
    bias: Option<Tensor>,
    lora: Option<LoraAdapter>,
}

impl Linear {
    /// `x · Wᵀ + b` over the last dimension, plus the LoRA adapter's term where there is one.
    pub fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let out = xs.f_linear(&self.weight, self.bias.as_ref())?;
        match &self.lora {
            Some(adapter) => Ok(out.f_add(&adapter.forward(xs)?)?),
            None => Ok(out),
        }
    }

    /// The weight, `[out, in]`.
    pub fn weight(&self) -> &Tensor {
        &self.weight
    }

    /// The bias, `[out]`, if any.
    pub fn bias(&self) -> Option<&Tensor> {
        self.bias.as_ref()
    }
}

/// `nn.LayerNorm` over the last dimension.
#[derive(Debug)]
pub struct LayerNorm {
    weight: Option<Tensor>,
    bias: Option<Tensor>,
    dim: i64,
    eps: f64,
}

impl LayerNorm {
    /// Normalises the last dimension (computed in the input's dtype, as PyTorch does).
    pub fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        Ok(xs.f_layer_norm([self.dim], self.weight.as_ref(), self.bias.as_ref(), self.eps, true)?)
    }

    /// diffusers' `FP32LayerNorm`: input and parameters upcast to fp32, the result cast back to
    /// the input's dtype (Wan normalises in fp32 whatever the weights' dtype).
    pub fn forward_fp32(&self, xs: &Tensor) -> Result<Tensor> {
        let upcast = |t: &Option<Tensor>| t.as_ref().map(|t| t.f_to_kind(Kind::Float)).transpose();
        let (weight, bias) = (upcast(&self.weight)?, upcast(&self.bias)?);
        let out =
            xs.f_to_kind(Kind::Float)?.f_layer_norm([self.dim], weight.as_ref(), bias.as_ref(), self.eps, true)?;
        Ok(out.f_to_kind(xs.kind())?)
    }
}

/// `torch.nn.RMSNorm` over the last dimension: `x / sqrt(mean(x²) + eps) · weight`.
#[derive(Debug)]
pub struct RmsNorm {
    weight: Option<Tensor>,
    eps: f64,
}

impl RmsNorm {
    /// Normalises the last dimension, accumulating in fp32 and returning the input's dtype (as
    /// PyTorch's fused kernel does for reduced precision).
    pub fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let x = xs.f_to_kind(Kind::Float)?;
        let mean_square = x.f_square()?.f_mean_dim(-1, true, Kind::Float)?;
        let mut out = x.f_mul(&mean_square.f_add_scalar(self.eps)?.f_rsqrt()?)?;
        if let Some(weight) = &self.weight {
            out = out.f_mul(&weight.f_to_kind(Kind::Float)?)?;
        }
        Ok(out.f_to_kind(xs.kind())?)
    }
}

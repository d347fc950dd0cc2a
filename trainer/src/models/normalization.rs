//! The adaptive layer norms of the CogVideoX transformer, mirroring diffusers'
//! `models/normalization.py`: `CogVideoXLayerNormZero` (each block's timestep-modulated norm of the
//! video and text streams, with gates) and `AdaLayerNorm` (the final modulated norm).

use tch::Tensor;

use crate::error::Result;
use crate::models::vars::{LayerNorm, Linear, Vars};

/// The modulated (normalised, scaled and shifted) streams and their residual gates.
#[derive(Debug)]
pub struct Modulated {
    /// Video tokens, `norm(x)·(1 + scale) + shift`.
    pub hidden_states: Tensor,
    /// Text tokens, modulated with their own scale and shift.
    pub encoder_hidden_states: Tensor,
    /// Gate of the video residual, `[B, 1, dim]`.
    pub gate: Tensor,
    /// Gate of the text residual, `[B, 1, dim]`.
    pub encoder_gate: Tensor,
}

/// diffusers' `CogVideoXLayerNormZero`: one `LayerNorm` shared by both streams, and
/// `linear(silu(temb))` giving six `[B, dim]` chunks: shift, scale, gate (video) then the same for
/// text.
#[derive(Debug)]
pub struct CogVideoXLayerNormZero {
    linear: Linear,
    norm: LayerNorm,
}

impl CogVideoXLayerNormZero {
    /// Variables `linear.*` (`conditioning_dim` → `6·dim`) and `norm.*`.
    pub fn new(vars: &Vars, conditioning_dim: i64, dim: i64, elementwise_affine: bool, eps: f64) -> Result<Self> {
        Ok(Self {
            linear: vars.sub("linear").linear(conditioning_dim, 6 * dim, true)?,
            norm: vars.sub("norm").layer_norm(dim, eps, elementwise_affine)?,
        })
    }

    /// Modulates `hidden_states` `[B, N, dim]` and `encoder_hidden_states` `[B, S, dim]` by `temb`.
    pub fn forward(&self, hidden_states: &Tensor, encoder_hidden_states: &Tensor, temb: &Tensor) -> Result<Modulated> {
        let chunks = self.linear.forward(&temb.f_silu()?)?.f_chunk(6, 1)?;
        let per_token = |t: &Tensor| t.f_unsqueeze(1);
        let modulate = |x: &Tensor, shift: &Tensor, scale: &Tensor| -> Result<Tensor> {
            Ok(self.norm.forward(x)?.f_mul(&per_token(&scale.f_add_scalar(1.0)?)?)?.f_add(&per_token(shift)?)?)
        };
        Ok(Modulated {
            hidden_states: modulate(hidden_states, &chunks[0], &chunks[1])?,
            encoder_hidden_states: modulate(encoder_hidden_states, &chunks[3], &chunks[4])?,
            gate: per_token(&chunks[2])?,
            encoder_gate: per_token(&chunks[5])?,
        })
    }
}

/// diffusers' `AdaLayerNorm` as CogVideoX builds it (`chunk_dim=1`, no embedding table):
/// `linear(silu(temb))` split into shift then scale, applied as `norm(x)·(1 + scale) + shift`.
#[derive(Debug)]
pub struct AdaLayerNorm {
    linear: Linear,
    norm: LayerNorm,
}

impl AdaLayerNorm {
    /// Variables `linear.*` (`embedding_dim` → `output_dim`) and `norm.*` over `output_dim / 2`.
    pub fn new(vars: &Vars, embedding_dim: i64, output_dim: i64, elementwise_affine: bool, eps: f64) -> Result<Self> {
        Ok(Self {
            linear: vars.sub("linear").linear(embedding_dim, output_dim, true)?,
            norm: vars.sub("norm").layer_norm(output_dim / 2, eps, elementwise_affine)?,
        })
    }

    /// Modulates `xs` `[B, N, dim]` by `temb` `[B, embedding_dim]`.
    pub fn forward(&self, xs: &Tensor, temb: &Tensor) -> Result<Tensor> {
        let chunks = self.linear.forward(&temb.f_silu()?)?.f_chunk(2, 1)?;
        let (shift, scale) = (chunks[0].f_unsqueeze(1)?, chunks[1].f_unsqueeze(1)?);
        Ok(self.norm.forward(xs)?.f_mul(&scale.f_add_scalar(1.0)?)?.f_add(&shift)?)
    }
}

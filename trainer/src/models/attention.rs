//! Attention and feed-forward of the CogVideoX transformer block, mirroring diffusers'
//! `Attention` with `CogVideoXAttnProcessor2_0` (`models/attention_processor.py`) and
//! `FeedForward` (`models/attention.py`).
//!
//! CogVideoX attends jointly: text tokens and video tokens form one sequence, queries and keys are
//! layer-normalised per head (QK norm), and the rotary embedding rotates only the video tokens'
//! queries and keys.

use tch::Tensor;

use crate::error::{Error, Result};
use crate::models::embeddings::RotaryEmbedding;
use crate::models::vars::{LayerNorm, Linear, Vars};

/// Epsilon of the per-head query/key LayerNorms (diffusers' `CogVideoXBlock` passes `eps=1e-6`).
const QK_NORM_EPS: f64 = 1e-6;

/// Joint self-attention over `[text; video]` tokens with QK norm: variables `to_q`, `to_k`, `to_v`,
/// `norm_q`, `norm_k` (over one head's channels) and `to_out.0`.
#[derive(Debug)]
pub struct Attention {
    heads: i64,
    head_dim: i64,
    to_q: Linear,
    to_k: Linear,
    to_v: Linear,
    norm_q: LayerNorm,
    norm_k: LayerNorm,
    to_out: Linear,
    dropout: f64,
}

impl Attention {
    /// `heads × head_dim` attention on `dim`-wide tokens; `bias` for q/k/v (the output projection
    /// always has one, diffusers' `out_bias=True`).
    pub fn new(
        vars: &Vars,
        dim: i64,
        heads: i64,
        head_dim: i64,
        bias: bool,
        affine: bool,
        dropout: f64,
    ) -> Result<Self> {
        let inner = heads * head_dim;
        Ok(Self {
            heads,
            head_dim,
            to_q: vars.sub("to_q").linear(dim, inner, bias)?,
            to_k: vars.sub("to_k").linear(dim, inner, bias)?,
            to_v: vars.sub("to_v").linear(dim, inner, bias)?,
            norm_q: vars.sub("norm_q").layer_norm(head_dim, QK_NORM_EPS, affine)?,
            norm_k: vars.sub("norm_k").layer_norm(head_dim, QK_NORM_EPS, affine)?,
            to_out: vars.sub("to_out").sub(0).linear(inner, dim, true)?,
            dropout,
        })
    }

    /// Attends over `[encoder_hidden_states; hidden_states]` and splits the result back into
    /// `(video, text)`. `rotary` covers the video tokens only.
    pub fn forward(
        &self,
        hidden_states: &Tensor,
        encoder_hidden_states: &Tensor,
        rotary: Option<&RotaryEmbedding>,
        train: bool,
    ) -> Result<(Tensor, Tensor)> {
        let text_len = encoder_hidden_states.size()[1];
        let joint = Tensor::f_cat(&[encoder_hidden_states, hidden_states], 1)?;
        let (batch, len) = (joint.size()[0], joint.size()[1]);
        let heads = |proj: &Linear| -> Result<Tensor> {
            Ok(proj.forward(&joint)?.f_view([batch, len, self.heads, self.head_dim])?.f_transpose(1, 2)?)
        };
        let mut query = self.norm_q.forward(&heads(&self.to_q)?)?;
        let mut key = self.norm_k.forward(&heads(&self.to_k)?)?;
        let value = heads(&self.to_v)?;
        if let Some(rope) = rotary {
            if rope.tokens() != len - text_len {
                return Err(Error::Shape {
                    tensor: "image_rotary_emb".to_string(),
                    expected: format!("[{}, {}] (one row per video token)", len - text_len, self.head_dim),
                    actual: rope.cos.size(),
                });
            }
            let rotate = |t: &Tensor| -> Result<Tensor> {
                let video = rope.apply(&t.f_narrow(2, text_len, len - text_len)?)?;
                Ok(Tensor::f_cat(&[t.f_narrow(2, 0, text_len)?, video], 2)?)
            };
            query = rotate(&query)?;
            key = rotate(&key)?;
        }
        let out =
            Tensor::f_scaled_dot_product_attention::<Tensor>(&query, &key, &value, None, 0.0, false, None, false)?;
        let out = out.f_transpose(1, 2)?.f_reshape([batch, len, self.heads * self.head_dim])?;
        let out = self.to_out.forward(&out)?.f_dropout(self.dropout, train)?;
        Ok((out.f_narrow(1, text_len, len - text_len)?, out.f_narrow(1, 0, text_len)?))
    }
}

/// The feed-forward activation (diffusers' `activation_fn`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    /// `gelu-approximate`: GELU with the tanh approximation (CogVideoX).
    GeluTanh,
    /// `gelu`: exact GELU.
    Gelu,
}

impl Activation {
    /// Parses diffusers' name; `None` for activations this crate does not implement.
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "gelu-approximate" => Some(Self::GeluTanh),
            "gelu" => Some(Self::Gelu),
            _ => None,
        }
    }
}

/// diffusers' `FeedForward`: `net.0.proj` (dim → 4·dim) with GELU, dropout, `net.2` (4·dim → dim),
/// and a final dropout (CogVideoX blocks use `final_dropout=True`).
#[derive(Debug)]
pub struct FeedForward {
    proj_in: Linear,
    proj_out: Linear,
    activation: Activation,
    dropout: f64,
}

impl FeedForward {
    /// Variables `net.0.proj.*` and `net.2.*`.
    pub fn new(vars: &Vars, dim: i64, inner_dim: i64, activation: Activation, dropout: f64) -> Result<Self> {
        Self::with_output(vars, dim, inner_dim, dim, activation, dropout)
    }

    /// As [`FeedForward::new`] with `dim_out` output channels (diffusers' `dim_out`; Wan's image
    /// embedder maps CLIP's width to the model's).
    pub fn with_output(
        vars: &Vars,
        dim: i64,
        inner_dim: i64,
        dim_out: i64,
        activation: Activation,
        dropout: f64,
    ) -> Result<Self> {
        let net = vars.sub("net");
        Ok(Self {
            proj_in: net.sub(0).sub("proj").linear(dim, inner_dim, true)?,
            proj_out: net.sub(2).linear(inner_dim, dim_out, true)?,
            activation,
            dropout,
        })
    }

    /// `[…, dim]` → `[…, dim_out]`.
    pub fn forward(&self, xs: &Tensor, train: bool) -> Result<Tensor> {
        let approximate = match self.activation {
            Activation::GeluTanh => "tanh",
            Activation::Gelu => "none",
        };
        let hidden = self.proj_in.forward(xs)?.f_gelu(approximate)?.f_dropout(self.dropout, train)?;
        Ok(self.proj_out.forward(&hidden)?.f_dropout(self.dropout, train)?)
    }
}

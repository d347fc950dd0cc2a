//! Embeddings of the CogVideoX transformer, mirroring diffusers' `models/embeddings.py`:
//! sinusoidal timestep features (`get_timestep_embedding`, `Timesteps`) and their MLP
//! (`TimestepEmbedding`), the 3D sin-cos positional table (`get_3d_sincos_pos_embed`), the 3D
//! rotary embedding (`get_3d_rotary_pos_embed`, `apply_rotary_emb`) and the patch embedding that
//! joins text and video tokens (`CogVideoXPatchEmbed`).
//!
//! Dtypes follow diffusers so fp32 results agree to rounding: timestep and rotary tables are
//! computed in fp32, the sin-cos table in fp64 (diffusers' CPU default) and cast to the input's
//! dtype when added.

use tch::{Device, Kind, Tensor};

use crate::error::{Error, Result};
use crate::models::vars::{Linear, ParamInit, Vars};

/// `max_period` of diffusers' `get_timestep_embedding` (and of every positional table here).
const MAX_PERIOD: f64 = 10_000.0;
/// Rotary base frequency (`theta` of `get_3d_rotary_pos_embed`).
const ROPE_THETA: f64 = 10_000.0;

/// Sinusoidal features of (possibly fractional) timesteps `[B]` → `[B, dim]` fp32, as diffusers'
/// `get_timestep_embedding(timesteps, dim, flip_sin_to_cos, downscale_freq_shift)`.
pub fn timestep_embedding(
    timesteps: &Tensor,
    dim: i64,
    flip_sin_to_cos: bool,
    downscale_freq_shift: f64,
) -> Result<Tensor> {
    if timesteps.dim() != 1 {
        return Err(Error::Shape {
            tensor: "timestep".to_string(),
            expected: "[B]".to_string(),
            actual: timesteps.size(),
        });
    }
    let half = dim / 2;
    let device = timesteps.device();
    let exponent = Tensor::f_arange(half, (Kind::Float, device))?.f_mul_scalar(-MAX_PERIOD.ln())?;
    let freqs = exponent.f_div_scalar(half as f64 - downscale_freq_shift)?.f_exp()?;
    let args = timesteps.f_to_kind(Kind::Float)?.f_unsqueeze(1)?.f_mul(&freqs.f_unsqueeze(0)?)?;
    let (sin, cos) = (args.f_sin()?, args.f_cos()?);
    let emb = if flip_sin_to_cos { Tensor::f_cat(&[cos, sin], -1)? } else { Tensor::f_cat(&[sin, cos], -1)? };
    if dim % 2 == 1 {
        return Ok(emb.f_constant_pad_nd([0, 1])?);
    }
    Ok(emb)
}

/// diffusers' `TimestepEmbedding`: `linear_2(act(linear_1(x)))` with SiLU.
#[derive(Debug)]
pub struct TimestepEmbedding {
    linear_1: Linear,
    linear_2: Linear,
}

impl TimestepEmbedding {
    /// `in_channels` sinusoidal features → `time_embed_dim`.
    pub fn new(vars: &Vars, in_channels: i64, time_embed_dim: i64) -> Result<Self> {
        Ok(Self {
            linear_1: vars.sub("linear_1").linear(in_channels, time_embed_dim, true)?,
            linear_2: vars.sub("linear_2").linear(time_embed_dim, time_embed_dim, true)?,
        })
    }

    /// `[B, in_channels]` → `[B, time_embed_dim]`.
    pub fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        self.linear_2.forward(&self.linear_1.forward(xs)?.f_silu()?)
    }

    /// The dtype of its weights.
    pub fn kind(&self) -> Kind {
        self.linear_1.weight().kind()
    }
}

/// diffusers' `get_1d_sincos_pos_embed_from_grid` in fp64: `[M]` positions → `[M, dim]`
/// (`sin` half then `cos` half).
fn sincos_1d(dim: i64, positions: &Tensor) -> Result<Tensor> {
    let device = positions.device();
    let omega = Tensor::f_arange(dim / 2, (Kind::Double, device))?.f_div_scalar(dim as f64 / 2.0)?;
    let omega = Tensor::f_full([1], MAX_PERIOD, (Kind::Double, device))?.f_pow(&omega)?.f_reciprocal()?;
    let out = positions.f_reshape([-1])?.f_to_kind(Kind::Double)?.f_outer(&omega)?;
    Ok(Tensor::f_cat(&[out.f_sin()?, out.f_cos()?], 1)?)
}

/// diffusers' `get_3d_sincos_pos_embed(embed_dim, (width, height), frames, spatial_scale,
/// temporal_scale)`: `[frames, height·width, embed_dim]` fp64, each token's row being its
/// temporal features (a quarter of the width) then spatial ones (x features, then y features).
pub fn sincos_pos_embed_3d(
    embed_dim: i64,
    width: i64,
    height: i64,
    frames: i64,
    spatial_interpolation_scale: f64,
    temporal_interpolation_scale: f64,
    device: Device,
) -> Result<Tensor> {
    if embed_dim % 16 != 0 {
        return Err(Error::InvalidArgument {
            name: "embed_dim".to_string(),
            reason: format!("{embed_dim} must be a multiple of 16 for 3D sin-cos positions"),
        });
    }
    let spatial_dim = 3 * embed_dim / 4;
    let temporal_dim = embed_dim / 4;
    let grid =
        |n: i64, scale: f64| -> Result<Tensor> { Ok(Tensor::f_arange(n, (Kind::Float, device))?.f_div_scalar(scale)?) };
    // Row-major over (y, x): x varies fastest, as the patch tokens do.
    let xs = grid(width, spatial_interpolation_scale)?.f_unsqueeze(0)?.f_expand([height, width], false)?;
    let ys = grid(height, spatial_interpolation_scale)?.f_unsqueeze(1)?.f_expand([height, width], false)?;
    let spatial = Tensor::f_cat(&[sincos_1d(spatial_dim / 2, &xs)?, sincos_1d(spatial_dim / 2, &ys)?], 1)?;
    let temporal = sincos_1d(temporal_dim, &grid(frames, temporal_interpolation_scale)?)?;
    let spatial = spatial.f_unsqueeze(0)?.f_expand([frames, height * width, spatial_dim], false)?;
    let temporal = temporal.f_unsqueeze(1)?.f_expand([frames, height * width, temporal_dim], false)?;
    Ok(Tensor::f_cat(&[temporal, spatial], -1)?)
}

/// A rotary embedding table: `cos` and `sin`, each `[tokens, head_dim]` fp32, the same rotation
/// for every head.
#[derive(Debug)]
pub struct RotaryEmbedding {
    /// Cosines, `[tokens, head_dim]`.
    pub cos: Tensor,
    /// Sines, `[tokens, head_dim]`.
    pub sin: Tensor,
}

/// diffusers' `get_1d_rotary_pos_embed(dim, positions, use_real=True)`: cos and sin of
/// `position · θ^(−2i/dim)`, each frequency repeated twice (interleaved pairs).
fn rotary_1d(dim: i64, positions: &Tensor) -> Result<(Tensor, Tensor)> {
    let device = positions.device();
    let exponents = Tensor::f_arange_start_step(0, dim, 2, (Kind::Float, device))?.f_div_scalar(dim as f64)?;
    let freqs = Tensor::f_full([1], ROPE_THETA, (Kind::Float, device))?.f_pow(&exponents)?.f_reciprocal()?;
    let angles = positions.f_to_kind(Kind::Float)?.f_outer(&freqs)?;
    Ok((
        angles.f_cos()?.f_repeat_interleave_self_int(2, 1, None)?,
        angles.f_sin()?.f_repeat_interleave_self_int(2, 1, None)?,
    ))
}

/// diffusers' `get_3d_rotary_pos_embed(head_dim, …)` over explicit positions on each axis: a
/// quarter of the head's channels rotate with time, three eighths with y and three eighths with
/// x; tokens are ordered (t, y, x), x fastest. The CogNVS trainer's `grid_type="slice"` grid is
/// positions `0..n` on every axis ([`Self::slice_grid`]); pipelines' `"linspace"` grids pass
/// their own positions.
impl RotaryEmbedding {
    /// The table for positions `t`, `y`, `x` (1-D each).
    pub fn from_positions(head_dim: i64, t: &Tensor, y: &Tensor, x: &Tensor) -> Result<Self> {
        if head_dim % 8 != 0 {
            return Err(Error::InvalidArgument {
                name: "attention_head_dim".to_string(),
                reason: format!("{head_dim} must be a multiple of 8 for 3D rotary positions"),
            });
        }
        let dim_t = head_dim / 4;
        let dim_hw = head_dim / 8 * 3;
        let (nt, ny, nx) = (t.size()[0], y.size()[0], x.size()[0]);
        let combine = |ft: &Tensor, fy: &Tensor, fx: &Tensor| -> Result<Tensor> {
            let ft = ft.f_view([nt, 1, 1, dim_t])?.f_expand([nt, ny, nx, dim_t], false)?;
            let fy = fy.f_view([1, ny, 1, dim_hw])?.f_expand([nt, ny, nx, dim_hw], false)?;
            let fx = fx.f_view([1, 1, nx, dim_hw])?.f_expand([nt, ny, nx, dim_hw], false)?;
            Ok(Tensor::f_cat(&[ft, fy, fx], -1)?.f_reshape([nt * ny * nx, -1])?)
        };
        let (t_cos, t_sin) = rotary_1d(dim_t, t)?;
        let (y_cos, y_sin) = rotary_1d(dim_hw, y)?;
        let (x_cos, x_sin) = rotary_1d(dim_hw, x)?;
        Ok(Self { cos: combine(&t_cos, &y_cos, &x_cos)?, sin: combine(&t_sin, &y_sin, &x_sin)? })
    }

    /// The `grid_type="slice"` table of a latent patch grid: positions `0..frames`, `0..height`,
    /// `0..width` (in patches).
    pub fn slice_grid(head_dim: i64, frames: i64, height: i64, width: i64, device: Device) -> Result<Self> {
        let axis = |n: i64| Tensor::f_arange(n, (Kind::Float, device));
        Self::from_positions(head_dim, &axis(frames)?, &axis(height)?, &axis(width)?)
    }

    /// Number of tokens the table covers.
    pub fn tokens(&self) -> i64 {
        self.cos.size()[0]
    }

    /// diffusers' `apply_rotary_emb(x, (cos, sin))` for `x` `[B, heads, tokens, head_dim]`: each
    /// channel pair `(a, b)` becomes `(a·cos − b·sin, b·cos + a·sin)`, computed in fp32 and cast
    /// back to `x`'s dtype.
    pub fn apply(&self, xs: &Tensor) -> Result<Tensor> {
        let size = xs.size();
        let pairs = xs.f_reshape([size[0], size[1], size[2], -1, 2])?;
        let (a, b) = (pairs.f_select(-1, 0)?, pairs.f_select(-1, 1)?);
        let rotated = Tensor::f_stack(&[b.f_neg()?, a], -1)?.f_flatten(3, -1)?;
        let out =
            xs.f_to_kind(Kind::Float)?.f_mul(&self.cos)?.f_add(&rotated.f_to_kind(Kind::Float)?.f_mul(&self.sin)?)?;
        Ok(out.f_to_kind(xs.kind())?)
    }
}

/// What [`CogVideoXPatchEmbed`] adds to the joint token sequence.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PositionalEmbedding {
    /// Nothing (rotary embeddings carry positions; CogVideoX 1.5).
    None,
    /// The 3D sin-cos table, computed (CogVideoX-2B).
    SinCos,
    /// A stored table `patch_embed.pos_embedding` `[1, text + video tokens, dim]`, initialised to
    /// the sin-cos table and loaded from the checkpoint (CogVideoX-5B-I2V, CogNVS).
    Learned,
}

/// The geometry [`CogVideoXPatchEmbed`] needs (fields of the transformer config).
#[derive(Debug, Clone)]
pub struct PatchEmbedConfig {
    /// Spatial patch size.
    pub patch_size: i64,
    /// Temporal patch size (CogVideoX 1.5) or none (1.0: frames are patched one by one).
    pub patch_size_t: Option<i64>,
    /// Latent channels in.
    pub in_channels: i64,
    /// Token width.
    pub embed_dim: i64,
    /// Text encoder width.
    pub text_embed_dim: i64,
    /// Nominal latent width / height and pixel frame count of the stored positional table.
    pub sample_width: i64,
    /// See `sample_width`.
    pub sample_height: i64,
    /// See `sample_width`.
    pub sample_frames: i64,
    /// Pixel frames per latent frame.
    pub temporal_compression_ratio: i64,
    /// Text tokens in front of the video tokens.
    pub max_text_seq_length: i64,
    /// Divisor of spatial positions in the sin-cos table.
    pub spatial_interpolation_scale: f64,
    /// Divisor of temporal positions in the sin-cos table.
    pub temporal_interpolation_scale: f64,
    /// Which positional embedding is added.
    pub positional: PositionalEmbedding,
}

/// diffusers' `CogVideoXPatchEmbed`: text tokens `text_proj(text)` followed by video tokens
/// (`proj` of each `patch_size²` latent patch, ordered frame, y, x), plus the positional table.
#[derive(Debug)]
pub struct CogVideoXPatchEmbed {
    config: PatchEmbedConfig,
    proj_weight: Tensor,
    proj_bias: Option<Tensor>,
    text_proj: Linear,
    pos_embedding: Option<Tensor>,
}

impl CogVideoXPatchEmbed {
    /// Variables `proj.{weight,bias}`, `text_proj.*` and, when learned, `pos_embedding`.
    pub fn new(vars: &Vars, config: PatchEmbedConfig, bias: bool) -> Result<Self> {
        let c = &config;
        let (proj_weight, proj_bias) = match c.patch_size_t {
            None => {
                let fan_in = c.in_channels * c.patch_size * c.patch_size;
                let proj = vars.sub("proj");
                let w = proj.param(
                    "weight",
                    &[c.embed_dim, c.in_channels, c.patch_size, c.patch_size],
                    ParamInit::FanInUniform(fan_in),
                )?;
                let b = if bias {
                    Some(proj.param("bias", &[c.embed_dim], ParamInit::FanInUniform(fan_in))?)
                } else {
                    None
                };
                (w, b)
            }
            Some(pt) => {
                // CogVideoX 1.5: a Linear over flattened (C, pt, p, p) patches; it always has a bias.
                let fan_in = c.in_channels * c.patch_size * c.patch_size * pt;
                let proj = vars.sub("proj");
                let w = proj.param("weight", &[c.embed_dim, fan_in], ParamInit::FanInUniform(fan_in))?;
                (w, Some(proj.param("bias", &[c.embed_dim], ParamInit::FanInUniform(fan_in))?))
            }
        };
        let text_proj = vars.sub("text_proj").linear(c.text_embed_dim, c.embed_dim, true)?;
        let pos_embedding = if c.positional == PositionalEmbedding::Learned {
            let tokens = c.max_text_seq_length
                + Self::video_tokens(c, c.sample_frames_latent(), c.sample_height, c.sample_width);
            let device = vars.device();
            Some(vars.buffer("pos_embedding", &[1, tokens, c.embed_dim], || {
                Self::sincos_table(c, c.sample_frames_latent(), c.sample_height, c.sample_width, device)
            })?)
        } else {
            None
        };
        Ok(Self { config, proj_weight, proj_bias, text_proj, pos_embedding })
    }

    fn video_tokens(c: &PatchEmbedConfig, latent_frames: i64, height: i64, width: i64) -> i64 {
        latent_frames * (height / c.patch_size) * (width / c.patch_size)
    }

    /// diffusers' `_get_positional_embeddings`: `[1, max_text_seq_length + video tokens, dim]`,
    /// zeros for the text tokens and the sin-cos table for the video tokens.
    fn sincos_table(
        c: &PatchEmbedConfig,
        latent_frames: i64,
        height: i64,
        width: i64,
        device: Device,
    ) -> Result<Tensor> {
        let (h, w) = (height / c.patch_size, width / c.patch_size);
        let video = sincos_pos_embed_3d(
            c.embed_dim,
            w,
            h,
            latent_frames,
            c.spatial_interpolation_scale,
            c.temporal_interpolation_scale,
            device,
        )?
        .f_reshape([1, latent_frames * h * w, c.embed_dim])?;
        let text = Tensor::f_zeros([1, c.max_text_seq_length, c.embed_dim], (Kind::Double, device))?;
        Ok(Tensor::f_cat(&[text, video], 1)?)
    }

    /// `text` `[B, S, text_embed_dim]` and `video` `[B, F, C, H, W]` → `[B, S + tokens, dim]`.
    pub fn forward(&self, text: &Tensor, video: &Tensor) -> Result<Tensor> {
        let c = &self.config;
        let text_tokens = self.text_proj.forward(text)?;
        let [b, f, ch, h, w]: [i64; 5] = video.size().try_into().expect("checked by the caller");
        let p = c.patch_size;
        let video_tokens = match c.patch_size_t {
            None => {
                let x = video.f_reshape([b * f, ch, h, w])?;
                let x = x.f_conv2d(&self.proj_weight, self.proj_bias.as_ref(), [p, p], [0, 0], [1, 1], 1)?;
                // [B·F, dim, h, w] → [B, F·h·w, dim]
                x.f_view([b, f, c.embed_dim, (h / p) * (w / p)])?.f_transpose(2, 3)?.f_reshape([b, -1, c.embed_dim])?
            }
            Some(pt) => {
                let x = video.f_permute([0, 1, 3, 4, 2])?.f_reshape([b, f / pt, pt, h / p, p, w / p, p, ch])?;
                let x = x.f_permute([0, 1, 3, 5, 7, 2, 4, 6])?.f_flatten(4, 7)?.f_flatten(1, 3)?;
                x.f_linear(&self.proj_weight, self.proj_bias.as_ref())?
            }
        };
        let embeds = Tensor::f_cat(&[text_tokens, video_tokens], 1)?;
        let table = match (c.positional, &self.pos_embedding) {
            (PositionalEmbedding::None, _) => return Ok(embeds),
            (PositionalEmbedding::Learned, _) if h != c.sample_height || w != c.sample_width => {
                return Err(Error::Shape {
                    tensor: "hidden_states".to_string(),
                    expected: format!(
                        "latent height × width {} × {} (the learned positional table `patch_embed.pos_embedding` \
                         covers only the config's sample_height × sample_width)",
                        c.sample_height, c.sample_width
                    ),
                    actual: video.size(),
                });
            }
            (PositionalEmbedding::Learned, Some(table)) if f == c.sample_frames_latent() => table.shallow_clone(),
            // diffusers recomputes the sin-cos table (text rows zero) whenever the frame count
            // differs from the stored one, for learned tables too.
            _ => Self::sincos_table(c, f, h, w, video.device())?,
        };
        if table.size()[1] != embeds.size()[1] {
            return Err(Error::Shape {
                tensor: "encoder_hidden_states".to_string(),
                expected: format!(
                    "[B, {}, {}] (max_text_seq_length text tokens)",
                    c.max_text_seq_length, c.text_embed_dim
                ),
                actual: text.size(),
            });
        }
        Ok(embeds.f_add(&table.f_to_kind(embeds.kind())?)?)
    }
}

impl PatchEmbedConfig {
    /// Latent frames of the stored positional table: `(sample_frames − 1) / ratio + 1`.
    pub fn sample_frames_latent(&self) -> i64 {
        (self.sample_frames - 1) / self.temporal_compression_ratio + 1
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotary_rotates_channel_pairs_by_position() {
        let rope = RotaryEmbedding::slice_grid(16, 2, 3, 4, Device::Cpu).unwrap();
        assert_eq!(rope.cos.size(), vec![24, 16]);
        // Token 0 sits at the origin: no rotation.
        let x = Tensor::randn([1, 2, 24, 16], (Kind::Float, Device::Cpu));
        let y = rope.apply(&x).unwrap();
        assert!(y.narrow(2, 0, 1).allclose(&x.narrow(2, 0, 1), 1e-6, 1e-6, false));
        // Rotations keep each pair's norm.
        let norms = |t: &Tensor| t.reshape([1, 2, 24, 8, 2]).square().sum_dim_intlist(-1, false, Kind::Float);
        assert!(norms(&y).allclose(&norms(&x), 1e-5, 1e-5, false));
    }

    #[test]
    fn timestep_features_match_the_closed_form() {
        let t = Tensor::from_slice(&[0.0f32, 500.0]);
        let e = timestep_embedding(&t, 8, true, 0.0).unwrap();
        assert_eq!(e.size(), vec![2, 8]);
        // flip_sin_to_cos: cos first; frequency i is 10000^(−i/4).
        let expected = (500.0f64 * 10_000f64.powf(-1.0 / 4.0)).cos();
        assert!((e.double_value(&[1, 1]) - expected).abs() < 1e-4);
        assert_eq!(e.double_value(&[0, 0]), 1.0);
        assert_eq!(e.double_value(&[0, 4]), 0.0);
    }
}

//! The Wan diffusion transformer: diffusers' `WanTransformer3DModel`
//! (`diffusers/models/transformers/transformer_wan.py`), weight-compatible with it and with the
//! released Wan2.1 and Wan2.2 checkpoints in the diffusers layout (`Wan-AI/*-Diffusers`).
//!
//! Latent video `[B, C, F, H, W]` is cut into `patch_size` patches by a 3D convolution; every block
//! modulates its norms by the timestep (one shared projection `condition_embedder.time_proj`, plus a
//! learned `scale_shift_table` per block), runs self-attention with 3D rotary positions and RMS
//! QK norm, cross-attention to the projected umT5 text tokens (and, for Wan2.1 image-to-video, to
//! CLIP image tokens through separate key/value projections, `added_kv_proj_dim`), and a GELU
//! feed-forward. The modulated final norm and `proj_out` map tokens back to
//! `[B, out_channels, F, H, W]`. The timestep is one per sample `[B]`, or one per token
//! `[B, tokens]` (Wan2.2 TI2V's `expand_timesteps`: the conditioning frame's tokens at 0).
//!
//! Norms and modulation run in fp32 whatever the weights' dtype, as diffusers' `FP32LayerNorm` and
//! `.float()` casts do. Variables live at diffusers' state-dict paths, so a diffusers checkpoint
//! loads unchanged ([`crate::models::weights::load`]) and [`crate::models::weights::save`] writes
//! one diffusers' `from_pretrained` reads.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor, nn};

use crate::diffusers_config::{self, DiffusersConfig};
use crate::error::{Error, Result};
use crate::models::attention::{Activation, FeedForward};
use crate::models::embeddings::{RotaryEmbedding, TimestepEmbedding, timestep_embedding};
use crate::models::vars::{LayerNorm, Linear, ParamInit, RmsNorm, Vars};
use crate::models::weights;

/// The class name diffusers writes into the transformer's `config.json` (`_class_name`).
pub const CLASS_NAME: &str = "WanTransformer3DModel";

/// Text tokens in the cross-attention context of image-conditioned models: diffusers'
/// `WanAttnProcessor` splits the image tokens off the front of the context by assuming this many
/// text tokens (umT5's padded length, "hardcoded for now" there), so image tokens are only
/// accepted beside a text sequence of exactly this length.
pub const TEXT_CONTEXT_LENGTH: i64 = 512;

/// The only QK norm diffusers' `WanAttention` builds (`qk_norm` is accepted but not read).
const QK_NORM: &str = "rms_norm_across_heads";
/// Epsilon of the image embedder's two `FP32LayerNorm`s (`nn.LayerNorm`'s default; diffusers'
/// `WanImageEmbedding` passes none).
const IMAGE_NORM_EPS: f64 = 1e-5;
/// Rotary base frequency (`theta` of diffusers' `WanRotaryPosEmbed`).
const ROPE_THETA: f64 = 10_000.0;
/// Modules whose parameters stay fp32 when the model is loaded in a lower precision (diffusers'
/// `_keep_in_fp32_modules` of `WanTransformer3DModel`; a parameter is kept when one of the
/// components of its dotted name is one of these, as `from_pretrained(torch_dtype=…)` decides).
pub const KEEP_IN_FP32_MODULES: [&str; 6] = ["rope", "time_embedder", "scale_shift_table", "norm1", "norm2", "norm3"];
/// Checkpoint tensors skipped when loading (diffusers' `_keys_to_ignore_on_load_unexpected`: the
/// image key norm's query twin, which early conversions of the I2V checkpoints wrote and the model
/// never uses).
pub const KEYS_TO_IGNORE_ON_LOAD_UNEXPECTED: [&str; 1] = ["norm_added_q"];
/// Largest value of one size field (channels, heads, layers, tokens): far above every released
/// model's (5120 channels, 40 heads, 1024 rotary positions) and small enough that products of two
/// or three stay inside 64-bit sizes.
pub const MAX_DIMENSION: i64 = 1 << 20;

// ------------------------------------------------------------------------------------------------
// Configuration
// ------------------------------------------------------------------------------------------------

/// The transformer's `config.json` as diffusers writes it, field names verbatim. Missing fields
/// take diffusers' `__init__` defaults (the Wan2.1 14B text-to-video transformer); keys starting
/// with `_` are diffusers metadata; any other key is kept in `extra` and reported, not dropped.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct WanTransformer3DModelConfig {
    /// Patch size `[t, h, w]` of the 3D patch embedding.
    pub patch_size: [i64; 3],
    /// Attention heads per block.
    pub num_attention_heads: i64,
    /// Channels per head; tokens are `heads × head_dim` wide.
    pub attention_head_dim: i64,
    /// Latent channels in (T2V: 16; Wan2.1 I2V: 16 noisy + 4 mask + 16 condition = 36).
    pub in_channels: i64,
    /// Latent channels out (defaults to `in_channels` when null).
    pub out_channels: Option<i64>,
    /// Width of the text encoder's tokens (umT5-XXL: 4096).
    pub text_dim: i64,
    /// Sinusoidal timestep features.
    pub freq_dim: i64,
    /// Feed-forward width.
    pub ffn_dim: i64,
    /// Transformer blocks.
    pub num_layers: i64,
    /// An affine LayerNorm before the cross-attention (otherwise none).
    pub cross_attn_norm: bool,
    /// Kept as read: diffusers builds RMS norms across heads whatever this says.
    pub qk_norm: Option<String>,
    /// Epsilon of every norm in the blocks and of the output norm.
    pub eps: f64,
    /// Width of the CLIP image tokens (Wan2.1 I2V: 1280); null for no image embedder.
    pub image_dim: Option<i64>,
    /// Input width of the image key/value projections of every cross-attention (= the token
    /// width); null for no image cross-attention.
    pub added_kv_proj_dim: Option<i64>,
    /// Rotary positions precomputed per axis: the most latent patches along any axis.
    pub rope_max_seq_len: i64,
    /// Image tokens of the image embedder's positional table (Wan2.1 FLF2V: the first and last
    /// frames' CLIP tokens); null for none.
    pub pos_embed_seq_len: Option<i64>,
    /// Every other key: `_class_name`, `_diffusers_version`, … and unknown keys.
    #[serde(flatten)]
    pub extra: BTreeMap<String, serde_json::Value>,
}

impl Default for WanTransformer3DModelConfig {
    /// diffusers' `WanTransformer3DModel.__init__` defaults (the Wan2.1 14B T2V architecture).
    fn default() -> Self {
        Self {
            patch_size: [1, 2, 2],
            num_attention_heads: 40,
            attention_head_dim: 128,
            in_channels: 16,
            out_channels: Some(16),
            text_dim: 4096,
            freq_dim: 256,
            ffn_dim: 13824,
            num_layers: 40,
            cross_attn_norm: true,
            qk_norm: Some(QK_NORM.to_string()),
            eps: 1e-6,
            image_dim: None,
            added_kv_proj_dim: None,
            rope_max_seq_len: 1024,
            pos_embed_seq_len: None,
            extra: BTreeMap::new(),
        }
    }
}

impl DiffusersConfig for WanTransformer3DModelConfig {
    const KIND: &'static str = "transformer";
    const CLASS_NAMES: &'static [&'static str] = &[CLASS_NAME];
    const FILE_NAME: &'static str = "config.json";

    /// Rejects values and combinations the architecture cannot build, naming the field.
    fn validate_fields(&self, source_name: &str) -> Result<()> {
        let err = diffusers_config::field_error(source_name);
        let [pt, ph, pw] = self.patch_size;
        let sizes = [
            ("patch_size", pt.min(ph).min(pw)),
            ("num_attention_heads", self.num_attention_heads),
            ("attention_head_dim", self.attention_head_dim),
            ("in_channels", self.in_channels),
            ("out_channels", self.output_channels()),
            ("text_dim", self.text_dim),
            ("freq_dim", self.freq_dim),
            ("ffn_dim", self.ffn_dim),
            ("num_layers", self.num_layers),
            ("rope_max_seq_len", self.rope_max_seq_len),
            ("image_dim", self.image_dim.unwrap_or(1)),
            ("added_kv_proj_dim", self.added_kv_proj_dim.unwrap_or(1)),
            ("pos_embed_seq_len", self.pos_embed_seq_len.unwrap_or(1)),
        ];
        diffusers_config::require_positive(source_name, &sizes)?;
        for (field, value) in sizes.into_iter().chain([("patch_size", pt.max(ph).max(pw))]) {
            if value > MAX_DIMENSION {
                return Err(err(field, format!("must be at most {MAX_DIMENSION}, got {value}")));
            }
        }
        if self.num_attention_heads * self.attention_head_dim > MAX_DIMENSION {
            return Err(err(
                "num_attention_heads",
                format!(
                    "num_attention_heads × attention_head_dim = {} × {} is more than {MAX_DIMENSION} channels",
                    self.num_attention_heads, self.attention_head_dim
                ),
            ));
        }
        if self.attention_head_dim % 2 != 0 {
            return Err(err(
                "attention_head_dim",
                format!("{} must be even (rotary positions rotate channel pairs)", self.attention_head_dim),
            ));
        }
        if let Some(added) = self.added_kv_proj_dim {
            if self.image_dim.is_none() {
                return Err(err(
                    "added_kv_proj_dim",
                    "needs image_dim: the image key/value projections read the image embedder's tokens".to_string(),
                ));
            }
            if added != self.inner_dim() {
                return Err(err(
                    "added_kv_proj_dim",
                    format!(
                        "{added} must equal num_attention_heads × attention_head_dim = {} (the image embedder's \
                         output width)",
                        self.inner_dim()
                    ),
                ));
            }
        }
        if self.pos_embed_seq_len.is_some() && self.image_dim.is_none() {
            return Err(err("pos_embed_seq_len", "needs image_dim (it is the image embedder's table)".to_string()));
        }
        if !(self.eps > 0.0 && self.eps.is_finite()) {
            return Err(err("eps", format!("must be positive and finite, got {}", self.eps)));
        }
        Ok(())
    }

    fn extra(&self) -> &BTreeMap<String, serde_json::Value> {
        &self.extra
    }

    fn warnings(&self) -> Vec<String> {
        match self.qk_norm.as_deref() {
            Some(QK_NORM) => Vec::new(),
            other => vec![format!(
                "transformer config field `qk_norm` is {other:?}; diffusers (and this port) use `{QK_NORM}` \
                 whatever it says"
            )],
        }
    }
}

impl WanTransformer3DModelConfig {
    /// Wan2.1 T2V 1.3B (`Wan-AI/Wan2.1-T2V-1.3B-Diffusers`, `transformer/config.json`): 30 blocks of
    /// 12 heads × 128.
    pub fn wan21_t2v_1_3b() -> Self {
        Self { num_attention_heads: 12, ffn_dim: 8960, num_layers: 30, ..Self::default() }
    }

    /// Wan2.1 T2V 14B (`Wan-AI/Wan2.1-T2V-14B-Diffusers`) = diffusers' defaults: 40 blocks of 40
    /// heads × 128.
    pub fn wan21_t2v_14b() -> Self {
        Self::default()
    }

    /// Wan2.1 I2V 14B (`Wan-AI/Wan2.1-I2V-14B-480P-Diffusers`): the 14B T2V blocks with 36 input
    /// channels (16 noisy + 4 mask + 16 condition latents) and CLIP ViT-H image tokens (1280 wide).
    pub fn wan21_i2v_14b() -> Self {
        Self { in_channels: 36, image_dim: Some(1280), added_kv_proj_dim: Some(5120), ..Self::default() }
    }

    /// Wan2.2 TI2V 5B (`Wan-AI/Wan2.2-TI2V-5B-Diffusers`): 30 blocks of 24 heads × 128 on the
    /// Wan2.2 VAE's 48 latent channels.
    pub fn wan22_ti2v_5b() -> Self {
        Self {
            num_attention_heads: 24,
            in_channels: 48,
            out_channels: Some(48),
            ffn_dim: 14336,
            num_layers: 30,
            ..Self::default()
        }
    }

    /// The Wan2.1 T2V structure at small widths for tests and CPU runs: 2 blocks of 2 heads × 16
    /// (8 temporal and 4 + 4 spatial rotary channels), 4 latent channels, text tokens 16 wide.
    /// `scripts/goldens_wan.py` builds the same model in diffusers.
    pub fn tiny_t2v() -> Self {
        Self {
            num_attention_heads: 2,
            attention_head_dim: 16,
            in_channels: 4,
            out_channels: Some(4),
            text_dim: 16,
            freq_dim: 32,
            ffn_dim: 48,
            num_layers: 2,
            rope_max_seq_len: 32,
            ..Self::default()
        }
    }

    /// [`tiny_t2v`](Self::tiny_t2v) with the Wan2.1 I2V structure: 12 input channels (4 noisy + 4
    /// mask + 4 condition) and image tokens 24 wide.
    pub fn tiny_i2v() -> Self {
        Self { in_channels: 12, image_dim: Some(24), added_kv_proj_dim: Some(32), ..Self::tiny_t2v() }
    }

    /// [`tiny_t2v`](Self::tiny_t2v) taking the CogNVS conditioning without image tokens: 12 input
    /// channels (4 noisy + 4 mask + 4 condition latents of the tiny Wan VAE), for CPU training runs.
    pub fn tiny_cognvs() -> Self {
        Self { in_channels: 12, ..Self::tiny_t2v() }
    }

    /// This model with the CogNVS conditioning's input channels (noisy latents, the hole mask's
    /// [`COGNVS_MASK_CHANNELS`], the render's latents): what [`widen_in_channels`] makes of a
    /// text-to-video (or TI2V) checkpoint before CogNVS training. An image-to-video model has
    /// them already.
    pub fn for_cognvs(self) -> Self {
        let latent = self.output_channels();
        Self { in_channels: 2 * latent + COGNVS_MASK_CHANNELS, out_channels: Some(latent), ..self }
    }

    /// A preset by name: `wan2.1-t2v-1.3b`, `wan2.1-t2v-14b`, `wan2.1-i2v-14b`, `wan2.2-ti2v-5b`,
    /// the CogNVS-widened `wan2.1-t2v-1.3b-cognvs` and `wan2.2-ti2v-5b-cognvs`
    /// ([`Self::for_cognvs`]), `tiny-t2v`, `tiny-i2v`, `tiny-cognvs`.
    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "wan2.1-t2v-1.3b" => Ok(Self::wan21_t2v_1_3b()),
            "wan2.1-t2v-1.3b-cognvs" => Ok(Self::wan21_t2v_1_3b().for_cognvs()),
            "wan2.2-ti2v-5b-cognvs" => Ok(Self::wan22_ti2v_5b().for_cognvs()),
            "wan2.1-t2v-14b" => Ok(Self::wan21_t2v_14b()),
            "wan2.1-i2v-14b" => Ok(Self::wan21_i2v_14b()),
            "wan2.2-ti2v-5b" => Ok(Self::wan22_ti2v_5b()),
            "tiny-t2v" => Ok(Self::tiny_t2v()),
            "tiny-i2v" => Ok(Self::tiny_i2v()),
            "tiny-cognvs" => Ok(Self::tiny_cognvs()),
            other => Err(Error::InvalidConfig {
                source_name: "preset".to_string(),
                field: "name".to_string(),
                reason: format!(
                    "unknown Wan transformer preset `{other}`; expected wan2.1-t2v-1.3b, wan2.1-t2v-14b, \
                     wan2.1-i2v-14b, wan2.2-ti2v-5b, wan2.1-t2v-1.3b-cognvs, wan2.2-ti2v-5b-cognvs, tiny-t2v, \
                     tiny-i2v or tiny-cognvs"
                ),
            }),
        }
    }

    /// Token width, `heads × head_dim`.
    pub fn inner_dim(&self) -> i64 {
        self.num_attention_heads * self.attention_head_dim
    }

    /// Output latent channels (`out_channels`, or `in_channels` when null).
    pub fn output_channels(&self) -> i64 {
        self.out_channels.unwrap_or(self.in_channels)
    }

    /// Rotary channels per head along (t, h, w): h and w get `2·⌊head_dim / 6⌋` each, t the rest
    /// (diffusers' `WanRotaryPosEmbed`).
    pub fn rotary_split(&self) -> [i64; 3] {
        let spatial = 2 * (self.attention_head_dim / 6);
        [self.attention_head_dim - 2 * spatial, spatial, spatial]
    }
}

// ------------------------------------------------------------------------------------------------
// Components
// ------------------------------------------------------------------------------------------------

/// diffusers' `WanRotaryPosEmbed` for a grid of `frames × height × width` patches: per axis,
/// `position · θ^(−2i/d)` in fp64 (each frequency repeated for its channel pair), cast to fp32;
/// the t, h and w channels concatenated per token, tokens ordered (t, h, w) with w fastest.
pub fn rotary_embedding(
    config: &WanTransformer3DModelConfig,
    grid: [i64; 3],
    device: Device,
) -> Result<RotaryEmbedding> {
    let [frames, height, width] = grid;
    if let Some(&n) = grid.iter().find(|&&n| n > config.rope_max_seq_len) {
        return Err(Error::Shape {
            tensor: "hidden_states".to_string(),
            expected: format!("at most rope_max_seq_len = {} patches along each axis", config.rope_max_seq_len),
            actual: vec![n],
        });
    }
    let axis = |dim: i64, n: i64| -> Result<(Tensor, Tensor)> {
        let exponents = Tensor::f_arange_start_step(0, dim, 2, (Kind::Double, device))?.f_div_scalar(dim as f64)?;
        let freqs = Tensor::f_full([1], ROPE_THETA, (Kind::Double, device))?.f_pow(&exponents)?.f_reciprocal()?;
        let angles = Tensor::f_arange(n, (Kind::Double, device))?.f_outer(&freqs)?;
        let table =
            |t: Tensor| -> Result<Tensor> { Ok(t.f_repeat_interleave_self_int(2, 1, None)?.f_to_kind(Kind::Float)?) };
        Ok((table(angles.f_cos()?)?, table(angles.f_sin()?)?))
    };
    let [dim_t, dim_h, dim_w] = config.rotary_split();
    let (t_cos, t_sin) = axis(dim_t, frames)?;
    let (h_cos, h_sin) = axis(dim_h, height)?;
    let (w_cos, w_sin) = axis(dim_w, width)?;
    let combine = |ft: &Tensor, fh: &Tensor, fw: &Tensor| -> Result<Tensor> {
        let shape = |d: i64| [frames, height, width, d];
        let ft = ft.f_view([frames, 1, 1, dim_t])?.f_expand(shape(dim_t), false)?;
        let fh = fh.f_view([1, height, 1, dim_h])?.f_expand(shape(dim_h), false)?;
        let fw = fw.f_view([1, 1, width, dim_w])?.f_expand(shape(dim_w), false)?;
        Ok(Tensor::f_cat(&[ft, fh, fw], -1)?.f_reshape([frames * height * width, -1])?)
    };
    Ok(RotaryEmbedding { cos: combine(&t_cos, &h_cos, &w_cos)?, sin: combine(&t_sin, &h_sin, &w_sin)? })
}

/// diffusers' `WanAttention` with `WanAttnProcessor`: projections `to_q`, `to_k`, `to_v`,
/// `to_out.0`, RMS norms `norm_q`, `norm_k` across all heads, and for image cross-attention the
/// image key/value projections `add_k_proj`, `add_v_proj` with `norm_added_k`, whose attention
/// output is added to the text attention's.
#[derive(Debug)]
pub struct WanAttention {
    heads: i64,
    to_q: Linear,
    to_k: Linear,
    to_v: Linear,
    norm_q: RmsNorm,
    norm_k: RmsNorm,
    image: Option<(Linear, Linear, RmsNorm)>,
    to_out: Linear,
}

impl WanAttention {
    /// `heads × head_dim` attention on `dim`-wide tokens; `added_kv_proj_dim` adds the image
    /// key/value projections.
    pub fn new(vars: &Vars, dim: i64, heads: i64, eps: f64, added_kv_proj_dim: Option<i64>) -> Result<Self> {
        // diffusers' inner width heads × (dim / heads) is the token width itself.
        let inner = dim;
        let image = match added_kv_proj_dim {
            Some(added) => Some((
                vars.sub("add_k_proj").linear(added, inner, true)?,
                vars.sub("add_v_proj").linear(added, inner, true)?,
                vars.sub("norm_added_k").rms_norm(inner, eps, true)?,
            )),
            None => None,
        };
        Ok(Self {
            heads,
            to_q: vars.sub("to_q").linear(dim, inner, true)?,
            to_k: vars.sub("to_k").linear(dim, inner, true)?,
            to_v: vars.sub("to_v").linear(dim, inner, true)?,
            norm_q: vars.sub("norm_q").rms_norm(inner, eps, true)?,
            norm_k: vars.sub("norm_k").rms_norm(inner, eps, true)?,
            image,
            to_out: vars.sub("to_out").sub(0).linear(inner, dim, true)?,
        })
    }

    /// Self-attention (`context` None, with `rotary`) or cross-attention to `context` (and to
    /// `image` tokens, already embedded, when this layer has image projections).
    pub fn forward(
        &self,
        hidden_states: &Tensor,
        context: Option<&Tensor>,
        image: Option<&Tensor>,
        rotary: Option<&RotaryEmbedding>,
    ) -> Result<Tensor> {
        let source = context.unwrap_or(hidden_states);
        // [B, S, heads·d] → [B, heads, S, d].
        let split = |t: Tensor| -> Result<Tensor> {
            let (b, s) = (t.size()[0], t.size()[1]);
            Ok(t.f_view([b, s, self.heads, -1])?.f_transpose(1, 2)?)
        };
        let mut query = split(self.norm_q.forward(&self.to_q.forward(hidden_states)?)?)?;
        let mut key = split(self.norm_k.forward(&self.to_k.forward(source)?)?)?;
        let value = split(self.to_v.forward(source)?)?;
        if let Some(rope) = rotary {
            query = rope.apply(&query)?;
            key = rope.apply(&key)?;
        }
        let attend = |k: &Tensor, v: &Tensor| -> Result<Tensor> {
            let out = Tensor::f_scaled_dot_product_attention::<Tensor>(&query, k, v, None, 0.0, false, None, false)?;
            Ok(out.f_transpose(1, 2)?.f_flatten(2, 3)?)
        };
        let mut out = attend(&key, &value)?;
        if let (Some((add_k, add_v, norm_added_k)), Some(image)) = (&self.image, image) {
            let key_img = split(norm_added_k.forward(&add_k.forward(image)?)?)?;
            let value_img = split(add_v.forward(image)?)?;
            out = out.f_add(&attend(&key_img, &value_img)?)?;
        }
        self.to_out.forward(&out)
    }
}

/// diffusers' `WanTransformerBlock`: modulated self-attention, (normalised) cross-attention, and a
/// modulated feed-forward, the modulation being `scale_shift_table` plus the timestep projection.
#[derive(Debug)]
pub struct WanTransformerBlock {
    norm1: LayerNorm,
    attn1: WanAttention,
    attn2: WanAttention,
    norm2: Option<LayerNorm>,
    ffn: FeedForward,
    norm3: LayerNorm,
    scale_shift_table: Tensor,
}

impl WanTransformerBlock {
    /// Variables `norm1` (none stored), `attn1`, `attn2`, `norm2`, `ffn`, `scale_shift_table`.
    pub fn new(vars: &Vars, c: &WanTransformer3DModelConfig) -> Result<Self> {
        let dim = c.inner_dim();
        let heads = c.num_attention_heads;
        Ok(Self {
            norm1: vars.sub("norm1").layer_norm(dim, c.eps, false)?,
            attn1: WanAttention::new(&vars.sub("attn1"), dim, heads, c.eps, None)?,
            attn2: WanAttention::new(&vars.sub("attn2"), dim, heads, c.eps, c.added_kv_proj_dim)?,
            norm2: if c.cross_attn_norm { Some(vars.sub("norm2").layer_norm(dim, c.eps, true)?) } else { None },
            ffn: FeedForward::new(&vars.sub("ffn"), dim, c.ffn_dim, Activation::GeluTanh, 0.0)?,
            norm3: vars.sub("norm3").layer_norm(dim, c.eps, false)?,
            scale_shift_table: vars.param(
                "scale_shift_table",
                &[1, 6, dim],
                ParamInit::Normal(1.0 / (dim as f64).sqrt()),
            )?,
        })
    }

    /// One block on `hidden_states` `[B, N, dim]`; `timestep_proj` is `[B, T, 6, dim]` with T = 1
    /// (one timestep per sample) or N (one per token).
    pub fn forward(
        &self,
        hidden_states: &Tensor,
        context: &Tensor,
        image: Option<&Tensor>,
        timestep_proj: &Tensor,
        rotary: &RotaryEmbedding,
    ) -> Result<Tensor> {
        let kind = hidden_states.kind();
        let modulation = self.scale_shift_table.f_unsqueeze(0)?.f_add(&timestep_proj.f_to_kind(Kind::Float)?)?;
        let m: Vec<Tensor> =
            modulation.f_chunk(6, 2)?.iter().map(|t| t.f_squeeze_dim(2)).collect::<tch::Result<_>>()?;
        let (shift, scale, gate, c_shift, c_scale, c_gate) = (&m[0], &m[1], &m[2], &m[3], &m[4], &m[5]);
        let modulate = |norm: &LayerNorm, x: &Tensor, shift: &Tensor, scale: &Tensor| -> Result<Tensor> {
            let normed = norm.forward_fp32(&x.f_to_kind(Kind::Float)?)?;
            Ok(normed.f_mul(&scale.f_add_scalar(1.0)?)?.f_add(shift)?.f_to_kind(kind)?)
        };

        let attn =
            self.attn1.forward(&modulate(&self.norm1, hidden_states, shift, scale)?, None, None, Some(rotary))?;
        let hidden_states = hidden_states.f_to_kind(Kind::Float)?.f_add(&attn.f_mul(gate)?)?.f_to_kind(kind)?;

        let normed = match &self.norm2 {
            Some(norm) => norm.forward_fp32(&hidden_states.f_to_kind(Kind::Float)?)?.f_to_kind(kind)?,
            None => hidden_states.shallow_clone(),
        };
        let hidden_states = hidden_states.f_add(&self.attn2.forward(&normed, Some(context), image, None)?)?;

        let ff = self.ffn.forward(&modulate(&self.norm3, &hidden_states, c_shift, c_scale)?, false)?;
        let out = hidden_states.f_to_kind(Kind::Float)?.f_add(&ff.f_to_kind(Kind::Float)?.f_mul(c_gate)?)?;
        Ok(out.f_to_kind(kind)?)
    }
}

/// diffusers' `WanImageEmbedding`: CLIP image tokens (plus a positional table for FLF2V, whose
/// two frames' tokens arrive as two batch entries per sample) → `FP32LayerNorm` → GELU MLP to the
/// token width → `FP32LayerNorm`.
#[derive(Debug)]
struct WanImageEmbedding {
    norm1: LayerNorm,
    ff: FeedForward,
    norm2: LayerNorm,
    pos_embed: Option<Tensor>,
}

impl WanImageEmbedding {
    fn new(vars: &Vars, in_features: i64, out_features: i64, pos_embed_seq_len: Option<i64>) -> Result<Self> {
        Ok(Self {
            norm1: vars.sub("norm1").layer_norm(in_features, IMAGE_NORM_EPS, true)?,
            ff: FeedForward::with_output(
                &vars.sub("ff"),
                in_features,
                in_features,
                out_features,
                Activation::Gelu,
                0.0,
            )?,
            norm2: vars.sub("norm2").layer_norm(out_features, IMAGE_NORM_EPS, true)?,
            pos_embed: match pos_embed_seq_len {
                Some(len) => Some(vars.param("pos_embed", &[1, len, in_features], ParamInit::Const(0.0))?),
                None => None,
            },
        })
    }

    fn forward(&self, image: &Tensor) -> Result<Tensor> {
        let image = match &self.pos_embed {
            Some(pos) => {
                let size = image.size();
                image.f_reshape([-1, 2 * size[1], size[2]])?.f_add(pos)?
            }
            None => image.shallow_clone(),
        };
        let hidden = self.norm1.forward_fp32(&image)?;
        self.norm2.forward_fp32(&self.ff.forward(&hidden, false)?)
    }
}

/// diffusers' `WanTimeTextImageEmbedding`: the timestep embedding and its six-way projection,
/// the text projection and the optional image embedder.
#[derive(Debug)]
struct WanTimeTextImageEmbedding {
    freq_dim: i64,
    time_embedder: TimestepEmbedding,
    time_proj: Linear,
    text_linear_1: Linear,
    text_linear_2: Linear,
    image_embedder: Option<WanImageEmbedding>,
}

/// What the condition embedder gives the blocks.
struct Conditions {
    /// `[B, T, dim]` (T = 1, or one per token).
    temb: Tensor,
    /// `[B, T, 6, dim]`.
    timestep_proj: Tensor,
    /// Projected text tokens `[B, S, dim]`.
    text: Tensor,
    /// Embedded image tokens `[B, N, dim]`.
    image: Option<Tensor>,
}

impl WanTimeTextImageEmbedding {
    fn new(vars: &Vars, c: &WanTransformer3DModelConfig) -> Result<Self> {
        let dim = c.inner_dim();
        let text = vars.sub("text_embedder");
        Ok(Self {
            freq_dim: c.freq_dim,
            time_embedder: TimestepEmbedding::new(&vars.sub("time_embedder"), c.freq_dim, dim)?,
            time_proj: vars.sub("time_proj").linear(dim, 6 * dim, true)?,
            text_linear_1: text.sub("linear_1").linear(c.text_dim, dim, true)?,
            text_linear_2: text.sub("linear_2").linear(dim, dim, true)?,
            image_embedder: match c.image_dim {
                Some(image_dim) => {
                    Some(WanImageEmbedding::new(&vars.sub("image_embedder"), image_dim, dim, c.pos_embed_seq_len)?)
                }
                None => None,
            },
        })
    }

    /// `timestep` is `[B, T]` here (a per-sample timestep as T = 1).
    fn forward(&self, timestep: &Tensor, text: &Tensor, image: Option<&Tensor>) -> Result<Conditions> {
        let (b, t) = (timestep.size()[0], timestep.size()[1]);
        let kind = text.kind();
        let features = timestep_embedding(&timestep.f_reshape([-1])?, self.freq_dim, true, 0.0)?;
        // The time embedder runs in its own (fp32-kept) dtype; its output in the text's.
        let features = features.f_view([b, t, -1])?.f_to_kind(self.time_embedder.kind())?;
        let temb = self.time_embedder.forward(&features)?.f_to_kind(kind)?;
        let timestep_proj = self.time_proj.forward(&temb.f_silu()?)?.f_unflatten(2, [6, -1])?;
        let text = self.text_linear_2.forward(&self.text_linear_1.forward(text)?.f_gelu("tanh")?)?;
        let image = match (&self.image_embedder, image) {
            (Some(embedder), Some(image)) => Some(embedder.forward(image)?),
            _ => None,
        };
        Ok(Conditions { temb, timestep_proj, text, image })
    }
}

// ------------------------------------------------------------------------------------------------
// Model
// ------------------------------------------------------------------------------------------------

/// The inputs of one transformer call, named after diffusers' `forward` arguments.
#[derive(Debug)]
pub struct WanTransformerInput<'a> {
    /// Noisy latents (I2V: with the mask and condition latents on channels) `[B, in_channels, F,
    /// H, W]`, F, H and W multiples of `patch_size`.
    pub hidden_states: &'a Tensor,
    /// Diffusion timestep per sample `[B]` (or one scalar for the batch), or per token
    /// `[B, F·H·W / patch volume]` (Wan2.2 TI2V).
    pub timestep: &'a Tensor,
    /// Text tokens `[B, S, text_dim]` (`TEXT_CONTEXT_LENGTH` of them beside image tokens).
    pub encoder_hidden_states: &'a Tensor,
    /// CLIP image tokens `[B, N, image_dim]` (FLF2V: `[2B, N, image_dim]`, first and last frame),
    /// required exactly when the config has `image_dim`.
    pub encoder_hidden_states_image: Option<&'a Tensor>,
}

/// diffusers' `WanTransformer3DModel`.
#[derive(Debug)]
pub struct WanTransformer3DModel {
    config: WanTransformer3DModelConfig,
    patch_embedding_weight: Tensor,
    patch_embedding_bias: Tensor,
    condition_embedder: WanTimeTextImageEmbedding,
    blocks: Vec<WanTransformerBlock>,
    norm_out: LayerNorm,
    proj_out: Linear,
    scale_shift_table: Tensor,
}

impl WanTransformer3DModel {
    /// Creates the variables under `vars` (the checkpoint's root: `patch_embedding.weight`, …).
    pub fn new(vars: &Vars, config: &WanTransformer3DModelConfig) -> Result<Self> {
        config.validate("transformer config")?;
        let c = config;
        let dim = c.inner_dim();
        let [pt, ph, pw] = c.patch_size;
        let fan_in = c.in_channels * pt * ph * pw;
        let patch = vars.sub("patch_embedding");
        let blocks = vars.sub("blocks");
        Ok(Self {
            config: config.clone(),
            patch_embedding_weight: patch.param(
                "weight",
                &[dim, c.in_channels, pt, ph, pw],
                ParamInit::FanInUniform(fan_in),
            )?,
            patch_embedding_bias: patch.param("bias", &[dim], ParamInit::FanInUniform(fan_in))?,
            condition_embedder: WanTimeTextImageEmbedding::new(&vars.sub("condition_embedder"), c)?,
            blocks: (0..c.num_layers).map(|i| WanTransformerBlock::new(&blocks.sub(i), c)).collect::<Result<_>>()?,
            norm_out: vars.sub("norm_out").layer_norm(dim, c.eps, false)?,
            proj_out: vars.sub("proj_out").linear(dim, c.output_channels() * pt * ph * pw, true)?,
            scale_shift_table: vars.param(
                "scale_shift_table",
                &[1, 2, dim],
                ParamInit::Normal(1.0 / (dim as f64).sqrt()),
            )?,
        })
    }

    /// The configuration the model was built from.
    pub fn config(&self) -> &WanTransformer3DModelConfig {
        &self.config
    }

    /// The prediction `[B, out_channels, F, H, W]` (the flow velocity, noise − sample, for Wan)
    /// for noisy latents, timesteps, text tokens and optional image tokens.
    pub fn forward(&self, input: &WanTransformerInput) -> Result<Tensor> {
        let c = &self.config;
        let [b, f, h, w] = self.check_input(input)?;
        let [pt, ph, pw] = c.patch_size;
        let grid = [f / pt, h / ph, w / pw];
        let rotary = rotary_embedding(c, grid, input.hidden_states.device())?;

        let hidden_states = input
            .hidden_states
            .f_conv3d(
                &self.patch_embedding_weight,
                Some(&self.patch_embedding_bias),
                [pt, ph, pw],
                [0, 0, 0],
                [1, 1, 1],
                1,
            )?
            .f_flatten(2, -1)?
            .f_transpose(1, 2)?
            .f_contiguous()?;

        let timestep = match input.timestep.dim() {
            0 => input.timestep.f_expand([b, 1], false)?,
            1 => input.timestep.f_unsqueeze(1)?,
            _ => input.timestep.shallow_clone(),
        };
        let conditions = self.condition_embedder.forward(
            &timestep,
            input.encoder_hidden_states,
            input.encoder_hidden_states_image,
        )?;
        let mut hidden_states = hidden_states;
        for block in &self.blocks {
            hidden_states = block.forward(
                &hidden_states,
                &conditions.text,
                conditions.image.as_ref(),
                &conditions.timestep_proj,
                &rotary,
            )?;
        }

        let kind = hidden_states.kind();
        let modulation = self.scale_shift_table.f_unsqueeze(0)?.f_add(&conditions.temb.f_unsqueeze(2)?)?;
        let m = modulation.f_chunk(2, 2)?;
        let (shift, scale) = (m[0].f_squeeze_dim(2)?, m[1].f_squeeze_dim(2)?);
        let normed = self.norm_out.forward_fp32(&hidden_states.f_to_kind(Kind::Float)?)?;
        let hidden_states = normed.f_mul(&scale.f_add_scalar(1.0)?)?.f_add(&shift)?.f_to_kind(kind)?;
        let out = self.proj_out.forward(&hidden_states)?;
        let [gf, gh, gw] = grid;
        Ok(out
            .f_reshape([b, gf, gh, gw, pt, ph, pw, -1])?
            .f_permute([0, 7, 1, 4, 2, 5, 3, 6])?
            .f_flatten(6, 7)?
            .f_flatten(4, 5)?
            .f_flatten(2, 3)?)
    }

    /// Checks names, shapes, dtypes and devices of the inputs; returns `[B, F, H, W]`.
    fn check_input(&self, input: &WanTransformerInput) -> Result<[i64; 4]> {
        let c = &self.config;
        let shape_err = |tensor: &str, expected: String, actual: Vec<i64>| Error::Shape {
            tensor: tensor.to_string(),
            expected,
            actual,
        };
        let hidden = input.hidden_states;
        let [pt, ph, pw] = c.patch_size;
        let expected_hidden =
            || format!("[B, {}, F, H, W] with F, H, W multiples of patch_size {:?}", c.in_channels, c.patch_size);
        let dims: [i64; 5] =
            hidden.size().try_into().map_err(|size| shape_err("hidden_states", expected_hidden(), size))?;
        let [b, ch, f, h, w] = dims;
        if ch != c.in_channels || b == 0 || f == 0 || f % pt != 0 || h % ph != 0 || w % pw != 0 || h == 0 || w == 0 {
            return Err(shape_err("hidden_states", expected_hidden(), hidden.size()));
        }
        let tokens = (f / pt) * (h / ph) * (w / pw);
        let t = input.timestep;
        let t_ok = t.dim() == 0 || (t.dim() == 1 && t.size()[0] == b) || (t.dim() == 2 && t.size() == [b, tokens]);
        if !t_ok {
            return Err(shape_err("timestep", format!("[{b}], [{b}, {tokens}] (one per token) or a scalar"), t.size()));
        }
        let text = input.encoder_hidden_states;
        let image_expected = c.image_dim.is_some();
        let text_len_ok = !image_expected || text.size().get(1) == Some(&TEXT_CONTEXT_LENGTH);
        if text.dim() != 3 || text.size()[0] != b || text.size()[2] != c.text_dim || !text_len_ok {
            let len = if image_expected { TEXT_CONTEXT_LENGTH.to_string() } else { "S".to_string() };
            return Err(shape_err("encoder_hidden_states", format!("[{b}, {len}, {}]", c.text_dim), text.size()));
        }
        match (c.image_dim, input.encoder_hidden_states_image) {
            (None, None) => {}
            (None, Some(_)) => {
                return Err(Error::InvalidArgument {
                    name: "encoder_hidden_states_image".to_string(),
                    reason: "given, but this config has no image embedder (image_dim is null)".to_string(),
                });
            }
            (Some(_), None) => {
                return Err(Error::InvalidArgument {
                    name: "encoder_hidden_states_image".to_string(),
                    reason: "required by this config (image_dim is set)".to_string(),
                });
            }
            (Some(image_dim), Some(image)) => {
                // FLF2V: two images per sample, whose tokens the positional table covers.
                let (images, tokens) = match c.pos_embed_seq_len {
                    Some(len) => (2 * b, (len % 2 == 0).then_some(len / 2)),
                    None => (b, None),
                };
                let size = image.size();
                let ok = size.len() == 3
                    && size[0] == images
                    && size[2] == image_dim
                    && size[1] > 0
                    && tokens.is_none_or(|n| size[1] == n);
                if !ok {
                    let n = tokens.map_or("N".to_string(), |n| n.to_string());
                    return Err(shape_err(
                        "encoder_hidden_states_image",
                        format!("[{images}, {n}, {image_dim}]"),
                        size,
                    ));
                }
            }
        }
        let kind = self.proj_out.weight().kind();
        let device = self.proj_out.weight().device();
        let floats = [("hidden_states", Some(hidden)), ("encoder_hidden_states", Some(text))]
            .into_iter()
            .chain([("encoder_hidden_states_image", input.encoder_hidden_states_image)]);
        for (name, tensor) in floats {
            if let Some(tensor) = tensor {
                weights::check_kind_device(name, tensor, kind, device)?;
            }
        }
        weights::check_device("timestep", t, device)?;
        Ok([b, f, h, w])
    }
}

/// A transformer on `device` in `kind` with its variables in a fresh VarStore (PyTorch's default
/// initialisation); in a lower precision the [`KEEP_IN_FP32_MODULES`] stay fp32, as diffusers
/// loads them, and [`crate::models::weights::load`] converts checkpoint tensors to each
/// variable's own dtype.
pub fn build(
    config: &WanTransformer3DModelConfig,
    device: Device,
    kind: Kind,
) -> Result<(nn::VarStore, WanTransformer3DModel)> {
    let mut vs = nn::VarStore::new(device);
    vs.set_kind(kind);
    let model = WanTransformer3DModel::new(&Vars::new(vs.root()), config)?;
    vs.set_kind(kind);
    keep_in_fp32(&vs)?;
    Ok((vs, model))
}

/// Input channels of the CogNVS hole mask on a Wan VAE's latent grid: the mask of each of the 4
/// frames a latent frame compresses (the VAEs' 4× temporal compression), as the image-to-video
/// pipeline folds its first-frame mask (`models::wan::cognvs::mask_channels`).
pub const COGNVS_MASK_CHANNELS: i64 = 4;

/// The patch embedding's weight, `[inner_dim, in_channels, pt, ph, pw]`.
pub const PATCH_EMBEDDING_WEIGHT: &str = "patch_embedding.weight";

/// The model of `config` (its variables in `vs`) widened to `in_channels` inputs: every variable
/// copied, the patch embedding's weight zero for the new input channels (after the old ones), so
/// that the widened model of `[x, anything]` on channels equals the original of `x`. This is how
/// a text-to-video checkpoint takes the CogNVS condition channels before training.
pub fn widen_in_channels(
    vs: &nn::VarStore,
    config: &WanTransformer3DModelConfig,
    in_channels: i64,
) -> Result<(nn::VarStore, WanTransformer3DModel)> {
    if in_channels < config.in_channels {
        return Err(Error::InvalidArgument {
            name: "in_channels".to_string(),
            reason: format!("{in_channels} is fewer than the model's {}", config.in_channels),
        });
    }
    let wide = WanTransformer3DModelConfig { in_channels, ..config.clone() };
    let old = vs.variables();
    let kind = old.get(PATCH_EMBEDDING_WEIGHT).map_or(Kind::Float, Tensor::kind);
    let (wide_vs, model) = build(&wide, vs.device(), kind)?;
    tch::no_grad(|| -> Result<()> {
        for (name, mut var) in wide_vs.variables() {
            let Some(source) = old.get(&name) else {
                return Err(Error::InvalidArgument {
                    name: "vs".to_string(),
                    reason: format!("no variable `{name}` in the model to widen"),
                });
            };
            if name == PATCH_EMBEDDING_WEIGHT {
                let _ = var.f_zero_()?;
                var.f_narrow(1, 0, config.in_channels)?.f_copy_(source)?;
            } else {
                var.f_copy_(source)?;
            }
        }
        Ok(())
    })?;
    Ok((wide_vs, model))
}

/// Loads a checkpoint (folder, file or index) into a store built by [`build`]: names and shapes
/// checked as [`crate::models::weights::load`] does, tensors of
/// [`KEYS_TO_IGNORE_ON_LOAD_UNEXPECTED`] skipped. Returns how many tensors were loaded.
pub fn load(vs: &nn::VarStore, path: &std::path::Path) -> Result<usize> {
    crate::models::weights::load_ignoring(vs, path, &KEYS_TO_IGNORE_ON_LOAD_UNEXPECTED)
}

/// Converts the variables of [`KEEP_IN_FP32_MODULES`] back to fp32 (in place: the model's handles
/// see the change).
pub fn keep_in_fp32(vs: &nn::VarStore) -> Result<()> {
    tch::no_grad(|| -> Result<()> {
        for (name, mut var) in vs.variables() {
            if name.split('.').any(|part| KEEP_IN_FP32_MODULES.contains(&part)) && var.kind() != Kind::Float {
                let fp32 = var.f_to_kind(Kind::Float)?;
                var.f_set_data(&fp32)?;
            }
        }
        Ok(())
    })
}

/// Name → shape of every variable of the model `config` describes, without allocating it.
pub fn variable_shapes(config: &WanTransformer3DModelConfig) -> Result<BTreeMap<String, Vec<i64>>> {
    let vs = nn::VarStore::new(Device::Cpu);
    WanTransformer3DModel::new(&Vars::shapes_only(vs.root()), config)?;
    Ok(crate::models::weights::variable_shapes(&vs))
}

// ------------------------------------------------------------------------------------------------
// LoRA
// ------------------------------------------------------------------------------------------------

/// The attention projections Wan LoRAs adapt (finetrainers' and diffusers' Wan recipes:
/// `to_q`, `to_k`, `to_v`, `to_out.0` of every block's self- and cross-attention), as peft
/// suffixes: files then hold `transformer.blocks.{i}.attn{1,2}.{module}.lora_{A,B}.weight`.
pub const LORA_TARGET_MODULES: [&str; 4] = ["to_q", "to_k", "to_v", "to_out.0"];
/// The image cross-attention's key and value projections of image-to-video models, which
/// diffusers' `WanLoraLoaderMixin` expects beside the text ones (it pads a text-to-video LoRA
/// with zero adapters on exactly these before loading it into an I2V transformer).
pub const LORA_IMAGE_TARGET_MODULES: [&str; 2] = ["add_k_proj", "add_v_proj"];

/// The linear layers of a block, for the message of a target that matches none.
const LORA_LAYER_NAMES: &str = "attention layers are `to_q`, `to_k`, `to_v`, `to_out.0` (and `add_k_proj`, \
                                `add_v_proj` with image cross-attention); feed-forward `ffn.net.0.proj`, `ffn.net.2`";

/// The LoRA targets of a Wan model: [`LORA_TARGET_MODULES`], plus
/// [`LORA_IMAGE_TARGET_MODULES`] when the model has image cross-attention (`added_kv_proj_dim`).
pub fn lora_target_modules(config: &WanTransformer3DModelConfig) -> Vec<String> {
    let image = config.added_kv_proj_dim.is_some().then_some(LORA_IMAGE_TARGET_MODULES.as_slice());
    LORA_TARGET_MODULES.iter().chain(image.into_iter().flatten()).map(|m| m.to_string()).collect()
}

/// A transformer as [`build`] with LoRA adapters on the linear layers `lora` targets, in a second
/// store: `(base, adapters, model)`. The base store comes back frozen (only the adapters get
/// gradients); every target must match at least one linear layer.
pub fn build_with_lora(
    config: &WanTransformer3DModelConfig,
    lora: &crate::models::lora::LoraConfig,
    device: Device,
    kind: Kind,
) -> Result<(nn::VarStore, nn::VarStore, WanTransformer3DModel)> {
    lora.validate("training config")?;
    let mut vs = nn::VarStore::new(device);
    let mut lora_vs = nn::VarStore::new(device);
    let model = WanTransformer3DModel::new(&Vars::new(vs.root()).with_lora(lora_vs.root(), lora), config)?;
    crate::models::lora::check_targets(lora, &lora_vs, LORA_LAYER_NAMES)?;
    vs.set_kind(kind);
    keep_in_fp32(&vs)?;
    vs.freeze();
    lora_vs.set_kind(kind);
    Ok((vs, lora_vs, model))
}

/// Checks `lora` against the model `config` describes without allocating it (every target
/// matches a linear layer; the rank fits each); returns the adapters' names and parameter counts
/// (`r·in + out·r` per adapted layer).
pub fn lora_shapes(
    config: &WanTransformer3DModelConfig,
    lora: &crate::models::lora::LoraConfig,
) -> Result<Vec<(String, u64)>> {
    lora.validate("training config")?;
    let vs = nn::VarStore::new(Device::Cpu);
    let lora_vs = nn::VarStore::new(Device::Cpu);
    WanTransformer3DModel::new(&Vars::shapes_only(vs.root()).with_lora(lora_vs.root(), lora), config)?;
    crate::models::lora::check_targets(lora, &lora_vs, LORA_LAYER_NAMES)?;
    Ok(crate::models::lora::adapter_sizes(&lora_vs))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn inputs(c: &WanTransformer3DModelConfig, text_len: i64) -> (Tensor, Tensor, Tensor) {
        let opts = (Kind::Float, Device::Cpu);
        (
            Tensor::randn([1, c.in_channels, 2, 4, 6], opts),
            Tensor::from_slice(&[500.0f32]),
            Tensor::randn([1, text_len, c.text_dim], opts),
        )
    }

    #[test]
    fn tiny_forward_has_the_output_shape() {
        let c = WanTransformer3DModelConfig::tiny_t2v();
        let (_vs, model) = build(&c, Device::Cpu, Kind::Float).unwrap();
        let (x, t, text) = inputs(&c, 5);
        let input = WanTransformerInput {
            hidden_states: &x,
            timestep: &t,
            encoder_hidden_states: &text,
            encoder_hidden_states_image: None,
        };
        let out = model.forward(&input).unwrap();
        assert_eq!(out.size(), vec![1, 4, 2, 4, 6]);
        assert!(out.isfinite().all().int64_value(&[]) == 1);
    }

    #[test]
    fn bad_inputs_are_named_errors() {
        let c = WanTransformer3DModelConfig::tiny_i2v();
        let (_vs, model) = build(&c, Device::Cpu, Kind::Float).unwrap();
        let (x, t, text) = inputs(&c, TEXT_CONTEXT_LENGTH);
        let image = Tensor::randn([1, 3, 24], (Kind::Float, Device::Cpu));
        let ok = |x: &Tensor, text: &Tensor, image: Option<&Tensor>, t: &Tensor| {
            let input = WanTransformerInput {
                hidden_states: x,
                timestep: t,
                encoder_hidden_states: text,
                encoder_hidden_states_image: image,
            };
            model.forward(&input).map(|_| ()).map_err(|e| e.to_string())
        };
        ok(&x, &text, Some(&image), &t).unwrap();
        let err = ok(&x, &text, None, &t).unwrap_err();
        assert!(err.contains("encoder_hidden_states_image") && err.contains("required"), "{err}");
        let err = ok(&x, &text.narrow(1, 0, 7), Some(&image), &t).unwrap_err();
        assert!(err.contains("encoder_hidden_states") && err.contains("512"), "{err}");
        let err = ok(&x.narrow(3, 0, 3), &text, Some(&image), &t).unwrap_err();
        assert!(err.contains("hidden_states") && err.contains("patch_size"), "{err}");
        let err = ok(&x, &text, Some(&image), &Tensor::zeros([1, 5], (Kind::Float, Device::Cpu))).unwrap_err();
        assert!(err.contains("timestep") && err.contains("[1, 12]"), "{err}");
        let err = ok(&x.to_kind(Kind::BFloat16), &text, Some(&image), &t).unwrap_err();
        assert!(err.contains("BFloat16") && err.contains("Float"), "{err}");
    }

    #[test]
    fn config_checks_name_the_field() {
        let err = |json: &str| WanTransformer3DModelConfig::from_json_str(json, "c.json").unwrap_err().to_string();
        let e = err(r#"{"added_kv_proj_dim": 5120}"#);
        assert!(e.contains("c.json") && e.contains("added_kv_proj_dim") && e.contains("image_dim"), "{e}");
        let e = err(r#"{"image_dim": 1280, "added_kv_proj_dim": 64}"#);
        assert!(e.contains("added_kv_proj_dim") && e.contains("5120"), "{e}");
        let e = err(r#"{"attention_head_dim": 15}"#);
        assert!(e.contains("attention_head_dim") && e.contains("even"), "{e}");
        let e = err(r#"{"patch_size": [1, 0, 2]}"#);
        assert!(e.contains("patch_size"), "{e}");
        let e = err(r#"{"_class_name": "CogVideoXTransformer3DModel"}"#);
        assert!(e.contains("_class_name") && e.contains(CLASS_NAME), "{e}");
        let c = WanTransformer3DModelConfig::from_json_str(r#"{"qk_norm": "rms_norm", "mystery": 1}"#, "c").unwrap();
        assert_eq!(c.unknown_keys(), vec!["mystery"]);
        assert!(c.warnings()[0].contains("qk_norm"));
    }

    /// diffusers' split of 128 rotary channels (44 temporal, 42 + 42 spatial) and of the tiny
    /// preset's 16.
    #[test]
    fn rotary_channels_split_as_diffusers() {
        assert_eq!(WanTransformer3DModelConfig::default().rotary_split(), [44, 42, 42]);
        assert_eq!(WanTransformer3DModelConfig::tiny_t2v().rotary_split(), [8, 4, 4]);
    }
}

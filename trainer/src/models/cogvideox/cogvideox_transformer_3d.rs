//! The CogVideoX diffusion transformer: diffusers' `CogVideoXTransformer3DModel`
//! (`diffusers/models/transformers/cogvideox_transformer_3d.py`), weight-compatible with it and
//! with the released CogNVS checkpoint (its `config.json`: 42 blocks of 48 heads × 64, 32 input
//! channels = 16 noisy + 16 condition latents, learned + 3D rotary positions).
//!
//! Latent video `[B, F, C, H, W]` is cut into `patch_size²` patches, joined behind the projected
//! text tokens and run through `num_layers` [`CogVideoXBlock`]s, each modulated by the timestep
//! embedding; the final modulated norm and `proj_out` map video tokens back to
//! `[B, F, out_channels, H, W]`. Variables live at diffusers' state-dict paths, so a diffusers
//! checkpoint loads unchanged ([`crate::models::weights::load`]) and [`crate::models::weights::save`] writes one
//! diffusers' `from_pretrained` reads.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor, nn};

use crate::diffusers_config::{self, DiffusersConfig};
use crate::error::{Error, Result};
use crate::models::attention::{Activation, Attention, FeedForward};
use crate::models::embeddings::{
    CogVideoXPatchEmbed, PatchEmbedConfig, PositionalEmbedding, RotaryEmbedding, TimestepEmbedding, timestep_embedding,
};
use crate::models::lora::LoraConfig;
use crate::models::normalization::{AdaLayerNorm, CogVideoXLayerNormZero};
use crate::models::vars::{LayerNorm, Linear, Vars};
use crate::models::weights;

/// The class name diffusers writes into the transformer's `config.json` (`_class_name`).
pub const CLASS_NAME: &str = "CogVideoXTransformer3DModel";
/// Feed-forward width as a multiple of the token width (diffusers' `FeedForward` `mult=4`).
const FF_MULT: i64 = 4;

// ------------------------------------------------------------------------------------------------
// Configuration
// ------------------------------------------------------------------------------------------------

/// The transformer's `config.json` as diffusers writes it, field names verbatim. Missing fields
/// take diffusers' `__init__` defaults (the CogVideoX-2B transformer); keys starting with `_` are
/// diffusers metadata; any other key is kept in `extra` and reported, not dropped.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CogVideoXTransformer3DModelConfig {
    /// Attention heads per block.
    pub num_attention_heads: i64,
    /// Channels per head; tokens are `heads × head_dim` wide.
    pub attention_head_dim: i64,
    /// Latent channels in (CogNVS: 16 noisy + 16 condition = 32).
    pub in_channels: i64,
    /// Latent channels out (defaults to `in_channels` when null).
    pub out_channels: Option<i64>,
    /// Timestep features ordered cos then sin.
    pub flip_sin_to_cos: bool,
    /// `downscale_freq_shift` of the timestep features.
    pub freq_shift: i64,
    /// Width of the timestep embedding that modulates every norm.
    pub time_embed_dim: i64,
    /// Width of the CogVideoX 1.5 I2V "ofs" embedding; null for none.
    pub ofs_embed_dim: Option<i64>,
    /// Width of the text encoder's tokens (T5-XXL: 4096).
    pub text_embed_dim: i64,
    /// Transformer blocks.
    pub num_layers: i64,
    /// Dropout of embeddings, attention output and feed-forward (training only).
    pub dropout: f64,
    /// Bias in the q/k/v projections.
    pub attention_bias: bool,
    /// Nominal latent width of the positional table.
    pub sample_width: i64,
    /// Nominal latent height of the positional table.
    pub sample_height: i64,
    /// Nominal pixel frames of the positional table (49 → 13 latent frames).
    pub sample_frames: i64,
    /// Spatial patch size.
    pub patch_size: i64,
    /// Temporal patch size (CogVideoX 1.5); null patches frames one by one.
    pub patch_size_t: Option<i64>,
    /// Pixel frames per latent frame.
    pub temporal_compression_ratio: i64,
    /// Text tokens in front of the video tokens.
    pub max_text_seq_length: i64,
    /// Feed-forward activation (`gelu-approximate`).
    pub activation_fn: String,
    /// Activation inside the timestep MLP (`silu`).
    pub timestep_activation_fn: String,
    /// Learned scale and shift in every LayerNorm.
    pub norm_elementwise_affine: bool,
    /// LayerNorm epsilon (the QK norms use 1e-6 whatever this is, as diffusers).
    pub norm_eps: f64,
    /// Divisor of spatial positions in the sin-cos table.
    pub spatial_interpolation_scale: f64,
    /// Divisor of temporal positions in the sin-cos table.
    pub temporal_interpolation_scale: f64,
    /// 3D rotary embeddings on queries and keys (otherwise the sin-cos table is added).
    pub use_rotary_positional_embeddings: bool,
    /// A stored, learned positional table `patch_embed.pos_embedding` (needs rotary too).
    pub use_learned_positional_embeddings: bool,
    /// Bias in the patch projection.
    pub patch_bias: bool,
    /// Every other key: `_class_name`, `_diffusers_version`, … and unknown keys.
    #[serde(flatten)]
    pub extra: BTreeMap<String, serde_json::Value>,
}

impl Default for CogVideoXTransformer3DModelConfig {
    /// diffusers' `CogVideoXTransformer3DModel.__init__` defaults (= `THUDM/CogVideoX-2b`
    /// `transformer/config.json`).
    fn default() -> Self {
        Self {
            num_attention_heads: 30,
            attention_head_dim: 64,
            in_channels: 16,
            out_channels: Some(16),
            flip_sin_to_cos: true,
            freq_shift: 0,
            time_embed_dim: 512,
            ofs_embed_dim: None,
            text_embed_dim: 4096,
            num_layers: 30,
            dropout: 0.0,
            attention_bias: true,
            sample_width: 90,
            sample_height: 60,
            sample_frames: 49,
            patch_size: 2,
            patch_size_t: None,
            temporal_compression_ratio: 4,
            max_text_seq_length: 226,
            activation_fn: "gelu-approximate".to_string(),
            timestep_activation_fn: "silu".to_string(),
            norm_elementwise_affine: true,
            norm_eps: 1e-5,
            spatial_interpolation_scale: 1.875,
            temporal_interpolation_scale: 1.0,
            use_rotary_positional_embeddings: false,
            use_learned_positional_embeddings: false,
            patch_bias: true,
            extra: BTreeMap::new(),
        }
    }
}

impl DiffusersConfig for CogVideoXTransformer3DModelConfig {
    const KIND: &'static str = "transformer";
    const CLASS_NAMES: &'static [&'static str] = &[CLASS_NAME];
    const FILE_NAME: &'static str = "config.json";

    /// Rejects values and combinations the architecture cannot build, naming the field.
    fn validate_fields(&self, source_name: &str) -> Result<()> {
        let err = diffusers_config::field_error(source_name);
        let sizes = [
            ("num_attention_heads", self.num_attention_heads),
            ("attention_head_dim", self.attention_head_dim),
            ("in_channels", self.in_channels),
            ("out_channels", self.output_channels()),
            ("time_embed_dim", self.time_embed_dim),
            ("text_embed_dim", self.text_embed_dim),
            ("num_layers", self.num_layers),
            ("sample_width", self.sample_width),
            ("sample_height", self.sample_height),
            ("sample_frames", self.sample_frames),
            ("patch_size", self.patch_size),
            ("temporal_compression_ratio", self.temporal_compression_ratio),
            ("max_text_seq_length", self.max_text_seq_length),
        ];
        diffusers_config::require_positive(source_name, &sizes)?;
        // Token width and the positional table, as the model forms them from several fields.
        let inner = self.num_attention_heads.checked_mul(self.attention_head_dim).filter(|&d| d <= MAX_DIMENSION);
        if inner.is_none() {
            return Err(err(
                "num_attention_heads",
                format!(
                    "num_attention_heads × attention_head_dim = {} × {} is more than {MAX_DIMENSION} channels",
                    self.num_attention_heads, self.attention_head_dim
                ),
            ));
        }
        for (field, value) in sizes {
            if value > MAX_DIMENSION {
                return Err(err(field, format!("must be at most {MAX_DIMENSION}, got {value}")));
            }
        }
        let table = ((self.sample_frames - 1) / self.temporal_compression_ratio + 1)
            .checked_mul(self.sample_height / self.patch_size)
            .and_then(|n| n.checked_mul(self.sample_width / self.patch_size))
            .and_then(|n| n.checked_add(self.max_text_seq_length))
            .and_then(|n| n.checked_mul(self.inner_dim()))
            .filter(|&n| n <= MAX_TABLE_ELEMENTS);
        if table.is_none() {
            return Err(err(
                "sample_frames",
                format!(
                    "the positional table of sample_frames × sample_height × sample_width = {} × {} × {} (in \
                     patches of {}, plus max_text_seq_length {}) by {} channels has more than \
                     {MAX_TABLE_ELEMENTS} values",
                    self.sample_frames,
                    self.sample_height,
                    self.sample_width,
                    self.patch_size,
                    self.max_text_seq_length,
                    self.inner_dim()
                ),
            ));
        }
        if let Some(v) = self.ofs_embed_dim.filter(|&v| v <= 0) {
            return Err(err("ofs_embed_dim", format!("must be positive or null, got {v}")));
        }
        if let Some(v) = self.patch_size_t.filter(|&v| v <= 0) {
            return Err(err("patch_size_t", format!("must be positive or null, got {v}")));
        }
        if !(0.0..1.0).contains(&self.dropout) {
            return Err(err("dropout", format!("must be in [0, 1), got {}", self.dropout)));
        }
        if Activation::from_name(&self.activation_fn).is_none() {
            return Err(err(
                "activation_fn",
                format!("`{}` is not supported (gelu-approximate, gelu)", self.activation_fn),
            ));
        }
        if self.timestep_activation_fn != "silu" && self.timestep_activation_fn != "swish" {
            return Err(err(
                "timestep_activation_fn",
                format!("`{}` is not supported (only silu)", self.timestep_activation_fn),
            ));
        }
        if !self.use_rotary_positional_embeddings && self.use_learned_positional_embeddings {
            return Err(err(
                "use_learned_positional_embeddings",
                "true needs use_rotary_positional_embeddings (no CogVideoX model has learned positions alone; \
                 diffusers rejects it too)"
                    .to_string(),
            ));
        }
        if self.positional_embedding() != PositionalEmbedding::None {
            if self.patch_size_t.is_some() {
                return Err(err(
                    "patch_size_t",
                    "temporal patching with a sin-cos or learned positional table is not supported \
                     (CogVideoX 1.5 uses rotary positions only)"
                        .to_string(),
                ));
            }
            if self.inner_dim() % 16 != 0 {
                return Err(err(
                    "num_attention_heads",
                    format!("heads × head_dim = {} must be a multiple of 16 for the sin-cos table", self.inner_dim()),
                ));
            }
        }
        if self.use_rotary_positional_embeddings && self.attention_head_dim % 8 != 0 {
            return Err(err(
                "attention_head_dim",
                format!("{} must be a multiple of 8 for 3D rotary positions", self.attention_head_dim),
            ));
        }
        if self.sample_height % self.patch_size != 0 || self.sample_width % self.patch_size != 0 {
            return Err(err(
                "patch_size",
                format!(
                    "sample_height × sample_width {} × {} must be multiples of patch_size {}",
                    self.sample_height, self.sample_width, self.patch_size
                ),
            ));
        }
        if self.norm_eps <= 0.0 {
            return Err(err("norm_eps", format!("must be positive, got {}", self.norm_eps)));
        }
        Ok(())
    }

    fn extra(&self) -> &BTreeMap<String, serde_json::Value> {
        &self.extra
    }
}

/// Largest value of one size field of the config (channels, heads, head width, layers, tokens,
/// latent sizes) and of the token width heads × head_dim: far above every released model's
/// (3072 channels, 48 heads, 226 text tokens, 42 layers, 90 latents a side), and small enough
/// that the products the model forms from two or three of them stay inside 64-bit sizes.
pub const MAX_DIMENSION: i64 = 1 << 20;

/// Most values of the positional table (tokens × channels): the released models' is 17 550 ×
/// 3072 ≈ 5.4e7; 2^36 (256 GiB in f32) is beyond any device, so a larger one is a config error.
pub const MAX_TABLE_ELEMENTS: i64 = 1 << 36;

impl CogVideoXTransformer3DModelConfig {
    /// The released CogNVS transformer (its checkpoint's `config.json`)
    /// (the CogVideoX-5B-I2V architecture: 42 × 48 heads × 64, learned + rotary positions) with
    /// 32 input channels.
    pub fn cognvs_5b() -> Self {
        Self {
            num_attention_heads: 48,
            in_channels: 32,
            num_layers: 42,
            use_rotary_positional_embeddings: true,
            use_learned_positional_embeddings: true,
            ..Self::default()
        }
    }

    /// The CogVideoX-2B transformer (`THUDM/CogVideoX-2b`: 30 × 30 heads × 64, sin-cos positions,
    /// = diffusers' defaults).
    pub fn cogvideox_2b() -> Self {
        Self::default()
    }

    /// The CogNVS structure (32 → 16 latent channels, learned + rotary positions, QK norm,
    /// gelu-tanh) at small widths for tests and CPU runs: 2 blocks of 2 heads × 16, 8 text tokens
    /// of width 16, and a positional table for 9 frames of 8 × 10 latents (the tiny VAE's 64 × 80
    /// pixels). `scripts/goldens_transformer.py` builds the same model in diffusers.
    pub fn tiny() -> Self {
        Self {
            num_attention_heads: 2,
            attention_head_dim: 16,
            in_channels: 32,
            out_channels: Some(16),
            time_embed_dim: 32,
            text_embed_dim: 16,
            num_layers: 2,
            sample_width: 10,
            sample_height: 8,
            sample_frames: 9,
            max_text_seq_length: 8,
            use_rotary_positional_embeddings: true,
            use_learned_positional_embeddings: true,
            ..Self::default()
        }
    }

    /// A preset by name: `cognvs-5b`, `cogvideox-2b`, `tiny`.
    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "cognvs-5b" => Ok(Self::cognvs_5b()),
            "cogvideox-2b" => Ok(Self::cogvideox_2b()),
            "tiny" => Ok(Self::tiny()),
            other => Err(Error::InvalidConfig {
                source_name: "preset".to_string(),
                field: "name".to_string(),
                reason: format!("unknown transformer preset `{other}`; expected cognvs-5b, cogvideox-2b or tiny"),
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

    /// Which positional embedding the patch embedding adds.
    pub fn positional_embedding(&self) -> PositionalEmbedding {
        match (self.use_rotary_positional_embeddings, self.use_learned_positional_embeddings) {
            (_, true) => PositionalEmbedding::Learned,
            (false, false) => PositionalEmbedding::SinCos,
            (true, false) => PositionalEmbedding::None,
        }
    }

    fn patch_embed_config(&self) -> PatchEmbedConfig {
        PatchEmbedConfig {
            patch_size: self.patch_size,
            patch_size_t: self.patch_size_t,
            in_channels: self.in_channels,
            embed_dim: self.inner_dim(),
            text_embed_dim: self.text_embed_dim,
            sample_width: self.sample_width,
            sample_height: self.sample_height,
            sample_frames: self.sample_frames,
            temporal_compression_ratio: self.temporal_compression_ratio,
            max_text_seq_length: self.max_text_seq_length,
            spatial_interpolation_scale: self.spatial_interpolation_scale,
            temporal_interpolation_scale: self.temporal_interpolation_scale,
            positional: self.positional_embedding(),
        }
    }
}

// ------------------------------------------------------------------------------------------------
// Model
// ------------------------------------------------------------------------------------------------

/// diffusers' `CogVideoXBlock`: modulated joint attention then a modulated feed-forward over the
/// joint sequence, each added back through per-stream gates.
#[derive(Debug)]
pub struct CogVideoXBlock {
    norm1: CogVideoXLayerNormZero,
    attn1: Attention,
    norm2: CogVideoXLayerNormZero,
    ff: FeedForward,
}

impl CogVideoXBlock {
    /// Variables `norm1`, `attn1`, `norm2`, `ff`.
    pub fn new(vars: &Vars, c: &CogVideoXTransformer3DModelConfig) -> Result<Self> {
        let dim = c.inner_dim();
        let activation = Activation::from_name(&c.activation_fn).expect("validated config");
        let norm = |name: &str| {
            CogVideoXLayerNormZero::new(&vars.sub(name), c.time_embed_dim, dim, c.norm_elementwise_affine, c.norm_eps)
        };
        Ok(Self {
            norm1: norm("norm1")?,
            attn1: Attention::new(
                &vars.sub("attn1"),
                dim,
                c.num_attention_heads,
                c.attention_head_dim,
                c.attention_bias,
                true,
                c.dropout,
            )?,
            norm2: norm("norm2")?,
            ff: FeedForward::new(&vars.sub("ff"), dim, FF_MULT * dim, activation, c.dropout)?,
        })
    }

    /// One block: `(video, text)` → `(video, text)`.
    pub fn forward(
        &self,
        hidden_states: &Tensor,
        encoder_hidden_states: &Tensor,
        temb: &Tensor,
        rotary: Option<&RotaryEmbedding>,
        train: bool,
    ) -> Result<(Tensor, Tensor)> {
        let text_len = encoder_hidden_states.size()[1];
        let m = self.norm1.forward(hidden_states, encoder_hidden_states, temb)?;
        let (attn, attn_text) = self.attn1.forward(&m.hidden_states, &m.encoder_hidden_states, rotary, train)?;
        let hidden_states = hidden_states.f_add(&m.gate.f_mul(&attn)?)?;
        let encoder_hidden_states = encoder_hidden_states.f_add(&m.encoder_gate.f_mul(&attn_text)?)?;

        let m = self.norm2.forward(&hidden_states, &encoder_hidden_states, temb)?;
        let joint = Tensor::f_cat(&[&m.encoder_hidden_states, &m.hidden_states], 1)?;
        let ff = self.ff.forward(&joint, train)?;
        let video_len = ff.size()[1] - text_len;
        let hidden_states = hidden_states.f_add(&m.gate.f_mul(&ff.f_narrow(1, text_len, video_len)?)?)?;
        let encoder_hidden_states =
            encoder_hidden_states.f_add(&m.encoder_gate.f_mul(&ff.f_narrow(1, 0, text_len)?)?)?;
        Ok((hidden_states, encoder_hidden_states))
    }
}

/// The inputs of one transformer call, named after diffusers' `forward` arguments.
#[derive(Debug)]
pub struct TransformerInput<'a> {
    /// Noisy (and, for CogNVS, condition) latents `[B, F, in_channels, H, W]`.
    pub hidden_states: &'a Tensor,
    /// Text tokens `[B, max_text_seq_length, text_embed_dim]`.
    pub encoder_hidden_states: &'a Tensor,
    /// Diffusion timestep per sample `[B]` (or one scalar for the batch).
    pub timestep: &'a Tensor,
    /// CogVideoX 1.5 I2V offsets `[B]`, required when `ofs_embed_dim` is set.
    pub ofs: Option<&'a Tensor>,
    /// A rotary table to use instead of the `grid_type="slice"` one computed from the input's
    /// latent patch grid (e.g. a pipeline's `"linspace"` grid).
    pub image_rotary_emb: Option<&'a RotaryEmbedding>,
}

/// What the blocks start from: the embeddings of one transformer call.
struct Embedded {
    emb: Tensor,
    hidden_states: Tensor,
    encoder_hidden_states: Tensor,
    rotary: Option<RotaryEmbedding>,
    dims: [i64; 4],
}

/// The modules after the blocks (see [`CogVideoXTransformer3DModel`]'s `head`): their gradients
/// are final once the loss has been back-propagated to the last block's output.
const HEAD_MODULES: [&str; 3] = ["norm_final", "norm_out", "proj_out"];

/// Reseeds tch's generator for block `i` when dropout is active.
fn reseed(seeds: Option<&[i64]>, i: usize) {
    if let Some(seeds) = seeds {
        tch::manual_seed(seeds[i]);
    }
}

/// Reseeds tch's generator with the seed that follows the blocks when dropout is active.
fn reseed_after_blocks(seeds: Option<&[i64]>) {
    if let Some(&last) = seeds.and_then(|s| s.last()) {
        tch::manual_seed(last);
    }
}

/// What [`CogVideoXTransformer3DModel::forward_taped`] keeps for its backward, which runs block
/// by block: each block's `(video, text)` input as a leaf of its own (the blocks' graphs, or,
/// with checkpointing, nothing: the blocks are recomputed), the leaves the head and the blocks
/// were built on, and the embedding outputs whose graphs lead to the patch and time embeddings.
pub struct BlockTape<'m> {
    model: &'m CogVideoXTransformer3DModel,
    /// Per block: its input leaves, and its outputs when their graphs are kept.
    blocks: Vec<TapedBlock>,
    last: Tensor,
    emb_leaf: Tensor,
    embedded_emb: Tensor,
    embedded_video: Tensor,
    embedded_text: Tensor,
    rotary: Option<RotaryEmbedding>,
    seeds: Option<Vec<i64>>,
    train: bool,
}

/// One block on a [`BlockTape`].
struct TapedBlock {
    video: Tensor,
    text: Tensor,
    /// The block's `(video, text)` outputs with their graphs (None: recompute the block).
    outputs: Option<(Tensor, Tensor)>,
}

impl BlockTape<'_> {
    /// Back-propagates through the blocks and the embeddings, once the output of
    /// [`CogVideoXTransformer3DModel::forward_taped`] has had its loss back-propagated (which
    /// leaves the gradient on the last block's output and finishes the head's). Parameter
    /// gradients accumulate, as with a plain `backward`. `on_stage(k)` is called as soon as the
    /// gradients of stage k's parameters are final (see
    /// [`CogVideoXTransformer3DModel::backward_stage_of`]): stage 0 (the head) first, then one
    /// stage per block from the last block to the first, then the embeddings.
    pub fn backward(self, on_stage: &mut dyn FnMut(usize) -> Result<()>) -> Result<()> {
        let mut grad_video = self.last.grad();
        if !grad_video.defined() {
            return Err(Error::InvalidArgument {
                name: "gradient checkpointing".to_string(),
                reason: "the output's loss must be back-propagated before the blocks".to_string(),
            });
        }
        on_stage(0)?;
        // diffusers drops the text stream after the last block: its gradient there is zero.
        let mut grad_text: Option<Tensor> = None;
        let rotary = self.rotary.as_ref();
        let count = self.blocks.len();
        let recomputed = self.blocks.iter().any(|b| b.outputs.is_none());
        for (i, (block, taped)) in self.model.transformer_blocks.iter().zip(self.blocks).enumerate().rev() {
            let TapedBlock { video, text, outputs } = taped;
            let (video, text, (out_video, out_text)) = match outputs {
                Some(outputs) => (video, text, outputs),
                None => {
                    reseed(self.seeds.as_deref(), i);
                    let video = video.detach().set_requires_grad(true);
                    let text = text.detach().set_requires_grad(true);
                    let outputs = block.forward(&video, &text, &self.emb_leaf, rotary, self.train)?;
                    (video, text, outputs)
                }
            };
            let mut surrogate = out_video.f_mul(&grad_video)?.f_sum(Kind::Float)?;
            if let Some(g) = &grad_text {
                surrogate = surrogate.f_add(&out_text.f_mul(g)?.f_sum(Kind::Float)?)?;
            }
            surrogate.f_backward()?;
            grad_video = video.grad();
            grad_text = Some(text.grad());
            on_stage(count - i)?;
        }
        if recomputed {
            reseed_after_blocks(self.seeds.as_deref());
        }
        let mut surrogate = self.embedded_video.f_mul(&grad_video)?.f_sum(Kind::Float)?;
        if let Some(g) = &grad_text {
            surrogate = surrogate.f_add(&self.embedded_text.f_mul(g)?.f_sum(Kind::Float)?)?;
        }
        let grad_emb = self.emb_leaf.grad();
        if grad_emb.defined() {
            surrogate = surrogate.f_add(&self.embedded_emb.f_mul(&grad_emb)?.f_sum(Kind::Float)?)?;
        }
        // With LoRA (or any frozen embedding) nothing below the blocks trains: no graph to walk.
        if surrogate.requires_grad() {
            surrogate.f_backward()?;
        }
        on_stage(count + 1)
    }
}

/// diffusers' `CogVideoXTransformer3DModel`.
#[derive(Debug)]
pub struct CogVideoXTransformer3DModel {
    config: CogVideoXTransformer3DModelConfig,
    patch_embed: CogVideoXPatchEmbed,
    time_embedding: TimestepEmbedding,
    ofs_embedding: Option<TimestepEmbedding>,
    transformer_blocks: Vec<CogVideoXBlock>,
    norm_final: LayerNorm,
    norm_out: AdaLayerNorm,
    proj_out: Linear,
    kind_probe: Tensor,
}

impl CogVideoXTransformer3DModel {
    /// Creates the variables under `vars` (the checkpoint's root: `patch_embed.proj.weight`, …).
    pub fn new(vars: &Vars, config: &CogVideoXTransformer3DModelConfig) -> Result<Self> {
        config.validate("transformer config")?;
        let c = config;
        let dim = c.inner_dim();
        let patch_embed = CogVideoXPatchEmbed::new(&vars.sub("patch_embed"), c.patch_embed_config(), c.patch_bias)?;
        let time_embedding = TimestepEmbedding::new(&vars.sub("time_embedding"), dim, c.time_embed_dim)?;
        let ofs_embedding = match c.ofs_embed_dim {
            Some(d) => Some(TimestepEmbedding::new(&vars.sub("ofs_embedding"), d, d)?),
            None => None,
        };
        let blocks = vars.sub("transformer_blocks");
        let transformer_blocks =
            (0..c.num_layers).map(|i| CogVideoXBlock::new(&blocks.sub(i), c)).collect::<Result<Vec<_>>>()?;
        let norm_final = vars.sub("norm_final").layer_norm(dim, c.norm_eps, c.norm_elementwise_affine)?;
        let norm_out =
            AdaLayerNorm::new(&vars.sub("norm_out"), c.time_embed_dim, 2 * dim, c.norm_elementwise_affine, c.norm_eps)?;
        let patch_volume = c.patch_size * c.patch_size * c.patch_size_t.unwrap_or(1);
        let proj_out = vars.sub("proj_out").linear(dim, patch_volume * c.output_channels(), true)?;
        let kind_probe = proj_out.weight().shallow_clone();
        Ok(Self {
            config: config.clone(),
            patch_embed,
            time_embedding,
            ofs_embedding,
            transformer_blocks,
            norm_final,
            norm_out,
            proj_out,
            kind_probe,
        })
    }

    /// The configuration the model was built from.
    pub fn config(&self) -> &CogVideoXTransformer3DModelConfig {
        &self.config
    }

    /// The rotary table the CogNVS trainer uses for a latent input of `frames × height × width`:
    /// `grid_type="slice"` positions over the patch grid.
    pub fn rotary_for(&self, frames: i64, height: i64, width: i64, device: Device) -> Result<RotaryEmbedding> {
        let c = &self.config;
        let t = frames / c.patch_size_t.unwrap_or(1);
        RotaryEmbedding::slice_grid(c.attention_head_dim, t, height / c.patch_size, width / c.patch_size, device)
    }

    /// The predicted latents `[B, F, out_channels, H, W]` (v-prediction for CogNVS) for noisy
    /// latents, text tokens and timesteps; dropout applies only when `train`.
    pub fn forward(&self, input: &TransformerInput, train: bool) -> Result<Tensor> {
        let embedded = self.embed(input, train)?;
        let seeds = self.block_seeds(train)?;
        let rotary = embedded.rotary.as_ref();
        let (mut hidden_states, mut encoder_hidden_states) = (embedded.hidden_states, embedded.encoder_hidden_states);
        for (i, block) in self.transformer_blocks.iter().enumerate() {
            reseed(seeds.as_deref(), i);
            (hidden_states, encoder_hidden_states) =
                block.forward(&hidden_states, &encoder_hidden_states, &embedded.emb, rotary, train)?;
        }
        reseed_after_blocks(seeds.as_deref());
        self.head(&hidden_states, &embedded.emb, embedded.dims)
    }

    /// [`forward`](Self::forward) for training block by block: every block starts from leaves of
    /// its own and the returned output's graph starts at the last block's output. After
    /// back-propagating a loss of that output, call [`BlockTape::backward`], which carries the
    /// gradient down one block at a time (last first) to the embeddings, so every parameter
    /// receives the gradient the plain forward would give it, and reports each finished stage as
    /// it goes (where a data-parallel run starts reducing those gradients).
    ///
    /// With `checkpointing` the blocks run without autograd and only each block's input is
    /// kept; the tape's backward recomputes each block: the same gradients for a fraction of the
    /// activation memory. Dropout replays identically: with dropout on, every block (in both
    /// forwards) reseeds tch's generator from a seed drawn before the blocks, and the generator
    /// continues after the tape's backward as it would after the plain forward, provided nothing
    /// draws from it between this call and [`BlockTape::backward`].
    pub fn forward_taped(
        &self,
        input: &TransformerInput,
        train: bool,
        checkpointing: bool,
    ) -> Result<(Tensor, BlockTape<'_>)> {
        let embedded = self.embed(input, train)?;
        let seeds = self.block_seeds(train)?;
        // The blocks see a leaf copy of the embedding whose gradient accumulates over the
        // blocks; the graph to the time embedding is walked once, at the end.
        let emb_leaf = embedded.emb.detach().set_requires_grad(true);
        let rotary = embedded.rotary.as_ref();
        let mut blocks = Vec::with_capacity(self.transformer_blocks.len());
        let (mut hidden_states, mut encoder_hidden_states) =
            (embedded.hidden_states.detach(), embedded.encoder_hidden_states.detach());
        for (i, block) in self.transformer_blocks.iter().enumerate() {
            reseed(seeds.as_deref(), i);
            let (video, text, outputs, next) = if checkpointing {
                let next =
                    tch::no_grad(|| block.forward(&hidden_states, &encoder_hidden_states, &emb_leaf, rotary, train))?;
                (hidden_states, encoder_hidden_states, None, next)
            } else {
                let video = hidden_states.detach().set_requires_grad(true);
                let text = encoder_hidden_states.detach().set_requires_grad(true);
                let (h, e) = block.forward(&video, &text, &emb_leaf, rotary, train)?;
                let outputs = (h.shallow_clone(), e.shallow_clone());
                (video, text, Some(outputs), (h, e))
            };
            blocks.push(TapedBlock { video, text, outputs });
            (hidden_states, encoder_hidden_states) = next;
        }
        reseed_after_blocks(seeds.as_deref());
        let last = hidden_states.detach().set_requires_grad(true);
        let out = self.head(&last, &emb_leaf, embedded.dims)?;
        let tape = BlockTape {
            model: self,
            blocks,
            last,
            emb_leaf,
            embedded_emb: embedded.emb,
            embedded_video: embedded.hidden_states,
            embedded_text: embedded.encoder_hidden_states,
            rotary: embedded.rotary,
            seeds,
            train,
        };
        Ok((out, tape))
    }

    /// Stages of [`BlockTape::backward`]: the head, one per block, the embeddings.
    pub fn backward_stages(&self) -> usize {
        self.transformer_blocks.len() + 2
    }

    /// The stage of [`BlockTape::backward`] after which the gradient of variable `name` (its
    /// path in the checkpoint, `transformer_blocks.3.attn1.to_q.weight`; LoRA adapters' paths
    /// extend their layer's) is final: 0 for the head (`norm_final`, `norm_out`, `proj_out`),
    /// `L − i` for block i of L, `L + 1` for everything else (the patch, time and ofs embeddings).
    pub fn backward_stage_of(&self, name: &str) -> usize {
        let count = self.transformer_blocks.len();
        let module = name.split('.').next().unwrap_or_default();
        if HEAD_MODULES.contains(&module) {
            return 0;
        }
        let block = name
            .strip_prefix("transformer_blocks.")
            .and_then(|rest| rest.split('.').next())
            .and_then(|index| index.parse::<usize>().ok())
            .filter(|&i| i < count);
        match block {
            Some(i) => count - i,
            None => count + 1,
        }
    }

    /// The timestep embedding, the patch-embedded joint sequence split into text and video
    /// tokens, and the rotary table.
    fn embed(&self, input: &TransformerInput, train: bool) -> Result<Embedded> {
        let c = &self.config;
        let [b, f, h, w] = self.check_input(input)?;
        let timestep = if input.timestep.dim() == 0 {
            input.timestep.f_expand([b], false)?
        } else {
            input.timestep.shallow_clone()
        };
        let kind = input.hidden_states.kind();

        let t_emb = timestep_embedding(&timestep, c.inner_dim(), c.flip_sin_to_cos, c.freq_shift as f64)?;
        let mut emb = self.time_embedding.forward(&t_emb.f_to_kind(kind)?)?;
        if let Some(ofs_embedding) = &self.ofs_embedding {
            let ofs = input.ofs.ok_or_else(|| Error::InvalidArgument {
                name: "ofs".to_string(),
                reason: "required by this config (ofs_embed_dim is set)".to_string(),
            })?;
            let ofs = if ofs.dim() == 0 { ofs.f_expand([b], false)? } else { ofs.shallow_clone() };
            let ofs_dim = c.ofs_embed_dim.expect("ofs embedding exists");
            let ofs_emb = timestep_embedding(&ofs, ofs_dim, c.flip_sin_to_cos, c.freq_shift as f64)?;
            emb = emb.f_add(&ofs_embedding.forward(&ofs_emb.f_to_kind(kind)?)?)?;
        }

        let joint = self.patch_embed.forward(input.encoder_hidden_states, input.hidden_states)?;
        let joint = joint.f_dropout(c.dropout, train)?;
        let text_len = input.encoder_hidden_states.size()[1];
        let encoder_hidden_states = joint.f_narrow(1, 0, text_len)?;
        let hidden_states = joint.f_narrow(1, text_len, joint.size()[1] - text_len)?;

        let rotary = match (c.use_rotary_positional_embeddings, input.image_rotary_emb) {
            (false, _) => None,
            (true, Some(table)) => {
                Some(RotaryEmbedding { cos: table.cos.shallow_clone(), sin: table.sin.shallow_clone() })
            }
            (true, None) => Some(self.rotary_for(f, h, w, input.hidden_states.device())?),
        };
        Ok(Embedded { emb, hidden_states, encoder_hidden_states, rotary, dims: [b, f, h, w] })
    }

    /// With dropout active, one seed per block drawn from tch's generator (see
    /// [`forward_taped`](Self::forward_taped)), and one to continue from after the
    /// blocks; `None` otherwise, leaving the generator's stream untouched.
    fn block_seeds(&self, train: bool) -> Result<Option<Vec<i64>>> {
        if !(train && self.config.dropout > 0.0) {
            return Ok(None);
        }
        let count = self.transformer_blocks.len() as i64 + 1;
        let seeds = Tensor::f_randint(i64::MAX, [count], (Kind::Int64, Device::Cpu))?;
        Ok(Some(Vec::<i64>::try_from(seeds)?))
    }

    /// The final norms and projection of the last block's video tokens, unpatchified to
    /// `[B, F, out_channels, H, W]`.
    fn head(&self, hidden_states: &Tensor, emb: &Tensor, [b, f, h, w]: [i64; 4]) -> Result<Tensor> {
        let c = &self.config;
        let hidden_states = self.norm_final.forward(hidden_states)?;
        let hidden_states = self.norm_out.forward(&hidden_states, emb)?;
        let hidden_states = self.proj_out.forward(&hidden_states)?;

        let p = c.patch_size;
        let out = match c.patch_size_t {
            None => hidden_states
                .f_reshape([b, f, h / p, w / p, -1, p, p])?
                .f_permute([0, 1, 4, 2, 5, 3, 6])?
                .f_flatten(5, 6)?
                .f_flatten(3, 4)?,
            Some(pt) => hidden_states
                .f_reshape([b, (f + pt - 1) / pt, h / p, w / p, -1, pt, p, p])?
                .f_permute([0, 1, 5, 4, 2, 6, 3, 7])?
                .f_flatten(6, 7)?
                .f_flatten(4, 5)?
                .f_flatten(1, 2)?,
        };
        Ok(out)
    }

    /// Checks names, shapes, dtypes and devices of the inputs; returns `[B, F, H, W]`.
    fn check_input(&self, input: &TransformerInput) -> Result<[i64; 4]> {
        let c = &self.config;
        let hidden = input.hidden_states;
        let shape_err = |tensor: &str, expected: String, actual: Vec<i64>| Error::Shape {
            tensor: tensor.to_string(),
            expected,
            actual,
        };
        let dims: [i64; 5] = hidden
            .size()
            .try_into()
            .map_err(|size| shape_err("hidden_states", format!("[B, F, {}, H, W]", c.in_channels), size))?;
        let [b, f, ch, h, w] = dims;
        let pt = c.patch_size_t.unwrap_or(1);
        if ch != c.in_channels || h % c.patch_size != 0 || w % c.patch_size != 0 || f % pt != 0 || b == 0 || f == 0 {
            return Err(shape_err(
                "hidden_states",
                format!(
                    "[B, F, {}, H, W] with H and W multiples of patch_size {}{}",
                    c.in_channels,
                    c.patch_size,
                    if pt > 1 { format!(" and F a multiple of patch_size_t {pt}") } else { String::new() }
                ),
                hidden.size(),
            ));
        }
        let text = input.encoder_hidden_states;
        let text_ok = text.dim() == 3 && text.size()[0] == b && text.size()[2] == c.text_embed_dim;
        let needs_len = c.positional_embedding() != PositionalEmbedding::None;
        if !text_ok || (needs_len && text.size()[1] != c.max_text_seq_length) {
            let len = if needs_len { c.max_text_seq_length.to_string() } else { "S".to_string() };
            return Err(shape_err("encoder_hidden_states", format!("[{b}, {len}, {}]", c.text_embed_dim), text.size()));
        }
        let t = input.timestep;
        if !(t.dim() == 0 || (t.dim() == 1 && t.size()[0] == b)) {
            return Err(shape_err("timestep", format!("[{b}] or a scalar"), t.size()));
        }
        let kind = self.kind_probe.kind();
        let device = self.kind_probe.device();
        for (name, tensor) in [("hidden_states", hidden), ("encoder_hidden_states", text)] {
            weights::check_kind_device(name, tensor, kind, device)?;
        }
        weights::check_device("timestep", t, device)?;
        Ok([b, f, h, w])
    }
}

/// A transformer on `device` in `kind` with its variables in a fresh VarStore (PyTorch's default
/// initialisation; the positional table starts as the sin-cos table, as in diffusers).
pub fn build(
    config: &CogVideoXTransformer3DModelConfig,
    device: Device,
    kind: Kind,
) -> Result<(nn::VarStore, CogVideoXTransformer3DModel)> {
    let mut vs = nn::VarStore::new(device);
    // New variables are created in `kind` (no fp32 copy of the whole model on the device first).
    vs.set_kind(kind);
    let model = CogVideoXTransformer3DModel::new(&Vars::new(vs.root()), config)?;
    vs.set_kind(kind);
    Ok((vs, model))
}

/// A transformer as [`build`] with LoRA adapters on the linear layers `lora` targets, in a
/// second store: `(base, adapters, model)`. Every target must match at least one layer.
pub fn build_with_lora(
    config: &CogVideoXTransformer3DModelConfig,
    lora: &LoraConfig,
    device: Device,
    kind: Kind,
) -> Result<(nn::VarStore, nn::VarStore, CogVideoXTransformer3DModel)> {
    lora.validate("training config")?;
    let mut vs = nn::VarStore::new(device);
    let mut lora_vs = nn::VarStore::new(device);
    let model = CogVideoXTransformer3DModel::new(&Vars::new(vs.root()).with_lora(lora_vs.root(), lora), config)?;
    check_lora_targets(lora, &lora_vs)?;
    vs.set_kind(kind);
    lora_vs.set_kind(kind);
    Ok((vs, lora_vs, model))
}

/// Checks `lora` against the model `config` describes without allocating it (every target
/// matches a linear layer; the rank fits each): the check [`build_with_lora`] makes, for
/// configs read before any model is built. Returns the number of adapted layers.
pub fn check_lora(config: &CogVideoXTransformer3DModelConfig, lora: &LoraConfig) -> Result<usize> {
    lora.validate("training config")?;
    let vs = nn::VarStore::new(Device::Cpu);
    let lora_vs = nn::VarStore::new(Device::Cpu);
    CogVideoXTransformer3DModel::new(&Vars::shapes_only(vs.root()).with_lora(lora_vs.root(), lora), config)?;
    check_lora_targets(lora, &lora_vs)
}

/// Every target of `lora` matched at least one layer of the adapters' store; returns their number.
fn check_lora_targets(lora: &LoraConfig, lora_vs: &nn::VarStore) -> Result<usize> {
    crate::models::lora::check_targets(
        lora,
        lora_vs,
        "attention layers are `to_q`, `to_k`, `to_v`, `to_out.0`; feed-forward `ff.net.0.proj`, `ff.net.2`",
    )
}

/// Name → shape of every variable of the model `config` describes, without allocating it.
pub fn variable_shapes(config: &CogVideoXTransformer3DModelConfig) -> Result<BTreeMap<String, Vec<i64>>> {
    let vs = nn::VarStore::new(Device::Cpu);
    CogVideoXTransformer3DModel::new(&Vars::shapes_only(vs.root()), config)?;
    Ok(crate::models::weights::variable_shapes(&vs))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn input_for(c: &CogVideoXTransformer3DModelConfig, frames: i64) -> (Tensor, Tensor, Tensor) {
        let opts = (Kind::Float, Device::Cpu);
        (
            Tensor::randn([1, frames, c.in_channels, c.sample_height, c.sample_width], opts),
            Tensor::randn([1, c.max_text_seq_length, c.text_embed_dim], opts),
            Tensor::from_slice(&[500i64]),
        )
    }

    /// How [`gradients`] back-propagates.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    enum Backward {
        /// `forward` and one `backward`.
        Plain,
        /// `forward_taped` without checkpointing: the blocks' graphs kept.
        Taped,
        /// `forward_taped` with checkpointing: the blocks recomputed.
        Checkpointed,
    }

    /// Every parameter's gradient of `Σ out · weights` after a backward of `mode`. A taped
    /// backward must report every stage once, in order, and the gradients of a stage's
    /// parameters must not change after it is reported.
    fn gradients(
        vs: &nn::VarStore,
        model: &CogVideoXTransformer3DModel,
        input: &TransformerInput,
        weights: &Tensor,
        mode: Backward,
        seed: i64,
    ) -> (f64, f64, BTreeMap<String, Option<Tensor>>) {
        for (_, v) in vs.variables() {
            let mut g = v.grad();
            if g.defined() {
                let _ = g.zero_();
            }
        }
        tch::manual_seed(seed);
        let final_gradient = |v: &Tensor| {
            let g = v.grad();
            g.defined().then(|| g.copy())
        };
        let loss = if mode == Backward::Plain {
            let loss = model.forward(input, true).unwrap().f_mul(weights).unwrap().sum(Kind::Float);
            loss.backward();
            loss
        } else {
            let (out, tape) = model.forward_taped(input, true, mode == Backward::Checkpointed).unwrap();
            let loss = out.f_mul(weights).unwrap().sum(Kind::Float);
            loss.backward();
            let mut stages = Vec::new();
            let mut reported = Vec::new();
            tape.backward(&mut |stage| {
                stages.push(stage);
                for (name, v) in vs.variables() {
                    if model.backward_stage_of(&name) == stage {
                        reported.push((name, final_gradient(&v)));
                    }
                }
                Ok(())
            })
            .unwrap();
            assert_eq!(stages, (0..model.backward_stages()).collect::<Vec<_>>(), "{mode:?}");
            assert_eq!(reported.len(), vs.variables().len(), "{mode:?}: every variable has a stage");
            let variables = vs.variables();
            for (name, at_stage) in reported {
                let now = final_gradient(&variables[&name]);
                let same = match (&at_stage, &now) {
                    (Some(a), Some(b)) => a.equal(b),
                    (a, b) => a.is_none() && b.is_none(),
                };
                assert!(same, "{mode:?}: {name}'s gradient changed after its stage was reported");
            }
            loss
        };
        // The generator continues as after the plain forward.
        let next = Tensor::randn([1], (Kind::Float, Device::Cpu)).double_value(&[0]);
        let grads = vs.variables().into_iter().map(|(name, v)| (name, final_gradient(&v))).collect();
        (loss.double_value(&[]), next, grads)
    }

    /// Taped gradients, with the blocks' graphs kept and with checkpointing, equal the plain
    /// backward's (fp32, relative 1e-5 of each gradient's largest entry: only the summation
    /// order differs), with dropout on too, whose masks must replay identically in the
    /// recomputed blocks; and every stage is reported once its gradients are final.
    #[test]
    fn checkpointed_backward_gives_the_plain_gradients() {
        // tch's generator is one per process and other tests draw from it on other threads; the
        // dropout replay checked here needs it alone, so the test runs in a child process.
        const ALONE: &str = "COGNVS_TEST_ALONE";
        if std::env::var_os(ALONE).is_none() {
            let module = module_path!().split_once("::").map_or(module_path!(), |(_, rest)| rest);
            let name = format!("{module}::checkpointed_backward_gives_the_plain_gradients");
            let output = std::process::Command::new(std::env::current_exe().unwrap())
                .args(["--exact", &name, "--test-threads=1", "--nocapture"])
                .env(ALONE, "1")
                .output()
                .unwrap();
            let stdout = String::from_utf8_lossy(&output.stdout);
            assert!(
                output.status.success() && stdout.contains("1 passed"),
                "{stdout}{}",
                String::from_utf8_lossy(&output.stderr)
            );
            return;
        }
        for dropout in [0.0, 0.2] {
            let c = CogVideoXTransformer3DModelConfig {
                num_layers: 3,
                dropout,
                ..CogVideoXTransformer3DModelConfig::tiny()
            };
            tch::manual_seed(11);
            let (vs, model) = build(&c, Device::Cpu, Kind::Float).unwrap();
            let (x, text, t) = input_for(&c, 3);
            let weights = Tensor::randn([1, 3, 16, c.sample_height, c.sample_width], (Kind::Float, Device::Cpu));
            let input = TransformerInput {
                hidden_states: &x,
                encoder_hidden_states: &text,
                timestep: &t,
                ofs: None,
                image_rotary_emb: None,
            };
            let (plain_loss, plain_next, plain) = gradients(&vs, &model, &input, &weights, Backward::Plain, 5);
            for mode in [Backward::Taped, Backward::Checkpointed] {
                let (taped_loss, taped_next, taped) = gradients(&vs, &model, &input, &weights, mode, 5);
                assert_eq!(plain_loss, taped_loss, "{mode:?}, dropout {dropout}: the forwards differ");
                assert_eq!(plain_next, taped_next, "{mode:?}, dropout {dropout}: the generator continues elsewhere");
                assert_eq!(plain.len(), taped.len());
                let mut with_gradient = 0;
                for (name, g) in &plain {
                    let (g, h) = match (g, &taped[name]) {
                        (Some(g), Some(h)) => (g, h),
                        (None, None) => continue,
                        _ => panic!("{mode:?}, dropout {dropout}: {name} has a gradient in one backward only"),
                    };
                    with_gradient += 1;
                    let scale = g.abs().max().double_value(&[]).max(1e-12);
                    let diff = (g - h).abs().max().double_value(&[]);
                    assert!(
                        diff <= 1e-5 * scale,
                        "{mode:?}, dropout {dropout}: {name}: gradients differ by {diff} (scale {scale})"
                    );
                }
                let trainable = vs.trainable_variables().len();
                assert_eq!(
                    with_gradient, trainable,
                    "{mode:?}, dropout {dropout}: every trainable variable has a gradient"
                );
            }
        }
    }

    /// The stages name the head, each block (last first) and the embeddings.
    #[test]
    fn backward_stages_follow_the_modules() {
        let c = CogVideoXTransformer3DModelConfig { num_layers: 3, ..CogVideoXTransformer3DModelConfig::tiny() };
        let (_vs, model) = build(&c, Device::Cpu, Kind::Float).unwrap();
        assert_eq!(model.backward_stages(), 5);
        assert_eq!(model.backward_stage_of("proj_out.weight"), 0);
        assert_eq!(model.backward_stage_of("norm_out.linear.bias"), 0);
        assert_eq!(model.backward_stage_of("transformer_blocks.2.attn1.to_q.weight"), 1);
        assert_eq!(model.backward_stage_of("transformer_blocks.0.ff.net.2.lora_B.weight"), 3);
        assert_eq!(model.backward_stage_of("time_embedding.linear_1.weight"), 4);
        assert_eq!(model.backward_stage_of("patch_embed.proj.weight"), 4);
    }

    #[test]
    fn tiny_forward_has_the_output_shape() {
        let c = CogVideoXTransformer3DModelConfig::tiny();
        let (_vs, model) = build(&c, Device::Cpu, Kind::Float).unwrap();
        let (x, text, t) = input_for(&c, 3);
        let input = TransformerInput {
            hidden_states: &x,
            encoder_hidden_states: &text,
            timestep: &t,
            ofs: None,
            image_rotary_emb: None,
        };
        let out = model.forward(&input, false).unwrap();
        assert_eq!(out.size(), vec![1, 3, 16, c.sample_height, c.sample_width]);
        assert!(out.isfinite().all().int64_value(&[]) == 1);
    }

    #[test]
    fn bad_inputs_are_named_errors() {
        let c = CogVideoXTransformer3DModelConfig::tiny();
        let (_vs, model) = build(&c, Device::Cpu, Kind::Float).unwrap();
        let (x, text, t) = input_for(&c, 3);
        let wrong_channels = x.narrow(2, 0, 16);
        let input = TransformerInput {
            hidden_states: &wrong_channels,
            encoder_hidden_states: &text,
            timestep: &t,
            ofs: None,
            image_rotary_emb: None,
        };
        let err = model.forward(&input, false).unwrap_err().to_string();
        assert!(err.contains("hidden_states") && err.contains("32") && err.contains("16"), "{err}");
        let short_text = text.narrow(1, 0, 3);
        let input = TransformerInput {
            hidden_states: &x,
            encoder_hidden_states: &short_text,
            timestep: &t,
            ofs: None,
            image_rotary_emb: None,
        };
        let err = model.forward(&input, false).unwrap_err().to_string();
        assert!(err.contains("encoder_hidden_states") && err.contains("[1, 8, 16]"), "{err}");
        let bf16 = x.to_kind(Kind::BFloat16);
        let input = TransformerInput {
            hidden_states: &bf16,
            encoder_hidden_states: &text,
            timestep: &t,
            ofs: None,
            image_rotary_emb: None,
        };
        let err = model.forward(&input, false).unwrap_err().to_string();
        assert!(err.contains("BFloat16") && err.contains("Float"), "{err}");
    }

    #[test]
    fn config_rejects_learned_positions_without_rotary() {
        let json = r#"{"use_learned_positional_embeddings": true}"#;
        let err = CogVideoXTransformer3DModelConfig::from_json_str(json, "t.json").unwrap_err().to_string();
        assert!(err.contains("use_learned_positional_embeddings") && err.contains("t.json"), "{err}");
        let json = r#"{"activation_fn": "swiglu", "mystery": 3}"#;
        let err = CogVideoXTransformer3DModelConfig::from_json_str(json, "t.json").unwrap_err().to_string();
        assert!(err.contains("activation_fn"), "{err}");
        let c = CogVideoXTransformer3DModelConfig::from_json_str(
            r#"{"mystery": 3, "_class_name": "CogVideoXTransformer3DModel"}"#,
            "t",
        )
        .unwrap();
        assert_eq!(c.unknown_keys(), vec!["mystery"]);
    }
}

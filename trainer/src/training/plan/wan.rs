//! The memory plan's counts for Wan models (`WanTransformer3DModel`, `AutoencoderKLWan`), from
//! their diffusers config shapes: parameters from the built module tree's variable shapes (the
//! [`KEEP_IN_FP32_MODULES`] stay fp32 in a bf16 run, as diffusers loads them), adapters from the
//! LoRA targets, and activations per block from what autograd keeps in
//! [`WanTransformerBlock::forward`](crate::models::wan::transformer_wan::WanTransformerBlock::forward)
//! (see [`WAN_BLOCK_TERMS`]). Its rows and peaks beside these are the parent's, shared with
//! CogVideoX.
//!
//! The unit is one `[B, N, D]` tensor of the video tokens (text and image tokens enter through
//! cross-attention only, so they do not lengthen the sequence). Unlike CogVideoX, Wan normalises
//! and modulates in fp32 whatever the weights' dtype, so some saved tensors are fp32 in a bf16
//! run: a term says which.

use tch::Kind;

use super::{
    ActivationPlan, CHECKPOINT_GRADIENT_UNITS, ENCODE_VIDEO_TENSORS, FP32_BYTES, FamilyCounts, PlanOptions, PlanRow,
    PlanShape, RGB, element_bytes, human_count, kind_name,
};
use crate::error::Result;
use crate::models::lora::LoraConfig;
use crate::models::wan::autoencoder_kl_wan::{self as vae, AutoencoderKLWanConfig};
use crate::models::wan::transformer_wan::{self as transformer, KEEP_IN_FP32_MODULES, WanTransformer3DModelConfig};
use crate::training::PretrainConfig;

/// Text tokens of the cross-attention context: umT5's padded length (`TEXT_CONTEXT_LENGTH`).
const TEXT_TOKENS: u64 = transformer::TEXT_CONTEXT_LENGTH as u64;
/// CLIP ViT-H/14 image tokens of Wan2.1 image-to-video (`image_encoder`'s penultimate hidden
/// state at 224 × 224: 16 × 16 patches + the class token).
const CLIP_IMAGE_TOKENS: u64 = 257;
/// Rows of the timestep projection per token (shift, scale and gate of both modulations).
const MODULATION_ROWS: u64 = 6;

/// Width of a saved tensor's last dimension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Width {
    /// The token width `D`.
    Model,
    /// The feed-forward's hidden width `ffn_dim`.
    Ffn,
}

/// The condition under which a [`WanTerm`] is saved (PyTorch saves a matmul's input only when
/// the weight needs a gradient, and a product's factor only when the other factor needs one).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WanNeeds {
    /// Always (an op whose input needs a gradient saves it whatever trains).
    Always,
    /// When the modulation trains (the block's `scale_shift_table` and the shared
    /// `condition_embedder.time_proj`: scale, shift and gate then need gradients).
    Modulation,
    /// When the norms' weights train (the whole model).
    NormWeights,
    /// When `attn1.to_q`, `to_k` or `to_v` trains (weight or adapter).
    Qkv,
    /// When `attn1.to_out.0` trains.
    ToOut,
    /// When `attn2.to_q` trains.
    CrossQ,
    /// When `attn2.to_out.0` trains.
    CrossOut,
    /// When `ffn.net.0.proj` trains.
    FfIn,
    /// When `ffn.net.2` trains.
    FfOut,
    /// With image cross-attention (`added_kv_proj_dim`).
    Image,
}

/// One tensor (or several of one size) a Wan block saves for its backward, per video token.
#[derive(Debug, Clone, Copy)]
pub struct WanTerm {
    /// What it is.
    pub what: &'static str,
    /// How many tensors of this size.
    pub units: u64,
    /// When it is kept.
    pub needs: WanNeeds,
    /// Its last dimension.
    pub width: Width,
    /// Whether it is fp32 whatever the working precision (Wan's norms and modulation).
    pub fp32: bool,
}

const fn term(what: &'static str, units: u64, needs: WanNeeds, width: Width, fp32: bool) -> WanTerm {
    WanTerm { what, units, needs, width, fp32 }
}

/// What a Wan block keeps for its backward, in order (read off `transformer_wan.rs`, `vars.rs`,
/// `attention.rs`, `embeddings.rs`). The norms upcast to fp32 and save that copy; a modulation
/// product keeps its normalised factor only when the modulation trains; an RMS norm keeps its
/// normalised output only when its weight trains; the rotary embedding multiplies by constant
/// tables; SDPA's flash kernel keeps q, k, v, its output and a per-row log-sum-exp. The
/// cross-attention's keys and values are on the context's tokens ([`context_bytes`]).
pub const WAN_BLOCK_TERMS: [WanTerm; 24] = [
    term("block input in fp32 (norm1)", 1, WanNeeds::Always, Width::Model, true),
    term("norm1 output (× (1 + scale))", 1, WanNeeds::Modulation, Width::Model, true),
    term("modulated input (to_q, to_k, to_v)", 1, WanNeeds::Qkv, Width::Model, false),
    term("q, k projections in fp32 (RMS norms)", 2, WanNeeds::Always, Width::Model, true),
    term("normalised q, k (× norm weights)", 2, WanNeeds::NormWeights, Width::Model, true),
    term("rotated q, k (SDPA)", 2, WanNeeds::Always, Width::Model, false),
    term("v (SDPA)", 1, WanNeeds::Always, Width::Model, false),
    term("SDPA output", 1, WanNeeds::Always, Width::Model, false),
    term("merged heads (to_out.0)", 1, WanNeeds::ToOut, Width::Model, false),
    term("attention output (× gate)", 1, WanNeeds::Modulation, Width::Model, false),
    term("norm2 input in fp32", 1, WanNeeds::Always, Width::Model, true),
    term("normalised input (attn2.to_q)", 1, WanNeeds::CrossQ, Width::Model, false),
    term("cross q projection in fp32 (RMS norm)", 1, WanNeeds::Always, Width::Model, true),
    term("normalised cross q (× norm weight)", 1, WanNeeds::NormWeights, Width::Model, true),
    term("cross q (SDPA)", 1, WanNeeds::Always, Width::Model, false),
    term("cross SDPA output (text)", 1, WanNeeds::Always, Width::Model, false),
    term("cross SDPA output (image)", 1, WanNeeds::Image, Width::Model, false),
    term("merged heads (attn2.to_out.0)", 1, WanNeeds::CrossOut, Width::Model, false),
    term("norm3 input in fp32", 1, WanNeeds::Always, Width::Model, true),
    term("norm3 output (× (1 + c_scale))", 1, WanNeeds::Modulation, Width::Model, true),
    term("modulated input (ffn.net.0.proj)", 1, WanNeeds::FfIn, Width::Model, false),
    term("ffn.net.0.proj output (GELU)", 1, WanNeeds::Always, Width::Ffn, false),
    term("GELU output (ffn.net.2)", 1, WanNeeds::FfOut, Width::Ffn, false),
    term("feed-forward output in fp32 (× c_gate)", 1, WanNeeds::Modulation, Width::Model, true),
];

/// `[B, N, D]` units of the per-token modulation a block keeps when every token has its own
/// timestep (Wan2.2 TI2V): the fp32 sum `scale_shift_table + timestep_proj` `[B, N, 6, D]`,
/// which the gates' views keep alive, and the two `1 + scale` factors.
const PER_TOKEN_MODULATION_UNITS: u64 = MODULATION_ROWS + 2;

/// The counts of a Wan model for `config` (see the module docs).
pub(super) fn counts(
    config: &PretrainConfig,
    transformer: &WanTransformer3DModelConfig,
    vae_config: &AutoencoderKLWanConfig,
    options: &PlanOptions,
    kind: Kind,
) -> Result<FamilyCounts> {
    let working = element_bytes(kind);
    let world = options.world_size as u64;
    let shapes = transformer::variable_shapes(transformer)?;
    let numel = |shape: &Vec<i64>| shape.iter().map(|&d| d.max(0) as u64).product::<u64>();
    let transformer_parameters: u64 = shapes.values().map(numel).sum();
    let largest_base = shapes.values().map(numel).max().unwrap_or(0);
    // diffusers keeps these fp32 in a bf16 model; `transformer_wan::build` does the same.
    let kept_fp32: u64 = shapes
        .iter()
        .filter(|(name, _)| name.split('.').any(|part| KEEP_IN_FP32_MODULES.contains(&part)))
        .map(|(_, shape)| numel(shape))
        .sum();
    let adapters = match &config.lora {
        Some(lora) => transformer::lora_shapes(transformer, lora)?,
        None => Vec::new(),
    };
    let adapter_parameters: u64 = adapters.iter().map(|(_, n)| n).sum();
    let largest_adapter = adapters.iter().map(|(_, n)| *n).max().unwrap_or(0);
    let vae_parameters: u64 = vae::variable_shapes(vae_config)?.values().map(numel).sum();

    let d = &config.data;
    let spatial = vae_config.spatial_compression_ratio() as u64;
    let temporal = vae_config.temporal_compression_ratio() as u64;
    let [pt, ph, pw] = transformer.patch_size.map(|p| p.max(1) as u64);
    let latent_frames = (d.frames as u64 - 1) / temporal + 1;
    let video_tokens = latent_frames.div_ceil(pt)
        * (u64::from(d.height) / spatial).div_ceil(ph)
        * (u64::from(d.width) / spatial).div_ceil(pw);
    let image_tokens = if transformer.image_dim.is_some() { CLIP_IMAGE_TOKENS } else { 0 };
    let shape = PlanShape {
        batch: (d.batch_size as u64).div_ceil(world),
        frames: d.frames as u64,
        video_tokens,
        text_tokens: TEXT_TOKENS,
        unit_tokens: video_tokens,
        width: transformer.inner_dim() as u64,
        blocks: transformer.num_layers as u64,
    };

    let weight_bytes = kept_fp32 * FP32_BYTES + (transformer_parameters - kept_fp32 + adapter_parameters) * working;
    let weights = PlanRow {
        what: "transformer weights".to_string(),
        bytes: weight_bytes,
        note: format!(
            "{} parameters{} × {working} B ({}; {} kept fp32), full on every rank",
            human_count(transformer_parameters),
            if adapter_parameters > 0 {
                format!(" + {} adapter", human_count(adapter_parameters))
            } else {
                String::new()
            },
            kind_name(kind),
            human_count(kept_fp32)
        ),
    };
    let text_bytes = TEXT_TOKENS * transformer.text_dim as u64 * FP32_BYTES;
    let image_bytes = image_tokens * transformer.image_dim.unwrap_or(0) as u64 * FP32_BYTES;
    let mut frozen = super::frozen_rows(
        vae_parameters,
        working,
        text_bytes,
        format!("[{TEXT_TOKENS}, {}] fp32 umT5 tokens, no gradients", transformer.text_dim),
    );
    if image_bytes > 0 {
        frozen.push(PlanRow {
            what: "image embedding (frozen)".to_string(),
            bytes: shape.batch * image_bytes,
            note: format!(
                "{} × [{image_tokens}, {}] fp32 CLIP tokens",
                shape.batch,
                transformer.image_dim.unwrap_or(0)
            ),
        });
    }

    let per_token = per_token_timesteps(vae_config);
    let activations = activation_plan(
        config.lora.as_ref(),
        transformer,
        &shape,
        working,
        config.train.gradient_checkpointing,
        per_token,
    );
    let pixels = shape.frames * u64::from(d.height) * u64::from(d.width);
    let video_bytes = shape.batch * RGB * pixels * FP32_BYTES;
    let patch = vae_config.patch_size.unwrap_or(1) as u64;
    let plane = |channels: i64| {
        shape.batch * channels as u64 * (u64::from(d.height) / patch) * (u64::from(d.width) / patch) * working
    };
    let vae_encode_peak = ENCODE_VIDEO_TENSORS * video_bytes
        + shape.batch * RGB * pixels * working
        + ENCODER_LIVE_FRAMES * plane(vae_config.base_dim);
    let decoder_width = vae_config.decoder_base_dim.unwrap_or(vae_config.base_dim);
    let vae_decode_peak = DECODER_LIVE_FRAMES * plane(decoder_width) + video_bytes;
    Ok(FamilyCounts {
        transformer_parameters,
        adapter_parameters,
        largest_base,
        largest_adapter,
        vae_parameters,
        weights,
        frozen,
        frozen_inputs: text_bytes + shape.batch * image_bytes,
        shape,
        activations,
        vae_encode_peak,
        vae_decode_peak,
    })
}

/// Frame planes of the encoder's first level alive at once while it encodes one chunk
/// (`autoencoder_kl_wan.rs`, chunks of [`vae::ENCODE_CHUNK_FRAMES`]): in a residual block the
/// input kept for the shortcut, the norm's and the SiLU's outputs, the input padded with the
/// [`vae::CACHE_T`] cached frames and the convolution's output (4 chunks and the padding), plus
/// the cache of each of the level's four causal convolutions (two residual blocks of two).
const ENCODER_LIVE_FRAMES: u64 = 4 * vae::ENCODE_CHUNK_FRAMES as u64 + vae::CACHE_T as u64 + 4 * vae::CACHE_T as u64;
/// The decoder's last level on one latent frame (which it expands to the temporal compression's
/// 4 pixel frames): the same live set as the encoder's chunk.
const DECODER_LIVE_FRAMES: u64 = ENCODER_LIVE_FRAMES;

/// Whether the model is trained with one timestep per token: Wan2.2 TI2V-5B's pipeline
/// (`expand_timesteps`), the one released model on Wan2.2's residual, patchified VAE, which is
/// how the plan tells it from a `[model]` section (its transformer config does not say).
fn per_token_timesteps(vae_config: &AutoencoderKLWanConfig) -> bool {
    vae_config.is_residual
}

/// The activation peaks of a Wan transformer for `shape` in the working precision.
fn activation_plan(
    lora: Option<&LoraConfig>,
    config: &WanTransformer3DModelConfig,
    shape: &PlanShape,
    working: u64,
    checkpointing: bool,
    per_token: bool,
) -> ActivationPlan {
    let trains = |module: &str| lora.is_none_or(|l| l.targets(&format!("blocks.0.{module}")));
    let modulation_trains = lora.is_none() || lora.is_some_and(|l| l.targets("condition_embedder.time_proj"));
    let image = config.added_kv_proj_dim.is_some();
    let needed = |needs: WanNeeds| match needs {
        WanNeeds::Always => true,
        WanNeeds::Modulation => modulation_trains,
        WanNeeds::NormWeights => lora.is_none(),
        WanNeeds::Qkv => trains("attn1.to_q") || trains("attn1.to_k") || trains("attn1.to_v"),
        WanNeeds::ToOut => trains("attn1.to_out.0"),
        WanNeeds::CrossQ => trains("attn2.to_q"),
        WanNeeds::CrossOut => trains("attn2.to_out.0"),
        WanNeeds::FfIn => trains("ffn.net.0.proj"),
        WanNeeds::FfOut => trains("ffn.net.2"),
        WanNeeds::Image => image,
    };
    let dim = config.inner_dim() as u64;
    let ffn = config.ffn_dim as u64;
    let rows = shape.batch * shape.unit_tokens;
    let bytes_of = |t: &WanTerm| {
        let width = match t.width {
            Width::Model => dim,
            Width::Ffn => ffn,
        };
        t.units * rows * width * if t.fp32 { FP32_BYTES } else { working }
    };
    let unit_bytes = rows * dim * working;
    let saved: u64 = WAN_BLOCK_TERMS.iter().filter(|t| needed(t.needs)).map(bytes_of).sum();
    let modulation = if per_token { PER_TOKEN_MODULATION_UNITS * rows * dim * FP32_BYTES } else { 0 };
    let context = context_bytes(&trains, config, shape, working, image);
    // An adapter's down-projection output `[B, tokens, r]` is kept for its up-projection.
    let adapter_bytes = lora.map_or(0, |l| {
        let video = ["attn1.to_q", "attn1.to_k", "attn1.to_v", "attn1.to_out.0", "attn2.to_q", "attn2.to_out.0"]
            .iter()
            .chain(&["ffn.net.0.proj", "ffn.net.2"])
            .filter(|m| l.targets(&format!("blocks.0.{m}")))
            .count() as u64;
        let text = ["attn2.to_k", "attn2.to_v"].iter().filter(|m| l.targets(&format!("blocks.0.{m}"))).count() as u64;
        let img = ["attn2.add_k_proj", "attn2.add_v_proj"]
            .iter()
            .filter(|m| image && l.targets(&format!("blocks.0.{m}")))
            .count() as u64;
        let per_token = video * shape.unit_tokens + text * TEXT_TOKENS + img * CLIP_IMAGE_TOKENS;
        per_token * shape.batch * l.rank as u64 * working
    });
    let per_block_bytes = saved + modulation + context + adapter_bytes;
    let block_units = per_block_bytes.div_ceil(unit_bytes.max(1));
    // The head: norm_out's fp32 input always; with the whole model training, its modulated
    // output (fp32) and proj_out's input.
    let head = rows * dim * (FP32_BYTES + if lora.is_none() { FP32_BYTES + working } else { 0 });
    // The timestep embedding's per-token outputs live through the whole step with per-token
    // timesteps: `temb` and the six-row projection the blocks read (working precision).
    let timestep_embedding = if per_token { (MODULATION_ROWS + 1) * rows * dim * working } else { 0 };
    // In a block's backward besides its saved tensors: the incoming gradient and the fp32
    // residual stream's two gradients, and the GELU's output and input gradients.
    let transient = unit_bytes + 2 * rows * dim * FP32_BYTES + 2 * rows * ffn * working;
    let without = shape.blocks * per_block_bytes + head + timestep_embedding + transient;
    // Checkpointed: each block's input and the last block's output are kept; the backward
    // rebuilds one block's graph at a time and carries two gradients between blocks.
    let kept = (shape.blocks + 1) * unit_bytes + timestep_embedding;
    let with = kept + per_block_bytes + CHECKPOINT_GRADIENT_UNITS * unit_bytes + transient;
    ActivationPlan {
        unit_bytes,
        block_units,
        per_block_bytes,
        without_checkpointing: without,
        // The head's backward runs before the blocks are recomputed, over the kept inputs.
        with_checkpointing: with.max(head + kept),
        checkpointing,
    }
}

/// Bytes a block keeps on the cross-attention context's tokens (text, and image tokens with
/// image cross-attention) when its key/value projections train: the key projection in fp32
/// (RMS norm), the normalised key and the value (SDPA).
fn context_bytes(
    trains: &impl Fn(&str) -> bool,
    config: &WanTransformer3DModelConfig,
    shape: &PlanShape,
    working: u64,
    image: bool,
) -> u64 {
    let dim = config.inner_dim() as u64;
    let per_token = dim * (FP32_BYTES + 2 * working);
    let text = trains("attn2.to_k") || trains("attn2.to_v");
    let img = image && (trains("attn2.add_k_proj") || trains("attn2.add_v_proj"));
    shape.batch * per_token * (u64::from(text) * TEXT_TOKENS + u64::from(img) * CLIP_IMAGE_TOKENS)
}

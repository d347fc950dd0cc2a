//! The memory plan of a training run: what one device holds for a training config
//! (parameters, gradients, master weights, AdamW moments, activations with and without
//! checkpointing, the VAE's encode and decode peaks) before anything is allocated, so
//! `trainer pretrain` and `trainer finetune` can refuse a run that cannot fit.
//!
//! The counts follow this crate's code, not a generic rule of thumb:
//! - parameters from the transformer's variable shapes (`variable_shapes`) and the VAE's store;
//! - AdamW (`training::adamw`) keeps two fp32 moments per trainable parameter, created while the
//!   parameters are still fp32, and fp32 master copies when training in bf16; gradients have the
//!   parameters' dtype and stay allocated between steps (`zero_grad` zeroes, it does not free);
//! - ZeRO-2 (`[distributed] zero_stage = 2`): moments and master weights are sharded 1/N; every
//!   rank holds a full-size gradient buffer during the backward plus its fp32 1/N shard after the
//!   reduction; the working weights stay full size on every rank;
//! - the models are built in fp32 and cast to bf16 only after the optimizer took its master
//!   copies (`training::pretrain`), so loading has its own peak;
//! - activations per block: what autograd saves for the backward in [`CogVideoXBlock`]'s forward
//!   (see [`BlockTerm`]), in units of one `[B, L, D]` tensor (L = text + video tokens, D = width).
//!
//! [`CogVideoXBlock`]: crate::models::cogvideox::cogvideox_transformer_3d::CogVideoXBlock

use std::fmt;

use tch::{Device, Kind};

use crate::diffusers_config::DiffusersConfig;
use crate::error::{Error, Result};
use crate::models::cogvideox::autoencoder_kl_cogvideox::{self as vae, AutoencoderKLCogVideoXConfig};
use crate::models::cogvideox::cogvideox_transformer_3d::{CogVideoXTransformer3DModelConfig, variable_shapes};
use crate::models::lora::LoraConfig;
use crate::training::PretrainConfig;

pub mod wan;

/// Bytes of one fp32 value (AdamW moments, master weights, the loader's frames).
const FP32_BYTES: u64 = 4;
/// Feed-forward width as a multiple of the token width (diffusers' `FeedForward` `mult=4`).
const FF_MULT: u64 = 4;
/// AdamW moments per trainable parameter (`exp_avg`, `exp_avg_sq`).
const ADAM_MOMENTS: u64 = 2;
/// fp32 temporaries of one bucket alive at once in `AdamW::step` (its fp32 gradient, the
/// denominator and the update quotient); the largest bucket (about `[distributed] bucket_mib`
/// of whole parameters, or the largest parameter alone) sets the step's peak.
const OPTIMIZER_TEMPORARIES: u64 = 3;
/// fp32 video tensors of a batch on the device during the VAE encode (`objective.rs`: target,
/// condition, its noise draw and the noisy condition), each `[B, 3, F, H, W]`.
const ENCODE_VIDEO_TENSORS: u64 = 4;
/// Video channels (RGB).
const RGB: u64 = 3;
/// fp32 values per pixel of one prefetched sample: 3 target + 3 condition + 1 mask channels
/// (`data.rs`'s `SAMPLE_BYTES_PER_PIXEL`), for monocular and multi-view pairs alike (a multi-view
/// pair's stored render takes the place of the masked target), so `data.multiview_share` does
/// not change the plan.
const LOADER_VALUES_PER_PIXEL: u64 = 7;
/// Resident memory of a training process on the CPU besides its tensors: libtorch's (and its
/// CUDA libraries') code and static data, FFmpeg's, OpenMP/oneDNN thread pools and allocator
/// arenas. Calibrated once on the 2-core x86-64 development machine (torch 2.13.0+cu130): the
/// tiny preset's `trainer pretrain` peaks at 940 MiB RSS (`/usr/bin/time -f %M`) of which the plan
/// counts 28 MiB of tensors; `trainer --help` alone (libraries loaded, no tensors) is 773 MiB.
/// scripts/bench_plan.sh measures both again; the mid-size rows there are the validation.
pub const CPU_RUNTIME_BYTES: u64 = 912 << 20;
/// Copies a checkpoint write holds in host memory per weight byte: `weights::save` copies each
/// tensor into a byte buffer, then `safetensors::serialize` builds the whole file in memory.
const CHECKPOINT_WEIGHT_COPIES: u64 = 2;
/// Share of a CUDA device's free memory the plan leaves to the caching allocator's rounding
/// and fragmentation and to cuDNN/cuBLAS workspaces (a margin, not a measurement: PyTorch's
/// allocator rounds blocks to 512 B / 2 MiB and splits large segments, which typically wastes a
/// few percent of the reserved memory).
pub const CUDA_MARGIN_FRACTION: f64 = 0.05;

/// One `[B, L, D]` tensor (or a multiple of it) that a transformer block saves for its backward.
/// `needs` says when autograd keeps it: PyTorch saves a matmul's input only when the weight
/// needs a gradient, and a product's factor only when the other factor needs one.
#[derive(Debug, Clone, Copy)]
pub struct BlockTerm {
    /// What the tensor is, as the plan prints it.
    pub what: &'static str,
    /// Size in `[B, L, D]` units.
    pub units: u64,
    /// When it is saved.
    pub needs: Needs,
}

/// The condition under which a [`BlockTerm`] is saved.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Needs {
    /// Always (an op whose input needs a gradient saves it whatever trains).
    Always,
    /// When `norm1.linear` trains (the attention's scale, shift and gate then need gradients).
    Norm1,
    /// When `norm2.linear` trains (the feed-forward's scale, shift and gate).
    Norm2,
    /// When `to_q`, `to_k` or `to_v` trains (weight or adapter).
    Qkv,
    /// When `attn1.to_out.0` trains.
    ToOut,
    /// When `ff.net.0.proj` trains.
    FfIn,
    /// When `ff.net.2` trains.
    FfOut,
}

/// What [`CogVideoXBlock::forward`](crate::models::cogvideox::cogvideox_transformer_3d::CogVideoXBlock::forward)
/// keeps for the backward, in order (read off `cogvideox_transformer_3d.rs`, `attention.rs`,
/// `normalization.rs`; SDPA runs a flash kernel on CUDA and on the CPU, which saves q, k, v, the
/// output and a per-row log-sum-exp, never the L × L scores). The rotary embedding multiplies by
/// constant tables (nothing saved); dropout 0 returns its input.
pub const BLOCK_TERMS: [BlockTerm; 15] = [
    BlockTerm { what: "block input (norm1's LayerNorm)", units: 1, needs: Needs::Always },
    BlockTerm { what: "norm1 output (× (1 + scale))", units: 1, needs: Needs::Norm1 },
    BlockTerm { what: "attention input (to_q, to_k, to_v)", units: 1, needs: Needs::Qkv },
    BlockTerm { what: "q, k projections (QK LayerNorms)", units: 2, needs: Needs::Always },
    BlockTerm { what: "rotated q, k (SDPA)", units: 2, needs: Needs::Always },
    BlockTerm { what: "v (SDPA)", units: 1, needs: Needs::Always },
    BlockTerm { what: "SDPA output", units: 1, needs: Needs::Always },
    BlockTerm { what: "merged heads (to_out.0)", units: 1, needs: Needs::ToOut },
    BlockTerm { what: "attention output (× gate)", units: 1, needs: Needs::Norm1 },
    BlockTerm { what: "norm2 input (LayerNorm)", units: 1, needs: Needs::Always },
    BlockTerm { what: "norm2 output (× (1 + scale))", units: 1, needs: Needs::Norm2 },
    BlockTerm { what: "feed-forward input (ff.net.0.proj)", units: 1, needs: Needs::FfIn },
    BlockTerm { what: "ff.net.0.proj output (GELU)", units: FF_MULT, needs: Needs::Always },
    BlockTerm { what: "GELU output (ff.net.2)", units: FF_MULT, needs: Needs::FfOut },
    BlockTerm { what: "feed-forward output (× gate)", units: 1, needs: Needs::Norm2 },
];

/// `[B, L, D]` units alive at once in a block's backward besides its saved tensors: the
/// incoming gradient, the GELU output's gradient (`FF_MULT`) and the GELU input's gradient
/// (`FF_MULT`), which coexist while the GELU backward runs.
const BACKWARD_TRANSIENT_UNITS: u64 = 2 * FF_MULT + 1;
/// `[B, L, D]` units of the gradients a checkpointed backward carries between blocks (the
/// gradient arriving at a block and the one it leaves on its input).
const CHECKPOINT_GRADIENT_UNITS: u64 = 2;
/// `[B, N, D]` units (video tokens only) the head keeps for its backward in full training:
/// norm_final's input, norm_out's input, its normalised output (× (1 + scale)) and proj_out's
/// input. With a frozen head only the two LayerNorm inputs.
const HEAD_UNITS_TRAINED: u64 = 4;
/// As [`HEAD_UNITS_TRAINED`] for a frozen head (LoRA on the blocks).
const HEAD_UNITS_FROZEN: u64 = 2;
/// Channels × frames units of the encoder's first level alive at once in a resnet's causal conv
/// (`autoencoder_kl_cogvideox.rs`): the resnet input (kept for the shortcut), the SiLU output,
/// the padded input (`b + 2` frames), the 2-frame cache copy and the conv output. With `b` the
/// first temporal batch's frames: `3b + (b + 2) + 2` frames.
fn encoder_live_frames(first_batch: u64) -> u64 {
    3 * first_batch + (first_batch + 2) + 2
}
/// The decoder's spatial norms add the latent's two 1×1 convolution outputs (`conv_y`, `conv_b`)
/// at full width to the encoder's live set.
const DECODER_EXTRA_TENSORS: u64 = 2;

/// How the plan should see the run.
#[derive(Debug, Clone, Copy)]
pub struct PlanOptions {
    /// Ranks sharing the work (overrides `data.world_size`).
    pub world_size: usize,
    /// The device one rank trains on (decides `precision = "auto"` and the runtime overhead).
    pub device: Device,
}

/// One line of the plan.
#[derive(Debug, Clone, PartialEq)]
pub struct PlanRow {
    /// What it is.
    pub what: String,
    /// Bytes on one device.
    pub bytes: u64,
    /// How it was counted.
    pub note: String,
}

/// The activation memory of the transformer, with and without checkpointing.
#[derive(Debug, Clone, PartialEq)]
pub struct ActivationPlan {
    /// Bytes of one `[B, L, D]` tensor in the working precision.
    pub unit_bytes: u64,
    /// `[B, L, D]` units one block saves (see [`BLOCK_TERMS`]).
    pub block_units: u64,
    /// Bytes one block saves for its backward.
    pub per_block_bytes: u64,
    /// Peak activation bytes without checkpointing (all blocks saved, the head, the backward's
    /// transients).
    pub without_checkpointing: u64,
    /// Peak activation bytes with checkpointing (every block's input, one block recomputed, the
    /// gradients carried between blocks, the backward's transients).
    pub with_checkpointing: u64,
    /// Whether the config checkpoints.
    pub checkpointing: bool,
}

impl ActivationPlan {
    /// The peak the config's setting gives.
    pub fn used(&self) -> u64 {
        if self.checkpointing { self.with_checkpointing } else { self.without_checkpointing }
    }
}

/// What one device holds for a training config.
#[derive(Debug, Clone, PartialEq)]
pub struct MemoryPlan {
    /// The device the plan is for.
    pub device: Device,
    /// Ranks.
    pub world_size: usize,
    /// ZeRO stage (0 or 2; 0 at world size 1).
    pub zero_stage: u8,
    /// Working precision of the weights and activations.
    pub kind: Kind,
    /// Transformer parameters (base, without adapters).
    pub transformer_parameters: u64,
    /// Parameters that train (the adapters in a LoRA run).
    pub trainable_parameters: u64,
    /// VAE parameters.
    pub vae_parameters: u64,
    /// Per-rank batch, frames and tokens `(B, F, video tokens, text tokens, width, blocks)`.
    pub shape: PlanShape,
    /// Persistent memory: weights, gradients, master weights, moments, inputs.
    pub persistent: Vec<PlanRow>,
    /// Activations.
    pub activations: ActivationPlan,
    /// Peak of the frozen VAE's encode (no autograd state), per step.
    pub vae_encode_peak: u64,
    /// Peak of a VAE decode (validation samples only).
    pub vae_decode_peak: u64,
    /// Whether validation samples decode during training.
    pub validation: bool,
    /// Peak of `AdamW::step`'s temporaries.
    pub optimizer_step_peak: u64,
    /// Peak while the models are loaded in fp32 and the optimizer takes its state.
    pub load_peak: u64,
    /// Host bytes a checkpoint write stages (on the CPU part of the device's peak).
    pub checkpoint_write: u64,
    /// Runtime overhead (CPU: the process's baseline; CUDA: the allocator margin is applied
    /// against free memory instead, see [`fits`]).
    pub runtime: u64,
    /// The predicted peak.
    pub total: u64,
}

/// The sizes the activation counts use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PlanShape {
    /// Samples per rank.
    pub batch: u64,
    /// Pixel frames.
    pub frames: u64,
    /// Video tokens after patching.
    pub video_tokens: u64,
    /// Text tokens.
    pub text_tokens: u64,
    /// Tokens of one activation unit `[B, L, D]`: video + text for CogVideoX's joint attention,
    /// video only for Wan (whose text enters through cross-attention).
    pub unit_tokens: u64,
    /// Token width.
    pub width: u64,
    /// Transformer blocks.
    pub blocks: u64,
}

/// The memory plan of a training run of `config` on `device` with `world_size` ranks (else the
/// launcher's, else the config's `[data] world_size`).
pub fn plan_run(config: &PretrainConfig, world_size: Option<usize>, device: Device) -> Result<MemoryPlan> {
    let world_size = match world_size {
        Some(n) => n,
        None => crate::distributed::launcher_world_size()?.unwrap_or(config.data.world_size),
    };
    plan(config, &PlanOptions { world_size, device })
}

/// The plan of a run about to start as (one rank of) `pg`, shown to `show` on rank 0, and on
/// CUDA refused when it does not fit the device's free memory, before anything is written.
pub fn check_run(
    config: &PretrainConfig,
    device: Device,
    pg: Option<&crate::distributed::ProcessGroup>,
    source_name: &str,
    show: impl FnOnce(&MemoryPlan),
) -> Result<()> {
    // The plan covers the families it runs.
    if !config.model.model_configs(false)?.0.family().runs(crate::models::family::Job::MemoryPlan) {
        return Ok(());
    }
    let plan = plan_run(config, pg.map(|pg| pg.world_size), device)?;
    if pg.is_none_or(|pg| pg.rank == 0) {
        show(&plan);
    }
    check_fits(&plan, source_name)
}

/// Plans `config` on `options.device` with `options.world_size` ranks. The config must have been
/// validated ([`PretrainConfig::validate`]); model configs are resolved (presets or
/// `config.json` files), no weights are read. The family of `[model]` picks the counting:
/// CogVideoX's here, Wan's in [`wan`].
pub fn plan(config: &PretrainConfig, options: &PlanOptions) -> Result<MemoryPlan> {
    if options.world_size == 0 {
        return Err(Error::InvalidArgument { name: "world-size".to_string(), reason: "must be ≥ 1".to_string() });
    }
    let kind = config.train.precision.kind(options.device);
    let counts = match config.model.wan_configs()? {
        Some((transformer, vae_config)) => wan::counts(config, &transformer, &vae_config, options, kind)?,
        None => cogvideox_counts(config, options, kind)?,
    };
    Ok(assemble(config, options, kind, counts))
}

/// What a family's counting gives [`assemble`]: the models' sizes, their rows and peaks.
struct FamilyCounts {
    /// Base transformer parameters.
    transformer_parameters: u64,
    /// Adapter parameters (0 without LoRA).
    adapter_parameters: u64,
    /// The largest base parameter tensor (elements).
    largest_base: u64,
    /// The largest adapter tensor pair of one layer (elements).
    largest_adapter: u64,
    /// VAE parameters.
    vae_parameters: u64,
    /// The transformer weights' row.
    weights: PlanRow,
    /// The frozen models' and inputs' rows after the optimizer's (VAE, text, image tokens).
    frozen: Vec<PlanRow>,
    /// Bytes of the frozen inputs among `frozen` (held while the models load in fp32).
    frozen_inputs: u64,
    /// The activation sizes.
    shape: PlanShape,
    /// The transformer's activations.
    activations: ActivationPlan,
    /// Peak of the frozen VAE's encode, per step.
    vae_encode_peak: u64,
    /// Peak of a VAE decode (validation samples).
    vae_decode_peak: u64,
}

/// CogVideoX's counts (see the module docs).
fn cogvideox_counts(config: &PretrainConfig, options: &PlanOptions, kind: Kind) -> Result<FamilyCounts> {
    let (transformer, vae_config) = config.model.configs(false)?;
    let working = element_bytes(kind);
    let world = options.world_size as u64;

    let base_shapes = variable_shapes(&transformer)?;
    let numel = |shape: &Vec<i64>| shape.iter().map(|&d| d.max(0) as u64).product::<u64>();
    let transformer_parameters: u64 = base_shapes.values().map(numel).sum();
    let largest_base = base_shapes.values().map(numel).max().unwrap_or(0);
    let adapters = match &config.lora {
        Some(lora) => lora_shapes(&transformer, lora)?,
        None => Vec::new(),
    };
    let adapter_parameters: u64 = adapters.iter().map(|(_, n)| n).sum();
    let largest_adapter = adapters.iter().map(|(_, n)| *n).max().unwrap_or(0);
    let vae_parameters = vae_parameter_count(&vae_config)?;

    let d = &config.data;
    let spatial = vae_config.spatial_compression_ratio() as u64;
    let temporal = vae_config.effective_temporal_compression_ratio() as u64;
    let patch = transformer.patch_size as u64;
    let patch_t = transformer.patch_size_t.unwrap_or(1) as u64;
    let latent_frames = (d.frames as u64 - 1) / temporal + 1;
    let video_tokens = latent_frames.div_ceil(patch_t)
        * (u64::from(d.height) / spatial / patch)
        * (u64::from(d.width) / spatial / patch);
    let shape = PlanShape {
        // `data.batch_size` is the global batch; each rank takes an equal share.
        batch: (d.batch_size as u64).div_ceil(world),
        frames: d.frames as u64,
        video_tokens,
        text_tokens: transformer.max_text_seq_length as u64,
        unit_tokens: video_tokens + transformer.max_text_seq_length as u64,
        width: transformer.inner_dim() as u64,
        blocks: transformer.num_layers as u64,
    };

    let weights = PlanRow {
        what: "transformer weights".to_string(),
        bytes: (transformer_parameters + adapter_parameters) * working,
        note: format!(
            "{} parameters{} × {working} B ({}), full on every rank",
            human_count(transformer_parameters),
            if adapter_parameters > 0 {
                format!(" + {} adapter", human_count(adapter_parameters))
            } else {
                String::new()
            },
            kind_name(kind)
        ),
    };
    let text_bytes = shape.text_tokens * transformer.text_embed_dim as u64 * FP32_BYTES;
    let frozen = frozen_rows(
        vae_parameters,
        working,
        text_bytes,
        format!("[{}, {}] fp32, no gradients", shape.text_tokens, transformer.text_embed_dim),
    );

    let activations = activation_plan(config.lora.as_ref(), &shape, working, config.train.gradient_checkpointing);
    let pixels = shape.frames * u64::from(d.height) * u64::from(d.width);
    let video_bytes = shape.batch * RGB * pixels * FP32_BYTES;
    let first_batch = first_temporal_batch(shape.frames, vae::SAMPLE_FRAMES_BATCH_SIZE as u64);
    let level0 = vae_config.block_out_channels.first().copied().unwrap_or(0) as u64;
    let frame_plane = shape.batch * level0 * u64::from(d.height) * u64::from(d.width) * working;
    let vae_encode_peak = ENCODE_VIDEO_TENSORS * video_bytes
        + shape.batch * RGB * pixels * working
        + encoder_live_frames(first_batch) * frame_plane;
    let decode_first = first_temporal_batch(latent_frames, vae::LATENT_FRAMES_BATCH_SIZE as u64);
    let decode_frames = (decode_first - 1) * temporal + 1;
    let vae_decode_peak =
        (encoder_live_frames(decode_frames) + DECODER_EXTRA_TENSORS * decode_frames) * frame_plane + video_bytes;
    Ok(FamilyCounts {
        transformer_parameters,
        adapter_parameters,
        largest_base,
        largest_adapter,
        vae_parameters,
        weights,
        frozen,
        frozen_inputs: text_bytes,
        shape,
        activations,
        vae_encode_peak,
        vae_decode_peak,
    })
}

/// The rows of the frozen inputs every family has: the VAE's weights (`vae_parameters` of
/// `working` bytes) and the text embedding (`text_bytes`, counted as `text_note` says).
fn frozen_rows(vae_parameters: u64, working: u64, text_bytes: u64, text_note: String) -> Vec<PlanRow> {
    vec![
        PlanRow {
            what: "VAE weights (frozen)".to_string(),
            bytes: vae_parameters * working,
            note: format!("{} parameters × {working} B, no gradients", human_count(vae_parameters)),
        },
        PlanRow { what: "text embedding (frozen)".to_string(), bytes: text_bytes, note: text_note },
    ]
}

/// The rows and peaks every family shares around its `counts`: gradients, master weights and
/// AdamW moments of what trains (ZeRO-2 sharded), the loader's batches on the CPU, the optimizer
/// step, the fp32 load, checkpoint writes and the CPU runtime.
fn assemble(config: &PretrainConfig, options: &PlanOptions, kind: Kind, counts: FamilyCounts) -> MemoryPlan {
    let FamilyCounts {
        transformer_parameters,
        adapter_parameters,
        largest_base,
        largest_adapter,
        vae_parameters,
        weights,
        frozen,
        frozen_inputs,
        shape,
        activations,
        vae_encode_peak,
        vae_decode_peak,
    } = counts;
    let working = element_bytes(kind);
    let world = options.world_size as u64;
    let zero_stage = if world > 1 { config.distributed.zero_stage } else { 0 };
    let shard = |bytes: u64| if zero_stage == 2 { bytes.div_ceil(world) } else { bytes };
    let (trainable, largest_trainable) = match &config.lora {
        Some(_) => (adapter_parameters, largest_adapter),
        None => (transformer_parameters, largest_base),
    };

    let mut persistent = vec![weights];
    let kind_name = kind_name(kind);
    let grads = trainable * working;
    let (grad_bytes, grad_note) = if zero_stage == 2 {
        (
            grads + (trainable * FP32_BYTES).div_ceil(world),
            format!(
                "{} trainable × {working} B full buffer during the backward + fp32 1/{world} shard",
                human_count(trainable)
            ),
        )
    } else {
        (grads, format!("{} trainable × {working} B ({kind_name})", human_count(trainable)))
    };
    persistent.push(PlanRow { what: "gradients".to_string(), bytes: grad_bytes, note: grad_note });
    let master = if kind == Kind::Float { 0 } else { shard(trainable * FP32_BYTES) };
    persistent.push(PlanRow {
        what: "master weights".to_string(),
        bytes: master,
        note: if kind == Kind::Float {
            "none (training in fp32)".to_string()
        } else {
            format!("fp32 copy of the trainable parameters{}", shard_note(zero_stage, world))
        },
    });
    let moments = shard(ADAM_MOMENTS * trainable * FP32_BYTES);
    persistent.push(PlanRow {
        what: "optimizer state".to_string(),
        bytes: moments,
        note: format!("AdamW exp_avg + exp_avg_sq, fp32{}", shard_note(zero_stage, world)),
    });
    persistent.extend(frozen);
    let d = &config.data;
    let pixels = shape.frames * u64::from(d.height) * u64::from(d.width);
    if options.device == Device::Cpu {
        // The loader's prefetched batches live in host memory, which on the CPU is the device.
        let batches = d.prefetch_batches as u64 + 1;
        persistent.push(PlanRow {
            what: "data loader batches (host)".to_string(),
            bytes: batches * shape.batch * pixels * LOADER_VALUES_PER_PIXEL * FP32_BYTES,
            note: format!("{batches} batches (prefetched + current) of {} samples, 7 fp32 per pixel", shape.batch),
        });
    }

    let validation = config.train.validate_every > 0;
    let bucket_elements = ((config.distributed.bucket_mib * (1u64 << 20) as f64) as u64 / working).min(trainable);
    let optimizer_step_peak = OPTIMIZER_TEMPORARIES * largest_trainable.max(bucket_elements) * FP32_BYTES;
    let persistent_total: u64 = persistent.iter().map(|r| r.bytes).sum();
    let step_peak = persistent_total
        + activations.used().max(vae_encode_peak).max(optimizer_step_peak).max(if validation {
            vae_decode_peak
        } else {
            0
        });
    // Loading: both models in fp32, then the optimizer's moments and (bf16) master copies, all
    // before the cast to the working precision.
    let load_peak =
        (transformer_parameters + adapter_parameters + vae_parameters) * FP32_BYTES + moments + master + frozen_inputs;
    // A checkpoint write (every `checkpoint_every` steps and at the end) stages the trained
    // weights and then the optimizer file in host memory: on the CPU that is the device.
    let saved_weights = if config.lora.is_some() { trainable } else { transformer_parameters } * FP32_BYTES;
    let checkpoint_write = (CHECKPOINT_WEIGHT_COPIES * saved_weights).max(ADAM_MOMENTS * trainable * FP32_BYTES);
    let host_checkpoint = if options.device == Device::Cpu { checkpoint_write } else { 0 };
    let runtime = if options.device == Device::Cpu { CPU_RUNTIME_BYTES } else { 0 };
    let total = step_peak.max(load_peak).max(persistent_total + host_checkpoint) + runtime;
    MemoryPlan {
        device: options.device,
        world_size: options.world_size,
        zero_stage,
        kind,
        transformer_parameters,
        trainable_parameters: trainable,
        vae_parameters,
        shape,
        persistent,
        activations,
        vae_encode_peak,
        vae_decode_peak,
        validation,
        optimizer_step_peak,
        load_peak,
        checkpoint_write,
        runtime,
        total,
    }
}

/// The activation peaks for `shape` in the working precision (`working` bytes per element).
fn activation_plan(lora: Option<&LoraConfig>, shape: &PlanShape, working: u64, checkpointing: bool) -> ActivationPlan {
    let trains = |module: &str| lora.is_none_or(|l| l.targets(&format!("transformer_blocks.0.{module}")));
    let needed = |needs: Needs| match needs {
        Needs::Always => true,
        Needs::Norm1 => trains("norm1.linear"),
        Needs::Norm2 => trains("norm2.linear"),
        Needs::Qkv => trains("attn1.to_q") || trains("attn1.to_k") || trains("attn1.to_v"),
        Needs::ToOut => trains("attn1.to_out.0"),
        Needs::FfIn => trains("ff.net.0.proj"),
        Needs::FfOut => trains("ff.net.2"),
    };
    let block_units: u64 = BLOCK_TERMS.iter().filter(|t| needed(t.needs)).map(|t| t.units).sum();
    let tokens = shape.unit_tokens;
    let unit_bytes = shape.batch * tokens * shape.width * working;
    // An adapter's down-projection output `[B, L, r]` is saved for its up-projection.
    let adapter_bytes = lora.map_or(0, |l| {
        let adapted = ["attn1.to_q", "attn1.to_k", "attn1.to_v", "attn1.to_out.0", "ff.net.0.proj", "ff.net.2"]
            .iter()
            .filter(|m| l.targets(&format!("transformer_blocks.0.{m}")))
            .count() as u64;
        adapted * shape.batch * tokens * l.rank as u64 * working
    });
    let per_block_bytes = block_units * unit_bytes + adapter_bytes;
    let head_units = if lora.is_some() { HEAD_UNITS_FROZEN } else { HEAD_UNITS_TRAINED };
    let head = head_units * shape.batch * shape.video_tokens * shape.width * working;
    let transient = BACKWARD_TRANSIENT_UNITS * unit_bytes;
    let without = shape.blocks * per_block_bytes + head + transient;
    // Checkpointed: each block's input and the last block's output are kept; the backward
    // rebuilds one block's graph at a time and carries two gradients between blocks.
    let with = (shape.blocks + 1) * unit_bytes + per_block_bytes + CHECKPOINT_GRADIENT_UNITS * unit_bytes + transient;
    ActivationPlan {
        unit_bytes,
        block_units,
        per_block_bytes,
        without_checkpointing: without,
        // The head's backward runs before the blocks are recomputed, over the kept inputs.
        with_checkpointing: with.max(head + (shape.blocks + 1) * unit_bytes),
        checkpointing,
    }
}

/// diffusers' temporal batching: the first batch holds `batch + n % batch` frames (all of them
/// when fewer than `batch`).
fn first_temporal_batch(n: u64, batch: u64) -> u64 {
    if n <= batch { n } else { batch + n % batch }
}

/// The adapters' names and parameter counts (`r·in + out·r` per adapted linear layer).
fn lora_shapes(transformer: &CogVideoXTransformer3DModelConfig, lora: &LoraConfig) -> Result<Vec<(String, u64)>> {
    let shapes = variable_shapes(transformer)?;
    let rank = lora.rank.max(0) as u64;
    Ok(shapes
        .iter()
        .filter(|(_, shape)| shape.len() == 2)
        .filter_map(|(name, shape)| {
            let module = name.strip_suffix(".weight")?;
            lora.targets(module).then(|| (module.to_string(), rank * (shape[0] + shape[1]).max(0) as u64))
        })
        .collect())
}

/// The VAE's parameter count, from a store built on the CPU (a few hundred MiB for the 5B VAE,
/// freed before anything else is allocated).
fn vae_parameter_count(config: &AutoencoderKLCogVideoXConfig) -> Result<u64> {
    tch::no_grad(|| -> Result<u64> {
        let (vs, _) = vae::build(config, Device::Cpu, Kind::Float)?;
        Ok(vs.variables().values().map(|t| t.numel() as u64).sum())
    })
}

fn element_bytes(kind: Kind) -> u64 {
    match kind {
        Kind::BFloat16 | Kind::Half => 2,
        Kind::Double => 8,
        _ => FP32_BYTES,
    }
}

fn kind_name(kind: Kind) -> &'static str {
    match kind {
        Kind::BFloat16 => "bf16",
        Kind::Half => "fp16",
        _ => "fp32",
    }
}

fn shard_note(zero_stage: u8, world: u64) -> String {
    if zero_stage == 2 { format!(", 1/{world} shard (ZeRO-2)") } else { String::new() }
}

fn human_count(n: u64) -> String {
    match n {
        n if n >= 1_000_000_000 => format!("{:.2} B", n as f64 / 1e9),
        n if n >= 1_000_000 => format!("{:.1} M", n as f64 / 1e6),
        n if n >= 1_000 => format!("{:.1} k", n as f64 / 1e3),
        n => n.to_string(),
    }
}

/// Bytes as GiB with two decimals (MiB below 1 GiB).
pub fn human_bytes(bytes: u64) -> String {
    const GIB: f64 = (1u64 << 30) as f64;
    const MIB: f64 = (1u64 << 20) as f64;
    if bytes as f64 >= GIB {
        format!("{:.2} GiB", bytes as f64 / GIB)
    } else {
        format!("{:.1} MiB", bytes as f64 / MIB)
    }
}

/// Checks `plan` against the free memory of its device: on CUDA, the predicted peak must fit in
/// the free memory less [`CUDA_MARGIN_FRACTION`]; elsewhere (or when free memory cannot be read)
/// nothing is checked. `source_name` names the config in the error, which says by how much the
/// plan is over and what would shrink it.
pub fn check_fits(plan: &MemoryPlan, source_name: &str) -> Result<()> {
    let Device::Cuda(index) = plan.device else { return Ok(()) };
    let Some((free, total)) = crate::distributed::cuda_mem_get_info(index) else { return Ok(()) };
    fits(plan, free, total, source_name)
}

/// [`check_fits`] for a given `free` / `total` device memory in bytes.
pub fn fits(plan: &MemoryPlan, free: u64, total: u64, source_name: &str) -> Result<()> {
    let Some(shortfall) = shortfall(plan.total, plan.device, free, total) else { return Ok(()) };
    let mut hints = Vec::new();
    if !plan.activations.checkpointing && plan.activations.with_checkpointing < plan.activations.without_checkpointing {
        hints.push(format!(
            "`[loop] gradient_checkpointing = true` (activations {} instead of {})",
            human_bytes(plan.activations.with_checkpointing),
            human_bytes(plan.activations.without_checkpointing)
        ));
    }
    if plan.trainable_parameters == plan.transformer_parameters {
        hints.push("a `[lora]` section (only the adapters train)".to_string());
        if plan.world_size > 1 && plan.zero_stage == 0 {
            hints.push("`[distributed] zero_stage = 2`".to_string());
        }
    }
    if plan.shape.batch > 1 {
        hints.push("a smaller `data.batch_size` with `optim.grad_accumulation`".to_string());
    }
    Err(Error::InvalidConfig {
        source_name: source_name.to_string(),
        field: "(memory plan)".to_string(),
        reason: format!(
            "the run {shortfall}; nothing was written.{}",
            if hints.is_empty() { String::new() } else { format!(" Try {}.", hints.join(", or ")) }
        ),
    })
}

/// "needs … on DEVICE but only … are free" when `needed` bytes exceed what [`CUDA_MARGIN_FRACTION`]
/// leaves of `free`; None when they fit.
fn shortfall(needed: u64, device: Device, free: u64, total: u64) -> Option<String> {
    let usable = (free as f64 * (1.0 - CUDA_MARGIN_FRACTION)) as u64;
    (needed > usable).then(|| {
        format!(
            "needs {} on {device:?} but only {} of its {} are free ({} after the {:.0} % allocator margin)",
            human_bytes(needed),
            human_bytes(free),
            human_bytes(total),
            human_bytes(usable),
            CUDA_MARGIN_FRACTION * 100.0,
        )
    })
}

impl fmt::Display for MemoryPlan {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = &self.shape;
        let lora = if self.trainable_parameters < self.transformer_parameters {
            format!("LoRA ({} trainable)", human_count(self.trainable_parameters))
        } else {
            "full training".to_string()
        };
        writeln!(
            f,
            "memory plan per device: {:?}, {}, world size {}{}, {lora}, gradient checkpointing {}",
            self.device,
            kind_name(self.kind),
            self.world_size,
            if self.zero_stage == 2 { " (ZeRO-2)" } else { "" },
            if self.activations.checkpointing { "on" } else { "off" }
        )?;
        writeln!(
            f,
            "  batch {} × {} frames → {} video + {} text tokens of width {}, {} blocks",
            s.batch, s.frames, s.video_tokens, s.text_tokens, s.width, s.blocks
        )?;
        let line = |f: &mut fmt::Formatter<'_>, what: &str, bytes: u64, note: &str| {
            writeln!(f, "  {what:<38} {:>11}  {note}", human_bytes(bytes))
        };
        for row in &self.persistent {
            line(f, &row.what, row.bytes, &row.note)?;
        }
        let a = &self.activations;
        line(
            f,
            "activations, per block",
            a.per_block_bytes,
            &format!("{} saved [{}, {}, {}] tensors + adapters", a.block_units, s.batch, s.unit_tokens, s.width),
        )?;
        line(
            f,
            "activations without checkpointing",
            a.without_checkpointing,
            if a.checkpointing { "" } else { "← used" },
        )?;
        line(f, "activations with checkpointing", a.with_checkpointing, if a.checkpointing { "← used" } else { "" })?;
        line(f, "VAE encode peak (no autograd)", self.vae_encode_peak, "per step, before the transformer")?;
        line(
            f,
            "VAE decode peak (no autograd)",
            self.vae_decode_peak,
            if self.validation { "validation samples" } else { "not used (no validation samples)" },
        )?;
        line(f, "optimizer step peak", self.optimizer_step_peak, "largest trainable tensor's fp32 temporaries")?;
        line(f, "load peak", self.load_peak, "models in fp32 + optimizer state, before any bf16 cast")?;
        line(
            f,
            "checkpoint write (host memory)",
            self.checkpoint_write,
            if self.device == Device::Cpu { "on top of the persistent rows" } else { "host RAM, not device memory" },
        )?;
        if self.runtime > 0 {
            line(f, "runtime (CPU process baseline)", self.runtime, "libtorch, thread pools, allocator")?;
        }
        write!(f, "  {:<38} {:>11}", "total (predicted peak)", human_bytes(self.total))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_temporal_batch_matches_the_vae_batching() {
        for (n, batch) in [(49, 8), (9, 8), (13, 2), (5, 8), (17, 8)] {
            let expected = vae::temporal_batches(n as i64, batch as usize)[0].1 as u64;
            assert_eq!(first_temporal_batch(n, batch), expected, "{n} frames, batch {batch}");
        }
    }

    #[test]
    fn full_and_lora_block_terms_follow_what_trains() {
        let shape =
            PlanShape { batch: 1, frames: 9, video_tokens: 60, text_tokens: 8, unit_tokens: 68, width: 32, blocks: 2 };
        let full = activation_plan(None, &shape, 4, false);
        // Every term when everything trains.
        assert_eq!(full.block_units, BLOCK_TERMS.iter().map(|t| t.units).sum::<u64>());
        let lora = LoraConfig::default();
        let adapted = activation_plan(Some(&lora), &shape, 4, false);
        // Frozen modulation and feed-forward: no norm outputs, gated outputs, ff inputs.
        assert_eq!(adapted.block_units, full.block_units - 2 - 2 - 1 - FF_MULT);
        assert!(activation_plan(None, &shape, 4, true).used() < full.used());
    }
}

/// `[B, L, D]` units alive at once in a block's forward without autograd: the residual stream,
/// the normalised input and the feed-forward's hidden and GELU outputs (`FF_MULT` each), the
/// largest point of a block (attention holds fewer: q, k, v, rotated q and k, and its output).
const INFERENCE_LIVE_UNITS: u64 = 2 + 2 * FF_MULT;
/// Tiled decoding keeps every decoded tile until they are blended: the output video and the
/// tiles' overlaps, about half as much again at diffusers' default overlaps.
const TILED_OUTPUT_COPIES: f64 = 1.5;

/// What one device holds to sample a video with [`crate::pipelines::sampling::CogNvsPipeline`].
#[derive(Debug, Clone, PartialEq)]
pub struct SamplingPlan {
    /// The device.
    pub device: Device,
    /// The models' element type.
    pub kind: Kind,
    /// Frames, height and width sampled.
    pub video: (u64, u64, u64),
    /// Whether guidance runs a batch of two.
    pub guided: bool,
    /// Whether the VAE tiles.
    pub tiling: bool,
    /// Resident rows: weights and text.
    pub persistent: Vec<PlanRow>,
    /// Peak of loading: the weights plus one tensor converted in fp32.
    pub load_peak: u64,
    /// Activations of one transformer forward (no autograd).
    pub denoise_peak: u64,
    /// Peak of the VAE encode of the conditioning.
    pub vae_encode_peak: u64,
    /// Peak of the VAE decode of the result.
    pub vae_decode_peak: u64,
    /// Runtime overhead (CPU only, as for training).
    pub runtime: u64,
    /// The predicted peak.
    pub total: u64,
}

/// The memory plan of sampling `frames` frames of `height × width` with these models in `kind`:
/// the same counting as [`plan`]'s VAE peaks, a forward's live activations
/// ([`INFERENCE_LIVE_UNITS`]) at batch 2 when `guided`, and the load's one-tensor conversions.
#[allow(clippy::too_many_arguments)]
pub fn sampling_plan(
    transformer: &CogVideoXTransformer3DModelConfig,
    vae_config: &AutoencoderKLCogVideoXConfig,
    (frames, height, width): (u64, u64, u64),
    kind: Kind,
    device: Device,
    tiling: Option<&vae::TilingConfig>,
    guided: bool,
) -> Result<SamplingPlan> {
    let working = element_bytes(kind);
    let numel = |shape: &Vec<i64>| shape.iter().map(|&d| d.max(0) as u64).product::<u64>();
    let shapes = variable_shapes(transformer)?;
    let transformer_parameters: u64 = shapes.values().map(numel).sum();
    let largest = shapes.values().map(numel).max().unwrap_or(0);
    let vae_parameters = vae_parameter_count(vae_config)?;
    let batch = if guided { 2 } else { 1 };
    let spatial = vae_config.spatial_compression_ratio() as u64;
    let temporal = vae_config.effective_temporal_compression_ratio() as u64;
    let patch = transformer.patch_size as u64;
    // `frames`, `height` and `width` come from flags: every count sized by them is checked, so a
    // huge value is refused naming it instead of wrapping (release) or panicking (debug).
    let overflow = || Error::InvalidArgument {
        name: "frames".to_string(),
        reason: format!(
            "{frames} frames of {width}x{height}: the memory they need does not fit 64 bits; sample fewer frames or \
             a smaller size"
        ),
    };
    let mul = |factors: &[u64]| factors.iter().try_fold(1u64, |total, &f| total.checked_mul(f)).ok_or_else(overflow);
    let add = |terms: &[u64]| terms.iter().try_fold(0u64, |total, &t| total.checked_add(t)).ok_or_else(overflow);
    let latent_frames = frames.saturating_sub(1) / temporal + 1;
    let video_tokens = mul(&[
        latent_frames.div_ceil(transformer.patch_size_t.unwrap_or(1) as u64),
        height / spatial / patch,
        width / spatial / patch,
    ])?;
    let tokens = add(&[video_tokens, transformer.max_text_seq_length as u64])?;
    let text_bytes = 2 * transformer.max_text_seq_length as u64 * transformer.text_embed_dim as u64 * working;
    let persistent = vec![
        PlanRow {
            what: "transformer weights".to_string(),
            bytes: transformer_parameters * working,
            note: format!("{} parameters × {working} B ({})", human_count(transformer_parameters), kind_name(kind)),
        },
        PlanRow {
            what: "VAE weights".to_string(),
            bytes: vae_parameters * working,
            note: format!("{} parameters × {working} B", human_count(vae_parameters)),
        },
        PlanRow {
            what: "text embeddings".to_string(),
            bytes: text_bytes,
            note: "prompt and negative prompt".to_string(),
        },
    ];
    let resident: u64 = persistent.iter().map(|r| r.bytes).sum();
    let denoise_peak = mul(&[INFERENCE_LIVE_UNITS, batch, tokens, transformer.inner_dim() as u64, working])?;
    let (tile_h, tile_w) = match tiling {
        Some(t) => ((t.tile_sample_min_height as u64).min(height), (t.tile_sample_min_width as u64).min(width)),
        None => (height, width),
    };
    let level0 = vae_config.block_out_channels.first().copied().unwrap_or(0) as u64;
    let video_bytes = mul(&[RGB, frames, height, width, working])?;
    let tile_plane = mul(&[level0, tile_h, tile_w, working])?;
    let first_batch = first_temporal_batch(frames, vae::SAMPLE_FRAMES_BATCH_SIZE as u64);
    let output_copies = if tiling.is_some() { TILED_OUTPUT_COPIES } else { 1.0 };
    let vae_encode_peak = add(&[mul(&[2, video_bytes])?, mul(&[encoder_live_frames(first_batch), tile_plane])?])?;
    let decode_first = first_temporal_batch(latent_frames, vae::LATENT_FRAMES_BATCH_SIZE as u64);
    let decode_frames = (decode_first - 1) * temporal + 1;
    let decode_live = encoder_live_frames(decode_frames) + DECODER_EXTRA_TENSORS * decode_frames;
    // Below 2^64 already (`video_bytes` is), so the float product converts back exactly enough.
    let output_bytes = (output_copies * video_bytes as f64).min(u64::MAX as f64) as u64;
    let vae_decode_peak = add(&[mul(&[decode_live, tile_plane])?, output_bytes])?;
    // Built in the working type; loading converts one checkpoint tensor at a time, and a LoRA
    // merge holds one layer in fp32.
    let load_peak = resident + largest * FP32_BYTES;
    let runtime = if device == Device::Cpu { CPU_RUNTIME_BYTES } else { 0 };
    let total =
        add(&[load_peak.max(add(&[resident, denoise_peak.max(vae_encode_peak).max(vae_decode_peak)])?), runtime])?;
    Ok(SamplingPlan {
        device,
        kind,
        video: (frames, height, width),
        guided,
        tiling: tiling.is_some(),
        persistent,
        load_peak,
        denoise_peak,
        vae_encode_peak,
        vae_decode_peak,
        runtime,
        total,
    })
}

impl fmt::Display for SamplingPlan {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (frames, height, width) = self.video;
        writeln!(
            f,
            "sampling memory plan: {:?}, {}, {frames} frames of {width}x{height}, guidance batch {}, VAE tiling {}",
            self.device,
            kind_name(self.kind),
            if self.guided { 2 } else { 1 },
            if self.tiling { "on" } else { "off" }
        )?;
        let line = |f: &mut fmt::Formatter<'_>, what: &str, bytes: u64, note: &str| {
            writeln!(f, "  {what:<38} {:>11}  {note}", human_bytes(bytes))
        };
        for row in &self.persistent {
            line(f, &row.what, row.bytes, &row.note)?;
        }
        line(f, "denoising activations", self.denoise_peak, "one forward's live tensors, no autograd")?;
        line(f, "VAE encode peak", self.vae_encode_peak, "the conditioning")?;
        line(f, "VAE decode peak", self.vae_decode_peak, "the result")?;
        line(f, "load peak", self.load_peak, "weights + one tensor converted in fp32")?;
        if self.runtime > 0 {
            line(f, "runtime (CPU process)", self.runtime, "libraries and allocator arenas")?;
        }
        line(f, "total (predicted peak)", self.total, "")
    }
}

/// The memory plan of sampling with `paths` as `options` and `framing` say (the model's size and
/// `framing.frames`), guided when a negative prompt is given; reads the configs only.
pub fn sampling_plan_for(
    paths: &crate::loaders::ModelPaths,
    options: crate::pipelines::sampling::LoadOptions,
    framing: &crate::pipelines::sampling::Framing,
) -> Result<SamplingPlan> {
    let config = CogVideoXTransformer3DModelConfig::from_json_file(&paths.transformer)?;
    let vae_config = AutoencoderKLCogVideoXConfig::from_json_file(&paths.vae)?;
    let spatial = vae_config.spatial_compression_ratio();
    let (width, height) = framing
        .size
        .map_or(((config.sample_width * spatial) as u64, (config.sample_height * spatial) as u64), |(w, h)| {
            (u64::from(w), u64::from(h))
        });
    let tiles = vae::TilingConfig::for_config(&vae_config);
    let tiling = (options.vae_tiling && tiles.lands_on_latent_pixels(spatial)).then_some(&tiles);
    sampling_plan(
        &config,
        &vae_config,
        (framing.frames as u64, height, width),
        options.precision.kind(options.device),
        options.device,
        tiling,
        paths.negative_text_embedding.is_some(),
    )
}

/// Refuses a sample of the models `paths` names that does not fit its CUDA device: CogVideoX's
/// sampling plan ([`sampling_plan_for`]) against the free memory; Wan has no sampling plan yet
/// and is not checked.
pub fn check_sampling_memory(
    paths: &crate::loaders::ModelPaths,
    options: crate::pipelines::sampling::LoadOptions,
    framing: &crate::pipelines::sampling::Framing,
) -> Result<()> {
    match crate::models::family::ModelFamily::of_transformer(&paths.transformer)? {
        crate::models::family::ModelFamily::CogVideoX => {
            check_sampling_fits(&sampling_plan_for(paths, options, framing)?)
        }
        crate::models::family::ModelFamily::Wan => Ok(()),
    }
}

/// Checks a sampling plan against the free memory of its CUDA device (nothing elsewhere).
pub fn check_sampling_fits(plan: &SamplingPlan) -> Result<()> {
    let Device::Cuda(index) = plan.device else { return Ok(()) };
    let Some((free, total)) = crate::distributed::cuda_mem_get_info(index) else { return Ok(()) };
    let Some(shortfall) = shortfall(plan.total, plan.device, free, total) else { return Ok(()) };
    let hint = if plan.tiling { "" } else { "; VAE tiling would lower the decode peak" };
    Err(Error::InvalidArgument { name: "device".to_string(), reason: format!("sampling {shortfall}{hint}") })
}

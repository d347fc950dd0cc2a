//! The CogVideoX 3D causal VAE: diffusers' `AutoencoderKLCogVideoX`
//! (`diffusers/models/autoencoders/autoencoder_kl_cogvideox.py`, with `CogVideoXDownsample3D` and
//! `CogVideoXUpsample3D` from `downsampling.py` / `upsampling.py`), weight-compatible with it.
//!
//! Video `[B, 3, F, H, W]` in `[-1, 1]` ⇄ latent `[B, 16, 1 + (F − 1)/4, H/8, W/8]`.
//! Every convolution is causal in time: a frame only sees itself and earlier frames, the first frame
//! being repeated as padding. That makes streaming possible: diffusers encodes a clip in temporal
//! batches of 8 frames (the first batch takes the extra leading frame, 1 + 8k frames in all) and
//! carries each causal convolution's last input frames (its *conv cache*) from one batch to the
//! next; decoding does the same with batches of 2 latent frames. [`EncoderStream`] and
//! [`DecoderStream`] expose that. Large frames can also be split into overlapping spatial tiles
//! blended linearly across the overlap ([`TilingConfig`], diffusers' `tiled_encode` /
//! `tiled_decode`), which bounds memory whatever the resolution.
//!
//! Note on exactness: the resnets' GroupNorm normalises over time as well, so its statistics (and
//! hence the output) depend on how frames are batched. Temporally batched encoding is what
//! diffusers (and so every CogVideoX latent ever trained on) computes; it is close to, not equal
//! to, a single pass over all frames. The causal convolutions themselves stream exactly.
//!
//! Variables live at diffusers' state-dict paths (`encoder.down_blocks.0.resnets.0.conv1.conv.weight`),
//! so a diffusers checkpoint loads into the [`tch::nn::VarStore`] unchanged.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor, nn};

use crate::diffusers_config::{self, DiffusersConfig};
use crate::error::{Error, Result};

/// The class name diffusers writes into the VAE's `config.json` (`_class_name`).
pub const CLASS_NAME: &str = "AutoencoderKLCogVideoX";
/// The only down block type diffusers' CogVideoX encoder accepts.
pub const DOWN_BLOCK_TYPE: &str = "CogVideoXDownBlock3D";
/// The only up block type diffusers' CogVideoX decoder accepts.
pub const UP_BLOCK_TYPE: &str = "CogVideoXUpBlock3D";

/// Frames per temporal batch when encoding (diffusers' `num_sample_frames_batch_size`).
pub const SAMPLE_FRAMES_BATCH_SIZE: usize = 8;
/// Latent frames per temporal batch when decoding (diffusers' `num_latent_frames_batch_size`;
/// diffusers notes the VAE was not trained for other values).
pub const LATENT_FRAMES_BATCH_SIZE: usize = 2;
/// Above this many input elements a 3D convolution runs in temporal pieces (diffusers'
/// `CogVideoXSafeConv3d`: "2 GB" of 2-byte values, i.e. 2^30 elements). The result is identical.
const SAFE_CONV_MAX_ELEMENTS: i64 = 1 << 30;
/// On the CPU libtorch runs 3D convolutions as unfold + GEMM, with an unfolded-input buffer of
/// `C_in · k³ · frames · H · W` elements (4.8 GB for one 480×720 frame at 128 channels); above
/// this many elements (1 GiB of fp32) the convolution runs a few output frames at a time.
const CPU_CONV_WORKSPACE_ELEMENTS: i64 = 1 << 28;
/// GroupNorm epsilon that diffusers hard-codes for the encoder's `norm_out` and for every
/// `CogVideoXSpatialNorm3D` (independent of `norm_eps`).
const FIXED_NORM_EPS: f64 = 1e-6;
/// Resnets in the encoder's and decoder's mid block (diffusers passes `num_layers=2` to both).
const MID_BLOCK_LAYERS: i64 = 2;
/// The diagonal Gaussian posterior clamps its log-variance to this range (diffusers'
/// `DiagonalGaussianDistribution`).
const LOGVAR_RANGE: (f64, f64) = (-30.0, 20.0);

// ------------------------------------------------------------------------------------------------
// Configuration
// ------------------------------------------------------------------------------------------------

/// The VAE's `config.json` as diffusers writes it, field names verbatim. Missing fields take
/// diffusers' `__init__` defaults; keys starting with `_` are diffusers metadata; any other key is
/// kept in [`Self::unknown_keys`] (and reported by [`Self::from_json_file`]) rather than dropped.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AutoencoderKLCogVideoXConfig {
    /// Channels of the input video (3, RGB).
    pub in_channels: i64,
    /// Channels of the decoded video (3, RGB).
    pub out_channels: i64,
    /// Encoder block types, one per resolution level; only `CogVideoXDownBlock3D`.
    pub down_block_types: Vec<String>,
    /// Decoder block types, one per resolution level; only `CogVideoXUpBlock3D`.
    pub up_block_types: Vec<String>,
    /// Channel width of each resolution level; `len − 1` spatial halvings.
    pub block_out_channels: Vec<i64>,
    /// Latent channels (16 for CogVideoX).
    pub latent_channels: i64,
    /// Resnets per encoder level (the decoder has one more per level).
    pub layers_per_block: i64,
    /// Activation; diffusers' CogVideoX VAE uses `silu` (`swish` is the same function).
    pub act_fn: String,
    /// GroupNorm epsilon inside the resnets.
    pub norm_eps: f64,
    /// GroupNorm groups everywhere.
    pub norm_num_groups: i64,
    /// Temporal compression (4): the first `int(log2(ratio))` levels also halve time, as in
    /// diffusers, but the last level never downsamples, so time is compressed by at most
    /// `2^(levels − 1)` (see [`Self::effective_temporal_compression_ratio`]). Valid: finite, > 0
    /// (what diffusers accepts); a ratio that is not a power of two or needs more levels than the
    /// config has is computed as diffusers computes it, with a warning.
    pub temporal_compression_ratio: f64,
    /// Nominal frame height; the default spatial tile is half of it.
    pub sample_height: i64,
    /// Nominal frame width; the default spatial tile is half of it.
    pub sample_width: i64,
    /// Latent scale used by the diffusion model: `z = posterior_mean · scaling_factor`
    /// (0.7 for the 5B models). Not applied by [`AutoencoderKLCogVideoX::encode`].
    pub scaling_factor: f64,
    /// Optional latent shift (unused by CogVideoX; kept for round-tripping).
    pub shift_factor: Option<f64>,
    /// Optional per-channel latent means (unused by CogVideoX).
    pub latents_mean: Option<Vec<f64>>,
    /// Optional per-channel latent standard deviations (unused by CogVideoX).
    pub latents_std: Option<Vec<f64>>,
    /// Whether pipelines should run the VAE in fp32.
    pub force_upcast: bool,
    /// An extra 1×1×1 conv after the encoder; CogVideoX checkpoints have none (rejected if true).
    pub use_quant_conv: bool,
    /// An extra 1×1×1 conv before the decoder; CogVideoX checkpoints have none (rejected if true).
    pub use_post_quant_conv: bool,
    /// CogVideoX 1.5 I2V pipelines divide instead of multiply by `scaling_factor` for the image
    /// latent; pipelines read it, the VAE does not.
    pub invert_scale_latents: bool,
    /// Every other key: `_class_name`, `_diffusers_version`, … and unknown keys.
    #[serde(flatten)]
    pub extra: BTreeMap<String, serde_json::Value>,
}

impl Default for AutoencoderKLCogVideoXConfig {
    /// diffusers' `AutoencoderKLCogVideoX.__init__` defaults (the CogVideoX-2B VAE).
    fn default() -> Self {
        Self {
            in_channels: 3,
            out_channels: 3,
            down_block_types: vec![DOWN_BLOCK_TYPE.to_string(); 4],
            up_block_types: vec![UP_BLOCK_TYPE.to_string(); 4],
            block_out_channels: vec![128, 256, 256, 512],
            latent_channels: 16,
            layers_per_block: 3,
            act_fn: "silu".to_string(),
            norm_eps: 1e-6,
            norm_num_groups: 32,
            temporal_compression_ratio: 4.0,
            sample_height: 480,
            sample_width: 720,
            scaling_factor: 1.152_584_26,
            shift_factor: None,
            latents_mean: None,
            latents_std: None,
            force_upcast: true,
            use_quant_conv: false,
            use_post_quant_conv: false,
            invert_scale_latents: false,
            extra: BTreeMap::new(),
        }
    }
}

impl DiffusersConfig for AutoencoderKLCogVideoXConfig {
    const KIND: &'static str = "VAE";
    const CLASS_NAMES: &'static [&'static str] = &[CLASS_NAME];
    const FILE_NAME: &'static str = "config.json";

    /// Rejects combinations the architecture cannot build, naming the field.
    fn validate_fields(&self, source_name: &str) -> Result<()> {
        let err = diffusers_config::field_error(source_name);
        let levels = self.block_out_channels.len();
        if levels == 0 {
            return Err(err("block_out_channels", "is empty".to_string()));
        }
        if levels > MAX_LEVELS {
            return Err(err(
                "block_out_channels",
                format!("{levels} levels: at most {MAX_LEVELS} (2^{} spatial compression)", MAX_LEVELS - 1),
            ));
        }
        if self.down_block_types.len() != levels {
            return Err(err(
                "down_block_types",
                format!("has {} entries but block_out_channels has {levels}", self.down_block_types.len()),
            ));
        }
        if self.up_block_types.len() != levels {
            return Err(err(
                "up_block_types",
                format!("has {} entries but block_out_channels has {levels}", self.up_block_types.len()),
            ));
        }
        if let Some(t) = self.down_block_types.iter().find(|t| *t != DOWN_BLOCK_TYPE) {
            return Err(err("down_block_types", format!("`{t}` is not supported (only `{DOWN_BLOCK_TYPE}`)")));
        }
        if let Some(t) = self.up_block_types.iter().find(|t| *t != UP_BLOCK_TYPE) {
            return Err(err("up_block_types", format!("`{t}` is not supported (only `{UP_BLOCK_TYPE}`)")));
        }
        if self.act_fn != "silu" && self.act_fn != "swish" {
            return Err(err("act_fn", format!("`{}` is not supported (only `silu`)", self.act_fn)));
        }
        if self.norm_num_groups <= 0 {
            return Err(err("norm_num_groups", format!("must be positive, got {}", self.norm_num_groups)));
        }
        for (field, value) in [
            ("in_channels", self.in_channels),
            ("out_channels", self.out_channels),
            ("latent_channels", self.latent_channels),
            ("layers_per_block", self.layers_per_block),
        ] {
            if value <= 0 {
                return Err(err(field, format!("must be positive, got {value}")));
            }
        }
        if let Some(c) = self.block_out_channels.iter().find(|&&c| c <= 0 || c % self.norm_num_groups != 0) {
            return Err(err(
                "block_out_channels",
                format!("{c} is not a positive multiple of norm_num_groups ({})", self.norm_num_groups),
            ));
        }
        // diffusers fails on `int(np.log2(r))` for r <= 0 (and NaN); anything else it builds.
        let ratio = self.temporal_compression_ratio;
        if !(ratio.is_finite() && ratio > 0.0) {
            return Err(err("temporal_compression_ratio", format!("{ratio} must be finite and > 0")));
        }
        if self.use_quant_conv {
            return Err(err("use_quant_conv", "true is not supported (no CogVideoX checkpoint uses it)".to_string()));
        }
        if self.use_post_quant_conv {
            return Err(err(
                "use_post_quant_conv",
                "true is not supported (no CogVideoX checkpoint uses it)".to_string(),
            ));
        }
        if self.sample_height <= 0 || self.sample_width <= 0 {
            return Err(err("sample_height", "sample_height and sample_width must be positive".to_string()));
        }
        Ok(())
    }

    fn extra(&self) -> &BTreeMap<String, serde_json::Value> {
        &self.extra
    }

    fn warnings(&self) -> Vec<String> {
        let ratio = self.temporal_compression_ratio;
        let effective = self.effective_temporal_compression_ratio();
        if ratio == effective as f64 {
            return Vec::new();
        }
        vec![format!(
            "temporal_compression_ratio {ratio} with {} levels compresses time by {effective} (diffusers halves time \
             in the first int(log2({ratio})) levels but never in the last one); computing what diffusers computes",
            self.block_out_channels.len()
        )]
    }
}

/// Most resolution levels a config may have: CogVideoX has 4; 16 already means 32768× spatial
/// compression, and the compression ratios are computed as `i64` powers of two.
pub const MAX_LEVELS: usize = 16;

impl AutoencoderKLCogVideoXConfig {
    /// The VAE of CogVideoX-5B / 5B-I2V (and so of CogNVS): `THUDM/CogVideoX-5b-I2V`
    /// `vae/config.json` — the 2B architecture with `scaling_factor` 0.7.
    pub fn cogvideox_5b() -> Self {
        Self { scaling_factor: 0.7, ..Self::default() }
    }

    /// The VAE of CogVideoX-2B: `THUDM/CogVideoX-2b` `vae/config.json` (= diffusers' defaults).
    pub fn cogvideox_2b() -> Self {
        Self::default()
    }

    /// Same structure as the real VAE (4 levels: 8× spatial, 4× temporal compression, 16 latent
    /// channels) with small widths, for tests; `scripts/goldens_vae_scheduler.py` builds the same.
    pub fn tiny() -> Self {
        Self {
            block_out_channels: vec![16, 32, 32, 64],
            layers_per_block: 1,
            norm_num_groups: 8,
            sample_height: 64,
            sample_width: 80,
            scaling_factor: 0.7,
            ..Self::default()
        }
    }

    /// A preset by name: `cogvideox-5b` (alias `cognvs-5b`), `cogvideox-2b`, `tiny`.
    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "cogvideox-5b" | "cognvs-5b" => Ok(Self::cogvideox_5b()),
            "cogvideox-2b" => Ok(Self::cogvideox_2b()),
            "tiny" => Ok(Self::tiny()),
            other => Err(Error::InvalidConfig {
                source_name: "preset".to_string(),
                field: "name".to_string(),
                reason: format!("unknown VAE preset `{other}`; expected cogvideox-5b, cogvideox-2b or tiny"),
            }),
        }
    }

    /// Spatial down-scaling factor, `2^(levels − 1)` (8).
    pub fn spatial_compression_ratio(&self) -> i64 {
        1 << (self.block_out_channels.len().saturating_sub(1))
    }

    /// diffusers' `temporal_compress_level = int(np.log2(temporal_compression_ratio))` (2): levels
    /// `i < temporal_compress_level` get `compress_time` (a truncation toward zero; negative for
    /// ratios below 1/2, then no level compresses time).
    pub fn temporal_compress_level(&self) -> usize {
        // `as` saturates negatives to 0, which selects the same (no) levels as diffusers' `i < −1`.
        self.temporal_compression_ratio.log2().trunc() as usize
    }

    /// The time compression the levels really give: `2^min(temporal_compress_level, levels − 1)`,
    /// since only levels with a downsampler (all but the last) can halve time.
    pub fn effective_temporal_compression_ratio(&self) -> i64 {
        let downsampling = self.block_out_channels.len().saturating_sub(1);
        1 << self.temporal_compress_level().min(downsampling)
    }
}

/// Spatial tiling (diffusers' `enable_tiling` arguments). Frames larger than a tile in either
/// dimension are split into tiles of `tile_sample_min_height × tile_sample_min_width` pixels whose
/// neighbours overlap by the given fractions; tile outputs are blended linearly across the overlap.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TilingConfig {
    /// Tile height in pixels (diffusers' default: `sample_height / 2`).
    pub tile_sample_min_height: i64,
    /// Tile width in pixels (diffusers' default: `sample_width / 2`).
    pub tile_sample_min_width: i64,
    /// Fraction of a tile's height shared with the tile below (diffusers' default: 1/6).
    pub tile_overlap_factor_height: f64,
    /// Fraction of a tile's width shared with the tile to the right (diffusers' default: 1/5).
    pub tile_overlap_factor_width: f64,
}

impl TilingConfig {
    /// diffusers' defaults for `config`: half the nominal frame, overlaps 1/6 (height) and 1/5
    /// (width), "chosen based on experimentation … for 720x480" (diffusers' comment).
    pub fn for_config(config: &AutoencoderKLCogVideoXConfig) -> Self {
        Self {
            tile_sample_min_height: config.sample_height / 2,
            tile_sample_min_width: config.sample_width / 2,
            tile_overlap_factor_height: 1.0 / 6.0,
            tile_overlap_factor_width: 1.0 / 5.0,
        }
    }

    /// Whether the tiles land on whole latent pixels, so that a tiled encode or decode has the
    /// untiled size: every tile and every stride between tiles a multiple of `spatial_ratio`
    /// pixels, and what each tile keeps after its blend exactly one stride. True of the default
    /// tiles of the 480×720 VAE; diffusers' default tiles of smaller nominal frames can break
    /// this (a 64×80 VAE encodes a 64×80 clip to 9×10 latents), which is why sampling tiles
    /// only where it holds.
    pub fn lands_on_latent_pixels(&self, spatial_ratio: i64) -> bool {
        let p = TilePlan::new(self, spatial_ratio);
        let axis = |tile: i64, latent_tile: i64, stride: i64, latent_blend: i64, latent_stride: i64, blend: i64| {
            tile % spatial_ratio == 0
                && stride % spatial_ratio == 0
                && latent_tile - latent_blend == stride / spatial_ratio
                && tile - blend == latent_stride * spatial_ratio
        };
        axis(p.sample_tile_h, p.latent_tile_h, p.sample_stride_h, p.latent_blend_h, p.latent_stride_h, p.sample_blend_h)
            && axis(
                p.sample_tile_w,
                p.latent_tile_w,
                p.sample_stride_w,
                p.latent_blend_w,
                p.latent_stride_w,
                p.sample_blend_w,
            )
    }

    fn validate(&self, spatial_ratio: i64) -> Result<()> {
        let bad = |reason: String| Error::InvalidConfig {
            source_name: "tiling".to_string(),
            field: "TilingConfig".to_string(),
            reason,
        };
        if self.tile_sample_min_height < spatial_ratio || self.tile_sample_min_width < spatial_ratio {
            return Err(bad(format!("tiles must be at least {spatial_ratio} pixels in each dimension")));
        }
        for f in [self.tile_overlap_factor_height, self.tile_overlap_factor_width] {
            if !(0.0..1.0).contains(&f) {
                return Err(bad(format!("overlap factor {f} must be in [0, 1)")));
            }
        }
        let plan = TilePlan::new(self, spatial_ratio);
        if plan.sample_stride_h <= 0
            || plan.sample_stride_w <= 0
            || plan.latent_stride_h <= 0
            || plan.latent_stride_w <= 0
        {
            return Err(bad("overlap leaves no stride between tiles".to_string()));
        }
        Ok(())
    }
}

/// The integer quantities diffusers derives from a [`TilingConfig`] (same truncations).
#[derive(Debug, Clone, Copy)]
struct TilePlan {
    sample_tile_h: i64,
    sample_tile_w: i64,
    latent_tile_h: i64,
    latent_tile_w: i64,
    /// Encode: stride between tiles in pixels; blend extent and kept size in latent pixels.
    sample_stride_h: i64,
    sample_stride_w: i64,
    latent_blend_h: i64,
    latent_blend_w: i64,
    /// Decode: stride between tiles in latent pixels; blend extent and kept size in pixels.
    latent_stride_h: i64,
    latent_stride_w: i64,
    sample_blend_h: i64,
    sample_blend_w: i64,
}

impl TilePlan {
    fn new(t: &TilingConfig, spatial_ratio: i64) -> Self {
        let latent_tile_h = t.tile_sample_min_height / spatial_ratio;
        let latent_tile_w = t.tile_sample_min_width / spatial_ratio;
        let (fh, fw) = (t.tile_overlap_factor_height, t.tile_overlap_factor_width);
        Self {
            sample_tile_h: t.tile_sample_min_height,
            sample_tile_w: t.tile_sample_min_width,
            latent_tile_h,
            latent_tile_w,
            sample_stride_h: (t.tile_sample_min_height as f64 * (1.0 - fh)) as i64,
            sample_stride_w: (t.tile_sample_min_width as f64 * (1.0 - fw)) as i64,
            latent_blend_h: (latent_tile_h as f64 * fh) as i64,
            latent_blend_w: (latent_tile_w as f64 * fw) as i64,
            latent_stride_h: (latent_tile_h as f64 * (1.0 - fh)) as i64,
            latent_stride_w: (latent_tile_w as f64 * (1.0 - fw)) as i64,
            sample_blend_h: (t.tile_sample_min_height as f64 * fh) as i64,
            sample_blend_w: (t.tile_sample_min_width as f64 * fw) as i64,
        }
    }
}

// ------------------------------------------------------------------------------------------------
// Building blocks
// ------------------------------------------------------------------------------------------------

/// The per-convolution temporal caches of one streaming pass, in the order the forward pass visits
/// the causal convolutions with a time kernel > 1 (the same order on every batch).
#[derive(Debug, Default)]
struct ConvCache {
    slots: Vec<Option<Tensor>>,
    cursor: usize,
}

impl ConvCache {
    /// Starts a new batch: the next forward pass reads the caches in order from the beginning.
    fn rewind(&mut self) {
        self.cursor = 0;
    }

    /// The cache of the next causal convolution (None on the first batch).
    fn take_next(&mut self) -> Option<Tensor> {
        if self.cursor == self.slots.len() {
            self.slots.push(None);
        }
        self.slots[self.cursor].take()
    }

    /// Stores the cache of the convolution whose cache [`Self::take_next`] just returned.
    fn put(&mut self, cache: Tensor) {
        self.slots[self.cursor] = Some(cache);
        self.cursor += 1;
    }
}

fn conv_init(fan_in: i64) -> (nn::Init, nn::Init) {
    // PyTorch's default Conv init: kaiming-uniform(a = √5) weights, uniform(±1/√fan_in) bias.
    let bound = 1.0 / (fan_in as f64).sqrt();
    (nn::Init::Uniform { lo: -bound, up: bound }, nn::Init::Uniform { lo: -bound, up: bound })
}

/// A convolution's parameters at `path.weight` / `path.bias`.
#[derive(Debug)]
struct ConvParams {
    weight: Tensor,
    bias: Tensor,
}

impl ConvParams {
    fn new(path: &nn::Path, out_channels: i64, in_channels: i64, kernel: &[i64]) -> Self {
        let fan_in = in_channels * kernel.iter().product::<i64>();
        let (w_init, b_init) = conv_init(fan_in);
        let mut dims = vec![out_channels, in_channels];
        dims.extend_from_slice(kernel);
        Self { weight: path.var("weight", &dims, w_init), bias: path.var("bias", &[out_channels], b_init) }
    }
}

/// `CogVideoXSafeConv3d`: a stride-1 `Conv3d` with spatial zero padding only, run in temporal
/// pieces (each re-reading the `k − 1` frames before it) when diffusers would split it (input
/// above [`SAFE_CONV_MAX_ELEMENTS`]) or, on the CPU, when libtorch's unfolded-input buffer would
/// exceed [`CPU_CONV_WORKSPACE_ELEMENTS`]. Every output frame is computed from the same inputs
/// either way, so the result does not depend on the split.
fn safe_conv3d(input: &Tensor, p: &ConvParams, padding: [i64; 3]) -> Result<Tensor> {
    let workspace = (input.device() == Device::Cpu).then_some(CPU_CONV_WORKSPACE_ELEMENTS);
    conv3d_in_pieces(input, p, padding, SAFE_CONV_MAX_ELEMENTS, workspace)
}

fn conv3d_in_pieces(
    input: &Tensor,
    p: &ConvParams,
    padding: [i64; 3],
    max_elements: i64,
    workspace_elements: Option<i64>,
) -> Result<Tensor> {
    let conv = |xs: &Tensor| xs.f_conv3d(&p.weight, Some(&p.bias), [1, 1, 1], padding, [1, 1, 1], 1);
    let size = input.size();
    let numel: i64 = size.iter().product();
    let wsize = p.weight.size();
    let (time_kernel, kernel_volume) = (wsize[2], wsize[2..].iter().product::<i64>());
    let out_frames = size[2] - time_kernel + 1;
    if out_frames <= 1 {
        return Ok(conv(input)?);
    }
    let mut per_piece = out_frames;
    if numel > max_elements {
        // diffusers: torch.chunk into numel / 2^30 + 1 pieces along time.
        let pieces = numel / max_elements + 1;
        per_piece = per_piece.min((out_frames + pieces - 1) / pieces);
    }
    if let Some(budget) = workspace_elements {
        // slow_conv3d unfolds [C_in · k³, frames · H · W] per sample.
        let per_frame = size[1] * kernel_volume * size[3] * size[4];
        per_piece = per_piece.min((budget / per_frame.max(1)).max(1));
    }
    if per_piece >= out_frames {
        return Ok(conv(input)?);
    }
    let mut outputs = Vec::new();
    let mut first = 0;
    while first < out_frames {
        let n = per_piece.min(out_frames - first);
        outputs.push(conv(&input.f_narrow(2, first, n + time_kernel - 1)?)?);
        first += n;
    }
    Ok(Tensor::f_cat(&outputs, 2)?)
}

/// `CogVideoXCausalConv3d` (pad mode "constant"): the time axis is padded on the past side only,
/// with the previous batch's last frames when streaming or else with copies of the first frame;
/// height and width are zero-padded symmetrically.
#[derive(Debug)]
struct CausalConv3d {
    conv: ConvParams,
    time_kernel: i64,
    height_pad: i64,
    width_pad: i64,
}

impl CausalConv3d {
    fn new(path: &nn::Path, in_channels: i64, out_channels: i64, kernel: i64) -> Self {
        Self {
            conv: ConvParams::new(&(path / "conv"), out_channels, in_channels, &[kernel, kernel, kernel]),
            time_kernel: kernel,
            height_pad: (kernel - 1) / 2,
            width_pad: (kernel - 1) / 2,
        }
    }

    fn forward(&self, xs: &Tensor, cache: &mut ConvCache) -> Result<Tensor> {
        let padding = [0, self.height_pad, self.width_pad];
        if self.time_kernel == 1 {
            return safe_conv3d(xs, &self.conv, padding);
        }
        let past = self.time_kernel - 1;
        let prefix = match cache.take_next() {
            Some(cached) => cached,
            None => xs.f_narrow(2, 0, 1)?.f_repeat([1, 1, past, 1, 1])?,
        };
        let padded = Tensor::f_cat(&[&prefix, xs], 2)?;
        let frames = padded.size()[2];
        // A copy, not a view: the view would keep the whole padded input alive.
        cache.put(padded.f_narrow(2, frames - past, past)?.copy());
        safe_conv3d(&padded, &self.conv, padding)
    }
}

/// `nn.GroupNorm` at `path.weight` / `path.bias`.
#[derive(Debug)]
struct GroupNorm {
    weight: Tensor,
    bias: Tensor,
    groups: i64,
    eps: f64,
}

impl GroupNorm {
    fn new(path: &nn::Path, channels: i64, groups: i64, eps: f64) -> Self {
        Self {
            weight: path.var("weight", &[channels], nn::Init::Const(1.0)),
            bias: path.var("bias", &[channels], nn::Init::Const(0.0)),
            groups,
            eps,
        }
    }

    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        Ok(xs.f_group_norm(self.groups, Some(&self.weight), Some(&self.bias), self.eps, true)?)
    }
}

/// Nearest-neighbour resize of `[B, C, T, H, W]` to `(t, h, w)` (`F.interpolate`, mode "nearest").
fn nearest3d(xs: &Tensor, t: i64, h: i64, w: i64) -> Result<Tensor> {
    Ok(xs.f_upsample_nearest3d([t, h, w], None, None, None)?)
}

/// `CogVideoXSpatialNorm3D`: GroupNorm whose scale and shift are 1×1×1 convolutions of the latent
/// `zq`, resized (nearest) to the feature map; an odd frame count keeps the first frame apart.
#[derive(Debug)]
struct SpatialNorm3D {
    norm_layer: GroupNorm,
    conv_y: CausalConv3d,
    conv_b: CausalConv3d,
}

impl SpatialNorm3D {
    fn new(path: &nn::Path, f_channels: i64, zq_channels: i64, groups: i64) -> Self {
        Self {
            norm_layer: GroupNorm::new(&(path / "norm_layer"), f_channels, groups, FIXED_NORM_EPS),
            conv_y: CausalConv3d::new(&(path / "conv_y"), zq_channels, f_channels, 1),
            conv_b: CausalConv3d::new(&(path / "conv_b"), zq_channels, f_channels, 1),
        }
    }

    fn forward(&self, f: &Tensor, zq: &Tensor, cache: &mut ConvCache) -> Result<Tensor> {
        let [_, _, t, h, w] = dims5(f, "spatial-norm features")?;
        let zt = zq.size()[2];
        let zq = if t > 1 && t % 2 == 1 && zt > 1 {
            let first = nearest3d(&zq.f_narrow(2, 0, 1)?, 1, h, w)?;
            let rest = nearest3d(&zq.f_narrow(2, 1, zt - 1)?, t - 1, h, w)?;
            Tensor::f_cat(&[first, rest], 2)?
        } else {
            nearest3d(zq, t, h, w)?
        };
        let y = self.conv_y.forward(&zq, cache)?;
        let b = self.conv_b.forward(&zq, cache)?;
        Ok(self.norm_layer.forward(f)?.f_mul(&y)?.f_add(&b)?)
    }
}

/// The two kinds of normalisation a resnet uses: plain GroupNorm (encoder) or spatial norm
/// conditioned on the latent (decoder).
#[derive(Debug)]
enum Norm {
    Group(GroupNorm),
    Spatial(SpatialNorm3D),
}

impl Norm {
    fn forward(&self, xs: &Tensor, zq: Option<&Tensor>, cache: &mut ConvCache) -> Result<Tensor> {
        match (self, zq) {
            (Norm::Group(n), _) => n.forward(xs),
            (Norm::Spatial(n), Some(zq)) => n.forward(xs, zq, cache),
            (Norm::Spatial(_), None) => unreachable!("decoder resnets always receive the latent"),
        }
    }
}

/// `CogVideoXResnetBlock3D` without time embedding (the VAE passes none): norm → SiLU → causal
/// conv, twice, plus a 1×1×1 `conv_shortcut` when the width changes.
#[derive(Debug)]
struct ResnetBlock3D {
    norm1: Norm,
    conv1: CausalConv3d,
    norm2: Norm,
    conv2: CausalConv3d,
    conv_shortcut: Option<ConvParams>,
}

impl ResnetBlock3D {
    fn new(path: &nn::Path, in_channels: i64, out_channels: i64, cfg: &AutoencoderKLCogVideoXConfig, zq: bool) -> Self {
        let groups = cfg.norm_num_groups;
        let norm = |name: &str, channels: i64| {
            if zq {
                Norm::Spatial(SpatialNorm3D::new(&(path / name), channels, cfg.latent_channels, groups))
            } else {
                Norm::Group(GroupNorm::new(&(path / name), channels, groups, cfg.norm_eps))
            }
        };
        Self {
            norm1: norm("norm1", in_channels),
            conv1: CausalConv3d::new(&(path / "conv1"), in_channels, out_channels, 3),
            norm2: norm("norm2", out_channels),
            conv2: CausalConv3d::new(&(path / "conv2"), out_channels, out_channels, 3),
            conv_shortcut: (in_channels != out_channels)
                .then(|| ConvParams::new(&(path / "conv_shortcut"), out_channels, in_channels, &[1, 1, 1])),
        }
    }

    fn forward(&self, xs: &Tensor, zq: Option<&Tensor>, cache: &mut ConvCache) -> Result<Tensor> {
        let h = self.norm1.forward(xs, zq, cache)?.f_silu()?;
        let h = self.conv1.forward(&h, cache)?;
        let h = self.norm2.forward(&h, zq, cache)?.f_silu()?;
        let h = self.conv2.forward(&h, cache)?;
        let shortcut = match &self.conv_shortcut {
            Some(p) => safe_conv3d(xs, p, [0, 0, 0])?,
            None => xs.shallow_clone(),
        };
        Ok(h.f_add(&shortcut)?)
    }
}

/// Per-frame 2D conv weights `[O, I, kh, kw]` applied as a 3D conv with a 1-frame kernel, which
/// equals diffusers' reshape to `[B·T, C, H, W]` + `Conv2d` without the two transposing copies.
fn frame_conv2d(xs: &Tensor, p: &ConvParams, stride: i64, padding: i64) -> Result<Tensor> {
    let weight = p.weight.f_unsqueeze(2)?;
    Ok(xs.f_conv3d(&weight, Some(&p.bias), [1, stride, stride], [0, padding, padding], [1, 1, 1], 1)?)
}

/// `CogVideoXDownsample3D`: optional temporal halving (average of frame pairs, an odd first frame
/// kept alone), then a stride-2 3×3 conv per frame after padding right and bottom by one.
#[derive(Debug)]
struct Downsample3D {
    conv: ConvParams,
    compress_time: bool,
}

impl Downsample3D {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let mut xs = xs.shallow_clone();
        if self.compress_time {
            let [b, c, t, h, w] = dims5(&xs, "downsample input")?;
            let odd = t % 2;
            let pairs = (t - odd) / 2;
            let rest = xs.f_narrow(2, odd, 2 * pairs)?.f_reshape([b, c, pairs, 2, h, w])?;
            // (a + b) / 2 exactly as avg_pool1d(kernel 2, stride 2) computes it.
            let pooled = rest.f_sum_dim_intlist([3i64].as_slice(), false, None::<Kind>)?.f_div_scalar(2.0)?;
            xs = if odd == 1 { Tensor::f_cat(&[xs.f_narrow(2, 0, 1)?, pooled], 2)? } else { pooled };
        }
        let xs = xs.f_constant_pad_nd([0, 1, 0, 1])?;
        frame_conv2d(&xs, &self.conv, 2, 0)
    }
}

/// `CogVideoXUpsample3D`: nearest 2× upsampling in space (and in time for the first levels, an odd
/// first frame staying single), then a 3×3 conv per frame.
#[derive(Debug)]
struct Upsample3D {
    conv: ConvParams,
    compress_time: bool,
}

impl Upsample3D {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let [_, _, t, h, w] = dims5(xs, "upsample input")?;
        let up = if self.compress_time && t > 1 && t % 2 == 1 {
            let first = nearest3d(&xs.f_narrow(2, 0, 1)?, 1, 2 * h, 2 * w)?;
            let rest = nearest3d(&xs.f_narrow(2, 1, t - 1)?, 2 * (t - 1), 2 * h, 2 * w)?;
            Tensor::f_cat(&[first, rest], 2)?
        } else if self.compress_time && t > 1 {
            nearest3d(xs, 2 * t, 2 * h, 2 * w)?
        } else {
            nearest3d(xs, t, 2 * h, 2 * w)?
        };
        frame_conv2d(&up, &self.conv, 1, 1)
    }
}

/// `CogVideoXEncoder3D`: conv_in → down blocks (resnets + downsampler) → 2-resnet mid block →
/// GroupNorm → SiLU → conv_out to `2 × latent_channels` moments (mean, log-variance).
#[derive(Debug)]
struct Encoder3D {
    conv_in: CausalConv3d,
    down_blocks: Vec<(Vec<ResnetBlock3D>, Option<Downsample3D>)>,
    mid_block: Vec<ResnetBlock3D>,
    norm_out: GroupNorm,
    conv_out: CausalConv3d,
}

impl Encoder3D {
    fn new(path: &nn::Path, cfg: &AutoencoderKLCogVideoXConfig) -> Self {
        let boc = &cfg.block_out_channels;
        let level = cfg.temporal_compress_level();
        let conv_in = CausalConv3d::new(&(path / "conv_in"), cfg.in_channels, boc[0], 3);
        let mut down_blocks = Vec::new();
        let mut out_ch = boc[0];
        for (i, &ch) in boc.iter().enumerate() {
            let block = path / "down_blocks" / i;
            let in_ch = out_ch;
            out_ch = ch;
            let resnets = (0..cfg.layers_per_block)
                .map(|j| {
                    let c_in = if j == 0 { in_ch } else { out_ch };
                    ResnetBlock3D::new(&(&block / "resnets" / j), c_in, out_ch, cfg, false)
                })
                .collect();
            let down = (i + 1 < boc.len()).then(|| Downsample3D {
                conv: ConvParams::new(&(&block / "downsamplers" / 0 / "conv"), out_ch, out_ch, &[3, 3]),
                compress_time: i < level,
            });
            down_blocks.push((resnets, down));
        }
        let last = *boc.last().expect("validated: block_out_channels is non-empty");
        let mid_block = (0..MID_BLOCK_LAYERS)
            .map(|j| ResnetBlock3D::new(&(path / "mid_block" / "resnets" / j), last, last, cfg, false))
            .collect();
        Self {
            conv_in,
            down_blocks,
            mid_block,
            norm_out: GroupNorm::new(&(path / "norm_out"), last, cfg.norm_num_groups, FIXED_NORM_EPS),
            conv_out: CausalConv3d::new(&(path / "conv_out"), last, 2 * cfg.latent_channels, 3),
        }
    }

    fn forward(&self, xs: &Tensor, cache: &mut ConvCache) -> Result<Tensor> {
        cache.rewind();
        let mut h = self.conv_in.forward(xs, cache)?;
        for (resnets, down) in &self.down_blocks {
            for r in resnets {
                h = r.forward(&h, None, cache)?;
            }
            if let Some(d) = down {
                h = d.forward(&h)?;
            }
        }
        for r in &self.mid_block {
            h = r.forward(&h, None, cache)?;
        }
        let h = self.norm_out.forward(&h)?.f_silu()?;
        self.conv_out.forward(&h, cache)
    }
}

/// `CogVideoXDecoder3D`: conv_in → 2-resnet mid block → up blocks (`layers_per_block + 1` resnets
/// + upsampler) → spatial norm → SiLU → conv_out; every norm is conditioned on the latent.
#[derive(Debug)]
struct Decoder3D {
    conv_in: CausalConv3d,
    mid_block: Vec<ResnetBlock3D>,
    up_blocks: Vec<(Vec<ResnetBlock3D>, Option<Upsample3D>)>,
    norm_out: SpatialNorm3D,
    conv_out: CausalConv3d,
}

impl Decoder3D {
    fn new(path: &nn::Path, cfg: &AutoencoderKLCogVideoXConfig) -> Self {
        let rev: Vec<i64> = cfg.block_out_channels.iter().rev().copied().collect();
        let level = cfg.temporal_compress_level();
        let conv_in = CausalConv3d::new(&(path / "conv_in"), cfg.latent_channels, rev[0], 3);
        let mid_block = (0..MID_BLOCK_LAYERS)
            .map(|j| ResnetBlock3D::new(&(path / "mid_block" / "resnets" / j), rev[0], rev[0], cfg, true))
            .collect();
        let mut up_blocks = Vec::new();
        let mut out_ch = rev[0];
        for (i, &ch) in rev.iter().enumerate() {
            let block = path / "up_blocks" / i;
            let in_ch = out_ch;
            out_ch = ch;
            let resnets = (0..cfg.layers_per_block + 1)
                .map(|j| {
                    let c_in = if j == 0 { in_ch } else { out_ch };
                    ResnetBlock3D::new(&(&block / "resnets" / j), c_in, out_ch, cfg, true)
                })
                .collect();
            let up = (i + 1 < rev.len()).then(|| Upsample3D {
                conv: ConvParams::new(&(&block / "upsamplers" / 0 / "conv"), out_ch, out_ch, &[3, 3]),
                compress_time: i < level,
            });
            up_blocks.push((resnets, up));
        }
        let last = *rev.last().expect("validated: block_out_channels is non-empty");
        Self {
            conv_in,
            mid_block,
            up_blocks,
            norm_out: SpatialNorm3D::new(&(path / "norm_out"), last, cfg.latent_channels, cfg.norm_num_groups),
            conv_out: CausalConv3d::new(&(path / "conv_out"), last, cfg.out_channels, 3),
        }
    }

    fn forward(&self, z: &Tensor, cache: &mut ConvCache) -> Result<Tensor> {
        cache.rewind();
        let mut h = self.conv_in.forward(z, cache)?;
        for r in &self.mid_block {
            h = r.forward(&h, Some(z), cache)?;
        }
        for (resnets, up) in &self.up_blocks {
            for r in resnets {
                h = r.forward(&h, Some(z), cache)?;
            }
            if let Some(u) = up {
                h = u.forward(&h)?;
            }
        }
        let h = self.norm_out.forward(&h, z, cache)?.f_silu()?;
        self.conv_out.forward(&h, cache)
    }
}

fn dims5(xs: &Tensor, name: &str) -> Result<[i64; 5]> {
    let size = xs.size();
    <[i64; 5]>::try_from(size.as_slice()).map_err(|_| Error::Shape {
        tensor: name.to_string(),
        expected: "[B, C, F, H, W]".to_string(),
        actual: size.clone(),
    })
}

/// diffusers' temporal batching: `max(n / batch, 1)` batches of `batch` frames, the remainder
/// `n % batch` going to the first one. Returns `(start, len)` pairs covering `0..n`.
pub fn temporal_batches(n: i64, batch: usize) -> Vec<(i64, i64)> {
    let batch = batch.max(1) as i64;
    let count = (n / batch).max(1);
    let rem = n % batch;
    (0..count)
        .map(|i| {
            let start = batch * i + if i == 0 { 0 } else { rem };
            let end = (batch * (i + 1) + rem).min(n);
            (start, end - start)
        })
        .collect()
}

// ------------------------------------------------------------------------------------------------
// The model
// ------------------------------------------------------------------------------------------------

/// The posterior `N(mean, exp(logvar))` of a latent (diffusers' `DiagonalGaussianDistribution`).
#[derive(Debug)]
pub struct DiagonalGaussian {
    /// Posterior mean `[B, latent_channels, f, h, w]` (the "mode"; unscaled).
    pub mean: Tensor,
    /// Log-variance, clamped to [−30, 20] like diffusers.
    pub logvar: Tensor,
}

impl DiagonalGaussian {
    /// Splits encoder moments `[B, 2·latent_channels, …]` into mean and clamped log-variance.
    pub(crate) fn from_moments(moments: &Tensor, latent_channels: i64) -> Result<Self> {
        let mean = moments.f_narrow(1, 0, latent_channels)?;
        let logvar = moments.f_narrow(1, latent_channels, latent_channels)?.f_clamp(LOGVAR_RANGE.0, LOGVAR_RANGE.1)?;
        Ok(Self { mean, logvar })
    }

    /// A sample `mean + exp(logvar / 2) · ε`, ε ~ N(0, 1) from tch's global generator.
    pub fn sample(&self) -> Result<Tensor> {
        let std = self.logvar.f_mul_scalar(0.5)?.f_exp()?;
        let eps = self.mean.f_randn_like()?;
        Ok(self.mean.f_add(&std.f_mul(&eps)?)?)
    }
}

/// diffusers' `AutoencoderKLCogVideoX` (eval mode): variables under `encoder.` and `decoder.` of
/// the given path, exactly diffusers' state-dict names.
#[derive(Debug)]
pub struct AutoencoderKLCogVideoX {
    config: AutoencoderKLCogVideoXConfig,
    encoder: Encoder3D,
    decoder: Decoder3D,
    tiling: Option<TilingConfig>,
    weight_probe: Tensor,
}

impl AutoencoderKLCogVideoX {
    /// Creates the variables under `path` (random init; load weights into the VarStore after).
    pub fn new(path: &nn::Path, config: &AutoencoderKLCogVideoXConfig) -> Result<Self> {
        config.validate("AutoencoderKLCogVideoX::new")?;
        let encoder = Encoder3D::new(&(path / "encoder"), config);
        let decoder = Decoder3D::new(&(path / "decoder"), config);
        let weight_probe = encoder.conv_in.conv.weight.shallow_clone();
        Ok(Self { config: config.clone(), encoder, decoder, tiling: None, weight_probe })
    }

    /// The configuration the model was built from.
    pub fn config(&self) -> &AutoencoderKLCogVideoXConfig {
        &self.config
    }

    /// The element type of the weights, which inputs must have.
    pub fn kind(&self) -> Kind {
        self.weight_probe.kind()
    }

    /// Turns spatial tiling on for frames larger than a tile (diffusers' `enable_tiling`).
    pub fn enable_tiling(&mut self, tiling: TilingConfig) -> Result<()> {
        tiling.validate(self.config.spatial_compression_ratio())?;
        self.tiling = Some(tiling);
        Ok(())
    }

    /// Turns spatial tiling off (the default).
    pub fn disable_tiling(&mut self) {
        self.tiling = None;
    }

    /// The tiling in force, if any.
    pub fn tiling(&self) -> Option<&TilingConfig> {
        self.tiling.as_ref()
    }

    /// Latent frames for `frames` video frames: `1 + (frames − 1) / r` for 1 + r·k frames, r the
    /// [effective temporal compression](AutoencoderKLCogVideoXConfig::effective_temporal_compression_ratio).
    pub fn latent_frames(&self, frames: i64) -> i64 {
        let ratio = self.config.effective_temporal_compression_ratio();
        1 + (frames - 1) / ratio.max(1)
    }

    /// Posterior mean (unscaled; multiply by `scaling_factor` for the diffusion model) of a video
    /// `[B, in_channels, F, H, W]` in [−1, 1], exactly as diffusers'
    /// `vae.encode(x).latent_dist.mean`: temporal batches of 8 frames with the conv cache carried
    /// across, spatial tiles when tiling is enabled and the frame is larger than a tile.
    pub fn encode(&self, sample: &Tensor) -> Result<Tensor> {
        Ok(self.encode_posterior(sample)?.mean)
    }

    /// The full posterior (mean and log-variance) of [`Self::encode`]; training samples from it.
    pub fn encode_posterior(&self, sample: &Tensor) -> Result<DiagonalGaussian> {
        self.check_input(sample, "sample", self.config.in_channels, "in_channels")?;
        let [_, _, _, h, w] = dims5(sample, "sample")?;
        let moments = match &self.tiling {
            Some(t) if h > t.tile_sample_min_height || w > t.tile_sample_min_width => self.tiled_encode(sample, t)?,
            _ => self.encode_moments(sample, SAMPLE_FRAMES_BATCH_SIZE)?,
        };
        DiagonalGaussian::from_moments(&moments, self.config.latent_channels)
    }

    /// Posterior mean from one pass over all frames at once (no temporal batching, no tiling).
    /// Not what diffusers computes for more than 8 frames (GroupNorm statistics then span the whole
    /// clip); used to measure how far batched encoding is from it.
    pub fn encode_whole(&self, sample: &Tensor) -> Result<Tensor> {
        self.check_input(sample, "sample", self.config.in_channels, "in_channels")?;
        let frames = sample.size()[2];
        let moments = self.encode_moments(sample, frames.max(1) as usize)?;
        Ok(DiagonalGaussian::from_moments(&moments, self.config.latent_channels)?.mean)
    }

    /// A streaming encoder: feed frames in temporal batches, get each batch's latent moments.
    pub fn encoder_stream(&self) -> EncoderStream<'_> {
        EncoderStream { vae: self, cache: ConvCache::default() }
    }

    /// A streaming decoder: feed latent frames in batches, get each batch's frames.
    pub fn decoder_stream(&self) -> DecoderStream<'_> {
        DecoderStream { vae: self, cache: ConvCache::default() }
    }

    /// Video `[B, out_channels, F, H, W]` from an (unscaled) latent `[B, latent_channels, f, h, w]`,
    /// exactly as diffusers' `vae.decode(z).sample`: temporal batches of 2 latent frames (the
    /// first takes the odd one) with the conv cache carried across, tiles when tiling is enabled.
    pub fn decode(&self, latent: &Tensor) -> Result<Tensor> {
        self.check_input(latent, "latent", self.config.latent_channels, "latent_channels")?;
        let [_, _, _, h, w] = dims5(latent, "latent")?;
        let ratio = self.config.spatial_compression_ratio();
        match &self.tiling {
            Some(t) if h > t.tile_sample_min_height / ratio || w > t.tile_sample_min_width / ratio => {
                self.tiled_decode(latent, t)
            }
            _ => self.decode_batched(latent),
        }
    }

    fn check_input(&self, xs: &Tensor, name: &str, channels: i64, field: &str) -> Result<()> {
        let [_, c, f, h, w] = dims5(xs, name)?;
        if c != channels || f < 1 || h < 1 || w < 1 {
            return Err(Error::Shape {
                tensor: name.to_string(),
                expected: format!("[B, {channels} ({field}), F ≥ 1, H ≥ 1, W ≥ 1]"),
                actual: xs.size(),
            });
        }
        let (kind, device) = (self.weight_probe.kind(), self.weight_probe.device());
        if xs.kind() != kind || xs.device() != device {
            return Err(Error::DtypeDevice {
                tensor: name.to_string(),
                expected: format!("{kind:?} on {device:?} (the VAE's weights)"),
                actual: format!("{:?} on {:?}", xs.kind(), xs.device()),
            });
        }
        Ok(())
    }

    fn encode_moments(&self, sample: &Tensor, batch: usize) -> Result<Tensor> {
        let mut stream = self.encoder_stream();
        let parts = temporal_batches(sample.size()[2], batch)
            .into_iter()
            .map(|(start, len)| stream.push_moments(&sample.f_narrow(2, start, len)?))
            .collect::<Result<Vec<_>>>()?;
        Ok(Tensor::f_cat(&parts, 2)?)
    }

    fn decode_batched(&self, latent: &Tensor) -> Result<Tensor> {
        let mut stream = self.decoder_stream();
        let parts = temporal_batches(latent.size()[2], LATENT_FRAMES_BATCH_SIZE)
            .into_iter()
            .map(|(start, len)| stream.push(&latent.f_narrow(2, start, len)?))
            .collect::<Result<Vec<_>>>()?;
        Ok(Tensor::f_cat(&parts, 2)?)
    }

    fn tiled_encode(&self, sample: &Tensor, tiling: &TilingConfig) -> Result<Tensor> {
        let plan = TilePlan::new(tiling, self.config.spatial_compression_ratio());
        let [_, _, _, h, w] = dims5(sample, "sample")?;
        let tiles = map_tiles(h, w, plan.sample_stride_h, plan.sample_stride_w, |i, j| {
            let tile =
                sample.f_narrow(3, i, plan.sample_tile_h.min(h - i))?.f_narrow(4, j, plan.sample_tile_w.min(w - j))?;
            self.encode_moments(&tile, SAMPLE_FRAMES_BATCH_SIZE)
        })?;
        blend_tiles(
            tiles,
            plan.latent_blend_h,
            plan.latent_blend_w,
            plan.latent_tile_h - plan.latent_blend_h,
            plan.latent_tile_w - plan.latent_blend_w,
        )
    }

    fn tiled_decode(&self, latent: &Tensor, tiling: &TilingConfig) -> Result<Tensor> {
        let plan = TilePlan::new(tiling, self.config.spatial_compression_ratio());
        let [_, _, _, h, w] = dims5(latent, "latent")?;
        let tiles = map_tiles(h, w, plan.latent_stride_h, plan.latent_stride_w, |i, j| {
            let tile =
                latent.f_narrow(3, i, plan.latent_tile_h.min(h - i))?.f_narrow(4, j, plan.latent_tile_w.min(w - j))?;
            self.decode_batched(&tile)
        })?;
        blend_tiles(
            tiles,
            plan.sample_blend_h,
            plan.sample_blend_w,
            plan.sample_tile_h - plan.sample_blend_h,
            plan.sample_tile_w - plan.sample_blend_w,
        )
    }
}

/// Runs `f(row_start, col_start)` on a grid of tile origins `0, stride, 2·stride, … < size`.
fn map_tiles(
    h: i64,
    w: i64,
    stride_h: i64,
    stride_w: i64,
    mut f: impl FnMut(i64, i64) -> Result<Tensor>,
) -> Result<Vec<Vec<Tensor>>> {
    (0..h).step_by(stride_h as usize).map(|i| (0..w).step_by(stride_w as usize).map(|j| f(i, j)).collect()).collect()
}

/// Linear ramp across `extent` rows (dim 3) or columns (dim 4): `b[k] = a[−extent + k]·(1 − k/extent)
/// + b[k]·k/extent` for `k < extent` (diffusers' `blend_v` / `blend_h`).
fn blend(a: &Tensor, b: &Tensor, extent: i64, dim: i64) -> Result<Tensor> {
    let extent = extent.min(a.size()[dim as usize]).min(b.size()[dim as usize]);
    if extent <= 0 {
        return Ok(b.shallow_clone());
    }
    let mut shape = vec![1i64; 5];
    shape[dim as usize] = extent;
    let ramp: Vec<f64> = (0..extent).map(|k| k as f64 / extent as f64).collect();
    let weight_b = Tensor::from_slice(&ramp).f_to_kind(b.kind())?.f_to_device(b.device())?.f_reshape(&shape)?;
    let weight_a = Tensor::from_slice(&ramp.iter().map(|r| 1.0 - r).collect::<Vec<f64>>())
        .f_to_kind(b.kind())?
        .f_to_device(b.device())?
        .f_reshape(&shape)?;
    let a_len = a.size()[dim as usize];
    let b_len = b.size()[dim as usize];
    let a_tail = a.f_narrow(dim, a_len - extent, extent)?;
    let b_head = b.f_narrow(dim, 0, extent)?;
    let mixed = a_tail.f_mul(&weight_a)?.f_add(&b_head.f_mul(&weight_b)?)?;
    Ok(Tensor::f_cat(&[mixed, b.f_narrow(dim, extent, b_len - extent)?], dim)?)
}

/// Blends each tile with its (already blended) upper and left neighbours, crops every tile to
/// `keep_h × keep_w` and assembles the grid (diffusers' second loop of `tiled_encode`).
fn blend_tiles(rows: Vec<Vec<Tensor>>, extent_h: i64, extent_w: i64, keep_h: i64, keep_w: i64) -> Result<Tensor> {
    let mut blended: Vec<Vec<Tensor>> = Vec::with_capacity(rows.len());
    let mut out_rows = Vec::with_capacity(rows.len());
    for (i, row) in rows.into_iter().enumerate() {
        let mut blended_row: Vec<Tensor> = Vec::with_capacity(row.len());
        let mut cropped = Vec::with_capacity(row.len());
        for (j, tile) in row.into_iter().enumerate() {
            let mut tile = tile;
            if i > 0 {
                tile = blend(&blended[i - 1][j], &tile, extent_h, 3)?;
            }
            if j > 0 {
                tile = blend(&blended_row[j - 1], &tile, extent_w, 4)?;
            }
            let th = tile.size()[3].min(keep_h);
            let tw = tile.size()[4].min(keep_w);
            cropped.push(tile.f_narrow(3, 0, th)?.f_narrow(4, 0, tw)?);
            blended_row.push(tile);
        }
        out_rows.push(Tensor::f_cat(&cropped, 4)?);
        blended.push(blended_row);
    }
    Ok(Tensor::f_cat(&out_rows, 3)?)
}

/// Streaming, causal encoding (diffusers' `_encode` loop made incremental). Push temporal batches
/// in order; the first may hold `1 + 8k` frames, later ones should hold multiples of 4 frames so
/// the temporal downsampling pairs frames the way a whole-clip pass would.
#[derive(Debug)]
pub struct EncoderStream<'a> {
    vae: &'a AutoencoderKLCogVideoX,
    cache: ConvCache,
}

impl EncoderStream<'_> {
    /// Posterior mean of the next batch of frames `[B, C, n, H, W]`.
    pub fn push(&mut self, frames: &Tensor) -> Result<Tensor> {
        let moments = self.push_moments(frames)?;
        Ok(DiagonalGaussian::from_moments(&moments, self.vae.config.latent_channels)?.mean)
    }

    fn push_moments(&mut self, frames: &Tensor) -> Result<Tensor> {
        self.vae.check_input(frames, "sample", self.vae.config.in_channels, "in_channels")?;
        self.vae.encoder.forward(frames, &mut self.cache)
    }
}

/// Streaming, causal decoding (diffusers' `_decode` loop made incremental).
#[derive(Debug)]
pub struct DecoderStream<'a> {
    vae: &'a AutoencoderKLCogVideoX,
    cache: ConvCache,
}

impl DecoderStream<'_> {
    /// Frames of the next batch of latent frames `[B, latent_channels, n, h, w]`.
    pub fn push(&mut self, latent: &Tensor) -> Result<Tensor> {
        self.vae.check_input(latent, "latent", self.vae.config.latent_channels, "latent_channels")?;
        self.vae.decoder.forward(latent, &mut self.cache)
    }
}

/// A VAE on `device` in `kind` with its variables in a fresh VarStore (random init).
pub fn build(
    config: &AutoencoderKLCogVideoXConfig,
    device: Device,
    kind: Kind,
) -> Result<(nn::VarStore, AutoencoderKLCogVideoX)> {
    let mut vs = nn::VarStore::new(device);
    // New variables are created in `kind` (no fp32 copy of the whole model on the device first).
    vs.set_kind(kind);
    let vae = AutoencoderKLCogVideoX::new(&vs.root(), config)?;
    vs.set_kind(kind);
    Ok((vs, vae))
}

#[cfg(test)]
mod tests {
    #[test]
    fn default_tiles_land_on_latent_pixels_only_where_the_frame_allows() {
        let tiles = |h, w| {
            TilingConfig::for_config(&AutoencoderKLCogVideoXConfig {
                sample_height: h,
                sample_width: w,
                ..AutoencoderKLCogVideoXConfig::tiny()
            })
        };
        assert!(tiles(480, 720).lands_on_latent_pixels(8));
        assert!(tiles(96, 80).lands_on_latent_pixels(8));
        assert!(!tiles(64, 80).lands_on_latent_pixels(8));
    }

    use super::*;

    #[test]
    fn temporal_batches_match_diffusers_loop() {
        // 49 frames: 9 then five batches of 8 (diffusers' _encode with frame_batch_size 8).
        let b = temporal_batches(49, 8);
        assert_eq!(b[0], (0, 9));
        assert_eq!(b.len(), 6);
        assert_eq!(b[5], (41, 8));
        assert_eq!(temporal_batches(13, 2), vec![(0, 3), (3, 2), (5, 2), (7, 2), (9, 2), (11, 2)]);
        assert_eq!(temporal_batches(5, 8), vec![(0, 5)]);
        assert_eq!(temporal_batches(1, 2), vec![(0, 1)]);
    }

    #[test]
    fn causal_conv_streams_exactly() {
        let vs = nn::VarStore::new(Device::Cpu);
        let conv = CausalConv3d::new(&vs.root(), 3, 4, 3);
        let xs = Tensor::randn([1, 3, 11, 6, 5], (Kind::Float, Device::Cpu));
        let whole = conv.forward(&xs, &mut ConvCache::default()).unwrap();
        let mut cache = ConvCache::default();
        let mut parts = Vec::new();
        for (start, len) in [(0, 1), (1, 4), (5, 1), (6, 5)] {
            cache.rewind();
            parts.push(conv.forward(&xs.narrow(2, start, len), &mut cache).unwrap());
        }
        let streamed = Tensor::cat(&parts, 2);
        let err = (whole - streamed).abs().max().double_value(&[]);
        assert!(err < 1e-6, "streamed causal conv differs by {err}");
    }

    #[test]
    fn safe_conv_pieces_equal_one_pass() {
        let vs = nn::VarStore::new(Device::Cpu);
        let p = ConvParams::new(&vs.root(), 2, 2, &[3, 3, 3]);
        let xs = Tensor::randn([1, 2, 9, 4, 4], (Kind::Float, Device::Cpu));
        let one = xs.conv3d(&p.weight, Some(&p.bias), [1, 1, 1], [0, 1, 1], [1, 1, 1], 1);
        // A budget of a third of the input forces 4 temporal pieces, a tiny workspace 1 frame each.
        let pieces = conv3d_in_pieces(&xs, &p, [0, 1, 1], xs.numel() as i64 / 3, None).unwrap();
        let frames = conv3d_in_pieces(&xs, &p, [0, 1, 1], i64::MAX, Some(1)).unwrap();
        assert_eq!(frames.size(), one.size());
        let err = (&one - frames).abs().max().double_value(&[]);
        assert!(err < 1e-6, "{err}");
        assert_eq!(one.size(), pieces.size());
        let err = (one - pieces).abs().max().double_value(&[]);
        assert!(err < 1e-6, "{err}");
    }

    #[test]
    fn config_rejects_bad_fields_by_name() {
        let json = r#"{"block_out_channels": [16, 30], "down_block_types": ["CogVideoXDownBlock3D", "CogVideoXDownBlock3D"],
            "up_block_types": ["CogVideoXUpBlock3D", "CogVideoXUpBlock3D"], "norm_num_groups": 8, "temporal_compression_ratio": 2}"#;
        let err = AutoencoderKLCogVideoXConfig::from_json_str(json, "t.json").unwrap_err().to_string();
        assert!(err.contains("block_out_channels") && err.contains("t.json"), "{err}");
        let json = r#"{"_class_name": "AutoencoderKL"}"#;
        let err = AutoencoderKLCogVideoXConfig::from_json_str(json, "t.json").unwrap_err().to_string();
        assert!(err.contains("_class_name"), "{err}");
    }

    #[test]
    fn temporal_ratio_is_accepted_as_diffusers_accepts_it_with_a_warning() {
        let json = r#"{"block_out_channels": [16, 32], "down_block_types": ["CogVideoXDownBlock3D", "CogVideoXDownBlock3D"],
            "up_block_types": ["CogVideoXUpBlock3D", "CogVideoXUpBlock3D"], "norm_num_groups": 8, "temporal_compression_ratio": 4}"#;
        let c = AutoencoderKLCogVideoXConfig::from_json_str(json, "t.json").unwrap();
        assert_eq!(c.effective_temporal_compression_ratio(), 2);
        assert!(c.warnings()[0].contains("compresses time by 2"), "{:?}", c.warnings());
        // int(log2(r)) as diffusers truncates it; no warning when the ratio is what the levels give.
        for (ratio, effective, warns) in
            [(4.0, 4, false), (3.0, 2, true), (8.0, 8, false), (0.5, 1, true), (1.0, 1, false)]
        {
            let c = AutoencoderKLCogVideoXConfig {
                temporal_compression_ratio: ratio,
                ..AutoencoderKLCogVideoXConfig::tiny()
            };
            c.validate("t").unwrap();
            assert_eq!(c.effective_temporal_compression_ratio(), effective, "{ratio}");
            assert_eq!(!c.warnings().is_empty(), warns, "{ratio}");
        }
        for bad in [0.0, -4.0, f64::NAN, f64::INFINITY] {
            let c = AutoencoderKLCogVideoXConfig {
                temporal_compression_ratio: bad,
                ..AutoencoderKLCogVideoXConfig::tiny()
            };
            let err = c.validate("t.json").unwrap_err().to_string();
            assert!(err.contains("temporal_compression_ratio"), "{err}");
        }
    }

    #[test]
    fn config_keeps_unknown_keys() {
        let json = r#"{"_class_name": "AutoencoderKLCogVideoX", "_diffusers_version": "0.31.0", "scaling_factor": 0.7, "mystery": 1}"#;
        let c = AutoencoderKLCogVideoXConfig::from_json_str(json, "t.json").unwrap();
        assert_eq!(c.unknown_keys(), vec!["mystery"]);
        assert_eq!(c.scaling_factor, 0.7);
        assert_eq!(c.block_out_channels, vec![128, 256, 256, 512]);
    }

    #[test]
    fn bad_input_shape_is_a_named_error() {
        let (_vs, vae) = build(&AutoencoderKLCogVideoXConfig::tiny(), Device::Cpu, Kind::Float).unwrap();
        let err = vae.encode(&Tensor::zeros([1, 4, 1, 8, 8], (Kind::Float, Device::Cpu))).unwrap_err().to_string();
        assert!(err.contains("sample") && err.contains("in_channels"), "{err}");
        let err = vae.decode(&Tensor::zeros([16, 1, 2, 2], (Kind::Float, Device::Cpu))).unwrap_err().to_string();
        assert!(err.contains("latent"), "{err}");
        let err = vae.encode(&Tensor::zeros([1, 3, 1, 8, 8], (Kind::Double, Device::Cpu))).unwrap_err().to_string();
        assert!(err.contains("Double"), "{err}");
    }
}

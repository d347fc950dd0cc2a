//! The Wan video VAE: diffusers' `AutoencoderKLWan`
//! (`diffusers/models/autoencoders/autoencoder_kl_wan.py`), weight-compatible with Wan2.1's VAE
//! (16 latent channels, 8× spatial and 4× temporal compression) and Wan2.2's (`is_residual`: down
//! and up blocks with parameter-free averaging / duplicating shortcuts, and `patch_size` 2: the
//! frame is cut into 2 × 2 patches on channels first, 48 latent channels, 16× spatial).
//!
//! Every temporal convolution is causal, and diffusers runs the encoder on chunks of 1, 4, 4, …
//! frames and the decoder on one latent frame at a time, each causal convolution keeping the last
//! [`CACHE_T`] frames of its input for the next chunk ([`FeatCache`], diffusers' `feat_cache`).
//! The chunking is not only a memory device: the temporal down- and upsamplers treat the first
//! chunk specially (the first frame passes through without the temporal convolution), so the
//! same chunks are run here. Norms are RMS norms over channels (`WanRMS_norm`), the mid blocks
//! have single-head attention within each frame. Spatial tiling is not ported.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use tch::{Device, Kind, Tensor, nn};

use crate::diffusers_config::{self, DiffusersConfig};
use crate::error::{Error, Result};
use crate::models::cogvideox::autoencoder_kl_cogvideox::DiagonalGaussian;
use crate::models::vars::{ParamInit, Vars};

/// The class name diffusers writes into the VAE's `config.json` (`_class_name`).
pub const CLASS_NAME: &str = "AutoencoderKLWan";
/// Input frames a causal convolution keeps for the next chunk (diffusers' `CACHE_T`: the time
/// kernel is 3, so two frames of left context).
pub const CACHE_T: i64 = 2;
/// Pixel frames per encoder chunk after the first frame (diffusers' `_encode` slices
/// `1 + 4·(i − 1) : 1 + 4·i`).
pub const ENCODE_CHUNK_FRAMES: i64 = 4;
/// Epsilon of `F.normalize` (PyTorch's default), which `WanRMS_norm` divides by at the least.
const NORMALIZE_EPS: f64 = 1e-12;
/// Largest channel count or multiplier accepted (far above the released 96–256 base widths).
const MAX_DIMENSION: i64 = 1 << 16;

// ------------------------------------------------------------------------------------------------
// Configuration
// ------------------------------------------------------------------------------------------------

/// The VAE's `config.json` as diffusers writes it, field names verbatim (`temperal_downsample` is
/// upstream's spelling). Missing fields take diffusers' `__init__` defaults (= Wan2.1's VAE).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct AutoencoderKLWanConfig {
    /// Channels of the encoder's first level.
    pub base_dim: i64,
    /// Channels of the decoder's last level (defaults to `base_dim` when null).
    pub decoder_base_dim: Option<i64>,
    /// Latent channels.
    pub z_dim: i64,
    /// Channel multiplier per level.
    pub dim_mult: Vec<i64>,
    /// Residual blocks per encoder level (the decoder has one more).
    pub num_res_blocks: i64,
    /// Encoder scales (1, 1/2, …) with an attention block after each residual block; must be
    /// empty (diffusers' encoder passes its cache to those blocks, which take none, and fails).
    pub attn_scales: Vec<f64>,
    /// Which of the first `len(dim_mult) − 1` levels also halve time (the decoder mirrors it).
    pub temperal_downsample: Vec<bool>,
    /// Dropout (training only; not applied here).
    pub dropout: f64,
    /// Per-channel latent mean (the pipelines normalise latents with it).
    pub latents_mean: Vec<f64>,
    /// Per-channel latent standard deviation.
    pub latents_std: Vec<f64>,
    /// Wan2.2's residual down/up blocks.
    pub is_residual: bool,
    /// Video channels in (after patchifying: × patch_size²).
    pub in_channels: i64,
    /// Video channels out (before unpatchifying).
    pub out_channels: i64,
    /// Spatial patch size folded into channels before encoding (Wan2.2: 2); null for none.
    pub patch_size: Option<i64>,
    /// Kept for the pipelines (frames per latent frame).
    pub scale_factor_temporal: Option<i64>,
    /// Kept for the pipelines (pixels per latent pixel).
    pub scale_factor_spatial: Option<i64>,
    /// Every other key: `_class_name`, `_diffusers_version`, … and unknown keys.
    #[serde(flatten)]
    pub extra: BTreeMap<String, serde_json::Value>,
}

impl Default for AutoencoderKLWanConfig {
    /// diffusers' `AutoencoderKLWan.__init__` defaults (`Wan-AI/Wan2.1-*-Diffusers`, `vae/`).
    fn default() -> Self {
        Self {
            base_dim: 96,
            decoder_base_dim: None,
            z_dim: 16,
            dim_mult: vec![1, 2, 4, 4],
            num_res_blocks: 2,
            attn_scales: Vec::new(),
            temperal_downsample: vec![false, true, true],
            dropout: 0.0,
            latents_mean: vec![
                -0.7571, -0.7089, -0.9113, 0.1075, -0.1745, 0.9653, -0.1517, 1.5508, 0.4134, -0.0715, 0.5517, -0.3632,
                -0.1922, -0.9497, 0.2503, -0.2921,
            ],
            latents_std: vec![
                2.8184, 1.4541, 2.3275, 2.6558, 1.2196, 1.7708, 2.6052, 2.0743, 3.2687, 2.1526, 2.8652, 1.5579, 1.6382,
                1.1253, 2.8251, 1.9160,
            ],
            is_residual: false,
            in_channels: 3,
            out_channels: 3,
            patch_size: None,
            scale_factor_temporal: Some(4),
            scale_factor_spatial: Some(8),
            extra: BTreeMap::new(),
        }
    }
}

impl DiffusersConfig for AutoencoderKLWanConfig {
    const KIND: &'static str = "VAE";
    const CLASS_NAMES: &'static [&'static str] = &[CLASS_NAME];
    const FILE_NAME: &'static str = "config.json";

    fn validate_fields(&self, source_name: &str) -> Result<()> {
        let err = diffusers_config::field_error(source_name);
        let mult_max = self.dim_mult.iter().copied().max().unwrap_or(1);
        let sizes = [
            ("base_dim", self.base_dim),
            ("decoder_base_dim", self.decoder_base_dim.unwrap_or(1)),
            ("z_dim", self.z_dim),
            ("num_res_blocks", self.num_res_blocks),
            ("in_channels", self.in_channels),
            ("out_channels", self.out_channels),
            ("patch_size", self.patch_size.unwrap_or(1)),
            ("dim_mult", self.dim_mult.iter().copied().min().unwrap_or(0)),
        ];
        diffusers_config::require_positive(source_name, &sizes)?;
        for (field, value) in sizes.into_iter().chain([("dim_mult", mult_max)]) {
            if value > MAX_DIMENSION {
                return Err(err(field, format!("must be at most {MAX_DIMENSION}, got {value}")));
            }
        }
        if self.temperal_downsample.len() + 1 != self.dim_mult.len() {
            return Err(err(
                "temperal_downsample",
                format!(
                    "has {} entries; one per level but the last ({} for dim_mult of {})",
                    self.temperal_downsample.len(),
                    self.dim_mult.len() - 1,
                    self.dim_mult.len()
                ),
            ));
        }
        for (field, values) in [("latents_mean", &self.latents_mean), ("latents_std", &self.latents_std)] {
            if values.len() as i64 != self.z_dim {
                return Err(err(field, format!("has {} values, expected z_dim = {}", values.len(), self.z_dim)));
            }
        }
        if !(0.0..1.0).contains(&self.dropout) {
            return Err(err("dropout", format!("must be in [0, 1), got {}", self.dropout)));
        }
        if !self.attn_scales.is_empty() {
            return Err(err(
                "attn_scales",
                format!(
                    "{:?} is not supported: diffusers' WanEncoder3d cannot run attention blocks in its down \
                     blocks (it passes them a cache they do not take); every released Wan VAE has none",
                    self.attn_scales
                ),
            ));
        }
        if self.is_residual {
            // AvgDown3D groups in·factor channels into out channels, DupUp3D the reverse.
            let levels = self.dim_mult.len();
            let (enc, dec) = (self.encoder_dims(), self.decoder_dims());
            let upsample: Vec<bool> = self.temperal_downsample.iter().rev().copied().collect();
            for i in 0..levels {
                let resampled = i != levels - 1;
                let factor = |temporal: &[bool]| match (resampled, resampled && temporal[i]) {
                    (false, _) => 1,
                    (true, false) => 4,
                    (true, true) => 8,
                };
                let (down, up) = (factor(&self.temperal_downsample), factor(&upsample));
                if enc[i] * down % enc[i + 1] != 0 {
                    return Err(err(
                        "dim_mult",
                        format!("encoder level {i}: {} channels × {down} are not a multiple of {}", enc[i], enc[i + 1]),
                    ));
                }
                if resampled && dec[i + 1] * up % dec[i] != 0 {
                    return Err(err(
                        "dim_mult",
                        format!("decoder level {i}: {} channels × {up} are not a multiple of {}", dec[i + 1], dec[i]),
                    ));
                }
            }
        }
        Ok(())
    }

    fn extra(&self) -> &BTreeMap<String, serde_json::Value> {
        &self.extra
    }
}

impl AutoencoderKLWanConfig {
    /// Wan2.1's VAE (`Wan-AI/Wan2.1-T2V-1.3B-Diffusers`, `vae/config.json`) = diffusers' defaults.
    pub fn wan21() -> Self {
        Self::default()
    }

    /// Wan2.2's VAE (`Wan-AI/Wan2.2-TI2V-5B-Diffusers`, `vae/config.json`): residual blocks, 2 × 2
    /// patches folded into 12 input channels, 160 encoder and 256 decoder base channels, 48 latent
    /// channels (16× spatial, 4× temporal). The latent statistics are placeholders (0 and 1): only
    /// the structure is used (memory plans, random-weight checks), never to normalise latents.
    pub fn wan22() -> Self {
        Self {
            base_dim: 160,
            decoder_base_dim: Some(256),
            z_dim: 48,
            latents_mean: vec![0.0; 48],
            latents_std: vec![1.0; 48],
            is_residual: true,
            in_channels: 12,
            out_channels: 12,
            patch_size: Some(2),
            scale_factor_spatial: Some(16),
            ..Self::default()
        }
    }

    /// A preset by name: `wan2.1` (the VAE of every Wan2.1 model and of Wan2.2 A14B), `wan2.2`
    /// (Wan2.2 TI2V-5B's), `tiny`, `tiny-residual`.
    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "wan2.1" => Ok(Self::wan21()),
            "wan2.2" => Ok(Self::wan22()),
            "tiny" => Ok(Self::tiny()),
            "tiny-residual" => Ok(Self::tiny_residual()),
            other => Err(Error::InvalidConfig {
                source_name: "preset".to_string(),
                field: "name".to_string(),
                reason: format!("unknown Wan VAE preset `{other}`; expected wan2.1, wan2.2, tiny or tiny-residual"),
            }),
        }
    }

    /// Pixels per latent pixel: the patch size times `2^(levels − 1)` (Wan2.1: 8, Wan2.2: 16).
    pub fn spatial_compression_ratio(&self) -> i64 {
        self.patch_size.unwrap_or(1) << self.dim_mult.len().saturating_sub(1)
    }

    /// Frames per latent frame after the first: 2 per level that halves time (4).
    pub fn temporal_compression_ratio(&self) -> i64 {
        1 << self.temperal_downsample.iter().filter(|&&t| t).count()
    }

    /// Wan2.1's structure at small widths for tests: 3 levels of 8, 16, 16 channels (4×
    /// spatial, 4× temporal), one residual block, 4 latent channels.
    pub fn tiny() -> Self {
        Self {
            base_dim: 8,
            z_dim: 4,
            dim_mult: vec![1, 2, 2],
            num_res_blocks: 1,
            temperal_downsample: vec![true, true],
            latents_mean: vec![0.1, -0.2, 0.3, 0.0],
            latents_std: vec![1.5, 0.8, 1.1, 2.0],
            scale_factor_spatial: Some(4),
            ..Self::default()
        }
    }

    /// Wan2.2's residual, patchified structure at small widths: [`tiny`](Self::tiny) with
    /// residual blocks, a decoder of its own width, `patch_size` 2 (12 channels in and out).
    pub fn tiny_residual() -> Self {
        Self {
            decoder_base_dim: Some(16),
            z_dim: 6,
            latents_mean: vec![0.0; 6],
            latents_std: vec![1.0; 6],
            is_residual: true,
            in_channels: 12,
            out_channels: 12,
            patch_size: Some(2),
            scale_factor_spatial: Some(8),
            ..Self::tiny()
        }
    }

    /// Encoder channels per level: `base_dim × [1, dim_mult…]`.
    fn encoder_dims(&self) -> Vec<i64> {
        std::iter::once(1).chain(self.dim_mult.iter().copied()).map(|m| self.base_dim * m).collect()
    }

    /// Decoder channels per level: `decoder_base_dim × [dim_mult[-1], dim_mult reversed…]`.
    fn decoder_dims(&self) -> Vec<i64> {
        let base = self.decoder_base_dim.unwrap_or(self.base_dim);
        let last = *self.dim_mult.last().expect("validated: non-empty");
        std::iter::once(last).chain(self.dim_mult.iter().rev().copied()).map(|m| base * m).collect()
    }
}

// ------------------------------------------------------------------------------------------------
// Layers
// ------------------------------------------------------------------------------------------------

/// A convolution's weight and bias (`{path}.weight`, `{path}.bias`), PyTorch's default init.
#[derive(Debug)]
struct Conv {
    weight: Tensor,
    bias: Tensor,
}

impl Conv {
    fn new(vars: &Vars, out_channels: i64, in_channels: i64, kernel: &[i64]) -> Result<Self> {
        let fan_in = in_channels * kernel.iter().product::<i64>();
        let mut dims = vec![out_channels, in_channels];
        dims.extend_from_slice(kernel);
        Ok(Self {
            weight: vars.param("weight", &dims, ParamInit::FanInUniform(fan_in))?,
            bias: vars.param("bias", &[out_channels], ParamInit::FanInUniform(fan_in))?,
        })
    }

    /// `nn.Conv2d` with symmetric `padding`.
    fn conv2d(&self, xs: &Tensor, stride: i64, padding: i64) -> Result<Tensor> {
        Ok(xs.f_conv2d(&self.weight, Some(&self.bias), [stride, stride], [padding, padding], [1, 1], 1)?)
    }
}

/// diffusers' `WanCausalConv3d`: spatial zero padding on both sides, temporal padding of twice the
/// nominal padding on the left only, of which the frames of the previous chunk replace as many.
#[derive(Debug)]
struct CausalConv3d {
    conv: Conv,
    stride: [i64; 3],
    /// Nominal padding (t, h, w).
    padding: [i64; 3],
}

impl CausalConv3d {
    fn new(
        vars: &Vars,
        in_channels: i64,
        out_channels: i64,
        kernel: [i64; 3],
        stride: [i64; 3],
        padding: [i64; 3],
    ) -> Result<Self> {
        Ok(Self { conv: Conv::new(vars, out_channels, in_channels, &kernel)?, stride, padding })
    }

    /// A cubic kernel `k` with padding `k / 2` (the 3 × 3 × 3 convolutions) or 1 × 1 × 1 without.
    fn cube(vars: &Vars, in_channels: i64, out_channels: i64, k: i64) -> Result<Self> {
        Self::new(vars, in_channels, out_channels, [k; 3], [1; 3], [k / 2; 3])
    }

    fn forward(&self, xs: &Tensor, cache: Option<&Tensor>) -> Result<Tensor> {
        let [pt, ph, pw] = self.padding;
        let mut time_pad = 2 * pt;
        let xs = match cache {
            Some(cache) if time_pad > 0 => {
                time_pad -= cache.size()[2];
                Tensor::f_cat(&[cache, xs], 2)?
            }
            _ => xs.shallow_clone(),
        };
        let padded = xs.f_constant_pad_nd([pw, pw, ph, ph, time_pad, 0])?;
        Ok(padded.f_conv3d(&self.conv.weight, Some(&self.conv.bias), self.stride, [0, 0, 0], [1, 1, 1], 1)?)
    }
}

/// One slot of [`FeatCache`].
#[derive(Debug)]
enum Slot {
    /// Nothing seen yet (the first chunk).
    Empty,
    /// The temporal upsampler's marker after the first chunk: the chunk passed through, and its
    /// frames are not used as context (diffusers' `"Rep"`).
    Rep,
    /// The last frames of the previous chunk's input.
    Frames(Tensor),
}

/// diffusers' `feat_cache` / `feat_idx`: per causal convolution, in call order, what it keeps of
/// the previous chunk. `cursor` restarts at 0 for every chunk.
#[derive(Debug, Default)]
pub struct FeatCache {
    slots: Vec<Slot>,
    cursor: usize,
}

impl FeatCache {
    /// The next slot (created empty on the first chunk).
    fn next(&mut self) -> usize {
        if self.cursor == self.slots.len() {
            self.slots.push(Slot::Empty);
        }
        self.cursor += 1;
        self.cursor - 1
    }

    /// The last [`CACHE_T`] frames of `xs`, with the previous chunk's last frame in front when
    /// the chunk is shorter than that.
    fn keep(xs: &Tensor, previous: &Slot) -> Result<Tensor> {
        let frames = xs.size()[2];
        let kept = xs.f_narrow(2, (frames - CACHE_T).max(0), frames.min(CACHE_T))?.copy();
        match previous {
            Slot::Frames(prev) if kept.size()[2] < CACHE_T => {
                let last = prev.f_narrow(2, prev.size()[2] - 1, 1)?;
                Ok(Tensor::f_cat(&[&last, &kept], 2)?)
            }
            _ => Ok(kept),
        }
    }

    /// `conv(xs)` with the previous chunk's frames as left context; stores this chunk's.
    fn causal(&mut self, conv: &CausalConv3d, xs: &Tensor) -> Result<Tensor> {
        let slot = self.next();
        let kept = Self::keep(xs, &self.slots[slot])?;
        let context = match &self.slots[slot] {
            Slot::Frames(prev) => Some(prev),
            _ => None,
        };
        let out = conv.forward(xs, context)?;
        self.slots[slot] = Slot::Frames(kept);
        Ok(out)
    }
}

/// diffusers' `WanRMS_norm`: `normalize(x, dim=1) · √C · γ` (in fp32 for reduced precision).
#[derive(Debug)]
struct RmsNorm {
    gamma: Tensor,
    scale: f64,
}

impl RmsNorm {
    /// `images`: γ is `[C, 1, 1]` (per-frame 2D input) instead of `[C, 1, 1, 1]`.
    fn new(vars: &Vars, dim: i64, images: bool) -> Result<Self> {
        let shape: Vec<i64> = if images { vec![dim, 1, 1] } else { vec![dim, 1, 1, 1] };
        Ok(Self { gamma: vars.param("gamma", &shape, ParamInit::Const(1.0))?, scale: (dim as f64).sqrt() })
    }

    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let kind = xs.kind();
        let x =
            if kind == Kind::Float || kind == Kind::Double { xs.shallow_clone() } else { xs.f_to_kind(Kind::Float)? };
        let norm = x.f_norm_scalaropt_dim(2.0, [1i64].as_slice(), true)?.f_clamp_min(NORMALIZE_EPS)?;
        let normalized = x.f_div(&norm)?.f_to_kind(kind)?;
        Ok(normalized.f_mul_scalar(self.scale)?.f_mul(&self.gamma)?)
    }
}

/// diffusers' `WanResidualBlock`: RMS norm, SiLU, causal 3³ conv, twice, plus a 1³ shortcut when
/// the width changes.
#[derive(Debug)]
struct ResidualBlock {
    norm1: RmsNorm,
    conv1: CausalConv3d,
    norm2: RmsNorm,
    conv2: CausalConv3d,
    conv_shortcut: Option<CausalConv3d>,
}

impl ResidualBlock {
    fn new(vars: &Vars, in_dim: i64, out_dim: i64) -> Result<Self> {
        Ok(Self {
            norm1: RmsNorm::new(&vars.sub("norm1"), in_dim, false)?,
            conv1: CausalConv3d::cube(&vars.sub("conv1"), in_dim, out_dim, 3)?,
            norm2: RmsNorm::new(&vars.sub("norm2"), out_dim, false)?,
            conv2: CausalConv3d::cube(&vars.sub("conv2"), out_dim, out_dim, 3)?,
            conv_shortcut: if in_dim != out_dim {
                Some(CausalConv3d::cube(&vars.sub("conv_shortcut"), in_dim, out_dim, 1)?)
            } else {
                None
            },
        })
    }

    fn forward(&self, xs: &Tensor, cache: &mut FeatCache) -> Result<Tensor> {
        let shortcut = match &self.conv_shortcut {
            Some(conv) => conv.forward(xs, None)?,
            None => xs.shallow_clone(),
        };
        let h = cache.causal(&self.conv1, &self.norm1.forward(xs)?.f_silu()?)?;
        let h = cache.causal(&self.conv2, &self.norm2.forward(&h)?.f_silu()?)?;
        Ok(h.f_add(&shortcut)?)
    }
}

/// diffusers' `WanAttentionBlock`: single-head self-attention over the pixels of each frame.
#[derive(Debug)]
struct AttentionBlock {
    norm: RmsNorm,
    to_qkv: Conv,
    proj: Conv,
}

impl AttentionBlock {
    fn new(vars: &Vars, dim: i64) -> Result<Self> {
        Ok(Self {
            norm: RmsNorm::new(&vars.sub("norm"), dim, true)?,
            to_qkv: Conv::new(&vars.sub("to_qkv"), 3 * dim, dim, &[1, 1])?,
            proj: Conv::new(&vars.sub("proj"), dim, dim, &[1, 1])?,
        })
    }

    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let [b, c, t, h, w] = dims5(xs)?;
        let frames = per_frame(xs)?;
        let qkv = self.to_qkv.conv2d(&self.norm.forward(&frames)?, 1, 0)?;
        let qkv = qkv.f_reshape([b * t, 1, 3 * c, h * w])?.f_permute([0, 1, 3, 2])?.f_contiguous()?;
        let parts = qkv.f_chunk(3, -1)?;
        let out = Tensor::f_scaled_dot_product_attention::<Tensor>(
            &parts[0], &parts[1], &parts[2], None, 0.0, false, None, false,
        )?;
        let out = out.f_squeeze_dim(1)?.f_permute([0, 2, 1])?.f_reshape([b * t, c, h, w])?;
        let out = self.proj.conv2d(&out, 1, 0)?;
        Ok(from_frames(&out, b, t)?.f_add(xs)?)
    }
}

/// `[B, C, T, H, W]` → `[B·T, C, H, W]`.
fn per_frame(xs: &Tensor) -> Result<Tensor> {
    let [b, c, t, h, w] = dims5(xs)?;
    Ok(xs.f_permute([0, 2, 1, 3, 4])?.f_reshape([b * t, c, h, w])?)
}

/// `[B·T, C, H, W]` → `[B, C, T, H, W]`.
fn from_frames(xs: &Tensor, b: i64, t: i64) -> Result<Tensor> {
    let s = xs.size();
    Ok(xs.f_view([b, t, s[1], s[2], s[3]])?.f_permute([0, 2, 1, 3, 4])?)
}

fn dims5(xs: &Tensor) -> Result<[i64; 5]> {
    xs.size().try_into().map_err(|size| Error::Shape {
        tensor: "(VAE activation)".to_string(),
        expected: "[B, C, T, H, W]".to_string(),
        actual: size,
    })
}

/// diffusers' `WanResample` modes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ResampleMode {
    Upsample2d,
    Upsample3d,
    Downsample2d,
    Downsample3d,
}

/// diffusers' `WanResample`: 2× nearest upsampling and a 3² conv, or a right/bottom zero pad and a
/// stride-2 3² conv, per frame; the 3D modes add a causal temporal conv (upsampling: to twice the
/// channels, interleaved into twice the frames; downsampling: stride 2).
#[derive(Debug)]
struct Resample {
    mode: ResampleMode,
    resample: Conv,
    time_conv: Option<CausalConv3d>,
}

impl Resample {
    fn new(vars: &Vars, dim: i64, mode: ResampleMode, upsample_out_dim: i64) -> Result<Self> {
        let out = match mode {
            ResampleMode::Upsample2d | ResampleMode::Upsample3d => upsample_out_dim,
            ResampleMode::Downsample2d | ResampleMode::Downsample3d => dim,
        };
        let time_conv = match mode {
            ResampleMode::Upsample3d => {
                Some(CausalConv3d::new(&vars.sub("time_conv"), dim, 2 * dim, [3, 1, 1], [1, 1, 1], [1, 0, 0])?)
            }
            ResampleMode::Downsample3d => {
                Some(CausalConv3d::new(&vars.sub("time_conv"), dim, dim, [3, 1, 1], [2, 1, 1], [0, 0, 0])?)
            }
            _ => None,
        };
        Ok(Self { mode, resample: Conv::new(&vars.sub("resample").sub(1), out, dim, &[3, 3])?, time_conv })
    }

    fn forward(&self, xs: &Tensor, cache: &mut FeatCache) -> Result<Tensor> {
        let [b, c, t, h, w] = dims5(xs)?;
        let mut xs = xs.shallow_clone();
        if let (ResampleMode::Upsample3d, Some(time_conv)) = (self.mode, &self.time_conv) {
            let slot = cache.next();
            if matches!(cache.slots[slot], Slot::Empty) {
                cache.slots[slot] = Slot::Rep;
            } else {
                let mut kept = FeatCache::keep(&xs, &cache.slots[slot])?;
                if matches!(cache.slots[slot], Slot::Rep) && kept.size()[2] < CACHE_T {
                    kept = Tensor::f_cat(&[&kept.f_zeros_like()?, &kept], 2)?;
                }
                let out = match &cache.slots[slot] {
                    Slot::Frames(prev) => time_conv.forward(&xs, Some(prev))?,
                    _ => time_conv.forward(&xs, None)?,
                };
                cache.slots[slot] = Slot::Frames(kept);
                // [B, 2C, T] → [B, C, 2T]: the two halves of the channels are frames 2t and 2t + 1.
                xs =
                    out.f_reshape([b, 2, c, t, h, w])?.f_permute([0, 2, 3, 1, 4, 5])?.f_reshape([b, c, 2 * t, h, w])?;
            }
        }
        let t = xs.size()[2];
        let frames = per_frame(&xs)?;
        let frames = match self.mode {
            ResampleMode::Upsample2d | ResampleMode::Upsample3d => {
                // nearest-exact at scale 2 repeats every pixel; computed in fp32 like WanUpsample.
                let kind = frames.kind();
                let up = frames
                    .f_to_kind(Kind::Float)?
                    .f_repeat_interleave_self_int(2, 2, None)?
                    .f_repeat_interleave_self_int(2, 3, None)?
                    .f_to_kind(kind)?;
                self.resample.conv2d(&up, 1, 1)?
            }
            ResampleMode::Downsample2d | ResampleMode::Downsample3d => {
                self.resample.conv2d(&frames.f_constant_pad_nd([0, 1, 0, 1])?, 2, 0)?
            }
        };
        let mut xs = from_frames(&frames, b, t)?;
        if let (ResampleMode::Downsample3d, Some(time_conv)) = (self.mode, &self.time_conv) {
            let slot = cache.next();
            let frames = xs.size()[2];
            match &cache.slots[slot] {
                Slot::Frames(prev) => {
                    let kept = xs.f_narrow(2, frames - 1, 1)?.copy();
                    let last = prev.f_narrow(2, prev.size()[2] - 1, 1)?;
                    xs = time_conv.forward(&Tensor::f_cat(&[&last, &xs], 2)?, None)?;
                    cache.slots[slot] = Slot::Frames(kept);
                }
                _ => cache.slots[slot] = Slot::Frames(xs.copy()),
            }
        }
        Ok(xs)
    }
}

/// diffusers' `AvgDown3D`: a parameter-free shortcut that folds `factor_t × factor_s²` neighbours
/// into channels and averages groups of them down to `out_channels` (time zero-padded in front to
/// a multiple of `factor_t`).
fn avg_down(xs: &Tensor, out_channels: i64, factor_t: i64, factor_s: i64) -> Result<Tensor> {
    let pad_t = (factor_t - xs.size()[2] % factor_t) % factor_t;
    let xs = xs.f_constant_pad_nd([0, 0, 0, 0, pad_t, 0])?;
    let [b, c, t, h, w] = dims5(&xs)?;
    let factor = factor_t * factor_s * factor_s;
    let (t, h, w) = (t / factor_t, h / factor_s, w / factor_s);
    Ok(xs
        .f_view([b, c, t, factor_t, h, factor_s, w, factor_s].as_slice())?
        .f_permute([0, 1, 3, 5, 7, 2, 4, 6])?
        .f_contiguous()?
        .f_view([b, out_channels, c * factor / out_channels, t, h, w])?
        .f_mean_dim(2, false, None)?)
}

/// diffusers' `DupUp3D`: the parameter-free inverse of [`avg_down`]: channels repeated and
/// unfolded into `factor_t × factor_s²` neighbours; the first chunk drops its first
/// `factor_t − 1` frames (the causal first frame is not doubled).
fn dup_up(xs: &Tensor, out_channels: i64, factor_t: i64, factor_s: i64, first_chunk: bool) -> Result<Tensor> {
    let [b, c, t, h, w] = dims5(xs)?;
    let repeats = out_channels * factor_t * factor_s * factor_s / c;
    let out = xs
        .f_repeat_interleave_self_int(repeats, 1, None)?
        .f_view([b, out_channels, factor_t, factor_s, factor_s, t, h, w].as_slice())?
        .f_permute([0, 1, 5, 2, 6, 3, 7, 4])?
        .f_contiguous()?
        .f_view([b, out_channels, t * factor_t, h * factor_s, w * factor_s])?;
    if first_chunk && factor_t > 1 {
        return Ok(out.f_narrow(2, factor_t - 1, t * factor_t - (factor_t - 1))?);
    }
    Ok(out)
}

/// diffusers' `WanMidBlock` with one attention layer: resnet, attention, resnet.
#[derive(Debug)]
struct MidBlock {
    resnets: [ResidualBlock; 2],
    attention: AttentionBlock,
}

impl MidBlock {
    fn new(vars: &Vars, dim: i64) -> Result<Self> {
        let resnets = vars.sub("resnets");
        Ok(Self {
            resnets: [ResidualBlock::new(&resnets.sub(0), dim, dim)?, ResidualBlock::new(&resnets.sub(1), dim, dim)?],
            attention: AttentionBlock::new(&vars.sub("attentions").sub(0), dim)?,
        })
    }

    fn forward(&self, xs: &Tensor, cache: &mut FeatCache) -> Result<Tensor> {
        let xs = self.resnets[0].forward(xs, cache)?;
        let xs = self.attention.forward(&xs)?;
        self.resnets[1].forward(&xs, cache)
    }
}

/// One entry of the Wan2.1 encoder's flat `down_blocks` list (no attention blocks: see
/// [`AutoencoderKLWanConfig::attn_scales`]).
#[derive(Debug)]
enum DownLayer {
    Residual(ResidualBlock),
    Resample(Resample),
}

/// diffusers' `WanResidualDownBlock` (Wan2.2): residual blocks and a downsampler, plus the
/// [`avg_down`] of the block's input.
#[derive(Debug)]
struct ResidualDownBlock {
    resnets: Vec<ResidualBlock>,
    downsampler: Option<Resample>,
    out_dim: i64,
    factor_t: i64,
    factor_s: i64,
}

/// The encoder's levels, Wan2.1's or Wan2.2's.
#[derive(Debug)]
enum DownBlocks {
    Plain(Vec<DownLayer>),
    Residual(Vec<ResidualDownBlock>),
}

/// diffusers' `WanEncoder3d`.
#[derive(Debug)]
struct Encoder {
    conv_in: CausalConv3d,
    down_blocks: DownBlocks,
    mid_block: MidBlock,
    norm_out: RmsNorm,
    conv_out: CausalConv3d,
}

impl Encoder {
    fn new(vars: &Vars, c: &AutoencoderKLWanConfig) -> Result<Self> {
        let dims = c.encoder_dims();
        let levels = c.dim_mult.len();
        let blocks = vars.sub("down_blocks");
        let mode =
            |i: usize| if c.temperal_downsample[i] { ResampleMode::Downsample3d } else { ResampleMode::Downsample2d };
        let down_blocks = if c.is_residual {
            let mut out = Vec::new();
            for i in 0..levels {
                let block = blocks.sub(i);
                let (mut in_dim, out_dim) = (dims[i], dims[i + 1]);
                let mut resnets = Vec::new();
                for j in 0..c.num_res_blocks {
                    resnets.push(ResidualBlock::new(&block.sub("resnets").sub(j), in_dim, out_dim)?);
                    in_dim = out_dim;
                }
                let down = i != levels - 1;
                let temporal = down && c.temperal_downsample[i];
                out.push(ResidualDownBlock {
                    resnets,
                    downsampler: if down {
                        Some(Resample::new(&block.sub("downsampler"), out_dim, mode(i), out_dim)?)
                    } else {
                        None
                    },
                    out_dim,
                    factor_t: if temporal { 2 } else { 1 },
                    factor_s: if down { 2 } else { 1 },
                });
            }
            DownBlocks::Residual(out)
        } else {
            let mut layers = Vec::new();
            for i in 0..levels {
                let (mut in_dim, out_dim) = (dims[i], dims[i + 1]);
                for _ in 0..c.num_res_blocks {
                    layers.push(DownLayer::Residual(ResidualBlock::new(&blocks.sub(layers.len()), in_dim, out_dim)?));
                    in_dim = out_dim;
                }
                if i != levels - 1 {
                    layers.push(DownLayer::Resample(Resample::new(
                        &blocks.sub(layers.len()),
                        out_dim,
                        mode(i),
                        out_dim,
                    )?));
                }
            }
            DownBlocks::Plain(layers)
        };
        let top = dims[levels];
        Ok(Self {
            conv_in: CausalConv3d::cube(&vars.sub("conv_in"), c.in_channels, dims[0], 3)?,
            down_blocks,
            mid_block: MidBlock::new(&vars.sub("mid_block"), top)?,
            norm_out: RmsNorm::new(&vars.sub("norm_out"), top, false)?,
            conv_out: CausalConv3d::cube(&vars.sub("conv_out"), top, 2 * c.z_dim, 3)?,
        })
    }

    fn forward(&self, xs: &Tensor, cache: &mut FeatCache) -> Result<Tensor> {
        let mut xs = cache.causal(&self.conv_in, xs)?;
        match &self.down_blocks {
            DownBlocks::Plain(layers) => {
                for layer in layers {
                    xs = match layer {
                        DownLayer::Residual(block) => block.forward(&xs, cache)?,
                        DownLayer::Resample(block) => block.forward(&xs, cache)?,
                    };
                }
            }
            DownBlocks::Residual(blocks) => {
                for block in blocks {
                    let input = xs.shallow_clone();
                    for resnet in &block.resnets {
                        xs = resnet.forward(&xs, cache)?;
                    }
                    if let Some(down) = &block.downsampler {
                        xs = down.forward(&xs, cache)?;
                    }
                    xs = xs.f_add(&avg_down(&input, block.out_dim, block.factor_t, block.factor_s)?)?;
                }
            }
        }
        let xs = self.mid_block.forward(&xs, cache)?;
        cache.causal(&self.conv_out, &self.norm_out.forward(&xs)?.f_silu()?)
    }
}

/// One decoder level: residual blocks and an upsampler (Wan2.2: plus the [`dup_up`] shortcut).
#[derive(Debug)]
struct UpBlock {
    resnets: Vec<ResidualBlock>,
    upsampler: Option<Resample>,
    /// Wan2.2's shortcut: (out channels, factor_t).
    shortcut: Option<(i64, i64)>,
}

/// diffusers' `WanDecoder3d`.
#[derive(Debug)]
struct Decoder {
    conv_in: CausalConv3d,
    mid_block: MidBlock,
    up_blocks: Vec<UpBlock>,
    norm_out: RmsNorm,
    conv_out: CausalConv3d,
}

impl Decoder {
    fn new(vars: &Vars, c: &AutoencoderKLWanConfig) -> Result<Self> {
        let dims = c.decoder_dims();
        let levels = c.dim_mult.len();
        let upsample: Vec<bool> = c.temperal_downsample.iter().rev().copied().collect();
        let blocks = vars.sub("up_blocks");
        let mut up_blocks = Vec::new();
        for i in 0..levels {
            let block = blocks.sub(i);
            let out_dim = dims[i + 1];
            // Wan2.1's upsamplers halve the channels, so every level after the first gets half.
            let mut in_dim = if i > 0 && !c.is_residual { dims[i] / 2 } else { dims[i] };
            let up = i != levels - 1;
            let temporal = up && upsample[i];
            let mode = if temporal { ResampleMode::Upsample3d } else { ResampleMode::Upsample2d };
            let mut resnets = Vec::new();
            for j in 0..=c.num_res_blocks {
                resnets.push(ResidualBlock::new(&block.sub("resnets").sub(j), in_dim, out_dim)?);
                in_dim = out_dim;
            }
            let (upsampler, shortcut) = match (up, c.is_residual) {
                (false, _) => (None, None),
                (true, true) => (
                    Some(Resample::new(&block.sub("upsampler"), out_dim, mode, out_dim)?),
                    Some((out_dim, if temporal { 2 } else { 1 })),
                ),
                (true, false) => {
                    (Some(Resample::new(&block.sub("upsamplers").sub(0), out_dim, mode, out_dim / 2)?), None)
                }
            };
            up_blocks.push(UpBlock { resnets, upsampler, shortcut });
        }
        let last = dims[levels];
        Ok(Self {
            conv_in: CausalConv3d::cube(&vars.sub("conv_in"), c.z_dim, dims[0], 3)?,
            mid_block: MidBlock::new(&vars.sub("mid_block"), dims[0])?,
            up_blocks,
            norm_out: RmsNorm::new(&vars.sub("norm_out"), last, false)?,
            conv_out: CausalConv3d::cube(&vars.sub("conv_out"), last, c.out_channels, 3)?,
        })
    }

    fn forward(&self, xs: &Tensor, cache: &mut FeatCache, first_chunk: bool) -> Result<Tensor> {
        let xs = cache.causal(&self.conv_in, xs)?;
        let mut xs = self.mid_block.forward(&xs, cache)?;
        for block in &self.up_blocks {
            let input = xs.shallow_clone();
            for resnet in &block.resnets {
                xs = resnet.forward(&xs, cache)?;
            }
            if let Some(up) = &block.upsampler {
                xs = up.forward(&xs, cache)?;
            }
            if let Some((out_dim, factor_t)) = block.shortcut {
                xs = xs.f_add(&dup_up(&input, out_dim, factor_t, 2, first_chunk)?)?;
            }
        }
        cache.causal(&self.conv_out, &self.norm_out.forward(&xs)?.f_silu()?)
    }
}

// ------------------------------------------------------------------------------------------------
// Model
// ------------------------------------------------------------------------------------------------

/// diffusers' `AutoencoderKLWan` (eval mode): `encoder.*`, `quant_conv.*`, `post_quant_conv.*`,
/// `decoder.*` at diffusers' state-dict names.
#[derive(Debug)]
pub struct AutoencoderKLWan {
    config: AutoencoderKLWanConfig,
    encoder: Encoder,
    quant_conv: CausalConv3d,
    post_quant_conv: CausalConv3d,
    decoder: Decoder,
}

impl AutoencoderKLWan {
    /// Creates the variables under `vars`.
    pub fn new(vars: &Vars, config: &AutoencoderKLWanConfig) -> Result<Self> {
        config.validate("VAE config")?;
        let z = config.z_dim;
        Ok(Self {
            config: config.clone(),
            encoder: Encoder::new(&vars.sub("encoder"), config)?,
            quant_conv: CausalConv3d::cube(&vars.sub("quant_conv"), 2 * z, 2 * z, 1)?,
            post_quant_conv: CausalConv3d::cube(&vars.sub("post_quant_conv"), z, z, 1)?,
            decoder: Decoder::new(&vars.sub("decoder"), config)?,
        })
    }

    /// The configuration the model was built from.
    pub fn config(&self) -> &AutoencoderKLWanConfig {
        &self.config
    }

    /// The element type of the weights, which inputs must have.
    pub fn kind(&self) -> Kind {
        self.quant_conv.conv.weight.kind()
    }

    /// Posterior mean `[B, z_dim, 1 + (F − 1)/4, H/s, W/s]` (unnormalised: the pipelines subtract
    /// `latents_mean` and divide by `latents_std`) of a video `[B, 3, F, H, W]` in [−1, 1] with
    /// F = 1 + 4k, as diffusers' `vae.encode(x).latent_dist.mean`.
    pub fn encode(&self, sample: &Tensor) -> Result<Tensor> {
        Ok(self.encode_posterior(sample)?.mean)
    }

    /// The full posterior of [`encode`](Self::encode).
    pub fn encode_posterior(&self, sample: &Tensor) -> Result<DiagonalGaussian> {
        let channels = self.config.in_channels / self.patch_area();
        let [_, c, f, h, w] = dims5(sample).map_err(|_| self.bad_sample(sample))?;
        let p = self.config.patch_size.unwrap_or(1);
        if c != channels || f < 1 || (f - 1) % ENCODE_CHUNK_FRAMES != 0 || h % p != 0 || w % p != 0 || h == 0 || w == 0
        {
            return Err(self.bad_sample(sample));
        }
        let xs = patchify(sample, p)?;
        let mut cache = FeatCache::default();
        let mut outs = Vec::new();
        for i in 0..1 + (f - 1) / ENCODE_CHUNK_FRAMES {
            let (start, len) = if i == 0 { (0, 1) } else { (1 + ENCODE_CHUNK_FRAMES * (i - 1), ENCODE_CHUNK_FRAMES) };
            cache.cursor = 0;
            outs.push(self.encoder.forward(&xs.f_narrow(2, start, len)?, &mut cache)?);
        }
        let moments = self.quant_conv.forward(&Tensor::f_cat(&outs, 2)?, None)?;
        DiagonalGaussian::from_moments(&moments, self.config.z_dim)
    }

    /// Video `[B, 3, 1 + 4(f − 1), H·s, W·s]` in [−1, 1] from a latent `[B, z_dim, f, h, w]`
    /// (unnormalised), as diffusers' `vae.decode(z).sample`: one latent frame at a time.
    pub fn decode(&self, latent: &Tensor) -> Result<Tensor> {
        let z = self.config.z_dim;
        let dims = dims5(latent).ok().filter(|d| d[1] == z && d[2] > 0 && d[3] > 0 && d[4] > 0);
        let Some([_, _, frames, _, _]) = dims else {
            return Err(Error::Shape {
                tensor: "latent".to_string(),
                expected: format!("[B, {z} (z_dim), f ≥ 1, h ≥ 1, w ≥ 1]"),
                actual: latent.size(),
            });
        };
        let xs = self.post_quant_conv.forward(latent, None)?;
        let mut cache = FeatCache::default();
        let mut outs = Vec::new();
        for i in 0..frames {
            cache.cursor = 0;
            outs.push(self.decoder.forward(&xs.f_narrow(2, i, 1)?, &mut cache, i == 0)?);
        }
        let out = unpatchify(&Tensor::f_cat(&outs, 2)?, self.config.patch_size.unwrap_or(1))?;
        Ok(out.f_clamp(-1.0, 1.0)?)
    }

    /// The Wan pipelines' latent normalisation, `(z − latents_mean) · (1 / latents_std)` per
    /// channel (the reciprocal taken in fp32, as they compute it): what the diffusion model sees.
    pub fn normalize_latents(&self, latent: &Tensor) -> Result<Tensor> {
        let (mean, inv_std) = self.latent_statistics(latent)?;
        Ok(latent.f_sub(&mean)?.f_mul(&inv_std)?)
    }

    /// The inverse of [`normalize_latents`](Self::normalize_latents), `z / (1 / latents_std) +
    /// latents_mean`, as the pipelines undo it before decoding.
    pub fn denormalize_latents(&self, latent: &Tensor) -> Result<Tensor> {
        let (mean, inv_std) = self.latent_statistics(latent)?;
        Ok(latent.f_div(&inv_std)?.f_add(&mean)?)
    }

    /// `latents_mean` and `1 / latents_std` as `[1, z_dim, 1, 1, 1]` in the latent's dtype and
    /// device.
    fn latent_statistics(&self, latent: &Tensor) -> Result<(Tensor, Tensor)> {
        let z = self.config.z_dim;
        if latent.dim() != 5 || latent.size()[1] != z {
            return Err(Error::Shape {
                tensor: "latent".to_string(),
                expected: format!("[B, {z} (z_dim), f, h, w]"),
                actual: latent.size(),
            });
        }
        let column = |values: &[f64]| -> Result<Tensor> {
            let fp32: Vec<f32> = values.iter().map(|&v| v as f32).collect();
            Ok(Tensor::from_slice(&fp32).f_view([1, z, 1, 1, 1])?)
        };
        let mean = column(&self.config.latents_mean)?;
        let inv_std = column(&self.config.latents_std)?.f_reciprocal()?;
        let place = |t: Tensor| -> Result<Tensor> { Ok(t.f_to_device(latent.device())?.f_to_kind(latent.kind())?) };
        Ok((place(mean)?, place(inv_std)?))
    }

    fn patch_area(&self) -> i64 {
        let p = self.config.patch_size.unwrap_or(1);
        p * p
    }

    fn bad_sample(&self, sample: &Tensor) -> Error {
        let p = self.config.patch_size.unwrap_or(1);
        Error::Shape {
            tensor: "sample".to_string(),
            expected: format!(
                "[B, {}, 1 + 4k, H, W] with H and W multiples of patch_size {p}",
                self.config.in_channels / self.patch_area()
            ),
            actual: sample.size(),
        }
    }
}

/// diffusers' `patchify`: `p × p` pixel patches onto channels, ordered (channel, column, row).
fn patchify(xs: &Tensor, p: i64) -> Result<Tensor> {
    if p == 1 {
        return Ok(xs.shallow_clone());
    }
    let [b, c, f, h, w] = dims5(xs)?;
    Ok(xs
        .f_view([b, c, f, h / p, p, w / p, p].as_slice())?
        .f_permute([0, 1, 6, 4, 2, 3, 5])?
        .f_contiguous()?
        .f_view([b, c * p * p, f, h / p, w / p])?)
}

/// diffusers' `unpatchify`, the inverse of [`patchify`].
fn unpatchify(xs: &Tensor, p: i64) -> Result<Tensor> {
    if p == 1 {
        return Ok(xs.shallow_clone());
    }
    let [b, cp, f, h, w] = dims5(xs)?;
    let c = cp / (p * p);
    Ok(xs.f_view([b, c, p, p, f, h, w].as_slice())?.f_permute([0, 1, 4, 5, 3, 6, 2])?.f_contiguous()?.f_view([
        b,
        c,
        f,
        h * p,
        w * p,
    ])?)
}

/// A VAE on `device` in `kind` with its variables in a fresh VarStore.
pub fn build(config: &AutoencoderKLWanConfig, device: Device, kind: Kind) -> Result<(nn::VarStore, AutoencoderKLWan)> {
    let mut vs = nn::VarStore::new(device);
    let model = AutoencoderKLWan::new(&Vars::new(vs.root()), config)?;
    vs.set_kind(kind);
    Ok((vs, model))
}

/// Name → shape of every variable of the VAE `config` describes, without allocating it.
pub fn variable_shapes(config: &AutoencoderKLWanConfig) -> Result<BTreeMap<String, Vec<i64>>> {
    let vs = nn::VarStore::new(Device::Cpu);
    AutoencoderKLWan::new(&Vars::shapes_only(vs.root()), config)?;
    Ok(crate::models::weights::variable_shapes(&vs))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patchify_round_trips() {
        let x = Tensor::randn([1, 3, 2, 4, 6], (Kind::Float, Device::Cpu));
        let p = patchify(&x, 2).unwrap();
        assert_eq!(p.size(), vec![1, 12, 2, 2, 3]);
        assert!(unpatchify(&p, 2).unwrap().equal(&x));
    }

    #[test]
    fn avg_down_inverts_dup_up_on_constant_groups() {
        let x = Tensor::randn([1, 4, 2, 3, 3], (Kind::Float, Device::Cpu));
        let up = dup_up(&x, 2, 2, 2, false).unwrap();
        assert_eq!(up.size(), vec![1, 2, 4, 6, 6]);
        let down = avg_down(&up, 4, 2, 2).unwrap();
        assert!((down - &x).abs().max().double_value(&[]) < 1e-6);
    }

    #[test]
    fn bad_inputs_and_configs_are_named() {
        let (_vs, vae) = build(&AutoencoderKLWanConfig::tiny(), Device::Cpu, Kind::Float).unwrap();
        let err = vae.encode(&Tensor::zeros([1, 3, 4, 8, 8], (Kind::Float, Device::Cpu))).unwrap_err().to_string();
        assert!(err.contains("sample") && err.contains("1 + 4k"), "{err}");
        let err = vae.decode(&Tensor::zeros([1, 3, 1, 2, 2], (Kind::Float, Device::Cpu))).unwrap_err().to_string();
        assert!(err.contains("latent") && err.contains("z_dim"), "{err}");
        let json =
            r#"{"z_dim": 4, "latents_mean": [0, 0, 0, 0], "latents_std": [1, 1, 1, 1], "temperal_downsample": [true]}"#;
        let err = AutoencoderKLWanConfig::from_json_str(json, "v.json").unwrap_err().to_string();
        assert!(err.contains("v.json") && err.contains("temperal_downsample"), "{err}");
        let err = AutoencoderKLWanConfig::from_json_str(r#"{"z_dim": 4}"#, "v.json").unwrap_err().to_string();
        assert!(err.contains("latents_mean"), "{err}");
        let err = AutoencoderKLWanConfig::from_json_str(r#"{"attn_scales": [1.0]}"#, "v.json").unwrap_err().to_string();
        assert!(err.contains("attn_scales"), "{err}");
    }
}

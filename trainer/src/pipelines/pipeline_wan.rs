//! Sampling with the Wan family, as diffusers' `WanPipeline` (text to video) and
//! `WanImageToVideoPipeline` compute it, so that a seed gives the same video as the pipeline
//! called with `generator=torch.Generator("cpu").manual_seed(seed)`:
//! 1. the initial latents `[1, C, 1 + (F − 1)/t, H/s, W/s]` (t, s: the VAE's temporal and
//!    spatial scale factors; C the transformer's `in_channels`, or with a condition the VAE's
//!    `z_dim`) are drawn in f32 on the CPU generator (the only draw);
//! 2. with a condition ([`WanCondition`]), its channels are computed once (below);
//! 3. the UniPC timesteps are set for `steps`; at each timestep t the expert is the transformer
//!    while `t ≥ boundary_ratio · num_train_timesteps` (always, without a boundary) and
//!    `transformer_2` after (Wan2.2 A14B's low-noise expert), each with its own guidance scale;
//! 4. the transformer runs on the latents (and the condition channels after them) cast to its
//!    element type with the prompt embedding and, when the scale is above 1, again with the
//!    negative one (two forwards, as the pipelines run them), mixed as `uncond + g·(cond −
//!    uncond)`; the timestep is one per sample, or with `expand_timesteps` (Wan2.2 TI2V, text to
//!    video) one per token, every token at t;
//! 5. the scheduler steps the f32 latents; at the end they are denormalised with the VAE's latent
//!    statistics and decoded.
//!
//! **The CogNVS conditioning on Wan.** The render video and its hole mask enter through the
//! image-to-video model's condition channels, `[mask (t channels), condition latents (z_dim)]`
//! after the noisy latents, built as `WanImageToVideoPipeline.prepare_latents` builds them for an
//! image, with the render in place of "the image followed by black frames" and the hole mask in
//! place of "the first frame is known": the render is VAE-encoded (posterior mean) and normalised;
//! the mask `[1, 1, F, H, W]` (1 known) is brought to the latent grid by a minimum over each
//! s × s block (a latent pixel is known only where all its pixels are), its first frame repeated
//! t times so that the F + t − 1 frames fold into t channels per latent frame. An input whose
//! render is the first frame followed by zeros and whose mask marks only the first frame is
//! therefore exactly `WanImageToVideoPipeline`'s input for that image.
//!
//! The video comes back as the VAE decodes it, `[1, 3, F, H, W]` in [−1, 1]; the pipelines'
//! `output_type="np"` frames are `(v / 2 + 0.5)` clamped to [0, 1].

use tch::{Device, Kind, Tensor};

use crate::error::{Error, Result};
use crate::models::backbone::{WAN_DEFAULT_SCALE_FACTOR_SPATIAL, WAN_DEFAULT_SCALE_FACTOR_TEMPORAL};
use crate::models::wan::autoencoder_kl_wan::AutoencoderKLWan;
use crate::models::wan::cognvs::mask_channels;
use crate::models::wan::transformer_wan::{WanTransformer3DModel, WanTransformerInput};
use crate::schedulers::scheduling_unipc_multistep::{UniPCMultistepScheduler, UniPCMultistepSchedulerConfig};

/// The denoising models: one transformer (Wan2.1, Wan2.2 TI2V-5B) or Wan2.2 A14B's two experts.
#[derive(Clone, Copy)]
pub struct WanExperts<'a> {
    /// The model (the high-noise expert when there are two).
    pub transformer: &'a WanTransformer3DModel,
    /// The low-noise expert, used below the boundary.
    pub transformer_2: Option<&'a WanTransformer3DModel>,
    /// The pipeline's `boundary_ratio`: the switch at this fraction of the training timesteps.
    pub boundary_ratio: Option<f64>,
}

/// What the video is conditioned on (image-to-video transformers; see the module docs).
#[derive(Clone, Copy)]
pub struct WanCondition<'a> {
    /// The render `[1, 3, F, H, W]` in [−1, 1] at the output size, zeros in the holes.
    pub video: &'a Tensor,
    /// Which pixels of `video` are known, `[1, 1, F, H, W]`: 1 known, 0 a hole.
    pub mask: &'a Tensor,
    /// CLIP image tokens `[1, N, image_dim]` for transformers with image cross-attention (Wan2.1
    /// I2V), precomputed as the pipeline's `encode_image` computes them.
    pub image_embeds: Option<&'a Tensor>,
}

/// What to sample: the pipeline's call arguments other than the text and the generator.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WanSampling {
    /// Frames, 1 + (the VAE's temporal scale factor)·k.
    pub frames: i64,
    /// Height in pixels, a multiple of the VAE's spatial scale factor × the patch height.
    pub height: i64,
    /// Width in pixels, likewise.
    pub width: i64,
    /// Denoising steps.
    pub steps: usize,
    /// Classifier-free guidance scale (of the high-noise expert when there are two).
    pub guidance_scale: f64,
    /// The low-noise expert's scale; the pipeline's default is `guidance_scale`.
    pub guidance_scale_2: Option<f64>,
    /// One timestep per token (the pipeline's `expand_timesteps`, Wan2.2 TI2V-5B).
    pub expand_timesteps: bool,
}

/// The video `[1, 3, F, H, W]` (f32, [−1, 1]) for `prompt` `[1, S, D]` (in the transformer's
/// element type, as the pipeline casts it) and `negative` (needed when a guidance scale is above
/// 1), conditioned on `condition` where given, drawing from tch's generator as it stands (seed it
/// with `tch::manual_seed`).
pub fn generate(
    experts: WanExperts<'_>,
    vae: &AutoencoderKLWan,
    scheduler: &UniPCMultistepSchedulerConfig,
    prompt: &Tensor,
    negative: Option<&Tensor>,
    condition: Option<WanCondition<'_>>,
    sampling: &WanSampling,
) -> Result<Tensor> {
    let invalid = |name: &str, reason: String| Error::InvalidArgument { name: name.to_string(), reason };
    let config = experts.transformer.config();
    let vae_config = vae.config();
    let temporal = vae_config.scale_factor_temporal.unwrap_or(WAN_DEFAULT_SCALE_FACTOR_TEMPORAL);
    let spatial = vae_config.scale_factor_spatial.unwrap_or(WAN_DEFAULT_SCALE_FACTOR_SPATIAL);
    let [_, patch_h, patch_w] = config.patch_size;
    let WanSampling { frames, height, width, steps, guidance_scale, expand_timesteps, .. } = *sampling;
    if frames < 1 || (frames - 1) % temporal != 0 {
        return Err(invalid("frames", format!("{frames} is not 1 + {temporal}k (the VAE's temporal scale factor)")));
    }
    if height <= 0 || width <= 0 || height % (spatial * patch_h) != 0 || width % (spatial * patch_w) != 0 {
        return Err(invalid(
            "size",
            format!("{width}x{height} is not a positive multiple of {}x{}", spatial * patch_w, spatial * patch_h),
        ));
    }
    let boundary = match (experts.boundary_ratio, experts.transformer_2) {
        (Some(ratio), Some(_)) => Some(ratio * scheduler.num_train_timesteps as f64),
        (None, None) => None,
        _ => return Err(invalid("boundary_ratio", "two experts need both transformer_2 and a boundary".into())),
    };
    if condition.is_some() && expand_timesteps {
        // TI2V-5B's image-to-video mode overwrites the first latent frame with the image's latent
        // and gives its tokens timestep 0 instead of adding condition channels: not this path.
        return Err(invalid("expand_timesteps", "per-token timesteps with a condition are not implemented".into()));
    }
    let guidance_scale_2 = sampling.guidance_scale_2.unwrap_or(guidance_scale);
    if (guidance_scale > 1.0 || (boundary.is_some() && guidance_scale_2 > 1.0)) && negative.is_none() {
        return Err(invalid("negative", "classifier-free guidance needs a negative prompt embedding".into()));
    }
    let kind = prompt.kind();
    tch::no_grad(|| -> Result<Tensor> {
        let channels = if condition.is_some() { vae_config.z_dim } else { config.in_channels };
        let shape = [1, channels, (frames - 1) / temporal + 1, height / spatial, width / spatial];
        // The pipeline draws on the CPU generator in f32 and moves the draw to the device.
        let mut latents = Tensor::f_randn(shape, (Kind::Float, Device::Cpu))?.f_to_device(prompt.device())?;
        let condition_channels = match condition {
            Some(c) => Some(condition_channels(vae, &c, sampling, (temporal, spatial), kind)?),
            None => None,
        };
        let conditioned = condition_channels.as_ref().map_or(channels, |c| channels + c.size()[1]);
        if conditioned != config.in_channels {
            return Err(invalid(
                "condition",
                format!(
                    "the transformer takes {} input channels; the latents and condition give {conditioned}",
                    config.in_channels
                ),
            ));
        }
        let image_embeds = match condition.and_then(|c| c.image_embeds) {
            Some(embeds) => Some(embeds.f_to_kind(kind)?),
            None => None,
        };
        let mut scheduler = UniPCMultistepScheduler::new(scheduler)?;
        scheduler.set_timesteps(steps, None)?;
        scheduler.set_begin_index(0);
        let timesteps = scheduler.timesteps().to_vec();
        let tokens = shape[2] * (shape[3] / patch_h) * (shape[4] / patch_w);
        for t in timesteps {
            let (model, scale) = match boundary {
                Some(b) if (t as f64) < b => (experts.transformer_2.expect("checked above"), guidance_scale_2),
                _ => (experts.transformer, guidance_scale),
            };
            let input = match &condition_channels {
                Some(c) => Tensor::f_cat(&[&latents, c], 1)?.f_to_kind(kind)?,
                None => latents.f_to_kind(kind)?,
            };
            // The pipeline's per-token timesteps are `ones_mask · t` in f32; per sample, t itself.
            let timestep = if expand_timesteps {
                Tensor::f_full([1, tokens], t as f64, (Kind::Float, prompt.device()))?
            } else {
                Tensor::from_slice(&[t]).f_to_device(prompt.device())?
            };
            let run = |text: &Tensor| {
                model.forward(&WanTransformerInput {
                    hidden_states: &input,
                    timestep: &timestep,
                    encoder_hidden_states: text,
                    encoder_hidden_states_image: image_embeds.as_ref(),
                })
            };
            let mut noise_pred = run(prompt)?;
            if scale > 1.0 {
                let uncond = run(negative.expect("checked above"))?;
                noise_pred = uncond.f_add(&noise_pred.f_sub(&uncond)?.f_mul_scalar(scale)?)?;
            }
            latents = scheduler.step(&noise_pred, t, &latents)?;
        }
        // The pipeline casts to the VAE's element type; both models run in one type here.
        let latents = vae.denormalize_latents(&latents.f_to_kind(kind)?)?;
        Ok(vae.decode(&latents)?.f_to_kind(Kind::Float)?)
    })
}

/// The condition channels `[1, t + z_dim, F', h, w]` of a render and its mask (module docs).
fn condition_channels(
    vae: &AutoencoderKLWan,
    condition: &WanCondition<'_>,
    sampling: &WanSampling,
    (temporal, spatial): (i64, i64),
    kind: Kind,
) -> Result<Tensor> {
    let (frames, height, width) = (sampling.frames, sampling.height, sampling.width);
    for (name, tensor, channels) in [("condition video", condition.video, 3), ("condition mask", condition.mask, 1)] {
        if tensor.size() != [1, channels, frames, height, width] {
            return Err(Error::InvalidArgument {
                name: name.to_string(),
                reason: format!("shape {:?}, expected [1, {channels}, {frames}, {height}, {width}]", tensor.size()),
            });
        }
    }
    // The pipeline encodes in the VAE's type (here the models' one type) and normalises in f32.
    let latent = vae.encode(&condition.video.f_to_kind(kind)?)?.f_to_kind(Kind::Float)?;
    let latent = vae.normalize_latents(&latent)?;
    let mask = mask_channels(&condition.mask.f_to_device(latent.device())?, temporal, spatial)?;
    Ok(Tensor::f_cat(&[mask, latent], 1)?)
}

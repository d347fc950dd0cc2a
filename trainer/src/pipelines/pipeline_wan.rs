//! Text-to-video sampling with the Wan family, as diffusers' `WanPipeline` computes it, so that a
//! seed gives the same video as the pipeline called with
//! `generator=torch.Generator("cpu").manual_seed(seed)`:
//! 1. the initial latents `[1, in_channels, 1 + (F − 1)/t, H/s, W/s]` (t, s: the VAE's temporal
//!    and spatial scale factors) are drawn in f32 on the CPU generator (the only draw);
//! 2. the UniPC timesteps are set for `steps`; at each timestep t the expert is the transformer
//!    while `t ≥ boundary_ratio · num_train_timesteps` (always, without a boundary) and
//!    `transformer_2` after (Wan2.2 A14B's low-noise expert), each with its own guidance scale;
//! 3. the transformer runs on the latents cast to its element type with the prompt embedding and,
//!    when the scale is above 1, again with the negative one (two forwards, as the pipeline runs
//!    them), mixed as `uncond + g·(cond − uncond)`; the timestep is one per sample, or with
//!    `expand_timesteps` (Wan2.2 TI2V) one per token, every token at t;
//! 4. the scheduler steps the f32 latents; at the end they are denormalised with the VAE's latent
//!    statistics and decoded.
//!
//! The video comes back as the VAE decodes it, `[1, 3, F, H, W]` in [−1, 1]; the pipeline's
//! `output_type="np"` frames are `(v / 2 + 0.5)` clamped to [0, 1].

use tch::{Device, Kind, Tensor};

use crate::error::{Error, Result};
use crate::models::autoencoder_kl_wan::AutoencoderKLWan;
use crate::models::transformer_wan::{WanTransformer3DModel, WanTransformerInput};
use crate::schedulers::scheduling_unipc_multistep::{UniPCMultistepScheduler, UniPCMultistepSchedulerConfig};

/// `AutoencoderKLWan`'s default `scale_factor_temporal` (diffusers' constructor), for configs
/// written before the key existed.
const DEFAULT_SCALE_FACTOR_TEMPORAL: i64 = 4;
/// `AutoencoderKLWan`'s default `scale_factor_spatial`.
const DEFAULT_SCALE_FACTOR_SPATIAL: i64 = 8;

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
/// 1), drawing from tch's generator as it stands (seed it with `tch::manual_seed`).
pub fn generate(
    experts: WanExperts<'_>,
    vae: &AutoencoderKLWan,
    scheduler: &UniPCMultistepSchedulerConfig,
    prompt: &Tensor,
    negative: Option<&Tensor>,
    sampling: &WanSampling,
) -> Result<Tensor> {
    let invalid = |name: &str, reason: String| Error::InvalidArgument { name: name.to_string(), reason };
    let config = experts.transformer.config();
    let vae_config = vae.config();
    let temporal = vae_config.scale_factor_temporal.unwrap_or(DEFAULT_SCALE_FACTOR_TEMPORAL);
    let spatial = vae_config.scale_factor_spatial.unwrap_or(DEFAULT_SCALE_FACTOR_SPATIAL);
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
    let guidance_scale_2 = sampling.guidance_scale_2.unwrap_or(guidance_scale);
    if (guidance_scale > 1.0 || (boundary.is_some() && guidance_scale_2 > 1.0)) && negative.is_none() {
        return Err(invalid("negative", "classifier-free guidance needs a negative prompt embedding".into()));
    }
    let kind = prompt.kind();
    tch::no_grad(|| -> Result<Tensor> {
        let shape = [1, config.in_channels, (frames - 1) / temporal + 1, height / spatial, width / spatial];
        // The pipeline draws on the CPU generator in f32 and moves the draw to the device.
        let mut latents = Tensor::f_randn(shape, (Kind::Float, Device::Cpu))?.f_to_device(prompt.device())?;
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
            let input = latents.f_to_kind(kind)?;
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
                    encoder_hidden_states_image: None,
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

//! Sampling novel views with a Wan model: the models, text embeddings and scheduler of a
//! [`ModelPaths`] loaded for [`pipeline_wan::generate`] with the CogNVS conditioning (the render
//! video and its hole mask as the image-to-video transformer's condition channels). The job-level
//! steps around it (reading the conditioning, the framing, writing frames) are
//! [`crate::pipelines::sampling`]'s, which picks this module or its CogVideoX pipeline by the
//! model folder's family.
//!
//! The scheduler is the folder's `scheduler/scheduler_config.json` (a `UniPCMultistepScheduler`,
//! as the Wan2.1 and Wan2.2 Diffusers releases ship), else Wan's 480p UniPC config (a run's
//! checkpoint has no scheduler folder). Where the negative text embedding is the prompt's (the
//! CogNVS default: the empty prompt on both sides) guidance returns the conditional prediction
//! exactly, so the sampler runs with scale 1 and one forward a step.

use std::path::PathBuf;

use tch::{Device, Kind, Tensor, nn};

use crate::diffusers_config::DiffusersConfig;
use crate::error::{Error, Result};
use crate::loaders::{ModelPaths, load_text_embedding};
use crate::models::family::ModelFamily;
use crate::models::wan::autoencoder_kl_wan::{self as wan_vae, AutoencoderKLWan, AutoencoderKLWanConfig};
use crate::models::wan::transformer_wan::{
    self as wan_transformer, WanTransformer3DModel, WanTransformer3DModelConfig,
};
use crate::models::weights;
use crate::pipelines::pipeline_wan::{self, WanCondition, WanExperts, WanSampling};
use crate::pipelines::video_processor;
use crate::schedulers::scheduling_unipc_multistep::UniPCMultistepSchedulerConfig;

/// What [`WanNvsPipeline::load_checked`] needs, read and checked without building a model.
#[derive(Debug)]
pub struct WanCheckedModels {
    config: WanTransformer3DModelConfig,
    vae_config: AutoencoderKLWanConfig,
    scheduler: UniPCMultistepSchedulerConfig,
    adapters: Vec<(crate::loaders::lora::LoraFile, PathBuf)>,
    text: Tensor,
    negative: Tensor,
}

impl WanCheckedModels {
    /// Reads the configs, the checkpoints' headers, the LoRA files and the text embeddings (on
    /// `device`) that `paths` names; the transformer must take the CogNVS condition channels.
    pub fn read(paths: &ModelPaths, device: Device) -> Result<Self> {
        paths.check_text_embedding()?;
        let adapters = paths
            .adapters
            .iter()
            .map(|file| Ok((crate::loaders::lora::LoraFile::read(file)?, file.clone())))
            .collect::<Result<Vec<_>>>()?;
        let config: WanTransformer3DModelConfig = crate::diffusers_config::read(&paths.transformer)?;
        weights::check_against(
            &wan_transformer::variable_shapes(&config)?,
            &weights::read_checkpoint_info(&paths.transformer)?,
            &paths.transformer,
        )?;
        if let Some(image_dim) = config.image_dim {
            // Wan2.1 I2V's image cross-attention takes CLIP tokens of a reference image, which
            // nothing here computes; the CogNVS conditioning is the render and its mask.
            return Err(Error::InvalidConfig {
                source_name: paths.transformer.join("config.json").display().to_string(),
                field: "image_dim".to_string(),
                reason: format!(
                    "is {image_dim}: a transformer with CLIP image cross-attention is not sampled here (no image tokens)"
                ),
            });
        }
        let vae_config: AutoencoderKLWanConfig = crate::diffusers_config::read(&paths.vae)?;
        weights::read_checkpoint_info(&paths.vae)?;
        // Noisy latents, then the mask (one channel per folded frame) and the render's latents.
        let conditioned = 2 * vae_config.z_dim + temporal_factor(&vae_config);
        if config.in_channels != conditioned || config.output_channels() != vae_config.z_dim {
            return Err(Error::InvalidConfig {
                source_name: paths.transformer.join("config.json").display().to_string(),
                field: "in_channels".to_string(),
                reason: format!(
                    "in_channels {} / out_channels {}: CogNVS sampling with the VAE's z_dim {} ({}) needs {conditioned} / {}",
                    config.in_channels,
                    config.output_channels(),
                    vae_config.z_dim,
                    paths.vae.display(),
                    vae_config.z_dim
                ),
            });
        }
        let scheduler = match &paths.scheduler {
            Some(folder) => UniPCMultistepSchedulerConfig::from_json_file(folder)?,
            None => UniPCMultistepSchedulerConfig::wan_480p(),
        };
        let text = load_text_embedding(paths.text_embedding.as_deref(), &config, device)?;
        let negative = match &paths.negative_text_embedding {
            Some(path) => load_text_embedding(Some(path), &config, device)?,
            None => text.shallow_clone(),
        };
        Ok(Self { config, vae_config, scheduler, adapters, text, negative })
    }

    /// Refuses sampling arguments these models cannot take, naming the flag (as
    /// [`crate::pipelines::sampling::CheckedModels::check_sampling`] does for CogVideoX): the
    /// steps, the guidance and the framing (see [`check_framing`]).
    pub fn check_sampling(&self, steps_flag: &str, steps: usize, guidance: f64, framing: WanFraming) -> Result<()> {
        crate::schedulers::scheduling_utils::check_inference_steps(
            steps_flag,
            steps,
            self.scheduler.num_train_timesteps as u64,
        )?;
        if !guidance.is_finite() {
            return Err(Error::InvalidArgument {
                name: "guidance".to_string(),
                reason: format!("must be a finite number, got {guidance}"),
            });
        }
        check_framing(&self.config, &self.vae_config, framing).map(|_| ())
    }
}

fn temporal_factor(vae: &AutoencoderKLWanConfig) -> i64 {
    vae.scale_factor_temporal.unwrap_or(crate::models::backbone::WAN_DEFAULT_SCALE_FACTOR_TEMPORAL)
}

fn spatial_factor(vae: &AutoencoderKLWanConfig) -> i64 {
    vae.scale_factor_spatial.unwrap_or(crate::models::backbone::WAN_DEFAULT_SCALE_FACTOR_SPATIAL)
}

/// What [`check_framing`] checks of a sampling's framing (`pipelines::sampling::Framing`'s fields).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WanFraming {
    /// Frames sampled.
    pub frames: usize,
    /// The model's input size (width, height); None: the family's default clip's.
    pub size: Option<(u32, u32)>,
    /// Frame rate of an mp4 output.
    pub fps: f64,
}

/// The input size for `framing` (its `size`, else the family's default clip: a Wan transformer has
/// no positional table of a fixed size), after checking frames, size and frame rate against the
/// models, naming the flag.
pub fn check_framing(
    config: &WanTransformer3DModelConfig,
    vae_config: &AutoencoderKLWanConfig,
    framing: WanFraming,
) -> Result<(u32, u32)> {
    let temporal = temporal_factor(vae_config) as usize;
    if framing.frames == 0 || !(framing.frames - 1).is_multiple_of(temporal) {
        return Err(Error::InvalidArgument {
            name: "frames".to_string(),
            reason: format!("{} is not 1 + {temporal}k (the VAE compresses time {temporal}×)", framing.frames),
        });
    }
    if framing.frames > video_processor::MAX_FRAMES {
        return Err(Error::InvalidArgument {
            name: "frames".to_string(),
            reason: format!("{}: at most {} frames are sampled", framing.frames, video_processor::MAX_FRAMES),
        });
    }
    if !(framing.fps.is_finite() && framing.fps > 0.0) {
        return Err(Error::InvalidArgument {
            name: "fps".to_string(),
            reason: format!("must be a finite number > 0, got {}", framing.fps),
        });
    }
    let clip = ModelFamily::Wan.default_clip();
    let (width, height) = framing.size.unwrap_or((clip.width, clip.height));
    let spatial = spatial_factor(vae_config);
    let [_, patch_h, patch_w] = config.patch_size;
    let (multiple_w, multiple_h) = ((spatial * patch_w) as u32, (spatial * patch_h) as u32);
    let reason = if width == 0 || height == 0 || width % multiple_w != 0 || height % multiple_h != 0 {
        format!("{width}x{height} is not a positive multiple of {multiple_w}x{multiple_h}")
    } else if width > video_processor::MAX_SIDE || height > video_processor::MAX_SIDE {
        format!("{width}x{height}: at most {} pixels a side", video_processor::MAX_SIDE)
    } else {
        return Ok((width, height));
    };
    Err(Error::InvalidArgument { name: "size".to_string(), reason })
}

/// A loaded Wan CogNVS pipeline: transformer, VAE, text embeddings and scheduler config.
#[derive(Debug)]
pub struct WanNvsPipeline {
    transformer: WanTransformer3DModel,
    vae: AutoencoderKLWan,
    scheduler: UniPCMultistepSchedulerConfig,
    text: Tensor,
    negative: Tensor,
    // The variable stores own the weights the models' tensors share.
    _stores: (nn::VarStore, nn::VarStore),
}

impl WanNvsPipeline {
    /// Builds and loads the checked models on the device in the requested arithmetic, the LoRA
    /// adapters merged into the transformer.
    /// The models are built on `device` in `kind`.
    pub fn load_checked(paths: &ModelPaths, checked: WanCheckedModels, device: Device, kind: Kind) -> Result<Self> {
        let WanCheckedModels { config, vae_config, scheduler, adapters, text, negative } = checked;
        let (vs, transformer) = wan_transformer::build(&config, device, kind)?;
        wan_transformer::load(&vs, &paths.transformer)?;
        for (adapter, file) in &adapters {
            adapter.merge_into(&vs, file)?;
        }
        let (vae_vs, vae) = wan_vae::build(&vae_config, device, kind)?;
        weights::load(&vae_vs, &paths.vae)?;
        Ok(Self {
            transformer,
            vae,
            scheduler,
            text: text.f_to_kind(kind)?,
            negative: negative.f_to_kind(kind)?,
            _stores: (vs, vae_vs),
        })
    }

    /// The input size the framing gets without a `size` (see [`check_framing`]).
    pub fn framing_size(&self, framing: WanFraming) -> Result<(u32, u32)> {
        check_framing(self.transformer.config(), self.vae.config(), framing)
    }

    /// The VAE's temporal compression.
    pub fn temporal_factor(&self) -> usize {
        temporal_factor(self.vae.config()) as usize
    }

    /// The models' element type.
    pub fn kind(&self) -> Kind {
        self.vae.kind()
    }

    /// The video `[1, 3, F, H, W]` (f32, [−1, 1]) sampled for the render `video` (same shape,
    /// zeros in the holes) and its `mask` `[1, 1, F, H, W]` (1 known) with `steps` UniPC steps and
    /// guidance scale `guidance`, tch's generator reseeded with `seed`. The sampler reports no
    /// step in between: `progress(steps, steps)` is called once at the end. Also returns the
    /// seconds of the whole run (encode, denoising and decode together).
    pub fn generate_timed(
        &self,
        video: &Tensor,
        mask: &Tensor,
        steps: usize,
        guidance: f64,
        seed: u64,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<(Tensor, f64)> {
        let [_, _, frames, height, width] = video.size()[..] else {
            return Err(Error::Shape {
                tensor: "condition video".to_string(),
                expected: "[1, 3, F, H, W]".to_string(),
                actual: video.size(),
            });
        };
        tch::manual_seed(seed as i64);
        let negative = (!self.negative.equal(&self.text)).then_some(&self.negative);
        let sampling = WanSampling {
            frames,
            height,
            width,
            steps,
            guidance_scale: if negative.is_some() { guidance } else { 1.0 },
            guidance_scale_2: None,
            expand_timesteps: false,
        };
        let experts = WanExperts { transformer: &self.transformer, transformer_2: None, boundary_ratio: None };
        let condition = WanCondition { video, mask, image_embeds: None };
        let started = std::time::Instant::now();
        let sampled = pipeline_wan::generate(
            experts,
            &self.vae,
            &self.scheduler,
            &self.text,
            negative,
            Some(condition),
            &sampling,
        )?;
        if let Device::Cuda(index) = video.device() {
            tch::Cuda::synchronize(index as i64);
        }
        progress(steps, steps);
        let seconds = started.elapsed().as_secs_f64();
        weights::check_finite("sampled video", &sampled)?;
        Ok((sampled, seconds))
    }
}

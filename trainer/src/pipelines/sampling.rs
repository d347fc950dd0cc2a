//! Sampling novel views: the CogNVS pipeline (the public `CogNVSPipeline` and its demo), from a
//! conditioning render to a video.
//!
//! What a call computes, in the order of the public pipeline, so that a seed gives the same video
//! as the pipeline called with `generator=torch.Generator(device).manual_seed(seed)`:
//! 1. the conditioning `[1, 3, F, H, W]` in [−1, 1] is VAE-encoded (spatial tiles where enabled)
//!    and a *sample* of the posterior is drawn (first draw), cast to the model's element type,
//!    put frames-first and multiplied by the VAE's `scaling_factor`;
//! 2. the initial latents `[1, F', C, h, w]` are drawn in the model's element type (second draw);
//! 3. 50 (or `steps`) steps of CogVideoX's DPM solver: the noisy and the condition latents
//!    concatenated on channels, the transformer run on the negative and the positive text
//!    embedding as one batch of two (classifier-free guidance `uncond + g·(cond − uncond)` in
//!    f32), the scheduler's step drawing its noise in the latents' element type, the latents
//!    cast back to the model's element type after each step;
//! 4. the latents divided by the scaling factor and VAE-decoded.
//!
//! Positions: the pipeline's rotary table (`grid_type="linspace"`, cropped to the transformer's
//! base grid when the input's differs). Where the prompt and the negative prompt are the same
//! embedding (CogNVS prompts with the empty string on both sides) the two halves of the batch
//! are equal, guidance returns the unconditional half, and one forward computes it.
//!
//! Models come from a [`ModelSource`]: a run's checkpoint, a diffusers transformer folder (the
//! released CogNVS transformer) or a CogVideoX pipeline folder, with the VAE and the scheduler
//! config from the checkpoint, its run, or a base model folder (CogVideoX-5B-I2V's layout).

use std::path::{Path, PathBuf};
use std::time::Instant;

use image::RgbImage;
use tch::{Device, Kind, Tensor, nn};

use crate::diffusers_config::DiffusersConfig;
use crate::error::{Error, Result};
use crate::loaders::{ModelPaths, ModelSource, load_text_embedding, scheduler_config};
use crate::models::cogvideox::autoencoder_kl_cogvideox::{
    self as vae, AutoencoderKLCogVideoX, AutoencoderKLCogVideoXConfig, TilingConfig,
};
use crate::models::cogvideox::cogvideox_transformer_3d::{
    self as transformer, CogVideoXTransformer3DModel, CogVideoXTransformer3DModelConfig, TransformerInput,
};
use crate::models::embeddings::RotaryEmbedding;
use crate::models::family::{Job, ModelFamily};
use crate::models::weights;
use crate::pipelines::sampling_wan::{WanCheckedModels, WanFraming, WanNvsPipeline};
use crate::pipelines::video_processor::{self, ResizeMode};
use crate::precision::Precision;
use crate::schedulers::CogVideoXSchedulerConfig;
use crate::schedulers::{CogVideoXDPMScheduler, Scheduler};

/// How a pipeline is loaded.
#[derive(Debug, Clone, Copy)]
pub struct LoadOptions {
    /// Compute device.
    pub device: Device,
    /// Arithmetic: `auto` is bf16 on CUDA (the demo's `torch_dtype=torch.bfloat16`), f32 on CPUs.
    pub precision: Precision,
    /// Spatial VAE tiling with diffusers' default tiles (the demo enables it), where those land on
    /// whole latent pixels (see [`CogNvsPipeline::vae_tiling`]).
    pub vae_tiling: bool,
}

/// A loaded CogNVS pipeline: transformer, VAE, text embeddings and scheduler config, ready to
/// sample any number of conditionings.
#[derive(Debug)]
pub struct CogNvsPipeline {
    transformer: CogVideoXTransformer3DModel,
    vae: AutoencoderKLCogVideoX,
    text: Tensor,
    negative: Tensor,
    scheduler: CogVideoXSchedulerConfig,
    // The variable stores own the weights the models' tensors share.
    _stores: (nn::VarStore, nn::VarStore),
}

/// What [`CogNvsPipeline::load`] reads and checks before it builds a model: every config (the
/// transformer's, the VAE's, the scheduler's), the checkpoints' headers, the LoRA files and the
/// text embeddings (each tensor finite). Small: no model weight is read.
#[derive(Debug)]
pub struct CheckedModels {
    config: CogVideoXTransformer3DModelConfig,
    vae_config: AutoencoderKLCogVideoXConfig,
    scheduler: CogVideoXSchedulerConfig,
    adapters: Vec<(crate::loaders::lora::LoraFile, PathBuf)>,
    text: Tensor,
    negative: Tensor,
}

impl CheckedModels {
    /// Reads and checks everything `paths` names that a pipeline needs, on `device` (the text
    /// embeddings are loaded there), without building a model: a job calls it before it writes
    /// anything.
    pub fn read(paths: &ModelPaths, device: Device) -> Result<Self> {
        // The CogVideoX pipeline's reader: [`Checked::read`] picks the family.
        let families = [
            (&paths.transformer, ModelFamily::of_transformer(&paths.transformer)?),
            (&paths.vae, ModelFamily::of_vae(&paths.vae)?),
        ];
        if let Some((path, family)) = families.into_iter().find(|(_, f)| *f != ModelFamily::CogVideoX) {
            return Err(Error::InvalidConfig {
                source_name: path.display().to_string(),
                field: "_class_name".to_string(),
                reason: format!("is a {} model; the CogVideoX pipeline reads CogVideoX models", family.name()),
            });
        }
        paths.check_text_embedding()?;
        let adapters = paths
            .adapters
            .iter()
            .map(|file| Ok((crate::loaders::lora::LoraFile::read(file)?, file.clone())))
            .collect::<Result<Vec<_>>>()?;
        let config = CogVideoXTransformer3DModelConfig::from_json_file(&paths.transformer)?;
        weights::check_against(
            &transformer::variable_shapes(&config)?,
            &weights::read_checkpoint_info(&paths.transformer)?,
            &paths.transformer,
        )?;
        let vae_config = AutoencoderKLCogVideoXConfig::from_json_file(&paths.vae)?;
        weights::read_checkpoint_info(&paths.vae)?;
        check_latent_channels(&config, &vae_config, &paths.transformer, &paths.vae)?;
        let scheduler = scheduler_config(paths.scheduler.as_deref())?;
        let text = load_text_embedding(paths.text_embedding.as_deref(), &config, device)?;
        let negative = match &paths.negative_text_embedding {
            Some(path) => load_text_embedding(Some(path), &config, device)?,
            None => text.shallow_clone(),
        };
        Ok(Self { config, vae_config, scheduler, adapters, text, negative })
    }

    /// Refuses sampling arguments these models cannot take, naming the flag: `steps` denoising
    /// steps (flag `steps_flag`; 1 to the scheduler's training timesteps), a finite `guidance`,
    /// and the framing's frame count, size and frame rate (see [`check_framing`]).
    pub fn check_sampling(&self, steps_flag: &str, steps: usize, guidance: f64, framing: &Framing) -> Result<()> {
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

/// The model's input size for `framing` (its `size`, else the transformer's own), after checking
/// the framing against the models, naming the flag: the frame count is 1 + (the VAE's temporal
/// compression)·k, the size a positive multiple of the VAE's spatial compression × the patch size
/// (and the positional table's size for a transformer with a learned one), the frame rate finite
/// and positive.
pub fn check_framing(
    config: &CogVideoXTransformer3DModelConfig,
    vae_config: &AutoencoderKLCogVideoXConfig,
    framing: &Framing,
) -> Result<(u32, u32)> {
    let temporal = vae_config.effective_temporal_compression_ratio() as usize;
    if framing.frames == 0 || !(framing.frames - 1).is_multiple_of(temporal) {
        return Err(Error::InvalidArgument {
            name: "frames".to_string(),
            reason: format!("{} is not 1 + {temporal}k (the VAE compresses time {temporal}×)", framing.frames),
        });
    }
    // No conditioning is sampled beyond these bounds (`prepare_condition`); refusing the flag
    // here keeps every size computed from it (the memory plan) within range.
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
    let spatial = vae_config.spatial_compression_ratio();
    let model_size = ((config.sample_width * spatial) as u32, (config.sample_height * spatial) as u32);
    let (width, height) = framing.size.unwrap_or(model_size);
    let multiple = (spatial * config.patch_size) as u32;
    let reason = if width == 0 || height == 0 || width % multiple != 0 || height % multiple != 0 {
        format!("{width}x{height} is not a positive multiple of {multiple} on both sides")
    } else if width > video_processor::MAX_SIDE || height > video_processor::MAX_SIDE {
        format!("{width}x{height}: at most {} pixels a side", video_processor::MAX_SIDE)
    } else if config.use_learned_positional_embeddings && (width, height) != model_size {
        let (w, h) = model_size;
        format!("this transformer has a learned positional table for {w}x{h} only")
    } else {
        return Ok((width, height));
    };
    Err(Error::InvalidArgument { name: "size".to_string(), reason })
}

impl CogNvsPipeline {
    /// Checks every config and header (see [`CheckedModels::read`]), then builds and loads the
    /// models on the device in the requested arithmetic.
    pub fn load(paths: &ModelPaths, options: LoadOptions) -> Result<Self> {
        let device = options.device;
        let checked = CheckedModels::read(paths, device)?;
        Self::load_checked(paths, checked, options)
    }

    /// [`Self::load`] with the configs and small files read already.
    pub fn load_checked(paths: &ModelPaths, checked: CheckedModels, options: LoadOptions) -> Result<Self> {
        let device = options.device;
        let kind = options.precision.kind(device);
        let CheckedModels { config, vae_config, scheduler, adapters, text, negative } = checked;

        // Built in the working type: each checkpoint tensor is converted as it is copied in, and
        // adapters are merged in f32 layer by layer.
        let (vs, model) = transformer::build(&config, device, kind)?;
        weights::load(&vs, &paths.transformer)?;
        for (adapter, file) in &adapters {
            adapter.merge_into(&vs, file)?;
        }
        let (vae_vs, mut vae_model) = vae::build(&vae_config, device, kind)?;
        weights::load(&vae_vs, &paths.vae)?;
        let tiles = TilingConfig::for_config(&vae_config);
        if options.vae_tiling && tiles.lands_on_latent_pixels(vae_config.spatial_compression_ratio()) {
            vae_model.enable_tiling(tiles)?;
        }
        Ok(Self {
            transformer: model,
            vae: vae_model,
            text: text.f_to_kind(kind)?,
            negative: negative.f_to_kind(kind)?,
            scheduler,
            _stores: (vs, vae_vs),
        })
    }

    /// The frame size (width, height) the model was trained at: its positional table's.
    pub fn model_size(&self) -> (u32, u32) {
        let (c, spatial) = (self.transformer.config(), self.vae.config().spatial_compression_ratio());
        ((c.sample_width * spatial) as u32, (c.sample_height * spatial) as u32)
    }

    /// The transformer's config.
    pub fn transformer_config(&self) -> &CogVideoXTransformer3DModelConfig {
        self.transformer.config()
    }

    /// The VAE's config.
    pub fn vae_config(&self) -> &AutoencoderKLCogVideoXConfig {
        self.vae.config()
    }

    /// Whether the VAE encodes and decodes in spatial tiles: asked for, and diffusers' default
    /// tiles land on whole latent pixels for this VAE (see
    /// [`TilingConfig::lands_on_latent_pixels`]; otherwise they change the latent size).
    pub fn vae_tiling(&self) -> bool {
        self.vae.tiling().is_some()
    }

    /// The models' element type.
    pub fn kind(&self) -> Kind {
        self.vae.kind()
    }

    /// The video `[1, 3, F, H, W]` (f32, [−1, 1]) sampled for `condition` (same shape, any float
    /// type; F = 1 + 4k) with `steps` DPM steps and guidance scale `guidance`, every draw from
    /// tch's generator reseeded with `seed`. `progress(i, steps)` is called after each step.
    pub fn generate(
        &self,
        condition: &Tensor,
        steps: usize,
        guidance: f64,
        seed: u64,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<Tensor> {
        Ok(self.generate_timed(condition, steps, guidance, seed, progress)?.0)
    }

    /// [`Self::generate`] with the time of each part.
    pub fn generate_timed(
        &self,
        condition: &Tensor,
        steps: usize,
        guidance: f64,
        seed: u64,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<(Tensor, Timings)> {
        tch::manual_seed(seed as i64);
        let negative = (!self.negative.equal(&self.text)).then_some(&self.negative);
        let denoiser = Denoiser { transformer: &self.transformer, vae: &self.vae, scheduler: &self.scheduler };
        let mut timings = Timings::default();
        let video = denoiser.run(condition, &self.text, negative, steps, guidance, progress, &mut timings)?;
        // A NaN anywhere (weights, adapters, text, arithmetic) comes out as black frames: an
        // error, never a result.
        weights::check_finite("sampled video", &video).map_err(|e| match e {
            Error::NonFinite { tensor, reason } => Error::NonFinite {
                tensor,
                reason: format!("{reason}: the model produced no usable video, nothing is written"),
            },
            other => other,
        })?;
        Ok((video, timings))
    }
}

fn check_latent_channels(
    config: &CogVideoXTransformer3DModelConfig,
    vae_config: &AutoencoderKLCogVideoXConfig,
    transformer_path: &Path,
    vae_path: &Path,
) -> Result<()> {
    if config.in_channels != 2 * vae_config.latent_channels || config.output_channels() != vae_config.latent_channels {
        return Err(Error::InvalidConfig {
            source_name: transformer_path.join("config.json").display().to_string(),
            field: "in_channels".to_string(),
            reason: format!(
                "in_channels {} / out_channels {} do not fit the VAE's latent_channels {} ({}): need twice / once",
                config.in_channels,
                config.output_channels(),
                vae_config.latent_channels,
                vae_path.display()
            ),
        });
    }
    Ok(())
}

/// Where a generation's time went, in seconds (synchronised with the device on CUDA).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Timings {
    /// The conditioning's VAE encode.
    pub encode: f64,
    /// The denoising loop.
    pub denoise: f64,
    /// The VAE decode.
    pub decode: f64,
}

/// Waits for the device's queued work (CUDA), so that wall time is the work's own.
fn synchronize(device: Device) {
    if let Device::Cuda(index) = device {
        tch::Cuda::synchronize(index as i64);
    }
}

/// The models and schedule of one denoising run.
struct Denoiser<'a> {
    transformer: &'a CogVideoXTransformer3DModel,
    vae: &'a AutoencoderKLCogVideoX,
    scheduler: &'a CogVideoXSchedulerConfig,
}

impl Denoiser<'_> {
    /// Steps 1–4 of the module docs; draws from tch's global generator as it stands.
    #[allow(clippy::too_many_arguments)]
    fn run(
        &self,
        condition: &Tensor,
        text: &Tensor,
        negative: Option<&Tensor>,
        steps: usize,
        guidance: f64,
        progress: &mut dyn FnMut(usize, usize),
        timings: &mut Timings,
    ) -> Result<Tensor> {
        let timesteps_in_training = self.scheduler.num_train_timesteps;
        if steps == 0 || steps as i64 > timesteps_in_training {
            return Err(Error::InvalidArgument {
                name: "steps".to_string(),
                reason: format!("{steps} must be in 1..={timesteps_in_training} (the scheduler's training timesteps)"),
            });
        }
        if !guidance.is_finite() {
            return Err(Error::InvalidArgument {
                name: "guidance".to_string(),
                reason: format!("{guidance} must be finite"),
            });
        }
        let config = self.transformer.config();
        let device = text.device();
        let kind = self.vae.kind();
        tch::no_grad(|| -> Result<Tensor> {
            synchronize(device);
            let mut clock = Instant::now();
            let mut lap = |device: Device| {
                synchronize(device);
                let seconds = clock.elapsed().as_secs_f64();
                clock = Instant::now();
                seconds
            };
            let scale = self.vae.config().scaling_factor;
            let cond = self
                .vae
                .encode_posterior(&condition.f_to_kind(kind)?)?
                .sample()?
                .f_to_kind(kind)?
                .f_permute([0, 2, 1, 3, 4])?
                .f_mul_scalar(scale)?;
            timings.encode = lap(device);
            let [_, frames, _, height, width] = cond.size()[..] else { unreachable!("5-D latents") };
            let mut latents = Tensor::f_randn([1, frames, config.output_channels(), height, width], (kind, device))?;
            let rotary = pipeline_rotary(config, frames, height, width, device)?;
            // Classifier-free guidance runs negative and positive as one batch of two.
            let guided = guidance > 1.0 && negative.is_some();
            let (text, cond) = match negative {
                Some(negative) if guided => (
                    Tensor::f_cat(&[negative.f_to_kind(kind)?, text.f_to_kind(kind)?], 0)?,
                    Tensor::f_cat(&[&cond, &cond], 0)?,
                ),
                _ => (text.f_to_kind(kind)?, cond),
            };
            let mut scheduler = CogVideoXDPMScheduler::new(self.scheduler)?;
            scheduler.set_timesteps(steps)?;
            let timesteps = scheduler.timesteps().to_vec();
            let mut old_pred: Option<Tensor> = None;
            for (i, &t) in timesteps.iter().enumerate() {
                let noisy = if guided { Tensor::f_cat(&[&latents, &latents], 0)? } else { latents.shallow_clone() };
                let input = Tensor::f_cat(&[&noisy, &cond], 2)?;
                let timestep = Tensor::from_slice(&[t]).f_to_device(device)?.f_expand([input.size()[0]], false)?;
                let prediction = self
                    .transformer
                    .forward(
                        &TransformerInput {
                            hidden_states: &input,
                            encoder_hidden_states: &text,
                            timestep: &timestep,
                            ofs: None,
                            image_rotary_emb: rotary.as_ref(),
                        },
                        false,
                    )?
                    .f_to_kind(Kind::Float)?;
                let v = if guided {
                    let (uncond, conditioned) = (prediction.f_narrow(0, 0, 1)?, prediction.f_narrow(0, 1, 1)?);
                    uncond.f_add(&conditioned.f_sub(&uncond)?.f_mul_scalar(guidance)?)?
                } else {
                    prediction
                };
                let back = if i > 0 { Some(timesteps[i - 1]) } else { None };
                let out = scheduler.step(&v, old_pred.as_ref(), t, back, &latents)?;
                latents = out.prev_sample.f_to_kind(kind)?;
                old_pred = Some(out.pred_original_sample);
                progress(i + 1, timesteps.len());
            }
            timings.denoise = lap(device);
            // `1 / scaling_factor * latents`, as the pipeline writes it (not a division).
            let latent = latents.f_permute([0, 2, 1, 3, 4])?.f_mul_scalar(1.0 / scale)?;
            let video = self.vae.decode(&latent)?;
            timings.decode = lap(device);
            Ok(video)
        })
    }
}

/// The rotary table a CogVideoX pipeline builds for a latent grid (`grid_type="linspace"`): the
/// patch grid's positions cropped to the transformer's base grid (diffusers'
/// `get_resize_crop_region_for_grid`); none for a transformer without rotary positions.
pub fn pipeline_rotary(
    config: &CogVideoXTransformer3DModelConfig,
    frames: i64,
    height: i64,
    width: i64,
    device: Device,
) -> Result<Option<RotaryEmbedding>> {
    if !config.use_rotary_positional_embeddings {
        return Ok(None);
    }
    let p = config.patch_size;
    let (grid_h, grid_w) = (height / p, width / p);
    let (base_h, base_w) = (config.sample_height / p, config.sample_width / p);
    // Fit the grid's aspect into the base grid, centred.
    let (resize_h, resize_w) = if grid_h as f64 / grid_w as f64 > base_h as f64 / base_w as f64 {
        (base_h, (base_h as f64 / grid_h as f64 * grid_w as f64).round_ties_even() as i64)
    } else {
        ((base_w as f64 / grid_w as f64 * grid_h as f64).round_ties_even() as i64, base_w)
    };
    let top = ((base_h - resize_h) as f64 / 2.0).round_ties_even() as i64;
    let left = ((base_w - resize_w) as f64 / 2.0).round_ties_even() as i64;
    let axis = |start: i64, stop: i64, n: i64| -> Result<Tensor> {
        let end = stop as f64 * (n - 1) as f64 / n as f64;
        Ok(Tensor::f_linspace(start as f64, end, n, (Kind::Float, device))?)
    };
    let t =
        Tensor::f_linspace(0.0, frames as f64 * (frames - 1) as f64 / frames as f64, frames, (Kind::Float, device))?;
    let t = if config.patch_size_t.is_some() { Tensor::f_arange(frames, (Kind::Float, device))? } else { t };
    let y = axis(top, top + resize_h, grid_h)?;
    let x = axis(left, left + resize_w, grid_w)?;
    Ok(Some(RotaryEmbedding::from_positions(config.attention_head_dim, &t, &y, &x)?))
}

/// Generates a video `[1, 3, F, H, W]` in [-1, 1] for a conditioning video of the same shape with
/// CogVideoX-5B's schedule, as [`CogNvsPipeline::generate`] does, drawing from tch's global
/// generator as it stands (the training loop's validation samples seed it themselves). The
/// models run in their weights' element type.
pub fn generate(
    model: &CogVideoXTransformer3DModel,
    vae_model: &AutoencoderKLCogVideoX,
    condition: &Tensor,
    text: &Tensor,
    negative: Option<&Tensor>,
    steps: usize,
    guidance: f64,
) -> Result<Tensor> {
    let scheduler = scheduler_config(None)?;
    Denoiser { transformer: model, vae: vae_model, scheduler: &scheduler }.run(
        condition,
        text,
        negative,
        steps,
        guidance,
        &mut |_, _| {},
        &mut Timings::default(),
    )
}

/// The frames of a video tensor `[1, 3, F, H, W]` in [-1, 1] (see
/// [`video_processor::video_to_frames`]).
pub fn to_frames(video: &Tensor) -> Result<Vec<RgbImage>> {
    video_processor::video_to_frames(video)
}

/// How a conditioning becomes the model's input and the result the user's output.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Framing {
    /// Frames sampled: the first this many, 1 + 4k (fewer when the input is shorter: see
    /// [`video_processor::take_frames`]).
    pub frames: usize,
    /// How frames of another size reach the model's size.
    pub resize: ResizeMode,
    /// The model's input size (width, height); None: the transformer's own.
    pub size: Option<(u32, u32)>,
    /// Resize the result back to the conditioning's size (the demo does).
    pub restore_size: bool,
    /// Frame rate of an mp4 output (the demo writes 10 fps).
    pub fps: f64,
}

impl Default for Framing {
    /// The public demo's: 49 frames, area resize to the model's size, back to the input's size,
    /// 10 fps.
    fn default() -> Self {
        Self { frames: DEMO_FRAMES, resize: ResizeMode::Area, size: None, restore_size: true, fps: DEMO_FPS }
    }
}

impl Framing {
    /// What the Wan pipeline checks of the framing.
    pub fn wan(&self) -> WanFraming {
        WanFraming { frames: self.frames, size: self.size, fps: self.fps }
    }
}

/// Frames the public demo samples.
pub const DEMO_FRAMES: usize = 49;
/// Frame rate the public demo writes.
pub const DEMO_FPS: f64 = 10.0;

/// A conditioning ready for [`CogNvsPipeline::generate`].
#[derive(Debug)]
pub struct PreparedCondition {
    /// The frames at the model's size.
    pub frames: Vec<RgbImage>,
    /// The input's own frame size.
    pub source_size: (u32, u32),
    /// The input frames that were used, at their own size.
    pub used: usize,
    /// The input's frames.
    pub available: usize,
}

/// Reads a conditioning (a `datagen render` folder, a frame folder or a video) and brings it to
/// the pipeline's input as `framing` says. Errors name the input.
pub fn prepare_condition(path: &Path, pipeline: &CogNvsPipeline, framing: &Framing) -> Result<PreparedCondition> {
    let size = check_framing(pipeline.transformer_config(), pipeline.vae_config(), framing)?;
    let temporal = pipeline.vae_config().effective_temporal_compression_ratio() as usize;
    prepare_condition_at(path, size, temporal, framing)
}

/// [`prepare_condition`] at the model input `size` for a VAE compressing time `temporal`×.
fn prepare_condition_at(
    path: &Path,
    size: (u32, u32),
    temporal: usize,
    framing: &Framing,
) -> Result<PreparedCondition> {
    let named = read_condition_named(path)?;
    let source_size = named.uniform_size()?;
    let used = video_processor::take_frames(named.frames.len(), framing.frames, temporal).ok_or_else(|| {
        Error::InvalidInput { path: path.to_path_buf(), what: "frames".to_string(), reason: "no frame".to_string() }
    })?;
    if used > crate::pipelines::video_processor::MAX_FRAMES
        || source_size.0 > crate::pipelines::video_processor::MAX_SIDE
        || source_size.1 > crate::pipelines::video_processor::MAX_SIDE
    {
        return Err(Error::InvalidInput {
            path: path.to_path_buf(),
            what: "video size".to_string(),
            reason: format!(
                "{used} frames of {}x{}: at most {} frames of {} pixels a side",
                source_size.0,
                source_size.1,
                crate::pipelines::video_processor::MAX_FRAMES,
                crate::pipelines::video_processor::MAX_SIDE
            ),
        });
    }
    let frames = named.frames[..used].iter().map(|f| video_processor::fit(f, size.0, size.1, framing.resize)).collect();
    Ok(PreparedCondition { frames, source_size, used, available: named.frames.len() })
}

/// Reads the conditioning frames: a `datagen render` folder (`frames/`), a frame folder or a video.
pub fn read_condition_named(path: &Path) -> Result<crate::eval::metrics::NamedFrames> {
    let folder = if path.is_dir() && path.join("frames").is_dir() { path.join("frames") } else { path.to_path_buf() };
    crate::eval::metrics::read_named_frames(&folder)
}

/// The user's frames from a sampled video: back at the conditioning's size when `framing` asks
/// (OpenCV's default linear resize, as the demo does).
pub fn finish_frames(video: &Tensor, condition: &PreparedCondition, framing: &Framing) -> Result<Vec<RgbImage>> {
    let frames = video_processor::video_to_frames(video)?;
    let (w, h) = condition.source_size;
    Ok(if framing.restore_size && frames.first().is_some_and(|f| f.dimensions() != (w, h)) {
        frames.iter().map(|f| video_processor::resize_linear(f, w, h)).collect()
    } else {
        frames
    })
}

/// The checked models of either family: where sampling picks the family (the transformer
/// folder's `_class_name`) and every job after it follows.
#[derive(Debug)]
pub enum Checked {
    /// A CogVideoX model: [`CogNvsPipeline`].
    CogVideoX(Box<CheckedModels>),
    /// A Wan model: [`WanNvsPipeline`].
    Wan(Box<WanCheckedModels>),
}

impl Checked {
    /// Reads and checks the models `paths` names for their family (see [`CheckedModels::read`],
    /// [`WanCheckedModels::read`]); the VAE must be of the transformer's family.
    pub fn read(paths: &ModelPaths, device: Device) -> Result<Self> {
        let family = ModelFamily::of_transformer(&paths.transformer)?.require(Job::Sampling, &paths.transformer)?;
        let vae_family = ModelFamily::of_vae(&paths.vae)?;
        if vae_family != family {
            return Err(Error::InvalidConfig {
                source_name: paths.vae.join("config.json").display().to_string(),
                field: "_class_name".to_string(),
                reason: format!(
                    "is a {} VAE; the transformer {} is a {} model",
                    vae_family.name(),
                    paths.transformer.display(),
                    family.name()
                ),
            });
        }
        Ok(match family {
            ModelFamily::CogVideoX => Self::CogVideoX(Box::new(CheckedModels::read(paths, device)?)),
            ModelFamily::Wan => Self::Wan(Box::new(WanCheckedModels::read(paths, device)?)),
        })
    }

    /// Refuses sampling arguments these models cannot take, naming the flag.
    pub fn check_sampling(&self, steps_flag: &str, steps: usize, guidance: f64, framing: &Framing) -> Result<()> {
        match self {
            Self::CogVideoX(c) => c.check_sampling(steps_flag, steps, guidance, framing),
            Self::Wan(c) => c.check_sampling(steps_flag, steps, guidance, framing.wan()),
        }
    }
}

/// A loaded sampling pipeline of either family.
#[derive(Debug)]
pub enum Pipeline {
    /// CogVideoX: the public CogNVS pipeline.
    CogVideoX(Box<CogNvsPipeline>),
    /// Wan: [`crate::pipelines::pipeline_wan`] with the render and hole-mask conditioning.
    Wan(Box<WanNvsPipeline>),
}

/// What [`Pipeline::sample`] produced for one conditioning.
#[derive(Debug)]
pub struct Sampled {
    /// The user's frames (see [`finish_frames`]).
    pub frames: Vec<RgbImage>,
    /// The conditioning as the model took it.
    pub condition: PreparedCondition,
    /// Seconds of generation (encode, denoising, decode).
    pub seconds: f64,
    /// Seconds of each part.
    pub timings: Timings,
}

impl Pipeline {
    /// Checks every config and header (see [`Checked::read`]), then builds and loads the models.
    pub fn load(paths: &ModelPaths, options: LoadOptions) -> Result<Self> {
        Self::load_checked(paths, Checked::read(paths, options.device)?, options)
    }

    /// [`Self::load`] with the configs and small files read already.
    pub fn load_checked(paths: &ModelPaths, checked: Checked, options: LoadOptions) -> Result<Self> {
        Ok(match checked {
            Checked::CogVideoX(c) => Self::CogVideoX(Box::new(CogNvsPipeline::load_checked(paths, *c, options)?)),
            Checked::Wan(c) => {
                let kind = options.precision.kind(options.device);
                Self::Wan(Box::new(WanNvsPipeline::load_checked(paths, *c, options.device, kind)?))
            }
        })
    }

    /// Samples the conditioning at `path` (a `datagen render` folder, a frame folder or a video;
    /// Wan needs the render folder's `holes/`) as `framing` says, on `device`, every draw from
    /// tch's generator reseeded with `seed`; `progress` hears the denoising steps.
    #[allow(clippy::too_many_arguments)]
    pub fn sample(
        &self,
        path: &Path,
        framing: &Framing,
        steps: usize,
        guidance: f64,
        seed: u64,
        device: Device,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<Sampled> {
        let (condition, started, (output, timings)) = match self {
            Self::CogVideoX(pipeline) => {
                let condition = prepare_condition(path, pipeline, framing)?;
                let video = video_processor::frames_to_video(&condition.frames, pipeline.kind(), device)?;
                let started = Instant::now();
                let sampled = pipeline.generate_timed(&video, steps, guidance, seed, progress)?;
                (condition, started, sampled)
            }
            Self::Wan(pipeline) => {
                let size = pipeline.framing_size(framing.wan())?;
                let condition = prepare_condition_at(path, size, pipeline.temporal_factor(), framing)?;
                let mask = hole_mask(path, &condition, size, framing, device)?;
                let video = video_processor::frames_to_video(&condition.frames, pipeline.kind(), device)?;
                let started = Instant::now();
                let (sampled, seconds) = pipeline.generate_timed(&video, &mask, steps, guidance, seed, progress)?;
                // The Wan sampler is timed as a whole.
                (condition, started, (sampled, Timings { denoise: seconds, ..Timings::default() }))
            }
        };
        let seconds = started.elapsed().as_secs_f64();
        let frames = finish_frames(&output, &condition, framing)?;
        Ok(Sampled { frames, condition, seconds, timings })
    }
}

/// The folder of a render's hole masks (`datagen render`'s `holes/%05d.png`, 255 a hole).
pub const HOLES_DIR: &str = "holes";

/// The known-pixel mask `[1, 1, F, H, W]` (f32, 1 known) of the render at `path` for the frames
/// `condition` used, brought to the model's `size` as its frames were: a pixel is known only
/// where no hole reaches it after the resize.
pub fn hole_mask(
    path: &Path,
    condition: &PreparedCondition,
    size: (u32, u32),
    framing: &Framing,
    device: Device,
) -> Result<Tensor> {
    let folder = path.join(HOLES_DIR);
    if !folder.is_dir() {
        return Err(Error::InvalidInput {
            path: path.to_path_buf(),
            what: "hole masks".to_string(),
            reason: format!(
                "a Wan model samples with the render's hole mask: no `{HOLES_DIR}/` folder here (pass a `datagen render` folder)"
            ),
        });
    }
    let holes = crate::eval::metrics::read_named_frames(&folder)?;
    if holes.frames.len() < condition.used || holes.uniform_size()? != condition.source_size {
        return Err(Error::InvalidInput {
            path: folder,
            what: "hole masks".to_string(),
            reason: format!(
                "{} masks of {:?} for {} frames of {:?}",
                holes.frames.len(),
                holes.uniform_size()?,
                condition.used,
                condition.source_size
            ),
        });
    }
    let (width, height) = size;
    let mut known = Vec::with_capacity(condition.used * (width * height) as usize);
    for frame in &holes.frames[..condition.used] {
        let fitted = video_processor::fit(frame, width, height, framing.resize);
        known.extend(fitted.pixels().map(|p| if p.0 == [0, 0, 0] { 1.0f32 } else { 0.0 }));
    }
    let shape = [1, 1, condition.used as i64, i64::from(height), i64::from(width)];
    Ok(Tensor::from_slice(&known).f_view(shape)?.f_to_device(device)?)
}

/// What to sample with `trainer sample`.
#[derive(Debug, Clone)]
pub struct SampleRequest {
    /// The models.
    pub model: ModelSource,
    /// The conditioning: a `datagen render` folder (its `frames/`), a folder of frames, or a video.
    pub condition: PathBuf,
    /// Output: an `.mp4` file (H.264), or any other path: a folder of lossless PNG frames
    /// (`00000.png`, …), bit-for-bit the sampled frames.
    pub out: PathBuf,
    /// Denoising steps.
    pub steps: usize,
    /// Classifier-free guidance scale.
    pub guidance: f64,
    /// Seed of every draw.
    pub seed: u64,
    /// Device, arithmetic and VAE tiling.
    pub load: LoadOptions,
    /// Frames, sizes and frame rate.
    pub framing: Framing,
}

/// What sampling produced.
#[derive(Debug, Clone)]
pub struct SampleReport {
    /// Frames written.
    pub frames: usize,
    /// The model's input size.
    pub model_size: (u32, u32),
    /// The size written.
    pub size: (u32, u32),
    /// The conditioning's own size.
    pub source_size: (u32, u32),
    /// The conditioning's frames, of which `frames` were sampled.
    pub source_frames: usize,
    /// Seconds of generation (encode, denoising, decode).
    pub seconds: f64,
    /// Seconds of each part.
    pub timings: Timings,
    /// On CUDA: the caching allocator's peak bytes (allocated, reserved) over the whole command.
    pub cuda_peaks: Option<(u64, u64)>,
}

/// `trainer sample`: loads the pipeline, prepares the conditioning, samples and writes the
/// frames. Configs, headers, text embeddings and the conditioning are checked before a model is
/// built.
pub fn sample(
    request: &SampleRequest,
    paths: &ModelPaths,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<SampleReport> {
    read_condition_named(&request.condition)?.uniform_size()?;
    let checked = Checked::read(paths, request.load.device)?;
    checked.check_sampling("steps", request.steps, request.guidance, &request.framing)?;
    let pipeline = Pipeline::load_checked(paths, checked, request.load)?;
    let Sampled { frames: images, condition, seconds, timings } = pipeline.sample(
        &request.condition,
        &request.framing,
        request.steps,
        request.guidance,
        request.seed,
        request.load.device,
        progress,
    )?;
    let cuda_peaks = match request.load.device {
        Device::Cuda(index) => crate::distributed::cuda_memory_peaks(index, false),
        _ => None,
    };
    write_frames(&request.out, &images, request.framing.fps)?;
    Ok(SampleReport {
        frames: images.len(),
        model_size: condition.frames[0].dimensions(),
        size: images[0].dimensions(),
        source_size: condition.source_size,
        source_frames: condition.available,
        seconds,
        timings,
        cuda_peaks,
    })
}

/// Writes sampled frames to `out`: an H.264 video when it ends in `.mp4`, else a folder of PNG
/// frames. The PNG folder holds exactly the sampled pixels; the video does not, and on this
/// toolkit's machines FFmpeg's encoder gave slightly different streams for the same frames
/// from run to run inside the trainer process (a read of uninitialised memory: runs under
/// glibc's `MALLOC_PERTURB_` repeat exactly), so comparisons belong on the PNG frames.
pub fn write_frames(out: &Path, images: &[RgbImage], fps: f64) -> Result<()> {
    let is_video = out.extension().is_some_and(|e| e.eq_ignore_ascii_case("mp4"));
    let folder = if is_video { out.parent().filter(|p| !p.as_os_str().is_empty()) } else { Some(out) };
    if let Some(folder) = folder {
        std::fs::create_dir_all(folder).map_err(|source| Error::Io { path: folder.to_path_buf(), error: source })?;
    }
    if is_video {
        foundation::video::encode_video(out, images, fps)?;
        return Ok(());
    }
    for (i, image) in images.iter().enumerate() {
        let path = out.join(format!("{i:05}.png"));
        image.save(&path).map_err(|e| Error::InvalidInput {
            path: path.clone(),
            what: "frame".to_string(),
            reason: format!("cannot write PNG: {e}"),
        })?;
    }
    Ok(())
}

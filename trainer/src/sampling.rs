//! Sampling a novel-view video (DESIGN §1, §6): the conditioning render (`datagen render` output
//! or a video) is VAE-encoded (posterior mean × `scaling_factor`), concatenated on channels with
//! the noisy latent, and denoised with CogVideoX's DPM scheduler (50 steps by default), with
//! classifier-free guidance between the prompt and the negative-prompt text embeddings; the
//! result is VAE-decoded and written as an H.264 mp4.
//!
//! CogNVS prompts with the empty string on both sides, so the two guidance branches are the same
//! and guidance changes nothing; the second branch is then skipped. Give a
//! `negative_text_embedding` to guide against another prompt.
//!
//! Models come from a checkpoint folder: `transformer/` (diffusers layout) inside it, or the folder
//! itself; the VAE from `--vae`, `CKPT/vae/` or the run folder's `vae/` (`CKPT/../../vae`); the
//! text embedding from the run's `config.json` when it names one, else zeros. All draws come from
//! tch's generator seeded with `seed`: the same seed gives the same video.

use std::path::{Path, PathBuf};
use std::time::Instant;

use image::RgbImage;
use tch::{Device, Kind, Tensor};

use crate::autoencoder_kl_cogvideox::{self as vae, AutoencoderKLCogVideoX, AutoencoderKLCogVideoXConfig};
use crate::cogvideox_transformer_3d::{
    self as transformer, CogVideoXTransformer3DModel, CogVideoXTransformer3DModelConfig, TransformerInput,
};
use crate::diffusers_config::DiffusersConfig;
use crate::error::{Error, Result};
use crate::scheduling_cogvideox_dpm::CogVideoXDPMScheduler;
use crate::scheduling_ddim::CogVideoXSchedulerConfig;
use crate::weights;

/// What to sample.
#[derive(Debug, Clone)]
pub struct SampleRequest {
    /// A checkpoint folder (with `transformer/`, or a LoRA run's with
    /// `pytorch_lora_weights.safetensors`) or a transformer model folder.
    pub checkpoint: PathBuf,
    /// A LoRA file merged into the checkpoint's transformer before sampling (a base plus an
    /// adapter); a LoRA checkpoint brings its own.
    pub lora: Option<PathBuf>,
    /// The VAE folder (default: found next to the checkpoint, see the module docs).
    pub vae: Option<PathBuf>,
    /// Text embedding `encoder_hidden_states` `[S, D]` (default: the run's, else zeros).
    pub text_embedding: Option<PathBuf>,
    /// Negative text embedding for guidance (default: the same as the prompt's).
    pub negative_text_embedding: Option<PathBuf>,
    /// The conditioning: a `datagen render` folder (its `frames/`), a folder of frames, or a video.
    pub condition: PathBuf,
    /// Output: an `.mp4` file (H.264), or any other path: a folder of lossless PNG frames
    /// (`00000.png`, …), bit-for-bit the sampled frames.
    pub out: PathBuf,
    /// Denoising steps.
    pub steps: usize,
    /// Classifier-free guidance scale.
    pub guidance: f64,
    /// Seed of the initial noise and of the sampler's noise.
    pub seed: u64,
    /// Compute device.
    pub device: Device,
}

/// What sampling produced.
#[derive(Debug, Clone)]
pub struct SampleReport {
    /// Frames written.
    pub frames: usize,
    /// Frame size.
    pub size: (u32, u32),
    /// Seconds of the denoising loop.
    pub seconds: f64,
    /// The conditioning's own frame size when it was resized to `size` (see [`fit_condition`]).
    pub resized_from: Option<(u32, u32)>,
}

/// A conditioning brought to a size the model takes.
#[derive(Debug, Clone)]
pub struct FittedCondition {
    /// The frames, all of `size`.
    pub frames: Vec<RgbImage>,
    /// Their size.
    pub size: (u32, u32),
    /// The size they had when they were resized.
    pub resized_from: Option<(u32, u32)>,
}

/// Brings conditioning frames to a size the model takes, the way the training loader brings
/// pairs to the training resolution ([`crate::data::cover_crop`]: scale to cover, centre crop):
/// to the learned positional table's size when the transformer has one, else to the largest
/// multiple of the VAE's spatial compression × the patch size that fits. Frames must share one
/// size (an error names the first that differs) and number 1 + r·k for the VAE's temporal
/// compression r (an error names the input).
pub fn fit_condition(
    condition: &crate::metrics::NamedFrames,
    input: &Path,
    config: &CogVideoXTransformer3DModelConfig,
    vae_config: &AutoencoderKLCogVideoXConfig,
) -> Result<FittedCondition> {
    let (width, height) = condition.uniform_size()?;
    let temporal = vae_config.effective_temporal_compression_ratio() as usize;
    let count = condition.frames.len();
    if count == 0 || count > crate::data::MAX_FRAMES || !(count - 1).is_multiple_of(temporal) {
        return Err(Error::InvalidInput {
            path: input.to_path_buf(),
            what: "frame count".to_string(),
            reason: format!(
                "{count} frames: the VAE needs {temporal}k + 1 frames (at most {})",
                crate::data::MAX_FRAMES
            ),
        });
    }
    let spatial = vae_config.spatial_compression_ratio();
    let multiple = (spatial * config.patch_size) as u32;
    let target = if config.use_learned_positional_embeddings {
        ((config.sample_width * spatial) as u32, (config.sample_height * spatial) as u32)
    } else {
        (width - width % multiple, height - height % multiple)
    };
    if target.0 == 0 || target.1 == 0 || width > crate::data::MAX_SIDE || height > crate::data::MAX_SIDE {
        return Err(Error::InvalidInput {
            path: input.to_path_buf(),
            what: "frame size".to_string(),
            reason: format!(
                "{width}x{height}: frames must be at least {multiple} and at most {} pixels a side",
                crate::data::MAX_SIDE
            ),
        });
    }
    if target == (width, height) {
        return Ok(FittedCondition { frames: condition.frames.clone(), size: target, resized_from: None });
    }
    let frames = condition
        .frames
        .iter()
        .map(|f| crate::data::cover_crop(f, target.0, target.1, image::imageops::FilterType::Triangle))
        .collect();
    Ok(FittedCondition { frames, size: target, resized_from: Some((width, height)) })
}

/// Reads the conditioning frames: a `datagen render` folder (`frames/`), a frame folder or a video.
pub fn read_condition(path: &Path) -> Result<(Vec<RgbImage>, f64)> {
    let named = read_condition_named(path)?;
    Ok((named.frames, named.fps))
}

/// [`read_condition`] keeping each frame's file, for messages.
pub fn read_condition_named(path: &Path) -> Result<crate::metrics::NamedFrames> {
    let folder = if path.is_dir() && path.join("frames").is_dir() { path.join("frames") } else { path.to_path_buf() };
    crate::metrics::read_named_frames(&folder)
}

/// The VAE folder of a checkpoint: `explicit`, `CKPT/vae` or the run's `vae/`.
pub fn find_vae(checkpoint: &Path, explicit: Option<&Path>) -> Result<PathBuf> {
    if let Some(v) = explicit {
        return Ok(v.to_path_buf());
    }
    let candidates = [checkpoint.join("vae"), checkpoint.join("../../vae")];
    candidates.iter().find(|c| c.join("config.json").is_file()).cloned().ok_or_else(|| Error::InvalidArgument {
        name: "vae".to_string(),
        reason: format!(
            "no VAE given and none at {} or {}; pass --vae",
            candidates[0].display(),
            candidates[1].display()
        ),
    })
}

/// The transformer folder of a checkpoint (`CKPT/transformer`) or the folder itself.
pub fn transformer_dir(checkpoint: &Path) -> PathBuf {
    let inner = checkpoint.join("transformer");
    if inner.join("config.json").is_file() { inner } else { checkpoint.to_path_buf() }
}

/// The text embedding named in the run's `config.json` (`model.text_embedding`), if any. A
/// run config that exists but is not JSON, or whose key is not a path, is an error naming it.
fn run_text_embedding(checkpoint: &Path) -> Result<Option<PathBuf>> {
    let path = checkpoint.join("../../config.json");
    let Ok(text) = std::fs::read_to_string(&path) else { return Ok(None) };
    let bad = |field: &str, reason: String| Error::InvalidConfig {
        source_name: path.display().to_string(),
        field: field.to_string(),
        reason,
    };
    let json: serde_json::Value = serde_json::from_str(&text).map_err(|e| bad("(json)", e.to_string()))?;
    match json.get("model").and_then(|m| m.get("text_embedding")) {
        None | Some(serde_json::Value::Null) => Ok(None),
        Some(serde_json::Value::String(p)) => Ok(Some(PathBuf::from(p))),
        Some(other) => Err(bad("model.text_embedding", format!("{other} is not a path string"))),
    }
}

/// The text embedding `[1, S, D]` from a safetensors file's `encoder_hidden_states` `[S, D]`
/// (shape checked against the transformer config), or zeros without a file.
pub fn load_text_embedding(
    path: Option<&Path>,
    config: &CogVideoXTransformer3DModelConfig,
    device: Device,
) -> Result<Tensor> {
    let shape = [config.max_text_seq_length, config.text_embed_dim];
    match path {
        None => Ok(Tensor::f_zeros([1, shape[0], shape[1]], (Kind::Float, device))?),
        Some(path) => {
            let tensor = weights::read_safetensors(path)?.remove("encoder_hidden_states").ok_or_else(|| {
                Error::MissingTensor {
                    path: path.to_path_buf(),
                    tensor: "encoder_hidden_states".to_string(),
                    expected: shape.to_vec(),
                }
            })?;
            weights::check_floating(path, "encoder_hidden_states", &tensor)?;
            weights::check_shape(&format!("encoder_hidden_states` in `{}", path.display()), &tensor, &shape)?;
            Ok(tensor.f_to_kind(Kind::Float)?.f_to_device(device)?.f_unsqueeze(0)?)
        }
    }
}

/// Samples the novel-view video and writes it to `request.out`. Configs, checkpoint headers,
/// text embeddings and the conditioning are all checked before a model is built; a
/// conditioning of another size than the model takes is resized as the training loader does
/// (see [`fit_condition`]).
pub fn sample(request: &SampleRequest) -> Result<SampleReport> {
    let device = request.device;
    let timesteps = CogVideoXSchedulerConfig::cogvideox_5b().num_train_timesteps;
    if request.steps == 0 || request.steps as i64 > timesteps {
        return Err(Error::InvalidArgument {
            name: "steps".to_string(),
            reason: format!("{} must be in 1..={timesteps} (the scheduler's training timesteps)", request.steps),
        });
    }
    if !request.guidance.is_finite() {
        return Err(Error::InvalidArgument {
            name: "guidance".to_string(),
            reason: format!("{} must be finite", request.guidance),
        });
    }
    let (transformer_path, lora_files) = match crate::lora::lora_checkpoint(&request.checkpoint)? {
        Some((base, file)) => (base, [Some(file), request.lora.clone()]),
        None => (transformer_dir(&request.checkpoint), [None, request.lora.clone()]),
    };
    // Adapters are read and checked before any model is built.
    let adapters = lora_files
        .into_iter()
        .flatten()
        .map(|file| Ok((crate::lora::LoraFile::read(&file)?, file)))
        .collect::<Result<Vec<_>>>()?;
    let config = CogVideoXTransformer3DModelConfig::from_json_file(&transformer_path)?;
    weights::check_against(
        &transformer::variable_shapes(&config)?,
        &weights::read_checkpoint_info(&transformer_path)?,
        &transformer_path,
    )?;
    let vae_path = find_vae(&request.checkpoint, request.vae.as_deref())?;
    let vae_config = AutoencoderKLCogVideoXConfig::from_json_file(&vae_path)?;
    weights::read_checkpoint_info(&vae_path)?;
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
    let prompt_path = match &request.text_embedding {
        Some(p) => Some(p.clone()),
        None => run_text_embedding(&request.checkpoint)?,
    };
    let text = load_text_embedding(prompt_path.as_deref(), &config, device)?;
    let negative = match &request.negative_text_embedding {
        Some(path) => load_text_embedding(Some(path), &config, device)?,
        None => text.shallow_clone(),
    };
    let guided = request.guidance > 1.0 && !text.equal(&negative);

    let condition = read_condition_named(&request.condition)?;
    let fps = condition.fps;
    let fitted = fit_condition(&condition, &request.condition, &config, &vae_config)?;
    let (width, height) = fitted.size;
    if let Some((w, h)) = fitted.resized_from {
        // Said before the long denoising loop, as a log line the user can act on.
        eprintln!(
            "note: {}: resized the conditioning from {w}x{h} to {width}x{height} (scaled to cover, centre-cropped, \
             as the training loader does) for this model",
            request.condition.display()
        );
    }
    let (frames, resized_from) = (fitted.frames, fitted.resized_from);

    let (vs, model) = transformer::build(&config, device, Kind::Float)?;
    weights::load(&vs, &transformer_path)?;
    for (adapter, file) in &adapters {
        adapter.merge_into(&vs, file)?;
    }
    let (vae_vs, vae_model) = vae::build(&vae_config, device, Kind::Float)?;
    weights::load(&vae_vs, &vae_path)?;

    let (f, h, w) = (frames.len() as i64, i64::from(height), i64::from(width));
    let bytes: Vec<u8> = frames.iter().flat_map(|fr| fr.as_raw().iter().copied()).collect();
    let video = Tensor::from_slice(&bytes)
        .f_view([1, f, h, w, 3])?
        .f_permute([0, 4, 1, 2, 3])?
        .f_to_kind(Kind::Float)?
        .f_div_scalar(127.5)?
        .f_sub_scalar(1.0)?
        .f_to_device(device)?;

    tch::manual_seed(request.seed as i64);
    let started = Instant::now();
    let negative = guided.then_some(&negative);
    let output = generate(&model, &vae_model, &video, &text, negative, request.steps, request.guidance)?;
    let seconds = started.elapsed().as_secs_f64();
    let images = to_frames(&output)?;
    let frames_out = images.len();
    write_frames(&request.out, &images, if fps > 0.0 { fps } else { DEFAULT_FPS })?;
    Ok(SampleReport { frames: frames_out, size: (width, height), seconds, resized_from })
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
        datagen::video::encode_video(out, images, fps)?;
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

/// Generates a video `[1, 3, F, H, W]` in [-1, 1] for a conditioning video of the same shape:
/// encode, DPM denoising with guidance against `negative` (when given), decode. Draws from tch's
/// global generator. The models run in their weights' element type (the transformer's must be
/// the VAE's); the scheduler and the returned video are fp32.
pub fn generate(
    model: &CogVideoXTransformer3DModel,
    vae_model: &AutoencoderKLCogVideoX,
    condition: &Tensor,
    text: &Tensor,
    negative: Option<&Tensor>,
    steps: usize,
    guidance: f64,
) -> Result<Tensor> {
    let config = model.config();
    let device = text.device();
    tch::no_grad(|| -> Result<Tensor> {
        let scale = vae_model.config().scaling_factor;
        let kind = vae_model.kind();
        let cond = vae_model
            .encode(&condition.f_to_kind(kind)?)?
            .f_mul_scalar(scale)?
            .f_permute([0, 2, 1, 3, 4])?
            .f_contiguous()?;
        let mut latents =
            cond.f_randn_like()?.f_narrow(2, 0, config.output_channels())?.f_to_kind(Kind::Float)?.f_contiguous()?;
        let (text, negative) = (text.f_to_kind(kind)?, negative.map(|n| n.f_to_kind(kind)).transpose()?);
        let mut scheduler = CogVideoXDPMScheduler::new(&CogVideoXSchedulerConfig::cogvideox_5b())?;
        scheduler.set_timesteps(steps)?;
        let timesteps = scheduler.timesteps().to_vec();
        let mut old_pred: Option<Tensor> = None;
        for (i, &t) in timesteps.iter().enumerate() {
            let input = Tensor::f_cat(&[&latents.f_to_kind(kind)?, &cond], 2)?;
            let timestep = Tensor::from_slice(&[t]).f_to_device(device)?;
            let run = |text: &Tensor| {
                model.forward(
                    &TransformerInput {
                        hidden_states: &input,
                        encoder_hidden_states: text,
                        timestep: &timestep,
                        ofs: None,
                        image_rotary_emb: None,
                    },
                    false,
                )
            };
            let mut v = run(&text)?.f_to_kind(Kind::Float)?;
            if let Some(negative) = &negative {
                let v_uncond = run(negative)?.f_to_kind(Kind::Float)?;
                v = v_uncond.f_add(&v.f_sub(&v_uncond)?.f_mul_scalar(guidance)?)?;
            }
            let back = if i > 0 { Some(timesteps[i - 1]) } else { None };
            let out = scheduler.step(&v, old_pred.as_ref(), t, back, &latents)?;
            latents = out.prev_sample;
            old_pred = Some(out.pred_original_sample);
        }
        let latent = latents.f_permute([0, 2, 1, 3, 4])?.f_div_scalar(scale)?.f_to_kind(kind)?;
        Ok(vae_model.decode(&latent)?.f_to_kind(Kind::Float)?)
    })
}

/// The frames of a video tensor `[1, 3, F, H, W]` in [-1, 1].
pub fn to_frames(video: &Tensor) -> Result<Vec<RgbImage>> {
    let size = video.size();
    let (height, width) = (size[3], size[4]);
    let pixels = video
        .f_squeeze_dim(0)?
        .f_permute([1, 2, 3, 0])?
        .f_add_scalar(1.0)?
        .f_mul_scalar(127.5)?
        .f_clamp(0.0, 255.0)?
        .f_round()?
        .f_to_kind(Kind::Uint8)?
        .f_to_device(Device::Cpu)?
        .f_contiguous()?;
    let data: Vec<u8> = Vec::<u8>::try_from(pixels.f_flatten(0, -1)?)?;
    Ok(data
        .chunks((width * height * 3) as usize)
        .map(|chunk| RgbImage::from_raw(width as u32, height as u32, chunk.to_vec()).expect("frame-sized chunk"))
        .collect())
}

/// Frame rate of the output when the conditioning has none (frame folders): CogVideoX's 8 fps.
const DEFAULT_FPS: f64 = 8.0;

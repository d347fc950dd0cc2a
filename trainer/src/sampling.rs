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
    /// A checkpoint folder (with `transformer/`) or a transformer model folder.
    pub checkpoint: PathBuf,
    /// The VAE folder (default: found next to the checkpoint, see the module docs).
    pub vae: Option<PathBuf>,
    /// Text embedding `encoder_hidden_states` `[S, D]` (default: the run's, else zeros).
    pub text_embedding: Option<PathBuf>,
    /// Negative text embedding for guidance (default: the same as the prompt's).
    pub negative_text_embedding: Option<PathBuf>,
    /// The conditioning: a `datagen render` folder (its `frames/`), a folder of frames, or a video.
    pub condition: PathBuf,
    /// Output mp4.
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
}

/// Reads the conditioning frames: a `datagen render` folder (`frames/`), a frame folder or a video.
pub fn read_condition(path: &Path) -> Result<(Vec<RgbImage>, f64)> {
    if path.is_file() {
        let video = datagen::video::decode_video(path)?;
        return Ok((video.frames, video.fps));
    }
    let folder = if path.join("frames").is_dir() { path.join("frames") } else { path.to_path_buf() };
    Ok((crate::metrics::read_frames(&folder)?, 0.0))
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

/// The text embedding named in the run's `config.json` (`model.text_embedding`), if any.
fn run_text_embedding(checkpoint: &Path) -> Option<PathBuf> {
    let text = std::fs::read_to_string(checkpoint.join("../../config.json")).ok()?;
    let json: serde_json::Value = serde_json::from_str(&text).ok()?;
    json["model"]["text_embedding"].as_str().map(PathBuf::from)
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
            let tensor = Tensor::read_safetensors(path)
                .map_err(|e| Error::Safetensors { path: path.to_path_buf(), reason: e.to_string() })?
                .into_iter()
                .find(|(n, _)| n == "encoder_hidden_states")
                .ok_or_else(|| Error::MissingTensor {
                    path: path.to_path_buf(),
                    tensor: "encoder_hidden_states".to_string(),
                    expected: shape.to_vec(),
                })?
                .1;
            weights::check_shape("encoder_hidden_states", &tensor, &shape)?;
            Ok(tensor.f_to_kind(Kind::Float)?.f_to_device(device)?.f_unsqueeze(0)?)
        }
    }
}

/// Samples the novel-view video and writes it to `request.out`.
pub fn sample(request: &SampleRequest) -> Result<SampleReport> {
    let device = request.device;
    let transformer_path = transformer_dir(&request.checkpoint);
    let config = CogVideoXTransformer3DModelConfig::from_json_file(&transformer_path)?;
    weights::check_against(
        &transformer::variable_shapes(&config)?,
        &weights::read_checkpoint_info(&transformer_path)?,
        &transformer_path,
    )?;
    let (vs, model) = transformer::build(&config, device, Kind::Float)?;
    weights::load(&vs, &transformer_path)?;
    let vae_path = find_vae(&request.checkpoint, request.vae.as_deref())?;
    let vae_config = AutoencoderKLCogVideoXConfig::from_json_file(&vae_path)?;
    let (vae_vs, vae_model) = vae::build(&vae_config, device, Kind::Float)?;
    weights::load(&vae_vs, &vae_path)?;
    let prompt_path = request.text_embedding.clone().or_else(|| run_text_embedding(&request.checkpoint));
    let text = load_text_embedding(prompt_path.as_deref(), &config, device)?;
    let negative = match &request.negative_text_embedding {
        Some(path) => load_text_embedding(Some(path), &config, device)?,
        None => text.shallow_clone(),
    };
    let guided = request.guidance > 1.0 && !text.equal(&negative);

    let (frames, fps) = read_condition(&request.condition)?;
    let (width, height) = frames.first().map(|f| f.dimensions()).unwrap_or((0, 0));
    let multiple = (vae_config.spatial_compression_ratio() * config.patch_size) as u32;
    let temporal = config.temporal_compression_ratio as usize;
    if frames.is_empty() || (frames.len() - 1) % temporal != 0 || width % multiple != 0 || height % multiple != 0 {
        return Err(Error::InvalidArgument {
            name: format!("cond {}", request.condition.display()),
            reason: format!(
                "{} frames of {width}x{height}: need {temporal}k + 1 frames with width and height multiples of {multiple}",
                frames.len()
            ),
        });
    }
    let (latent_w, latent_h) = (
        i64::from(width) / vae_config.spatial_compression_ratio(),
        i64::from(height) / vae_config.spatial_compression_ratio(),
    );
    if config.use_learned_positional_embeddings && (latent_w, latent_h) != (config.sample_width, config.sample_height) {
        let ratio = vae_config.spatial_compression_ratio();
        return Err(Error::InvalidArgument {
            name: format!("cond {}", request.condition.display()),
            reason: format!(
                "frames are {width}x{height}; this model's learned positional table needs {}x{}",
                config.sample_width * ratio,
                config.sample_height * ratio
            ),
        });
    }
    if frames.iter().any(|f| f.dimensions() != (width, height)) {
        return Err(Error::InvalidArgument {
            name: format!("cond {}", request.condition.display()),
            reason: "frames differ in size".to_string(),
        });
    }
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
    if let Some(parent) = request.out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|source| Error::Io { path: parent.to_path_buf(), source })?;
    }
    datagen::video::encode_video(&request.out, &images, if fps > 0.0 { fps } else { DEFAULT_FPS })?;
    Ok(SampleReport { frames: frames_out, size: (width, height), seconds })
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

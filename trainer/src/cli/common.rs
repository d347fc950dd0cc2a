//! Flag groups several commands share, defined once and taken in with `#[command(flatten)]`:
//! the compute device, where the models come from besides the checkpoint, how a conditioning is
//! sampled (with its dtype), the eval networks' weights, the sequence layout; and the progress
//! bars of the long commands.

use std::path::PathBuf;

use clap::{Args, ValueEnum};

use crate::loaders::ModelSource;
use crate::pipelines::sampling::{DEMO_FPS, DEMO_FRAMES, Framing, LoadOptions};
use crate::pipelines::video_processor::ResizeMode;
use crate::training::Precision;

/// The compute device (shared by `forward`, `pretrain`, `sample`, `finetune`, `nvs` and
/// `benchmark`).
#[derive(Debug, Args)]
pub struct DeviceArgs {
    /// Compute device: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

impl DeviceArgs {
    /// The device, checked to be usable here.
    pub fn usable(&self) -> crate::Result<tch::Device> {
        crate::precision::usable_device(&self.device)
    }
}

/// Where the models come from besides the checkpoint (shared by `sample`, `finetune`, `nvs` and
/// `benchmark`).
#[derive(Debug, Args)]
pub struct ModelArgs {
    /// A CogVideoX pipeline folder in CogVideoX-5B-I2V's layout (vae/, scheduler/, text_encoder/,
    /// tokenizer/, transformer/): the VAE and the scheduler config come from it when the
    /// checkpoint has none (the released CogNVS transformer is such a checkpoint).
    #[arg(long)]
    pub base_model: Option<PathBuf>,
    /// VAE folder [default: CKPT/vae, the run's vae/, or --base-model's vae/].
    #[arg(long)]
    pub vae: Option<PathBuf>,
    /// A LoRA file (pytorch_lora_weights.safetensors) merged into the checkpoint's transformer.
    #[arg(long)]
    pub lora: Option<PathBuf>,
    /// Text embedding safetensors (`encoder_hidden_states` [226, 4096] for the released models),
    /// made once with `scripts/encode_prompt.py` [default: the run's, else required for
    /// T5-XXL-shaped transformers].
    #[arg(long)]
    pub text_embedding: Option<PathBuf>,
    /// Use zeros as the text embedding, also for a transformer trained on T5-XXL text.
    #[arg(long, conflicts_with = "text_embedding")]
    pub zero_text_embedding: bool,
}

impl ModelArgs {
    /// The models of `checkpoint` with these flags.
    pub fn source(self, checkpoint: PathBuf) -> ModelSource {
        ModelSource {
            checkpoint,
            base_model: self.base_model,
            vae: self.vae,
            lora: self.lora,
            text_embedding: self.text_embedding,
            negative_text_embedding: None,
            zero_text_embedding: self.zero_text_embedding,
        }
    }
}

/// How a conditioning is sampled (shared by `sample`, `nvs` and `benchmark`); the defaults are
/// the public CogNVS demo's.
#[derive(Debug, Args)]
pub struct SamplingArgs {
    /// Classifier-free guidance scale (no effect when prompt and negative prompt are the same).
    #[arg(long, default_value_t = 6.0)]
    pub guidance: f64,
    /// Seed of every draw (the public pipeline's `torch.Generator(device).manual_seed(SEED)`).
    #[arg(long, default_value_t = 42)]
    pub seed: u64,
    /// Arithmetic: auto (bf16 on CUDA as the demo, fp32 on CPUs), fp32 or bf16.
    #[arg(long, value_enum, default_value_t = DtypeArg::Auto)]
    pub dtype: DtypeArg,
    /// Decode and encode without spatial VAE tiles (the demo tiles; tiles bound memory).
    #[arg(long)]
    pub no_vae_tiling: bool,
    /// Frames sampled: the first N of the conditioning (fewer when it is shorter: the most
    /// that make 1 + 4k).
    #[arg(long, default_value_t = DEMO_FRAMES)]
    pub frames: usize,
    /// How frames of another size reach the model's size: area (stretch with an area average,
    /// as the demo) or crop (scale to cover and crop the centre, as the training loader).
    #[arg(long, value_enum, default_value_t = ResizeArg::Area)]
    pub resize: ResizeArg,
    /// The model's input size WIDTHxHEIGHT [default: the transformer's own, 720x480 for CogNVS].
    #[arg(long, value_parser = parse_size)]
    pub size: Option<(u32, u32)>,
    /// Keep the model's size instead of resizing the result back to the conditioning's.
    #[arg(long)]
    pub keep_model_size: bool,
    /// Frame rate of mp4 outputs.
    #[arg(long, default_value_t = DEMO_FPS)]
    pub fps: f64,
}

impl SamplingArgs {
    /// Frames, sizes and frame rate.
    pub fn framing(&self) -> Framing {
        Framing {
            frames: self.frames,
            resize: match self.resize {
                ResizeArg::Area => ResizeMode::Area,
                ResizeArg::Crop => ResizeMode::Crop,
            },
            size: self.size,
            restore_size: !self.keep_model_size,
            fps: self.fps,
        }
    }

    /// Device, arithmetic and VAE tiling.
    pub fn load(&self, device: tch::Device) -> LoadOptions {
        LoadOptions { device, precision: self.dtype.precision(), vae_tiling: !self.no_vae_tiling }
    }
}

/// `--dtype` of sampling.
// The values are their own help: doc comments would add a list of them to `--help`.
#[allow(missing_docs)]
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum DtypeArg {
    Auto,
    Fp32,
    Bf16,
}

impl DtypeArg {
    /// The library's precision.
    pub fn precision(self) -> Precision {
        match self {
            Self::Auto => Precision::Auto,
            Self::Fp32 => Precision::Fp32,
            Self::Bf16 => Precision::Bf16,
        }
    }
}

/// `--resize` of sampling.
// The values are their own help: doc comments would add a list of them to `--help`.
#[allow(missing_docs)]
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum ResizeArg {
    Area,
    Crop,
}

/// An auto/on/off switch.
// The values are their own help: doc comments would add a list of them to `--help`.
#[allow(missing_docs)]
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum SwitchArg {
    Auto,
    On,
    Off,
}

impl SwitchArg {
    /// None for auto, else whether on.
    pub fn choice(self) -> Option<bool> {
        match self {
            Self::Auto => None,
            Self::On => Some(true),
            Self::Off => Some(false),
        }
    }
}

/// The eval networks' weights and KID's subsets (shared by `eval` and `benchmark`).
#[derive(Debug, Args)]
pub struct EvalWeightArgs {
    /// LPIPS weights (safetensors from `scripts/convert_eval_weights.py lpips`) [default: no
    /// LPIPS].
    #[arg(long)]
    pub lpips_weights: Option<PathBuf>,
    /// LPIPS backbone of --lpips-weights.
    #[arg(long, value_enum, default_value = "alex")]
    pub lpips_net: LpipsNetArg,
    /// Inception weights for FID/KID (safetensors from `scripts/convert_eval_weights.py
    /// inception`) [default: no FID/KID].
    #[arg(long)]
    pub inception_weights: Option<PathBuf>,
    /// Largest KID subset (clean-fid's max_subset_size: subsets of min(frames, this); smaller
    /// sets use all frames).
    #[arg(long, default_value_t = crate::eval::fid::KID_SUBSET_SIZE)]
    pub kid_subset_size: usize,
    /// KID subsets (clean-fid's default).
    #[arg(long, default_value_t = crate::eval::fid::KID_SUBSETS)]
    pub kid_subsets: usize,
}

/// `--lpips-net`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum LpipsNetArg {
    /// AlexNet (the lpips default).
    Alex,
    /// VGG16.
    Vgg,
}

impl LpipsNetArg {
    /// The library's backbone.
    pub fn net(self) -> crate::eval::lpips::LpipsNet {
        match self {
            Self::Alex => crate::eval::lpips::LpipsNet::Alex,
            Self::Vgg => crate::eval::lpips::LpipsNet::Vgg,
        }
    }
}

/// The video a job reads (`nvs`, `finetune`): its folder and the folder's layout.
#[derive(Debug, Args)]
pub struct SequenceArgs {
    /// The video's sequence folder: any layout `datagen pairs` reads (cog-nvs, MegaSAM npz,
    /// generic, a reconstruction tool's output, a scene's input camera).
    #[arg(long)]
    pub sequence: PathBuf,
    /// The folder's layout, by the names `datagen pairs --layout` takes [default: detected from
    /// its files].
    #[arg(long)]
    pub layout: Option<datagen::api::LayoutName>,
}

/// WIDTHxHEIGHT, both at least 1.
pub fn parse_size(text: &str) -> Result<(u32, u32), String> {
    let (w, h) = text.split_once(['x', 'X']).ok_or_else(|| format!("{text}: expected WIDTHxHEIGHT"))?;
    let parse = |v: &str| v.trim().parse::<u32>().map_err(|e| format!("{text}: {e}"));
    let (width, height) = (parse(w)?, parse(h)?);
    if width == 0 || height == 0 {
        return Err(format!("{text}: an image needs at least one pixel a side"));
    }
    Ok((width, height))
}

/// The progress bar of a training run: steps, loss and speed, ETA.
pub fn step_bar(steps: u64) -> indicatif::ProgressBar {
    indicatif::ProgressBar::new(steps).with_style(
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} steps {msg} [{elapsed_precise}, eta {eta}]")
            .expect("valid template"),
    )
}

/// Shows a finished training step on `bar`.
pub fn show_step(bar: &indicatif::ProgressBar, m: &crate::training::StepMetrics) {
    bar.set_position(m.step);
    bar.set_message(format!("loss {:.4}, {:.2} step/s", m.loss, 1.0 / m.seconds.max(1e-9)));
}

/// Shows a training run's events: the memory plan on stderr, steps on `bar`.
pub fn show_run(bar: &indicatif::ProgressBar, event: crate::training::RunEvent) {
    match event {
        crate::training::RunEvent::Plan(plan) => eprintln!("{plan}"),
        crate::training::RunEvent::Step(m) => show_step(bar, m),
    }
}

/// A progress bar of `len` units named `what`, on stderr.
pub fn progress_bar(len: u64, what: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template(&format!(
            "{what} {{bar:30}} {{pos}}/{{len}} {{msg}} [{{elapsed_precise}}, eta {{eta}}]"
        ))
        .expect("valid template"),
    );
    bar
}

/// Writes `text` to `path` when a path is given.
pub fn write_optional(path: &Option<PathBuf>, text: &str) -> anyhow::Result<()> {
    use anyhow::Context;
    if let Some(out) = path {
        std::fs::write(out, text).with_context(|| format!("writing {}", out.display()))?;
    }
    Ok(())
}

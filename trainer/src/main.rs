//! The `trainer` command line: a thin layer that parses arguments and calls the library.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Args, Parser, Subcommand, ValueEnum};
use trainer::forward::{self, ForwardRequest, Module};

/// CogNVS video-to-video diffusion in tch: the CogVideoX transformer, VAE and schedulers,
/// weight-compatible with diffusers.
#[derive(Debug, Parser)]
#[command(name = "trainer", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run one component on tensors from a safetensors file and write its output: for checking
    /// this port or a checkpoint against diffusers. Inputs and outputs use diffusers' argument
    /// names: transformer `hidden_states` [B,F,C,H,W], `encoder_hidden_states` [B,S,D],
    /// `timestep` [B] → `sample`; vae_encoder `sample` [B,3,F,H,W] → `latent` (posterior mean,
    /// unscaled); vae_decoder `latent` → `sample`. Outputs are written as fp32.
    Forward(ForwardArgs),
    /// Compare a predicted video with the target: PSNR and SSIM (scikit-image conventions, data
    /// range 1) per frame and on average, and over co-visible pixels only when --mask is given.
    /// Prints JSON. LPIPS and FID are not computed (they need network weights this tool does
    /// not download).
    Eval(EvalArgs),
    /// Pretrain the transformer on training-pair shards (datagen pairs/build output): v-prediction
    /// with the CogVideoX-5B schedule, AdamW, checkpoints in the diffusers layout plus optimizer
    /// and data position; --resume continues the run exactly.
    Pretrain(PretrainArgs),
    /// Sample a novel-view video from a checkpoint and a conditioning render (datagen render
    /// output, a frame folder or a video): DPM sampler, classifier-free guidance, mp4 out.
    Sample(SampleArgs),
    /// Test-time finetuning: build the video's own self-supervised pairs in-process (datagen
    /// library) and finetune a checkpoint on them.
    Finetune(FinetuneArgs),
    /// Merge a LoRA file into a base transformer and write the full diffusers transformer folder
    /// (config.json + diffusion_pytorch_model.safetensors).
    MergeLora(MergeLoraArgs),
}

#[derive(Debug, Args)]
struct MergeLoraArgs {
    /// Base transformer: a diffusers folder, a checkpoint with transformer/, or a LoRA run's
    /// checkpoint (its base is found in the run).
    #[arg(long)]
    base: PathBuf,
    /// The LoRA file (pytorch_lora_weights.safetensors: ours, diffusers' or peft's layout).
    #[arg(long)]
    lora: PathBuf,
    /// Output transformer folder.
    #[arg(long)]
    out: PathBuf,
}

#[derive(Debug, Args)]
struct FinetuneArgs {
    /// Checkpoint to start from (RUN/checkpoints/step-N).
    #[arg(long)]
    init: PathBuf,
    /// The test video's sequence folder (cog-nvs, MegaSAM npz or generic layout).
    #[arg(long)]
    sequence: PathBuf,
    /// Run folder for the finetuned checkpoints, metrics and the pairs built.
    #[arg(long)]
    out: PathBuf,
    /// Optimizer steps.
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u64).range(1..))]
    steps: u64,
    /// Sampled trajectories per clip.
    #[arg(long, default_value_t = 2)]
    trajectories: u32,
    /// Training TOML overriding the init run's settings.
    #[arg(long)]
    config: Option<PathBuf>,
    /// A LoRA file (pytorch_lora_weights.safetensors) merged into the init transformer first.
    #[arg(long)]
    lora: Option<PathBuf>,
    /// Compute device: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    device: String,
}

#[derive(Debug, Args)]
struct SampleArgs {
    /// Checkpoint folder (RUN/checkpoints/step-N, with transformer/ or a LoRA run's adapters) or a
    /// transformer folder.
    #[arg(long)]
    ckpt: PathBuf,
    /// A LoRA file (pytorch_lora_weights.safetensors) merged into the checkpoint's transformer.
    #[arg(long)]
    lora: Option<PathBuf>,
    /// Conditioning: a `datagen render` folder, a folder of frames, or a video (4k+1 frames).
    #[arg(long)]
    cond: PathBuf,
    /// Output: a video (.mp4), or a folder of lossless PNG frames (any other path).
    #[arg(long)]
    out: PathBuf,
    /// Denoising steps.
    #[arg(long, default_value_t = 50)]
    steps: usize,
    /// Classifier-free guidance scale (no effect when prompt and negative prompt are the same).
    #[arg(long, default_value_t = 6.0)]
    guidance: f64,
    /// Seed of the noise.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// VAE folder [default: CKPT/vae or the run's vae/].
    #[arg(long)]
    vae: Option<PathBuf>,
    /// Text embedding safetensors (`encoder_hidden_states` [S, D]) [default: the run's, else zeros].
    #[arg(long)]
    text_embedding: Option<PathBuf>,
    /// Negative text embedding for guidance [default: the prompt's].
    #[arg(long)]
    negative_text_embedding: Option<PathBuf>,
    /// Compute device: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    device: String,
}

#[derive(Debug, Args)]
struct PretrainArgs {
    /// Training TOML: [model] (transformer, vae, text_embedding), [data] (frames, height, width,
    /// batch_size, seed), [optim], [loop] (see configs/pretrain_tiny.toml).
    #[arg(long)]
    config: PathBuf,
    /// Shard folders or files; repeatable.
    #[arg(long, required = true, num_args = 1..)]
    shards: Vec<PathBuf>,
    /// Run folder: checkpoints/, metrics.jsonl, config.json.
    #[arg(long)]
    out: PathBuf,
    /// Continue the run in --out from its latest checkpoint.
    #[arg(long)]
    resume: bool,
    /// Optimizer steps in all, overriding the config's `loop.steps`.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    steps: Option<u64>,
    /// Compute device: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    device: String,
}

#[derive(Debug, Args)]
struct EvalArgs {
    /// Predicted video: a video file or a folder of PNG/JPEG frames.
    #[arg(long)]
    pred: PathBuf,
    /// Target video: a video file or a folder of PNG/JPEG frames.
    #[arg(long)]
    target: PathBuf,
    /// Folder of per-frame mask PNGs (non-zero = co-visible), e.g. an export's mask/ folder.
    #[arg(long)]
    mask: Option<PathBuf>,
    /// Also write the JSON to this file.
    #[arg(long)]
    out: Option<PathBuf>,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum ModuleArg {
    /// CogVideoXTransformer3DModel.
    #[value(name = "transformer")]
    Transformer,
    /// The VAE encoder (posterior mean).
    #[value(name = "vae_encoder")]
    VaeEncoder,
    /// The VAE decoder.
    #[value(name = "vae_decoder")]
    VaeDecoder,
}

#[derive(Debug, Args)]
struct ForwardArgs {
    /// Which component to run.
    #[arg(long, value_enum)]
    module: ModuleArg,
    /// The component's diffusers config.json (or the model folder holding it).
    #[arg(long)]
    config: PathBuf,
    /// Weights: a .safetensors file, a .safetensors.index.json (sharded) or a model folder.
    #[arg(long)]
    weights: PathBuf,
    /// Input tensors (safetensors).
    #[arg(long)]
    inputs: PathBuf,
    /// Output file (safetensors, one tensor).
    #[arg(long)]
    out: PathBuf,
    /// Compute dtype: f32 or bf16.
    #[arg(long, default_value = "f32")]
    dtype: String,
    /// Compute device: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    device: String,
    /// VAE only: split large frames into diffusers' default spatial tiles (bounds memory).
    #[arg(long)]
    tiling: bool,
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Forward(args) => run_forward(args),
        Command::Eval(args) => run_eval(args),
        Command::Pretrain(args) => run_pretrain(args),
        Command::Sample(args) => run_sample(args),
        Command::Finetune(args) => run_finetune(args),
        Command::MergeLora(args) => {
            let merged = trainer::lora::merge_lora(&args.base, &args.lora, &args.out)?;
            println!("merged {merged} adapted layers into {}", args.out.display());
            Ok(())
        }
    }
}

/// The progress bar of a training run: steps, loss and speed, ETA.
fn step_bar(steps: u64) -> indicatif::ProgressBar {
    indicatif::ProgressBar::new(steps).with_style(
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} steps {msg} [{elapsed_precise}, eta {eta}]")
            .expect("valid template"),
    )
}

fn show_step(bar: &indicatif::ProgressBar, m: &trainer::training::StepMetrics) {
    bar.set_position(m.step);
    bar.set_message(format!("loss {:.4}, {:.2} step/s", m.loss, 1.0 / m.seconds.max(1e-9)));
}

fn run_finetune(args: FinetuneArgs) -> anyhow::Result<()> {
    let device = forward::parse_device(&args.device)?;
    let bar = step_bar(args.steps);
    let request = trainer::training::FinetuneRequest {
        init: args.init,
        sequence: args.sequence,
        out: args.out.clone(),
        steps: args.steps,
        trajectories: args.trajectories,
        config: args.config,
        lora: args.lora,
    };
    let summary = trainer::training::finetune(&request, device, |m| show_step(&bar, m))?;
    bar.finish_and_clear();
    println!(
        "finetuned {} steps into {}; checkpoint: {}",
        summary.steps,
        args.out.display(),
        summary.last_checkpoint.map_or("none".to_string(), |p| p.display().to_string())
    );
    Ok(())
}

fn run_sample(args: SampleArgs) -> anyhow::Result<()> {
    let request = trainer::sampling::SampleRequest {
        checkpoint: args.ckpt,
        lora: args.lora,
        vae: args.vae,
        text_embedding: args.text_embedding,
        negative_text_embedding: args.negative_text_embedding,
        condition: args.cond,
        out: args.out.clone(),
        steps: args.steps,
        guidance: args.guidance,
        seed: args.seed,
        device: forward::parse_device(&args.device)?,
    };
    let report = trainer::sampling::sample(&request)?;
    println!(
        "wrote {} ({} frames, {}x{}) after {} steps in {:.1} s",
        args.out.display(),
        report.frames,
        report.size.0,
        report.size.1,
        args.steps,
        report.seconds
    );
    Ok(())
}

fn run_pretrain(args: PretrainArgs) -> anyhow::Result<()> {
    use trainer::training;
    let mut config = training::PretrainConfig::from_toml_file(&args.config)?;
    if let Some(steps) = args.steps {
        config.train.steps = steps;
    }
    let device = forward::parse_device(&args.device)?;
    let bar = step_bar(config.train.steps);
    let summary = training::pretrain(&config, &args.shards, &args.out, args.resume, device, |m| show_step(&bar, m))?;
    bar.finish_and_clear();
    println!(
        "trained steps {}..{} into {}; last checkpoint: {}",
        summary.resumed_from,
        summary.steps,
        args.out.display(),
        summary.last_checkpoint.map_or("none".to_string(), |p| p.display().to_string())
    );
    Ok(())
}

fn run_eval(args: EvalArgs) -> anyhow::Result<()> {
    let result = trainer::metrics::evaluate(&args.pred, &args.target, args.mask.as_deref())?;
    let json = serde_json::to_string_pretty(&result)?;
    if let Some(out) = &args.out {
        std::fs::write(out, &json).with_context(|| format!("writing {}", out.display()))?;
    }
    println!("{json}");
    Ok(())
}

fn run_forward(args: ForwardArgs) -> anyhow::Result<()> {
    let module = match args.module {
        ModuleArg::Transformer => Module::Transformer,
        ModuleArg::VaeEncoder => Module::VaeEncoder,
        ModuleArg::VaeDecoder => Module::VaeDecoder,
    };
    let request = ForwardRequest {
        module,
        config: args.config,
        weights: args.weights,
        inputs: args.inputs,
        out: args.out.clone(),
        kind: forward::parse_dtype(&args.dtype)?,
        device: forward::parse_device(&args.device)?,
        tiling: args.tiling,
    };
    // No context line: the library's error names the file and tensor on the first line.
    let report = forward::run(&request)?;
    for (name, shape) in &report.inputs {
        println!("input  {name}: {shape:?}");
    }
    for name in &report.ignored_inputs {
        println!("ignored input `{name}` (not read by this module)");
    }
    println!("output {}: {:?} → {}", report.output.0, report.output.1, args.out.display());
    println!(
        "load {:.2} s, forward {:.2} s on {} ({})",
        report.load_seconds, report.forward_seconds, args.device, args.dtype
    );
    Ok(())
}

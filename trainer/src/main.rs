//! The `trainer` command line: a thin layer that parses arguments and calls the library.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Args, Parser, Subcommand, ValueEnum};
use trainer::pipelines::forward::{self, ForwardRequest, Module};
use trainer::precision::usable_device;

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
    /// this port or a checkpoint against diffusers. The config's `_class_name` picks CogVideoX or
    /// Wan. Inputs and outputs use diffusers' argument names: CogVideoX transformer
    /// `hidden_states` [B,F,C,H,W], `encoder_hidden_states` [B,S,D], `timestep` [B] → `sample`;
    /// Wan transformer `hidden_states` [B,C,F,H,W], `timestep`, `encoder_hidden_states` and for
    /// image-to-video `encoder_hidden_states_image` → `sample`; vae_encoder `sample`
    /// [B,3,F,H,W] → `latent` (posterior mean, unscaled); vae_decoder `latent` → `sample`.
    /// Outputs are written as fp32.
    Forward(ForwardArgs),
    /// Compare predictions with targets: PSNR and SSIM (scikit-image conventions), LPIPS (the
    /// lpips package) and FID/KID (clean-fid) from weight files you convert once with
    /// scripts/convert_eval_weights.py, masked mPSNR/mSSIM/mLPIPS with --mask. One video pair
    /// (video files or frame folders; JSON as before), or folders of videos matched by name
    /// (a Markdown table and JSON, per video and mean, FID/KID over all frames).
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
    /// The whole novel-view job on one video: test-time finetune a checkpoint (the released
    /// CogNVS one, or a run's) on the video's own pairs, render the video from each --trajectory,
    /// sample every render with one load of the finetuned model, and write OUT/<name>.mp4, PNG
    /// frames, a contact sheet (source | render | result) and OUT/nvs.json (settings, seeds,
    /// digests). Run again with the same arguments after a kill, it continues from the last
    /// finished phase.
    Nvs(NvsArgs),
    /// The paper's evaluation of a checkpoint on a dataset folder in one command: per scene, the
    /// split's input camera is the source, each held-out camera's poses a trajectory, `nvs`
    /// (finetuning with the paper's settings unless --steps 0) samples the novel views, and
    /// PSNR/SSIM/LPIPS (DyCheck: also over its co-visibility masks) and pooled FID/KID are
    /// computed at the protocol's size. Writes OUT/report.{md,json} with the paper's CogNVS rows
    /// beside ours; rerun with the same arguments it continues, skipping scored scenes.
    /// --compare RUN_A RUN_B prints the per-scene differences of two benchmark folders.
    Benchmark(BenchmarkArgs),
    /// Merge a LoRA file into a base transformer and write the full diffusers transformer folder
    /// (config.json + diffusion_pytorch_model.safetensors).
    MergeLora(MergeLoraArgs),
    /// Print the memory plan of a training config per device: parameters, gradients, master
    /// weights, optimizer state, activations with and without checkpointing (per block and in
    /// all), VAE encode/decode peaks and the predicted peak, for the config's precision, LoRA
    /// and ZeRO settings. `pretrain` and `finetune` print the same plan and, on CUDA, refuse a
    /// run that does not fit the device's free memory.
    Plan(PlanArgs),
    /// Check the multi-process setup the launcher gives (torchrun, srun, RANK/WORLD_SIZE): every
    /// collective the trainer uses, verified against values computed locally, then all-reduce
    /// bandwidth. Prints one line per check on rank 0; exits non-zero on any mismatch.
    CommCheck(CommCheckArgs),
    /// How much of a data-parallel training step the gradient and weight exchange costs: the
    /// config's model trains on random clips, ZeRO-0 and ZeRO-2 each with real collectives and
    /// with local no-ops, interleaved in rounds; prints one JSON line (rank 0) with each
    /// variant's median step time and the exposed share of each stage. Run it under the launcher
    /// (torchrun, srun, RANK/WORLD_SIZE), at any world size, 1 included.
    CommCost(CommCostArgs),
}

#[derive(Debug, Args)]
struct CommCostArgs {
    /// Training TOML (as for `pretrain --config`; its [distributed] zero_stage and
    /// noop_collectives are overridden per variant).
    #[arg(long)]
    config: PathBuf,
    /// Timed steps per variant and round (after one warm-up step).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u64).range(1..))]
    steps: u64,
    /// Rounds over the four variants.
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u64).range(1..))]
    rounds: u64,
    /// Compute device: cpu (Gloo) or cuda (NCCL, the GPU chosen by LOCAL_RANK).
    #[arg(long, default_value = "cpu")]
    device: String,
}

#[derive(Debug, Args)]
struct CommCheckArgs {
    /// Size of the all-reduce bandwidth test in MiB (fp32).
    #[arg(long, default_value_t = 64)]
    mib: usize,
    /// All-reduces timed.
    #[arg(long, default_value_t = 5)]
    iterations: usize,
    /// Compute device: cpu (Gloo) or cuda (NCCL, the GPU chosen by LOCAL_RANK).
    #[arg(long, default_value = "cpu")]
    device: String,
    /// Seconds any collective may wait.
    #[arg(long, default_value_t = 60.0)]
    timeout: f64,
}

#[derive(Debug, Args)]
struct PlanArgs {
    /// Training TOML (as for `pretrain --config`).
    #[arg(long)]
    config: PathBuf,
    /// Ranks [default: the launcher's WORLD_SIZE / SLURM_NTASKS, else the config's
    /// data.world_size].
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    world_size: Option<u64>,
    /// Device the plan is for (decides precision = "auto"): cpu, cuda or cuda:N; no device is
    /// needed to plan.
    #[arg(long, default_value = "cuda")]
    device: String,
    /// Plan sampling instead of training: the config's models and [data] frames and size, its
    /// precision, with VAE tiling unless --no-vae-tiling.
    #[arg(long)]
    sampling: bool,
    /// With --sampling: guidance against another prompt (a batch of two).
    #[arg(long, requires = "sampling")]
    guided: bool,
    /// With --sampling: without VAE tiling.
    #[arg(long, requires = "sampling")]
    no_vae_tiling: bool,
}

#[derive(Debug, Args)]
struct NvsArgs {
    /// Checkpoint to finetune and sample: the released CogNVS transformer folder (with
    /// --base-model), a run's checkpoint, or a pipeline folder with transformer/.
    #[arg(long)]
    init: PathBuf,
    /// The video's sequence folder (cog-nvs, MegaSAM npz or generic layout).
    #[arg(long)]
    sequence: PathBuf,
    /// A camera path (.npy (N,4,4), .json, or the public trajs/*.txt); repeatable. The outputs
    /// are named after the file's stem.
    #[arg(long = "trajectory", required = true)]
    trajectories: Vec<PathBuf>,
    /// Output folder.
    #[arg(long)]
    out: PathBuf,
    /// Test-time finetuning steps (0: sample the checkpoint as it is).
    #[arg(long, default_value_t = trainer::pipelines::nvs::DEFAULT_FINETUNE_STEPS)]
    steps: u64,
    /// Sampled trajectories per clip for the finetuning pairs (the paper: 5 for DyCheck, 9 for
    /// Kubric-4D and ParDom-4D).
    #[arg(long = "finetune-trajectories", default_value_t = 5)]
    finetune_trajectories: u32,
    /// Training TOML for finetuning (required for a checkpoint that is not a trainer run's:
    /// configs/finetune_5b_lora_1gpu.toml, finetune_5b_full_1gpu.toml or finetune_5b_full.toml).
    #[arg(long)]
    config: Option<PathBuf>,
    #[command(flatten)]
    model: ModelArgs,
    /// Denoising steps per sample.
    #[arg(long, default_value_t = 50)]
    sample_steps: usize,
    #[command(flatten)]
    sampling: SamplingArgs,
    /// Fill render holes from the static background stacked over all frames: auto (when the
    /// video has more frames than are sampled), on or off.
    #[arg(long, value_enum, default_value_t = SwitchArg::Auto)]
    stack_background: SwitchArg,
    /// Compute device: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    device: String,
}

#[derive(Debug, Args)]
struct BenchmarkArgs {
    /// Print the per-scene differences (B − A) of two finished benchmark folders and exit;
    /// refused when their protocols or scene lists differ.
    #[arg(long, num_args = 2, value_names = ["RUN_A", "RUN_B"], conflicts_with_all = ["dataset", "root", "init", "out"])]
    compare: Option<Vec<PathBuf>>,
    /// The dataset, which fixes the protocol (dycheck: DyCheck's, with masked metrics over its
    /// co-visibility masks; kubric4d, pardom4d: GCD's) and the paper's rows shown.
    #[arg(long, value_enum, required_unless_present = "compare")]
    dataset: Option<DatasetArg>,
    /// The dataset folder: one sub-folder per multi-camera scene.
    #[arg(long, required_unless_present = "compare")]
    root: Option<PathBuf>,
    /// Scenes to evaluate (folder names under --root) [default: every scene].
    #[arg(long, num_args = 1.., value_delimiter = ',')]
    scenes: Vec<String>,
    /// The scenes' layout: dycheck, kubric4d, pardom4d or generic (a sequence folder per camera)
    /// [default: detected per scene from its files].
    #[arg(long)]
    layout: Option<datagen::io::multiview_layout::MultiViewLayoutName>,
    /// What the source video is rendered from: `dataset` (the input camera's own depth and
    /// cameras) or a folder with one reconstruction per scene, DIR/<scene>/ (MegaSAM's, MoSca's
    /// exported, any layout datagen reads), scaled to the dataset's units by the median depth
    /// ratio.
    #[arg(long, default_value = "dataset")]
    reconstruction: String,
    /// The input camera, overriding the dataset's split (the generic layout has none: its first
    /// camera).
    #[arg(long)]
    input_camera: Option<String>,
    /// A held-out camera, overriding the dataset's split; repeatable (the generic layout's
    /// default: every camera but the input).
    #[arg(long = "held-out-camera")]
    held_out_cameras: Vec<String>,
    /// Checkpoint to evaluate (as `nvs --init`).
    #[arg(long, required_unless_present = "compare")]
    init: Option<PathBuf>,
    /// Output folder.
    #[arg(long, required_unless_present = "compare")]
    out: Option<PathBuf>,
    /// Test-time finetuning steps per scene (0: sample the checkpoint as it is).
    #[arg(long, default_value_t = trainer::pipelines::nvs::DEFAULT_FINETUNE_STEPS)]
    steps: u64,
    /// Sampled trajectories per clip for the finetuning pairs [default: the paper's, 5 for
    /// DyCheck, 9 for Kubric-4D and ParDom-4D].
    #[arg(long = "finetune-trajectories")]
    finetune_trajectories: Option<u32>,
    /// Training TOML for finetuning (as `nvs --config`).
    #[arg(long)]
    config: Option<PathBuf>,
    #[command(flatten)]
    model: ModelArgs,
    /// Denoising steps per sample.
    #[arg(long, default_value_t = 50)]
    sample_steps: usize,
    #[command(flatten)]
    sampling: SamplingArgs,
    /// Fill render holes from the stacked static background: auto, on or off.
    #[arg(long, value_enum, default_value_t = SwitchArg::Auto)]
    stack_background: SwitchArg,
    /// Compute the metrics at WIDTHxHEIGHT instead of the protocol's size (the paper's numbers
    /// then do not compare; for quick checks).
    #[arg(long, value_parser = parse_size)]
    eval_size: Option<(u32, u32)>,
    /// LPIPS weights (safetensors from `scripts/convert_eval_weights.py lpips`) [default: no LPIPS].
    #[arg(long)]
    lpips_weights: Option<PathBuf>,
    /// LPIPS backbone of --lpips-weights.
    #[arg(long, value_enum, default_value = "alex")]
    lpips_net: LpipsNetArg,
    /// Inception weights for FID/KID (`scripts/convert_eval_weights.py inception`) [default: none].
    #[arg(long)]
    inception_weights: Option<PathBuf>,
    /// KID's largest subset size (clean-fid's max_subset_size; smaller sets use all frames).
    #[arg(long, default_value_t = trainer::eval::fid::KID_SUBSET_SIZE)]
    kid_subset_size: usize,
    /// KID subsets.
    #[arg(long, default_value_t = trainer::eval::fid::KID_SUBSETS)]
    kid_subsets: usize,
    /// DyCheck: a folder of dycheck_<scene>_source_target_correspondence.txt files (the CogNVS
    /// evaluation bundle's dycheck/) selecting the held-out frames scored, as the official script
    /// selects them [default: every held-out frame the input camera's instants meet].
    #[arg(long)]
    correspondence: Option<PathBuf>,
    /// Compute device: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    device: String,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum DatasetArg {
    /// DyCheck iPhone (DyCheck protocol, masked metrics).
    Dycheck,
    /// Kubric-4D (GCD protocol).
    Kubric4d,
    /// ParallelDomain-4D (GCD protocol).
    Pardom4d,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum SwitchArg {
    Auto,
    On,
    Off,
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
    /// Training TOML overriding the init run's settings (required for a checkpoint that is not
    /// a trainer run's, such as the released CogNVS transformer: configs/finetune_5b_*.toml).
    #[arg(long)]
    config: Option<PathBuf>,
    #[command(flatten)]
    model: ModelArgs,
    /// Continue the run in --out from its newest intact checkpoint (after a preemption, exit
    /// status 75), on the pairs it built.
    #[arg(long)]
    resume: bool,
    /// Compute device: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    device: String,
}

/// Where the models come from besides the checkpoint (shared by `sample`, `finetune` and `nvs`).
#[derive(Debug, Args)]
struct ModelArgs {
    /// A CogVideoX pipeline folder in CogVideoX-5B-I2V's layout (vae/, scheduler/, text_encoder/,
    /// tokenizer/, transformer/): the VAE and the scheduler config come from it when the
    /// checkpoint has none (the released CogNVS transformer is such a checkpoint).
    #[arg(long)]
    base_model: Option<PathBuf>,
    /// VAE folder [default: CKPT/vae, the run's vae/, or --base-model's vae/].
    #[arg(long)]
    vae: Option<PathBuf>,
    /// A LoRA file (pytorch_lora_weights.safetensors) merged into the checkpoint's transformer.
    #[arg(long)]
    lora: Option<PathBuf>,
    /// Text embedding safetensors (`encoder_hidden_states` [226, 4096] for the released models),
    /// made once with `scripts/encode_prompt.py` [default: the run's, else required for
    /// T5-XXL-shaped transformers].
    #[arg(long)]
    text_embedding: Option<PathBuf>,
    /// Use zeros as the text embedding, also for a transformer trained on T5-XXL text.
    #[arg(long, conflicts_with = "text_embedding")]
    zero_text_embedding: bool,
}

impl ModelArgs {
    fn source(&self, checkpoint: PathBuf) -> trainer::loaders::ModelSource {
        trainer::loaders::ModelSource {
            checkpoint,
            base_model: self.base_model.clone(),
            vae: self.vae.clone(),
            lora: self.lora.clone(),
            text_embedding: self.text_embedding.clone(),
            negative_text_embedding: None,
            zero_text_embedding: self.zero_text_embedding,
        }
    }
}

/// How a conditioning is sampled (shared by `sample` and `nvs`); the defaults are the public
/// CogNVS demo's.
#[derive(Debug, Args)]
struct SamplingArgs {
    /// Classifier-free guidance scale (no effect when prompt and negative prompt are the same).
    #[arg(long, default_value_t = 6.0)]
    guidance: f64,
    /// Seed of every draw (the public pipeline's `torch.Generator(device).manual_seed(SEED)`).
    #[arg(long, default_value_t = 42)]
    seed: u64,
    /// Arithmetic: auto (bf16 on CUDA as the demo, fp32 on CPUs), fp32 or bf16.
    #[arg(long, value_enum, default_value_t = DtypeArg::Auto)]
    dtype: DtypeArg,
    /// Decode and encode without spatial VAE tiles (the demo tiles; tiles bound memory).
    #[arg(long)]
    no_vae_tiling: bool,
    /// Frames sampled: the first N of the conditioning (fewer when it is shorter: the most
    /// that make 1 + 4k).
    #[arg(long, default_value_t = trainer::pipelines::sampling::DEMO_FRAMES)]
    frames: usize,
    /// How frames of another size reach the model's size: area (stretch with an area average,
    /// as the demo) or crop (scale to cover and crop the centre, as the training loader).
    #[arg(long, value_enum, default_value_t = ResizeArg::Area)]
    resize: ResizeArg,
    /// The model's input size WIDTHxHEIGHT [default: the transformer's own, 720x480 for CogNVS].
    #[arg(long, value_parser = parse_size)]
    size: Option<(u32, u32)>,
    /// Keep the model's size instead of resizing the result back to the conditioning's.
    #[arg(long)]
    keep_model_size: bool,
    /// Frame rate of mp4 outputs.
    #[arg(long, default_value_t = trainer::pipelines::sampling::DEMO_FPS)]
    fps: f64,
}

impl SamplingArgs {
    fn framing(&self) -> trainer::pipelines::sampling::Framing {
        trainer::pipelines::sampling::Framing {
            frames: self.frames,
            resize: match self.resize {
                ResizeArg::Area => trainer::pipelines::video_processor::ResizeMode::Area,
                ResizeArg::Crop => trainer::pipelines::video_processor::ResizeMode::Crop,
            },
            size: self.size,
            restore_size: !self.keep_model_size,
            fps: self.fps,
        }
    }

    fn load(&self, device: tch::Device) -> trainer::pipelines::sampling::LoadOptions {
        trainer::pipelines::sampling::LoadOptions {
            device,
            precision: self.dtype.precision(),
            vae_tiling: !self.no_vae_tiling,
        }
    }
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum DtypeArg {
    Auto,
    Fp32,
    Bf16,
}

impl DtypeArg {
    fn precision(self) -> trainer::training::Precision {
        match self {
            Self::Auto => trainer::training::Precision::Auto,
            Self::Fp32 => trainer::training::Precision::Fp32,
            Self::Bf16 => trainer::training::Precision::Bf16,
        }
    }
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum ResizeArg {
    Area,
    Crop,
}

fn parse_size(text: &str) -> Result<(u32, u32), String> {
    let (w, h) = text.split_once(['x', 'X']).ok_or_else(|| format!("{text}: expected WIDTHxHEIGHT"))?;
    let parse = |v: &str| v.trim().parse::<u32>().map_err(|e| format!("{text}: {e}"));
    let (width, height) = (parse(w)?, parse(h)?);
    if width == 0 || height == 0 {
        return Err(format!("{text}: an image needs at least one pixel a side"));
    }
    Ok((width, height))
}

#[derive(Debug, Args)]
struct SampleArgs {
    /// Checkpoint: a run's (RUN/checkpoints/step-N, full or LoRA), a transformer folder (the
    /// released CogNVS transformer) or a pipeline folder with transformer/.
    #[arg(long)]
    ckpt: PathBuf,
    #[command(flatten)]
    model: ModelArgs,
    /// Conditioning: a `datagen render` folder, a folder of frames, or a video.
    #[arg(long)]
    cond: PathBuf,
    /// Output: a video (.mp4), or a folder of lossless PNG frames (any other path).
    #[arg(long)]
    out: PathBuf,
    /// Negative text embedding for guidance [default: the prompt's].
    #[arg(long)]
    negative_text_embedding: Option<PathBuf>,
    /// Denoising steps.
    #[arg(long, default_value_t = 50)]
    steps: usize,
    #[command(flatten)]
    sampling: SamplingArgs,
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
    /// Continue the run in --out from its newest intact checkpoint (every file checked against
    /// the digests its state.json lists; damaged ones are skipped, naming the file).
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
    /// Predicted video: a video file or a folder of PNG/JPEG frames (or a folder of such videos).
    #[arg(long, required_unless_present = "bundle", conflicts_with = "bundle")]
    pred: Option<PathBuf>,
    /// Target video: a video file or a folder of PNG/JPEG frames (or a folder of such videos).
    #[arg(long, required_unless_present = "bundle", conflicts_with = "bundle")]
    target: Option<PathBuf>,
    /// Score one method of the paper's evaluation bundle as the official eval_metrics.py does:
    /// ROOT/<dataset>/<method>/*<scene>_<method>[_cam<k>].mp4 against target_gt[_1x]/, DyCheck
    /// frames selected by ROOT/dycheck/dycheck_<scene>_source_target_correspondence.txt.
    #[arg(long, requires_all = ["dataset", "method"], conflicts_with_all = ["mask", "protocol", "top_k"])]
    bundle: Option<PathBuf>,
    /// The bundle's dataset folder.
    #[arg(long, value_enum, requires = "bundle")]
    dataset: Option<BundleDatasetArg>,
    /// The bundle's method (its folder and file-name key: cognvs, gcd, trajcrafter, megasam_render,
    /// shape_of_motion, mosca, gt_render).
    #[arg(long, requires = "bundle")]
    method: Option<String>,
    /// DyCheck's resolution in the bundle: 720p (target_gt_1x/, 960x720) or 360p (target_gt/, 480x360).
    #[arg(long, value_enum, default_value = "720p", requires = "bundle")]
    dycheck_resolution: DycheckResolutionArg,
    /// Folder of per-frame mask PNGs (non-zero = co-visible), e.g. an export's mask/ folder;
    /// for folders of videos, a folder with one such folder per video name.
    #[arg(long)]
    mask: Option<PathBuf>,
    /// Also write the JSON to this file.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Resize predictions and targets to the protocol's size first (cv2.resize, as the official
    /// script; masks nearest): gcd 384x576, dycheck 960x720, dycheck360 480x360 (HxW). Without
    /// it, sizes must agree.
    #[arg(long, value_enum)]
    protocol: Option<ProtocolArg>,
    /// Each prediction PRED/NAME/ holds K samples; the best by PSNR (mPSNR with masks) is scored.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    top_k: Option<u64>,
    /// Metrics beyond PSNR/SSIM (comma-separated: lpips, fid, kid) [default: those whose
    /// weights are given].
    #[arg(long, value_delimiter = ',')]
    metrics: Vec<MetricArg>,
    /// LPIPS weights (safetensors from `scripts/convert_eval_weights.py lpips`).
    #[arg(long)]
    lpips_weights: Option<PathBuf>,
    /// LPIPS backbone of --lpips-weights.
    #[arg(long, value_enum, default_value = "alex")]
    lpips_net: LpipsNetArg,
    /// Inception weights for FID/KID (safetensors from `scripts/convert_eval_weights.py inception`).
    #[arg(long)]
    inception_weights: Option<PathBuf>,
    /// Largest KID subset (clean-fid's max_subset_size: subsets of min(frames, this)).
    #[arg(long, default_value_t = trainer::eval::fid::KID_SUBSET_SIZE)]
    kid_subset_size: usize,
    /// KID subsets (clean-fid's default).
    #[arg(long, default_value_t = trainer::eval::fid::KID_SUBSETS)]
    kid_subsets: usize,
    /// Seed of KID's subsets.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Also write the Markdown table to this file.
    #[arg(long)]
    markdown: Option<PathBuf>,
    /// Compute device of the networks: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    device: String,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum ProtocolArg {
    /// Kubric-4D / ParallelDomain-4D (GCD): 384x576.
    Gcd,
    /// DyCheck iPhone at 720p: 960x720.
    Dycheck,
    /// DyCheck iPhone at 360p: 480x360.
    Dycheck360,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum BundleDatasetArg {
    /// kubric_4d/ (GCD protocol).
    #[value(name = "kubric_4d")]
    Kubric4d,
    /// pardom_4d/ (GCD protocol).
    #[value(name = "pardom_4d")]
    Pardom4d,
    /// dycheck/.
    Dycheck,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum DycheckResolutionArg {
    /// 480x360 (HxW), targets in target_gt/.
    #[value(name = "360p")]
    P360,
    /// 960x720 (HxW), targets in target_gt_1x/.
    #[value(name = "720p")]
    P720,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum MetricArg {
    /// LPIPS (needs --lpips-weights).
    Lpips,
    /// FID (needs --inception-weights).
    Fid,
    /// KID (needs --inception-weights).
    Kid,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum LpipsNetArg {
    /// AlexNet (the lpips default).
    Alex,
    /// VGG16.
    Vgg,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum ModuleArg {
    /// The transformer (CogVideoXTransformer3DModel or WanTransformer3DModel).
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

/// The command line as clap builds it, with every value argument taking values that look like
/// negative numbers (`--seed -1`): the value then reaches the flag's parser, whose refusal names
/// the flag, instead of being read as an unknown flag `-1`.
fn command_line() -> clap::Command {
    use clap::CommandFactory;
    Cli::command().mut_subcommands(|sub| {
        sub.mut_args(|arg| if arg.get_action().takes_values() { arg.allow_negative_numbers(true) } else { arg })
    })
}

fn main() -> anyhow::Result<()> {
    use clap::FromArgMatches;
    let cli = Cli::from_arg_matches(&command_line().get_matches()).unwrap_or_else(|e| e.exit());
    match cli.command {
        Command::Forward(args) => run_forward(args),
        Command::Eval(args) => run_eval(args),
        Command::Pretrain(args) => training_exit(run_pretrain(args)),
        Command::Sample(args) => run_sample(args),
        Command::Finetune(args) => training_exit(run_finetune(args)),
        Command::Nvs(args) => training_exit(run_nvs(args)),
        Command::Benchmark(args) => training_exit(run_benchmark(args)),
        Command::Plan(args) => run_plan(args),
        Command::CommCheck(args) => run_comm_check(args),
        Command::CommCost(args) => run_comm_cost(args),
        Command::MergeLora(args) => {
            let merged = trainer::loaders::lora::merge_lora(&args.base, &args.lora, &args.out)?;
            println!("merged {merged} adapted layers into {}", args.out.display());
            Ok(())
        }
    }
}

/// Ends a training command with its documented exit status (README, "Long runs"): 0 done,
/// 75 preempted after a complete checkpoint, 74 a checkpoint could not be written, 1 any other
/// error. `preempted` comes back once the run's process group is gone.
fn training_exit(result: anyhow::Result<bool>) -> anyhow::Result<()> {
    use trainer::training::preempt;
    match result {
        Ok(false) => Ok(()),
        Ok(true) => std::process::exit(preempt::EXIT_PREEMPTED),
        Err(e) if matches!(e.downcast_ref(), Some(trainer::Error::CheckpointWrite { .. })) => {
            eprintln!("Error: {e:?}");
            std::process::exit(preempt::EXIT_CHECKPOINT_FAILED)
        }
        Err(e) => Err(e),
    }
}

fn run_comm_check(args: CommCheckArgs) -> anyhow::Result<()> {
    use trainer::distributed::comm_check;
    // A launcher's world size of 1 still gets a process group: a backend check on one GPU.
    let launch = trainer::distributed::Launch::from_env_any_size()?;
    let (device, pg) = trainer::distributed::join(launch, usable_device(&args.device)?, args.timeout)?;
    let Some(pg) = pg else {
        println!("no launcher variables (torchrun, srun, RANK/WORLD_SIZE): nothing to check");
        return Ok(());
    };
    let lead = pg.rank == 0;
    comm_check::check_collectives(&pg, device, |name| {
        if lead {
            println!("{name} ok");
        }
    })?;
    let bandwidth = comm_check::all_reduce_bandwidth(&pg, device, args.mib as u64, args.iterations)?;
    if lead {
        println!("{bandwidth}");
    }
    Ok(())
}

fn run_comm_cost(args: CommCostArgs) -> anyhow::Result<()> {
    let config = trainer::training::PretrainConfig::from_toml_file(&args.config)?;
    // A launcher's world size of 1 still gets a process group: the exchange on one GPU.
    let launch = trainer::distributed::Launch::from_env_any_size()?;
    let device = usable_device(&args.device)?;
    let (device, pg) = trainer::distributed::join(launch, device, config.distributed.timeout_seconds)?;
    let Some(pg) = pg else {
        anyhow::bail!("no launcher variables (torchrun, srun, RANK/WORLD_SIZE): run it under a launcher");
    };
    let cost = trainer::training::comm_cost(&config, device, &pg, args.steps as usize, args.rounds as usize)
        .with_context(|| format!("comm-cost with {}", args.config.display()))?;
    if pg.rank == 0 {
        println!("{}", serde_json::to_string(&cost)?);
    }
    Ok(())
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

/// Shows a training run's events: the memory plan on stderr, steps on `bar`.
fn show_run(bar: &indicatif::ProgressBar, event: trainer::training::RunEvent) {
    match event {
        trainer::training::RunEvent::Plan(plan) => eprintln!("{plan}"),
        trainer::training::RunEvent::Step(m) => show_step(bar, m),
    }
}

fn run_finetune(args: FinetuneArgs) -> anyhow::Result<bool> {
    let device = usable_device(&args.device)?;
    let bar = step_bar(args.steps);
    let request = trainer::training::FinetuneRequest {
        init: args.init,
        base_model: args.model.base_model,
        vae: args.model.vae,
        text_embedding: args.model.text_embedding,
        zero_text_embedding: args.model.zero_text_embedding,
        sequence: args.sequence,
        out: args.out.clone(),
        steps: args.steps,
        trajectories: args.trajectories,
        config: args.config,
        lora: args.model.lora,
        resume: args.resume,
    };
    let summary = trainer::training::finetune_launched(&request, device, |event| show_run(&bar, event))?;
    bar.finish_and_clear();
    println!(
        "finetuned {} steps into {}; checkpoint: {}",
        summary.steps,
        args.out.display(),
        summary.last_checkpoint.map_or("none".to_string(), |p| p.display().to_string())
    );
    Ok(summary.preempted)
}

fn run_nvs(args: NvsArgs) -> anyhow::Result<bool> {
    use trainer::pipelines::nvs::Progress;
    let device = usable_device(&args.device)?;
    let request = trainer::pipelines::nvs::NvsRequest {
        model: args.model.source(args.init),
        sequence: args.sequence,
        trajectories: args.trajectories,
        out: args.out.clone(),
        steps: args.steps,
        finetune_trajectories: args.finetune_trajectories,
        config: args.config,
        sample_steps: args.sample_steps,
        guidance: args.sampling.guidance,
        seed: args.sampling.seed,
        load: args.sampling.load(device),
        framing: args.sampling.framing(),
        stack_background: match args.stack_background {
            SwitchArg::Auto => None,
            SwitchArg::On => Some(true),
            SwitchArg::Off => Some(false),
        },
    };
    let mut bar = indicatif::ProgressBar::hidden();
    let outcome = trainer::pipelines::nvs::run_launched(&request, device, &mut |event| match event {
        Progress::Phase(phase, len) => {
            bar.finish();
            bar = match phase {
                "finetune" => step_bar(len),
                _ => progress_bar(len, &format!("{phase:<8}")),
            };
        }
        Progress::Skipped(phase) => eprintln!("{phase}: finished by an earlier run"),
        Progress::Step(m) => show_step(&bar, m),
        Progress::Trajectory(name) => {
            bar.inc(1);
            bar.set_message(name.to_string());
        }
        Progress::Denoise(step, steps) => bar.set_message(format!("denoising {step}/{steps}")),
    })?;
    bar.finish();
    if outcome.preempted {
        eprintln!(
            "preempted: every finished phase and trajectory is recorded in {}; run the same command again to \
             continue (exit status {})",
            args.out.join("nvs.json").display(),
            trainer::training::preempt::EXIT_PREEMPTED
        );
        return Ok(true);
    }
    if let Some(record) = outcome.record {
        for output in &record.outputs {
            println!(
                "{}: {} ({} frames), {}",
                output.name,
                args.out.join(output.video.as_deref().unwrap_or_default()).display(),
                output.digests.len().saturating_sub(2),
                args.out.join(output.sheet.as_deref().unwrap_or_default()).display()
            );
        }
        println!("settings, seeds and digests: {}", args.out.join("nvs.json").display());
    }
    Ok(false)
}

fn run_benchmark(args: BenchmarkArgs) -> anyhow::Result<bool> {
    use trainer::benchmark::{self, Progress};
    if let Some(runs) = &args.compare {
        let comparison = benchmark::compare(&runs[0], &runs[1])?;
        println!("{}", benchmark::report::comparison_markdown(&comparison));
        return Ok(false);
    }
    let (Some(dataset), Some(root), Some(init), Some(out)) = (args.dataset, args.root, args.init, args.out) else {
        unreachable!("clap requires them without --compare")
    };
    let dataset = match dataset {
        DatasetArg::Dycheck => benchmark::Dataset::Dycheck,
        DatasetArg::Kubric4d => benchmark::Dataset::Kubric4d,
        DatasetArg::Pardom4d => benchmark::Dataset::Pardom4d,
    };
    let device = trainer::precision::usable_device(&args.device)?;
    let request = benchmark::Request {
        dataset,
        root,
        scenes: args.scenes,
        layout: args.layout,
        split: benchmark::SplitOverride { input: args.input_camera, held_out: args.held_out_cameras },
        reconstruction: match args.reconstruction.as_str() {
            "dataset" => benchmark::Reconstruction::Dataset,
            dir => benchmark::Reconstruction::Folder(PathBuf::from(dir)),
        },
        out: out.clone(),
        model: args.model.source(init),
        steps: args.steps,
        finetune_trajectories: args.finetune_trajectories.unwrap_or(dataset.finetune_trajectories()),
        config: args.config,
        sample_steps: args.sample_steps,
        guidance: args.sampling.guidance,
        seed: args.sampling.seed,
        load: args.sampling.load(device),
        framing: args.sampling.framing(),
        stack_background: match args.stack_background {
            SwitchArg::Auto => None,
            SwitchArg::On => Some(true),
            SwitchArg::Off => Some(false),
        },
        eval_size: args.eval_size,
        lpips: args.lpips_weights,
        lpips_net: match args.lpips_net {
            LpipsNetArg::Alex => trainer::eval::lpips::LpipsNet::Alex,
            LpipsNetArg::Vgg => trainer::eval::lpips::LpipsNet::Vgg,
        },
        inception: args.inception_weights,
        kid_subsets: args.kid_subsets,
        kid_subset_size: args.kid_subset_size,
        correspondence: args.correspondence,
    };
    let outcome = benchmark::run(&request, &mut |event| match event {
        Progress::Scene(name, i, n) => eprintln!("scene {}/{n}: {name}", i + 1),
        Progress::Skipped(name) => eprintln!("scene {name}: scored by an earlier run, skipped"),
        Progress::Failed(name, reason) => eprintln!("scene {name}: FAILED: {reason}"),
        Progress::Window(name, i, n, start) => eprintln!("scene {name}: window {}/{n} from frame {start}", i + 1),
        Progress::Done(name, line) => eprintln!(
            "scene {name}: {} frames, PSNR {}",
            line.frames,
            line.metrics.psnr.map_or("–".to_string(), |v| format!("{v:.3}"))
        ),
        Progress::Nvs(trainer::pipelines::nvs::Progress::Phase(phase, len)) => eprintln!("  {phase} ({len})"),
        Progress::Nvs(trainer::pipelines::nvs::Progress::Skipped(phase)) => {
            eprintln!("  {phase}: finished by an earlier run")
        }
        Progress::Nvs(_) => {}
    })?;
    let Some(report) = outcome.report else {
        eprintln!(
            "preempted: scored scenes are kept in {}; run the same command again to continue (exit status {})",
            out.display(),
            trainer::training::preempt::EXIT_PREEMPTED
        );
        return Ok(true);
    };
    println!("{}", benchmark::report::markdown(&report));
    println!(
        "table: {}, JSON: {}",
        out.join(benchmark::REPORT_MD).display(),
        out.join(benchmark::REPORT_JSON).display()
    );
    Ok(false)
}

fn run_sample(args: SampleArgs) -> anyhow::Result<()> {
    let device = usable_device(&args.device)?;
    let mut model = args.model.source(args.ckpt);
    model.negative_text_embedding = args.negative_text_embedding;
    let request = trainer::pipelines::sampling::SampleRequest {
        model,
        condition: args.cond,
        out: args.out.clone(),
        steps: args.steps,
        guidance: args.sampling.guidance,
        seed: args.sampling.seed,
        load: args.sampling.load(device),
        framing: args.sampling.framing(),
    };
    let paths = request.model.resolve()?;
    trainer::training::plan::check_sampling_fits(&trainer::training::plan::sampling_plan_for(
        &paths,
        request.load,
        &request.framing,
    )?)?;
    let bar = progress_bar(request.steps as u64, "denoising");
    let report = trainer::pipelines::sampling::sample(&request, &paths, &mut |i, _| bar.set_position(i as u64))?;
    bar.finish_and_clear();
    if report.source_size != report.model_size {
        let ((w, h), (mw, mh)) = (report.source_size, report.model_size);
        let back =
            if request.framing.restore_size { format!(" and the result back to {w}x{h}") } else { String::new() };
        eprintln!(
            "note: resized the conditioning from {w}x{h} to the model's {mw}x{mh} ({:?}){back}",
            request.framing.resize
        );
    }
    if report.frames < report.source_frames.min(request.framing.frames) {
        eprintln!(
            "note: sampled the first {} of the conditioning's {} frames (1 + 8k frames decode back to as many)",
            report.frames, report.source_frames
        );
    }
    if let Some((allocated, reserved)) = report.cuda_peaks {
        let gib = |b: u64| b as f64 / (1u64 << 30) as f64;
        println!("cuda memory: peak allocated {:.2} GiB, peak reserved {:.2} GiB", gib(allocated), gib(reserved));
    }
    let t = &report.timings;
    println!("seconds: encode {:.2}, denoise {:.2}, decode {:.2}", t.encode, t.denoise, t.decode);
    println!(
        "wrote {} ({} frames, {}x{}; sampled at {}x{}) after {} steps in {:.1} s",
        args.out.display(),
        report.frames,
        report.size.0,
        report.size.1,
        report.model_size.0,
        report.model_size.1,
        request.steps,
        report.seconds
    );
    Ok(())
}

/// A progress bar of `len` units named `what`, on stderr.
fn progress_bar(len: u64, what: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template(&format!(
            "{what} {{bar:30}} {{pos}}/{{len}} {{msg}} [{{elapsed_precise}}, eta {{eta}}]"
        ))
        .expect("valid template"),
    );
    bar
}

fn run_pretrain(args: PretrainArgs) -> anyhow::Result<bool> {
    use trainer::training;
    let mut config = training::PretrainConfig::from_toml_file(&args.config)?;
    if let Some(steps) = args.steps {
        config.train.steps = steps;
    }
    let device = usable_device(&args.device)?;
    let bar = step_bar(config.train.steps);
    let source_name = args.config.display().to_string();
    let summary =
        training::pretrain_launched(&config, &source_name, &args.shards, &args.out, args.resume, device, |event| {
            show_run(&bar, event)
        })?;
    bar.finish_and_clear();
    println!(
        "trained steps {}..{} into {}; last checkpoint: {}",
        summary.resumed_from,
        summary.steps,
        args.out.display(),
        summary.last_checkpoint.map_or("none".to_string(), |p| p.display().to_string())
    );
    Ok(summary.preempted)
}

fn run_plan(args: PlanArgs) -> anyhow::Result<()> {
    let config = trainer::training::PretrainConfig::from_toml_file(&args.config)?;
    let device = trainer::precision::parse_device(&args.device)?;
    if args.sampling {
        let (transformer, vae) = config.model.configs(true)?;
        let tiles = trainer::models::cogvideox::autoencoder_kl_cogvideox::TilingConfig::for_config(&vae);
        let aligned = !args.no_vae_tiling && tiles.lands_on_latent_pixels(vae.spatial_compression_ratio());
        let d = &config.data;
        let plan = trainer::training::plan::sampling_plan(
            &transformer,
            &vae,
            (d.frames as u64, u64::from(d.height), u64::from(d.width)),
            config.train.precision.kind(device),
            device,
            aligned.then_some(&tiles),
            args.guided,
        )?;
        println!("{plan}");
        return Ok(());
    }
    let plan = trainer::training::plan::plan_run(&config, args.world_size.map(|n| n as usize), device)?;
    println!("{plan}");
    Ok(())
}

fn run_eval(args: EvalArgs) -> anyhow::Result<()> {
    use trainer::eval::{inception, lpips, score};
    let write = |path: &Option<PathBuf>, text: &str| -> anyhow::Result<()> {
        if let Some(out) = path {
            std::fs::write(out, text).with_context(|| format!("writing {}", out.display()))?;
        }
        Ok(())
    };
    let bundle = match (&args.bundle, args.dataset, &args.method) {
        (Some(root), Some(dataset), Some(method)) => Some(score::Bundle {
            root: root.clone(),
            dataset: match dataset {
                BundleDatasetArg::Kubric4d => score::BundleDataset::Kubric4d,
                BundleDatasetArg::Pardom4d => score::BundleDataset::Pardom4d,
                BundleDatasetArg::Dycheck => score::BundleDataset::Dycheck,
            },
            method: method.clone(),
            dycheck_720p: args.dycheck_resolution == DycheckResolutionArg::P720,
        }),
        _ => None,
    };
    // clap requires --pred and --target without --bundle.
    let (pred, target) = (args.pred.clone().unwrap_or_default(), args.target.clone().unwrap_or_default());
    // One pair: a video file, or a folder holding frames itself (not videos).
    let single =
        bundle.is_none() && (pred.is_file() || trainer::eval::metrics::read_frames(&pred).is_ok_and(|f| !f.is_empty()));
    let wants = |m: MetricArg| args.metrics.contains(&m);
    let networks = args.lpips_weights.is_some() || args.inception_weights.is_some() || !args.metrics.is_empty();
    if single && !networks && args.protocol.is_none() && args.top_k.is_none() {
        let result = trainer::eval::metrics::evaluate(&pred, &target, args.mask.as_deref())?;
        let json = serde_json::to_string_pretty(&result)?;
        write(&args.out, &json)?;
        println!("{json}");
        return Ok(());
    }
    if wants(MetricArg::Lpips) && args.lpips_weights.is_none() {
        anyhow::bail!("--metrics lpips needs --lpips-weights FILE: {}", lpips::HOW_TO_GET);
    }
    if (wants(MetricArg::Fid) || wants(MetricArg::Kid)) && args.inception_weights.is_none() {
        anyhow::bail!("--metrics fid/kid needs --inception-weights FILE: {}", inception::HOW_TO_GET);
    }
    let fid_requested = args.metrics.is_empty() || wants(MetricArg::Fid) || wants(MetricArg::Kid);
    let (bundle_protocol, bundle_pairs, bundle_notes) = match &bundle {
        Some(b) => {
            let (protocol, pairs, notes) = score::bundle_pairs(b)?;
            (Some(protocol), Some(pairs), notes)
        }
        None => (None, None, Vec::new()),
    };
    let request = score::ScoreRequest {
        pred,
        target,
        mask: args.mask,
        single,
        protocol: bundle_protocol.or(args.protocol.map(|p| match p {
            ProtocolArg::Gcd => score::Protocol::Gcd,
            ProtocolArg::Dycheck => score::Protocol::Dycheck,
            ProtocolArg::Dycheck360 => score::Protocol::Dycheck360,
        })),
        top_k: args.top_k.map(|k| k as usize),
        lpips: args.lpips_weights.filter(|_| args.metrics.is_empty() || wants(MetricArg::Lpips)),
        lpips_net: match args.lpips_net {
            LpipsNetArg::Alex => lpips::LpipsNet::Alex,
            LpipsNetArg::Vgg => lpips::LpipsNet::Vgg,
        },
        inception: args.inception_weights.filter(|_| fid_requested),
        kid: args.metrics.is_empty() || wants(MetricArg::Kid),
        kid_subsets: args.kid_subsets,
        kid_subset_size: args.kid_subset_size,
        seed: args.seed,
        device: usable_device(&args.device)?,
    };
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} videos [{elapsed_precise}, eta {eta}]")
            .expect("valid template"),
    );
    let progress = |done: usize, total: usize| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    };
    let mut report = match &bundle_pairs {
        Some(pairs) => score::run_pairs(&request, pairs, progress)?,
        None => score::run(&request, progress)?,
    };
    report.notes.splice(0..0, bundle_notes);
    bar.finish_and_clear();
    let json = serde_json::to_string_pretty(&report)?;
    let table = score::markdown(&report);
    write(&args.out, &json)?;
    write(&args.markdown, &table)?;
    println!("{table}\n{json}");
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
        kind: trainer::precision::parse_dtype(&args.dtype)?,
        device: usable_device(&args.device)?,
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

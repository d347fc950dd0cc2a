//! `trainer nvs`: the whole novel-view job on one video (finetune, render, sample).

use std::path::PathBuf;

use clap::Args;

use super::common::{DeviceArgs, ModelArgs, SamplingArgs, SequenceArgs, SwitchArg, progress_bar, show_step, step_bar};
use crate::pipelines::nvs::{DEFAULT_FINETUNE_STEPS, NvsRequest, NvsSettings, Progress};

/// `trainer nvs`'s flags.
#[derive(Debug, Args)]
pub struct NvsArgs {
    /// Checkpoint to finetune and sample: the released CogNVS transformer folder (with
    /// --base-model), a run's checkpoint, or a pipeline folder with transformer/.
    #[arg(long)]
    pub init: PathBuf,
    /// The video's sequence folder and its layout.
    #[command(flatten)]
    pub input: SequenceArgs,
    /// A camera path (.npy (N,4,4), .json, or the public trajs/*.txt); repeatable. The outputs
    /// are named after the file's stem.
    #[arg(long = "trajectory", required = true)]
    pub trajectories: Vec<PathBuf>,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// How the nvs job finetunes and samples.
    #[command(flatten)]
    pub job: JobArgs,
    /// Sampled trajectories per clip for the finetuning pairs (the paper: 5 for DyCheck, 9 for
    /// Kubric-4D and ParDom-4D).
    #[arg(long = "finetune-trajectories", default_value_t = 5)]
    pub finetune_trajectories: u32,
    /// The compute device.
    #[command(flatten)]
    pub device: DeviceArgs,
}

/// The nvs job's settings as flags (shared by `nvs` and `benchmark`; the finetuning
/// trajectories' default differs, so each command has its own flag).
#[derive(Debug, Args)]
pub struct JobArgs {
    /// Test-time finetuning steps (`benchmark`: per scene; 0: sample the checkpoint as it is).
    #[arg(long, default_value_t = DEFAULT_FINETUNE_STEPS)]
    pub steps: u64,
    /// Training TOML for finetuning (required for a checkpoint that is not a trainer run's:
    /// configs/finetune_5b_lora_1gpu.toml, finetune_5b_full_1gpu.toml or finetune_5b_full.toml).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Where the models come from besides the checkpoint.
    #[command(flatten)]
    pub model: ModelArgs,
    /// Denoising steps per sample.
    #[arg(long, default_value_t = 50)]
    pub sample_steps: usize,
    /// How each conditioning is sampled.
    #[command(flatten)]
    pub sampling: SamplingArgs,
    /// Fill render holes from the static background stacked over all frames: auto (when the
    /// video has more frames than are sampled), on or off.
    #[arg(long, value_enum, default_value_t = SwitchArg::Auto)]
    pub stack_background: SwitchArg,
}

impl JobArgs {
    /// The library's settings for checkpoint `init`, finetuning on `finetune_trajectories` per
    /// clip, sampling on `device`.
    pub fn settings(self, init: PathBuf, finetune_trajectories: u32, device: tch::Device) -> NvsSettings {
        NvsSettings {
            model: self.model.source(init),
            steps: self.steps,
            finetune_trajectories,
            config: self.config,
            sample_steps: self.sample_steps,
            guidance: self.sampling.guidance,
            seed: self.sampling.seed,
            load: self.sampling.load(device),
            framing: self.sampling.framing(),
            stack_background: self.stack_background.choice(),
        }
    }
}

impl NvsArgs {
    /// The library's request.
    pub fn request(self) -> crate::Result<NvsRequest> {
        let device = self.device.usable()?;
        Ok(NvsRequest {
            sequence: self.input.sequence,
            layout: self.input.layout,
            trajectories: self.trajectories,
            out: self.out,
            settings: self.job.settings(self.init, self.finetune_trajectories, device),
        })
    }
}

/// Runs (or continues) the job with progress bars and prints its outputs; true when a
/// preemption stopped it.
pub fn run(args: NvsArgs) -> anyhow::Result<bool> {
    let request = args.request()?;
    let out = &request.out;
    let mut bar = indicatif::ProgressBar::hidden();
    let device = request.settings.load.device;
    let outcome = crate::pipelines::nvs::run_launched(&request, device, &mut |event| match event {
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
            out.join("nvs.json").display(),
            crate::training::preempt::EXIT_PREEMPTED
        );
        return Ok(true);
    }
    if let Some(record) = outcome.record {
        for output in &record.outputs {
            println!(
                "{}: {} ({} frames), {}",
                output.name,
                out.join(output.video.as_deref().unwrap_or_default()).display(),
                output.digests.len().saturating_sub(2),
                out.join(output.sheet.as_deref().unwrap_or_default()).display()
            );
        }
        println!("settings, seeds and digests: {}", out.join("nvs.json").display());
    }
    Ok(false)
}

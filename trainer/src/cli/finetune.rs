//! `trainer finetune`: test-time finetuning of a checkpoint on one video's own pairs.

use std::path::PathBuf;

use clap::Args;

use super::common::{DeviceArgs, ModelArgs, SequenceArgs, show_run, step_bar};
use crate::training::FinetuneRequest;

/// `trainer finetune`'s flags.
#[derive(Debug, Args)]
pub struct FinetuneArgs {
    /// Checkpoint to start from (RUN/checkpoints/step-N).
    #[arg(long)]
    pub init: PathBuf,
    /// The video's sequence folder and its layout.
    #[command(flatten)]
    pub input: SequenceArgs,
    /// Run folder for the finetuned checkpoints, metrics and the pairs built.
    #[arg(long)]
    pub out: PathBuf,
    /// Optimizer steps.
    #[arg(long, default_value_t = 200, value_parser = clap::value_parser!(u64).range(1..))]
    pub steps: u64,
    /// Sampled trajectories per clip.
    #[arg(long, default_value_t = 2)]
    pub trajectories: u32,
    /// Training TOML overriding the init run's settings (required for a checkpoint that is not
    /// a trainer run's, such as the released CogNVS transformer: configs/finetune_5b_*.toml).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Where the models come from besides the checkpoint.
    #[command(flatten)]
    pub model: ModelArgs,
    /// Continue the run in --out from its newest intact checkpoint (after a preemption, exit
    /// status 75), on the pairs it built.
    #[arg(long)]
    pub resume: bool,
    /// The compute device.
    #[command(flatten)]
    pub device: DeviceArgs,
}

impl FinetuneArgs {
    /// The library's request.
    pub fn request(self) -> FinetuneRequest {
        FinetuneRequest {
            init: self.init,
            base_model: self.model.base_model,
            vae: self.model.vae,
            text_embedding: self.model.text_embedding,
            zero_text_embedding: self.model.zero_text_embedding,
            sequence: self.input.sequence,
            layout: self.input.layout,
            read: None,
            out: self.out,
            steps: self.steps,
            trajectories: self.trajectories,
            config: self.config,
            lora: self.model.lora,
            resume: self.resume,
        }
    }
}

/// Finetunes (or continues) the run; true when a preemption stopped it.
pub fn run(args: FinetuneArgs) -> anyhow::Result<bool> {
    let device = args.device.usable()?;
    let request = args.request();
    let bar = step_bar(request.steps);
    let summary = crate::training::finetune_launched(&request, device, |event| show_run(&bar, event))?;
    bar.finish_and_clear();
    println!(
        "finetuned {} steps into {}; checkpoint: {}",
        summary.steps,
        request.out.display(),
        summary.last_checkpoint.map_or("none".to_string(), |p| p.display().to_string())
    );
    Ok(summary.preempted)
}

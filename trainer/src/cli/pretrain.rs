//! `trainer pretrain`: the transformer trained on pair shards.

use std::path::PathBuf;

use clap::Args;

use super::common::{DeviceArgs, show_run, step_bar};

/// `trainer pretrain`'s flags.
#[derive(Debug, Args)]
pub struct PretrainArgs {
    /// Training TOML: [model] (transformer, vae, text_embedding), [data] (frames, height, width,
    /// batch_size, seed), [optim], [loop] (see configs/pretrain_tiny.toml).
    #[arg(long)]
    pub config: PathBuf,
    /// Shard folders or files; repeatable.
    #[arg(long, required = true, num_args = 1..)]
    pub shards: Vec<PathBuf>,
    /// Run folder: checkpoints/, metrics.jsonl, config.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Continue the run in --out from its newest intact checkpoint (every file checked against
    /// the digests its state.json lists; damaged ones are skipped, naming the file).
    #[arg(long)]
    pub resume: bool,
    /// Optimizer steps in all, overriding the config's `loop.steps`.
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub steps: Option<u64>,
    /// The compute device.
    #[command(flatten)]
    pub device: DeviceArgs,
}

/// Trains (or continues) the run; true when a preemption stopped it.
pub fn run(args: PretrainArgs) -> anyhow::Result<bool> {
    let mut config = crate::training::PretrainConfig::from_toml_file(&args.config)?;
    if let Some(steps) = args.steps {
        config.train.steps = steps;
    }
    let device = args.device.usable()?;
    let bar = step_bar(config.train.steps);
    let source_name = args.config.display().to_string();
    let summary =
        crate::training::pretrain_launched(&config, &source_name, &args.shards, &args.out, args.resume, device, |e| {
            show_run(&bar, e)
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

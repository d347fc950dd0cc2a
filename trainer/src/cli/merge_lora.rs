//! `trainer merge-lora`: a LoRA file merged into a base transformer, written as a full one.

use std::path::PathBuf;

use clap::Args;

/// `trainer merge-lora`'s flags.
#[derive(Debug, Args)]
pub struct MergeLoraArgs {
    /// Base transformer: a diffusers folder, a checkpoint with transformer/, or a LoRA run's
    /// checkpoint (its base is found in the run).
    #[arg(long)]
    pub base: PathBuf,
    /// The LoRA file (pytorch_lora_weights.safetensors: ours, diffusers' or peft's layout).
    #[arg(long)]
    pub lora: PathBuf,
    /// Output transformer folder.
    #[arg(long)]
    pub out: PathBuf,
}

/// Merges and prints how many layers were adapted.
pub fn run(args: MergeLoraArgs) -> anyhow::Result<()> {
    let merged = crate::loaders::lora::merge_lora(&args.base, &args.lora, &args.out)?;
    println!("merged {merged} adapted layers into {}", args.out.display());
    Ok(())
}

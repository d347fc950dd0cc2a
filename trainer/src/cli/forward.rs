//! `trainer forward`: one component on tensors from a safetensors file.

use std::path::PathBuf;

use clap::{Args, ValueEnum};

use super::common::DeviceArgs;
use crate::pipelines::forward::{self, ForwardRequest, Module};

/// `trainer forward`'s flags.
#[derive(Debug, Args)]
pub struct ForwardArgs {
    /// Which component to run.
    #[arg(long, value_enum)]
    pub module: ModuleArg,
    /// The component's diffusers config.json (or the model folder holding it).
    #[arg(long)]
    pub config: PathBuf,
    /// Weights: a .safetensors file, a .safetensors.index.json (sharded) or a model folder.
    #[arg(long)]
    pub weights: PathBuf,
    /// Input tensors (safetensors).
    #[arg(long)]
    pub inputs: PathBuf,
    /// Output file (safetensors, one tensor).
    #[arg(long)]
    pub out: PathBuf,
    /// Compute dtype: f32 or bf16.
    #[arg(long, default_value = "f32")]
    pub dtype: String,
    /// The compute device.
    #[command(flatten)]
    pub device: DeviceArgs,
    /// VAE only: split large frames into diffusers' default spatial tiles (bounds memory).
    #[arg(long)]
    pub tiling: bool,
}

/// `--module`.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum ModuleArg {
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

impl ForwardArgs {
    /// The library's request.
    pub fn request(&self) -> crate::Result<ForwardRequest> {
        Ok(ForwardRequest {
            module: match self.module {
                ModuleArg::Transformer => Module::Transformer,
                ModuleArg::VaeEncoder => Module::VaeEncoder,
                ModuleArg::VaeDecoder => Module::VaeDecoder,
            },
            config: self.config.clone(),
            weights: self.weights.clone(),
            inputs: self.inputs.clone(),
            out: self.out.clone(),
            kind: crate::precision::parse_dtype(&self.dtype)?,
            device: self.device.usable()?,
            tiling: self.tiling,
        })
    }
}

/// Runs the component and prints the shapes and timings.
pub fn run(args: ForwardArgs) -> anyhow::Result<()> {
    // No context line: the library's error names the file and tensor on the first line.
    let report = forward::run(&args.request()?)?;
    for (name, shape) in &report.inputs {
        println!("input  {name}: {shape:?}");
    }
    for name in &report.ignored_inputs {
        println!("ignored input `{name}` (not read by this module)");
    }
    println!("output {}: {:?} → {}", report.output.0, report.output.1, args.out.display());
    println!(
        "load {:.2} s, forward {:.2} s on {} ({})",
        report.load_seconds, report.forward_seconds, args.device.device, args.dtype
    );
    Ok(())
}

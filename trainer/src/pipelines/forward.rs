//! One forward pass of a model component on tensors from a safetensors file: the `trainer
//! forward` command, for checking a port or a checkpoint against another implementation.
//!
//! Tensor names follow diffusers' argument names: the transformer reads `hidden_states`
//! `[B, F, C, H, W]`, `encoder_hidden_states` `[B, S, D]` and `timestep` `[B]` and writes `sample`;
//! the VAE encoder reads `sample` `[B, 3, F, H, W]` and writes `latent` (the posterior mean,
//! unscaled); the VAE decoder reads `latent` and writes `sample`. The transformer computes its
//! rotary table the way the CogNVS trainer does (`grid_type="slice"` over the latent patch grid).
//! Outputs are written as fp32 whatever the compute dtype (bf16 → fp32 is exact).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use tch::{Device, Kind, Tensor};

use crate::diffusers_config::DiffusersConfig;
use crate::error::{Error, Result};
use crate::models::autoencoder_kl_cogvideox::{self as vae, AutoencoderKLCogVideoXConfig, TilingConfig};
use crate::models::cogvideox_transformer_3d::{
    self as transformer, CogVideoXTransformer3DModelConfig, TransformerInput,
};
use crate::models::weights;

/// Which component runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Module {
    /// `CogVideoXTransformer3DModel`.
    Transformer,
    /// The VAE's encoder (video → posterior mean).
    VaeEncoder,
    /// The VAE's decoder (latent → video).
    VaeDecoder,
}

impl Module {
    /// The input tensors this module reads, in order.
    pub fn input_names(self) -> &'static [&'static str] {
        match self {
            Module::Transformer => &["hidden_states", "encoder_hidden_states", "timestep"],
            Module::VaeEncoder => &["sample"],
            Module::VaeDecoder => &["latent"],
        }
    }

    /// The output tensor's name.
    pub fn output_name(self) -> &'static str {
        match self {
            Module::Transformer | Module::VaeDecoder => "sample",
            Module::VaeEncoder => "latent",
        }
    }
}

/// What to run, on what.
#[derive(Debug, Clone)]
pub struct ForwardRequest {
    /// The component.
    pub module: Module,
    /// Its diffusers `config.json` (or the folder holding it).
    pub config: PathBuf,
    /// Its weights: a `.safetensors` file, a `.safetensors.index.json` or a model folder.
    pub weights: PathBuf,
    /// The input tensors.
    pub inputs: PathBuf,
    /// Where the output goes (a safetensors file with one tensor).
    pub out: PathBuf,
    /// Compute dtype (weights and floating-point inputs are converted to it).
    pub kind: Kind,
    /// Compute device.
    pub device: Device,
    /// VAE only: spatial tiling with diffusers' default tiles for the config.
    pub tiling: bool,
}

/// What a forward run did.
#[derive(Debug, Clone)]
pub struct ForwardReport {
    /// Input names and shapes.
    pub inputs: Vec<(String, Vec<i64>)>,
    /// Output name and shape.
    pub output: (String, Vec<i64>),
    /// Input names in the file that the module does not read.
    pub ignored_inputs: Vec<String>,
    /// Seconds to build the model and load its weights.
    pub load_seconds: f64,
    /// Seconds of the forward pass.
    pub forward_seconds: f64,
}

/// Runs the request: config → model (shapes checked against the checkpoint's headers before
/// anything is allocated) → weights → forward → `out`.
pub fn run(request: &ForwardRequest) -> Result<ForwardReport> {
    let mut file: BTreeMap<String, Tensor> = weights::read_safetensors(&request.inputs)?;
    let mut inputs = Vec::new();
    for &name in request.module.input_names() {
        let tensor = file.remove(name).ok_or_else(|| Error::InvalidArgument {
            name: "inputs".to_string(),
            reason: format!(
                "{}: no tensor `{name}` (this module reads {})",
                request.inputs.display(),
                request.module.input_names().join(", ")
            ),
        })?;
        // Timesteps may be integers (diffusers takes both); every other input is a float tensor.
        if name != "timestep" {
            weights::check_floating(&request.inputs, name, &tensor)?;
        }
        let tensor = if tensor.is_floating_point() { tensor.f_to_kind(request.kind)? } else { tensor };
        inputs.push(tensor.f_to_device(request.device)?);
    }
    let ignored_inputs: Vec<String> = file.into_keys().collect();

    let started = Instant::now();
    let (output, load_seconds) = tch::no_grad(|| -> Result<(Tensor, f64)> {
        match request.module {
            Module::Transformer => {
                let config = CogVideoXTransformer3DModelConfig::from_json_file(&request.config)?;
                check_weights(&transformer::variable_shapes(&config)?, &request.weights)?;
                let (vs, model) = transformer::build(&config, request.device, request.kind)?;
                weights::load(&vs, &request.weights)?;
                let load_seconds = started.elapsed().as_secs_f64();
                let input = TransformerInput {
                    hidden_states: &inputs[0],
                    encoder_hidden_states: &inputs[1],
                    timestep: &inputs[2],
                    ofs: None,
                    image_rotary_emb: None,
                };
                Ok((model.forward(&input, false)?, load_seconds))
            }
            Module::VaeEncoder | Module::VaeDecoder => {
                let config = AutoencoderKLCogVideoXConfig::from_json_file(&request.config)?;
                // Truncated or mislabelled weight files fail before the model is allocated.
                weights::read_checkpoint_info(&request.weights)?;
                let (vs, mut model) = vae::build(&config, request.device, request.kind)?;
                weights::load(&vs, &request.weights)?;
                if request.tiling {
                    model.enable_tiling(TilingConfig::for_config(&config))?;
                }
                let load_seconds = started.elapsed().as_secs_f64();
                let out = if request.module == Module::VaeEncoder {
                    model.encode(&inputs[0])?
                } else {
                    model.decode(&inputs[0])?
                };
                Ok((out, load_seconds))
            }
        }
    })?;
    let forward_seconds = started.elapsed().as_secs_f64() - load_seconds;
    let output = output.f_to_kind(Kind::Float)?.f_to_device(Device::Cpu)?.f_contiguous()?;
    let name = request.module.output_name();
    if let Some(parent) = request.out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|source| Error::Io { path: parent.to_path_buf(), error: source })?;
    }
    Tensor::write_safetensors(&[(name, &output)], &request.out)
        .map_err(|e| Error::Safetensors { path: request.out.clone(), reason: e.to_string() })?;
    Ok(ForwardReport {
        inputs: request.module.input_names().iter().zip(&inputs).map(|(n, t)| (n.to_string(), t.size())).collect(),
        output: (name.to_string(), output.size()),
        ignored_inputs,
        load_seconds,
        forward_seconds,
    })
}

/// Names and shapes of a checkpoint against a model's, from the headers only.
fn check_weights(expected: &BTreeMap<String, Vec<i64>>, checkpoint: &Path) -> Result<()> {
    let found = weights::read_checkpoint_info(checkpoint)?;
    weights::check_against(expected, &found, checkpoint)
}

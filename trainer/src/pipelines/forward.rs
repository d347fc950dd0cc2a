//! One forward pass of a model component on tensors from a safetensors file: the `trainer
//! forward` command, for checking a port or a checkpoint against another implementation.
//!
//! The config's `_class_name` selects the model family (a config without one is CogVideoX's, as
//! before the Wan family existed). Tensor names follow diffusers' argument names:
//! - `CogVideoXTransformer3DModel` reads `hidden_states` `[B, F, C, H, W]`,
//!   `encoder_hidden_states` `[B, S, D]` and `timestep` `[B]` and writes `sample`; it computes its
//!   rotary table the way the CogNVS trainer does (`grid_type="slice"` over the latent patch grid);
//! - `WanTransformer3DModel` reads `hidden_states` `[B, C, F, H, W]`, `timestep` `[B]` (or
//!   `[B, tokens]`), `encoder_hidden_states` `[B, S, D]` and, for image-to-video configs,
//!   `encoder_hidden_states_image` `[B, N, image_dim]`, and writes `sample`;
//! - the VAE encoders (`AutoencoderKLCogVideoX`, `AutoencoderKLWan`) read `sample`
//!   `[B, 3, F, H, W]` and write `latent` (the posterior mean, unscaled); the decoders read
//!   `latent` and write `sample`.
//!
//! Outputs are written as fp32 whatever the compute dtype (bf16 → fp32 is exact).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use tch::{Device, Kind, Tensor};

use crate::diffusers_config::DiffusersConfig;
use crate::error::{Error, Result};
use crate::models::cogvideox::autoencoder_kl_cogvideox::{self as vae, AutoencoderKLCogVideoXConfig, TilingConfig};
use crate::models::cogvideox::cogvideox_transformer_3d::{
    self as transformer, CogVideoXTransformer3DModelConfig, TransformerInput,
};
use crate::models::family::{Job, ModelFamily};
use crate::models::wan::autoencoder_kl_wan::{self as wan_vae, AutoencoderKLWanConfig};
use crate::models::wan::transformer_wan::{self as wan_transformer, WanTransformer3DModelConfig, WanTransformerInput};
use crate::models::weights;

/// Which component runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Module {
    /// `CogVideoXTransformer3DModel` or `WanTransformer3DModel`.
    Transformer,
    /// The VAE's encoder (video → posterior mean).
    VaeEncoder,
    /// The VAE's decoder (latent → video).
    VaeDecoder,
}

impl Module {
    /// The output tensor's name.
    pub fn output_name(self) -> &'static str {
        match self {
            Module::Transformer | Module::VaeDecoder => "sample",
            Module::VaeEncoder => "latent",
        }
    }

    /// The family of this module's config: its `_class_name` (see [`ModelFamily`]).
    fn family(self, config: &Path) -> Result<ModelFamily> {
        let family = match self {
            Module::Transformer => ModelFamily::of_transformer(config)?,
            Module::VaeEncoder | Module::VaeDecoder => ModelFamily::of_vae(config)?,
        };
        family.require(Job::Forward, config)
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

/// The input tensors of a run, taken by name, converted to the compute dtype and device.
struct Inputs<'a> {
    request: &'a ForwardRequest,
    file: BTreeMap<String, Tensor>,
    read: Vec<(String, Vec<i64>)>,
}

impl Inputs<'_> {
    /// The tensor `name`, if the file has it. Timesteps may be integers (diffusers takes both);
    /// every other input must be a float tensor.
    fn optional(&mut self, name: &str) -> Result<Option<Tensor>> {
        let Some(tensor) = self.file.remove(name) else { return Ok(None) };
        if name != "timestep" {
            weights::check_floating(&self.request.inputs, name, &tensor)?;
        }
        let tensor = if tensor.is_floating_point() { tensor.f_to_kind(self.request.kind)? } else { tensor };
        self.read.push((name.to_string(), tensor.size()));
        Ok(Some(tensor.f_to_device(self.request.device)?))
    }

    /// The tensor `name`; `all` lists what the module reads, for the message.
    fn required(&mut self, name: &str, all: &[&str]) -> Result<Tensor> {
        self.optional(name)?.ok_or_else(|| Error::InvalidArgument {
            name: "inputs".to_string(),
            reason: format!(
                "{}: no tensor `{name}` (this module reads {})",
                self.request.inputs.display(),
                all.join(", ")
            ),
        })
    }
}

/// Runs the request: config (its `_class_name` picks the family) → model (shapes checked against
/// the checkpoint's headers before anything is allocated) → weights → forward → `out`.
pub fn run(request: &ForwardRequest) -> Result<ForwardReport> {
    let file: BTreeMap<String, Tensor> = weights::read_safetensors(&request.inputs)?;
    let mut inputs = Inputs { request, file, read: Vec::new() };
    let family = request.module.family(&request.config)?;
    let started = Instant::now();
    let (output, load_seconds) = tch::no_grad(|| -> Result<(Tensor, f64)> {
        let loaded = || started.elapsed().as_secs_f64();
        match (request.module, family) {
            (Module::Transformer, ModelFamily::Wan) => {
                const NAMES: [&str; 4] =
                    ["hidden_states", "timestep", "encoder_hidden_states", "encoder_hidden_states_image (I2V)"];
                let hidden_states = inputs.required("hidden_states", &NAMES)?;
                let timestep = inputs.required("timestep", &NAMES)?;
                let encoder_hidden_states = inputs.required("encoder_hidden_states", &NAMES)?;
                let image = inputs.optional("encoder_hidden_states_image")?;
                let config = WanTransformer3DModelConfig::from_json_file(&request.config)?;
                let ignored = &wan_transformer::KEYS_TO_IGNORE_ON_LOAD_UNEXPECTED;
                check_weights(&wan_transformer::variable_shapes(&config)?, &request.weights, ignored)?;
                let (vs, model) = wan_transformer::build(&config, request.device, request.kind)?;
                wan_transformer::load(&vs, &request.weights)?;
                let load_seconds = loaded();
                let input = WanTransformerInput {
                    hidden_states: &hidden_states,
                    timestep: &timestep,
                    encoder_hidden_states: &encoder_hidden_states,
                    encoder_hidden_states_image: image.as_ref(),
                };
                Ok((model.forward(&input)?, load_seconds))
            }
            (Module::Transformer, ModelFamily::CogVideoX) => {
                const NAMES: [&str; 3] = ["hidden_states", "encoder_hidden_states", "timestep"];
                let hidden_states = inputs.required("hidden_states", &NAMES)?;
                let encoder_hidden_states = inputs.required("encoder_hidden_states", &NAMES)?;
                let timestep = inputs.required("timestep", &NAMES)?;
                let config = CogVideoXTransformer3DModelConfig::from_json_file(&request.config)?;
                check_weights(&transformer::variable_shapes(&config)?, &request.weights, &[])?;
                let (vs, model) = transformer::build(&config, request.device, request.kind)?;
                weights::load(&vs, &request.weights)?;
                let load_seconds = loaded();
                let input = TransformerInput {
                    hidden_states: &hidden_states,
                    encoder_hidden_states: &encoder_hidden_states,
                    timestep: &timestep,
                    ofs: None,
                    image_rotary_emb: None,
                };
                Ok((model.forward(&input, false)?, load_seconds))
            }
            (Module::VaeEncoder | Module::VaeDecoder, family) => {
                let encoding = request.module == Module::VaeEncoder;
                let name = if encoding { "sample" } else { "latent" };
                let input = inputs.required(name, &[name])?;
                // Truncated or mislabelled weight files fail before the model is allocated.
                weights::read_checkpoint_info(&request.weights)?;
                if family == ModelFamily::Wan {
                    if request.tiling {
                        return Err(Error::InvalidArgument {
                            name: "--tiling".to_string(),
                            reason: format!("spatial tiling is not implemented for {}", family.vae_class()),
                        });
                    }
                    let config = AutoencoderKLWanConfig::from_json_file(&request.config)?;
                    let (vs, model) = wan_vae::build(&config, request.device, request.kind)?;
                    weights::load(&vs, &request.weights)?;
                    let load_seconds = loaded();
                    let out = if encoding { model.encode(&input)? } else { model.decode(&input)? };
                    return Ok((out, load_seconds));
                }
                let config = AutoencoderKLCogVideoXConfig::from_json_file(&request.config)?;
                let (vs, mut model) = vae::build(&config, request.device, request.kind)?;
                weights::load(&vs, &request.weights)?;
                if request.tiling {
                    model.enable_tiling(TilingConfig::for_config(&config))?;
                }
                let load_seconds = loaded();
                let out = if encoding { model.encode(&input)? } else { model.decode(&input)? };
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
        inputs: inputs.read,
        output: (name.to_string(), output.size()),
        ignored_inputs: inputs.file.into_keys().collect(),
        load_seconds,
        forward_seconds,
    })
}

/// Names and shapes of a checkpoint against a model's, from the headers only.
fn check_weights(expected: &BTreeMap<String, Vec<i64>>, checkpoint: &Path, ignored: &[&str]) -> Result<()> {
    let mut found = weights::read_checkpoint_info(checkpoint)?;
    found.retain(|name, _| expected.contains_key(name) || !ignored.iter().any(|p| name.contains(p)));
    weights::check_against(expected, &found, checkpoint)
}

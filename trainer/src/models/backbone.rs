//! The one model interface the jobs reach a backbone through: a family's transformer and VAE
//! behind one type each ([`Transformer`], [`Vae`] and their configs), so that sampling, the
//! training objective, the latent cache and checkpointing hold no family's types.
//!
//! What differs between the families lives here and in [`ModelFamily`], once:
//! - which family a model folder is (its `config.json`'s `_class_name`) and its presets;
//! - the VAE's latent rule: frames `1 + (F − 1)/t`, the scaling the diffusion model sees
//!   (CogVideoX: × `scaling_factor`, laid out `[B, F', C, h, w]`; Wan: the per-channel latent
//!   statistics, laid out `[B, C, F', h, w]`) and the channel axis the inputs are joined on;
//! - the model input from the CogNVS conditioning (CogVideoX: the render's latent; Wan: the hole
//!   mask folded onto the latent grid, then the render's latent: see [`crate::models::wan::cognvs`]);
//! - the transformer's forward (and the block-by-block tape for the backward, where the family
//!   has one), its weights' layout and the training objective ([`crate::models::family::Objective`]).
//!
//! Adding a family adds `models/<family>/`, a variant to each enum here and to [`ModelFamily`];
//! no pipeline or training loop changes.

use std::collections::BTreeMap;
use std::path::Path;

use tch::{Device, Kind, Tensor, nn};

use crate::diffusers_config;
use crate::error::{Error, Result};
use crate::models::cogvideox::autoencoder_kl_cogvideox::{
    self as cog_vae, AutoencoderKLCogVideoX, AutoencoderKLCogVideoXConfig, DiagonalGaussian,
};
use crate::models::cogvideox::cogvideox_transformer_3d::{
    self as cog_transformer, BlockTape, CogVideoXTransformer3DModel, CogVideoXTransformer3DModelConfig,
    TransformerInput,
};
use crate::models::family::ModelFamily;
use crate::models::lora::LoraConfig;
use crate::models::wan::autoencoder_kl_wan::{self as wan_vae, AutoencoderKLWan, AutoencoderKLWanConfig};
use crate::models::wan::transformer_wan::{
    self as wan_transformer, WanTransformer3DModel, WanTransformer3DModelConfig, WanTransformerInput,
};
use crate::models::weights::{self, WrittenFile};

/// The text tokens a transformer takes, `[sequence, width]`: the shape of a text embedding file.
pub trait TextShape {
    /// `[S, D]` of `encoder_hidden_states` without the batch axis.
    fn text_shape(&self) -> [i64; 2];
}

impl TextShape for CogVideoXTransformer3DModelConfig {
    fn text_shape(&self) -> [i64; 2] {
        [self.max_text_seq_length, self.text_embed_dim]
    }
}

impl TextShape for WanTransformer3DModelConfig {
    /// The umT5 context the Wan pipelines pad every prompt to.
    fn text_shape(&self) -> [i64; 2] {
        [wan_transformer::TEXT_CONTEXT_LENGTH, self.text_dim]
    }
}

/// A transformer's config, of either family.
#[derive(Debug, Clone, PartialEq)]
pub enum TransformerConfig {
    /// `CogVideoXTransformer3DModel`.
    CogVideoX(CogVideoXTransformer3DModelConfig),
    /// `WanTransformer3DModel`.
    Wan(WanTransformer3DModelConfig),
}

impl TransformerConfig {
    /// Reads a transformer `config.json` (or the one in a folder) as its `_class_name`'s family
    /// says; returns the read's warnings (unknown keys) for the caller to print once.
    pub fn read_quiet(path: &Path) -> Result<(Self, Vec<String>)> {
        Ok(match ModelFamily::of_transformer(path)? {
            ModelFamily::CogVideoX => diffusers_config::read_quiet(path).map(|(c, w)| (Self::CogVideoX(c), w))?,
            ModelFamily::Wan => diffusers_config::read_quiet(path).map(|(c, w)| (Self::Wan(c), w))?,
        })
    }

    /// A preset by name: CogVideoX's (`tiny`, `cognvs-5b`, `cogvideox-2b`) or Wan's
    /// (`wan2.1-t2v-1.3b`, …, `tiny-t2v`, `tiny-i2v`, `tiny-cognvs`).
    pub fn preset(name: &str) -> Result<Self> {
        match CogVideoXTransformer3DModelConfig::preset(name) {
            Ok(config) => Ok(Self::CogVideoX(config)),
            Err(cog) => WanTransformer3DModelConfig::preset(name).map(Self::Wan).map_err(|wan| Error::InvalidConfig {
                source_name: "preset".to_string(),
                field: "name".to_string(),
                reason: format!("{cog}; {wan}"),
            }),
        }
    }

    /// The family.
    pub fn family(&self) -> ModelFamily {
        match self {
            Self::CogVideoX(_) => ModelFamily::CogVideoX,
            Self::Wan(_) => ModelFamily::Wan,
        }
    }

    /// Input channels of the patch embedding (noisy latents and the condition).
    pub fn in_channels(&self) -> i64 {
        match self {
            Self::CogVideoX(c) => c.in_channels,
            Self::Wan(c) => c.in_channels,
        }
    }

    /// Output (latent) channels.
    pub fn output_channels(&self) -> i64 {
        match self {
            Self::CogVideoX(c) => c.output_channels(),
            Self::Wan(c) => c.output_channels(),
        }
    }

    /// Name → shape of every variable, without allocating the model.
    pub fn variable_shapes(&self) -> Result<BTreeMap<String, Vec<i64>>> {
        match self {
            Self::CogVideoX(c) => cog_transformer::variable_shapes(c),
            Self::Wan(c) => wan_transformer::variable_shapes(c),
        }
    }

    /// Checks a LoRA config against the model (every target matches a layer); the number of
    /// adapted layers.
    pub fn check_lora(&self, lora: &LoraConfig) -> Result<usize> {
        match self {
            Self::CogVideoX(c) => cog_transformer::check_lora(c, lora),
            Self::Wan(c) => wan_transformer::lora_shapes(c, lora).map(|adapters| adapters.len()),
        }
    }

    /// The spatial patch `[ph, pw]` a latent side must be a multiple of.
    pub fn spatial_patch(&self) -> [i64; 2] {
        match self {
            Self::CogVideoX(c) => [c.patch_size, c.patch_size],
            Self::Wan(c) => [c.patch_size[1], c.patch_size[2]],
        }
    }
}

impl TextShape for TransformerConfig {
    fn text_shape(&self) -> [i64; 2] {
        match self {
            Self::CogVideoX(c) => c.text_shape(),
            Self::Wan(c) => c.text_shape(),
        }
    }
}

/// A VAE's config, of either family.
#[derive(Debug, Clone, PartialEq)]
pub enum VaeConfig {
    /// `AutoencoderKLCogVideoX`.
    CogVideoX(AutoencoderKLCogVideoXConfig),
    /// `AutoencoderKLWan`.
    Wan(AutoencoderKLWanConfig),
}

/// `AutoencoderKLWan`'s default `scale_factor_temporal` (diffusers' constructor), for configs
/// written before the key existed.
pub const WAN_DEFAULT_SCALE_FACTOR_TEMPORAL: i64 = 4;
/// `AutoencoderKLWan`'s default `scale_factor_spatial`.
pub const WAN_DEFAULT_SCALE_FACTOR_SPATIAL: i64 = 8;

impl VaeConfig {
    /// Reads a VAE folder's `config.json` as its `_class_name`'s family says, with the warnings.
    pub fn read_quiet(path: &Path) -> Result<(Self, Vec<String>)> {
        Ok(match ModelFamily::of_vae(path)? {
            ModelFamily::CogVideoX => diffusers_config::read_quiet(path).map(|(c, w)| (Self::CogVideoX(c), w))?,
            ModelFamily::Wan => diffusers_config::read_quiet(path).map(|(c, w)| (Self::Wan(c), w))?,
        })
    }

    /// A preset by name: CogVideoX's (`tiny`, `cogvideox-5b`) or Wan's (`wan2.1`, `wan2.2`,
    /// `tiny-residual`; `tiny-wan` is Wan's `tiny`, whose name CogVideoX's takes).
    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "tiny-wan" => Ok(Self::Wan(AutoencoderKLWanConfig::tiny())),
            _ => AutoencoderKLCogVideoXConfig::preset(name).map(Self::CogVideoX).or_else(|cog| {
                AutoencoderKLWanConfig::preset(name).map(Self::Wan).map_err(|wan| Error::InvalidConfig {
                    source_name: "preset".to_string(),
                    field: "name".to_string(),
                    reason: format!("{cog}; {wan}"),
                })
            }),
        }
    }

    /// A preset of `family` by name: a CogVideoX VAE preset for a CogVideoX transformer, a Wan one
    /// (`wan2.1`, `wan2.2`, `tiny`, `tiny-residual`, `tiny-wan`) for a Wan transformer, so that a
    /// name both families have (`tiny`) means the transformer's.
    pub fn preset_of(family: ModelFamily, name: &str) -> Result<Self> {
        match (family, name) {
            (ModelFamily::CogVideoX, _) => AutoencoderKLCogVideoXConfig::preset(name).map(Self::CogVideoX),
            (ModelFamily::Wan, "tiny-wan") => Ok(Self::Wan(AutoencoderKLWanConfig::tiny())),
            (ModelFamily::Wan, _) => AutoencoderKLWanConfig::preset(name).map(Self::Wan),
        }
    }

    /// The family.
    pub fn family(&self) -> ModelFamily {
        match self {
            Self::CogVideoX(_) => ModelFamily::CogVideoX,
            Self::Wan(_) => ModelFamily::Wan,
        }
    }

    /// Latent channels.
    pub fn latent_channels(&self) -> i64 {
        match self {
            Self::CogVideoX(c) => c.latent_channels,
            Self::Wan(c) => c.z_dim,
        }
    }

    /// Frames per latent frame after the first (`F = 1 + t·(F' − 1)`).
    pub fn temporal_factor(&self) -> i64 {
        match self {
            Self::CogVideoX(c) => c.effective_temporal_compression_ratio(),
            Self::Wan(c) => c.scale_factor_temporal.unwrap_or(WAN_DEFAULT_SCALE_FACTOR_TEMPORAL),
        }
    }

    /// Pixels per latent pixel along each side.
    pub fn spatial_factor(&self) -> i64 {
        match self {
            Self::CogVideoX(c) => c.spatial_compression_ratio(),
            Self::Wan(c) => c.scale_factor_spatial.unwrap_or(WAN_DEFAULT_SCALE_FACTOR_SPATIAL),
        }
    }

    /// Latent frames of a clip of `frames` frames (`frames` must be `1 + t·k`).
    pub fn latent_frames(&self, frames: i64) -> i64 {
        (frames - 1) / self.temporal_factor() + 1
    }

    /// Channels the CogNVS conditioning adds to the transformer's input: the render's latent
    /// (CogVideoX), or Wan's mask channels (one per frame of a latent frame) and the render's
    /// latent.
    pub fn condition_channels(&self) -> i64 {
        match self {
            Self::CogVideoX(c) => c.latent_channels,
            Self::Wan(c) => self.temporal_factor() + c.z_dim,
        }
    }
}

/// A transformer of either family.
#[derive(Debug)]
pub enum Transformer {
    /// `CogVideoXTransformer3DModel`.
    CogVideoX(CogVideoXTransformer3DModel),
    /// `WanTransformer3DModel`.
    Wan(WanTransformer3DModel),
}

/// A transformer's inputs in its family's layout (see [`Vae::to_model_latent`]).
pub struct ModelInput<'a> {
    /// Noisy latents.
    pub latents: &'a Tensor,
    /// The conditioning's channels ([`Vae::condition_input`]), joined after the latents.
    pub condition: &'a Tensor,
    /// Text tokens `[B, S, D]`.
    pub text: &'a Tensor,
    /// One timestep per sample `[B]`.
    pub timestep: &'a Tensor,
}

/// What [`Transformer::forward_taped`] keeps for the backward.
pub enum Tape<'a> {
    /// CogVideoX's block-by-block tape.
    Blocks(BlockTape<'a>),
    /// The plain autograd graph: one stage, final once the loss is back-propagated.
    Whole,
}

impl Tape<'_> {
    /// Finishes the backward after the loss of the output was back-propagated, calling
    /// `on_stage` for each stage whose gradients are final, in order.
    pub fn backward(self, on_stage: &mut dyn FnMut(usize) -> Result<()>) -> Result<()> {
        match self {
            Tape::Blocks(tape) => tape.backward(on_stage),
            Tape::Whole => on_stage(0),
        }
    }
}

impl Transformer {
    /// A fresh model of `config` on `device` in `kind` (random init) and its variables; with
    /// `lora`, adapters in a second store.
    pub fn build(
        config: &TransformerConfig,
        lora: Option<&LoraConfig>,
        device: Device,
        kind: Kind,
    ) -> Result<(nn::VarStore, Option<nn::VarStore>, Self)> {
        Ok(match (config, lora) {
            (TransformerConfig::CogVideoX(c), None) => {
                let (vs, model) = cog_transformer::build(c, device, kind)?;
                (vs, None, Self::CogVideoX(model))
            }
            (TransformerConfig::CogVideoX(c), Some(lora)) => {
                let (vs, lora_vs, model) = cog_transformer::build_with_lora(c, lora, device, kind)?;
                (vs, Some(lora_vs), Self::CogVideoX(model))
            }
            (TransformerConfig::Wan(c), None) => {
                let (vs, model) = wan_transformer::build(c, device, kind)?;
                (vs, None, Self::Wan(model))
            }
            (TransformerConfig::Wan(c), Some(lora)) => {
                let (vs, lora_vs, model) = wan_transformer::build_with_lora(c, lora, device, kind)?;
                (vs, Some(lora_vs), Self::Wan(model))
            }
        })
    }

    /// Loads a checkpoint folder into `vs` (names and shapes checked; the family's ignored keys
    /// skipped).
    pub fn load(&self, vs: &nn::VarStore, dir: &Path) -> Result<usize> {
        match self {
            Self::CogVideoX(_) => weights::load(vs, dir),
            Self::Wan(_) => wan_transformer::load(vs, dir),
        }
    }

    /// The config the model was built from.
    pub fn config(&self) -> TransformerConfig {
        match self {
            Self::CogVideoX(m) => TransformerConfig::CogVideoX(m.config().clone()),
            Self::Wan(m) => TransformerConfig::Wan(m.config().clone()),
        }
    }

    /// The family.
    pub fn family(&self) -> ModelFamily {
        match self {
            Self::CogVideoX(_) => ModelFamily::CogVideoX,
            Self::Wan(_) => ModelFamily::Wan,
        }
    }

    /// Writes `variables` as a diffusers model folder of this model's class and config.
    pub fn save(
        &self,
        variables: BTreeMap<String, Tensor>,
        dir: &Path,
        max_shard_bytes: u64,
    ) -> Result<Vec<WrittenFile>> {
        match self {
            Self::CogVideoX(m) => {
                weights::save_tensors(variables, m.config(), cog_transformer::CLASS_NAME, dir, max_shard_bytes)
            }
            Self::Wan(m) => {
                weights::save_tensors(variables, m.config(), wan_transformer::CLASS_NAME, dir, max_shard_bytes)
            }
        }
    }

    /// The stages of [`Tape::backward`].
    pub fn backward_stages(&self) -> usize {
        match self {
            Self::CogVideoX(m) => m.backward_stages(),
            Self::Wan(_) => 1,
        }
    }

    /// The stage after which the gradient of variable `name` is final.
    pub fn backward_stage_of(&self, name: &str) -> usize {
        match self {
            Self::CogVideoX(m) => m.backward_stage_of(name),
            Self::Wan(_) => 0,
        }
    }

    /// The prediction for `input` (the model's output in the latents' layout).
    pub fn forward(&self, input: &ModelInput<'_>, train: bool) -> Result<Tensor> {
        Ok(self.forward_taped(input, train, None)?.0)
    }

    /// The prediction and, with `taped` (`Some(checkpointing)`), what the training backward
    /// needs ([`Tape::backward`]); CogVideoX runs block by block (with gradient checkpointing
    /// when asked), Wan on the plain graph.
    pub fn forward_taped(
        &self,
        input: &ModelInput<'_>,
        train: bool,
        taped: Option<bool>,
    ) -> Result<(Tensor, Option<Tape<'_>>)> {
        match self {
            Self::CogVideoX(model) => {
                let hidden_states = Tensor::f_cat(&[input.latents, input.condition], 2)?;
                let transformer_input = TransformerInput {
                    hidden_states: &hidden_states,
                    encoder_hidden_states: input.text,
                    timestep: input.timestep,
                    ofs: None,
                    image_rotary_emb: None,
                };
                match taped {
                    Some(checkpointing) => {
                        let (out, tape) = model.forward_taped(&transformer_input, train, checkpointing)?;
                        Ok((out, Some(Tape::Blocks(tape))))
                    }
                    None => Ok((model.forward(&transformer_input, train)?, None)),
                }
            }
            Self::Wan(model) => {
                let hidden_states = Tensor::f_cat(&[input.latents, input.condition], 1)?;
                let out = model.forward(&WanTransformerInput {
                    hidden_states: &hidden_states,
                    timestep: input.timestep,
                    encoder_hidden_states: input.text,
                    encoder_hidden_states_image: None,
                })?;
                Ok((out, taped.map(|_| Tape::Whole)))
            }
        }
    }
}

/// A VAE of either family.
#[derive(Debug)]
pub enum Vae {
    /// `AutoencoderKLCogVideoX` (both boxed: the models are large and of unequal sizes).
    CogVideoX(Box<AutoencoderKLCogVideoX>),
    /// `AutoencoderKLWan`.
    Wan(Box<AutoencoderKLWan>),
}

impl Vae {
    /// A fresh VAE of `config` (random init) and its variables.
    pub fn build(config: &VaeConfig, device: Device, kind: Kind) -> Result<(nn::VarStore, Self)> {
        Ok(match config {
            VaeConfig::CogVideoX(c) => {
                let (vs, vae) = cog_vae::build(c, device, kind)?;
                (vs, Self::CogVideoX(Box::new(vae)))
            }
            VaeConfig::Wan(c) => {
                let (vs, vae) = wan_vae::build(c, device, kind)?;
                (vs, Self::Wan(Box::new(vae)))
            }
        })
    }

    /// The config the VAE was built from.
    pub fn config(&self) -> VaeConfig {
        match self {
            Self::CogVideoX(v) => VaeConfig::CogVideoX(v.config().clone()),
            Self::Wan(v) => VaeConfig::Wan(v.config().clone()),
        }
    }

    /// The config's fields as compact JSON (what keys must change with when the VAE does, such
    /// as the latent cache's).
    pub fn config_fingerprint(&self) -> String {
        match self {
            Self::CogVideoX(v) => serde_json::to_string(v.config()),
            Self::Wan(v) => serde_json::to_string(v.config()),
        }
        .expect("a config serialises")
    }

    /// Writes the VAE's variables `vs` as a diffusers model folder.
    pub fn save(&self, vs: &nn::VarStore, dir: &Path, max_shard_bytes: u64) -> Result<Vec<WrittenFile>> {
        match self {
            Self::CogVideoX(v) => weights::save(vs, v.config(), cog_vae::CLASS_NAME, dir, max_shard_bytes),
            Self::Wan(v) => weights::save(vs, v.config(), wan_vae::CLASS_NAME, dir, max_shard_bytes),
        }
    }

    /// The posterior of a video `[B, 3, F, H, W]` in [−1, 1] (in the VAE's element type), as
    /// the VAE lays latents out (`[B, C, F', h, w]`, unscaled).
    pub fn encode_posterior(&self, video: &Tensor) -> Result<DiagonalGaussian> {
        match self {
            Self::CogVideoX(v) => v.encode_posterior(video),
            Self::Wan(v) => v.encode_posterior(video),
        }
    }

    /// A VAE latent `[B, C, F', h, w]` (f32) as the diffusion model sees it: CogVideoX scales
    /// it by `scaling_factor` and lays it out `[B, F', C, h, w]`; Wan normalises it with the
    /// latent statistics and keeps the layout.
    pub fn to_model_latent(&self, latent: &Tensor) -> Result<Tensor> {
        match self {
            Self::CogVideoX(v) => {
                Ok(latent.f_mul_scalar(v.config().scaling_factor)?.f_permute([0, 2, 1, 3, 4])?.f_contiguous()?)
            }
            Self::Wan(v) => v.normalize_latents(latent),
        }
    }

    /// The axis latents and condition channels are joined on in the model's layout.
    pub fn channel_axis(&self) -> i64 {
        match self {
            Self::CogVideoX(_) => 2,
            Self::Wan(_) => 1,
        }
    }

    /// The conditioning latent the family trains and samples with, from the render's posterior:
    /// CogVideoX a posterior sample (`eps` its standard normal draw, as CogVideoX's I2V pipeline
    /// samples it), Wan the posterior mean (as `WanImageToVideoPipeline` takes the mode).
    pub fn condition_latent(&self, posterior: &DiagonalGaussian, eps: &Tensor) -> Result<Tensor> {
        match self {
            Self::CogVideoX(_) => {
                let std = posterior.logvar.f_mul_scalar(0.5)?.f_exp()?;
                Ok(posterior.mean.f_add(&std.f_mul(eps)?)?)
            }
            Self::Wan(_) => Ok(posterior.mean.shallow_clone()),
        }
    }

    /// The transformer's condition channels from the render's latent in the model's layout
    /// ([`Self::to_model_latent`]) and the hole mask `[B, 1, F, H, W]` (1 known): the latent
    /// (CogVideoX), or the mask folded onto the latent grid followed by the latent (Wan).
    pub fn condition_input(&self, latent: &Tensor, mask: &Tensor) -> Result<Tensor> {
        match self {
            Self::CogVideoX(_) => Ok(latent.shallow_clone()),
            Self::Wan(_) => {
                let config = self.config();
                let mask = crate::models::wan::cognvs::mask_channels(
                    &mask.f_to_device(latent.device())?,
                    config.temporal_factor(),
                    config.spatial_factor(),
                )?;
                Ok(Tensor::f_cat(&[mask.f_to_kind(latent.kind())?, latent.shallow_clone()], 1)?)
            }
        }
    }

    /// The VAE's element type, which its inputs must have.
    pub fn kind(&self) -> Kind {
        match self {
            Self::CogVideoX(v) => v.kind(),
            Self::Wan(v) => v.kind(),
        }
    }
}

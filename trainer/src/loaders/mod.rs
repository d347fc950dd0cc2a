//! Where models come from: the checkpoint layouts this crate reads, in one place (as diffusers'
//! `loaders/`). A model is named as a run's checkpoint (`RUN/checkpoints/step-N`, full or LoRA), a
//! diffusers transformer folder (the released CogNVS transformer) or a pipeline folder with
//! `transformer/`, plus what the checkpoint lacks: a base model folder in CogVideoX-5B-I2V's layout
//! (`vae/`, `scheduler/`, `text_encoder/`, `tokenizer/`), a VAE folder, LoRA files and text
//! embedding files. [`ModelSource::resolve`] finds every file; [`lora`] reads, writes and merges
//! LoRA files.

pub mod lora;

use std::path::{Path, PathBuf};

use tch::{Device, Kind, Tensor};

use crate::diffusers_config::DiffusersConfig;
use crate::error::{Error, Result};
use crate::models::backbone::{TextShape, TransformerConfig};
use crate::models::weights;
use crate::schedulers::CogVideoXSchedulerConfig;

/// The text shape of the released CogVideoX-5B / CogNVS transformers: T5-XXL's 226 tokens of
/// 4096 channels (`max_text_seq_length`, `text_embed_dim`). Such a model never saw zeros there.
pub const T5_XXL_TEXT_SHAPE: [i64; 2] = [226, 4096];

/// The script that writes a text embedding file from a CogVideoX model folder.
pub const ENCODE_PROMPT_SCRIPT: &str = "scripts/encode_prompt.py";

/// Where the models of a sampling or finetuning run come from, as the user names them.
#[derive(Debug, Clone, Default)]
pub struct ModelSource {
    /// A run's checkpoint (`RUN/checkpoints/step-N`, full or LoRA), a diffusers transformer
    /// folder (the released CogNVS transformer), or a pipeline folder with `transformer/`.
    pub checkpoint: PathBuf,
    /// A CogVideoX pipeline folder (CogVideoX-5B-I2V's layout: `vae/`, `scheduler/`,
    /// `text_encoder/`, `tokenizer/`, `transformer/`) that supplies what the checkpoint lacks.
    pub base_model: Option<PathBuf>,
    /// The VAE folder, overriding every other place.
    pub vae: Option<PathBuf>,
    /// A LoRA file merged into the transformer (after a LoRA checkpoint's own adapter).
    pub lora: Option<PathBuf>,
    /// The prompt's text embedding file (`encoder_hidden_states` `[S, D]`).
    pub text_embedding: Option<PathBuf>,
    /// The negative prompt's text embedding file (default: the prompt's).
    pub negative_text_embedding: Option<PathBuf>,
    /// Use zeros where no text embedding is given, also for a T5-XXL-shaped transformer.
    pub zero_text_embedding: bool,
}

/// The files a [`ModelSource`] resolves to.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelPaths {
    /// The transformer folder (diffusers layout).
    pub transformer: PathBuf,
    /// LoRA files merged into it, in order.
    pub adapters: Vec<PathBuf>,
    /// The VAE folder.
    pub vae: PathBuf,
    /// The folder holding `scheduler_config.json`, if any (else CogVideoX-5B's schedule).
    pub scheduler: Option<PathBuf>,
    /// The prompt's text embedding (None: zeros).
    pub text_embedding: Option<PathBuf>,
    /// The negative prompt's text embedding (None: the prompt's).
    pub negative_text_embedding: Option<PathBuf>,
    /// Zeros asked for where no text embedding is given.
    pub zero_text_embedding: bool,
}

impl ModelSource {
    /// Finds every file the models need (nothing large is read). Whether a T5-XXL-shaped
    /// transformer got a text embedding is [`ModelPaths::check_text_embedding`]'s to say.
    pub fn resolve(&self) -> Result<ModelPaths> {
        let checkpoint = &self.checkpoint;
        let (transformer, mut adapters) = match lora::lora_checkpoint(checkpoint)? {
            Some((base, file)) => (base, vec![file]),
            None => (transformer_dir(checkpoint), Vec::new()),
        };
        adapters.extend(self.lora.clone());
        let base = self.base_model.as_deref();
        let vae = find_vae(checkpoint, self.vae.as_deref().or(base.map(|b| b.join("vae")).as_deref()))?;
        let scheduler = [base.map(|b| b.join("scheduler")), Some(checkpoint.join("scheduler"))]
            .into_iter()
            .flatten()
            .find(|d| d.join(CogVideoXSchedulerConfig::FILE_NAME).is_file());
        let text_embedding = match &self.text_embedding {
            Some(p) => Some(p.clone()),
            None => run_text_embedding(checkpoint)?,
        };
        Ok(ModelPaths {
            transformer,
            adapters,
            vae,
            scheduler,
            text_embedding,
            negative_text_embedding: self.negative_text_embedding.clone(),
            zero_text_embedding: self.zero_text_embedding,
        })
    }
}

impl ModelPaths {
    /// Refuses zeros as the text of a transformer trained on T5-XXL text unless asked for (see
    /// [`require_text_embedding`]); reads the transformer's config only.
    pub fn check_text_embedding(&self) -> Result<()> {
        let (config, _) = TransformerConfig::read_quiet(&self.transformer)?;
        require_text_embedding(&config, self.text_embedding.as_deref(), self.zero_text_embedding, &self.transformer)
    }
}

/// Refuses a transformer with the released checkpoints' T5-XXL text shape and no embedding, unless
/// zeros are asked for explicitly: such a model never saw zero text tokens in training.
pub fn require_text_embedding(
    config: &impl TextShape,
    embedding: Option<&Path>,
    zeros_allowed: bool,
    transformer: &Path,
) -> Result<()> {
    let t5_xxl = config.text_shape() == T5_XXL_TEXT_SHAPE;
    if embedding.is_none() && t5_xxl && !zeros_allowed {
        return Err(Error::InvalidArgument {
            name: "text-embedding".to_string(),
            reason: format!(
                "{} takes T5-XXL text ({} × {}) and was trained on the empty prompt's encoding, not on zeros: \
                 make the file once with `.venv/bin/python {ENCODE_PROMPT_SCRIPT} --model COGVIDEOX_5B_I2V_DIR \
                 --out empty_prompt.safetensors` and pass `--text-embedding empty_prompt.safetensors` \
                 (`[model] text_embedding` in a training config), or pass `--zero-text-embedding` \
                 (`[model] zero_text_embedding = true`) to use zeros anyway",
                transformer.display(),
                T5_XXL_TEXT_SHAPE[0],
                T5_XXL_TEXT_SHAPE[1]
            ),
        });
    }
    Ok(())
}

/// The VAE folder of a checkpoint: `explicit`, `CKPT/vae` or the run's `vae/`.
pub fn find_vae(checkpoint: &Path, explicit: Option<&Path>) -> Result<PathBuf> {
    if let Some(v) = explicit {
        return Ok(v.to_path_buf());
    }
    let candidates = [checkpoint.join("vae"), checkpoint.join("../../vae"), checkpoint.join("../vae")];
    candidates.iter().find(|c| c.join("config.json").is_file()).cloned().ok_or_else(|| Error::InvalidArgument {
        name: "vae".to_string(),
        reason: format!(
            "no VAE given and none at {}, {} or {}; pass --vae VAE_DIR or --base-model COGVIDEOX_5B_I2V_DIR",
            candidates[0].display(),
            candidates[1].display(),
            candidates[2].display()
        ),
    })
}

/// The transformer folder of a checkpoint (`CKPT/transformer`) or the folder itself.
pub fn transformer_dir(checkpoint: &Path) -> PathBuf {
    let inner = checkpoint.join("transformer");
    if inner.join("config.json").is_file() { inner } else { checkpoint.to_path_buf() }
}

/// The text embedding named in the run's `config.json` (`model.text_embedding`), if any. A
/// run config that exists but is not JSON, or whose key is not a path, is an error naming it.
fn run_text_embedding(checkpoint: &Path) -> Result<Option<PathBuf>> {
    let path = checkpoint.join("../../config.json");
    let Ok(text) = std::fs::read_to_string(&path) else { return Ok(None) };
    let bad = |field: &str, reason: String| Error::InvalidConfig {
        source_name: path.display().to_string(),
        field: field.to_string(),
        reason,
    };
    let json: serde_json::Value = serde_json::from_str(&text).map_err(|e| bad("(json)", e.to_string()))?;
    match json.get("model").and_then(|m| m.get("text_embedding")) {
        None | Some(serde_json::Value::Null) => Ok(None),
        Some(serde_json::Value::String(p)) => Ok(Some(PathBuf::from(p))),
        Some(other) => Err(bad("model.text_embedding", format!("{other} is not a path string"))),
    }
}

/// The text embedding `[1, S, D]` from a safetensors file's `encoder_hidden_states` `[S, D]`
/// (shape checked against the transformer config), or zeros without a file; f32.
pub fn load_text_embedding(path: Option<&Path>, config: &impl TextShape, device: Device) -> Result<Tensor> {
    let shape = config.text_shape();
    match path {
        None => Ok(Tensor::f_zeros([1, shape[0], shape[1]], (Kind::Float, device))?),
        Some(path) => {
            let mut tensors = weights::read_safetensors(path)?;
            let tensor = tensors.remove("encoder_hidden_states").ok_or_else(|| Error::MissingTensor {
                path: path.to_path_buf(),
                tensor: "encoder_hidden_states".to_string(),
                expected: shape.to_vec(),
            })?;
            weights::check_floating(path, "encoder_hidden_states", &tensor)?;
            // The script's files may keep the batch axis of `(1, S, D)`.
            let tensor = if tensor.dim() == 3 && tensor.size()[0] == 1 { tensor.f_squeeze_dim(0)? } else { tensor };
            weights::check_shape(&format!("encoder_hidden_states` in `{}", path.display()), &tensor, &shape)?;
            Ok(tensor.f_to_kind(Kind::Float)?.f_to_device(device)?.f_unsqueeze(0)?)
        }
    }
}

/// The scheduler config a pipeline samples with: the folder's `scheduler_config.json` when one
/// is given, else CogVideoX-5B's, with trailing timestep spacing as the CogNVS demo sets it.
pub fn scheduler_config(folder: Option<&Path>) -> Result<CogVideoXSchedulerConfig> {
    let mut config = match folder {
        Some(folder) => CogVideoXSchedulerConfig::from_json_file(folder)?,
        None => CogVideoXSchedulerConfig::cogvideox_5b(),
    };
    config.timestep_spacing = "trailing".to_string();
    Ok(config)
}

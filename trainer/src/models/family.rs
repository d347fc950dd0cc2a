//! The model families, and the one place that tells them apart: a model folder's `config.json`
//! names its class (`_class_name`, as diffusers writes it), and that class picks the family for
//! every job (`trainer forward`, sampling, training). A config without a class name is
//! CogVideoX's, as before a second family existed.
//!
//! A family is a transformer class, a VAE class, its training objective, its default clip, its
//! LoRA targets and the jobs that can run it so far. A job asks
//! [`ModelFamily::of_transformer`] (or [`ModelFamily::of_vae`]) and then
//! [`ModelFamily::require`]: a checkpoint of a family the job does not run yet is refused by
//! name, before its config is parsed as another family's.

use std::path::Path;

use crate::diffusers_config;
use crate::error::{Error, Result};
use crate::models::cogvideox::{autoencoder_kl_cogvideox, cogvideox_transformer_3d};
use crate::models::wan::{autoencoder_kl_wan, transformer_wan};

/// A model family: its transformer and VAE classes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelFamily {
    /// CogVideoX (`CogVideoXTransformer3DModel`, `AutoencoderKLCogVideoX`): the CogNVS release.
    CogVideoX,
    /// Wan2.1 and Wan2.2 (`WanTransformer3DModel`, `AutoencoderKLWan`).
    Wan,
}

/// How a family is trained.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Objective {
    /// CogVideoX: v-prediction on its DDPM noise schedule (the scheduler config's), the x̂₀ loss
    /// weighted by 1/(1 − ᾱ_t).
    VPrediction,
    /// Wan: rectified flow, `x_σ = (1 − σ)·x₀ + σ·ε`, the model predicting `ε − x₀`, σ drawn
    /// uniformly from the shifted training schedule of `FlowMatchEulerDiscreteScheduler`.
    RectifiedFlow,
}

/// A clip's frames and size in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClipShape {
    /// Frames.
    pub frames: usize,
    /// Height in pixels.
    pub height: u32,
    /// Width in pixels.
    pub width: u32,
}

/// What a job does with a model, for the refusal's message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Job {
    /// One forward pass of a component (`trainer forward`).
    Forward,
    /// Sampling videos (`trainer sample`, `nvs`, `benchmark`, validation samples).
    Sampling,
    /// Training (`pretrain`, `finetune`).
    Training,
    /// The memory plan of a training run (`trainer plan`, the check before a run).
    MemoryPlan,
}

impl Job {
    fn name(self) -> &'static str {
        match self {
            Job::Forward => "a forward pass",
            Job::Sampling => "sampling",
            Job::Training => "training",
            Job::MemoryPlan => "the memory plan",
        }
    }
}

impl ModelFamily {
    /// Every family, the default (a config without a class name) first.
    pub const ALL: [ModelFamily; 2] = [ModelFamily::CogVideoX, ModelFamily::Wan];

    /// The family's name in messages.
    pub fn name(self) -> &'static str {
        match self {
            ModelFamily::CogVideoX => "CogVideoX",
            ModelFamily::Wan => "Wan",
        }
    }

    /// The transformer's diffusers class.
    pub fn transformer_class(self) -> &'static str {
        match self {
            ModelFamily::CogVideoX => cogvideox_transformer_3d::CLASS_NAME,
            ModelFamily::Wan => transformer_wan::CLASS_NAME,
        }
    }

    /// The VAE's diffusers class.
    pub fn vae_class(self) -> &'static str {
        match self {
            ModelFamily::CogVideoX => autoencoder_kl_cogvideox::CLASS_NAME,
            ModelFamily::Wan => autoencoder_kl_wan::CLASS_NAME,
        }
    }

    /// Whether `job` runs this family's models yet: every job runs both families (Wan trains
    /// with the rectified-flow objective and samples through `pipelines::pipeline_wan`).
    pub fn runs(self, job: Job) -> bool {
        match self {
            ModelFamily::CogVideoX => true,
            ModelFamily::Wan => matches!(job, Job::Forward | Job::Sampling | Job::Training | Job::MemoryPlan),
        }
    }

    /// How the family is trained.
    pub fn objective(self) -> Objective {
        match self {
            ModelFamily::CogVideoX => Objective::VPrediction,
            ModelFamily::Wan => Objective::RectifiedFlow,
        }
    }

    /// The clip the family's released models were trained on: CogVideoX 49 frames of 480×720
    /// (CogVideoX-5B-I2V), Wan 81 frames of 480×832 (Wan2.1's 480p setting).
    pub fn default_clip(self) -> ClipShape {
        match self {
            ModelFamily::CogVideoX => ClipShape { frames: 49, height: 480, width: 720 },
            ModelFamily::Wan => ClipShape { frames: 81, height: 480, width: 832 },
        }
    }

    /// The linear layers LoRA adapts by default (peft's `target_modules` as the family's diffusers
    /// trainers set them): the attention projections of every block.
    pub fn lora_target_modules(self) -> &'static [&'static str] {
        match self {
            ModelFamily::CogVideoX | ModelFamily::Wan => &["to_q", "to_k", "to_v", "to_out.0"],
        }
    }

    /// The family of a transformer config (a `config.json`, or a folder holding one).
    pub fn of_transformer(config: &Path) -> Result<Self> {
        Self::of_class(config, Self::transformer_class)
    }

    /// The family of a VAE config (a `config.json`, or a folder holding one).
    pub fn of_vae(config: &Path) -> Result<Self> {
        Self::of_class(config, Self::vae_class)
    }

    /// `Ok(self)` when `job` runs this family; otherwise an error naming the config, the class
    /// and what runs it today.
    pub fn require(self, job: Job, config: &Path) -> Result<Self> {
        if self.runs(job) {
            return Ok(self);
        }
        let running: Vec<&str> = Self::ALL.iter().filter(|f| f.runs(job)).map(|f| f.name()).collect();
        Err(Error::InvalidConfig {
            source_name: config.display().to_string(),
            field: "_class_name".to_string(),
            reason: format!(
                "is a {} model; {} runs {} models only so far (`trainer forward` runs every family)",
                self.name(),
                job.name(),
                running.join(" and ")
            ),
        })
    }

    fn of_class(config: &Path, class_of: fn(Self) -> &'static str) -> Result<Self> {
        let Some(class) = diffusers_config::class_name(config, "config.json")? else { return Ok(Self::ALL[0]) };
        Self::ALL.into_iter().find(|f| class_of(*f) == class).ok_or_else(|| {
            let known: Vec<&str> = Self::ALL.into_iter().map(class_of).collect();
            Error::InvalidConfig {
                source_name: config.display().to_string(),
                field: "_class_name".to_string(),
                reason: format!("is `{class}`; the classes this toolkit runs here are {}", known.join(", ")),
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config_file(dir: &Path, json: &str) -> std::path::PathBuf {
        std::fs::create_dir_all(dir).unwrap();
        std::fs::write(dir.join("config.json"), json).unwrap();
        dir.to_path_buf()
    }

    #[test]
    fn the_class_name_picks_the_family_and_none_is_cogvideox() {
        let root = tempfile::tempdir().unwrap();
        let wan = config_file(&root.path().join("wan"), r#"{"_class_name": "WanTransformer3DModel"}"#);
        let cog = config_file(&root.path().join("cog"), r#"{"_class_name": "CogVideoXTransformer3DModel"}"#);
        let bare = config_file(&root.path().join("bare"), r#"{"num_layers": 2}"#);
        let wan_vae = config_file(&root.path().join("wan_vae"), r#"{"_class_name": "AutoencoderKLWan"}"#);
        assert_eq!(ModelFamily::of_transformer(&wan).unwrap(), ModelFamily::Wan);
        assert_eq!(ModelFamily::of_transformer(&cog).unwrap(), ModelFamily::CogVideoX);
        assert_eq!(ModelFamily::of_transformer(&bare.join("config.json")).unwrap(), ModelFamily::CogVideoX);
        assert_eq!(ModelFamily::of_vae(&wan_vae).unwrap(), ModelFamily::Wan);
        // A VAE class is not a transformer class.
        let e = ModelFamily::of_transformer(&wan_vae).unwrap_err().to_string();
        assert!(e.contains("AutoencoderKLWan") && e.contains("WanTransformer3DModel"), "{e}");
    }

    #[test]
    fn a_job_refuses_a_family_it_does_not_run_by_name() {
        let path = Path::new("some/wan/transformer");
        assert!(ModelFamily::CogVideoX.require(Job::Sampling, path).is_ok());
        assert!(ModelFamily::Wan.require(Job::Forward, path).is_ok());
        assert!(ModelFamily::Wan.require(Job::Training, path).is_ok());
        assert!(ModelFamily::Wan.require(Job::Sampling, path).is_ok());
    }

    #[test]
    fn each_family_has_its_clip_and_objective() {
        assert_eq!(ModelFamily::CogVideoX.default_clip(), ClipShape { frames: 49, height: 480, width: 720 });
        assert_eq!(ModelFamily::Wan.default_clip(), ClipShape { frames: 81, height: 480, width: 832 });
        assert_eq!(ModelFamily::CogVideoX.objective(), Objective::VPrediction);
        assert_eq!(ModelFamily::Wan.objective(), Objective::RectifiedFlow);
    }
}

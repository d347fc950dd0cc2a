//! `trainer finetune`: test-time finetuning on one video.

use std::path::PathBuf;
use std::sync::Arc;

use datagen::api::{ClipConfig, InputDigest, LayoutName, PairsConfig, PairsJob, Sequence};

use tch::Device;

use super::{PretrainConfig, RunSummary, StepMetrics};
use crate::distributed::ProcessGroup;
use crate::error::{Error, Result};

/// The dataset name the finetuning pairs are stored with.
const PAIRS_DATASET: &str = "finetune";

/// What `trainer finetune` trains.
#[derive(Debug, Clone, Default)]
pub struct FinetuneRequest {
    /// Checkpoint to start from: a run's checkpoint, a diffusers transformer folder (the released
    /// CogNVS transformer) or a pipeline folder with `transformer/`.
    pub init: PathBuf,
    /// A CogVideoX pipeline folder (CogVideoX-5B-I2V's layout) supplying the VAE and the scheduler
    /// config where `init` has none.
    pub base_model: Option<PathBuf>,
    /// The VAE folder, overriding every other place.
    pub vae: Option<PathBuf>,
    /// The text embedding file, overriding the config's.
    pub text_embedding: Option<PathBuf>,
    /// Zeros as the text embedding also for a transformer trained on T5-XXL text.
    pub zero_text_embedding: bool,
    /// The test video's sequence folder.
    pub sequence: PathBuf,
    /// Its layout (None: detected from its files).
    pub layout: Option<LayoutName>,
    /// The video read already (by a job's checks, as `trainer nvs` reads it): the pairs are made
    /// from it instead of reading `sequence` again.
    pub read: Option<Arc<ReadSequence>>,
    /// Run folder.
    pub out: PathBuf,
    /// Optimizer steps.
    pub steps: u64,
    /// Sampled trajectories per clip.
    pub trajectories: u32,
    /// Training TOML overriding the init run's settings.
    pub config: Option<PathBuf>,
    /// A LoRA file merged into `init`'s transformer before finetuning (a base plus an adapter).
    pub lora: Option<PathBuf>,
    /// Continue the run in `out` from its newest intact checkpoint (after a preemption), on the
    /// pairs it built; a folder without a run starts one.
    pub resume: bool,
}

/// A sequence folder read, with the content hash of its files (the shard's input digest).
#[derive(Debug)]
pub struct ReadSequence {
    /// The video.
    pub sequence: Sequence,
    /// `foundation::hashing::hash_tree` of the folder.
    pub content_hash: String,
}

/// The pair settings of test-time finetuning under `config`: clips of the training length, back
/// to back, every clip of the video; the rest `datagen pairs`' defaults. `trainer nvs` renders
/// its trajectories with the same settings (mesh and static background).
pub fn finetune_pairs_config(config: &PretrainConfig) -> Result<PairsConfig> {
    // Within `video_processor::MAX_FRAMES` once validated; narrowed checked all the same.
    let frames = u32::try_from(config.data.frames).map_err(|_| Error::InvalidArgument {
        name: "data.frames".to_string(),
        reason: format!("{} frames per clip", config.data.frames),
    })?;
    Ok(PairsConfig { clip: ClipConfig { length: frames, stride: frames, max_clips: 0 }, ..Default::default() })
}

/// `trainer finetune`: test-time finetuning on one video. Its self-supervised pairs
/// are built in-process with the `datagen` library (clips of the training length, back to back,
/// `trajectories` sampled paths each) into `RUN/pairs/`, then the transformer of checkpoint
/// `init` is trained on them for `steps` steps with the init run's settings (its `config.json`,
/// or `config` when given) and the init run's VAE. Checkpoints and metrics go to `run`.
pub fn finetune(request: &FinetuneRequest, device: Device, progress: impl FnMut(&StepMetrics)) -> Result<RunSummary> {
    finetune_on(request, device, None, progress)
}

/// `trainer finetune`: joins the job the launcher started (if any; see
/// [`crate::distributed::join_job`]), checks the run's memory plan against the device, and
/// finetunes as [`finetune_on`]; `on_event` hears rank 0's plan and steps.
pub fn finetune_launched(
    request: &FinetuneRequest,
    device: Device,
    mut on_event: impl FnMut(super::RunEvent),
) -> Result<RunSummary> {
    let timeout = super::config::timeout_seconds(request.config.as_deref())?;
    let (device, pg) = crate::distributed::join_job(device, timeout)?;
    let (config, source_name) = finetune_config(request)?;
    crate::training::plan::check_run(&config, device, pg.as_ref(), &source_name, |plan| {
        on_event(super::RunEvent::Plan(plan))
    })?;
    let lead = pg.as_ref().is_none_or(|pg| pg.rank == 0);
    finetune_on(request, device, pg.as_ref(), |m| {
        if lead {
            on_event(super::RunEvent::Step(m))
        }
    })
}

/// [`finetune`] as one rank of `pg` (None: one process). Rank 0 takes the run folder's lock,
/// then builds the video's pairs (one shard in `RUN/pairs/`) while the others wait at a barrier;
/// then every rank trains on its share of each global batch as in [`super::pretrain_on`]
/// (preemption signals included). The pairs, the global batch and every draw are those of a
/// single process, so the result does not depend on the world size (up to fp32 reduction
/// order), provided the global batch divides by it. With `resume`, the pairs already built are
/// reused and training continues from the newest intact checkpoint.
pub fn finetune_on(
    request: &FinetuneRequest,
    device: Device,
    pg: Option<&ProcessGroup>,
    progress: impl FnMut(&StepMetrics),
) -> Result<RunSummary> {
    let (rank, world) = pg.map_or((0, 1), |pg| (pg.rank, pg.world_size));
    let FinetuneRequest { sequence: sequence_dir, out: run, trajectories, .. } = request;
    let trajectories = *trajectories;
    let (mut config, _) = finetune_config(request)?;
    config.validate(&config.source_name())?;
    config.model.check_text_embedding()?;
    let started = run.join("config.json").exists();
    if started && !request.resume {
        return Err(Error::InvalidArgument {
            name: "out".to_string(),
            reason: format!(
                "{} already holds a run; pass --resume to continue it or choose another folder",
                run.display()
            ),
        });
    }
    // Every rank has checked the folder before rank 0 locks and writes into it.
    let lock = super::RunLock::acquire_on(run, "trainer finetune", pg)?;
    let pairs_dir = run.join("pairs");
    let built = request.resume && crate::training::data::ClipIndex::open(std::slice::from_ref(&pairs_dir)).is_ok();
    if rank == 0 && !built {
        // `datagen pairs` as the command runs it, into RUN/pairs/.
        let job = PairsJob {
            seq_dir: sequence_dir.clone(),
            layout: request.layout,
            read_options: Default::default(),
            out: pairs_dir.clone(),
            trajectories: Some(trajectories),
            trajectory_files: Vec::new(),
            seed: config.data.seed,
            config: finetune_pairs_config(&config)?,
            dataset: PAIRS_DATASET.to_string(),
            second_depth: None,
        };
        match &request.read {
            Some(read) => {
                let input = InputDigest {
                    source_path: sequence_dir.display().to_string(),
                    content_hash: read.content_hash.clone(),
                };
                datagen::api::make_pairs_of(&job, &read.sequence, input)?
            }
            None => datagen::api::make_pairs(&job)?,
        };
    }
    if let Some(pg) = pg {
        pg.barrier("pairs written by rank 0")?;
    }
    // Small test videos have few clips: never ask for more per batch than there are, and with
    // several ranks keep the global batch a multiple of the world size.
    let clips = crate::training::data::ClipIndex::open(std::slice::from_ref(&pairs_dir))?.len();
    if clips < world {
        return Err(Error::InvalidArgument {
            name: "world size".to_string(),
            reason: format!(
                "{} gives {clips} clips, fewer than the {world} ranks: finetune on fewer ranks",
                sequence_dir.display()
            ),
        });
    }
    let batch = config.data.batch_size.min(clips).max(1);
    config.data.batch_size = (batch / world).max(1) * world;
    super::pretrain::train(&config, &[pairs_dir], run, started, device, pg, Some(lock), progress)
}

/// The training config `trainer finetune` runs `request` with, and the name of the file it came
/// from: the request's TOML or the init run's `config.json`, with the init checkpoint's
/// transformer (or a LoRA checkpoint's base plus its adapter, or `--lora`'s), its VAE and
/// scheduler config (the checkpoint's, its run's, or the base model's), the request's text
/// embedding and steps. Nothing is written. The data's batch may still shrink to the number of
/// clips the video gives (see [`finetune_on`]).
pub fn finetune_config(request: &FinetuneRequest) -> Result<(PretrainConfig, String)> {
    let init = &request.init;
    let run_config = init.join("../../config.json");
    let (mut config, source_name) = match &request.config {
        Some(path) => (PretrainConfig::from_toml_file(path)?, path.display().to_string()),
        None if run_config.is_file() => {
            let mut config = PretrainConfig::from_json_file(&run_config)?;
            // The init run's held-out pairs belong to its corpus, not to the test video.
            config.validation = None;
            (config, run_config.display().to_string())
        }
        None => {
            return Err(Error::InvalidArgument {
                name: "config".to_string(),
                reason: format!(
                    "{} is not the checkpoint of a trainer run (no {}): pass --config with the training settings \
                     (configs/finetune_5b_lora_1gpu.toml, finetune_5b_full_1gpu.toml or finetune_5b_full.toml for \
                     the released CogNVS checkpoint)",
                    init.display(),
                    run_config.display()
                ),
            });
        }
    };
    let source = crate::loaders::ModelSource {
        checkpoint: init.clone(),
        base_model: request.base_model.clone(),
        vae: request.vae.clone(),
        lora: request.lora.clone(),
        text_embedding: request.text_embedding.clone(),
        negative_text_embedding: None,
        zero_text_embedding: request.zero_text_embedding,
    };
    let paths = source.resolve()?;
    if let [first, second, ..] = &paths.adapters[..] {
        return Err(Error::InvalidArgument {
            name: "lora".to_string(),
            reason: format!(
                "{} is a LoRA checkpoint already ({}); pass its base to combine it with {}",
                init.display(),
                first.display(),
                second.display()
            ),
        });
    }
    config.model.transformer = paths.transformer.display().to_string();
    config.model.transformer_lora = paths.adapters.first().cloned();
    config.model.vae = paths.vae.display().to_string();
    if paths.scheduler.is_some() {
        config.model.scheduler = paths.scheduler;
    }
    if let Some(text) = request.text_embedding.clone() {
        config.model.text_embedding = Some(text);
    }
    config.model.zero_text_embedding |= request.zero_text_embedding;
    config.train.steps = request.steps;
    if let super::CheckpointEvery::Steps(every) = config.train.checkpoint_every {
        config.train.checkpoint_every = super::CheckpointEvery::Steps(every.min(request.steps.max(1)));
    }
    Ok((config, source_name))
}

//! The `trainer pretrain` loop: per-step seeding, accumulation, clipping, metrics, validation
//! samples and checkpoints, resuming exactly from the latest checkpoint.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use tch::{Device, Kind};

use super::checkpoint::{list_checkpoints, save_checkpoint};
use super::objective::step_seed;
use super::parallel::StepOptimizer;
use super::preempt::PreemptWatch;
use super::run_lock::RunLock;
use super::validation::ValidationMetrics;
use super::{
    Backward, CheckpointEvery, CheckpointLayout, CogNvsModel, Draws, LatentCache, PretrainConfig, TrainState,
    consensus, learning_rate,
};
use crate::distributed::ProcessGroup;
use crate::error::{Error, Result};
use crate::models::weights;
use crate::training::data::{ClipIndex, DataConfig, DataPosition, ShardLoader};

/// One line of `metrics.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StepMetrics {
    /// Optimizer step (1-based).
    pub step: u64,
    /// Mean loss over the step's micro-batches.
    pub loss: f64,
    /// Learning rate used.
    pub lr: f64,
    /// Gradient norm before clipping.
    pub grad_norm: f64,
    /// Wall seconds of the step.
    pub seconds: f64,
    /// Of those, seconds in VAE encodes (the condition and the target; none from a latent cache).
    #[serde(default)]
    pub encode_seconds: f64,
    /// On CUDA: the caching allocator's peak bytes allocated during the step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cuda_peak_allocated: Option<u64>,
    /// On CUDA: the caching allocator's peak bytes reserved during the step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cuda_peak_reserved: Option<u64>,
}

/// What a pretraining run did.
#[derive(Debug, Clone)]
pub struct RunSummary {
    /// The step the run started from (0, or a resumed checkpoint's).
    pub resumed_from: u64,
    /// Steps done at the end.
    pub steps: u64,
    /// The last checkpoint.
    pub last_checkpoint: Option<PathBuf>,
    /// Whether a preemption signal stopped the run before its last step (after writing the
    /// checkpoint of the step it was in): the caller exits with [`super::preempt::EXIT_PREEMPTED`].
    pub preempted: bool,
}

/// `trainer pretrain`: trains up to `config.train.steps`, resuming from the run's latest
/// checkpoint when `resume` is set. `progress(step, metrics)` is called after every step.
pub fn pretrain(
    config: &PretrainConfig,
    shards: &[PathBuf],
    run: &Path,
    resume: bool,
    device: Device,
    progress: impl FnMut(&StepMetrics),
) -> Result<RunSummary> {
    pretrain_on(config, shards, run, resume, device, None, progress)
}

/// What a launched training run reports to its caller, on rank 0 only: the memory plan before
/// anything is written, then each finished step.
#[derive(Debug)]
pub enum RunEvent<'a> {
    /// The run's memory plan (printed by the commands).
    Plan(&'a crate::training::plan::MemoryPlan),
    /// A finished optimizer step.
    Step(&'a StepMetrics),
}

/// `trainer pretrain`: joins the job the launcher started (if any; see
/// [`crate::distributed::join_job`]), validates `config` (`source_name` names it in errors),
/// checks its memory plan against the device, and trains as [`pretrain_on`].
pub fn pretrain_launched(
    config: &PretrainConfig,
    source_name: &str,
    shards: &[PathBuf],
    run: &Path,
    resume: bool,
    device: Device,
    mut on_event: impl FnMut(RunEvent),
) -> Result<RunSummary> {
    let (device, pg) = crate::distributed::join_job(device, config.distributed.timeout_seconds)?;
    config.validate(source_name)?;
    crate::training::plan::check_run(config, device, pg.as_ref(), source_name, |plan| on_event(RunEvent::Plan(plan)))?;
    let lead = pg.as_ref().is_none_or(|pg| pg.rank == 0);
    pretrain_on(config, shards, run, resume, device, pg.as_ref(), |m| {
        if lead {
            on_event(RunEvent::Step(m))
        }
    })
}

/// [`pretrain`] as one rank of `pg` (None: one process). `config.data.batch_size` is the global
/// batch: each rank takes `batch_size / world_size` samples of it (the loader's interleaved
/// partition), draws every random value for the whole global batch and keeps its own
/// ([`Draws`]), and gradients are averaged over ranks once per optimizer step, so the run
/// computes what one process would at that batch size. Only rank 0 writes the run folder
/// (config, metrics, TensorBoard events, samples, checkpoints), holding its [`RunLock`] for the
/// whole run; the others meet it at collectives. The configured preemption signals stop the run
/// after the step in progress with a complete checkpoint (see [`super::preempt`]).
pub fn pretrain_on(
    config: &PretrainConfig,
    shards: &[PathBuf],
    run: &Path,
    resume: bool,
    device: Device,
    pg: Option<&ProcessGroup>,
    progress: impl FnMut(&StepMetrics),
) -> Result<RunSummary> {
    train(config, shards, run, resume, device, pg, None, progress)
}

/// What every phase of a run reads: the config, the data, the run folder, and who this process
/// is in the job.
struct RunContext<'a> {
    config: &'a PretrainConfig,
    shards: &'a [PathBuf],
    run: &'a Path,
    device: Device,
    pg: Option<&'a ProcessGroup>,
    rank: usize,
    world: usize,
    /// Rank 0, the only writer of the run folder.
    lead: bool,
}

impl RunContext<'_> {
    /// Whether any rank has received a preemption signal (one small collective).
    fn any_signal(&self, watch: &PreemptWatch) -> Result<bool> {
        Ok(consensus::any_rank(self.pg, [watch.received().is_some()], "preemption")?[0])
    }
}

/// A run folder made ready to train in: this rank's data, the held-out clips, the lock, the
/// signal watch, and the checkpoint to resume from.
struct Prepared {
    data: DataConfig,
    training_clips: Arc<ClipIndex>,
    held_out: Option<ClipIndex>,
    _lock: RunLock,
    watch: PreemptWatch,
    latest: Option<(PathBuf, TrainState)>,
}

/// [`pretrain_on`], with the run's lock already taken by the caller (`finetune` takes it before
/// it writes the video's pairs into the run folder) or taken here, after the ranks agree.
#[allow(clippy::too_many_arguments)]
pub(super) fn train(
    config: &PretrainConfig,
    shards: &[PathBuf],
    run: &Path,
    resume: bool,
    device: Device,
    pg: Option<&ProcessGroup>,
    lock: Option<RunLock>,
    mut progress: impl FnMut(&StepMetrics),
) -> Result<RunSummary> {
    let (rank, world) = pg.map_or((0, 1), |pg| (pg.rank, pg.world_size));
    let ctx = RunContext { config, shards, run, device, pg, rank, world, lead: rank == 0 };
    let Prepared { data, training_clips, held_out, _lock, watch, latest } = prepare(&ctx, resume, lock)?;
    let (mut model, mut optimizer, mut state) = start_model(&ctx, latest.as_ref())?;
    let resumed_from = state.step;
    let mut log = RunLog::open(&ctx, resumed_from)?;
    let mut loader = ShardLoader::new(training_clips, data, state.data_position)?;
    let mut last_checkpoint = latest.map(|(dir, _)| dir);
    let cache = match &config.train.latent_cache {
        Some(dir) => Some(LatentCache::open(dir, &model.vae, &model.vae_vs, &config.data)?),
        None => None,
    };
    let validation = super::validation::Validation::new(config, held_out, device)?;
    let mut since_checkpoint = Instant::now();
    // Until here a signal ended the process at once (nothing to save); from here on it stops the
    // loop after its step, with a checkpoint.
    let checkpointable = super::preempt::Checkpointable::enter();
    // A signal on another rank during its start-up stops before the first step.
    let mut preempted = ctx.any_signal(&watch)?;
    while state.step < config.train.steps && !preempted {
        let metrics =
            train_step(&ctx, &mut model, &mut optimizer, &mut loader, cache.as_ref(), &mut state, &last_checkpoint)?;
        log.step(&metrics, config)?;
        if ctx.lead {
            progress(&metrics);
        }
        // Once per step the ranks agree on a preemption signal and on rank 0's checkpoint clock.
        let clock_due = match config.train.checkpoint_every {
            CheckpointEvery::Minutes(minutes) => ctx.lead && since_checkpoint.elapsed().as_secs_f64() >= minutes * 60.0,
            CheckpointEvery::Steps(_) => false,
        };
        let [signalled, clock_due] =
            consensus::any_rank(pg, [watch.received().is_some(), clock_due], "preemption and checkpoint clock")?;
        preempted = signalled;
        if !preempted && config.train.validate_every > 0 && state.step.is_multiple_of(config.train.validate_every) {
            let (measured, sheet) = validation.run(state.step, &model, config, shards, run, pg)?;
            log.validation(state.step, measured.as_ref(), sheet.as_ref())?;
            // A signal that came during validation is acted on now, not a step later.
            preempted = ctx.any_signal(&watch)?;
        }
        let scheduled = match config.train.checkpoint_every {
            CheckpointEvery::Steps(every) => state.step.is_multiple_of(every),
            CheckpointEvery::Minutes(_) => clock_due,
        };
        let last = state.step == config.train.steps;
        if config.train.save_checkpoints && (scheduled || last || preempted) {
            let written = save_checkpoint(run, &model, &optimizer, &state, config.train.keep_last, pg)?;
            since_checkpoint = Instant::now();
            log.checkpoint(state.step, &written)?;
            last_checkpoint = Some(written.dir);
            if !preempted && !last {
                // A signal that came while the checkpoint was written needs no second one.
                preempted = ctx.any_signal(&watch)?;
            }
        }
    }
    let preempted = preempted && state.step < config.train.steps;
    let signal = watch.received();
    if preempted {
        watch.hold_until_exit();
    }
    drop(checkpointable);
    if preempted && ctx.lead {
        let signal = signal.map_or("a preemption signal (on another rank)".to_string(), super::preempt::signal_name);
        eprintln!(
            "{signal}: stopped after step {} with a complete checkpoint ({}); exit status {}: rerun with --resume",
            state.step,
            last_checkpoint.as_ref().map_or("none".to_string(), |p| p.display().to_string()),
            super::preempt::EXIT_PREEMPTED
        );
    }
    Ok(RunSummary { resumed_from, steps: state.step, last_checkpoint, preempted })
}

/// Everything before the first weight is loaded: the config and the shards checked, the ranks'
/// agreement on them, the run folder's lock, the preemption watch, what a killed run left
/// removed, the checkpoint to resume from, and the run's `config.json`. A bad config or bad shard
/// folders fail before the run folder is touched.
fn prepare(ctx: &RunContext, resume: bool, lock: Option<RunLock>) -> Result<Prepared> {
    let RunContext { config, shards, run, pg, rank, world, lead, .. } = *ctx;
    config.validate(&config.source_name())?;
    config.model.check_text_embedding()?;
    let data = rank_data_config(config, rank, world)?;
    let (training_clips, held_out) = super::validation::split_training_clips(config, shards)?;
    if lead && let Some(held_out) = &held_out {
        eprintln!("data: training on {} clips; {} held out for validation", training_clips.len(), held_out.len());
    }
    let training_clips = Arc::new(training_clips);
    crate::training::data::batches_per_epoch(training_clips.clone(), &data)?;
    let run_config = run.join("config.json");
    // Read by every rank before the agreement, so before rank 0 writes the folder.
    let holds_a_run = run_config.exists();
    let text = serde_json::to_vec_pretty(config).expect("config serialises");
    if let Some(pg) = pg {
        // Ranks that disagree stop here, before anything is written.
        let shard_list: Vec<String> = shards.iter().map(|p| p.display().to_string()).collect();
        let seen: Vec<String> = list_checkpoints(run).iter().map(|(step, _)| step.to_string()).collect();
        pg.agree(&[
            ("the training config", blake3::hash(&text).to_hex()[..16].to_string()),
            ("the shard folders", blake3::hash(shard_list.join("\n").as_bytes()).to_hex()[..16].to_string()),
            ("the world size", world.to_string()),
            ("the checkpoints in the run folder", if resume { seen.join(",") } else { "(not resuming)".to_string() }),
        ])?;
    }
    let lock = match lock {
        Some(lock) => lock,
        None => RunLock::acquire_on(run, "trainer pretrain", pg)?,
    };
    if !resume && holds_a_run {
        return Err(Error::InvalidArgument {
            name: "out".to_string(),
            reason: format!(
                "{} already holds a run; pass --resume to continue it or choose another folder",
                run.display()
            ),
        });
    }
    let signals: Vec<i32> =
        config.train.preempt_signals.iter().filter_map(|name| super::preempt::signal_number(name)).collect();
    let grace =
        (config.train.preempt_grace_seconds > 0.0).then(|| Duration::from_secs_f64(config.train.preempt_grace_seconds));
    let watch = PreemptWatch::install(&signals, grace)?;
    if lead {
        // The lock holder is the only writer: what a killed run left half written can go.
        super::checkpoint::remove_partial(run);
    }
    let latest = if resume { super::checkpoint::newest_intact(run, pg)? } else { None };
    if lead {
        std::fs::write(&run_config, &text).map_err(|source| Error::Io { path: run_config.clone(), error: source })?;
    }
    Ok(Prepared { data, training_clips, held_out, _lock: lock, watch, latest })
}

/// The model, its optimizer and the training state, from the configured weights (every rank
/// taking rank 0's) or, when resuming, from the checkpoint `latest`; in the run's precision.
fn start_model(
    ctx: &RunContext,
    latest: Option<&(PathBuf, TrainState)>,
) -> Result<(CogNvsModel, StepOptimizer, TrainState)> {
    let RunContext { config, run, device, pg, world, lead, .. } = *ctx;
    let mut model = CogNvsModel::load(&config.model, config.lora.as_ref(), config.train.seed, device)?;
    if let Some(pg) = pg {
        // Every rank starts from rank 0's weights, whatever its own initialisation gave.
        let trainable: Vec<tch::Tensor> = model.trainable().trainable_variables();
        tch::no_grad(|| pg.broadcast_from_zero(&trainable, "initial weights"))?;
    }
    if lead && config.train.save_checkpoints {
        write_run_models(run, config, &model)?;
    }
    let mut optimizer = StepOptimizer::new(&model, config, pg)?;
    let mut state = TrainState {
        step: 0,
        data_position: DataPosition::default(),
        seed: config.train.seed,
        layout: pg.map(|_| CheckpointLayout { world_size: world, zero_stage: config.distributed.zero_stage }),
        files: Default::default(),
    };
    if let Some((dir, saved)) = latest {
        // A LoRA run's adapters resume from the optimizer file's exact values; its base is the
        // configured model, loaded above.
        let lora_file = dir.join(crate::loaders::lora::LORA_WEIGHTS_NAME);
        match (model.lora_vs.is_some(), lora_file.is_file()) {
            (false, false) => {
                model.transformer.load(&model.vs, &dir.join("transformer"))?;
            }
            (true, true) => {}
            (lora, _) => {
                return Err(Error::InvalidArgument {
                    name: "resume".to_string(),
                    reason: format!(
                        "{} is a {} checkpoint but the config {} a [lora] section: resume with the run's own config",
                        dir.display(),
                        if lora { "full-model" } else { "LoRA" },
                        if lora { "has" } else { "has no" }
                    ),
                });
            }
        }
        optimizer.load(dir, model.lora_vs.is_some(), pg)?;
        state = TrainState { layout: state.layout, files: Default::default(), ..saved.clone() };
    }
    let kind = config.train.precision.kind(device);
    if kind != Kind::Float {
        // Mixed precision: the optimizer keeps the fp32 weights (as initialised or resumed).
        optimizer.keep_master_weights()?;
        model.set_kind(kind);
    }
    Ok((model, optimizer, state))
}

/// One optimizer step: seeded from (seed, step), its micro-batches' losses and backwards (the
/// last one starting each gradient bucket's exchange as it ends), the mean loss over ranks (a
/// non-finite one anywhere stops every rank, naming the batch), clipping and the update.
fn train_step(
    ctx: &RunContext,
    model: &mut CogNvsModel,
    optimizer: &mut StepOptimizer,
    loader: &mut ShardLoader,
    cache: Option<&LatentCache>,
    state: &mut TrainState,
    last_checkpoint: &Option<PathBuf>,
) -> Result<StepMetrics> {
    let RunContext { config, device, pg, rank, world, .. } = *ctx;
    let started = Instant::now();
    let accumulation = config.optim.grad_accumulation;
    let draws = Draws { rank: rank as i64, world: world as i64 };
    // Every draw of this step comes from (seed, step): resumed runs repeat them exactly.
    tch::manual_seed(step_seed(config.train.seed, state.step));
    optimizer.zero_grad()?;
    let mut loss_sum = 0.0;
    let mut bad_batch = None;
    for micro_batch in 1..=accumulation {
        let batch = loader.next_batch()?;
        // The last micro-batch's backward starts each gradient bucket's exchange as it ends.
        let mut exchange = |stage| optimizer.backward_stage_done(stage, pg);
        let backward = Backward {
            checkpointing: config.train.gradient_checkpointing,
            on_stage: (micro_batch == accumulation).then_some(&mut exchange as _),
        };
        let value = model.loss_backward(
            &batch,
            (config.train.condition_noise_log_mean, config.train.condition_noise_log_std),
            cache,
            accumulation as f64,
            backward,
            draws,
        )?;
        loss_sum += value;
        if !value.is_finite() && bad_batch.is_none() {
            bad_batch = Some((value, batch.provenance.clone()));
            if pg.is_none() {
                break;
            }
        }
    }
    // The mean over ranks (one process: itself); a non-finite loss anywhere stops every rank.
    let loss = match pg {
        Some(pg) => pg.sum_f64(loss_sum, "loss")? / world as f64,
        None => loss_sum,
    };
    if !loss.is_finite() {
        let (value, where_) = match bad_batch {
            Some((value, provenance)) => (value, format!("on batch {provenance:?}")),
            None => (loss, "on another rank".to_string()),
        };
        return Err(Error::InvalidArgument {
            name: "loss".to_string(),
            reason: format!(
                "non-finite loss {value} at step {} {where_}; last good checkpoint: {}",
                state.step + 1,
                last_checkpoint.as_ref().map_or("none".to_string(), |p| p.display().to_string())
            ),
        });
    }
    let lr = learning_rate(&config.optim, state.step, config.train.steps);
    let grad_norm = optimizer.step(lr, config.optim.max_grad_norm, pg)?;
    state.step += 1;
    state.data_position = loader.position();
    let peaks = match device {
        Device::Cuda(index) => crate::distributed::cuda_memory_peaks(index, true),
        _ => None,
    };
    Ok(StepMetrics {
        step: state.step,
        loss: loss / accumulation as f64,
        lr,
        grad_norm,
        seconds: started.elapsed().as_secs_f64(),
        encode_seconds: model.take_encode_seconds(),
        cuda_peak_allocated: peaks.map(|p| p.0),
        cuda_peak_reserved: peaks.map(|p| p.1),
    })
}

/// What rank 0 writes while it trains: `metrics.jsonl` (rewritten to the resumed step first) and
/// TensorBoard events. Other ranks hold an empty log that writes nothing.
struct RunLog {
    metrics: Option<(PathBuf, std::fs::File)>,
    events: Option<crate::training::tensorboard::EventWriter>,
}

impl RunLog {
    fn open(ctx: &RunContext, resumed_from: u64) -> Result<Self> {
        if !ctx.lead {
            return Ok(Self { metrics: None, events: None });
        }
        rewrite_metrics(ctx.run, resumed_from)?;
        let path = ctx.run.join("metrics.jsonl");
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(|source| Error::Io { path: path.clone(), error: source })?;
        let events = crate::training::tensorboard::EventWriter::create(ctx.run)?;
        Ok(Self { metrics: Some((path, file)), events: Some(events) })
    }

    fn line(&mut self, line: String) -> Result<()> {
        if let Some((path, file)) = self.metrics.as_mut() {
            writeln!(file, "{line}").map_err(|source| Error::Io { path: path.clone(), error: source })?;
        }
        Ok(())
    }

    /// A finished step: its metrics line and scalars.
    fn step(&mut self, metrics: &StepMetrics, config: &PretrainConfig) -> Result<()> {
        self.line(serde_json::to_string(metrics).expect("metrics serialise"))?;
        if let Some(events) = self.events.as_mut() {
            let samples = (config.data.batch_size as u64 * config.optim.grad_accumulation) as f64;
            events.scalars(
                metrics.step as i64,
                &[
                    ("train/loss", metrics.loss as f32),
                    ("train/lr", metrics.lr as f32),
                    ("train/grad_norm", metrics.grad_norm as f32),
                    ("train/step_seconds", metrics.seconds as f32),
                    ("train/samples_per_second", (samples / metrics.seconds.max(f64::MIN_POSITIVE)) as f32),
                ],
            )?;
            events.flush()?;
        }
        Ok(())
    }

    /// A validation's metrics and contact sheet.
    fn validation(
        &mut self,
        step: u64,
        measured: Option<&ValidationMetrics>,
        sheet: Option<&image::RgbImage>,
    ) -> Result<()> {
        if let Some(measured) = measured {
            self.line(serde_json::json!({ "step": step, "validation": measured }).to_string())?;
        }
        if let Some(events) = self.events.as_mut() {
            if let Some(measured) = measured {
                events.scalars(step as i64, &measured.scalars())?;
            }
            if let Some(sheet) = sheet {
                events.image("validation/contact_sheet", step as i64, sheet)?;
            }
            events.flush()?;
        }
        Ok(())
    }

    /// A written checkpoint: its size and speed, printed and logged.
    fn checkpoint(&mut self, step: u64, written: &super::checkpoint::Written) -> Result<()> {
        if let Some(events) = self.events.as_mut() {
            let gigabytes = written.bytes as f64 / 1e9;
            eprintln!(
                "checkpoint {}: {gigabytes:.3} GB in {:.1} s ({:.2} GB/s)",
                written.dir.display(),
                written.seconds,
                gigabytes / written.seconds.max(f64::MIN_POSITIVE)
            );
            events.scalars(
                step as i64,
                &[("checkpoint/gigabytes", gigabytes as f32), ("checkpoint/seconds", written.seconds as f32)],
            )?;
            events.flush()?;
        }
        Ok(())
    }
}

/// This rank's data config: its share of the global batch, its rank and the world size.
fn rank_data_config(config: &PretrainConfig, rank: usize, world: usize) -> Result<DataConfig> {
    let global = config.data.batch_size;
    if world > 1 && !global.is_multiple_of(world) {
        return Err(Error::InvalidConfig {
            source_name: config.source_name(),
            field: "data.batch_size".to_string(),
            reason: format!(
                "the global batch {global} must be a multiple of the world size {world} (each rank takes an equal share)"
            ),
        });
    }
    Ok(DataConfig { batch_size: global / world, rank, world_size: world, ..config.data.clone() })
}

/// The run's frozen VAE, and a LoRA run's base transformer, saved once with the run.
fn write_run_models(run: &Path, config: &PretrainConfig, model: &CogNvsModel) -> Result<()> {
    // The frozen VAE goes with the run once (sampling and finetuning find it there).
    let vae_dir = run.join("vae");
    if !vae_dir.join("config.json").exists() {
        model.vae.save(&model.vae_vs, &vae_dir, weights::DEFAULT_MAX_SHARD_BYTES)?;
    }
    // A LoRA run's checkpoints hold only adapters: the base they sit on is kept once, unless it is
    // simply the configured model folder.
    let base_is_folder = Path::new(&config.model.transformer).is_dir() && config.model.transformer_lora.is_none();
    let base_dir = run.join(crate::loaders::lora::BASE_TRANSFORMER_DIR);
    if model.lora_vs.is_some() && !base_is_folder && !base_dir.join("config.json").exists() {
        let variables = model.vs.variables().into_iter().collect();
        model.transformer.save(variables, &base_dir, weights::DEFAULT_MAX_SHARD_BYTES)?;
    }
    Ok(())
}

/// A line of `metrics.jsonl` that is not a step's: `{"step": N, "validation": {...}}`.
#[derive(Deserialize)]
struct ValidationLine {
    step: u64,
    validation: ValidationMetrics,
}

/// Keeps the metrics lines (steps' and validations') of steps up to `step` (a resumed run
/// rewrites what followed).
fn rewrite_metrics(run: &Path, step: u64) -> Result<()> {
    #[derive(Deserialize)]
    struct Step {
        step: u64,
    }
    let path = run.join("metrics.jsonl");
    let Ok(text) = std::fs::read_to_string(&path) else { return Ok(()) };
    let kept: String = text
        .lines()
        .filter(|line| serde_json::from_str::<Step>(line).is_ok_and(|m| m.step <= step))
        .map(|line| format!("{line}\n"))
        .collect();
    schemas::write_atomic(&path, kept.as_bytes())?;
    Ok(())
}

/// The lines of a run's `metrics.jsonl` that parse as `T`, or the first error of a line that is
/// neither a `T` nor skipped by `skip`.
fn read_lines<T: serde::de::DeserializeOwned>(run: &Path, skip: impl Fn(&serde_json::Value) -> bool) -> Result<Vec<T>> {
    let path = run.join("metrics.jsonl");
    let text = std::fs::read_to_string(&path).map_err(|source| Error::Io { path: path.clone(), error: source })?;
    let bad = |e: serde_json::Error| Error::InvalidConfig {
        source_name: path.display().to_string(),
        field: "(jsonl)".to_string(),
        reason: e.to_string(),
    };
    let mut out = Vec::new();
    for line in text.lines() {
        let value: serde_json::Value = serde_json::from_str(line).map_err(bad)?;
        if !skip(&value) {
            out.push(serde_json::from_str(line).map_err(bad)?);
        }
    }
    Ok(out)
}

/// Reads the step lines of a run's `metrics.jsonl`.
pub fn read_metrics(run: &Path) -> Result<Vec<StepMetrics>> {
    read_lines(run, |v| v.get("validation").is_some())
}

/// Reads the validation lines of a run's `metrics.jsonl`: (step, means).
pub fn read_validation(run: &Path) -> Result<Vec<(u64, ValidationMetrics)>> {
    let lines: Vec<ValidationLine> = read_lines(run, |v| v.get("validation").is_none())?;
    Ok(lines.into_iter().map(|l| (l.step, l.validation)).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A mean over ranks of f32 losses is often the exact midpoint of two f32 values, whose
    /// shortest decimal form has 17 digits: it must read back as the same f64, or rounding it to
    /// f32 (as the TensorBoard log does) can land on the other neighbour.
    #[test]
    fn metrics_lines_read_back_bit_for_bit() {
        let run = tempfile::tempdir().unwrap();
        let mut loss = 1.0f32;
        let written: Vec<StepMetrics> = (1..=2000)
            .map(|step| {
                let next = f32::from_bits(loss.to_bits() + 1);
                let midpoint = (f64::from(loss) + f64::from(next)) / 2.0;
                loss = f32::from_bits(loss.to_bits() + 7919);
                StepMetrics {
                    step,
                    loss: midpoint,
                    lr: 2e-5,
                    grad_norm: midpoint * 3.0,
                    seconds: 0.1,
                    encode_seconds: 0.0,
                    cuda_peak_allocated: None,
                    cuda_peak_reserved: None,
                }
            })
            .collect();
        let lines: String = written.iter().map(|m| serde_json::to_string(m).unwrap() + "\n").collect();
        std::fs::write(run.path().join("metrics.jsonl"), lines).unwrap();
        let read = read_metrics(run.path()).unwrap();
        assert_eq!(read.len(), written.len());
        for (a, b) in written.iter().zip(&read) {
            assert_eq!(a.loss.to_bits(), b.loss.to_bits(), "step {}: loss {} read as {}", a.step, a.loss, b.loss);
            assert_eq!(a.loss as f32, b.loss as f32);
            assert_eq!(a.grad_norm.to_bits(), b.grad_norm.to_bits());
        }
    }
}

//! `trainer nvs`: the whole novel-view job on one video in one command: test-time finetuning on
//! the video's own pairs, a render of the video from each camera path, and a sample of every
//! render with one load of the finetuned model.
//!
//! Phases, each recorded in `OUT/nvs.json` when it ends, so that the same command run again after
//! a kill continues from the last finished one (finetuning itself from its last checkpoint):
//! 1. `finetune` (skipped with 0 steps): `OUT/finetune/` is a `trainer finetune` run;
//! 2. `render`: `OUT/renders/<name>/` is `datagen render`'s output for trajectory `<name>` (the
//!    file's stem), hole-filled from the stacked static background when the video is longer
//!    than the frames sampled;
//! 3. `sample`: `OUT/<name>.mp4`, `OUT/<name>/` (PNG frames) and `OUT/<name>_sheet.png`
//!    (source | render | result rows) per trajectory.
//!
//! `nvs.json` keeps every setting, the seeds, the inputs' digests and the outputs' digests. A
//! folder whose `nvs.json` records other settings or other inputs is refused, and one that
//! another `nvs` is working in (its `trainer.lock`) too. Every argument, model folder and input
//! (output names included: one plain file name each, clashing neither with the job's own files
//! nor with each other) is checked before the first write, so a refused command leaves OUT as it
//! was; the job is recorded once it starts.
//!
//! Preemption: a signal during finetuning ends it as `finetune` does (a complete checkpoint, see
//! [`crate::training::preempt`]; before its first step, at once); during rendering and sampling
//! the job stops after the trajectory in progress. Either way the caller exits with
//! [`crate::training::preempt::EXIT_PREEMPTED`] and the same command continues the job.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use datagen::api::LayoutName;
use image::RgbImage;
use serde::{Deserialize, Serialize};
use tch::Device;

use crate::error::{Error, Result};
use crate::loaders::ModelSource;
use crate::pipelines::sampling::{Framing, LoadOptions, Pipeline};
use crate::training::ReadSequence;
use crate::training::preempt::Checkpointable;
use crate::training::{FinetuneRequest, StepMetrics};

/// Test-time finetuning steps by default: the paper finetunes 200 to 400 steps per video (CogNVS
/// §3.3); the lower end, as the public code's default.
pub const DEFAULT_FINETUNE_STEPS: u64 = 200;

/// How an nvs job finetunes and samples: every setting but its inputs and output folder.
/// `trainer nvs` and each window of `trainer benchmark` run with one, and both run records
/// (`nvs.json`, the benchmark's `settings.json`) write it as its [`SettingsRecord`].
#[derive(Debug, Clone)]
pub struct NvsSettings {
    /// The checkpoint to finetune (and sample) and where its other models come from; `lora`,
    /// `text_embedding` and `zero_text_embedding` apply to both phases.
    pub model: ModelSource,
    /// Finetuning steps (0: sample the checkpoint as it is).
    pub steps: u64,
    /// Trajectories sampled per clip for the finetuning pairs.
    pub finetune_trajectories: u32,
    /// Training TOML for finetuning (needed for a checkpoint that is not a trainer run's).
    pub config: Option<PathBuf>,
    /// Denoising steps per sample.
    pub sample_steps: usize,
    /// Classifier-free guidance scale.
    pub guidance: f64,
    /// Seed of every sampling draw (each trajectory samples with it, as the demo does).
    pub seed: u64,
    /// Device, arithmetic and VAE tiling of sampling.
    pub load: LoadOptions,
    /// Frames, sizes and frame rate of sampling.
    pub framing: Framing,
    /// Fill render holes from the stacked static background: None decides by length (on when
    /// the video has more frames than are sampled).
    pub stack_background: Option<bool>,
}

/// Everything `trainer nvs` is asked to do.
#[derive(Debug, Clone)]
pub struct NvsRequest {
    /// The video's sequence folder (cog-nvs, MegaSAM npz or generic layout).
    pub sequence: PathBuf,
    /// The sequence folder's layout (None: detected from its files).
    pub layout: Option<LayoutName>,
    /// Camera paths (`.npy`, `.json` or `trajs/*.txt`), one output each, named by file stem.
    pub trajectories: Vec<PathBuf>,
    /// Output folder.
    pub out: PathBuf,
    /// How the job finetunes and samples.
    pub settings: NvsSettings,
}

/// [`NvsSettings`] as the run records write them (paths as given, enums by their names).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SettingsRecord {
    init: String,
    base_model: Option<String>,
    vae: Option<String>,
    lora: Option<String>,
    text_embedding: Option<String>,
    zero_text_embedding: bool,
    steps: u64,
    finetune_trajectories: u32,
    config: Option<String>,
    sample_steps: usize,
    guidance: f64,
    seed: u64,
    precision: String,
    vae_tiling: bool,
    frames: usize,
    resize: String,
    size: Option<(u32, u32)>,
    restore_size: bool,
    fps: f64,
    stack_background: Option<bool>,
}

impl NvsSettings {
    /// The settings as the run records write them.
    pub fn record(&self) -> SettingsRecord {
        let show = |p: &Option<PathBuf>| p.as_ref().map(|p| p.display().to_string());
        SettingsRecord {
            init: self.model.checkpoint.display().to_string(),
            base_model: show(&self.model.base_model),
            vae: show(&self.model.vae),
            lora: show(&self.model.lora),
            text_embedding: show(&self.model.text_embedding),
            zero_text_embedding: self.model.zero_text_embedding,
            steps: self.steps,
            finetune_trajectories: self.finetune_trajectories,
            config: show(&self.config),
            sample_steps: self.sample_steps,
            guidance: self.guidance,
            seed: self.seed,
            precision: format!("{:?}", self.load.precision),
            vae_tiling: self.load.vae_tiling,
            frames: self.framing.frames,
            resize: format!("{:?}", self.framing.resize),
            size: self.framing.size,
            restore_size: self.framing.restore_size,
            fps: self.framing.fps,
            stack_background: self.stack_background,
        }
    }
}

/// The settings `nvs.json` records and a re-run must repeat: the job's settings and its inputs'
/// paths (the layout only when one is named, so that records of detected layouts stay as they
/// were).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Settings {
    #[serde(flatten)]
    job: SettingsRecord,
    sequence: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    layout: Option<String>,
    trajectories: Vec<String>,
}

/// One trajectory's outputs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Output {
    /// Its name (the trajectory file's stem).
    pub name: String,
    /// The render folder.
    pub render: String,
    /// Render holes filled from the stacked background.
    pub stacked_background: bool,
    /// The video, the PNG frame folder and the contact sheet.
    pub video: Option<String>,
    /// The PNG frames' folder.
    pub frames: Option<String>,
    /// The contact sheet.
    pub sheet: Option<String>,
    /// blake3 of each output file (video, sheet, every frame), by path relative to OUT.
    pub digests: std::collections::BTreeMap<String, String>,
    /// Seconds of sampling.
    pub sample_seconds: Option<f64>,
}

/// `OUT/nvs.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Record {
    /// What was asked (see the module docs).
    settings: serde_json::Value,
    /// blake3 of the inputs that are not models: the sequence folder, each trajectory file and
    /// the text embedding.
    pub inputs: std::collections::BTreeMap<String, String>,
    /// The checkpoint sampled (the finetuned one, or the init checkpoint with 0 steps).
    pub checkpoint: Option<String>,
    /// Seconds of finetuning.
    pub finetune_seconds: Option<f64>,
    /// Per trajectory, in the order given.
    pub outputs: Vec<Output>,
    /// Whether every phase has finished.
    pub complete: bool,
}

/// What a phase reports while it runs.
#[derive(Debug)]
pub enum Progress<'a> {
    /// A phase starts (`finetune` with its steps, `render`/`sample` with the trajectory count).
    Phase(&'static str, u64),
    /// A phase was finished by an earlier run.
    Skipped(&'static str),
    /// A finetuning step ended.
    Step(&'a StepMetrics),
    /// A trajectory of the `render` or `sample` phase ended.
    Trajectory(&'a str),
    /// A denoising step ended (step, of steps).
    Denoise(usize, usize),
}

/// The job's record in OUT.
const RECORD: &str = "nvs.json";
/// The record while it is written (renamed over [`RECORD`]).
const RECORD_TEMPORARY: &str = "nvs.json.tmp";
/// The finetuning run's folder in OUT.
const FINETUNE_DIR: &str = "finetune";
/// The renders' folder in OUT.
const RENDERS_DIR: &str = "renders";
/// The sequence folder's key among the record's input digests.
const SEQUENCE_INPUT: &str = "sequence";

/// How a call of [`run`] ended.
#[derive(Debug)]
pub struct Outcome {
    /// The record as written (None on ranks other than 0).
    pub record: Option<Record>,
    /// Whether a preemption signal stopped the job before its end (run it again to continue).
    pub preempted: bool,
}

/// `trainer nvs`: joins the job the launcher started (if any; see
/// [`crate::distributed::join_job`]) and runs [`run`] as one rank of it; `progress` hears rank 0's
/// events only.
pub fn run_launched(request: &NvsRequest, device: Device, progress: &mut dyn FnMut(Progress)) -> Result<Outcome> {
    let timeout = crate::training::timeout_seconds(request.settings.config.as_deref())?;
    let (device, pg) = crate::distributed::join_job(device, timeout)?;
    let lead = pg.as_ref().is_none_or(|pg| pg.rank == 0);
    run(request, device, pg.as_ref(), &mut |event| {
        if lead {
            progress(event)
        }
    })
}

/// Runs (or continues) the job; `pg` makes the finetuning phase one rank of a multi-process run
/// (the other phases run on rank 0 alone; other ranks return after finetuning).
pub fn run(
    request: &NvsRequest,
    device: Device,
    pg: Option<&crate::distributed::ProcessGroup>,
    progress: &mut dyn FnMut(Progress),
) -> Result<Outcome> {
    let rank = pg.map_or(0, |pg| pg.rank);
    // Every argument, model folder and input is checked before the first write: a refused
    // command leaves OUT as it was, and the corrected command starts there as if new.
    let Preflight { names, video, poses, pairs, settings, inputs, train } = preflight(request)?;
    let record_path = request.out.join(RECORD);
    // One job per output folder; the finetuning run below holds its own folder's lock as well.
    let _lock = crate::training::RunLock::acquire_on(&request.out, "trainer nvs", pg)?;
    // Alive for the whole job, so that no signal falls between the phases' own watches.
    let watch = preemption_watch(&train)?;
    // Read again under the lock: another job may have recorded itself since the check.
    let mut record = job_record(request, &settings, &inputs)?;
    record.inputs = inputs;
    if rank == 0 {
        write_record(&record_path, &record)?;
    }

    // 1. Finetuning. Until it ends a signal stops the job at once (finetuning's own loop
    // excepted): the record holds what was done. From then on the job stops between
    // trajectories, each of which is recorded as it ends.
    let mut checkpointable = None;
    let mut model = request.settings.model.clone();
    if request.settings.steps > 0 && record.checkpoint.is_none() {
        progress(Progress::Phase("finetune", request.settings.steps));
        let started = Instant::now();
        let finetune = finetune_request(request, Some(video.clone()));
        let summary = crate::training::finetune_on(&finetune, device, pg, |m| progress(Progress::Step(m)))?;
        checkpointable = Some(Checkpointable::enter());
        if summary.preempted || rank != 0 {
            return Ok(Outcome { record: (rank == 0).then_some(record), preempted: summary.preempted });
        }
        let checkpoint = summary.last_checkpoint.ok_or_else(|| Error::InvalidArgument {
            name: "steps".to_string(),
            reason: "finetuning wrote no checkpoint".to_string(),
        })?;
        record.checkpoint = Some(checkpoint.display().to_string());
        record.finetune_seconds = Some(started.elapsed().as_secs_f64());
        write_record(&record_path, &record)?;
    } else if request.settings.steps > 0 {
        progress(Progress::Skipped("finetune"));
        if rank != 0 {
            return Ok(Outcome { record: None, preempted: false });
        }
    } else {
        record.checkpoint = Some(request.settings.model.checkpoint.display().to_string());
    }
    if request.settings.steps > 0 {
        // The finetuned checkpoint brings its run's VAE, text embedding and (for LoRA) base; the
        // adapter given at the start is merged into it already.
        model.checkpoint = PathBuf::from(record.checkpoint.as_ref().expect("set above"));
        model.lora = None;
    }

    // Rendering and sampling stop between trajectories on a preemption signal.
    let _checkpointable = checkpointable.unwrap_or_else(Checkpointable::enter);
    let stopped = |record: Record| -> Result<Outcome> {
        write_record(&record_path, &record)?;
        Ok(Outcome { record: Some(record), preempted: true })
    };

    // 2. Renders.
    let sequence = &video.sequence;
    let stack = request.settings.stack_background.unwrap_or(sequence.len() > request.settings.framing.frames);
    let to_render: Vec<usize> =
        (0..names.len()).filter(|&i| !record.outputs.iter().any(|o| o.name == names[i])).collect();
    if to_render.is_empty() {
        progress(Progress::Skipped("render"));
    } else {
        progress(Progress::Phase("render", to_render.len() as u64));
    }
    for &i in &to_render {
        let folder = request.out.join(RENDERS_DIR).join(&names[i]);
        datagen::api::render_sequence(sequence, &poses[i], &folder, &pairs, stack)?;
        record.outputs.push(Output {
            name: names[i].clone(),
            render: relative(&folder, &request.out),
            stacked_background: stack,
            video: None,
            frames: None,
            sheet: None,
            digests: Default::default(),
            sample_seconds: None,
        });
        write_record(&record_path, &record)?;
        progress(Progress::Trajectory(&names[i]));
        if watch.received().is_some() {
            watch.hold_until_exit();
            return stopped(record);
        }
    }

    // 3. Samples, with one load of the model.
    let pending: Vec<usize> = (0..record.outputs.len()).filter(|&i| record.outputs[i].video.is_none()).collect();
    if pending.is_empty() {
        progress(Progress::Skipped("sample"));
    } else {
        progress(Progress::Phase("sample", pending.len() as u64));
        if watch.received().is_some() {
            watch.hold_until_exit();
            return stopped(record);
        }
        let paths = model.resolve()?;
        crate::training::plan::check_sampling_memory(&paths, request.settings.load, &request.settings.framing)?;
        let pipeline = Pipeline::load(&paths, request.settings.load)?;
        for i in pending {
            let name = record.outputs[i].name.clone();
            let render = request.out.join(&record.outputs[i].render);
            let sampled = pipeline.sample(
                &render,
                &request.settings.framing,
                request.settings.sample_steps,
                request.settings.guidance,
                request.settings.seed,
                request.settings.load.device,
                &mut |s, n| progress(Progress::Denoise(s, n)),
            )?;
            let (frames, seconds) = (sampled.frames, sampled.seconds);
            let output =
                write_outputs(&request.out, &name, &frames, &sequence.frames, &render, request.settings.framing.fps)?;
            record.outputs[i] = Output { sample_seconds: Some(seconds), ..output.with_render(&record.outputs[i]) };
            write_record(&record_path, &record)?;
            progress(Progress::Trajectory(&name));
            if watch.received().is_some() && record.outputs.iter().any(|o| o.video.is_none()) {
                watch.hold_until_exit();
                return stopped(record);
            }
        }
    }
    record.complete = true;
    write_record(&record_path, &record)?;
    Ok(Outcome { record: Some(record), preempted: false })
}

/// The preemption watch of the rendering and sampling phases: the finetuning config's signals
/// and grace (`[loop] preempt_signals`, `preempt_grace_seconds`), else their defaults.
fn preemption_watch(train: &crate::training::LoopConfig) -> Result<crate::training::preempt::PreemptWatch> {
    let signals: Vec<i32> =
        train.preempt_signals.iter().filter_map(|name| crate::training::preempt::signal_number(name)).collect();
    let grace =
        (train.preempt_grace_seconds > 0.0).then(|| std::time::Duration::from_secs_f64(train.preempt_grace_seconds));
    crate::training::preempt::PreemptWatch::install(&signals, grace)
}

/// What [`preflight`] found.
struct Preflight {
    /// The trajectories' output names.
    names: Vec<String>,
    /// The video, read once for every phase.
    video: Arc<ReadSequence>,
    /// Each trajectory's poses, read once.
    poses: Vec<Vec<datagen::api::DMat4>>,
    /// The pair settings of finetuning, which the renders share (their mesh and background).
    pairs: datagen::api::PairsConfig,
    /// The settings `nvs.json` records.
    settings: serde_json::Value,
    /// The inputs' digests.
    inputs: std::collections::BTreeMap<String, String>,
    /// The `[loop]` settings of `--config` (its preemption signals and grace), else defaults.
    train: crate::training::LoopConfig,
}

/// Checks the whole request without writing anything: the output names, the output folder and
/// its record (same settings, same inputs), the video and every trajectory against it, the
/// finetuning config and models (with `--steps` > 0), and the sampled models (configs, headers,
/// LoRA files, text embeddings) with the sampling arguments.
fn preflight(request: &NvsRequest) -> Result<Preflight> {
    let names = trajectory_names(&request.trajectories)?;
    if request.out.exists() && !request.out.is_dir() {
        return Err(Error::InvalidArgument {
            name: "out".to_string(),
            reason: format!("{} exists and is not a folder", request.out.display()),
        });
    }
    let settings = serde_json::to_value(settings(request)).expect("settings serialise");
    // Settings first: a folder of another job is named before any input is read.
    let record = job_record(request, &settings, &Default::default())?;
    if record.inputs.is_empty() {
        // A new job: it must not replace what is in OUT already.
        let ours = [FINETUNE_DIR, RENDERS_DIR].into_iter().map(str::to_string);
        let outputs = names.iter().flat_map(|n| output_entries(n));
        if let Some(entry) = ours.chain(outputs).find(|entry| request.out.join(entry).exists()) {
            return Err(Error::InvalidArgument {
                name: "out".to_string(),
                reason: format!(
                    "{} holds {entry} but no {RECORD}: this job's output would replace it; choose an empty or new \
                     folder",
                    request.out.display()
                ),
            });
        }
    }
    let given = request.settings.config.as_deref().map(crate::training::PretrainConfig::from_toml_file).transpose()?;
    let train = given.as_ref().map(|c| c.train.clone()).unwrap_or_default();
    let sequence = datagen::api::read_sequence(&request.sequence, request.layout)?;
    let poses = request
        .trajectories
        .iter()
        .map(|path| datagen::api::read_trajectory(path, &sequence))
        .collect::<std::result::Result<Vec<_>, _>>()?;
    let inputs = input_digests(request)?;
    job_record(request, &settings, &inputs)?;
    let video = Arc::new(ReadSequence { sequence, content_hash: inputs[SEQUENCE_INPUT].clone() });
    let mut pairs = match &given {
        Some(config) => crate::training::finetune_pairs_config(config)?,
        None => datagen::api::PairsConfig::default(),
    };
    if request.settings.steps > 0 {
        if request.settings.finetune_trajectories == 0 {
            return Err(Error::InvalidArgument {
                name: "finetune-trajectories".to_string(),
                reason: "0 trajectories per clip give no finetuning pairs: pass at least 1 (or --steps 0)".to_string(),
            });
        }
        let (config, source_name) = crate::training::finetune_config(&finetune_request(request, None))?;
        config.validate(&source_name)?;
        config.model.check_text_embedding()?;
        pairs = crate::training::finetune_pairs_config(&config)?;
    }
    let paths = request.settings.model.resolve()?;
    let checked = crate::pipelines::sampling::Checked::read(&paths, Device::Cpu)?;
    checked.check_sampling(
        "sample-steps",
        request.settings.sample_steps,
        request.settings.guidance,
        &request.settings.framing,
    )?;
    crate::training::plan::check_sampling_memory(&paths, request.settings.load, &request.settings.framing)?;
    Ok(Preflight { names, video, poses, pairs, settings, inputs, train })
}

/// The job `OUT/nvs.json` records (a new one when there is none), refused when it was asked with
/// other settings or, once `inputs` are known (not empty), on other inputs.
fn job_record(
    request: &NvsRequest,
    settings: &serde_json::Value,
    inputs: &std::collections::BTreeMap<String, String>,
) -> Result<Record> {
    let record_path = request.out.join(RECORD);
    match read_record(&record_path)? {
        Some(record) if &record.settings != settings => Err(Error::InvalidArgument {
            name: "out".to_string(),
            reason: format!(
                "{} holds a job with other settings ({}); use the same arguments to continue it or another folder",
                request.out.display(),
                record_path.display()
            ),
        }),
        Some(record) if !inputs.is_empty() && !record.inputs.is_empty() && &record.inputs != inputs => {
            Err(Error::InvalidArgument {
                name: "sequence".to_string(),
                reason: format!(
                    "the inputs changed since {} was written (the video, a trajectory or the text embedding): \
                     start a new output folder",
                    record_path.display()
                ),
            })
        }
        Some(record) => Ok(record),
        None => Ok(Record {
            settings: settings.clone(),
            inputs: Default::default(),
            checkpoint: None,
            finetune_seconds: None,
            outputs: Vec::new(),
            complete: false,
        }),
    }
}

/// The finetuning phase's request: the job's models and video (`read` when read already), its
/// run in `OUT/finetune`.
fn finetune_request(request: &NvsRequest, read: Option<Arc<ReadSequence>>) -> FinetuneRequest {
    FinetuneRequest {
        init: request.settings.model.checkpoint.clone(),
        base_model: request.settings.model.base_model.clone(),
        vae: request.settings.model.vae.clone(),
        text_embedding: request.settings.model.text_embedding.clone(),
        zero_text_embedding: request.settings.model.zero_text_embedding,
        sequence: request.sequence.clone(),
        layout: request.layout,
        read,
        out: request.out.join(FINETUNE_DIR),
        steps: request.settings.steps,
        trajectories: request.settings.finetune_trajectories,
        config: request.settings.config.clone(),
        lora: request.settings.model.lora.clone(),
        resume: true,
    }
}

impl Output {
    fn with_render(self, rendered: &Output) -> Output {
        Output { render: rendered.render.clone(), stacked_background: rendered.stacked_background, ..self }
    }
}

/// Writes `OUT/<name>.mp4`, `OUT/<name>/%05d.png` and the contact sheet, with their digests.
fn write_outputs(
    out: &Path,
    name: &str,
    frames: &[RgbImage],
    source: &[RgbImage],
    render: &Path,
    fps: f64,
) -> Result<Output> {
    let video = out.join(format!("{name}.mp4"));
    let folder = out.join(name);
    crate::pipelines::sampling::write_frames(&folder, frames, fps)?;
    crate::pipelines::sampling::write_frames(&video, frames, fps)?;
    let rendered = crate::pipelines::sampling::read_condition_named(render)?.frames;
    let sheet = out.join(format!("{name}_sheet.png"));
    contact_sheet(source, &rendered, frames).save(&sheet).map_err(|e| Error::InvalidInput {
        path: sheet.clone(),
        what: "contact sheet".to_string(),
        reason: e.to_string(),
    })?;
    let mut digests = std::collections::BTreeMap::new();
    let mut files = vec![video.clone(), sheet.clone()];
    files.extend((0..frames.len()).map(|i| folder.join(format!("{i:05}.png"))));
    for file in files {
        digests.insert(relative(&file, out), digest(&file)?);
    }
    Ok(Output {
        name: name.to_string(),
        render: String::new(),
        stacked_background: false,
        video: Some(relative(&video, out)),
        frames: Some(relative(&folder, out)),
        sheet: Some(relative(&sheet, out)),
        digests,
        sample_seconds: None,
    })
}

/// Rows of source | render | result at evenly spaced frames, each tile at the result's size.
fn contact_sheet(source: &[RgbImage], render: &[RgbImage], result: &[RgbImage]) -> RgbImage {
    /// Rows of the sheet (first, last and evenly between).
    const ROWS: usize = 4;
    let count = result.len().min(source.len()).min(render.len());
    let (w, h) = result[0].dimensions();
    let fit = |image: &RgbImage| {
        if image.dimensions() == (w, h) {
            image.clone()
        } else {
            crate::pipelines::video_processor::resize_linear(image, w, h)
        }
    };
    let rows: Vec<Vec<RgbImage>> = (0..ROWS.min(count))
        .map(|k| k * (count - 1) / (ROWS.min(count) - 1).max(1))
        .map(|i| vec![fit(&source[i]), fit(&render[i]), result[i].clone()])
        .collect();
    foundation::contact_sheet::contact_sheet(&rows)
}

/// Trajectory names (file stems). Each names files and folders in OUT (`<name>/`, `<name>.mp4`,
/// `<name>_sheet.png`, `renders/<name>/`), so it must be one plain path component (not `..`,
/// `.`, empty or a path), valid UTF-8, and its outputs must clash neither with the job's own
/// files (`nvs.json`, its temporary, the lock, `finetune/`, `renders/`) nor with another
/// trajectory's. Errors name `--trajectory` and the file.
fn trajectory_names(paths: &[PathBuf]) -> Result<Vec<String>> {
    if paths.is_empty() {
        return Err(Error::InvalidArgument {
            name: "trajectory".to_string(),
            reason: "give at least one --trajectory FILE".to_string(),
        });
    }
    let refuse = |path: &Path, why: String| Error::InvalidArgument {
        name: "trajectory".to_string(),
        reason: format!(
            "--trajectory {}: the outputs are named after the file's stem, and {why}; rename the file",
            path.display()
        ),
    };
    let reserved = [RECORD, RECORD_TEMPORARY, crate::training::run_lock::LOCK_NAME, FINETUNE_DIR, RENDERS_DIR];
    // Each output entry in OUT, with the trajectory that makes it.
    let mut taken: Vec<(String, &Path)> = Vec::new();
    let mut names = Vec::new();
    for path in paths {
        let stem = path.file_stem().unwrap_or_default();
        let Some(name) = stem.to_str() else {
            return Err(refuse(path, format!("{} is not valid UTF-8", stem.to_string_lossy())));
        };
        let mut components = Path::new(name).components();
        let plain = matches!((components.next(), components.next()), (Some(std::path::Component::Normal(c)), None) if c == name);
        if !plain || name.contains(['/', '\\', '\0']) {
            return Err(refuse(path, format!("`{name}` is not one plain file name (empty, `.`, `..` or a path)")));
        }
        if output_entries(name).iter().any(|entry| entry.len() > NAME_MAX_BYTES) {
            return Err(refuse(path, format!("`{name}` makes output names longer than {NAME_MAX_BYTES} bytes")));
        }
        for entry in output_entries(name) {
            if reserved.contains(&entry.as_str()) {
                return Err(refuse(
                    path,
                    format!("its output `{entry}` would replace the job's own `{entry}` in --out"),
                ));
            }
            if let Some((_, other)) = taken.iter().find(|(e, _)| *e == entry) {
                return Err(refuse(
                    path,
                    format!("its output `{entry}` is also an output of --trajectory {}", other.display()),
                ));
            }
            taken.push((entry, path));
        }
        names.push(name.to_string());
    }
    Ok(names)
}

/// The entries of OUT a trajectory named `name` writes: its frame folder, video and sheet.
fn output_entries(name: &str) -> [String; 3] {
    [name.to_string(), format!("{name}.mp4"), format!("{name}_sheet.png")]
}

/// The longest file name Linux file systems take (`NAME_MAX`).
const NAME_MAX_BYTES: usize = 255;

fn settings(r: &NvsRequest) -> Settings {
    Settings {
        job: r.settings.record(),
        sequence: r.sequence.display().to_string(),
        layout: r.layout.map(|l| l.as_str().to_string()),
        trajectories: r.trajectories.iter().map(|p| p.display().to_string()).collect(),
    }
}

fn input_digests(request: &NvsRequest) -> Result<std::collections::BTreeMap<String, String>> {
    let mut digests = std::collections::BTreeMap::new();
    digests.insert(SEQUENCE_INPUT.to_string(), foundation::hashing::hash_tree(&request.sequence)?);
    for path in request.trajectories.iter().chain(&request.settings.model.text_embedding) {
        digests.insert(path.display().to_string(), digest(path)?);
    }
    Ok(digests)
}

fn digest(path: &Path) -> Result<String> {
    let bytes = std::fs::read(path).map_err(|e| Error::Io { path: path.to_path_buf(), error: e })?;
    Ok(blake3::hash(&bytes).to_hex().to_string())
}

fn relative(path: &Path, root: &Path) -> String {
    path.strip_prefix(root).unwrap_or(path).display().to_string()
}

fn read_record(path: &Path) -> Result<Option<Record>> {
    match std::fs::read_to_string(path) {
        Ok(text) => serde_json::from_str(&text).map(Some).map_err(|e| Error::InvalidConfig {
            source_name: path.display().to_string(),
            field: "(json)".to_string(),
            reason: e.to_string(),
        }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(Error::Io { path: path.to_path_buf(), error: e }),
    }
}

/// Writes the record atomically (a temporary file renamed over it).
fn write_record(path: &Path, record: &Record) -> Result<()> {
    let text = serde_json::to_vec_pretty(record).expect("record serialises");
    let temporary = path.with_file_name(RECORD_TEMPORARY);
    std::fs::write(&temporary, text).map_err(|e| Error::Io { path: temporary.clone(), error: e })?;
    std::fs::rename(&temporary, path).map_err(|e| Error::Io { path: path.to_path_buf(), error: e })
}

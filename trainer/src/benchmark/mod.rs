//! `trainer benchmark`: the paper's evaluation of a checkpoint on a multi-camera dataset in one
//! command (CogNVS Table 1: Kubric-4D and ParallelDomain-4D under GCD's protocol; Table 2 and the
//! appendix's masked table: DyCheck iPhone).
//!
//! Per scene of `ROOT` (each sub-folder a multi-camera scene in the DyCheck, Kubric-4D,
//! ParallelDomain-4D or generic layout, [`datagen::api::read_multiview`]): the
//! frames scored are every held-out camera's frames at instants the split's input camera films
//! (for DyCheck with `correspondence`, those its correspondence file lists, as the official
//! script selects them). The input camera's video is sampled in windows of `--frames` instants
//! that cover every scored instant ([`scene::plan_windows`]: back to back from the first, the
//! last shifted back to end at the last scored instant; an instant two windows cover is scored
//! from the earlier). Per window the source, rendered from the dataset's own depth and cameras
//! or from a reconstruction folder ([`Reconstruction`]), and each held-out camera's poses at
//! its instants (a trajectory) make one `trainer nvs` job ([`crate::pipelines::nvs::run`]:
//! finetuning on the window's source, then a sample of every trajectory). Each result is brought
//! to the held-out camera's intrinsics and size ([`scene::write_view`]) and a camera's frames of
//! every window are scored against its frames at the same instants by `trainer eval`'s code
//! ([`crate::eval::score::run_pairs`]) at the protocol's size, over the co-visibility masks the
//! dataset ships where it ships them (DyCheck). Means pool frames and keep infinite values (∞ in
//! the table, `"inf"` in the JSON), as the official codes' `np.mean` does. FID/KID pool every
//! frame of every scene, as GCD and the paper do.
//!
//! `OUT/settings.json` holds every setting and the checkpoint's digest; a rerun with other
//! settings is refused naming what changed. `OUT/scenes/<scene>/` is a scene's work
//! (`window-<start>/` per window with its source sequence, trajectories and `nvs/` job; `pred/`,
//! `target/`, `mask/` per held-out camera); `OUT/results/<scene>.json`, written atomically when
//! the scene is scored, marks it done: a rerun skips it, and a scene killed part way skips its
//! finished windows' jobs and continues the one it was in. A scene whose inputs are broken
//! is reported as failed with its reason (and tried again by the next run); the rest go on.
//! `OUT/report.{json,md}` hold the table (see [`report`]).

pub mod report;
pub mod scene;

use std::path::{Path, PathBuf};
use std::time::Instant;

use datagen::api::LayoutName;
use serde::{Deserialize, Serialize};
use tch::Device;

use crate::error::{Error, Result};
use crate::eval::lpips::LpipsNet;
use crate::eval::score::{Protocol, ScoreRequest};
use crate::loaders::ModelSource;
use crate::pipelines::nvs::{NvsSettings, SettingsRecord};
pub use report::{Comparison, Metrics, Report, compare};
pub use scene::{Reconstruction, SplitOverride};

/// The benchmark datasets of the paper.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Dataset {
    /// DyCheck iPhone (the paper's Table 2).
    Dycheck,
    /// Kubric-4D as GCD distributes it (Table 1).
    Kubric4d,
    /// ParallelDomain-4D as GCD distributes it (Table 1).
    Pardom4d,
}

impl Dataset {
    /// The protocol whose size the metrics are computed at: DyCheck's, else GCD's.
    pub fn protocol(self) -> Protocol {
        match self {
            Dataset::Dycheck => Protocol::Dycheck,
            Dataset::Kubric4d | Dataset::Pardom4d => Protocol::Gcd,
        }
    }

    /// Trajectories per clip of the paper's test-time finetuning: N = 5 on DyCheck, 9 on
    /// Kubric-4D and ParallelDomain-4D (CogNVS §4, implementation details).
    pub fn finetune_trajectories(self) -> u32 {
        match self {
            Dataset::Dycheck => 5,
            Dataset::Kubric4d | Dataset::Pardom4d => 9,
        }
    }

    /// The command-line name.
    pub fn name(self) -> &'static str {
        match self {
            Dataset::Dycheck => "dycheck",
            Dataset::Kubric4d => "kubric4d",
            Dataset::Pardom4d => "pardom4d",
        }
    }

    /// The name in a table's title.
    pub fn title(self) -> &'static str {
        match self {
            Dataset::Dycheck => "DyCheck iPhone",
            Dataset::Kubric4d => "Kubric-4D",
            Dataset::Pardom4d => "ParallelDomain-4D",
        }
    }
}

/// Everything `trainer benchmark` is asked to do.
#[derive(Debug, Clone)]
pub struct Request {
    /// The dataset (protocol, paper rows, finetuning trajectories).
    pub dataset: Dataset,
    /// The dataset folder: one sub-folder per scene.
    pub root: PathBuf,
    /// Scenes to evaluate, by folder name (empty: every scene of `root`, sorted).
    pub scenes: Vec<String>,
    /// The scenes' layout (None: detected per scene from its files).
    pub layout: Option<LayoutName>,
    /// Input and held-out cameras other than the dataset's split.
    pub split: SplitOverride,
    /// What the source is rendered from.
    pub reconstruction: Reconstruction,
    /// Output folder.
    pub out: PathBuf,
    /// How each window's nvs job finetunes and samples (as `trainer nvs`); `framing.frames` is
    /// also the source window's length.
    pub nvs: NvsSettings,
    /// (width, height) of the metrics; None: the protocol's.
    pub eval_size: Option<(u32, u32)>,
    /// LPIPS weights (None: no LPIPS).
    pub lpips: Option<PathBuf>,
    /// LPIPS backbone.
    pub lpips_net: LpipsNet,
    /// Inception weights (None: no FID/KID).
    pub inception: Option<PathBuf>,
    /// KID subsets.
    pub kid_subsets: usize,
    /// KID's largest subset size (clean-fid's `max_subset_size`).
    pub kid_subset_size: usize,
    /// DyCheck: a folder of `dycheck_<scene>_source_target_correspondence.txt` files (the CogNVS
    /// evaluation bundle's `dycheck/`) selecting the held-out frames scored, as the official
    /// `eval_metrics.py` selects them (None: every held-out frame the input camera's instants
    /// meet).
    pub correspondence: Option<PathBuf>,
}

/// What the benchmark reports while it runs.
#[derive(Debug)]
pub enum Progress<'a> {
    /// Scene `name` starts (index, of scenes).
    Scene(&'a str, usize, usize),
    /// Scene `name` was scored by an earlier run with these settings.
    Skipped(&'a str),
    /// Scene `name` failed; the reason.
    Failed(&'a str, &'a str),
    /// Scene `name`'s window (index, of windows) starting at input frame `start` starts.
    Window(&'a str, usize, usize, usize),
    /// The window's `nvs` job reports.
    Nvs(crate::pipelines::nvs::Progress<'a>),
    /// Scene `name` is scored.
    Done(&'a str, &'a report::SceneLine),
}

/// How a call of [`run`] ended.
#[derive(Debug)]
pub struct Outcome {
    /// The report as written (None when preempted).
    pub report: Option<Report>,
    /// Whether a preemption signal stopped it (run it again to continue).
    pub preempted: bool,
}

/// The settings record in OUT.
const SETTINGS_JSON: &str = "settings.json";
/// The report in OUT.
pub const REPORT_JSON: &str = "report.json";
/// The Markdown table in OUT.
pub const REPORT_MD: &str = "report.md";
/// Per-scene results in OUT.
const RESULTS_DIR: &str = "results";
/// Per-scene work in OUT.
const SCENES_DIR: &str = "scenes";
/// A window's `nvs` job in its work folder.
const NVS_DIR: &str = "nvs";

/// One held-out camera's scores in a scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraResult {
    /// The camera's id.
    pub camera: String,
    /// Time ids of the frames scored.
    pub time_ids: Vec<usize>,
    /// Its metrics.
    pub metrics: Metrics,
    /// Mean squared error of the render over the pixels it covers ([0, 1] intensities).
    pub render_mse: Option<f64>,
    /// Share of the held-out camera's pixels the render covers.
    pub render_coverage: f64,
}

/// `OUT/results/<scene>.json`: a scored scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneResult {
    /// The scene.
    pub scene: String,
    /// The input camera.
    pub input_camera: String,
    /// The windows of the input camera's video sampled, in order.
    pub windows: Vec<WindowResult>,
    /// Dataset units per reconstruction unit (1 for the dataset's reconstruction).
    pub reconstruction_scale: f64,
    /// Per held-out camera.
    pub cameras: Vec<CameraResult>,
    /// Frames scored (all cameras).
    pub frames: usize,
    /// The frame-weighted mean over cameras.
    pub metrics: Metrics,
    /// Seconds of finetuning, sampling (all windows and trajectories) and the whole scene.
    pub seconds: SceneSeconds,
    /// The toolkit's commit that produced it.
    pub toolkit_commit: Option<String>,
}

/// One window of a scene: a clip of the input camera's video sampled by its own `nvs` job.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WindowResult {
    /// First frame (index into the input camera's video).
    pub start: usize,
    /// One past the last frame.
    pub end: usize,
    /// The instants (time ids) scored from this window; an instant two windows cover is scored
    /// from the earlier one.
    pub time_ids: Vec<usize>,
    /// The checkpoint sampled (the window's finetuned one with steps > 0).
    pub checkpoint: Option<String>,
}

/// Where a scene's time went.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct SceneSeconds {
    /// Test-time finetuning, all windows.
    pub finetune: Option<f64>,
    /// Sampling, all windows and trajectories.
    pub sample: Option<f64>,
    /// The scene from start to scores, in the run that finished it.
    pub total: f64,
}

impl SceneResult {
    /// PSNR of the render over its covered pixels, pooled over cameras (None if exact or empty).
    pub fn render_psnr(&self) -> Option<f64> {
        let (sum, weight) = self
            .cameras
            .iter()
            .filter_map(|c| {
                c.render_mse.map(|m| {
                    (m * c.render_coverage * c.time_ids.len() as f64, c.render_coverage * c.time_ids.len() as f64)
                })
            })
            .fold((0.0, 0.0), |(s, w), (m, c)| (s + m, w + c));
        (weight > 0.0 && sum > 0.0).then(|| -10.0 * (sum / weight).log10())
    }
}

/// The toolkit's commit: `git describe --always --dirty` in the source tree this binary was
/// built from, when it is still there.
pub fn toolkit_commit() -> Option<String> {
    let output = std::process::Command::new("git")
        .args(["-C", env!("CARGO_MANIFEST_DIR"), "describe", "--always", "--dirty", "--abbrev=12"])
        .stderr(std::process::Stdio::null())
        .output()
        .ok()?;
    let text = String::from_utf8(output.stdout).ok()?.trim().to_string();
    (output.status.success() && !text.is_empty()).then_some(text)
}

/// What `settings.json` records: everything that changes a scene's result, the nvs job's
/// settings as `nvs.json` records them beside the benchmark's own.
#[derive(Serialize)]
struct Settings {
    dataset: &'static str,
    root: String,
    layout: Option<&'static str>,
    input_camera: Option<String>,
    held_out_cameras: Vec<String>,
    reconstruction: String,
    checkpoint_digest: String,
    #[serde(flatten)]
    nvs: SettingsRecord,
    eval_size: (u32, u32),
    lpips: Option<String>,
    lpips_net: String,
    inception: Option<String>,
    kid_subsets: usize,
    kid_subset_size: usize,
    correspondence: Option<String>,
}

/// The settings `settings.json` records.
fn settings(r: &Request, checkpoint_digest: &str) -> serde_json::Value {
    let show = |p: &Option<PathBuf>| p.as_ref().map(|p| p.display().to_string());
    let settings = Settings {
        dataset: r.dataset.name(),
        root: r.root.display().to_string(),
        layout: r.layout.map(|l| l.as_str()),
        input_camera: r.split.input.clone(),
        held_out_cameras: r.split.held_out.clone(),
        reconstruction: match &r.reconstruction {
            Reconstruction::Dataset => "dataset".to_string(),
            Reconstruction::Folder(dir) => dir.display().to_string(),
        },
        checkpoint_digest: checkpoint_digest.to_string(),
        nvs: r.nvs.record(),
        eval_size: r.eval_size.unwrap_or(r.dataset.protocol().size()),
        lpips: show(&r.lpips),
        lpips_net: format!("{:?}", r.lpips_net),
        inception: show(&r.inception),
        kid_subsets: r.kid_subsets,
        kid_subset_size: r.kid_subset_size,
        correspondence: show(&r.correspondence),
    };
    serde_json::to_value(settings).expect("settings serialise")
}

/// blake3 of the checkpoint folder, with the LoRA file's when one is given.
fn checkpoint_digest(model: &ModelSource) -> Result<String> {
    let mut digest = foundation::hashing::hash_tree(&model.checkpoint)?;
    if let Some(lora) = &model.lora {
        digest =
            blake3::hash(format!("{digest}{}", foundation::hashing::hash_tree(lora)?).as_bytes()).to_hex().to_string();
    }
    Ok(digest)
}

/// Checks OUT and its settings (writing them for a new benchmark); refuses other settings,
/// naming each that changed.
fn check_settings(out: &Path, settings: &serde_json::Value) -> Result<()> {
    if out.exists() && !out.is_dir() {
        return Err(Error::InvalidArgument {
            name: "out".to_string(),
            reason: format!("{} exists and is not a folder", out.display()),
        });
    }
    let path = out.join(SETTINGS_JSON);
    match std::fs::read_to_string(&path) {
        Ok(text) => {
            let recorded: serde_json::Value = serde_json::from_str(&text).map_err(|e| Error::InvalidInput {
                path: path.clone(),
                what: "settings".to_string(),
                reason: e.to_string(),
            })?;
            if &recorded == settings {
                return Ok(());
            }
            let (Some(old), Some(new)) = (recorded.as_object(), settings.as_object()) else {
                return Err(Error::InvalidInput {
                    path,
                    what: "settings".to_string(),
                    reason: "not an object".to_string(),
                });
            };
            // Each key once, whether it is in both records or only one.
            let keys: std::collections::BTreeSet<&String> = new.keys().chain(old.keys()).collect();
            let changed: Vec<String> = keys
                .into_iter()
                .filter(|k| old.get(*k) != new.get(*k))
                .map(|k| {
                    format!(
                        "{k}: {} → {}",
                        old.get(k).cloned().unwrap_or_default(),
                        new.get(k).cloned().unwrap_or_default()
                    )
                })
                .collect();
            Err(Error::InvalidArgument {
                name: "out".to_string(),
                reason: format!(
                    "{} holds a benchmark with other settings ({}); rerun it with the same arguments to continue it, \
                     or give another --out",
                    out.display(),
                    changed.join(", ")
                ),
            })
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            std::fs::create_dir_all(out).map_err(|error| Error::Io { path: out.to_path_buf(), error })?;
            write_atomic(&path, &serde_json::to_vec_pretty(settings).expect("json"))
        }
        Err(error) => Err(Error::Io { path, error }),
    }
}

/// Writes `bytes` to a temporary name beside `path` and renames it over `path`.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let temporary = path.with_extension("tmp");
    std::fs::write(&temporary, bytes).map_err(|error| Error::Io { path: temporary.clone(), error })?;
    std::fs::rename(&temporary, path).map_err(|error| Error::Io { path: path.to_path_buf(), error })
}

/// The scenes to evaluate: `--scenes` in the order given, else every non-hidden sub-folder of
/// ROOT but OUT, sorted.
fn scene_names(request: &Request) -> Result<Vec<String>> {
    if !request.scenes.is_empty() {
        return Ok(request.scenes.clone());
    }
    let read = std::fs::read_dir(&request.root).map_err(|error| Error::Io { path: request.root.clone(), error })?;
    // OUT may live inside ROOT: it is no scene.
    let out = request.out.canonicalize().ok();
    let mut names: Vec<String> = read
        .filter_map(|e| e.ok())
        .filter(|e| e.path().is_dir() && (out.is_none() || e.path().canonicalize().ok() != out))
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| !n.starts_with('.'))
        .collect();
    names.sort();
    if names.is_empty() {
        return Err(Error::InvalidInput {
            path: request.root.clone(),
            what: "scenes".to_string(),
            reason: "no scene folders".to_string(),
        });
    }
    Ok(names)
}

/// Reads one scene folder in `layout` (None: detected).
fn read_scene(dir: &Path, layout: Option<LayoutName>) -> Result<datagen::api::MultiViewScene> {
    Ok(datagen::api::read_multiview(dir, layout)?)
}

/// The eval request of one scene's cameras (LPIPS, no FID) or of the pooled frames (FID/KID only).
fn eval_request(request: &Request, pooled: bool) -> ScoreRequest {
    ScoreRequest {
        pred: PathBuf::new(),
        target: PathBuf::new(),
        mask: None,
        single: false,
        protocol: None,
        top_k: None,
        lpips: if pooled { None } else { request.lpips.clone() },
        lpips_net: request.lpips_net,
        inception: if pooled { request.inception.clone() } else { None },
        kid: pooled,
        kid_subsets: request.kid_subsets,
        kid_subset_size: request.kid_subset_size,
        seed: request.nvs.seed,
        device: request.nvs.load.device,
    }
}

/// Every frame of `frames` at `size` (the protocol's), as `trainer eval --protocol` resizes
/// (`cv2.resize` for frames, nearest for masks).
fn resize_folder(dir: &Path, size: (u32, u32), nearest: bool) -> Result<()> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|error| Error::Io { path: dir.to_path_buf(), error })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    paths.sort();
    for path in paths {
        let image = image::open(&path).map_err(|e| Error::InvalidInput {
            path: path.clone(),
            what: "image".to_string(),
            reason: e.to_string(),
        })?;
        if (image.width(), image.height()) == size {
            continue;
        }
        let resized = if nearest {
            let resized = image.resize_exact(size.0, size.1, image::imageops::FilterType::Nearest);
            image::DynamicImage::ImageLuma8(resized.to_luma8())
        } else {
            image::DynamicImage::ImageRgb8(crate::eval::score::resize_to(&image.to_rgb8(), size))
        };
        resized.save(&path).map_err(|e| Error::InvalidInput {
            path: path.clone(),
            what: "image".to_string(),
            reason: e.to_string(),
        })?;
    }
    Ok(())
}

/// Runs (or continues) the benchmark.
pub fn run(request: &Request, progress: &mut dyn FnMut(Progress)) -> Result<Outcome> {
    if request.scenes.iter().any(|s| s.is_empty() || s.contains(['/', '\\']) || s == "." || s == "..") {
        return Err(Error::InvalidArgument {
            name: "scenes".to_string(),
            reason: format!("scene names are folder names under --root, got {:?}", request.scenes),
        });
    }
    // The models are checked once here, so a scene fails only for its own inputs.
    let paths = request.nvs.model.resolve()?;
    let checked = crate::pipelines::sampling::Checked::read(&paths, Device::Cpu)?;
    checked.check_sampling("sample-steps", request.nvs.sample_steps, request.nvs.guidance, &request.nvs.framing)?;
    for (name, path) in [("lpips-weights", &request.lpips), ("inception-weights", &request.inception)] {
        if let Some(path) = path.as_ref().filter(|p| !p.is_file()) {
            return Err(Error::InvalidArgument {
                name: name.to_string(),
                reason: format!("{}: no such file", path.display()),
            });
        }
    }
    if let Some(dir) = &request.correspondence
        && (request.dataset != Dataset::Dycheck || !dir.is_dir())
    {
        return Err(Error::InvalidArgument {
            name: "correspondence".to_string(),
            reason: if request.dataset == Dataset::Dycheck {
                format!("{}: not a folder (give the evaluation bundle's dycheck/ folder)", dir.display())
            } else {
                "correspondence files select DyCheck frames; this is a benchmark of another dataset".to_string()
            },
        });
    }
    if let Reconstruction::Folder(dir) = &request.reconstruction
        && !dir.is_dir()
    {
        return Err(Error::InvalidArgument {
            name: "reconstruction".to_string(),
            reason: format!(
                "{}: not a folder (give `dataset` or a folder of per-scene reconstructions)",
                dir.display()
            ),
        });
    }
    if let Some((width, height)) = request.eval_size
        && (width == 0 || height == 0)
    {
        return Err(Error::InvalidArgument {
            name: "eval-size".to_string(),
            reason: format!("{width}x{height}: the frames scored need at least one pixel a side"),
        });
    }
    // Every argument is checked above, before OUT records the settings: a refused argument must
    // not leave a record that then refuses the corrected command as "other settings".
    let names = scene_names(request)?;
    let digest = checkpoint_digest(&request.nvs.model)?;
    let settings = settings(request, &digest);
    check_settings(&request.out, &settings)?;
    let _lock = crate::training::RunLock::acquire_on(&request.out, "trainer benchmark", None)?;
    let commit = toolkit_commit();
    let size = request.eval_size.unwrap_or(request.dataset.protocol().size());

    let (mut done, mut failed) = (Vec::new(), Vec::new());
    for (index, name) in names.iter().enumerate() {
        let result_path = request.out.join(RESULTS_DIR).join(format!("{name}.json"));
        if let Some(result) = read_result(&result_path, name)? {
            progress(Progress::Skipped(name));
            done.push(result);
            continue;
        }
        progress(Progress::Scene(name, index, names.len()));
        match run_scene(request, name, size, commit.clone(), progress) {
            Ok(SceneOutcome::Done(result)) => {
                let results = request.out.join(RESULTS_DIR);
                std::fs::create_dir_all(&results).map_err(|error| Error::Io { path: results, error })?;
                write_atomic(&result_path, &serde_json::to_vec_pretty(&result).expect("json"))?;
                progress(Progress::Done(name, &scene_line(&result)));
                done.push(*result);
            }
            Ok(SceneOutcome::Preempted) => return Ok(Outcome { report: None, preempted: true }),
            Err(error) => {
                let reason = error.to_string();
                progress(Progress::Failed(name, &reason));
                failed.push(report::FailedScene { scene: name.clone(), reason });
            }
        }
    }

    let report = finish(request, &settings, &digest, commit, size, &done, &failed)?;
    write_atomic(&request.out.join(REPORT_JSON), &serde_json::to_vec_pretty(&report).expect("json"))?;
    write_atomic(&request.out.join(REPORT_MD), report::markdown(&report).as_bytes())?;
    if done.is_empty() {
        // A benchmark that scored nothing is a failure, with each scene's reason, not "0/N".
        let reasons: Vec<String> = failed.iter().map(|f| format!("{}: {}", f.scene, f.reason)).collect();
        return Err(Error::InvalidInput {
            path: request.root.clone(),
            what: "scenes".to_string(),
            reason: format!("no scene could be scored ({})", reasons.join("; ")),
        });
    }
    Ok(Outcome { report: Some(report), preempted: false })
}

/// `OUT/results/<scene>.json` of scene `name`, if it was scored. Its names become paths (the
/// scene's work folders, one per camera), so the scene must be `name` and every camera name a
/// plain relative name.
fn read_result(path: &Path, name: &str) -> Result<Option<SceneResult>> {
    let invalid = |what: &str, reason: String| Error::InvalidInput {
        path: path.to_path_buf(),
        what: what.to_string(),
        reason: format!("{reason}; delete it to evaluate the scene again"),
    };
    let result: SceneResult = match std::fs::read_to_string(path) {
        Ok(text) => serde_json::from_str(&text).map_err(|e| invalid("scene result", e.to_string()))?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(error) => return Err(Error::Io { path: path.to_path_buf(), error }),
    };
    if result.scene != name {
        return Err(invalid("scene", format!("`{}` in the result of scene `{name}`", result.scene)));
    }
    for (i, camera) in result.cameras.iter().enumerate() {
        foundation::paths::check_name(&camera.camera)
            .map_err(|reason| invalid(&format!("cameras[{i}].camera"), reason))?;
    }
    Ok(Some(result))
}

fn scene_line(result: &SceneResult) -> report::SceneLine {
    report::SceneLine {
        scene: result.scene.clone(),
        frames: result.frames,
        metrics: result.metrics.clone(),
        render_psnr: result.render_psnr(),
    }
}

/// How one scene ended: scored, or stopped by a preemption signal (run again to continue).
enum SceneOutcome {
    Done(Box<SceneResult>),
    Preempted,
}

/// One scene: prepare its windows, one `nvs` job per window, bring the results to the held-out
/// cameras, score each camera over every window.
fn run_scene(
    request: &Request,
    name: &str,
    size: (u32, u32),
    commit: Option<String>,
    progress: &mut dyn FnMut(Progress),
) -> Result<SceneOutcome> {
    let started = Instant::now();
    let dir = request.root.join(name);
    if !dir.is_dir() {
        return Err(Error::InvalidInput {
            path: dir,
            what: "scene".to_string(),
            reason: "no such scene folder".to_string(),
        });
    }
    let correspondence = match &request.correspondence {
        Some(folder) => {
            let path = folder.join(datagen::api::correspondence_file_name(name));
            if !path.is_file() {
                return Err(Error::InvalidInput {
                    path,
                    what: "correspondence".to_string(),
                    reason: "no correspondence file for the scene".to_string(),
                });
            }
            Some(path)
        }
        None => None,
    };
    let scene = read_scene(&dir, request.layout)?;
    let work = request.out.join(SCENES_DIR).join(name);
    let prepared = scene::prepare(
        &scene,
        &request.split,
        &request.reconstruction,
        request.nvs.framing.frames,
        correspondence.as_deref(),
        &work,
    )?;
    let mut records = Vec::with_capacity(prepared.windows.len());
    for (index, window) in prepared.windows.iter().enumerate() {
        progress(Progress::Window(name, index, prepared.windows.len(), window.window.start));
        let nvs = crate::pipelines::nvs::NvsRequest {
            sequence: window.source.clone(),
            layout: None,
            trajectories: window.trajectories.clone(),
            out: window.dir.join(NVS_DIR),
            settings: request.nvs.clone(),
        };
        let outcome = crate::pipelines::nvs::run(&nvs, request.nvs.load.device, None, &mut |event| {
            progress(Progress::Nvs(event))
        })?;
        if outcome.preempted {
            return Ok(SceneOutcome::Preempted);
        }
        records.push(outcome.record.expect("rank 0 has the record"));
    }
    let (input, held) = scene::cameras(&scene, &request.split)?;
    let mut cameras = Vec::new();
    for camera in held {
        let folders = scene::ViewFolders::create(&work, camera)?;
        let (mut time_ids, mut error) = (Vec::new(), scene::RenderError::default());
        for (window, record) in prepared.windows.iter().zip(&records) {
            let Some(view) = window.views.iter().find(|v| v.camera == camera.id) else { continue };
            let output = record.outputs.iter().find(|o| o.name == view.name).expect("one output per trajectory");
            let nvs_out = window.dir.join(NVS_DIR);
            let sampled =
                crate::eval::metrics::read_frames(&nvs_out.join(output.frames.as_deref().unwrap_or(&view.name)))?;
            let render_dir = nvs_out.join(&output.render);
            let render = crate::eval::metrics::read_frames(&render_dir.join("frames"))?;
            let holes = crate::eval::metrics::read_masks(&render_dir.join("holes"))?;
            let outputs = scene::WindowOutputs {
                source_cameras: &window.source_cameras,
                sampled: &sampled,
                render: &render,
                holes: &holes,
            };
            let written = scene::write_view(&folders, time_ids.len(), view, camera, &outputs, &mut error)?;
            time_ids.extend(written.iter().map(|&(_, j)| camera.time_ids[j]));
        }
        if time_ids.is_empty() {
            continue;
        }
        resize_folder(&folders.pred, size, false)?;
        resize_folder(&folders.target, size, false)?;
        if let Some(mask) = &folders.mask {
            resize_folder(mask, size, true)?;
        }
        let pair = crate::eval::score::Pair::new(
            camera.id.clone(),
            folders.pred.clone(),
            folders.target.clone(),
            folders.mask.clone(),
        );
        let scored = crate::eval::score::run_pairs(&eval_request(request, false), &[pair], |_, _| {})?;
        cameras.push(CameraResult {
            camera: camera.id.clone(),
            time_ids,
            metrics: Metrics::from_row(&scored.videos[0]),
            render_mse: error.mse(),
            render_coverage: error.coverage(),
        });
    }
    if cameras.is_empty() {
        return Err(Error::InvalidInput {
            path: dir,
            what: "held-out frames".to_string(),
            reason: "no held-out camera films an instant of the sampled windows".to_string(),
        });
    }
    let frames = cameras.iter().map(|c| c.time_ids.len()).sum();
    let metrics = Metrics::weighted_mean(cameras.iter().map(|c| (&c.metrics, c.time_ids.len() as f64)));
    let sum = |values: Vec<f64>| (!values.is_empty()).then(|| values.iter().sum());
    let finetune = sum(records.iter().filter_map(|r| r.finetune_seconds).collect());
    let sample = sum(records.iter().flat_map(|r| r.outputs.iter().filter_map(|o| o.sample_seconds)).collect());
    let windows = prepared
        .windows
        .iter()
        .zip(&records)
        .map(|(w, record)| WindowResult {
            start: w.window.start,
            end: w.window.end,
            time_ids: w.window.scored.iter().map(|&i| input.time_ids[i]).collect(),
            checkpoint: record.checkpoint.clone(),
        })
        .collect();
    Ok(SceneOutcome::Done(Box::new(SceneResult {
        scene: name.to_string(),
        input_camera: input.id.clone(),
        windows,
        reconstruction_scale: prepared.scale,
        cameras,
        frames,
        metrics,
        seconds: SceneSeconds { finetune, sample, total: started.elapsed().as_secs_f64() },
        toolkit_commit: commit,
    })))
}

/// The report over the scored scenes: means, pooled FID/KID, the paper's rows, the summary.
fn finish(
    request: &Request,
    settings: &serde_json::Value,
    digest: &str,
    commit: Option<String>,
    size: (u32, u32),
    done: &[SceneResult],
    failed: &[report::FailedScene],
) -> Result<Report> {
    let lines: Vec<report::SceneLine> = done.iter().map(scene_line).collect();
    // Every frame of every scene weighs the same, as the official script pools its frames
    // (`np.mean` over all frames; a scene's metrics are already its frames' mean).
    let mean = Metrics::weighted_mean(lines.iter().map(|l| (&l.metrics, l.frames as f64)));
    let pairs: Vec<crate::eval::score::Pair> = done
        .iter()
        .flat_map(|r| {
            let work = request.out.join(SCENES_DIR).join(&r.scene);
            r.cameras.iter().map(move |c| {
                crate::eval::score::Pair::new(
                    format!("{}/{}", r.scene, c.camera),
                    work.join("pred").join(&c.camera),
                    work.join("target").join(&c.camera),
                    None,
                )
            })
        })
        .collect();
    let frames: usize = done.iter().map(|r| r.frames).sum();
    let (mut fid, mut kid, mut kid_subset_size) = (None, None, None);
    if request.inception.is_some() && frames >= 2 {
        let mut eval = eval_request(request, true);
        eval.kid_subset_size = request.kid_subset_size.min(frames);
        let pooled = crate::eval::score::run_pairs(&eval, &pairs, |_, _| {})?;
        (fid, kid, kid_subset_size) = (pooled.fid, pooled.kid, pooled.kid_subset_size);
    }
    let mut report = Report {
        dataset: request.dataset,
        protocol: match request.dataset.protocol() {
            Protocol::Gcd => "gcd".to_string(),
            Protocol::Dycheck => "dycheck".to_string(),
            Protocol::Dycheck360 => "dycheck360".to_string(),
        },
        eval_size: size,
        protocol_size: size == request.dataset.protocol().size(),
        settings: settings.clone(),
        checkpoint_digest: digest.to_string(),
        toolkit_commit: commit,
        seed: request.nvs.seed,
        scenes: lines,
        failed: failed.to_vec(),
        mean,
        fid,
        kid,
        kid_subset_size,
        paper: report::paper_rows(request.dataset),
        summary: String::new(),
    };
    report.summary = report::summary(&report);
    Ok(report)
}

#[cfg(test)]
mod tests {
    use crate::cli::{Command, benchmark::Asked, parse_from};

    #[test]
    fn settings_json_records_every_nvs_setting_beside_the_benchmarks_own() {
        let flags = ["trainer", "benchmark", "--dataset", "dycheck", "--root", "r", "--init", "c", "--out", "o"];
        let flags = [&flags[..], &["--layout", "dycheck", "--steps", "3", "--fps", "10"]].concat();
        let Command::Benchmark(args) = parse_from(flags).unwrap().command else { panic!("a benchmark") };
        let Asked::Run(request) = args.asked().unwrap() else { panic!("a run") };
        let settings = super::settings(&request, "digest");
        let nvs = serde_json::to_value(request.nvs.record()).unwrap();
        for (key, value) in nvs.as_object().unwrap() {
            assert_eq!(&settings[key], value, "settings.json's {key}");
        }
        assert_eq!(
            (settings["layout"].as_str(), settings["checkpoint_digest"].as_str()),
            (Some("dycheck"), Some("digest"))
        );
        assert_eq!((settings["steps"].as_u64(), settings["fps"].as_f64()), (Some(3), Some(10.0)));
    }
}

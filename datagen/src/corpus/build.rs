//! The resumable corpus build: crawl the configured sources, keep this worker's share
//! of inputs, turn each into clips with an [`InputProcessor`], pack the clips into shards of a
//! target size, and record every input's outcome.
//!
//! Crash safety, by construction:
//! - a shard is written under a temporary name, renamed, and only then gets its stats marker;
//!   an input counts as done once it is listed in a finished shard's stats, or once its latest
//!   attempt is recorded as skipped/failed in a status table (written atomically, each time a
//!   shard finishes and at the end) on files whose content hash is still the same: an input
//!   whose files changed is retried, and `--retry-failed` retries every failed one;
//! - a build holds an OS lock on `build-wXXXXofYYYY.lock` for its whole run ([`lock_output`]),
//!   so a second build of the same folder and worker refuses to start rather than delete the
//!   first one's files; the OS releases it when the process dies;
//! - on start, under that lock, this worker's temporary files, any shard without a stats marker
//!   (a crash between rename and marker) and any stats marker without its shard are removed, and
//!   their inputs are simply redone, as is any input whose status says ok but whose shard is
//!   gone; each repair is listed in [`BuildSummary::repairs`];
//! - shard names carry the worker and a sequence number past every existing one, so workers and
//!   resumed runs never collide and nothing is duplicated;
//! - input keys are unique within a build ([`crawl_all`]), so no input is built twice.

use std::collections::{BTreeMap, BTreeSet};
use std::fs::{File, OpenOptions, TryLockError};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use schemas::{ClipRecord, InputDigest, InputStatus, ShardWriter, ShardWriterOptions, StatusRecord};
use serde::{Deserialize, Serialize};

use super::crawl::{FrameSource, MaskSource, SourceConfig, VideoEntry, crawl_all, sorted_dir};
use super::partition::Worker;
use crate::config_file::{Checked, KeyError, Validate, check_count};
use crate::error::{Error, Result};
use foundation::hashing::{files_under, hash_files};

/// Default shard size target: a few hundred MB, as readers stream row groups anyway.
pub const DEFAULT_SHARD_BYTES: u64 = 256 << 20;

/// Where the build writes and how it packs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputConfig {
    /// Output folder, shared by all workers. Valid: a non-empty path.
    pub dir: PathBuf,
    /// Start a new shard once the current one holds this many bytes (encoded, before compression).
    /// Valid: at least 1.
    #[serde(default = "default_shard_bytes")]
    pub shard_bytes: u64,
    /// Parquet row-group size target in bytes. Valid: at least 1.
    #[serde(default = "default_row_group_bytes")]
    pub row_group_bytes: u64,
}

impl Validate for OutputConfig {
    fn validate(&self) -> Checked {
        if self.dir.as_os_str().is_empty() {
            return Err(KeyError::new("dir", "is empty; name the output folder"));
        }
        check_count("shard_bytes", self.shard_bytes, 1, u64::MAX)?;
        check_count("row_group_bytes", self.row_group_bytes, 1, usize::MAX as u64)
    }
}

fn default_shard_bytes() -> u64 {
    DEFAULT_SHARD_BYTES
}

fn default_row_group_bytes() -> u64 {
    schemas::shard::DEFAULT_ROW_GROUP_BYTES as u64
}

/// A corpus build as configured in TOML (`datagen build --config`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BuildConfig {
    /// Dataset trees to crawl.
    pub sources: Vec<SourceConfig>,
    /// Output folder and packing.
    pub output: OutputConfig,
    /// Seed of every random choice (combined with stable ids).
    #[serde(default)]
    pub seed: u64,
    /// Sampled trajectories per clip (the paper's pretraining N = 2). Valid: 1 to
    /// [`crate::pairs::generator::MAX_TRAJECTORIES`].
    #[serde(default = "default_trajectories")]
    pub trajectories: u32,
    /// Clip windows, trajectory ranges, occlusion test (every field checked at load).
    #[serde(default)]
    pub pairs: crate::pairs::generator::PairsConfig,
    /// The reconstruction filter: inputs below a static depth consistency are skipped.
    #[serde(default)]
    pub check: super::quality::BuildCheckConfig,
    /// The layout of every input's folder, named instead of detected (`datagen build --layout`
    /// overrides it): a single-camera name for sequence folders and reconstructions, a
    /// multi-camera name for scene folders (`generic` names both); inputs of the other kind keep
    /// detection. Unset: every layout detected from its files.
    #[serde(default)]
    pub layout: Option<crate::io::layout::LayoutName>,
}

fn default_trajectories() -> u32 {
    crate::pairs::generator::PAPER_TRAJECTORIES
}

impl BuildConfig {
    /// Reads a corpus TOML and checks every field ([`Validate`]); errors name the file and the
    /// key (`pairs.trajectory.azimuth_deg`, `sources[1].root`) on their first line.
    pub fn from_toml_file(path: &Path) -> Result<Self> {
        crate::config_file::load_toml(path)
    }
}

impl Validate for BuildConfig {
    fn validate(&self) -> Checked {
        if self.sources.is_empty() {
            return Err(KeyError::new("sources", "at least one [[sources]] table is needed"));
        }
        for (i, source) in self.sources.iter().enumerate() {
            source.validate().map_err(|e| e.under(&format!("sources[{i}]")))?;
        }
        self.output.validate().map_err(|e| e.under("output"))?;
        check_count("trajectories", self.trajectories, 1, crate::pairs::generator::MAX_TRAJECTORIES.into())?;
        self.pairs.validate().map_err(|e| e.under("pairs"))?;
        self.check.validate().map_err(|e| e.under("check"))
    }
}

/// What happened to one input.
#[derive(Debug)]
pub enum Outcome {
    /// Clips to write.
    Clips(Vec<ClipRecord>),
    /// Deliberately not processed, with the reason.
    Skipped(String),
}

/// Turns one input into clips. Implementations must be deterministic given the input, so a
/// resumed run writes the same pairs as an uninterrupted one.
pub trait InputProcessor: Sync {
    /// Processes `entry`; an error marks the input failed with the error's message.
    fn process(&self, entry: &VideoEntry) -> Result<Outcome>;
}

/// Counts of a finished (or dry) run.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct BuildSummary {
    /// Inputs listed by the crawl, all workers.
    pub inputs_total: u64,
    /// Inputs owned by this worker.
    pub inputs_owned: u64,
    /// Owned inputs already done before this run (resume).
    pub inputs_already_done: u64,
    /// Inputs processed ok in this run.
    pub ok: u64,
    /// Inputs skipped in this run.
    pub skipped: u64,
    /// Inputs failed in this run.
    pub failed: u64,
    /// Clips written in this run.
    pub clips: u64,
    /// Pairs written in this run.
    pub pairs: u64,
    /// Shards finished in this run.
    pub shards: u64,
    /// Bytes of shards finished in this run.
    pub bytes: u64,
    /// Wall time of this run in seconds.
    pub seconds: f64,
    /// Of which hashing inputs' content (for the status table and stats markers).
    pub hash_seconds: f64,
    /// Of which processing inputs (decode, reconstruction, pairs).
    pub process_seconds: f64,
    /// Of which writing shards, stats markers and status tables.
    pub write_seconds: f64,
    /// Leftovers of interrupted runs found on start and what was done about each (temporary
    /// files, unmarked shards and stats markers without a shard removed; inputs whose status
    /// says ok but whose shard is gone rebuilt), and other workers' leftovers, reported.
    #[serde(default)]
    pub repairs: Vec<String>,
}

/// Progress callback events, for a progress bar.
#[derive(Debug, Clone, Copy)]
pub enum Progress {
    /// The number of inputs this run will process.
    Start {
        /// Inputs left to do.
        pending: u64,
    },
    /// One input finished.
    Input {
        /// Its outcome.
        status: InputStatus,
        /// Pairs it produced.
        pairs: u64,
    },
}

/// How a build treats the outcomes of earlier runs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BuildOptions {
    /// Retry every input whose latest attempt failed even if its files are unchanged
    /// (`datagen build --retry-failed`: after fixing the code or freeing memory). A failed or
    /// skipped input whose files changed since (its content hash differs) is retried anyway.
    pub retry_failed: bool,
}

/// File name prefix of this worker's shards and status tables.
fn worker_prefix(worker: Worker) -> String {
    format!("w{:04}of{:04}", worker.index, worker.count)
}

/// Whether `name` (a shard, marker, status table, manifest or their temporary files) belongs to
/// `worker`: its prefix delimited on both sides, so `w0001of1000` never matches `w0001of10000`.
fn is_mine(name: &str, worker: Worker) -> bool {
    let prefix = worker_prefix(worker);
    name.contains(&format!("-{prefix}-")) || name.contains(&format!("-{prefix}."))
}

fn shard_name(worker: Worker, sequence: u64) -> String {
    format!("shard-{}-{sequence:06}.parquet", worker_prefix(worker))
}

fn status_dir(out: &Path) -> PathBuf {
    out.join("status")
}

/// File name of the lock a build of `worker` holds on its output folder for the whole run.
fn lock_name(worker: Worker) -> String {
    format!("build-{}.lock", worker_prefix(worker))
}

/// An exclusive OS advisory lock (`flock`) on `<out>/build-wXXXXofYYYY.lock`, held for a build's
/// whole run: a second `datagen build` for the same output folder and worker refuses to start
/// instead of deleting the first one's temporary files and overwriting its status tables. The OS
/// drops it when the process ends however it ends, so a crash or `kill -9` leaves no stale lock.
#[derive(Debug)]
pub struct BuildLock {
    _file: File,
}

/// Takes the build lock of `worker` on the folder `out` (which must exist), or fails naming the
/// lock file and the process holding it. Also refuses while a build with another worker count
/// holds its lock on `out`: partitions of different counts overlap, so both would build (and
/// write twice) the same inputs.
pub fn lock_output(out: &Path, worker: Worker) -> Result<BuildLock> {
    let path = out.join(lock_name(worker));
    let file = OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .map_err(|e| Error::io(&path, e))?;
    match file.try_lock() {
        Ok(()) => {}
        Err(TryLockError::WouldBlock) => {
            return Err(busy(&path, format!("is writing worker {}/{} into this folder", worker.index, worker.count)));
        }
        Err(TryLockError::Error(e)) => return Err(Error::io(&path, e)),
    }
    for entry in std::fs::read_dir(out).map_err(|e| Error::io(out, e))?.filter_map(|e| e.ok()) {
        let name = entry.file_name().to_string_lossy().into_owned();
        let count = name.strip_prefix("build-w").and_then(|r| r.strip_suffix(".lock")).and_then(|r| r.split_once("of"));
        let Some(count) = count.and_then(|(_, count)| count.parse::<u32>().ok()) else { continue };
        if count == worker.count {
            continue; // Another index of the same partition: disjoint inputs, meant to run together.
        }
        let other = entry.path();
        let Ok(handle) = File::open(&other) else { continue };
        if let Err(TryLockError::WouldBlock) = handle.try_lock() {
            return Err(busy(
                &other,
                format!(
                    "builds with --num-workers {count}, whose partition overlaps this run's --num-workers {}",
                    worker.count
                ),
            ));
        }
        // Dropping `handle` closes it, which releases the probe's lock.
    }
    // Say who holds the lock, for the message a second process prints.
    let mut writer = &file;
    writer
        .set_len(0)
        .and_then(|()| writer.write_all(format!("pid {}\n", std::process::id()).as_bytes()))
        .map_err(|e| Error::io(&path, e))?;
    Ok(BuildLock { _file: file })
}

fn busy(lock: &Path, doing: String) -> Error {
    let holder = std::fs::read_to_string(lock).ok().map(|t| t.trim().to_owned()).filter(|t| !t.is_empty());
    let holder = holder.map(|h| format!(" ({h})")).unwrap_or_default();
    Error::io(
        lock,
        std::io::Error::new(
            std::io::ErrorKind::WouldBlock,
            format!(
                "another `datagen build`{holder} {doing}; wait for it to finish (a crashed build releases \
                 the lock by itself), or build into another --out"
            ),
        ),
    )
}

/// What an output folder already holds: keys done in finished shards (any worker), the latest
/// status row per key, this worker's next free shard and status numbers, and what recovery
/// repaired or found.
#[derive(Default)]
struct ExistingState {
    in_shards: BTreeSet<String>,
    latest: BTreeMap<String, StatusRecord>,
    next_sequence: u64,
    next_status: u64,
    repairs: Vec<String>,
}

fn is_temp(name: &str) -> bool {
    name.contains(schemas::shard::TEMP_MARKER)
}

/// Reads what `out` holds. With `repair` (under this worker's lock only), removes this worker's
/// leftovers of an interrupted run: temporary files, shards renamed but never marked, and stats
/// markers whose shard is gone (their inputs are then simply rebuilt). Other workers' leftovers
/// are reported, never touched: that worker may be running.
fn read_state(out: &Path, worker: Worker, repair: bool) -> Result<ExistingState> {
    let mut state = ExistingState::default();
    if !out.is_dir() {
        return Ok(state);
    }
    let prefix = format!("shard-{}-", worker_prefix(worker));
    let remove = |path: &Path, note: String, state: &mut ExistingState| -> Result<()> {
        std::fs::remove_file(path).map_err(|e| Error::io(path, e))?;
        state.repairs.push(note);
        Ok(())
    };
    // A temporary file is this run's to remove only when this worker wrote it.
    let remove_temp = |path: &Path, name: &str, state: &mut ExistingState| -> Result<()> {
        if repair && is_mine(name, worker) {
            remove(path, format!("removed {}, a temporary file of an interrupted run", path.display()), state)?;
        }
        Ok(())
    };
    for path in sorted_dir(out)? {
        let name = path.file_name().unwrap_or_default().to_string_lossy().into_owned();
        if is_temp(&name) {
            remove_temp(&path, &name, &mut state)?;
            continue;
        }
        if let Some(shard) = name.strip_suffix(schemas::shard::STATS_SUFFIX) {
            if shard.starts_with("shard-") && !out.join(shard).is_file() {
                if repair && shard.starts_with(&prefix) {
                    let note = format!(
                        "removed {}, a stats marker whose shard is gone; its inputs are rebuilt",
                        path.display()
                    );
                    remove(&path, note, &mut state)?;
                } else {
                    state
                        .repairs
                        .push(format!("{}: stats marker whose shard is gone (left to its worker)", path.display()));
                }
            }
            continue;
        }
        if !name.ends_with(".parquet") || !name.starts_with("shard-") {
            continue;
        }
        let mine = name.starts_with(&prefix);
        if mine {
            let sequence = name.trim_start_matches(&prefix).trim_end_matches(".parquet").parse::<u64>().unwrap_or(0);
            state.next_sequence = state.next_sequence.max(sequence + 1);
        }
        if schemas::is_finished(&path) {
            state.in_shards.extend(schemas::read_stats(&path)?.inputs.into_iter().map(|i| i.source_path));
        } else if repair && mine {
            let note = format!("removed {}, a shard never marked finished; its inputs are rebuilt", path.display());
            remove(&path, note, &mut state)?;
        }
    }
    let status = status_dir(out);
    if status.is_dir() {
        let status_prefix = format!("status-{}-", worker_prefix(worker));
        for path in sorted_dir(&status)? {
            let name = path.file_name().unwrap_or_default().to_string_lossy().into_owned();
            if is_temp(&name) {
                remove_temp(&path, &name, &mut state)?;
            } else if let Some(rest) = name.strip_prefix(&status_prefix) {
                let number = rest.trim_end_matches(".parquet").parse::<u64>().unwrap_or(0);
                state.next_status = state.next_status.max(number + 1);
            }
        }
        state.latest = read_corpus_status(out)?;
    }
    Ok(state)
}

/// What a run does with one owned input, given what the folder holds.
enum Decision {
    /// In a finished shard, or its latest attempt failed or skipped on these very files.
    Done,
    /// To process; `hash` if already computed, `plan` saying why (for dry runs).
    Todo { hash: Option<String>, plan: &'static str, note: Option<String> },
}

/// Decides one input: done if a finished shard lists it; rebuilt if its status says ok but that
/// shard is gone; retried if its latest attempt failed or was skipped and its content hash has
/// changed since (or it failed and `retry_failed`); processed if never attempted.
fn decide(state: &ExistingState, entry: &VideoEntry, options: BuildOptions) -> Decision {
    let key = entry.key();
    if state.in_shards.contains(&key) {
        return Decision::Done;
    }
    let Some(latest) = state.latest.get(&key) else {
        return Decision::Todo { hash: None, plan: "build", note: None };
    };
    if latest.status == InputStatus::Ok {
        let note = format!("`{key}`: status says ok in {}, which is gone or unfinished; rebuilding it", latest.shard);
        return Decision::Todo { hash: None, plan: "redo: shard lost", note: Some(note) };
    }
    if options.retry_failed && latest.status == InputStatus::Failed {
        return Decision::Todo { hash: None, plan: "retry: --retry-failed", note: None };
    }
    let hash = content_hash(entry).unwrap_or_default();
    if hash == latest.content_hash {
        Decision::Done
    } else {
        Decision::Todo { hash: Some(hash), plan: "retry: inputs changed", note: None }
    }
}

/// BLAKE3 over an input's files (frames or video, annotations, reconstruction, and shared files
/// such as a TAO split's JSON), in a stable order.
pub fn content_hash(entry: &VideoEntry) -> Result<String> {
    let mut files: Vec<PathBuf> = Vec::new();
    match &entry.frames {
        FrameSource::Video(path) => files.push(path.clone()),
        FrameSource::Images(paths) => files.extend(paths.iter().cloned()),
        FrameSource::Sequence(dir) | FrameSource::MultiView(dir) => files_under(dir, &mut files)?,
    }
    match &entry.masks {
        MaskSource::Sav(path) => files.push(path.clone()),
        MaskSource::IdPngs(dir) => files_under(dir, &mut files)?,
        MaskSource::None | MaskSource::Boxes { .. } => {}
    }
    if let Some(reconstruction) = &entry.reconstruction {
        files_under(reconstruction, &mut files)?;
    }
    // A missing shared file (a split list not there yet) changes the hash by appearing, rather
    // than making it unreadable.
    files.extend(entry.shared_files.iter().filter(|p| p.is_file()).cloned());
    Ok(hash_files(files)?)
}

/// One input's planned fate in a dry run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PlannedInput {
    /// Its key.
    pub key: String,
    /// `done` (resume), `build`, `retry: ...`, `redo: shard lost`, `skip: no reconstruction`, or
    /// `fail: ...` (a shared annotation file it depends on is malformed).
    pub plan: &'static str,
}

/// Lists this worker's inputs and what a build with `options` would do with each, writing nothing.
pub fn plan(sources: &[SourceConfig], out: &Path, worker: Worker, options: BuildOptions) -> Result<Vec<PlannedInput>> {
    let state = read_state(out, worker, false)?;
    let mut planned = Vec::new();
    for entry in crawl_all(sources)?.into_iter().filter(|e| worker.owns(&e.key())) {
        let plan = match decide(&state, &entry, options) {
            Decision::Done => "done",
            Decision::Todo { .. } if entry.crawl_error.is_some() => "fail: a shared annotation file is malformed",
            Decision::Todo { .. } if entry.reconstruction.is_none() => "skip: no reconstruction",
            Decision::Todo { plan, .. } => plan,
        };
        planned.push(PlannedInput { key: entry.key(), plan });
    }
    Ok(planned)
}

/// The shard being filled and the inputs whose clips it holds.
struct OpenShard {
    writer: ShardWriter,
    name: String,
    bytes: u64,
    inputs: Vec<StatusRecord>,
}

/// Runs (or resumes) the build of `sources` into `output.dir` for `worker`, with the default
/// [`BuildOptions`].
pub fn build(
    sources: &[SourceConfig],
    output: &OutputConfig,
    worker: Worker,
    processor: &dyn InputProcessor,
    progress: impl FnMut(Progress),
) -> Result<BuildSummary> {
    build_with_options(sources, output, worker, BuildOptions::default(), processor, progress)
}

/// Runs (or resumes) the build of `sources` into `output.dir` for `worker`. Fails before
/// writing anything if two inputs share a key, or if another build holds this worker's lock.
pub fn build_with_options(
    sources: &[SourceConfig],
    output: &OutputConfig,
    worker: Worker,
    options: BuildOptions,
    processor: &dyn InputProcessor,
    mut progress: impl FnMut(Progress),
) -> Result<BuildSummary> {
    let started = Instant::now();
    let out = &output.dir;
    let entries = crawl_all(sources)?;
    std::fs::create_dir_all(status_dir(out)).map_err(|e| Error::io(status_dir(out), e))?;
    let _lock = lock_output(out, worker)?;
    let mut state = read_state(out, worker, true)?;

    let mut summary = BuildSummary { repairs: std::mem::take(&mut state.repairs), ..BuildSummary::default() };
    let mut pending = Vec::new();
    for entry in entries {
        summary.inputs_total += 1;
        if !worker.owns(&entry.key()) {
            continue;
        }
        summary.inputs_owned += 1;
        let hash_started = Instant::now();
        let decision = decide(&state, &entry, options);
        summary.hash_seconds += hash_started.elapsed().as_secs_f64();
        match decision {
            Decision::Done => summary.inputs_already_done += 1,
            Decision::Todo { hash, note, .. } => {
                summary.repairs.extend(note);
                pending.push((entry, hash));
            }
        }
    }
    progress(Progress::Start { pending: pending.len() as u64 });

    let options = ShardWriterOptions { row_group_bytes: output.row_group_bytes as usize };
    let mut open: Option<OpenShard> = None;
    let mut unflushed: Vec<StatusRecord> = Vec::new();
    let record = |entry: &VideoEntry, status: InputStatus, reason: String, hash: String, seconds: f64| StatusRecord {
        input_key: entry.key(),
        status,
        reason,
        clips: 0,
        pairs: 0,
        shard: String::new(),
        content_hash: hash,
        seconds,
        worker_index: worker.index,
        worker_count: worker.count,
    };

    for (entry, hash) in &pending {
        let input_started = Instant::now();
        let hash = match hash {
            Some(hash) => hash.clone(),
            None => content_hash(entry).unwrap_or_default(),
        };
        summary.hash_seconds += input_started.elapsed().as_secs_f64();
        let process_started = Instant::now();
        let outcome = if let Some(reason) = &entry.crawl_error {
            Err(reason.clone())
        } else if entry.reconstruction.is_none() {
            Ok(Outcome::Skipped("no reconstruction found for this video".to_owned()))
        } else {
            processor.process(entry).map_err(|error| error.to_string())
        };
        summary.process_seconds += process_started.elapsed().as_secs_f64();
        let seconds = input_started.elapsed().as_secs_f64();
        let write_started = Instant::now();
        match outcome {
            Ok(Outcome::Clips(clips)) => {
                if open.is_none() {
                    let name = shard_name(worker, state.next_sequence);
                    state.next_sequence += 1;
                    let writer = ShardWriter::create(&out.join(&name), options.clone())?;
                    open = Some(OpenShard { writer, name, bytes: 0, inputs: Vec::new() });
                }
                let shard = open.as_mut().expect("opened above");
                let mut status = record(entry, InputStatus::Ok, String::new(), hash.clone(), seconds);
                status.shard = shard.name.clone();
                for clip in &clips {
                    shard.writer.write(clip)?;
                    shard.bytes += clip_bytes(clip);
                    status.clips += 1;
                    status.pairs += clip.trajectories.len() as u32;
                }
                shard.writer.add_input(InputDigest { source_path: entry.key(), content_hash: hash });
                progress(Progress::Input { status: InputStatus::Ok, pairs: u64::from(status.pairs) });
                summary.ok += 1;
                summary.clips += u64::from(status.clips);
                summary.pairs += u64::from(status.pairs);
                shard.inputs.push(status);
                if shard.bytes >= output.shard_bytes {
                    let shard = open.take().expect("open");
                    finish_shard(out, worker, shard, &mut unflushed, &mut state, &mut summary)?;
                }
            }
            Ok(Outcome::Skipped(reason)) => {
                progress(Progress::Input { status: InputStatus::Skipped, pairs: 0 });
                summary.skipped += 1;
                unflushed.push(record(entry, InputStatus::Skipped, reason, hash, seconds));
            }
            Err(reason) => {
                progress(Progress::Input { status: InputStatus::Failed, pairs: 0 });
                summary.failed += 1;
                unflushed.push(record(entry, InputStatus::Failed, reason, hash, seconds));
            }
        }
        summary.write_seconds += write_started.elapsed().as_secs_f64();
    }
    let write_started = Instant::now();
    if let Some(shard) = open.take() {
        finish_shard(out, worker, shard, &mut unflushed, &mut state, &mut summary)?;
    }
    if !unflushed.is_empty() {
        write_status(out, worker, &mut state, &unflushed)?;
    }
    summary.write_seconds += write_started.elapsed().as_secs_f64();
    summary.seconds = started.elapsed().as_secs_f64();
    let manifest = serde_json::json!({
        "tool_version": format!("datagen {}", env!("CARGO_PKG_VERSION")),
        "worker": {"index": worker.index, "count": worker.count},
        "sources": sources,
        "output": output,
        "summary": summary,
    });
    let manifest_path = out.join(format!("manifest-{}.json", worker_prefix(worker)));
    schemas::write_atomic(&manifest_path, &serde_json::to_vec_pretty(&manifest).expect("json"))?;
    Ok(summary)
}

/// Encoded size of a clip's byte columns (what the shard-size target counts).
fn clip_bytes(clip: &ClipRecord) -> u64 {
    let lists = [&clip.frames, &clip.depth];
    let mut bytes: u64 = lists.iter().flat_map(|l| l.iter()).map(|b| b.len() as u64).sum();
    bytes += clip.dynamic_mask.iter().flatten().map(|b| b.len() as u64).sum::<u64>();
    for trajectory in &clip.trajectories {
        bytes += trajectory.covisible_mask.iter().map(|b| b.len() as u64).sum::<u64>();
        bytes += trajectory.condition.iter().flatten().map(|b| b.len() as u64).sum::<u64>();
    }
    bytes
}

fn finish_shard(
    out: &Path,
    worker: Worker,
    shard: OpenShard,
    unflushed: &mut Vec<StatusRecord>,
    state: &mut ExistingState,
    summary: &mut BuildSummary,
) -> Result<()> {
    let stats = shard.writer.finish()?;
    summary.shards += 1;
    summary.bytes += stats.bytes;
    let mut records = shard.inputs;
    records.append(unflushed);
    write_status(out, worker, state, &records)
}

fn write_status(out: &Path, worker: Worker, state: &mut ExistingState, records: &[StatusRecord]) -> Result<()> {
    let path = status_dir(out).join(format!("status-{}-{:06}.parquet", worker_prefix(worker), state.next_status));
    state.next_status += 1;
    Ok(schemas::write_status_table(&path, records)?)
}

/// Every status row of a corpus folder (all workers), latest attempt per input. Tables are read
/// oldest first (by modification time, then name: a worker's numbers count up), so a retry's
/// row replaces the attempt before it, whichever worker count wrote either.
pub fn read_corpus_status(out: &Path) -> Result<BTreeMap<String, StatusRecord>> {
    let status = status_dir(out);
    let mut files: Vec<(std::time::SystemTime, PathBuf)> = Vec::new();
    for path in sorted_dir(&status)? {
        let name = path.file_name().unwrap_or_default().to_string_lossy().into_owned();
        if name.ends_with(".parquet") && !is_temp(&name) {
            let modified = std::fs::metadata(&path).and_then(|m| m.modified()).map_err(|e| Error::io(&path, e))?;
            files.push((modified, path));
        }
    }
    files.sort();
    let mut latest = BTreeMap::new();
    for (_, file) in files {
        for record in schemas::read_status_table(&file)? {
            latest.insert(record.input_key.clone(), record);
        }
    }
    Ok(latest)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_example_corpus_config_parses() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/corpus_example.toml");
        let config = BuildConfig::from_toml_file(&path).unwrap();
        assert_eq!(config.sources.len(), 5);
        assert_eq!(config.sources[4].dataset, super::super::crawl::DatasetKind::Multiview);
        assert_eq!(config.pairs.multiview.min_covisible_fraction, 0.1);
        assert!(!config.pairs.depth_noise.enabled);
        assert_eq!(config.pairs.depth_noise.correlation_px, 8);
    }
}

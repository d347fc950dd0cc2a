//! The resumable corpus build (DESIGN §5): crawl the configured sources, keep this worker's share
//! of inputs, turn each into clips with an [`InputProcessor`], pack the clips into shards of a
//! target size, and record every input's outcome.
//!
//! Crash safety, by construction:
//! - a shard is written under a temporary name, renamed, and only then gets its stats marker;
//!   an input counts as done once it is listed in a finished shard's stats, or recorded as
//!   skipped/failed in a status table (written atomically, each time a shard finishes and at the
//!   end);
//! - on start, this worker's temporary files and any shard without a stats marker (a crash
//!   between rename and marker) are removed, and their inputs are simply redone;
//! - shard names carry the worker and a sequence number past every existing one, so workers and
//!   resumed runs never collide and nothing is duplicated.

use std::collections::{BTreeMap, BTreeSet};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

use schemas::{ClipRecord, InputDigest, InputStatus, ShardWriter, ShardWriterOptions, StatusRecord};
use serde::{Deserialize, Serialize};

use super::crawl::{FrameSource, MaskSource, SourceConfig, VideoEntry, crawl};
use super::partition::Worker;
use crate::error::{Error, Result};

/// Default shard size target: a few hundred MB, as readers stream row groups anyway.
pub const DEFAULT_SHARD_BYTES: u64 = 256 << 20;

/// Where the build writes and how it packs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputConfig {
    /// Output folder, shared by all workers.
    pub dir: PathBuf,
    /// Start a new shard once the current one holds this many bytes (encoded, before compression).
    #[serde(default = "default_shard_bytes")]
    pub shard_bytes: u64,
    /// Parquet row-group size target in bytes.
    #[serde(default = "default_row_group_bytes")]
    pub row_group_bytes: u64,
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
    /// Sampled trajectories per clip (the paper's pretraining N = 2).
    #[serde(default = "default_trajectories")]
    pub trajectories: u32,
    /// Clip windows, trajectory ranges, occlusion test.
    #[serde(default)]
    pub pairs: crate::pairs::PairsConfig,
}

fn default_trajectories() -> u32 {
    crate::pairs::PAPER_TRAJECTORIES
}

impl BuildConfig {
    /// Reads a corpus TOML, naming the file and field on error.
    pub fn from_toml_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let config: Self = toml::from_str(&text).map_err(|e| Error::invalid(path, "config", e.to_string()))?;
        if config.sources.is_empty() {
            return Err(Error::invalid(path, "sources", "at least one [[sources]] table is needed"));
        }
        if config.trajectories == 0 {
            return Err(Error::invalid(path, "trajectories", "must be at least 1"));
        }
        config.pairs.validate(path)?;
        Ok(config)
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

/// File name prefix of this worker's shards and status tables.
fn worker_prefix(worker: Worker) -> String {
    format!("w{:04}of{:04}", worker.index, worker.count)
}

fn shard_name(worker: Worker, sequence: u64) -> String {
    format!("shard-{}-{sequence:06}.parquet", worker_prefix(worker))
}

fn status_dir(out: &Path) -> PathBuf {
    out.join("status")
}

/// Inputs already accounted for in `out` (by any worker): done keys from finished shards' stats
/// and from status tables, and the next free shard sequence number of `worker`.
struct ExistingState {
    done: BTreeSet<String>,
    next_sequence: u64,
    next_status: u64,
}

fn is_temp(name: &str) -> bool {
    name.contains(schemas::shard::TEMP_MARKER)
}

/// Removes this worker's temporary files and unfinished shards, then reads what is done.
fn recover(out: &Path, worker: Worker) -> Result<ExistingState> {
    let prefix = format!("shard-{}-", worker_prefix(worker));
    let mut done = BTreeSet::new();
    let mut next_sequence = 0;
    let entries = std::fs::read_dir(out).map_err(|e| Error::io(out, e))?;
    for entry in entries.filter_map(|e| e.ok()) {
        let path = entry.path();
        let name = entry.file_name().to_string_lossy().into_owned();
        let mine = name.trim_start_matches('.').starts_with(&prefix);
        if mine && is_temp(&name) {
            std::fs::remove_file(&path).map_err(|e| Error::io(&path, e))?;
            continue;
        }
        if !name.ends_with(".parquet") || !name.starts_with("shard-") {
            continue;
        }
        if mine {
            let sequence = name.trim_start_matches(&prefix).trim_end_matches(".parquet").parse::<u64>().unwrap_or(0);
            next_sequence = next_sequence.max(sequence + 1);
        }
        if schemas::is_finished(&path) {
            done.extend(schemas::read_stats(&path)?.inputs.into_iter().map(|i| i.source_path));
        } else if mine {
            // Renamed but never marked: its inputs are redone into a new shard.
            std::fs::remove_file(&path).map_err(|e| Error::io(&path, e))?;
        }
    }
    let status = status_dir(out);
    let mut next_status = 0;
    if status.is_dir() {
        let status_prefix = format!("status-{}-", worker_prefix(worker));
        for entry in std::fs::read_dir(&status).map_err(|e| Error::io(&status, e))?.filter_map(|e| e.ok()) {
            let path = entry.path();
            let name = entry.file_name().to_string_lossy().into_owned();
            if is_temp(&name) {
                if name.trim_start_matches('.').starts_with(&status_prefix) {
                    std::fs::remove_file(&path).map_err(|e| Error::io(&path, e))?;
                }
                continue;
            }
            if let Some(rest) = name.strip_prefix(&status_prefix) {
                let number = rest.trim_end_matches(".parquet").parse::<u64>().unwrap_or(0);
                next_status = next_status.max(number + 1);
            }
            if name.ends_with(".parquet") {
                for record in schemas::read_status_table(&path)? {
                    if record.status != InputStatus::Ok {
                        done.insert(record.input_key);
                    }
                }
            }
        }
    }
    Ok(ExistingState { done, next_sequence, next_status })
}

/// BLAKE3 over an input's files (frames or video, annotations, reconstruction), in a stable order.
pub fn content_hash(entry: &VideoEntry) -> Result<String> {
    let mut files: Vec<PathBuf> = Vec::new();
    match &entry.frames {
        FrameSource::Video(path) => files.push(path.clone()),
        FrameSource::Images(paths) => files.extend(paths.iter().cloned()),
        FrameSource::Sequence(dir) => files_under(dir, &mut files)?,
    }
    match &entry.masks {
        MaskSource::Sav(path) => files.push(path.clone()),
        MaskSource::IdPngs(dir) => files_under(dir, &mut files)?,
        MaskSource::None | MaskSource::Boxes { .. } => {}
    }
    if let Some(reconstruction) = &entry.reconstruction {
        files_under(reconstruction, &mut files)?;
    }
    hash_files(files)
}

/// BLAKE3 over every file under `root` (or the file `root`), in a stable order.
pub fn hash_tree(root: &Path) -> Result<String> {
    let mut files = Vec::new();
    files_under(root, &mut files)?;
    hash_files(files)
}

fn files_under(root: &Path, files: &mut Vec<PathBuf>) -> Result<()> {
    let mut pending = vec![root.to_owned()];
    while let Some(path) = pending.pop() {
        if path.is_dir() {
            let entries = std::fs::read_dir(&path).map_err(|e| Error::io(&path, e))?;
            pending.extend(entries.filter_map(|e| e.ok().map(|e| e.path())));
        } else {
            files.push(path);
        }
    }
    Ok(())
}

fn hash_files(mut files: Vec<PathBuf>) -> Result<String> {
    files.sort();
    files.dedup();
    let mut hasher = blake3::Hasher::new();
    let mut buffer = vec![0u8; 1 << 20];
    for path in files {
        hasher.update(path.file_name().unwrap_or_default().as_encoded_bytes());
        let mut file = std::fs::File::open(&path).map_err(|e| Error::io(&path, e))?;
        loop {
            let read = file.read(&mut buffer).map_err(|e| Error::io(&path, e))?;
            if read == 0 {
                break;
            }
            hasher.update(&buffer[..read]);
        }
    }
    Ok(hasher.finalize().to_hex().to_string())
}

/// One input's planned fate in a dry run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PlannedInput {
    /// Its key.
    pub key: String,
    /// Already done (resume), to be processed, or to be skipped for lack of a reconstruction.
    pub plan: &'static str,
}

/// Lists this worker's inputs and what a build would do with each, writing nothing.
pub fn plan(sources: &[SourceConfig], out: &Path, worker: Worker) -> Result<Vec<PlannedInput>> {
    let done = if out.is_dir() { read_done(out)? } else { BTreeSet::new() };
    let mut planned = Vec::new();
    for source in sources {
        for entry in crawl(source)?.into_iter().filter(|e| worker.owns(&e.key())) {
            let plan = if done.contains(&entry.key()) {
                "done"
            } else if entry.reconstruction.is_none() {
                "skip: no reconstruction"
            } else {
                "build"
            };
            planned.push(PlannedInput { key: entry.key(), plan });
        }
    }
    Ok(planned)
}

/// Done keys without touching anything (for dry runs and inspection).
fn read_done(out: &Path) -> Result<BTreeSet<String>> {
    let mut done = BTreeSet::new();
    for entry in std::fs::read_dir(out).map_err(|e| Error::io(out, e))?.filter_map(|e| e.ok()) {
        let path = entry.path();
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with("shard-") && name.ends_with(".parquet") && schemas::is_finished(&path) {
            done.extend(schemas::read_stats(&path)?.inputs.into_iter().map(|i| i.source_path));
        }
    }
    let status = status_dir(out);
    if status.is_dir() {
        for entry in std::fs::read_dir(&status).map_err(|e| Error::io(&status, e))?.filter_map(|e| e.ok()) {
            let name = entry.file_name().to_string_lossy().into_owned();
            if name.ends_with(".parquet") && !is_temp(&name) {
                done.extend(
                    schemas::read_status_table(&entry.path())?
                        .into_iter()
                        .filter(|r| r.status != InputStatus::Ok)
                        .map(|r| r.input_key),
                );
            }
        }
    }
    Ok(done)
}

/// The shard being filled and the inputs whose clips it holds.
struct OpenShard {
    writer: ShardWriter,
    name: String,
    bytes: u64,
    inputs: Vec<StatusRecord>,
}

/// Runs (or resumes) the build of `sources` into `output.dir` for `worker`.
pub fn build(
    sources: &[SourceConfig],
    output: &OutputConfig,
    worker: Worker,
    processor: &dyn InputProcessor,
    mut progress: impl FnMut(Progress),
) -> Result<BuildSummary> {
    let started = Instant::now();
    let out = &output.dir;
    std::fs::create_dir_all(status_dir(out)).map_err(|e| Error::io(status_dir(out), e))?;
    let mut state = recover(out, worker)?;

    let mut summary = BuildSummary::default();
    let mut pending = Vec::new();
    for source in sources {
        for entry in crawl(source)? {
            summary.inputs_total += 1;
            if !worker.owns(&entry.key()) {
                continue;
            }
            summary.inputs_owned += 1;
            if state.done.contains(&entry.key()) {
                summary.inputs_already_done += 1;
            } else {
                pending.push(entry);
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

    for entry in &pending {
        let input_started = Instant::now();
        let hash = content_hash(entry).unwrap_or_default();
        summary.hash_seconds += input_started.elapsed().as_secs_f64();
        let process_started = Instant::now();
        let outcome = if entry.reconstruction.is_none() {
            Ok(Outcome::Skipped("no reconstruction found for this video".to_owned()))
        } else {
            processor.process(entry)
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
            Err(error) => {
                progress(Progress::Input { status: InputStatus::Failed, pairs: 0 });
                summary.failed += 1;
                unflushed.push(record(entry, InputStatus::Failed, error.to_string(), hash, seconds));
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

/// Every status row of a corpus folder (all workers), latest attempt per input.
pub fn read_corpus_status(out: &Path) -> Result<BTreeMap<String, StatusRecord>> {
    let status = status_dir(out);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&status)
        .map_err(|e| Error::io(&status, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "parquet") && !is_temp(&p.to_string_lossy()))
        .collect();
    files.sort();
    let mut latest = BTreeMap::new();
    for file in files {
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
        assert_eq!(config.sources.len(), 4);
        assert!(!config.pairs.depth_noise.enabled);
        assert_eq!(config.pairs.depth_noise.correlation_px, 8);
    }
}

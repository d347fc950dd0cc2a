//! Checkpoints: `RUN/checkpoints/step-NNNNNNNN/` with the transformer in the diffusers layout,
//! the optimizer state and `state.json`, written under a temporary name and renamed.
//!
//! Verified: `state.json`, written last, lists every other file of the checkpoint with its size
//! and BLAKE3 digest, hashed as the bytes went to disk (never by reading 60 GB back). `--resume`
//! checks them, the files shared out over the ranks, and skips a damaged or incomplete newest
//! checkpoint, naming the file, for the newest intact one. Retention (`keep_last`) counts intact
//! checkpoints only (sizes checked), so it never deletes the last intact one.
//!
//! A write that fails (disk full, quota, I/O error) on any rank removes the partial folder,
//! leaves every earlier checkpoint as it was and stops the run with
//! [`Error::CheckpointWrite`] on every rank.

use std::collections::{BTreeMap, BTreeSet};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor};

use super::CogNvsModel;
use super::consensus;
use super::parallel::StepOptimizer;
use crate::distributed::ProcessGroup;
use crate::error::{Error, Result};
use crate::models::weights::{self, WrittenFile};
use crate::training::data::DataPosition;

/// `state.json` of a checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainState {
    /// Optimizer steps done.
    pub step: u64,
    /// The data position of the next batch.
    pub data_position: DataPosition,
    /// The run seed.
    pub seed: u64,
    /// How the ranks that wrote the checkpoint shared the optimizer state (absent: one process).
    /// Any world size and stage resumes from any checkpoint.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layout: Option<CheckpointLayout>,
    /// Every other file of the checkpoint, by path relative to its folder, as written (empty in
    /// checkpoints from before files were listed: those are resumed unverified).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub files: BTreeMap<String, FileRecord>,
}

/// A checkpoint file as `state.json` lists it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileRecord {
    /// Size in bytes.
    pub bytes: u64,
    /// BLAKE3 of the content, hex.
    pub blake3: String,
}

/// The world that wrote a checkpoint.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CheckpointLayout {
    /// Ranks.
    pub world_size: usize,
    /// ZeRO stage (0: `optimizer.safetensors`; 2: one `optimizer-rank-R-of-N.safetensors` per rank).
    pub zero_stage: u8,
}

/// Name of the file that marks a checkpoint complete.
pub const STATE_NAME: &str = "state.json";
/// Prefix of a checkpoint folder's name while it is being written.
const TEMP_PREFIX: &str = ".tmp-";

fn checkpoints_dir(run: &Path) -> PathBuf {
    run.join("checkpoints")
}

/// Every `step-N` folder of a run, complete or not, oldest first.
fn step_folders(run: &Path) -> Vec<(u64, PathBuf)> {
    let mut found: Vec<(u64, PathBuf)> = std::fs::read_dir(checkpoints_dir(run))
        .into_iter()
        .flatten()
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let step = name.strip_prefix("step-")?.parse().ok()?;
            e.path().is_dir().then(|| (step, e.path()))
        })
        .collect();
    found.sort();
    found
}

/// The complete checkpoints of a run (those with a `state.json`), oldest first.
pub fn list_checkpoints(run: &Path) -> Vec<(u64, PathBuf)> {
    step_folders(run).into_iter().filter(|(_, dir)| dir.join(STATE_NAME).is_file()).collect()
}

/// Reads a checkpoint's `state.json`, refusing a record that reaches beyond its folder: every
/// listed file must be a relative path of plain names inside the folder (no `..`, no absolute
/// path, no device), and the step must be the folder's own (`step-N` holds step N).
pub fn read_state(dir: &Path) -> Result<TrainState> {
    let path = dir.join(STATE_NAME);
    let text = std::fs::read_to_string(&path).map_err(|error| Error::Io { path: path.clone(), error })?;
    let bad = |field: &str, reason: String| Error::InvalidConfig {
        source_name: path.display().to_string(),
        field: field.to_string(),
        reason,
    };
    let state: TrainState = serde_json::from_str(&text).map_err(|e| bad("(json)", e.to_string()))?;
    let folder = dir.file_name().unwrap_or_default().to_string_lossy();
    if let Some(step) = folder.strip_prefix("step-").and_then(|n| n.parse::<u64>().ok())
        && step != state.step
    {
        return Err(bad("step", format!("is {}, but the checkpoint's folder is {folder} (step {step})", state.step)));
    }
    for name in state.files.keys() {
        let plain = !name.is_empty()
            && Path::new(name).components().all(|c| matches!(c, std::path::Component::Normal(_)))
            && name != STATE_NAME;
        if !plain {
            return Err(bad(
                &format!("files.{name}"),
                "is not a file inside the checkpoint's folder (a relative path of plain names)".to_string(),
            ));
        }
    }
    Ok(state)
}

/// What is wrong with the listed files of a checkpoint: each missing, of another size or, with
/// `digests`, of another content, as `FILE: problem`. Checks the files `i` with
/// `i % parts.1 == parts.0` (one rank's share).
pub fn check_files(dir: &Path, state: &TrainState, digests: bool, parts: (usize, usize)) -> Vec<String> {
    let (part, of) = parts;
    let mut problems = Vec::new();
    for (i, (name, record)) in state.files.iter().enumerate() {
        if i % of != part {
            continue;
        }
        let path = dir.join(name);
        // Only regular files inside the folder are read (a link to a device would never end).
        let inside = |path: &Path| matches!((path.canonicalize(), dir.canonicalize()), (Ok(file), Ok(folder)) if file.starts_with(&folder));
        let size = match std::fs::symlink_metadata(&path) {
            Ok(meta) if meta.is_file() && inside(&path) => meta.len(),
            Ok(_) => {
                problems.push(format!("{name}: not a regular file inside the checkpoint's folder"));
                continue;
            }
            Err(e) => {
                problems.push(format!(
                    "{name}: {}",
                    if e.kind() == std::io::ErrorKind::NotFound { "missing".to_string() } else { e.to_string() }
                ));
                continue;
            }
        };
        if size != record.bytes {
            problems
                .push(format!("{name}: {size} bytes, {STATE_NAME} lists {} (truncated or overwritten)", record.bytes));
            continue;
        }
        if digests {
            match digest_of(&path) {
                Ok(found) if found == record.blake3 => {}
                Ok(found) => problems.push(format!(
                    "{name}: BLAKE3 {}…, {STATE_NAME} lists {}… (the content changed)",
                    &found[..12],
                    &record.blake3[..record.blake3.len().min(12)]
                )),
                Err(e) => problems.push(format!("{name}: {e}")),
            }
        }
    }
    problems
}

/// BLAKE3 of a file's content, hex.
fn digest_of(path: &Path) -> std::io::Result<String> {
    let mut file = std::fs::File::open(path)?;
    let mut hasher = blake3::Hasher::new();
    let mut buffer = vec![0u8; READ_CHUNK_BYTES];
    loop {
        let n = file.read(&mut buffer)?;
        if n == 0 {
            break;
        }
        hasher.update(&buffer[..n]);
    }
    Ok(hasher.finalize().to_hex().to_string())
}

/// Read size of the digest check: long sequential reads.
const READ_CHUNK_BYTES: usize = 16 << 20;

/// The newest checkpoint of `run` whose files are all intact (sizes and digests, the files
/// shared out over the ranks of `pg`), with its state; `None` when the run has no checkpoint.
/// Newer ones that are damaged or incomplete are skipped with a message (rank 0) naming the
/// file; when checkpoints exist but none is intact, that is an error naming each one's problem.
pub fn newest_intact(run: &Path, pg: Option<&ProcessGroup>) -> Result<Option<(PathBuf, TrainState)>> {
    let (rank, world) = pg.map_or((0, 1), |pg| (pg.rank, pg.world_size));
    let folders = step_folders(run);
    let mut skipped = Vec::new();
    for (_, dir) in folders.iter().rev() {
        let name = dir.file_name().unwrap_or_default().to_string_lossy().into_owned();
        // Every rank reads state.json (small); each checks its share of the files.
        let (state, mine) = if !dir.join(STATE_NAME).exists() {
            (None, vec![format!("{STATE_NAME}: missing (the checkpoint was never completed)")])
        } else {
            match read_state(dir) {
                Ok(state) => {
                    let problems = check_files(dir, &state, true, (rank, world));
                    (Some(state), problems)
                }
                Err(e) => (None, vec![e.to_string()]),
            }
        };
        // The same problem seen by several ranks (an unreadable state.json) is named once.
        let mut problems: Vec<String> = Vec::new();
        for text in consensus::gather_text(pg, &mine.join("\n"), "checkpoint check")? {
            for line in text.lines() {
                if !problems.iter().any(|p| p == line) {
                    problems.push(line.to_string());
                }
            }
        }
        let state = state.filter(|_| problems.is_empty());
        match state {
            Some(state) => {
                if rank == 0 {
                    if state.files.is_empty() {
                        eprintln!("resume: {name} lists no files (written by an older trainer): not verified");
                    }
                    if !skipped.is_empty() {
                        eprintln!("resume: continuing from {name}, the newest intact checkpoint");
                    }
                }
                return Ok(Some((dir.clone(), state)));
            }
            None => {
                if rank == 0 {
                    eprintln!("resume: skipping checkpoint {name}: {}", problems.join("; "));
                }
                skipped.push(format!("{name}: {}", problems.join("; ")));
            }
        }
    }
    if skipped.is_empty() {
        Ok(None)
    } else {
        Err(Error::InvalidArgument {
            name: "resume".to_string(),
            reason: format!(
                "{} has no intact checkpoint: {}; move the run folder away to start over",
                run.display(),
                skipped.join(" | ")
            ),
        })
    }
}

/// Removes what an interrupted run left half written: checkpoint folders under their temporary
/// name. Only the holder of the run lock may call this (no other writer is at work).
pub(super) fn remove_partial(run: &Path) {
    for entry in std::fs::read_dir(checkpoints_dir(run)).into_iter().flatten().filter_map(|e| e.ok()) {
        if entry.file_name().to_string_lossy().starts_with(TEMP_PREFIX) {
            let _ = std::fs::remove_dir_all(entry.path());
        }
    }
}

/// How one checkpoint write went.
#[derive(Debug, Clone)]
pub struct Written {
    /// The checkpoint folder.
    pub dir: PathBuf,
    /// Bytes of all its files.
    pub bytes: u64,
    /// Wall seconds from the first collective to the last.
    pub seconds: f64,
}

/// Writes the checkpoint of `state` (every rank takes part): each rank's share of the optimizer
/// state, then on rank 0 the weights and `state.json` listing every file with its digest, the
/// rename, and the removal of checkpoints beyond the newest `keep` intact ones. Any rank's failure
/// to write is every rank's [`Error::CheckpointWrite`], with the partial folder removed.
pub(super) fn save_checkpoint(
    run: &Path,
    model: &CogNvsModel,
    optimizer: &StepOptimizer,
    state: &TrainState,
    keep: usize,
    pg: Option<&ProcessGroup>,
) -> Result<Written> {
    let started = Instant::now();
    let dir = checkpoints_dir(run);
    let final_dir = dir.join(format!("step-{:08}", state.step));
    let temp = dir.join(format!("{TEMP_PREFIX}step-{:08}", state.step));
    let rank = pg.map_or(0, |pg| pg.rank);
    // fp32 throughout: a mixed-precision run's master weights replace its bf16 parameters
    // (under ZeRO-2 every rank takes part in gathering them).
    let masters: BTreeMap<String, Tensor> = optimizer.master_weights(pg)?.into_iter().flatten().collect();
    let failed = |reason: String| {
        if rank == 0 {
            let _ = std::fs::remove_dir_all(&temp);
        }
        let kept = list_checkpoints(run)
            .last()
            .map_or("there are none".to_string(), |(_, d)| format!("newest: {}", d.display()));
        Error::CheckpointWrite { step: state.step, reason, kept }
    };
    let created = if rank == 0 {
        let _ = std::fs::remove_dir_all(&temp);
        std::fs::create_dir_all(&temp).map_err(|error| Error::Io { path: temp.clone(), error }.to_string())
    } else {
        Ok(())
    };
    let [create_failed] = consensus::any_rank(pg, [created.is_err()], "checkpoint folder created")?;
    if create_failed {
        return Err(failed(created.err().unwrap_or_else(|| "rank 0 could not create the folder".to_string())));
    }
    // Each rank's optimizer share, then what each wrote (or why it could not) to rank 0.
    // A LoRA run keeps its adapters' exact values here too (the LoRA file holds B scaled).
    let report = match optimizer.save(&temp, model.lora_vs.is_some()) {
        Ok(files) => serde_json::to_string(&Report::Wrote(records(&temp, &files))),
        Err(e) => serde_json::to_string(&Report::Failed(format!("rank {rank}: {e}"))),
    }
    .expect("reports serialise");
    let reports = consensus::gather_text(pg, &report, "optimizer state written")?;
    let mut files = BTreeMap::new();
    let mut failures = Vec::new();
    for text in reports {
        match serde_json::from_str::<Report>(&text) {
            Ok(Report::Wrote(written)) => files.extend(written),
            Ok(Report::Failed(reason)) => failures.push(reason),
            Err(e) => failures.push(format!("unreadable report from a rank: {e}")),
        }
    }
    let outcome = if !failures.is_empty() {
        Err(failures.join("; "))
    } else if rank == 0 {
        finish(run, model, &masters, state, files, &temp, &final_dir, keep).map_err(|e| e.to_string())
    } else {
        Ok(0)
    };
    let [finish_failed] = consensus::any_rank(pg, [outcome.is_err()], "checkpoint complete")?;
    match outcome {
        Err(reason) => Err(failed(reason)),
        Ok(_) if finish_failed => Err(failed("rank 0 could not complete it (its message says why)".to_string())),
        Ok(bytes) => Ok(Written { dir: final_dir, bytes, seconds: started.elapsed().as_secs_f64() }),
    }
}

/// One rank's part of a checkpoint, for rank 0.
#[derive(Serialize, Deserialize)]
enum Report {
    /// Files written, relative to the checkpoint folder.
    Wrote(BTreeMap<String, FileRecord>),
    /// Why this rank could not write its part.
    Failed(String),
}

fn records(dir: &Path, files: &[WrittenFile]) -> BTreeMap<String, FileRecord> {
    files
        .iter()
        .map(|f| {
            let name = f.path.strip_prefix(dir).unwrap_or(&f.path).to_string_lossy().into_owned();
            (name, FileRecord { bytes: f.bytes, blake3: f.blake3.clone() })
        })
        .collect()
}

/// Rank 0's part after every optimizer shard is in: the weights, `state.json` (last), the
/// rename and the pruning. Returns the checkpoint's bytes.
#[allow(clippy::too_many_arguments)]
fn finish(
    run: &Path,
    model: &CogNvsModel,
    masters: &BTreeMap<String, Tensor>,
    state: &TrainState,
    mut files: BTreeMap<String, FileRecord>,
    temp: &Path,
    final_dir: &Path,
    keep: usize,
) -> Result<u64> {
    let written = match (&model.lora_vs, &model.lora) {
        (Some(lora_vs), Some(lora)) => {
            vec![crate::loaders::lora::save(
                lora_vs,
                masters,
                lora.scale(),
                &temp.join(crate::loaders::lora::LORA_WEIGHTS_NAME),
            )?]
        }
        _ => {
            let mut variables: BTreeMap<String, Tensor> = model.vs.variables().into_iter().collect();
            variables.extend(masters.iter().map(|(name, t)| (name.clone(), t.shallow_clone())));
            let variables = variables
                .into_iter()
                .map(|(name, t)| Ok((name, if t.is_floating_point() { t.f_to_kind(Kind::Float)? } else { t })))
                .collect::<Result<_>>()?;
            model.transformer.save(variables, &temp.join("transformer"), weights::DEFAULT_MAX_SHARD_BYTES)?
        }
    };
    files.extend(records(temp, &written));
    let bytes = files.values().map(|f| f.bytes).sum();
    let state = TrainState { files, ..state.clone() };
    let json = serde_json::to_vec_pretty(&state).expect("state serialises");
    weights::write_file(&temp.join(STATE_NAME), &json)?;
    let _ = std::fs::remove_dir_all(final_dir);
    std::fs::rename(temp, final_dir).map_err(|error| Error::Io { path: final_dir.to_path_buf(), error })?;
    // The rename itself reaches the disk with its folder.
    let parent = checkpoints_dir(run);
    std::fs::File::open(&parent).and_then(|d| d.sync_all()).map_err(|error| Error::Io { path: parent, error })?;
    prune(run, keep, state.step);
    Ok(bytes)
}

/// Removes checkpoints older than `newest` beyond the newest `keep` intact ones (sizes checked
/// against `state.json`): damaged ones never count towards `keep`, so the last intact checkpoint
/// is never removed in their favour. Damaged checkpoints newer than `newest` (left behind when a
/// resume skipped them) are kept until the run rewrites their step.
fn prune(run: &Path, keep: usize, newest: u64) {
    let all = list_checkpoints(run);
    let intact: Vec<u64> = all
        .iter()
        .filter(|(_, dir)| read_state(dir).is_ok_and(|s| check_files(dir, &s, false, (0, 1)).is_empty()))
        .map(|(step, _)| *step)
        .collect();
    let kept: BTreeSet<u64> = intact.iter().rev().take(keep).copied().collect();
    for (step, dir) in &all {
        if *step < newest && !kept.contains(step) {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
}

//! `datagen pairs` as one library call: one sequence folder to one shard of training pairs
//! (read the sequence while hashing its files for the shard's stats marker, attach the second
//! depth of measured depth noise, generate every clip's pairs, write the shard), so a test or
//! another program runs exactly what the command runs.

use std::borrow::Cow;
use std::path::PathBuf;
use std::time::Instant;

use schemas::{InputDigest, ShardStats};

use crate::error::{Error, Result};
use crate::io::sequence::{LayoutName, ReadOptions, Sequence, read_sequence_with};
use crate::pairs::generator::{PairsConfig, PhaseTimes, generate_clips_timed, trajectory_request, write_shard};

/// What to make pairs from and where to write them.
#[derive(Debug, Clone)]
pub struct PairsJob {
    /// The sequence folder.
    pub seq_dir: PathBuf,
    /// Its layout (None: detected from its files).
    pub layout: Option<LayoutName>,
    /// How a tool's output is read (VGGT's confidence filter).
    pub read_options: ReadOptions,
    /// The output folder; the shard is `out/{source id}.parquet`.
    pub out: PathBuf,
    /// Sampled trajectories per clip (None: 2, or 0 when trajectory files are given).
    pub trajectories: Option<u32>,
    /// The user's trajectory files.
    pub trajectory_files: Vec<PathBuf>,
    /// Seed of every random choice.
    pub seed: u64,
    /// The pair settings.
    pub config: PairsConfig,
    /// Dataset name stored with the pairs.
    pub dataset: String,
    /// A second depth source for measured depth noise (used when depth noise is on), else the
    /// config's template path if it exists.
    pub second_depth: Option<PathBuf>,
}

/// One trajectory's outcome.
#[derive(Debug, Clone, PartialEq)]
pub struct TrajectorySummary {
    /// The clip it belongs to.
    pub clip_id: String,
    /// Its index in the clip.
    pub index: u32,
    /// Share of co-visible source pixels over the clip.
    pub covisible_fraction: f64,
    /// Samples the crossing test rejected before this one.
    pub rejected_samples: u32,
}

/// What [`make_pairs`] wrote and where its time went.
#[derive(Debug, Clone)]
pub struct PairsReport {
    /// The finished shard.
    pub path: PathBuf,
    /// Its statistics (the stats marker's).
    pub stats: ShardStats,
    /// Every trajectory of every clip, in order.
    pub trajectories: Vec<TrajectorySummary>,
    /// Things the user should know that did not stop the job.
    pub notes: Vec<String>,
    /// Wall seconds reading, decoding and hashing the input.
    pub read_seconds: f64,
    /// The generator's phases.
    pub phases: PhaseTimes,
    /// Wall seconds writing the shard.
    pub write_seconds: f64,
    /// Wall seconds of the whole job.
    pub seconds: f64,
}

/// Makes the pairs of one sequence folder and writes them as one finished shard.
pub fn make_pairs(job: &PairsJob) -> Result<PairsReport> {
    let started = Instant::now();
    // The input's content hash (for the stats marker) is taken while the sequence is read.
    let (sequence, content_hash) = rayon::join(
        || read_sequence_with(&job.seq_dir, job.layout, &job.read_options),
        || foundation::hashing::hash_tree(&job.seq_dir),
    );
    let sequence = sequence?;
    let input = InputDigest { source_path: job.seq_dir.display().to_string(), content_hash: content_hash? };
    let read_seconds = started.elapsed().as_secs_f64();
    let mut report = make_pairs_from(job, Cow::Owned(sequence), input)?;
    report.read_seconds += read_seconds;
    report.seconds = started.elapsed().as_secs_f64();
    Ok(report)
}

/// [`make_pairs`] on a sequence read already (`job.seq_dir`, `job.layout` and
/// `job.read_options` are not read again; `input` is the folder's digest for the stats marker).
/// An owned sequence is freed before the shard is written; a borrowed one is copied only when
/// depth noise loads a second depth into it.
pub fn make_pairs_from(job: &PairsJob, mut sequence: Cow<'_, Sequence>, input: InputDigest) -> Result<PairsReport> {
    let started = Instant::now();
    let noise = &job.config.depth_noise;
    let source_id = sequence.source_id.clone();
    if noise.enabled {
        noise.load_second_depth(sequence.to_mut(), job.second_depth.as_deref(), &job.dataset, &source_id)?;
    }
    let mut notes = Vec::new();
    if noise.enabled && sequence.dynamic_masks.is_none() {
        notes.push(format!("{} has no dynamic-object masks; depth noise changes nothing", job.seq_dir.display()));
    }
    let read_seconds = started.elapsed().as_secs_f64();
    let request = trajectory_request(&sequence, &job.trajectory_files, job.trajectories)?;
    if request.sampled == 0 && request.explicit.is_empty() {
        return Err(Error::invalid(
            &job.seq_dir,
            "trajectories",
            "0 trajectories requested and no trajectory file given",
        ));
    }
    let (records, phases) = generate_clips_timed(&sequence, &job.dataset, &job.config, &request, job.seed)?;
    // The decoded frames and depth are not needed for writing: their memory goes first.
    drop(sequence);
    let clock = Instant::now();
    let (path, stats) = write_shard(&job.out, &source_id, &records, input)?;
    let write_seconds = clock.elapsed().as_secs_f64();
    let trajectories = records
        .iter()
        .flat_map(|record| {
            record.trajectories.iter().map(|t| TrajectorySummary {
                clip_id: record.clip_id.clone(),
                index: t.index,
                covisible_fraction: t.covisible_fraction,
                rejected_samples: t.rejected_samples,
            })
        })
        .collect();
    Ok(PairsReport {
        path,
        stats,
        trajectories,
        notes,
        read_seconds,
        phases,
        write_seconds,
        seconds: started.elapsed().as_secs_f64(),
    })
}

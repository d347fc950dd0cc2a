//! Training batches from `schemas` shards: each sample is one training pair —
//! a window of a stored clip, one of its trajectories' conditioning (the masked source, or the
//! stored depth-noise conditioning) and mask, and the clip's frames as the target — resized to
//! cover the training resolution, centre-cropped and scaled to [-1, 1].
//!
//! Order: every epoch visits every clip of the corpus once in a fresh global permutation (seeded
//! by the run seed and the epoch), which shuffles across shards completely rather than within a
//! buffer; ranks take interleaved slices of it (`rank`, `rank + world_size`, …), so they are
//! disjoint and together cover the epoch. Which trajectory and which window of a clip a sample
//! uses is drawn from the seed, epoch and clip, so a batch is a pure function of
//! (seed, epoch, batch index, rank): a run restarted at a [`DataPosition`] continues exactly.
//! Clips are read by random access (`schemas::read_clip` decodes only the row group holding one;
//! the corpus builder sizes row groups by bytes). Clips shorter than the window repeat their last
//! frame.
//!
//! A background thread decodes batches ahead of the trainer (frames of a batch in parallel) into a
//! bounded queue of `prefetch_batches`, so memory stays at a few batches whatever the corpus size.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;

use image::imageops::FilterType;
use image::{GrayImage, Rgb, RgbImage};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use schemas::ClipRecord;
use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor};

use crate::error::{Error, Result};
use crate::pipelines::video_processor::cover_crop;
use crate::pipelines::video_processor::{MAX_FRAMES, MAX_SIDE};

/// What the loader produces.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DataConfig {
    /// Frames per sample (CogVideoX: 4k + 1, 49 in the paper). Valid: 1 to [`MAX_FRAMES`], and
    /// k·r + 1 for the VAE's temporal compression r (checked against the model by
    /// `PretrainConfig::validate`).
    pub frames: usize,
    /// Training height in pixels. Valid: 1 to [`MAX_SIDE`], a multiple of the VAE's spatial
    /// compression × the transformer's patch size (8 × 2 = 16 for CogVideoX), and the learned
    /// positional table's height when the transformer has one.
    pub height: u32,
    /// Training width in pixels. Valid: as `height`.
    pub width: u32,
    /// Samples per batch. In a training config's `[data]` table the global batch, which the
    /// trainer splits evenly over the ranks; the loader a rank opens is given its share (the
    /// global batch / world size). Valid: 1 to [`MAX_BATCH_SIZE`], and one batch's decoded
    /// tensors within [`MAX_BATCH_BYTES`].
    pub batch_size: usize,
    /// Seed of the order, trajectory and window choices. Valid: any.
    pub seed: u64,
    /// This process's rank. Valid: below `world_size`.
    #[serde(default)]
    pub rank: usize,
    /// Number of ranks. Valid: ≥ 1.
    #[serde(default = "one")]
    pub world_size: usize,
    /// Batches decoded ahead of the trainer. Valid: 1 to [`MAX_PREFETCH_BATCHES`].
    #[serde(default = "two")]
    pub prefetch_batches: usize,
    /// Share of multi-view pairs (`pair_kind = multiview`: one real camera rendered into
    /// another) in every global batch; the rest are monocular pairs. Each global batch holds
    /// the share × the global batch, rounded so that the running total over the epoch's batches
    /// stays at the share (a batch of 8 at 0.3 alternates 2 and 3); which slots are multi-view
    /// is drawn from the seed, epoch and batch, so it does not depend on the world size. Unset:
    /// every pair of the corpus in one order, whatever its kind (the corpus's own proportion).
    /// Valid: in [0, 1]; above 0 the corpus must hold multi-view pairs, below 1 monocular ones.
    #[serde(default)]
    pub multiview_share: Option<f64>,
}

/// Most samples per batch and rank (the paper: 8).
pub const MAX_BATCH_SIZE: usize = 1024;
/// Most batches decoded ahead.
pub const MAX_PREFETCH_BATCHES: usize = 64;
/// Bytes of one batch's decoded tensors may not exceed this (64 GiB): target, condition (3 fp32
/// channels each) and mask (1) per pixel, checked before anything is allocated.
pub const MAX_BATCH_BYTES: u64 = 64 << 30;
/// fp32 bytes per pixel of a sample: 3 target + 3 condition + 1 mask channels.
const SAMPLE_BYTES_PER_PIXEL: u64 = 7 * 4;

impl DataConfig {
    /// Checks each field against its documented range; fields are named `data.<key>` as in the
    /// training TOML and `source_name` names the config.
    pub fn validate(&self, source_name: &str) -> Result<()> {
        let bad = |field: &str, reason: String| Error::InvalidConfig {
            source_name: source_name.to_string(),
            field: format!("data.{field}"),
            reason,
        };
        if !(1..=MAX_FRAMES).contains(&self.frames) {
            return Err(bad("frames", format!("{} must be in 1..={MAX_FRAMES}", self.frames)));
        }
        for (field, value) in [("height", self.height), ("width", self.width)] {
            if !(1..=MAX_SIDE).contains(&value) {
                return Err(bad(field, format!("{value} must be in 1..={MAX_SIDE}")));
            }
        }
        if !(1..=MAX_BATCH_SIZE).contains(&self.batch_size) {
            return Err(bad("batch_size", format!("{} must be in 1..={MAX_BATCH_SIZE}", self.batch_size)));
        }
        let bytes = self.batch_size as u64
            * self.frames as u64
            * u64::from(self.height)
            * u64::from(self.width)
            * SAMPLE_BYTES_PER_PIXEL;
        if bytes > MAX_BATCH_BYTES {
            return Err(bad(
                "batch_size",
                format!(
                    "{} samples of {} frames of {}x{} need {} GiB per batch, above the {} GiB ceiling",
                    self.batch_size,
                    self.frames,
                    self.width,
                    self.height,
                    bytes >> 30,
                    MAX_BATCH_BYTES >> 30
                ),
            ));
        }
        if self.world_size == 0 {
            return Err(bad("world_size", "0 must be ≥ 1".to_string()));
        }
        if self.rank >= self.world_size {
            return Err(bad("rank", format!("{} must be below world_size {}", self.rank, self.world_size)));
        }
        if let Some(share) = self.multiview_share
            && !(share.is_finite() && (0.0..=1.0).contains(&share))
        {
            return Err(bad("multiview_share", format!("{share} must be a finite number in [0, 1]")));
        }
        if !(1..=MAX_PREFETCH_BATCHES).contains(&self.prefetch_batches) {
            return Err(bad(
                "prefetch_batches",
                format!("{} must be in 1..={MAX_PREFETCH_BATCHES}", self.prefetch_batches),
            ));
        }
        Ok(())
    }
}

fn one() -> usize {
    1
}

fn two() -> usize {
    2
}

/// Where a loader is in the data: the next batch it will return. Stored in checkpoints.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct DataPosition {
    /// Epoch (0-based).
    pub epoch: u64,
    /// Batch index within the epoch, for this rank.
    pub batch: u64,
}

/// One batch.
#[derive(Debug)]
pub struct Batch {
    /// Target frames `[B, 3, F, H, W]` in [-1, 1].
    pub target: Tensor,
    /// Conditioning frames `[B, 3, F, H, W]` in [-1, 1] (hidden pixels black, i.e. -1).
    pub condition: Tensor,
    /// Co-visibility `[B, 1, F, H, W]`, 1 co-visible, 0 hidden.
    pub mask: Tensor,
    /// Per sample: `clip_id#t<trajectory>@<window start>`, for error messages.
    pub provenance: Vec<String>,
    /// This batch's position.
    pub position: DataPosition,
}

/// A clip in the corpus: its shard and row, and whether its pairs are multi-view.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct ClipRef {
    shard: usize,
    row: usize,
    multiview: bool,
}

/// Every clip of a set of shard folders (finished shards only).
#[derive(Debug, Clone)]
pub struct ClipIndex {
    shards: Vec<PathBuf>,
    clips: Vec<ClipRef>,
}

impl ClipIndex {
    /// Lists the finished shards (`*.parquet` with a stats marker) of `dirs` (or shard files) and
    /// their clip counts; a shard of another schema or version is an error naming it.
    pub fn open(dirs: &[PathBuf]) -> Result<Self> {
        let mut shards = Vec::new();
        for dir in dirs {
            if dir.is_file() {
                shards.push(dir.clone());
                continue;
            }
            let entries = std::fs::read_dir(dir).map_err(|source| Error::Io { path: dir.clone(), error: source })?;
            let (mut found, unfinished): (Vec<PathBuf>, Vec<PathBuf>) = entries
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|e| e == "parquet"))
                .partition(|p| schemas::is_finished(p));
            if found.is_empty() {
                // Each folder must hold shards: one empty folder among several is a wrong path.
                let reason = match unfinished.first() {
                    None => "no *.parquet shards in this folder (a datagen pairs/build output folder?)".to_string(),
                    Some(example) => format!(
                        "no finished shards: {} *.parquet without a stats marker (unfinished or not \
                         datagen shards), e.g. {}",
                        unfinished.len(),
                        example.display()
                    ),
                };
                return Err(Error::Io { path: dir.clone(), error: std::io::Error::other(reason) });
            }
            found.sort();
            shards.extend(found);
        }
        let mut clips = Vec::new();
        for (shard, path) in shards.iter().enumerate() {
            // One entry per row (the footer's count for shards before v3, which are monocular).
            let kinds = schemas::pair_kinds(path)?;
            clips.extend(kinds.into_iter().enumerate().map(|(row, kind)| ClipRef {
                shard,
                row,
                multiview: kind == schemas::PairKind::Multiview,
            }));
        }
        if clips.is_empty() {
            let names: Vec<String> = shards.iter().map(|d| d.display().to_string()).collect();
            return Err(Error::InvalidArgument {
                name: "shards".to_string(),
                reason: format!(
                    "no clips in {}",
                    if names.is_empty() { "(no shards given)".to_string() } else { names.join(", ") }
                ),
            });
        }
        Ok(Self { shards, clips })
    }

    /// Number of clips.
    pub fn len(&self) -> usize {
        self.clips.len()
    }

    /// Whether there are no clips (never true for an opened index).
    pub fn is_empty(&self) -> bool {
        self.clips.is_empty()
    }

    /// Number of clips of multi-view pairs.
    pub fn multiview_len(&self) -> usize {
        self.clips.iter().filter(|c| c.multiview).count()
    }

    /// The shard files, in index order.
    pub fn shards(&self) -> &[PathBuf] {
        &self.shards
    }

    /// The clips whose id `held` selects, and the others, each in index order (reads only the
    /// shards' clip-id columns). Either part may be empty.
    pub fn split_by_id(&self, held: impl Fn(&str) -> bool) -> Result<(Self, Self)> {
        let ids: Vec<Vec<String>> = self.shards.iter().map(|path| schemas::clip_ids(path)).collect::<Result<_, _>>()?;
        let (selected, rest) = self.clips.iter().partition(|clip| held(&ids[clip.shard][clip.row]));
        Ok((Self { shards: self.shards.clone(), clips: selected }, Self { shards: self.shards.clone(), clips: rest }))
    }

    /// This index's clips followed by `other`'s.
    pub fn joined(&self, other: &Self) -> Self {
        let offset = self.shards.len();
        let moved = other.clips.iter().map(|c| ClipRef { shard: c.shard + offset, ..*c });
        Self {
            shards: self.shards.iter().chain(&other.shards).cloned().collect(),
            clips: self.clips.iter().copied().chain(moved).collect(),
        }
    }
}

fn rng(seed: u64, parts: &[u64]) -> ChaCha8Rng {
    let mut hasher = blake3::Hasher::new();
    hasher.update(b"cognvs data v1");
    hasher.update(&seed.to_le_bytes());
    for p in parts {
        hasher.update(&p.to_le_bytes());
    }
    ChaCha8Rng::from_seed(*hasher.finalize().as_bytes())
}

/// The epoch's global clip order (Fisher–Yates on a seeded generator).
fn epoch_order(len: usize, seed: u64, epoch: u64) -> Vec<usize> {
    shuffled(len, rng(seed, &[epoch]))
}

/// Purpose tags leading the seed's parts of a mixed plan's draws ([`Mix`]): far above any epoch,
/// so they never coincide with the unmixed order's `[epoch]` or a clip's `[epoch, shard, row]`.
const MONOCULAR_ORDER: u64 = u64::MAX - 1;
const MULTIVIEW_ORDER: u64 = u64::MAX - 2;
const MULTIVIEW_SLOTS: u64 = u64::MAX - 3;

/// A plan with a fixed share of multi-view pairs per global batch (`data.multiview_share`): the
/// two kinds' clips are ordered separately each epoch, and each global batch takes its multi-view
/// slots from one order and the others from the other.
struct Mix {
    /// Index positions of the monocular clips.
    monocular: Vec<usize>,
    /// Index positions of the multi-view clips.
    multiview: Vec<usize>,
    /// The share.
    share: f64,
    /// Samples per global batch (all ranks).
    global_batch: usize,
}

impl Mix {
    /// Multi-view slots in the epoch's global batches before batch `b`: the share of their slots,
    /// rounded, so each batch holds the share rounded down or up and the total stays on it.
    fn multiview_before(&self, b: u64) -> usize {
        (self.share * self.global_batch as f64 * b as f64).round() as usize
    }

    /// Whole global batches an epoch can fill without reusing a clip of either kind.
    fn batches_per_epoch(&self) -> u64 {
        let fits = |n: u64| {
            let multiview = self.multiview_before(n);
            multiview <= self.multiview.len() && n as usize * self.global_batch - multiview <= self.monocular.len()
        };
        // Both counts grow with n: the largest n that fits, by bisection.
        let (mut low, mut high) = (0u64, ((self.monocular.len() + self.multiview.len()) / self.global_batch) as u64);
        while low < high {
            let mid = (low + high).div_ceil(2);
            if fits(mid) { low = mid } else { high = mid - 1 }
        }
        low
    }

    /// The index positions of the clips of every slot of global batch `b` of `epoch`, in slot
    /// order (rank r of w takes slots r, r + w, ...).
    fn global_batch_clips(&self, seed: u64, epoch: u64, b: u64) -> Vec<usize> {
        let before = self.multiview_before(b);
        let here = self.multiview_before(b + 1) - before;
        let mut multiview = vec![false; self.global_batch];
        for &slot in &shuffled(self.global_batch, rng(seed, &[MULTIVIEW_SLOTS, epoch, b]))[..here] {
            multiview[slot] = true;
        }
        let multiview_order = shuffled(self.multiview.len(), rng(seed, &[MULTIVIEW_ORDER, epoch]));
        let monocular_order = shuffled(self.monocular.len(), rng(seed, &[MONOCULAR_ORDER, epoch]));
        // Each kind's slots continue that kind's order after the epoch's earlier batches.
        let (mut next_multiview, mut next_monocular) = (before, b as usize * self.global_batch - before);
        multiview
            .into_iter()
            .map(|is_multiview| {
                if is_multiview {
                    next_multiview += 1;
                    self.multiview[multiview_order[next_multiview - 1]]
                } else {
                    next_monocular += 1;
                    self.monocular[monocular_order[next_monocular - 1]]
                }
            })
            .collect()
    }
}

/// `0..len` in the order of a Fisher–Yates shuffle drawn from `rng`.
fn shuffled(len: usize, mut rng: ChaCha8Rng) -> Vec<usize> {
    let mut order: Vec<usize> = (0..len).collect();
    for i in (1..len).rev() {
        order.swap(i, rng.random_range(0..=i));
    }
    order
}

/// Batches of the dataset for one rank.
struct Plan {
    index: Arc<ClipIndex>,
    config: DataConfig,
    batches_per_epoch: u64,
    /// Set with `multiview_share`; otherwise one order over every clip.
    mix: Option<Mix>,
}

impl Plan {
    fn new(index: Arc<ClipIndex>, config: DataConfig) -> Result<Self> {
        let bad = |name: &str, reason: String| Error::InvalidArgument { name: name.to_string(), reason };
        config.validate("data config")?;
        let mix = match config.multiview_share {
            Some(share) => Some(mix(&index, &config, share)?),
            None => None,
        };
        let batches_per_epoch = match &mix {
            Some(mix) => mix.batches_per_epoch(),
            None => (index.len() / config.world_size / config.batch_size) as u64,
        };
        if let (Some(mix), 0) = (&mix, batches_per_epoch) {
            return Err(bad(
                "batch_size",
                format!(
                    "{} monocular and {} multi-view clips cannot fill one global batch of {} × {} ranks \
                     with a multi-view share of {}",
                    mix.monocular.len(),
                    mix.multiview.len(),
                    config.batch_size,
                    config.world_size,
                    mix.share
                ),
            ));
        }
        if batches_per_epoch == 0 {
            return Err(bad(
                "batch_size",
                format!(
                    "{} clips cannot fill one batch of {} on each of {} ranks",
                    index.len(),
                    config.batch_size,
                    config.world_size
                ),
            ));
        }
        Ok(Self { index, config, batches_per_epoch, mix })
    }

    fn batch(&self, position: DataPosition) -> Result<Batch> {
        let c = &self.config;
        // The clips of the global batch's slots, from one order over all clips or, mixed, from
        // one order per kind.
        let global = c.batch_size * c.world_size;
        let slots = match &self.mix {
            Some(mix) => mix.global_batch_clips(c.seed, position.epoch, position.batch),
            None => {
                let start = position.batch as usize * global;
                epoch_order(self.index.len(), c.seed, position.epoch)[start..start + global].to_vec()
            }
        };
        let samples = (0..c.batch_size)
            .into_par_iter()
            .map(|k| {
                // Slot j of the global batch: ranks take interleaved slots of the same global draw.
                let j = k * c.world_size + c.rank;
                let clip = self.index.clips[slots[j]];
                let mut choice = rng(c.seed, &[position.epoch, clip.shard as u64, clip.row as u64]);
                let record = schemas::read_clip(&self.index.shards[clip.shard], clip.row)?;
                sample(&record, c, &mut choice)
            })
            .collect::<Result<Vec<_>>>()?;
        let stack = |pick: fn(&Sample) -> &Tensor| Tensor::f_stack(&samples.iter().map(pick).collect::<Vec<_>>(), 0);
        Ok(Batch {
            target: stack(|s| &s.target)?,
            condition: stack(|s| &s.condition)?,
            mask: stack(|s| &s.mask)?,
            provenance: samples.iter().map(|s| s.provenance.clone()).collect(),
            position,
        })
    }

    fn advance(&self, position: DataPosition) -> DataPosition {
        if position.batch + 1 >= self.batches_per_epoch {
            DataPosition { epoch: position.epoch + 1, batch: 0 }
        } else {
            DataPosition { epoch: position.epoch, batch: position.batch + 1 }
        }
    }
}

/// The mixed plan of `index` for `share`: an error naming `data.multiview_share` when the corpus
/// lacks a kind the share asks for.
fn mix(index: &ClipIndex, config: &DataConfig, share: f64) -> Result<Mix> {
    let (multiview, monocular): (Vec<usize>, Vec<usize>) =
        (0..index.clips.len()).partition(|&i| index.clips[i].multiview);
    let lacking = if share > 0.0 && multiview.is_empty() {
        Some("multi-view pairs (make them with `datagen pairs` or `datagen build` from multi-camera scenes)")
    } else if share < 1.0 && monocular.is_empty() {
        Some("monocular pairs")
    } else {
        None
    };
    if let Some(lacking) = lacking {
        let shards: Vec<String> = index.shards.iter().take(3).map(|p| p.display().to_string()).collect();
        return Err(Error::InvalidConfig {
            source_name: "data config".to_string(),
            field: "data.multiview_share".to_string(),
            reason: format!(
                "{share} asks for {lacking}, but the {} clips of the shards ({}{}) hold none",
                index.clips.len(),
                shards.join(", "),
                if index.shards.len() > 3 { ", ..." } else { "" }
            ),
        });
    }
    Ok(Mix { monocular, multiview, share, global_batch: config.batch_size * config.world_size })
}

struct Sample {
    target: Tensor,
    condition: Tensor,
    mask: Tensor,
    provenance: String,
}

fn decode_png(bytes: &[u8], clip: &str, field: String) -> Result<image::DynamicImage> {
    image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
        .map_err(|e| Error::InvalidArgument { name: format!("{clip}: {field}"), reason: format!("not a PNG: {e}") })
}

fn sample(record: &ClipRecord, c: &DataConfig, choice: &mut ChaCha8Rng) -> Result<Sample> {
    let id = &record.clip_id;
    let n = record.num_frames();
    if record.trajectories.is_empty() || n == 0 {
        return Err(Error::InvalidArgument {
            name: id.clone(),
            reason: "clip has no frames or no trajectories".to_string(),
        });
    }
    let t = choice.random_range(0..record.trajectories.len());
    let start = if n > c.frames { choice.random_range(0..=n - c.frames) } else { 0 };
    let trajectory = &record.trajectories[t];
    let frames: Vec<(RgbImage, RgbImage, GrayImage)> = (0..c.frames)
        .map(|k| {
            let i = (start + k).min(n - 1);
            let target = decode_png(&record.frames[i], id, format!("frames[{i}]"))?.to_rgb8();
            let mask = decode_png(&trajectory.covisible_mask[i], id, format!("trajectories[{t}].covisible_mask[{i}]"))?
                .to_luma8();
            let condition = match &trajectory.condition {
                Some(stored) => decode_png(&stored[i], id, format!("trajectories[{t}].condition[{i}]"))?.to_rgb8(),
                None => target.clone(),
            };
            let target = cover_crop(&target, c.width, c.height, FilterType::Triangle);
            let mut condition = cover_crop(&condition, c.width, c.height, FilterType::Triangle);
            let mask = cover_crop(&mask, c.width, c.height, FilterType::Nearest);
            for (pixel, m) in condition.pixels_mut().zip(mask.pixels()) {
                if m.0[0] == 0 {
                    *pixel = Rgb([0, 0, 0]);
                }
            }
            Ok((target, condition, mask))
        })
        .collect::<Result<_>>()?;
    let (f, h, w) = (c.frames as i64, i64::from(c.height), i64::from(c.width));
    let video = |pick: fn(&(RgbImage, RgbImage, GrayImage)) -> &RgbImage| -> Result<Tensor> {
        let bytes: Vec<u8> = frames.iter().flat_map(|fr| pick(fr).as_raw().iter().copied()).collect();
        // [F, H, W, 3] → [3, F, H, W], scaled to [-1, 1].
        Ok(Tensor::from_slice(&bytes)
            .f_view([f, h, w, 3])?
            .f_permute([3, 0, 1, 2])?
            .f_to_kind(Kind::Float)?
            .f_div_scalar(127.5)?
            .f_sub_scalar(1.0)?)
    };
    let mask_bytes: Vec<u8> = frames.iter().flat_map(|fr| fr.2.as_raw().iter().map(|&v| u8::from(v != 0))).collect();
    Ok(Sample {
        target: video(|fr| &fr.0)?,
        condition: video(|fr| &fr.1)?,
        mask: Tensor::from_slice(&mask_bytes).f_view([1, f, h, w])?.f_to_kind(Kind::Float)?,
        provenance: format!("{id}#t{}@{start}", trajectory.index),
    })
}

/// Batches from a background thread, in order, from a starting position.
pub struct ShardLoader {
    receiver: Option<Receiver<Result<Batch>>>,
    stop: Arc<AtomicBool>,
    worker: Option<JoinHandle<()>>,
    next: DataPosition,
    batches_per_epoch: u64,
}

impl ShardLoader {
    /// Starts loading at `start` (the beginning: `DataPosition::default()`).
    pub fn new(index: Arc<ClipIndex>, config: DataConfig, start: DataPosition) -> Result<Self> {
        let prefetch = config.prefetch_batches.max(1);
        let plan = Plan::new(index, config)?;
        let batches_per_epoch = plan.batches_per_epoch;
        let stop = Arc::new(AtomicBool::new(false));
        let (sender, receiver) = sync_channel(prefetch);
        let worker = {
            let stop = Arc::clone(&stop);
            std::thread::Builder::new()
                .name("cognvs-data".to_string())
                .spawn(move || produce(plan, start, sender, stop))
                .map_err(|source| Error::Io { path: PathBuf::from("<data loader thread>"), error: source })?
        };
        Ok(Self { receiver: Some(receiver), stop, worker: Some(worker), next: start, batches_per_epoch })
    }

    /// Opens the shards under `dirs` and starts loading at `start`.
    pub fn open(dirs: &[PathBuf], config: DataConfig, start: DataPosition) -> Result<Self> {
        Self::new(Arc::new(ClipIndex::open(dirs)?), config, start)
    }

    /// The next batch (blocks while it is being decoded).
    pub fn next_batch(&mut self) -> Result<Batch> {
        let batch = self.receiver.as_ref().expect("open until dropped").recv().map_err(|_| {
            Error::InvalidArgument { name: "data loader".to_string(), reason: "the loading thread stopped".to_string() }
        })??;
        self.next = if batch.position.batch + 1 >= self.batches_per_epoch {
            DataPosition { epoch: batch.position.epoch + 1, batch: 0 }
        } else {
            DataPosition { epoch: batch.position.epoch, batch: batch.position.batch + 1 }
        };
        Ok(batch)
    }

    /// Where the next [`Self::next_batch`] continues: store it to resume exactly.
    pub fn position(&self) -> DataPosition {
        self.next
    }

    /// Batches per epoch for this rank.
    pub fn batches_per_epoch(&self) -> u64 {
        self.batches_per_epoch
    }
}

fn produce(plan: Plan, start: DataPosition, sender: SyncSender<Result<Batch>>, stop: Arc<AtomicBool>) {
    let mut position = start;
    while !stop.load(Ordering::Relaxed) {
        let batch = plan.batch(position);
        let failed = batch.is_err();
        if sender.send(batch).is_err() || failed {
            return;
        }
        position = plan.advance(position);
    }
}

impl Drop for ShardLoader {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        // Closing the channel unblocks a producer waiting to send.
        drop(self.receiver.take());
        if let Some(worker) = self.worker.take() {
            let _ = worker.join();
        }
    }
}

/// The shard folders' clip count and the batches per epoch a config gives, without loading.
pub fn describe(dirs: &[PathBuf], config: &DataConfig) -> Result<(usize, u64)> {
    let index = Arc::new(ClipIndex::open(dirs)?);
    Ok((index.len(), batches_per_epoch(index, config)?))
}

/// The batches per epoch a config gives over `index`; an error when not even one fits.
pub fn batches_per_epoch(index: Arc<ClipIndex>, config: &DataConfig) -> Result<u64> {
    Ok(Plan::new(index, config.clone())?.batches_per_epoch)
}

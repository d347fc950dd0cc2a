//! Data parallelism over a [`ProcessGroup`]: the flat layout the optimizer works in, the
//! gradient exchange that overlaps the backward, and the optimizer state of checkpoints written
//! at any world size.
//!
//! The flat layout ([`FlatLayout`]): the trainable parameters in the order the backward
//! finishes their gradients (the model's backward stages: for the transformer its head, its
//! blocks from the last to the first, then the embeddings; name order within a stage), end to
//! end in buckets of about `[distributed] bucket_mib` of whole parameters, each padded to a
//! multiple of the world size N. Every bucket is one tensor for the parameters and one for their
//! gradients, and each parameter (and its `.grad`) is a view into them, so the backward
//! accumulates straight into the buffers the collectives and the optimizer read: no gradient is
//! flattened or copied back. Under ZeRO-2 rank r owns elements `[r·s, (r+1)·s)` of a bucket
//! padded to N·s: it keeps the reduced gradient, AdamW moments and fp32 master weights of that
//! slice only, and the updated weights are all-gathered into every rank's bucket in place.
//!
//! The exchange ([`GradientExchange`]): the backward reports each finished stage; every bucket
//! whose gradients are then final starts its reduction at once (NCCL on its own stream, ordered
//! after the backward's kernels by an event; Gloo on its worker threads) while the backward goes
//! on. The optimizer waits for each bucket's reduction only when it comes to that bucket. Stage 0
//! all-reduces a bucket in place; ZeRO-2 reduce-scatters it in place on NCCL (half the bytes
//! each rank receives), and all-reduces it in place on Gloo, whose reduce-scatter is itself an
//! all-reduce of a full copy of the input.
//!
//! Checkpoints: the moments (and masters) are saved by flat ranges of the name-ordered parameter
//! space, whatever the layout: one `optimizer.safetensors` with per-parameter tensors (stage 0,
//! rank 0) or one `optimizer-rank-R-of-N.safetensors` per rank with the ranges it holds (ZeRO-2);
//! [`FlatState`] reads any range from either, so a run resumes at any world size and stage.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use tch::{Kind, Tensor};

use super::{Backend, Pending, ProcessGroup};
use crate::error::{Error, Result};

/// File-name pattern of one rank's optimizer shard.
pub const SHARD_PREFIX: &str = "optimizer-rank-";
/// One MiB.
const MIB: f64 = 1024.0 * 1024.0;

/// A run of whole parameters reduced in one collective.
#[derive(Debug, Clone)]
struct Bucket {
    /// Parameter indices (name order) in the bucket's order.
    members: Vec<usize>,
    /// Elements before padding.
    len: i64,
    /// Elements after padding: a multiple of the world size.
    padded: i64,
    /// The backward stage after which every member's gradient is final.
    ready_after: usize,
    /// Where this rank's optimizer state for the bucket starts (the local space: whole buckets
    /// end to end when replicated, this rank's slices end to end under ZeRO-2).
    local: i64,
}

/// Where the trainable parameters live in the flat buckets, and what this rank owns of them.
#[derive(Debug, Clone)]
pub struct FlatLayout {
    buckets: Vec<Bucket>,
    /// Per parameter (name order): its bucket and its offset in it.
    places: Vec<(usize, i64)>,
    /// Per parameter: its offset in the name-ordered flat space (checkpoint ranges).
    name_offsets: Vec<i64>,
    /// Per parameter: elements.
    numels: Vec<i64>,
    rank: usize,
    world: usize,
    sharded: bool,
    local_len: i64,
}

impl FlatLayout {
    /// Buckets of about `bucket_mib` MiB over `params` (name-ordered, as the optimizer keeps
    /// them), in the order of `stage_of(name)`: the backward stage after which the parameter's
    /// gradient is final. `sharded`: ZeRO-2 over `world` ranks (else every rank owns all).
    pub fn new(
        params: &[(String, Tensor)],
        stage_of: impl Fn(&str) -> usize,
        bucket_mib: f64,
        rank: usize,
        world: usize,
        sharded: bool,
    ) -> Self {
        assert!(rank < world, "rank {rank} of {world}");
        let numels: Vec<i64> = params.iter().map(|(_, p)| p.numel() as i64).collect();
        let mut name_offsets = Vec::with_capacity(params.len());
        let mut offset = 0;
        for &numel in &numels {
            name_offsets.push(offset);
            offset += numel;
        }
        let stages: Vec<usize> = params.iter().map(|(name, _)| stage_of(name)).collect();
        let mut order: Vec<usize> = (0..params.len()).collect();
        // Stable: name order within a stage.
        order.sort_by_key(|&i| stages[i]);
        let bucket_bytes = bucket_mib * MIB;
        let mut buckets: Vec<Bucket> = Vec::new();
        let mut bytes = 0.0;
        for i in order {
            let size = numels[i] as f64 * params[i].1.kind().elt_size_in_bytes() as f64;
            match buckets.last_mut() {
                Some(last) if bytes + size <= bucket_bytes => {
                    last.members.push(i);
                    last.len += numels[i];
                    last.ready_after = last.ready_after.max(stages[i]);
                    bytes += size;
                }
                _ => {
                    buckets.push(Bucket {
                        members: vec![i],
                        len: numels[i],
                        padded: 0,
                        ready_after: stages[i],
                        local: 0,
                    });
                    bytes = size;
                }
            }
        }
        let mut places = vec![(0, 0); params.len()];
        let mut local = 0;
        for (b, bucket) in buckets.iter_mut().enumerate() {
            let mut at = 0;
            for &i in &bucket.members {
                places[i] = (b, at);
                at += numels[i];
            }
            bucket.padded = (bucket.len + world as i64 - 1) / world as i64 * world as i64;
            bucket.local = local;
            local += if sharded { bucket.padded / world as i64 } else { bucket.padded };
        }
        Self { buckets, places, name_offsets, numels, rank, world, sharded, local_len: local }
    }

    /// Buckets, in the order their gradients become final.
    pub fn bucket_count(&self) -> usize {
        self.buckets.len()
    }

    /// Elements of bucket `b` with its padding (the length of its flat tensors).
    pub fn padded_len(&self, b: usize) -> i64 {
        self.buckets[b].padded
    }

    /// The backward stage after which bucket `b`'s gradients are final.
    pub fn ready_after(&self, b: usize) -> usize {
        self.buckets[b].ready_after
    }

    /// Parameter `i`'s bucket and its offset in it.
    pub fn place(&self, i: usize) -> (usize, i64) {
        self.places[i]
    }

    /// The ranks and this one.
    pub fn world(&self) -> (usize, usize) {
        (self.rank, self.world)
    }

    /// Whether each rank owns a 1/N slice of every bucket (ZeRO-2).
    pub fn sharded(&self) -> bool {
        self.sharded
    }

    /// `(offset in the bucket, length)` of what this rank updates of bucket `b`: all of it, or
    /// its slice under ZeRO-2.
    pub fn owned(&self, b: usize) -> (i64, i64) {
        let padded = self.buckets[b].padded;
        if self.sharded {
            let shard = padded / self.world as i64;
            (self.rank as i64 * shard, shard)
        } else {
            (0, padded)
        }
    }

    /// Where bucket `b`'s owned part starts in the local space of the optimizer state.
    pub fn local_offset(&self, b: usize) -> i64 {
        self.buckets[b].local
    }

    /// Elements of the local space (the optimizer state's length).
    pub fn local_len(&self) -> i64 {
        self.local_len
    }

    /// Every `(name-ordered flat start, length, local offset)` this rank owns, padding left out:
    /// the ranges of its checkpoint shard, and what it reads back on resume.
    pub fn owned_ranges(&self) -> Vec<(i64, i64, i64)> {
        let mut ranges = Vec::new();
        for (b, bucket) in self.buckets.iter().enumerate() {
            let (own_start, own_len) = self.owned(b);
            let mut at = 0;
            for &i in &bucket.members {
                let (start, end) = (own_start.max(at), (own_start + own_len).min(at + self.numels[i]));
                if start < end {
                    ranges.push((self.name_offsets[i] + start - at, end - start, bucket.local + start - own_start));
                }
                at += self.numels[i];
            }
        }
        ranges
    }
}

/// The collectives of one optimizer step over the flat gradient and parameter buckets: each
/// bucket's reduction, started as soon as the backward has finished its gradients, and under
/// ZeRO-2 the all-gather of the updated weights. With `noop` (`[distributed] noop_collectives`)
/// every one of them is skipped: a rank's buckets keep its own values, in place.
pub struct GradientExchange {
    noop: bool,
    /// Per bucket: the reduction in flight.
    reductions: Vec<Option<Pending>>,
    /// Buckets whose reduction has started: always a prefix, in bucket order.
    started: usize,
    /// Per bucket: the all-gather in flight.
    gathers: Vec<Option<Pending>>,
}

impl GradientExchange {
    /// Nothing in flight, for a layout of `buckets` buckets.
    pub fn new(buckets: usize, noop: bool) -> Self {
        Self {
            noop,
            reductions: (0..buckets).map(|_| None).collect(),
            started: 0,
            gathers: (0..buckets).map(|_| None).collect(),
        }
    }

    /// Starts the reduction of every bucket not started yet whose gradients are final once
    /// backward stage `stage` is done (`usize::MAX`: all that remain). `grads` are the flat
    /// gradient buckets.
    pub fn start_ready(
        &mut self,
        layout: &FlatLayout,
        grads: &[Tensor],
        stage: usize,
        pg: &ProcessGroup,
    ) -> Result<()> {
        let total = layout.bucket_count();
        while self.started < total && layout.ready_after(self.started) <= stage {
            let b = self.started;
            self.started += 1;
            if self.noop {
                continue;
            }
            let what = format!("gradient bucket {}/{total}", b + 1);
            let bucket = &grads[b];
            let pending = if layout.sharded() && pg.backend() == Backend::Nccl {
                let (offset, shard) = layout.owned(b);
                // In place: this rank's slice of the bucket receives its slice of the sum.
                pg.reduce_scatter_sum_start(&bucket.f_narrow(0, offset, shard)?, bucket, &what)?
            } else {
                pg.all_reduce_sum_start(bucket, &what)?
            };
            self.reductions[b] = Some(pending);
        }
        Ok(())
    }

    /// Waits for bucket `b`'s reduction (started by [`Self::start_ready`]): afterwards its owned
    /// part holds the sum over ranks. `block`: wait on the host with the timeout (a stalled peer
    /// then fails here, naming it), else only order the device's next work after it.
    pub fn finish_reduction(&mut self, b: usize, block: bool, pg: &ProcessGroup) -> Result<()> {
        assert!(b < self.started, "bucket {b} was never reduced");
        match self.reductions[b].take() {
            Some(pending) if block => pg.wait(pending),
            Some(pending) => pg.wait_on_stream(pending),
            None => Ok(()),
        }
    }

    /// Starts the all-gather of bucket `b`'s weights into every rank's `params` bucket, whose
    /// owned slice holds this rank's updated values (ZeRO-2), in place.
    pub fn start_gather(&mut self, layout: &FlatLayout, params: &Tensor, b: usize, pg: &ProcessGroup) -> Result<()> {
        if self.noop {
            return Ok(());
        }
        let (offset, shard) = layout.owned(b);
        let what = format!("weights bucket {}/{}", b + 1, layout.bucket_count());
        self.gathers[b] = Some(pg.all_gather_start(params, &params.f_narrow(0, offset, shard)?, &what)?);
        Ok(())
    }

    /// Waits for every all-gather started, the last on the host (see [`Self::finish_reduction`]).
    pub fn finish_gathers(&mut self, pg: &ProcessGroup) -> Result<()> {
        let pending: Vec<Pending> = self.gathers.iter_mut().filter_map(Option::take).collect();
        let last = pending.len().saturating_sub(1);
        for (k, gather) in pending.into_iter().enumerate() {
            if k == last { pg.wait(gather)? } else { pg.wait_on_stream(gather)? }
        }
        Ok(())
    }

    /// Forgets the step's reductions (all waited for): the next backward starts from bucket 0.
    pub fn reset(&mut self) {
        debug_assert!(self.reductions.iter().all(Option::is_none), "a reduction was never waited for");
        self.started = 0;
    }
}

/// Optimizer state over the flat parameter space, read from a checkpoint written by either
/// stage at any world size: ZeRO shards (`optimizer-rank-*`) or one `optimizer.safetensors`
/// with per-parameter tensors (`exp_avg.NAME`, `exp_avg_sq.NAME`, `param.NAME`).
pub struct FlatState {
    /// `(flat start, length, tensors by name)` per saved range.
    pieces: Vec<(i64, i64, BTreeMap<String, Tensor>)>,
    masters: bool,
    /// The optimizer step the state is at.
    pub step: u64,
}

impl FlatState {
    /// Reads the optimizer state in checkpoint `dir` for `params` (name-ordered).
    pub fn open(dir: &Path, params: &[(String, Tensor)]) -> Result<Self> {
        let read = |path: &Path| -> Result<BTreeMap<String, Tensor>> {
            Ok(Tensor::read_safetensors(path)
                .map_err(|e| Error::Safetensors { path: path.to_path_buf(), reason: e.to_string() })?
                .into_iter()
                .collect())
        };
        let single = dir.join("optimizer.safetensors");
        let step_of =
            |tensors: &BTreeMap<String, Tensor>| tensors.get("step").map_or(0, |t| t.int64_value(&[0]) as u64);
        if single.is_file() {
            let tensors = read(&single)?;
            let step = step_of(&tensors);
            let masters = params.iter().all(|(name, _)| tensors.contains_key(&format!("param.{name}")));
            let mut pieces = Vec::new();
            let mut offset = 0;
            for (name, p) in params {
                let mut map = BTreeMap::new();
                for (key, file_key) in [
                    ("exp_avg", format!("exp_avg.{name}")),
                    ("exp_avg_sq", format!("exp_avg_sq.{name}")),
                    ("master", format!("param.{name}")),
                ] {
                    match tensors.get(&file_key) {
                        Some(t) => {
                            crate::models::weights::check_shape(&file_key, t, &p.size())?;
                            map.insert(key.to_string(), t.f_reshape([-1])?.f_to_kind(Kind::Float)?);
                        }
                        None if key == "master" => {}
                        None => {
                            return Err(Error::MissingTensor {
                                path: single.clone(),
                                tensor: file_key,
                                expected: p.size(),
                            });
                        }
                    }
                }
                pieces.push((offset, p.numel() as i64, map));
                offset += p.numel() as i64;
            }
            return Ok(Self { pieces, masters, step });
        }
        let mut shards: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(|source| Error::Io { path: dir.to_path_buf(), error: source })?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.file_name().is_some_and(|n| n.to_string_lossy().starts_with(SHARD_PREFIX)))
            .collect();
        shards.sort();
        if shards.is_empty() {
            return Err(Error::InvalidInput {
                path: dir.to_path_buf(),
                what: "optimizer state".to_string(),
                reason: format!("neither optimizer.safetensors nor {SHARD_PREFIX}*.safetensors"),
            });
        }
        let mut pieces = Vec::new();
        let mut step = None;
        for shard in &shards {
            let tensors = read(shard)?;
            let ranges = tensors.get("ranges").ok_or_else(|| Error::MissingTensor {
                path: shard.clone(),
                tensor: "ranges".to_string(),
                expected: vec![-1, 3],
            })?;
            let this_step = step_of(&tensors);
            if *step.get_or_insert(this_step) != this_step {
                return Err(Error::InvalidInput {
                    path: shard.clone(),
                    what: "step".to_string(),
                    reason: format!(
                        "{this_step}, but another shard of this checkpoint is at step {}",
                        step.unwrap_or(0)
                    ),
                });
            }
            let rows = ranges.size()[0];
            for row in 0..rows {
                let (start, len, local) =
                    (ranges.int64_value(&[row, 0]), ranges.int64_value(&[row, 1]), ranges.int64_value(&[row, 2]));
                let mut map = BTreeMap::new();
                for key in ["exp_avg", "exp_avg_sq", "master"] {
                    let t = tensors.get(key).ok_or_else(|| Error::MissingTensor {
                        path: shard.clone(),
                        tensor: key.to_string(),
                        expected: vec![-1],
                    })?;
                    map.insert(key.to_string(), t.f_narrow(0, local, len)?);
                }
                pieces.push((start, len, map));
            }
        }
        let total: i64 = params.iter().map(|(_, p)| p.numel() as i64).sum();
        let covered: i64 = pieces.iter().map(|(_, len, _)| len).sum();
        if covered != total {
            return Err(Error::InvalidInput {
                path: dir.to_path_buf(),
                what: "optimizer shards".to_string(),
                reason: format!(
                    "cover {covered} parameter elements, the model trains {total}: a shard is missing or from another model"
                ),
            });
        }
        Ok(Self { pieces, masters: true, step: step.unwrap_or(0) })
    }

    /// Whether the state holds fp32 master values.
    pub fn has_masters(&self) -> bool {
        self.masters
    }

    /// Elements `[start, start + len)` of state `name` (`exp_avg`, `exp_avg_sq`, `master`).
    pub fn read(&self, name: &str, start: i64, len: i64) -> Result<Tensor> {
        let out = Tensor::f_zeros([len], (Kind::Float, tch::Device::Cpu))?;
        for (p_start, p_len, map) in &self.pieces {
            let (a, b) = (start.max(*p_start), (start + len).min(p_start + p_len));
            if a < b
                && let Some(t) = map.get(name)
            {
                out.f_narrow(0, a - start, b - a)?.f_copy_(&t.f_narrow(0, a - p_start, b - a)?)?;
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use tch::Device;

    use super::*;

    /// Parameters `w0..w5` of the given sizes, fp32 (4 bytes each).
    fn params(sizes: &[i64]) -> Vec<(String, Tensor)> {
        sizes
            .iter()
            .enumerate()
            .map(|(i, &n)| (format!("w{i}"), Tensor::zeros([n], (Kind::Float, Device::Cpu))))
            .collect()
    }

    /// Buckets follow the stages (later stages later, name order within one), hold whole
    /// parameters up to the size (one may span two stages: it is ready after the later), are
    /// padded to the world size, and the ranks' owned ranges tile the name-ordered space once.
    #[test]
    fn buckets_follow_the_backward_and_shards_tile_the_parameters() {
        let sizes = [1, 3, 7, 2, 4, 6];
        let p = params(&sizes);
        // w4, w5 finish first (stage 0), then w2, w3 (1), then w0, w1 (2).
        let stage_of = |name: &str| match name {
            "w4" | "w5" => 0,
            "w2" | "w3" => 1,
            _ => 2,
        };
        // 10 elements of 4 bytes a bucket.
        let bucket_mib = 40.0 / MIB;
        let total: i64 = sizes.iter().sum();
        for world in [1, 2, 3] {
            let mut covered = vec![0u32; total as usize];
            for rank in 0..world {
                let layout = FlatLayout::new(&p, stage_of, bucket_mib, rank, world, true);
                let members: Vec<Vec<usize>> = layout.buckets.iter().map(|b| b.members.clone()).collect();
                assert_eq!(members, vec![vec![4, 5], vec![2, 3, 0], vec![1]], "world {world}");
                let ready: Vec<usize> = (0..layout.bucket_count()).map(|b| layout.ready_after(b)).collect();
                assert_eq!(ready, vec![0, 2, 2]);
                for b in 0..layout.bucket_count() {
                    assert_eq!(layout.padded_len(b) % world as i64, 0);
                    assert!(layout.padded_len(b) - layout.buckets[b].len < world as i64);
                }
                assert_eq!(layout.place(0), (1, 9), "w0 follows w2 and w3 in its bucket");
                for (start, len, local) in layout.owned_ranges() {
                    assert!(local + len <= layout.local_len());
                    for e in start..start + len {
                        covered[e as usize] += 1;
                    }
                }
            }
            assert!(covered.iter().all(|&c| c == 1), "world {world}: {covered:?}");
        }
    }

    /// Replicated, every rank owns whole buckets and its local space is the bucket space.
    #[test]
    fn replicated_layout_owns_everything() {
        let p = params(&[5, 3, 7]);
        let layout = FlatLayout::new(&p, |_| 0, 1.0, 1, 2, false);
        assert_eq!(layout.bucket_count(), 1);
        assert_eq!(layout.owned(0), (0, 16));
        assert_eq!(layout.local_len(), 16);
        assert_eq!(layout.owned_ranges(), vec![(0, 5, 0), (5, 3, 5), (8, 7, 8)]);
    }
}

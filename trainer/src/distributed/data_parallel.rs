//! Data parallelism over a [`ProcessGroup`]: gradients flattened into buckets of about
//! `[distributed] bucket_mib` and reduced one collective per bucket, once per optimizer step
//! (after all micro-batches of gradient accumulation); and ZeRO-2, where each rank keeps only its
//! share of the reduced gradients, AdamW moments and fp32 master weights.
//!
//! The flat parameter space: the trainable parameters in name order (the optimizer's order),
//! each flattened, end to end. Buckets are consecutive runs of whole parameters. Under ZeRO-2 a
//! bucket of `len` elements is padded to `N·s` (s = ⌈len/N⌉) and rank r owns its elements
//! `[r·s, (r+1)·s)`: reduce-scatter hands each rank exactly that slice, AdamW runs on it, and an
//! all-gather returns the updated weights to everyone. Optimizer checkpoints are written per rank
//! (`optimizer-rank-R-of-N.safetensors`) with the flat ranges they hold, so a run resumes at any
//! world size and with either stage: [`FlatState`] reads any range from either layout.
//!
//! Overlap: tch has no backward hooks, so reductions cannot start while backward still runs; they
//! start bucket after bucket as soon as backward ends, up to [`IN_FLIGHT`] at a time, so flattening
//! and copying overlap with communication.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use tch::{Kind, Tensor};

use super::{Pending, ProcessGroup};
use crate::error::{Error, Result};
use crate::training::OptimConfig;

/// Buckets reduced at the same time: two keep the link busy while the next is flattened.
const IN_FLIGHT: usize = 2;
/// File-name pattern of one rank's optimizer shard.
const SHARD_PREFIX: &str = "optimizer-rank-";

/// A run of whole parameters reduced in one collective.
#[derive(Debug, Clone)]
struct Bucket {
    /// First element in the flat parameter space.
    start: i64,
    /// Elements (before padding).
    len: i64,
    /// Parameter indices, in order.
    members: Vec<usize>,
}

impl Bucket {
    /// Elements per rank under ZeRO-2 (the padded length is `world · shard`).
    fn shard(&self, world: usize) -> i64 {
        (self.len + world as i64 - 1) / world as i64
    }
}

fn make_buckets(params: &[(String, Tensor)], bucket_bytes: f64) -> Vec<Bucket> {
    let mut buckets: Vec<Bucket> = Vec::new();
    let mut start = 0i64;
    let mut bytes = 0.0;
    for (i, (_, p)) in params.iter().enumerate() {
        let numel = p.numel() as i64;
        let size = numel as f64 * p.kind().elt_size_in_bytes() as f64;
        match buckets.last_mut() {
            Some(last) if bytes + size <= bucket_bytes || last.members.is_empty() => {
                last.members.push(i);
                last.len += numel;
                bytes += size;
            }
            _ => {
                buckets.push(Bucket { start, len: numel, members: vec![i] });
                bytes = size;
            }
        }
        start += numel;
    }
    buckets
}

/// The flat (name-ordered) offsets of `params`.
fn offsets(params: &[(String, Tensor)]) -> Vec<i64> {
    let mut offset = 0;
    params
        .iter()
        .map(|(_, p)| {
            let here = offset;
            offset += p.numel() as i64;
            here
        })
        .collect()
}

/// The bucket's gradients end to end (zeros where a parameter has none yet), padded to `padded`.
fn flatten_gradients(params: &[(String, Tensor)], bucket: &Bucket, padded: i64) -> Result<Tensor> {
    let mut parts = Vec::with_capacity(bucket.members.len() + 1);
    for &i in &bucket.members {
        let (_, p) = &params[i];
        let grad = p.grad();
        parts.push(if grad.defined() { grad.f_reshape([-1])? } else { p.f_zeros_like()?.f_reshape([-1])? });
    }
    if padded > bucket.len {
        let first = &params[bucket.members[0]].1;
        parts.push(Tensor::f_zeros([padded - bucket.len], (first.kind(), first.device()))?);
    }
    Ok(Tensor::f_cat(&parts, 0)?)
}

/// DDP's gradient averaging (ZeRO stage 0): every rank ends with the mean gradient.
pub struct GradientBuckets {
    params: Vec<(String, Tensor)>,
    buckets: Vec<Bucket>,
}

impl GradientBuckets {
    /// Buckets of about `bucket_mib` MiB over `params` (the optimizer's, in its order).
    pub fn new(params: Vec<(String, Tensor)>, bucket_mib: f64) -> Self {
        let buckets = make_buckets(&params, bucket_mib * MIB);
        Self { params, buckets }
    }

    /// Replaces every gradient by its mean over ranks.
    pub fn average(&self, pg: &ProcessGroup) -> Result<()> {
        tch::no_grad(|| -> Result<()> {
            let total = self.buckets.len();
            let mut pending: std::collections::VecDeque<(usize, Tensor, Pending)> = Default::default();
            for (b, bucket) in self.buckets.iter().enumerate() {
                if pending.len() == IN_FLIGHT {
                    let (done, flat, work) = pending.pop_front().expect("non-empty");
                    pg.wait(work)?;
                    self.scatter_back(done, &flat, pg.world_size)?;
                }
                let flat = flatten_gradients(&self.params, bucket, bucket.len)?;
                let work = pg.all_reduce_sum_start(&flat, &format!("gradient bucket {}/{total}", b + 1))?;
                pending.push_back((b, flat, work));
            }
            for (done, flat, work) in pending {
                pg.wait(work)?;
                self.scatter_back(done, &flat, pg.world_size)?;
            }
            Ok(())
        })
    }

    fn scatter_back(&self, bucket: usize, flat: &Tensor, world: usize) -> Result<()> {
        let flat = flat.f_div_scalar(world as f64)?;
        let mut offset = 0;
        for &i in &self.buckets[bucket].members {
            let (name, p) = &self.params[i];
            let numel = p.numel() as i64;
            let mut grad = p.grad();
            if !grad.defined() {
                return Err(Error::InvalidArgument {
                    name: "distributed".to_string(),
                    reason: format!(
                        "parameter `{name}` received no gradient: every trainable parameter must take part in the loss"
                    ),
                });
            }
            grad.f_copy_(&flat.f_narrow(0, offset, numel)?.f_view_as(&grad)?)?;
            offset += numel;
        }
        Ok(())
    }
}

/// One MiB.
const MIB: f64 = 1024.0 * 1024.0;

/// ZeRO-2 AdamW: this rank's slices of the reduced gradient, the moments and the fp32 master
/// weights; same arithmetic as [`crate::training::AdamW`], element for element.
pub struct ShardedAdamW {
    config: OptimConfig,
    params: Vec<(String, Tensor)>,
    buckets: Vec<Bucket>,
    rank: usize,
    world: usize,
    /// Where bucket b's owned slice starts in the local vectors.
    local_offsets: Vec<i64>,
    /// Each parameter's start in the flat parameter space.
    offsets: Vec<i64>,
    master: Tensor,
    exp_avg: Tensor,
    exp_avg_sq: Tensor,
    grad: Tensor,
    step: u64,
}

impl ShardedAdamW {
    /// Shards over `pg` the state for `params` (fp32 at this point: the masters start as their values).
    pub fn new(params: Vec<(String, Tensor)>, config: OptimConfig, bucket_mib: f64, pg: &ProcessGroup) -> Result<Self> {
        let buckets = make_buckets(&params, bucket_mib * MIB);
        let (rank, world) = (pg.rank, pg.world_size);
        let mut local_offsets = Vec::with_capacity(buckets.len());
        let mut local = 0;
        for bucket in &buckets {
            local_offsets.push(local);
            local += bucket.shard(world);
        }
        let device = params.first().map_or(tch::Device::Cpu, |(_, p)| p.device());
        let zeros = || Tensor::f_zeros([local], (Kind::Float, device));
        let flat_offsets = offsets(&params);
        let mut this = Self {
            config,
            params,
            buckets,
            rank,
            world,
            local_offsets,
            offsets: flat_offsets,
            master: zeros()?,
            exp_avg: zeros()?,
            exp_avg_sq: zeros()?,
            grad: zeros()?,
            step: 0,
        };
        this.master = this.owned_from_parameters()?;
        Ok(this)
    }

    /// `(flat start, length, local offset)` of every owned range (padding left out).
    fn owned_ranges(&self) -> Vec<(i64, i64, i64)> {
        self.buckets
            .iter()
            .zip(&self.local_offsets)
            .filter_map(|(bucket, &local)| {
                let shard = bucket.shard(self.world);
                let first = self.rank as i64 * shard;
                let len = shard.min(bucket.len - first);
                (len > 0).then_some((bucket.start + first, len, local))
            })
            .collect()
    }

    /// This rank's slices of the current parameter values, as fp32.
    fn owned_from_parameters(&self) -> Result<Tensor> {
        let offsets = &self.offsets;
        let out = self.master.f_zeros_like()?;
        for (start, len, local) in self.owned_ranges() {
            for (i, (_, p)) in self.params.iter().enumerate() {
                let (p_start, p_len) = (offsets[i], p.numel() as i64);
                let (a, b) = (start.max(p_start), (start + len).min(p_start + p_len));
                if a < b {
                    let values = p.f_reshape([-1])?.f_narrow(0, a - p_start, b - a)?.f_to_kind(Kind::Float)?;
                    out.f_narrow(0, local + a - start, b - a)?.f_copy_(&values)?;
                }
            }
        }
        Ok(out)
    }

    /// Zeroes the parameters' gradients (the full-size buffers backward accumulates into).
    pub fn zero_grad(&self) {
        for (_, p) in &self.params {
            let mut grad = p.grad();
            if grad.defined() {
                let _ = grad.zero_();
            }
        }
    }

    /// Reduce-scatters the gradients, clips on the global norm, updates this rank's slices and
    /// all-gathers the new weights. Returns the global gradient norm before clipping.
    pub fn step(&mut self, pg: &ProcessGroup, lr: f64) -> Result<f64> {
        tch::no_grad(|| -> Result<f64> {
            let total = self.buckets.len();
            let world = self.world as f64;
            let mut pending: std::collections::VecDeque<(usize, Tensor, Tensor, Pending)> = Default::default();
            let finish = |this: &Self, b: usize, out: &Tensor| -> Result<()> {
                let shard = this.buckets[b].shard(this.world);
                let mean = out.f_div_scalar(world)?.f_to_kind(Kind::Float)?;
                this.grad.f_narrow(0, this.local_offsets[b], shard)?.f_copy_(&mean)?;
                Ok(())
            };
            for (b, bucket) in self.buckets.iter().enumerate() {
                if pending.len() == IN_FLIGHT {
                    let (done, _input, out, work) = pending.pop_front().expect("non-empty");
                    pg.wait(work)?;
                    finish(self, done, &out)?;
                }
                let shard = bucket.shard(self.world);
                let input = flatten_gradients(&self.params, bucket, shard * self.world as i64)?;
                let out = Tensor::f_zeros([shard], (input.kind(), input.device()))?;
                let work = pg.reduce_scatter_sum_start(&out, &input, &format!("gradient bucket {}/{total}", b + 1))?;
                pending.push_back((b, input, out, work));
            }
            for (done, _input, out, work) in pending {
                pg.wait(work)?;
                finish(self, done, &out)?;
            }
            let local = self.grad.f_square()?.f_sum(Kind::Double)?.double_value(&[]);
            let norm = pg.sum_f64(local, "gradient norm")?.sqrt();
            let max_norm = self.config.max_grad_norm;
            if max_norm > 0.0 {
                // The same coefficient as `AdamW::clip_grad_norm`.
                let coef = (max_norm / (norm + 1e-6)).min(1.0);
                if coef < 1.0 {
                    let _ = self.grad.f_mul_scalar_(coef)?;
                }
            }
            self.step += 1;
            crate::training::adamw_update(
                &mut self.master,
                &self.grad,
                &mut self.exp_avg,
                &mut self.exp_avg_sq,
                lr,
                &self.config,
                self.step,
            )?;
            self.gather_parameters(pg)?;
            Ok(norm)
        })
    }

    /// Every rank's updated slices into every rank's parameters (up to [`IN_FLIGHT`] buckets
    /// gathering at once).
    fn gather_parameters(&self, pg: &ProcessGroup) -> Result<()> {
        let total = self.buckets.len();
        let offsets = &self.offsets;
        let copy_back = |b: usize, output: &Tensor| -> Result<()> {
            let bucket = &self.buckets[b];
            for &i in &bucket.members {
                let (_, p) = &self.params[i];
                let values = output.f_narrow(0, offsets[i] - bucket.start, p.numel() as i64)?;
                p.shallow_clone().f_copy_(&values.f_view_as(p)?)?;
            }
            Ok(())
        };
        let mut pending: std::collections::VecDeque<(usize, Tensor, Tensor, Pending)> = Default::default();
        for (b, bucket) in self.buckets.iter().enumerate() {
            if pending.len() == IN_FLIGHT {
                let (done, _input, output, work) = pending.pop_front().expect("non-empty");
                pg.wait(work)?;
                copy_back(done, &output)?;
            }
            let shard = bucket.shard(self.world);
            let kind = self.params[bucket.members[0]].1.kind();
            let input = self.master.f_narrow(0, self.local_offsets[b], shard)?.f_to_kind(kind)?;
            let output = Tensor::f_empty([shard * self.world as i64], (kind, input.device()))?;
            let work = pg.all_gather_start(&output, &input, &format!("weights bucket {}/{total}", b + 1))?;
            pending.push_back((b, input, output, work));
        }
        for (done, _input, output, work) in pending {
            pg.wait(work)?;
            copy_back(done, &output)?;
        }
        Ok(())
    }

    /// Optimizer steps taken.
    pub fn steps(&self) -> u64 {
        self.step
    }

    /// The full fp32 master weights, gathered from every rank (all ranks take part).
    pub fn gather_masters(&self, pg: &ProcessGroup) -> Result<Vec<(String, Tensor)>> {
        let total = self.buckets.len();
        let offsets = &self.offsets;
        let mut out = Vec::with_capacity(self.params.len());
        for (b, bucket) in self.buckets.iter().enumerate() {
            let shard = bucket.shard(self.world);
            let input = self.master.f_narrow(0, self.local_offsets[b], shard)?;
            let output = Tensor::f_zeros([shard * self.world as i64], (Kind::Float, input.device()))?;
            let work = pg.all_gather_start(&output, &input, &format!("master weights bucket {}/{total}", b + 1))?;
            pg.wait(work)?;
            for &i in &bucket.members {
                let (name, p) = &self.params[i];
                let values =
                    output.f_narrow(0, offsets[i] - bucket.start, p.numel() as i64)?.f_view(p.size().as_slice())?;
                out.push((name.clone(), values.f_to_device(tch::Device::Cpu)?));
            }
        }
        Ok(out)
    }

    /// Writes this rank's shard (`optimizer-rank-R-of-N.safetensors` in `dir`); returns its size
    /// and digest.
    pub fn save(&self, dir: &Path) -> Result<crate::weights::WrittenFile> {
        let ranges = self.owned_ranges();
        let path = dir.join(format!("{SHARD_PREFIX}{:05}-of-{:05}.safetensors", self.rank, self.world));
        let flat: Vec<i64> = ranges.iter().flat_map(|&(s, l, o)| [s, l, o]).collect();
        let cpu = |t: &Tensor| t.f_to_device(tch::Device::Cpu);
        let named = [
            ("ranges", Tensor::from_slice(&flat).f_view([-1, 3])?),
            ("exp_avg", cpu(&self.exp_avg)?),
            ("exp_avg_sq", cpu(&self.exp_avg_sq)?),
            ("master", cpu(&self.master)?),
            ("step", Tensor::from_slice(&[self.step as i64])),
        ];
        crate::weights::write_safetensors(&path, &named.map(|(n, t)| (n.to_string(), t)))
    }

    /// Loads this rank's slices from a checkpoint of any world size and stage, and sets every
    /// parameter from the loaded masters when `with_params` (LoRA runs) — else from its current
    /// (just loaded) value.
    pub fn load(&mut self, dir: &Path, pg: &ProcessGroup, with_params: bool) -> Result<()> {
        let state = FlatState::open(dir, &self.params)?;
        let device = self.master.device();
        for (start, len, local) in self.owned_ranges() {
            for (name, target) in [("exp_avg", &self.exp_avg), ("exp_avg_sq", &self.exp_avg_sq)] {
                target.f_narrow(0, local, len)?.f_copy_(&state.read(name, start, len)?.f_to_device(device)?)?;
            }
            if with_params || state.has_masters() {
                self.master
                    .f_narrow(0, local, len)?
                    .f_copy_(&state.read("master", start, len)?.f_to_device(device)?)?;
            }
        }
        if !(with_params || state.has_masters()) {
            self.master = self.owned_from_parameters()?;
        }
        self.step = state.step;
        tch::no_grad(|| self.gather_parameters(pg))
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
            let offsets = offsets(params);
            let masters = params.iter().all(|(name, _)| tensors.contains_key(&format!("param.{name}")));
            let mut pieces = Vec::new();
            for (i, (name, p)) in params.iter().enumerate() {
                let mut map = BTreeMap::new();
                for (key, file_key) in [
                    ("exp_avg", format!("exp_avg.{name}")),
                    ("exp_avg_sq", format!("exp_avg_sq.{name}")),
                    ("master", format!("param.{name}")),
                ] {
                    match tensors.get(&file_key) {
                        Some(t) => {
                            crate::weights::check_shape(&file_key, t, &p.size())?;
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
                pieces.push((offsets[i], p.numel() as i64, map));
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

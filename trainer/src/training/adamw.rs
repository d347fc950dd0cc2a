//! AdamW with saveable state: PyTorch's `torch.optim.AdamW` with gradient-norm clipping and fp32
//! master weights for mixed precision, over flat buckets of parameters
//! ([`crate::distributed::FlatLayout`]): one process, data parallel (every rank updates every
//! bucket after the gradients are averaged) or ZeRO-2 (each rank its 1/N of every bucket, then
//! the weights are all-gathered). The same update in all three, element for element.
//!
//! The parameters and their gradients are views into one tensor per bucket (bound at the first
//! [`AdamW::zero_grad`], once the model has its final dtype), so clipping and the update run a
//! handful of element-wise kernels per bucket rather than per tensor, and the global gradient
//! norm costs one host synchronization per step. The update keeps PyTorch's unfused arithmetic
//! (`torch._fused_adamw_` rounds differently: fewer, fused operations), so its values do not
//! depend on how parameters are grouped.

use std::path::Path;

use tch::{Kind, Tensor, nn};

use super::OptimConfig;
use crate::distributed::{FlatLayout, FlatState, GradientExchange, ProcessGroup, SHARD_PREFIX, ffi};
use crate::error::{Error, Result};

/// The flat buckets the parameters and gradients are views into.
struct Bound {
    /// Per bucket: the parameters end to end (padded).
    params: Vec<Tensor>,
    /// Per bucket: their gradients.
    grads: Vec<Tensor>,
    /// Under ZeRO-2 with low-precision gradients: this rank's reduced slices in fp32 (local
    /// space), what clipping and the update read.
    grads32: Option<Tensor>,
}

/// AdamW over flat buckets (see the module docs), with its moments (and master weights) in the
/// layout's local space: every bucket end to end when replicated, this rank's slices under ZeRO-2.
pub struct AdamW {
    config: OptimConfig,
    params: Vec<(String, Tensor)>,
    layout: FlatLayout,
    exp_avg: Tensor,
    exp_avg_sq: Tensor,
    /// fp32 master weights: when the parameters are kept in a lower precision, and always under
    /// ZeRO-2 (where they are this rank's slices).
    master: Option<Tensor>,
    bound: Option<Bound>,
    /// The collectives, with several ranks.
    exchange: Option<GradientExchange>,
    step: u64,
}

impl AdamW {
    /// Optimizes every trainable variable of `vs` in one process (buckets of 25 MiB).
    pub fn new(vs: &nn::VarStore, config: OptimConfig) -> Result<Self> {
        let params = trainable_parameters(vs);
        let layout = FlatLayout::new(&params, |_| 0, DEFAULT_BUCKET_MIB, 0, 1, false);
        Self::with_layout(params, config, layout, None)
    }

    /// Optimizes `params` (name-ordered, still fp32) laid out by `layout`; with several ranks
    /// `exchange` carries the collectives. Under ZeRO-2 the masters start as the parameters.
    pub fn with_layout(
        params: Vec<(String, Tensor)>,
        config: OptimConfig,
        layout: FlatLayout,
        exchange: Option<GradientExchange>,
    ) -> Result<Self> {
        let device = params.first().map_or(tch::Device::Cpu, |(_, p)| p.device());
        let zeros = || Tensor::f_zeros([layout.local_len()], (Kind::Float, device));
        let mut this = Self {
            config,
            exp_avg: zeros()?,
            exp_avg_sq: zeros()?,
            master: None,
            bound: None,
            exchange,
            step: 0,
            params,
            layout,
        };
        if this.layout.sharded() {
            this.master = Some(this.owned_parameters()?);
        }
        Ok(this)
    }

    /// This rank's owned parts of the parameters' current values, as fp32 in the local space.
    fn owned_parameters(&self) -> Result<Tensor> {
        let device = self.exp_avg.device();
        let out = Tensor::f_zeros([self.layout.local_len()], (Kind::Float, device))?;
        let offsets = name_offsets(&self.params);
        tch::no_grad(|| -> Result<()> {
            for (start, len, local) in self.layout.owned_ranges() {
                let i = offsets.partition_point(|&o| o <= start) - 1;
                let p = &self.params[i].1;
                let values = p.f_reshape([-1])?.f_narrow(0, start - offsets[i], len)?.f_to_kind(Kind::Float)?;
                out.f_narrow(0, local, len)?.f_copy_(&values)?;
            }
            Ok(())
        })?;
        Ok(out)
    }

    /// Keeps fp32 master copies of the parameters, which must still be fp32: call before the
    /// model is cast to a lower precision (ZeRO-2 keeps its slices' masters always).
    pub fn keep_master_weights(&mut self) -> Result<()> {
        if let Some((name, p)) = self.params.iter().find(|(_, p)| p.kind() != Kind::Float) {
            return Err(Error::InvalidArgument {
                name: "precision".to_string(),
                reason: format!("master weights are taken from fp32 parameters; {name} is {:?}", p.kind()),
            });
        }
        if self.master.is_none() {
            self.master = Some(self.owned_parameters()?);
        }
        Ok(())
    }

    /// The fp32 master weights by variable name, when kept (every rank takes part under ZeRO-2,
    /// which gathers them: `pg` is required there).
    pub fn master_weights(&self, pg: Option<&ProcessGroup>) -> Result<Option<Vec<(String, Tensor)>>> {
        let Some(master) = &self.master else { return Ok(None) };
        if !self.layout.sharded() {
            let named = self
                .params
                .iter()
                .enumerate()
                .map(|(i, (name, p))| Ok((name.clone(), self.local_view(master, i)?.f_view(p.size().as_slice())?)))
                .collect::<Result<_>>()?;
            return Ok(Some(named));
        }
        let pg = pg.expect("ZeRO-2 runs have a process group");
        let (_, world) = self.layout.world();
        let total = self.layout.bucket_count();
        let mut gathered: Vec<Option<Tensor>> = (0..self.params.len()).map(|_| None).collect();
        tch::no_grad(|| -> Result<()> {
            for b in 0..total {
                let (_, shard) = self.layout.owned(b);
                let input = master.f_narrow(0, self.layout.local_offset(b), shard)?;
                let output = Tensor::f_zeros([shard * world as i64], (Kind::Float, input.device()))?;
                let work = pg.all_gather_start(&output, &input, &format!("master weights bucket {}/{total}", b + 1))?;
                pg.wait(work)?;
                for (i, slot) in gathered.iter_mut().enumerate() {
                    let (bucket, at) = self.layout.place(i);
                    if bucket == b {
                        let p = &self.params[i].1;
                        let values = output.f_narrow(0, at, p.numel() as i64)?.f_view(p.size().as_slice())?;
                        *slot = Some(values.f_to_device(tch::Device::Cpu)?);
                    }
                }
            }
            Ok(())
        })?;
        Ok(Some(
            self.params.iter().zip(gathered).map(|((name, _), t)| (name.clone(), t.expect("every bucket"))).collect(),
        ))
    }

    /// Parameter `i`'s elements in a local-space tensor (replicated layouts only).
    fn local_view(&self, local: &Tensor, i: usize) -> Result<Tensor> {
        let (b, at) = self.layout.place(i);
        Ok(local.f_narrow(0, self.layout.local_offset(b) + at, self.params[i].1.numel() as i64)?)
    }

    /// Whether every parameter and gradient is still the view of its bucket set up by
    /// [`Self::bind`] (a cast of the model, say to bf16, gives the parameters new storage).
    fn is_bound(&self) -> bool {
        let Some(bound) = &self.bound else { return false };
        self.params.iter().enumerate().all(|(i, (_, p))| {
            let (b, at) = self.layout.place(i);
            let offset = at as usize * p.kind().elt_size_in_bytes();
            let at_bucket = |flat: &Tensor, t: &Tensor| {
                t.defined() && t.kind() == flat.kind() && t.data_ptr() as usize == flat.data_ptr() as usize + offset
            };
            at_bucket(&bound.params[b], p) && at_bucket(&bound.grads[b], &p.grad())
        })
    }

    /// Makes every parameter and its gradient a view into its bucket's flat tensors (values
    /// kept), unless they already are.
    fn bind(&mut self) -> Result<()> {
        if self.is_bound() || self.params.is_empty() {
            return Ok(());
        }
        let (kind, device) = (self.params[0].1.kind(), self.params[0].1.device());
        let buckets = self.layout.bucket_count();
        let mut params = Vec::with_capacity(buckets);
        let mut grads = Vec::with_capacity(buckets);
        for b in 0..buckets {
            params.push(Tensor::f_zeros([self.layout.padded_len(b)], (kind, device))?);
            grads.push(Tensor::f_zeros([self.layout.padded_len(b)], (kind, device))?);
        }
        tch::no_grad(|| -> Result<()> {
            for (i, (name, p)) in self.params.iter().enumerate() {
                if p.kind() != kind || p.device() != device {
                    return Err(Error::InvalidArgument {
                        name: "optimizer".to_string(),
                        reason: format!(
                            "`{name}` is {:?} on {:?}, the others {kind:?} on {device:?}",
                            p.kind(),
                            p.device()
                        ),
                    });
                }
                let (b, at) = self.layout.place(i);
                let (size, numel) = (p.size(), p.numel() as i64);
                params[b].f_narrow(0, at, numel)?.f_copy_(&p.f_reshape([-1])?)?;
                let grad = grads[b].f_narrow(0, at, numel)?.f_view(size.as_slice())?;
                let old = p.grad();
                if old.defined() {
                    grad.shallow_clone().f_copy_(&old)?;
                }
                let _ = p.shallow_clone().f_set_source_tensor_storage_offset_(
                    &params[b],
                    at,
                    &size,
                    contiguous_strides(&size),
                )?;
                ffi::set_grad(p, &grad).map_err(|e| Error::InvalidArgument {
                    name: "optimizer".to_string(),
                    reason: format!("`{name}`: {e}"),
                })?;
            }
            Ok(())
        })?;
        let grads32 = if self.layout.sharded() && kind != Kind::Float {
            Some(Tensor::f_zeros([self.layout.local_len()], (Kind::Float, device))?)
        } else {
            None
        };
        self.bound = Some(Bound { params, grads, grads32 });
        Ok(())
    }

    /// Zeroes every gradient (the flat buckets; binds them first, see the module docs).
    pub fn zero_grad(&mut self) -> Result<()> {
        self.bind()?;
        let bound = self.bound.as_ref().expect("bound above");
        for grad in &bound.grads {
            let _ = grad.shallow_clone().f_zero_()?;
        }
        Ok(())
    }

    /// Called by the backward after each of its stages: starts the reduction of every bucket
    /// whose gradients are now final (nothing with one process).
    pub fn backward_stage_done(&mut self, stage: usize, pg: Option<&ProcessGroup>) -> Result<()> {
        if let (Some(exchange), Some(pg), Some(bound)) = (self.exchange.as_mut(), pg, self.bound.as_ref()) {
            tch::no_grad(|| exchange.start_ready(&self.layout, &bound.grads, stage, pg))?;
        }
        Ok(())
    }

    /// The gradients over ranks (waiting for each bucket's reduction when it is needed; buckets
    /// no backward stage started are reduced now), clipping to a global norm of `max_norm` (0:
    /// none), the update with learning rate `lr` and, under ZeRO-2, the weights gathered.
    /// Returns the global gradient norm before clipping.
    pub fn step(&mut self, lr: f64, max_norm: f64, pg: Option<&ProcessGroup>) -> Result<f64> {
        self.bind()?;
        self.step += 1;
        tch::no_grad(|| -> Result<f64> {
            let norm = self.reduce(pg)?;
            // PyTorch's `clip_grad_norm_` coefficient.
            let coef = (max_norm > 0.0).then(|| (max_norm / (norm + 1e-6)).min(1.0)).filter(|&c| c < 1.0);
            let bound = self.bound.as_ref().expect("bound above");
            let sharded = self.layout.sharded();
            for b in 0..self.layout.bucket_count() {
                let (offset, len) = self.layout.owned(b);
                let local = self.layout.local_offset(b);
                let grad = self.gradient32(bound, b)?;
                if let Some(coef) = coef {
                    let _ = grad.shallow_clone().f_mul_scalar_(coef)?;
                }
                let mut exp_avg = self.exp_avg.f_narrow(0, local, len)?;
                let mut exp_avg_sq = self.exp_avg_sq.f_narrow(0, local, len)?;
                let param = bound.params[b].f_narrow(0, offset, len)?;
                match &self.master {
                    Some(master) => {
                        let mut master = master.f_narrow(0, local, len)?;
                        update(&mut master, &grad, &mut exp_avg, &mut exp_avg_sq, lr, &self.config, self.step)?;
                        param.shallow_clone().f_copy_(&master)?;
                    }
                    None => {
                        let mut param = param;
                        update(&mut param, &grad, &mut exp_avg, &mut exp_avg_sq, lr, &self.config, self.step)?;
                    }
                }
                if sharded && let (Some(exchange), Some(pg)) = (self.exchange.as_mut(), pg) {
                    // Goes out while the next buckets update.
                    exchange.start_gather(&self.layout, &bound.params[b], b, pg)?;
                }
            }
            if let (Some(exchange), Some(pg)) = (self.exchange.as_mut(), pg) {
                exchange.finish_gathers(pg)?;
                exchange.reset();
            }
            Ok(norm)
        })
    }

    /// Finishes every bucket's reduction and returns the global gradient norm: the owned parts
    /// divided by the world size (the mean), each one's sum of squares summed on the device
    /// (and over ranks under ZeRO-2), read once on the host.
    fn reduce(&mut self, pg: Option<&ProcessGroup>) -> Result<f64> {
        let bound = self.bound.as_ref().expect("bound");
        let (_, world) = self.layout.world();
        let buckets = self.layout.bucket_count();
        if let (Some(exchange), Some(pg)) = (self.exchange.as_mut(), pg) {
            exchange.start_ready(&self.layout, &bound.grads, usize::MAX, pg)?;
        }
        let mut squares = Vec::with_capacity(buckets);
        for b in 0..buckets {
            if let (Some(exchange), Some(pg)) = (self.exchange.as_mut(), pg) {
                // The last replicated bucket is waited for on the host: a stalled peer fails here.
                exchange.finish_reduction(b, b + 1 == buckets && !self.layout.sharded(), pg)?;
            }
            let (offset, len) = self.layout.owned(b);
            let owned = bound.grads[b].f_narrow(0, offset, len)?;
            if world > 1 {
                let _ = owned.shallow_clone().f_div_scalar_(world as f64)?;
            }
            if let Some(grads32) = &bound.grads32 {
                grads32.f_narrow(0, self.layout.local_offset(b), len)?.f_copy_(&owned)?;
            }
            squares.push(self.gradient32(bound, b)?.f_square()?.f_sum(Kind::Double)?);
        }
        let device = self.exp_avg.device();
        let total = if squares.is_empty() {
            Tensor::f_zeros([1], (Kind::Double, device))?
        } else {
            Tensor::f_stack(&squares, 0)?.f_sum(Kind::Double)?.f_reshape([1])?
        };
        if self.layout.sharded() {
            pg.expect("ZeRO-2 runs have a process group").all_reduce_sum(&total, "gradient norm")?;
        }
        Ok(total.double_value(&[0]).sqrt())
    }

    /// Bucket `b`'s owned gradient in fp32: the bucket's own slice when the gradients are fp32,
    /// the fp32 copy under ZeRO-2, else a fresh fp32 copy.
    fn gradient32(&self, bound: &Bound, b: usize) -> Result<Tensor> {
        let (offset, len) = self.layout.owned(b);
        Ok(match &bound.grads32 {
            Some(grads32) => grads32.f_narrow(0, self.layout.local_offset(b), len)?,
            None => bound.grads[b].f_narrow(0, offset, len)?.f_to_kind(Kind::Float)?,
        })
    }

    /// Optimizer steps taken.
    pub fn steps(&self) -> u64 {
        self.step
    }

    /// Writes the optimizer state into checkpoint folder `dir`: `optimizer.safetensors` with the
    /// moments and the step count per parameter, and with `with_params` the parameters' own
    /// fp32 values (`param.{name}`; the master copies in mixed precision), for runs whose
    /// parameters are saved nowhere else exactly (LoRA adapters), written by rank 0 when every
    /// rank holds the whole state; under ZeRO-2 every rank's slices with the ranges they cover
    /// (`optimizer-rank-R-of-N.safetensors`, masters always). Returns the file this rank wrote,
    /// with its size and digest (None where it writes none).
    pub fn save(&self, dir: &Path, with_params: bool) -> Result<Option<crate::models::weights::WrittenFile>> {
        let (rank, world) = self.layout.world();
        let (path, named) = if self.layout.sharded() {
            let flat: Vec<i64> = self.layout.owned_ranges().iter().flat_map(|&(s, l, o)| [s, l, o]).collect();
            let cpu = |t: &Tensor| t.f_to_device(tch::Device::Cpu);
            let master = self.master.as_ref().expect("ZeRO-2 keeps master weights");
            let named = vec![
                ("ranges".to_string(), Tensor::from_slice(&flat).f_view([-1, 3])?),
                ("exp_avg".to_string(), cpu(&self.exp_avg)?),
                ("exp_avg_sq".to_string(), cpu(&self.exp_avg_sq)?),
                ("master".to_string(), cpu(master)?),
                ("step".to_string(), Tensor::from_slice(&[self.step as i64])),
            ];
            (dir.join(format!("{SHARD_PREFIX}{rank:05}-of-{world:05}.safetensors")), named)
        } else if rank == 0 {
            let mut named: Vec<(String, Tensor)> = Vec::new();
            for (i, (name, param)) in self.params.iter().enumerate() {
                let size = param.size();
                named.push((format!("exp_avg.{name}"), self.local_view(&self.exp_avg, i)?.f_view(size.as_slice())?));
                named.push((
                    format!("exp_avg_sq.{name}"),
                    self.local_view(&self.exp_avg_sq, i)?.f_view(size.as_slice())?,
                ));
                if with_params {
                    let value = match &self.master {
                        Some(master) => self.local_view(master, i)?.f_view(size.as_slice())?,
                        None => param.f_to_kind(Kind::Float)?.f_detach()?,
                    };
                    named.push((format!("param.{name}"), value));
                }
            }
            named.push(("step".to_string(), Tensor::from_slice(&[self.step as i64])));
            (dir.join("optimizer.safetensors"), named)
        } else {
            return Ok(None);
        };
        Ok(Some(crate::models::weights::write_safetensors(&path, &named)?))
    }

    /// Loads the state of checkpoint `dir`, written by either layout at any world size. With
    /// `with_params` (LoRA runs) the parameters take the saved fp32 values; under ZeRO-2 the
    /// masters are read (or, from a checkpoint without them, taken from the just loaded
    /// parameters) and every parameter is set from them, all ranks taking part.
    pub fn load(&mut self, dir: &Path, with_params: bool, pg: Option<&ProcessGroup>) -> Result<()> {
        let state = FlatState::open(dir, &self.params)?;
        if with_params && !state.has_masters() {
            return Err(Error::InvalidInput {
                path: dir.to_path_buf(),
                what: "optimizer state".to_string(),
                reason: "holds no parameter values (`param.NAME`), which a LoRA run resumes its adapters from"
                    .to_string(),
            });
        }
        let device = self.exp_avg.device();
        let sharded = self.layout.sharded();
        let read_masters = sharded && (with_params || state.has_masters());
        tch::no_grad(|| -> Result<()> {
            for (start, len, local) in self.layout.owned_ranges() {
                for (name, target) in [("exp_avg", &self.exp_avg), ("exp_avg_sq", &self.exp_avg_sq)] {
                    target.f_narrow(0, local, len)?.f_copy_(&state.read(name, start, len)?.f_to_device(device)?)?;
                }
                if read_masters && let Some(master) = &self.master {
                    master.f_narrow(0, local, len)?.f_copy_(&state.read("master", start, len)?.f_to_device(device)?)?;
                }
            }
            if with_params && !sharded {
                let mut offset = 0;
                for (_, p) in &self.params {
                    let numel = p.numel() as i64;
                    let value = state.read("master", offset, numel)?.f_view(p.size().as_slice())?;
                    p.shallow_clone().f_copy_(&value.f_to_device(p.device())?)?;
                    offset += numel;
                }
            }
            Ok(())
        })?;
        self.step = state.step;
        if sharded {
            if !read_masters {
                self.master = Some(self.owned_parameters()?);
            }
            let pg = pg.expect("ZeRO-2 runs have a process group");
            self.bind()?;
            let bound = self.bound.as_ref().expect("bound above");
            let master = self.master.as_ref().expect("ZeRO-2 keeps master weights");
            let exchange = self.exchange.as_mut().expect("ZeRO-2 runs exchange");
            tch::no_grad(|| -> Result<()> {
                for b in 0..self.layout.bucket_count() {
                    let (offset, len) = self.layout.owned(b);
                    let values = master.f_narrow(0, self.layout.local_offset(b), len)?;
                    bound.params[b].f_narrow(0, offset, len)?.f_copy_(&values)?;
                    exchange.start_gather(&self.layout, &bound.params[b], b, pg)?;
                }
                exchange.finish_gathers(pg)
            })?;
        }
        Ok(())
    }
}

/// Bucket size of a one-process [`AdamW::new`] (PyTorch DDP's default).
pub const DEFAULT_BUCKET_MIB: f64 = 25.0;

/// Row-major strides of a tensor of `size`.
fn contiguous_strides(size: &[i64]) -> Vec<i64> {
    let mut strides = vec![1; size.len()];
    for d in (0..size.len().saturating_sub(1)).rev() {
        strides[d] = strides[d + 1] * size[d + 1].max(1);
    }
    strides
}

/// Each parameter's start in the name-ordered flat space.
fn name_offsets(params: &[(String, Tensor)]) -> Vec<i64> {
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

/// The parameters of `vs` that train, sorted by name: the order of the optimizer's parameter
/// list and of the name-ordered flat space checkpoints address.
pub(crate) fn trainable_parameters(vs: &nn::VarStore) -> Vec<(String, Tensor)> {
    let mut params: Vec<(String, Tensor)> = vs.variables().into_iter().filter(|(_, t)| t.requires_grad()).collect();
    params.sort_by(|a, b| a.0.cmp(&b.0));
    params
}

/// One AdamW update (PyTorch's `torch.optim.AdamW` formula, unfused) of `p` at optimizer step
/// `step` (1-based), in place, element-wise: values do not depend on how elements are grouped.
pub(crate) fn update(
    p: &mut Tensor,
    grad: &Tensor,
    exp_avg: &mut Tensor,
    exp_avg_sq: &mut Tensor,
    lr: f64,
    c: &OptimConfig,
    step: u64,
) -> Result<()> {
    let bias1 = 1.0 - c.beta1.powi(step as i32);
    let bias2 = 1.0 - c.beta2.powi(step as i32);
    let _ = p.f_mul_scalar_(1.0 - lr * c.weight_decay)?;
    let _ = exp_avg.f_mul_scalar_(c.beta1)?.f_add_(&grad.f_mul_scalar(1.0 - c.beta1)?)?;
    let _ = exp_avg_sq.f_mul_scalar_(c.beta2)?.f_add_(&grad.f_square()?.f_mul_scalar(1.0 - c.beta2)?)?;
    let denom = exp_avg_sq.f_sqrt()?.f_div_scalar(bias2.sqrt())?.f_add_scalar(c.eps)?;
    let _ = p.f_sub_(&exp_avg.f_div(&denom)?.f_mul_scalar(lr / bias1)?)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use tch::Device;

    use super::*;

    /// A var store with trainable variables `a` `[4, 3]`, `b` `[5]` and `c` `[2, 2]` holding
    /// `values` (12 + 5 + 4 = 21 elements), and those variables.
    fn store(values: &Tensor) -> (nn::VarStore, Vec<Tensor>) {
        let vs = nn::VarStore::new(Device::Cpu);
        let root = vs.root();
        let a = root.var_copy("a", &values.narrow(0, 0, 12).view([4, 3]));
        let b = root.var_copy("b", &values.narrow(0, 12, 5));
        let c = root.var_copy("c", &values.narrow(0, 17, 4).view([2, 2]));
        (vs, vec![a, b, c])
    }

    /// PyTorch's `clip_grad_norm_` then `torch.optim.AdamW`, tensor by tensor: the reference.
    fn reference_step(params: &[Tensor], moments: &mut [(Tensor, Tensor)], c: &OptimConfig, lr: f64, step: u64) -> f64 {
        let total: f64 = params.iter().map(|p| p.grad().square().sum(Kind::Double).double_value(&[])).sum();
        let norm = total.sqrt();
        let coef = (c.max_grad_norm / (norm + 1e-6)).min(1.0);
        tch::no_grad(|| {
            for (p, (m, v)) in params.iter().zip(moments.iter_mut()) {
                let mut grad = p.grad();
                if coef < 1.0 {
                    let _ = grad.f_mul_scalar_(coef).unwrap();
                }
                update(&mut p.shallow_clone(), &grad, m, v, lr, c, step).unwrap();
            }
        });
        norm
    }

    /// Flat buckets (one bucket, and buckets cutting between the tensors) give the per-tensor
    /// reference's weights bit for bit, with clipping active, over several steps.
    #[test]
    fn flat_buckets_update_as_the_per_tensor_reference() {
        tch::manual_seed(3);
        let init = Tensor::randn([21], (Kind::Float, Device::Cpu));
        let config = OptimConfig { weight_decay: 0.01, max_grad_norm: 0.5, ..OptimConfig::default() };
        // 4-byte elements: 48 bytes hold `a` alone, so `b` and `c` share the second bucket.
        for bucket_mib in [DEFAULT_BUCKET_MIB, 48.0 / (1024.0 * 1024.0)] {
            let (reference_vs, reference) = store(&init);
            let mut moments: Vec<(Tensor, Tensor)> =
                reference.iter().map(|p| (p.zeros_like(), p.zeros_like())).collect();
            let (flat_vs, flat) = store(&init);
            let params = trainable_parameters(&flat_vs);
            let layout = FlatLayout::new(&params, |_| 0, bucket_mib, 0, 1, false);
            let buckets = layout.bucket_count();
            let mut optimizer = AdamW::with_layout(params, config.clone(), layout, None).unwrap();
            for step in 1..=3 {
                optimizer.zero_grad().unwrap();
                for p in &reference {
                    let mut g = p.grad();
                    if g.defined() {
                        let _ = g.zero_();
                    }
                }
                let target = Tensor::randn([21], (Kind::Float, Device::Cpu)) * 3.0;
                let loss = |w: &[Tensor]| {
                    let all = Tensor::cat(&[w[0].view([-1]), w[1].view([-1]), w[2].view([-1])], 0);
                    (all - &target).square().sum(Kind::Float)
                };
                loss(&flat).backward();
                loss(&reference).backward();
                let norm = optimizer.step(1e-2, config.max_grad_norm, None).unwrap();
                let expected = reference_step(&reference, &mut moments, &config, 1e-2, step);
                assert!(expected > config.max_grad_norm, "the test must clip");
                assert!((norm - expected).abs() <= 1e-12 * expected, "step {step}: norm {norm} vs {expected}");
                for (f, r) in flat.iter().zip(&reference) {
                    assert!(f.equal(r), "{buckets} bucket(s), step {step}: weights differ");
                }
            }
            drop(reference_vs);
        }
    }

    /// Mixed precision updates the fp32 master exactly as fp32 AdamW would with the same
    /// (bf16-rounded) gradients, and the bf16 parameter is the master rounded.
    #[test]
    fn adamw_master_weights_follow_the_fp32_update() {
        tch::manual_seed(3);
        let init = Tensor::randn([21], (Kind::Float, Device::Cpu));
        let config = OptimConfig { weight_decay: 0.01, ..OptimConfig::default() };
        let (reference_vs, reference) = store(&init);
        let mut reference_optimizer = AdamW::new(&reference_vs, config.clone()).unwrap();
        let (mut mixed_vs, mixed) = store(&init);
        let mut mixed_optimizer = AdamW::new(&mixed_vs, config).unwrap();
        mixed_optimizer.keep_master_weights().unwrap();
        mixed_vs.set_kind(Kind::BFloat16);
        assert_eq!(mixed[0].kind(), Kind::BFloat16);
        for step in 0..3 {
            reference_optimizer.zero_grad().unwrap();
            mixed_optimizer.zero_grad().unwrap();
            let target = Tensor::randn([21], (Kind::Float, Device::Cpu));
            // The same loss; the reference sees the gradient the bf16 parameters receive.
            let flat = |w: &[Tensor]| Tensor::cat(&[w[0].view([-1]), w[1].view([-1]), w[2].view([-1])], 0);
            flat(&mixed).to_kind(Kind::Float).f_sub(&target).unwrap().square().sum(Kind::Float).backward();
            // d/dw Σ w·g = g: the reference's gradient is the mixed one, exactly.
            for (r, m) in reference.iter().zip(&mixed) {
                r.f_mul(&m.grad().to_kind(Kind::Float)).unwrap().sum(Kind::Float).backward();
            }
            reference_optimizer.step(1e-2, 0.0, None).unwrap();
            mixed_optimizer.step(1e-2, 0.0, None).unwrap();
            let masters = mixed_optimizer.master_weights(None).unwrap().unwrap();
            for ((name, master), (r, m)) in masters.iter().zip(reference.iter().zip(&mixed)) {
                assert!(master.equal(r), "step {step}: master {name} differs from the fp32 update");
                assert!(m.equal(&r.to_kind(Kind::BFloat16)), "step {step}: {name} is not the rounded master");
            }
        }
    }

    #[test]
    fn master_weights_must_come_from_fp32_parameters() {
        let (mut vs, _) = store(&Tensor::zeros([21], (Kind::Float, Device::Cpu)));
        vs.set_kind(Kind::BFloat16);
        let mut optimizer = AdamW::new(&vs, OptimConfig::default()).unwrap();
        assert!(optimizer.keep_master_weights().is_err());
    }

    /// After binding, the parameters and their gradients are views into the buckets: the
    /// backward's gradients land there, and the update changes what the model reads.
    #[test]
    fn parameters_and_gradients_are_bucket_views() {
        let (vs, params) = store(&Tensor::ones([21], (Kind::Float, Device::Cpu)));
        let mut optimizer = AdamW::new(&vs, OptimConfig::default()).unwrap();
        optimizer.zero_grad().unwrap();
        assert!(optimizer.is_bound());
        (&params[1] * 2.0).sum(Kind::Float).backward();
        let bound = optimizer.bound.as_ref().unwrap();
        let (b, at) = optimizer.layout.place(1);
        assert!(bound.grads[b].narrow(0, at, 5).equal(&Tensor::full([5], 2.0, (Kind::Float, Device::Cpu))));
        let _ = tch::no_grad(|| bound.params[b].narrow(0, at, 5).fill_(7.0));
        assert_eq!(params[1].double_value(&[0]), 7.0);
    }
}

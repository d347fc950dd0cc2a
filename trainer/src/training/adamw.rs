//! AdamW with saveable state: PyTorch's `torch.optim.AdamW`, with fp32 master weights for mixed
//! precision and gradient-norm clipping.

use std::collections::BTreeMap;
use std::path::Path;

use tch::{Kind, Tensor, nn};

use super::OptimConfig;
use crate::error::{Error, Result};
use crate::weights;

/// PyTorch's `torch.optim.AdamW` (decoupled weight decay, bias correction), with its moments in
/// tensors that checkpoints save and load. For mixed precision it keeps fp32 master weights:
/// updates apply to them (with fp32 gradients and moments) and are copied, rounded, into the
/// low-precision parameters.
pub struct AdamW {
    config: OptimConfig,
    params: Vec<(String, Tensor)>,
    exp_avg: Vec<Tensor>,
    exp_avg_sq: Vec<Tensor>,
    step: u64,
    /// fp32 master copies of `params` when those are kept in lower precision.
    master: Option<Vec<Tensor>>,
}

impl AdamW {
    /// Optimizes every trainable variable of `vs`.
    pub fn new(vs: &nn::VarStore, config: OptimConfig) -> Self {
        let params = trainable_parameters(vs);
        let zeros = |p: &Tensor| p.zeros_like();
        let exp_avg = params.iter().map(|(_, p)| zeros(p)).collect();
        let exp_avg_sq = params.iter().map(|(_, p)| zeros(p)).collect();
        Self { config, params, exp_avg, exp_avg_sq, step: 0, master: None }
    }

    /// Keeps fp32 master copies of the parameters, which must still be fp32: call before the
    /// model is cast to a lower precision.
    pub fn keep_master_weights(&mut self) -> Result<()> {
        if let Some((name, p)) = self.params.iter().find(|(_, p)| p.kind() != Kind::Float) {
            return Err(Error::InvalidArgument {
                name: "precision".to_string(),
                reason: format!("master weights are taken from fp32 parameters; {name} is {:?}", p.kind()),
            });
        }
        self.master = Some(tch::no_grad(|| self.params.iter().map(|(_, p)| p.detach().copy()).collect()));
        Ok(())
    }

    /// The fp32 master weights by variable name, when kept.
    pub fn master_weights(&self) -> Option<Vec<(String, Tensor)>> {
        let master = self.master.as_ref()?;
        Some(self.params.iter().zip(master).map(|((name, _), m)| (name.clone(), m.shallow_clone())).collect())
    }

    /// Zeroes every gradient.
    pub fn zero_grad(&self) {
        for (_, p) in &self.params {
            let mut grad = p.grad();
            if grad.defined() {
                let _ = grad.zero_();
            }
        }
    }

    /// Scales gradients so their global L2 norm is at most `max_norm` (PyTorch's
    /// `clip_grad_norm_`); returns the norm before clipping.
    pub fn clip_grad_norm(&self, max_norm: f64) -> Result<f64> {
        let mut total = 0.0;
        for (_, p) in &self.params {
            let grad = p.grad();
            if grad.defined() {
                total += grad.f_square()?.f_sum(Kind::Double)?.double_value(&[]);
            }
        }
        let norm = total.sqrt();
        if max_norm > 0.0 {
            let coef = (max_norm / (norm + 1e-6)).min(1.0);
            if coef < 1.0 {
                for (_, p) in &self.params {
                    let mut grad = p.grad();
                    if grad.defined() {
                        let _ = grad.f_mul_scalar_(coef)?;
                    }
                }
            }
        }
        Ok(norm)
    }

    /// One update with learning rate `lr`.
    pub fn step(&mut self, lr: f64) -> Result<()> {
        self.step += 1;
        let c = &self.config;
        tch::no_grad(|| -> Result<()> {
            for (i, (_, param)) in self.params.iter().enumerate() {
                let grad = param.grad();
                if !grad.defined() {
                    continue;
                }
                let (mut p, grad) = match &self.master {
                    Some(master) => (master[i].shallow_clone(), grad.f_to_kind(Kind::Float)?),
                    None => (param.shallow_clone(), grad),
                };
                update(&mut p, &grad, &mut self.exp_avg[i], &mut self.exp_avg_sq[i], lr, c, self.step)?;
                if self.master.is_some() {
                    param.shallow_clone().f_copy_(&p)?;
                }
            }
            Ok(())
        })
    }

    /// Optimizer steps taken.
    pub fn steps(&self) -> u64 {
        self.step
    }

    /// Loads the state from ZeRO-2 shards (any world size) in checkpoint folder `dir`.
    fn load_flat(&mut self, dir: &Path, with_params: bool) -> Result<()> {
        let state = crate::distributed::FlatState::open(dir, &self.params)?;
        let mut offset = 0;
        for (i, (_, p)) in self.params.iter().enumerate() {
            let numel = p.numel() as i64;
            let read = |name: &str| -> Result<Tensor> {
                Ok(state
                    .read(name, offset, numel)?
                    .f_view(p.size().as_slice())?
                    .f_to_kind(p.kind())?
                    .f_to_device(p.device())?)
            };
            self.exp_avg[i] = read("exp_avg")?;
            self.exp_avg_sq[i] = read("exp_avg_sq")?;
            if with_params {
                let value = read("master")?;
                tch::no_grad(|| p.shallow_clone().f_copy_(&value))?;
            }
            offset += numel;
        }
        self.step = state.step;
        Ok(())
    }

    /// Writes the moments and the step count, and with `with_params` the parameters' own fp32
    /// values (`param.{name}`; the master copies in mixed precision), for runs whose parameters
    /// are saved nowhere else exactly (LoRA adapters). Returns the file's size and digest.
    pub(super) fn save(&self, path: &Path, with_params: bool) -> Result<crate::weights::WrittenFile> {
        let mut named: Vec<(String, Tensor)> = Vec::new();
        let masters = self.master_weights();
        for (i, (name, param)) in self.params.iter().enumerate() {
            named.push((format!("exp_avg.{name}"), self.exp_avg[i].shallow_clone()));
            named.push((format!("exp_avg_sq.{name}"), self.exp_avg_sq[i].shallow_clone()));
            if with_params {
                let value = masters.as_ref().map_or_else(|| param.shallow_clone(), |m| m[i].1.shallow_clone());
                named.push((format!("param.{name}"), value.f_to_kind(Kind::Float)?.f_detach()?));
            }
        }
        named.push(("step".to_string(), Tensor::from_slice(&[self.step as i64])));
        crate::weights::write_safetensors(path, &named)
    }

    /// Reads what [`Self::save`] wrote; with `with_params` also copies the saved parameter
    /// values into the parameters (before any master copies are taken).
    pub(super) fn load(&mut self, path: &Path, with_params: bool) -> Result<()> {
        if !path.is_file()
            && let Some(dir) = path.parent()
        {
            // A ZeRO-2 checkpoint: per-rank shards of the flat state.
            return self.load_flat(dir, with_params);
        }
        let tensors: BTreeMap<String, Tensor> = Tensor::read_safetensors(path)
            .map_err(|e| Error::Safetensors { path: path.to_path_buf(), reason: e.to_string() })?
            .into_iter()
            .collect();
        let get = |name: &str, like: &Tensor| -> Result<Tensor> {
            let t = tensors.get(name).ok_or_else(|| Error::MissingTensor {
                path: path.to_path_buf(),
                tensor: name.to_string(),
                expected: like.size(),
            })?;
            weights::check_shape(name, t, &like.size())?;
            Ok(t.f_to_kind(like.kind())?.f_to_device(like.device())?)
        };
        for (i, (name, p)) in self.params.iter().enumerate() {
            self.exp_avg[i] = get(&format!("exp_avg.{name}"), p)?;
            self.exp_avg_sq[i] = get(&format!("exp_avg_sq.{name}"), p)?;
            if with_params {
                let value = get(&format!("param.{name}"), p)?;
                tch::no_grad(|| p.shallow_clone().f_copy_(&value))?;
            }
        }
        self.step = tensors.get("step").map(|t| t.int64_value(&[0]) as u64).unwrap_or(0);
        Ok(())
    }
}

/// The parameters of `vs` that train, sorted by name: the order of the optimizer state, and of
/// the flat parameter space the distributed engine buckets and shards.
pub(crate) fn trainable_parameters(vs: &nn::VarStore) -> Vec<(String, Tensor)> {
    let mut params: Vec<(String, Tensor)> = vs.variables().into_iter().filter(|(_, t)| t.requires_grad()).collect();
    params.sort_by(|a, b| a.0.cmp(&b.0));
    params
}

/// One AdamW update (PyTorch's `torch.optim.AdamW` formula) of `p` at optimizer step `step`
/// (1-based), in place, elementwise: whole parameters here, flat ZeRO shards in
/// [`crate::distributed::ShardedAdamW`], with identical values either way.
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

    /// A var store with one trainable `[4, 3]` variable holding `values`, and that variable.
    fn store(values: &Tensor) -> (nn::VarStore, Tensor) {
        let vs = nn::VarStore::new(Device::Cpu);
        let w = vs.root().var_copy("w", values);
        (vs, w)
    }

    /// Mixed precision updates the fp32 master exactly as fp32 AdamW would with the same
    /// (bf16-rounded) gradients, and the bf16 parameter is the master rounded.
    #[test]
    fn adamw_master_weights_follow_the_fp32_update() {
        tch::manual_seed(3);
        let init = Tensor::randn([4, 3], (Kind::Float, Device::Cpu));
        let config = OptimConfig { weight_decay: 0.01, ..OptimConfig::default() };
        let (reference_vs, reference) = store(&init);
        let mut reference_optimizer = AdamW::new(&reference_vs, config.clone());
        let (mut mixed_vs, mixed) = store(&init);
        let mut mixed_optimizer = AdamW::new(&mixed_vs, config);
        mixed_optimizer.keep_master_weights().unwrap();
        mixed_vs.set_kind(Kind::BFloat16);
        assert_eq!(mixed.kind(), Kind::BFloat16);
        for step in 0..3 {
            let target = Tensor::randn([4, 3], (Kind::Float, Device::Cpu));
            reference_optimizer.zero_grad();
            mixed_optimizer.zero_grad();
            // The same loss; the reference sees the gradient the bf16 parameter receives.
            let loss = |w: &Tensor| w.to_kind(Kind::Float).f_sub(&target).unwrap().square().sum(Kind::Float);
            loss(&mixed).backward();
            // d/dw Σ w·g = g: the reference's gradient is the mixed one, exactly.
            let gradient = mixed.grad().to_kind(Kind::Float);
            reference.f_mul(&gradient).unwrap().sum(Kind::Float).backward();
            reference_optimizer.step(1e-2).unwrap();
            mixed_optimizer.step(1e-2).unwrap();
            let master = &mixed_optimizer.master_weights().unwrap()[0].1;
            assert!(master.equal(&reference), "step {step}: master differs from the fp32 update");
            assert!(
                mixed.equal(&reference.to_kind(Kind::BFloat16)),
                "step {step}: parameter is not the rounded master"
            );
        }
    }

    #[test]
    fn master_weights_must_come_from_fp32_parameters() {
        let (mut vs, _) = store(&Tensor::zeros([4, 3], (Kind::Float, Device::Cpu)));
        vs.set_kind(Kind::BFloat16);
        let mut optimizer = AdamW::new(&vs, OptimConfig::default());
        assert!(optimizer.keep_master_weights().is_err());
    }
}

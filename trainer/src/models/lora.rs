//! LoRA adapters on the transformer's linear layers (peft's `LoraLayer` on `nn.Linear`, as
//! diffusers' CogVideoX LoRA training scripts attach them): the `[lora]` settings and the adapter
//! a targeted layer adds. Their file is [`crate::loaders::lora`]'s.
//!
//! A targeted linear layer computes `x·Wᵀ + b + s·(x·Aᵀ)·Bᵀ` with `A` `[r, in]`, `B` `[out, r]`
//! and `s = alpha / r`. Only `A` and `B` train; the base weights stay frozen.

use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor, nn};

use crate::error::{Error, Result};

/// How the adapters start (peft's `init_lora_weights`); `B` is zero either way, so a fresh
/// adapter leaves the model unchanged.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LoraInit {
    /// peft's default (`True`): `A` Kaiming-uniform with `a = √5`, i.e. uniform in ±1/√in.
    #[default]
    Default,
    /// peft's `"gaussian"`: `A` normal with standard deviation 1/r.
    Gaussian,
}

/// The `[lora]` section of a training TOML. Its defaults are those of diffusers'
/// `examples/cogvideo/train_cogvideox_lora.py` as the CogVideoX finetuning guides run it
/// (rank 128, alpha 64, attention projections of every block).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LoraConfig {
    /// Adapter rank r. Valid: 1 to the smaller side of every targeted layer.
    pub rank: i64,
    /// Scale numerator: adapters are scaled by `alpha / rank`. Valid: finite, > 0.
    pub alpha: f64,
    /// Module names (or their last components, peft's suffix match) whose linear layers get
    /// adapters. Valid: non-empty; each must match at least one linear layer of the model.
    pub target_modules: Vec<String>,
    /// Initialisation of `A`. Valid: `default`, `gaussian`.
    pub init: LoraInit,
}

impl Default for LoraConfig {
    fn default() -> Self {
        Self {
            rank: 128,
            alpha: 64.0,
            target_modules: ["to_q", "to_k", "to_v", "to_out.0"].map(String::from).to_vec(),
            init: LoraInit::Default,
        }
    }
}

impl LoraConfig {
    /// The factor `alpha / rank` applied to every adapter's output.
    pub fn scale(&self) -> f64 {
        self.alpha / self.rank as f64
    }

    /// Whether `module` (a full dotted path such as `transformer_blocks.0.attn1.to_q`) is
    /// targeted: equal to a target or ending in `.` + a target, as peft matches.
    pub fn targets(&self, module: &str) -> bool {
        self.target_modules
            .iter()
            .any(|t| module == t || module.strip_suffix(t.as_str()).is_some_and(|p| p.ends_with('.')))
    }

    /// Checks every field, naming it as `lora.FIELD` in `source_name`.
    pub fn validate(&self, source_name: &str) -> Result<()> {
        let bad = |field: &str, reason: String| Error::InvalidConfig {
            source_name: source_name.to_string(),
            field: format!("lora.{field}"),
            reason,
        };
        if self.rank < 1 {
            return Err(bad("rank", format!("must be ≥ 1, got {}", self.rank)));
        }
        if !(self.alpha.is_finite() && self.alpha > 0.0) {
            return Err(bad("alpha", format!("must be finite and > 0, got {}", self.alpha)));
        }
        if self.target_modules.is_empty() {
            return Err(bad("target_modules", "must name at least one module (e.g. \"to_q\")".to_string()));
        }
        if let Some(t) = self.target_modules.iter().find(|t| t.is_empty() || t.starts_with('.') || t.ends_with('.')) {
            return Err(bad("target_modules", format!("`{t}` is not a module name")));
        }
        Ok(())
    }
}

/// The adapted modules of an adapters' store: every `{module}.lora_A.weight`'s module.
fn adapted_modules(lora_vs: &nn::VarStore) -> Vec<String> {
    lora_vs.variables().into_keys().filter_map(|name| name.strip_suffix(".lora_A.weight").map(str::to_string)).collect()
}

/// Checks that every target of `lora` matched at least one layer of the adapters' store (built
/// with [`crate::models::vars::Vars::with_lora`]); `layers` names the model's linear layers for
/// the message. Returns the number of adapted layers.
pub fn check_targets(lora: &LoraConfig, lora_vs: &nn::VarStore, layers: &str) -> Result<usize> {
    let modules = adapted_modules(lora_vs);
    for target in &lora.target_modules {
        let single = LoraConfig { target_modules: vec![target.clone()], ..lora.clone() };
        if !modules.iter().any(|m| single.targets(m)) {
            return Err(Error::InvalidConfig {
                source_name: "training config".to_string(),
                field: "lora.target_modules".to_string(),
                reason: format!("`{target}` matches no linear layer of the transformer ({layers})"),
            });
        }
    }
    Ok(modules.len())
}

/// Each adapted module of an adapters' store with its parameter count (`r·in + out·r`), by name.
pub fn adapter_sizes(lora_vs: &nn::VarStore) -> Vec<(String, u64)> {
    let variables = lora_vs.variables();
    let mut sizes: Vec<(String, u64)> = adapted_modules(lora_vs)
        .into_iter()
        .map(|module| {
            let numel = |part: &str| variables.get(&format!("{module}.{part}.weight")).map_or(0, |t| t.numel() as u64);
            let n = numel("lora_A") + numel("lora_B");
            (module, n)
        })
        .collect();
    sizes.sort();
    sizes
}

/// One layer's adapter: `A` `[r, in]`, `B` `[out, r]` and the scale.
#[derive(Debug)]
pub struct LoraAdapter {
    a: Tensor,
    b: Tensor,
    scale: f64,
}

impl LoraAdapter {
    /// Creates `lora_A.weight` and `lora_B.weight` under `path` (the targeted module's path in
    /// the adapters' store) for a layer `in_dim → out_dim`.
    pub fn new(path: &nn::Path, config: &LoraConfig, in_dim: i64, out_dim: i64, shapes_only: bool) -> Result<Self> {
        let r = config.rank;
        if r > in_dim.min(out_dim) {
            return Err(Error::InvalidConfig {
                source_name: "training config".to_string(),
                field: "lora.rank".to_string(),
                reason: format!(
                    "{r} exceeds the smaller side of {} ({in_dim} → {out_dim}), so the adapter cannot be low-rank",
                    path.path("weight").trim_end_matches(".weight")
                ),
            });
        }
        let options = (Kind::Float, path.device());
        let (a, b) = if shapes_only {
            let one = Tensor::f_zeros([1], options)?;
            (one.f_expand([r, in_dim], true)?, one.f_expand([out_dim, r], true)?)
        } else {
            let a = match config.init {
                LoraInit::Default => {
                    let bound = 1.0 / (in_dim as f64).sqrt();
                    Tensor::f_empty([r, in_dim], options)?.f_uniform_(-bound, bound)?
                }
                LoraInit::Gaussian => Tensor::f_randn([r, in_dim], options)?.f_mul_scalar(1.0 / r as f64)?,
            };
            (a, Tensor::f_zeros([out_dim, r], options)?)
        };
        let lora_a = path.sub("lora_A").add("weight", a, true);
        let lora_b = path.sub("lora_B").add("weight", b, true);
        Ok(Self { a: lora_a, b: lora_b, scale: config.scale() })
    }

    /// The adapter's contribution `s·(x·Aᵀ)·Bᵀ`, peft's `lora_B(lora_A(x)) * scaling`.
    pub fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        Ok(xs.f_linear::<&Tensor>(&self.a, None)?.f_linear::<&Tensor>(&self.b, None)?.f_mul_scalar(self.scale)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn targets_match_whole_name_components() {
        let c = LoraConfig::default();
        assert!(c.targets("transformer_blocks.3.attn1.to_q"));
        assert!(c.targets("transformer_blocks.3.attn1.to_out.0"));
        assert!(!c.targets("transformer_blocks.3.attn1.xto_q"));
        assert!(!c.targets("transformer_blocks.3.ff.net.0.proj"));
        assert!(c.targets("to_k"));
    }

    #[test]
    fn bad_fields_are_named() {
        let err = |c: LoraConfig| c.validate("x.toml").unwrap_err().to_string();
        assert!(err(LoraConfig { rank: 0, ..Default::default() }).contains("lora.rank"));
        assert!(err(LoraConfig { alpha: f64::NAN, ..Default::default() }).contains("lora.alpha"));
        assert!(err(LoraConfig { target_modules: vec![], ..Default::default() }).contains("lora.target_modules"));
    }
}

//! LoRA files in the layout diffusers' `load_lora_weights` / `load_lora_adapter` and peft read
//! unchanged, a LoRA run's checkpoint layout, and merging an adapter into a base transformer.
//!
//! The file (`pytorch_lora_weights.safetensors`, diffusers' `LORA_WEIGHT_NAME_SAFE`) holds
//! `transformer.{module}.lora_A.weight` and `transformer.{module}.lora_B.weight` in fp32.
//! diffusers assumes `alpha = r` (scale 1) when a file carries no adapter metadata, so the file
//! stores `s·B` in place of `B`: every loader then computes exactly what training computed, with
//! no metadata to agree on. Training state that must resume bit for bit (the unscaled `B`) lives
//! in the checkpoint's optimizer file, not here.

use std::collections::BTreeMap;
use std::path::Path;

use tch::{Kind, Tensor, nn};

use crate::diffusers_config::DiffusersConfig;
use crate::error::{Error, Result};

/// File name of a LoRA checkpoint (diffusers' `LORA_WEIGHT_NAME_SAFE`).
pub const LORA_WEIGHTS_NAME: &str = "pytorch_lora_weights.safetensors";
/// The run folder's copy of a LoRA run's base transformer (`RUN/base_transformer/`), written when
/// the base is not simply the configured model folder (a random-init preset, or a folder with a
/// LoRA merged in).
pub const BASE_TRANSFORMER_DIR: &str = "base_transformer";
/// Key prefix of the transformer's adapters (diffusers' `CogVideoXLoraLoaderMixin.transformer_name`).
pub const LORA_PREFIX: &str = "transformer";
/// The safetensors metadata key under which diffusers stores an adapter's peft config (its
/// `LORA_ADAPTER_METADATA_KEY`), read for `lora_alpha` and `r` of files other tools wrote.
const ADAPTER_METADATA_KEY: &str = "lora_adapter_metadata";

/// The adapters of a store (`{module}.lora_A.weight`, `{module}.lora_B.weight`) as the file's
/// tensors: keys prefixed with `transformer.`, fp32, and `B` multiplied by `scale` (see the
/// module docs). `values` replaces a store variable by name (a mixed-precision run's fp32
/// master weights).
pub fn file_tensors(
    lora_vs: &nn::VarStore,
    values: &BTreeMap<String, Tensor>,
    scale: f64,
) -> Result<Vec<(String, Tensor)>> {
    let mut named: Vec<(String, Tensor)> = Vec::new();
    let mut variables: Vec<(String, Tensor)> = lora_vs.variables().into_iter().collect();
    variables.sort_by(|x, y| x.0.cmp(&y.0));
    for (name, variable) in variables {
        let value = values.get(&name).unwrap_or(&variable).f_to_kind(Kind::Float)?.f_detach()?;
        let value = if name.ends_with(".lora_B.weight") { value.f_mul_scalar(scale)? } else { value };
        named.push((format!("{LORA_PREFIX}.{name}"), value));
    }
    Ok(named)
}

/// Writes the adapters of `lora_vs` to `path` in diffusers' layout (see [`file_tensors`]);
/// returns the file's size and digest.
pub fn save(
    lora_vs: &nn::VarStore,
    values: &BTreeMap<String, Tensor>,
    scale: f64,
    path: &Path,
) -> Result<crate::models::weights::WrittenFile> {
    crate::models::weights::write_safetensors(path, &file_tensors(lora_vs, values, scale)?)
}

/// A LoRA file's adapters by module: `(A, B·s)` with the file's scale applied (1 for the files
/// this crate writes; `lora_alpha / r` from diffusers' adapter metadata where a file has it).
#[derive(Debug)]
pub struct LoraFile {
    /// Module path (`transformer_blocks.0.attn1.to_q`) → (`A` `[r, in]`, scaled `B` `[out, r]`).
    pub adapters: BTreeMap<String, (Tensor, Tensor)>,
}

impl LoraFile {
    /// Reads and checks a LoRA safetensors file: every key is a `lora_A`/`lora_B` weight of a
    /// module, optionally behind the `transformer.` prefix; each module has both, of rank-matching
    /// 2-D shapes, and all modules share one rank.
    pub fn read(path: &Path) -> Result<Self> {
        let bad = |field: String, reason: String| Error::InvalidConfig {
            source_name: path.display().to_string(),
            field,
            reason,
        };
        // Checked header first: a truncated or foreign file is an error naming it.
        let tensors = crate::models::weights::read_safetensors(path)?;
        let scale = metadata_scale(&read_file_metadata(path)?, path)?;
        let mut parts: BTreeMap<String, (Option<Tensor>, Option<Tensor>)> = BTreeMap::new();
        for (key, tensor) in tensors {
            let name = key.strip_prefix(&format!("{LORA_PREFIX}.")).unwrap_or(&key);
            let (module, is_a) = match (name.strip_suffix(".lora_A.weight"), name.strip_suffix(".lora_B.weight")) {
                (Some(m), _) => (m, true),
                (_, Some(m)) => (m, false),
                _ => {
                    return Err(bad(
                        key.clone(),
                        "is not a LoRA weight (expected `transformer.{module}.lora_A.weight` or `.lora_B.weight`)"
                            .to_string(),
                    ));
                }
            };
            if tensor.dim() != 2 || !tensor.is_floating_point() {
                return Err(bad(
                    key.clone(),
                    format!("must be a 2-D float matrix, got {:?} {:?}", tensor.kind(), tensor.size()),
                ));
            }
            let entry = parts.entry(module.to_string()).or_default();
            if is_a {
                entry.0 = Some(tensor)
            } else {
                entry.1 = Some(tensor)
            };
        }
        if parts.is_empty() {
            return Err(bad("(tensors)".to_string(), "holds no LoRA weights".to_string()));
        }
        let mut adapters = BTreeMap::new();
        let mut rank: Option<(i64, String)> = None;
        for (module, pair) in parts {
            let (Some(a), Some(b)) = pair else {
                return Err(bad(module.clone(), "has only one of lora_A and lora_B".to_string()));
            };
            let (r, r_b) = (a.size()[0], b.size()[1]);
            if r != r_b {
                return Err(bad(
                    module.clone(),
                    format!("lora_A is {:?} and lora_B {:?}: their ranks differ", a.size(), b.size()),
                ));
            }
            match &rank {
                Some((first, first_module)) if *first != r => {
                    return Err(bad(module.clone(), format!("has rank {r}, but {first_module} has rank {first}")));
                }
                None => rank = Some((r, module.clone())),
                _ => {}
            }
            let b = b.f_to_kind(Kind::Float)?.f_mul_scalar(scale)?;
            adapters.insert(module, (a.f_to_kind(Kind::Float)?, b));
        }
        Ok(Self { adapters })
    }

    /// Adds every adapter into its base weight, `W += (s·B)·A`, checking that the module exists
    /// in `vs` as a linear layer with matching shapes.
    pub fn merge_into(&self, vs: &nn::VarStore, source: &Path) -> Result<()> {
        let variables = vs.variables();
        tch::no_grad(|| -> Result<()> {
            for (module, (a, b)) in &self.adapters {
                let key = format!("{module}.weight");
                let weight = variables.get(&key).ok_or_else(|| Error::InvalidConfig {
                    source_name: source.display().to_string(),
                    field: format!("{LORA_PREFIX}.{module}.lora_A.weight"),
                    reason: format!("the base model has no linear layer `{module}` (no variable `{key}`)"),
                })?;
                let [out_dim, in_dim] = weight.size()[..] else {
                    return Err(Error::InvalidConfig {
                        source_name: source.display().to_string(),
                        field: format!("{LORA_PREFIX}.{module}.lora_A.weight"),
                        reason: format!("`{key}` is {:?}, not a linear layer's weight", weight.size()),
                    });
                };
                let shape_err = |which: &str, actual: Vec<i64>, expected: String| Error::InvalidConfig {
                    source_name: source.display().to_string(),
                    field: format!("{LORA_PREFIX}.{module}.{which}.weight"),
                    reason: format!("is {actual:?}; the base layer {key} {:?} needs {expected}", weight.size()),
                };
                if a.size()[1] != in_dim {
                    return Err(shape_err("lora_A", a.size(), format!("[r, {in_dim}]")));
                }
                if b.size()[0] != out_dim {
                    return Err(shape_err("lora_B", b.size(), format!("[{out_dim}, r]")));
                }
                let delta = b.f_to_device(weight.device())?.f_matmul(&a.f_to_device(weight.device())?)?;
                let merged = weight.f_to_kind(Kind::Float)?.f_add(&delta)?.f_to_kind(weight.kind())?;
                weight.shallow_clone().f_copy_(&merged)?;
            }
            Ok(())
        })
    }
}

/// The `__metadata__` string map of a safetensors file's header (empty when it has none).
fn read_file_metadata(path: &Path) -> Result<BTreeMap<String, String>> {
    use std::io::Read;
    let io = |source| Error::Io { path: path.to_path_buf(), error: source };
    let mut file = std::fs::File::open(path).map_err(io)?;
    let mut len = [0u8; 8];
    file.read_exact(&mut len).map_err(io)?;
    // The header was already checked against the file's size by `read_safetensors`.
    let mut header = vec![0u8; u64::from_le_bytes(len) as usize];
    file.read_exact(&mut header).map_err(io)?;
    let json: serde_json::Value = serde_json::from_slice(&header)
        .map_err(|e| Error::Safetensors { path: path.to_path_buf(), reason: format!("header is not JSON: {e}") })?;
    Ok(json
        .get("__metadata__")
        .and_then(|m| m.as_object())
        .map(|m| m.iter().filter_map(|(k, v)| Some((k.clone(), v.as_str()?.to_string()))).collect())
        .unwrap_or_default())
}

/// The base transformer folder and the LoRA file of a LoRA run's checkpoint
/// (`RUN/checkpoints/step-N/` holding [`LORA_WEIGHTS_NAME`] and no `transformer/`): the base is
/// `RUN/base_transformer/` when the run kept one, else the run's configured model folder.
/// `None` for any other folder.
pub fn lora_checkpoint(checkpoint: &Path) -> Result<Option<(std::path::PathBuf, std::path::PathBuf)>> {
    let file = checkpoint.join(LORA_WEIGHTS_NAME);
    if !file.is_file() || checkpoint.join("transformer").is_dir() {
        return Ok(None);
    }
    let run = checkpoint.join("../..");
    let kept = run.join(BASE_TRANSFORMER_DIR);
    if kept.join("config.json").is_file() {
        return Ok(Some((kept, file)));
    }
    let config_path = run.join("config.json");
    let bad = |reason: String| Error::InvalidConfig {
        source_name: config_path.display().to_string(),
        field: "model.transformer".to_string(),
        reason,
    };
    let text = std::fs::read_to_string(&config_path).map_err(|_| {
        bad(format!("{} is a LoRA checkpoint, but its run names no base transformer", checkpoint.display()))
    })?;
    let json: serde_json::Value = serde_json::from_str(&text).map_err(|e| bad(format!("not JSON: {e}")))?;
    match json.get("model").and_then(|m| m.get("transformer")).and_then(|t| t.as_str()) {
        Some(base) if Path::new(base).is_dir() => Ok(Some((base.into(), file))),
        other => Err(bad(format!(
            "the base of LoRA checkpoint {} must be a diffusers folder, got {other:?}",
            checkpoint.display()
        ))),
    }
}

/// `trainer merge-lora`: the transformer of `base` (a diffusers model folder or a checkpoint
/// with `transformer/`, of either family: its `_class_name` decides) with the adapters of `lora`
/// added into its weights, written to `out` as a full diffusers transformer folder. Everything is
/// read and checked before `out` is written. Returns the number of layers merged.
pub fn merge_lora(base: &Path, lora: &Path, out: &Path) -> Result<usize> {
    use crate::models::family::ModelFamily;
    let base = match lora_checkpoint(base)? {
        Some((kept, _)) => kept,
        None => super::transformer_dir(base),
    };
    let file = LoraFile::read(lora)?;
    let max_shard = crate::models::weights::DEFAULT_MAX_SHARD_BYTES;
    match ModelFamily::of_transformer(&base)? {
        ModelFamily::CogVideoX => {
            use crate::models::cogvideox::cogvideox_transformer_3d::{
                self as transformer, CogVideoXTransformer3DModelConfig,
            };
            let config = CogVideoXTransformer3DModelConfig::from_json_file(&base)?;
            let shapes = transformer::variable_shapes(&config)?;
            crate::models::weights::check_against(
                &shapes,
                &crate::models::weights::read_checkpoint_info(&base)?,
                &base,
            )?;
            let (vs, _model) = transformer::build(&config, tch::Device::Cpu, Kind::Float)?;
            crate::models::weights::load(&vs, &base)?;
            file.merge_into(&vs, lora)?;
            crate::models::weights::save(&vs, &config, transformer::CLASS_NAME, out, max_shard)?;
        }
        ModelFamily::Wan => {
            use crate::models::wan::transformer_wan::{self as transformer, WanTransformer3DModelConfig};
            let config = WanTransformer3DModelConfig::from_json_file(&base)?;
            // Built in fp32 (no `keep_in_fp32` split) and loaded with diffusers' ignored keys.
            let (vs, _model) = transformer::build(&config, tch::Device::Cpu, Kind::Float)?;
            transformer::load(&vs, &base)?;
            file.merge_into(&vs, lora)?;
            crate::models::weights::save(&vs, &config, transformer::CLASS_NAME, out, max_shard)?;
        }
    }
    Ok(file.adapters.len())
}

/// The scale a file's adapter metadata implies (peft's: `lora_alpha / r`, or `lora_alpha / √r`
/// with `use_rslora`; of the transformer's entry, diffusers' packing `transformer.lora_alpha`), or
/// 1 where it has none. Settings that make the scale differ per layer (`rank_pattern`,
/// `alpha_pattern`) or the adapter more than `B·A` (`use_dora`) are refused by name.
fn metadata_scale(metadata: &BTreeMap<String, String>, path: &Path) -> Result<f64> {
    let Some(text) = metadata.get(ADAPTER_METADATA_KEY) else { return Ok(1.0) };
    let bad = |reason: String| Error::InvalidConfig {
        source_name: path.display().to_string(),
        field: ADAPTER_METADATA_KEY.to_string(),
        reason,
    };
    let json: serde_json::Value = serde_json::from_str(text).map_err(|e| bad(format!("not JSON: {e}")))?;
    let field = |name: &str| json.get(format!("{LORA_PREFIX}.{name}")).or_else(|| json.get(name));
    for pattern in ["rank_pattern", "alpha_pattern"] {
        if field(pattern).and_then(serde_json::Value::as_object).is_some_and(|p| !p.is_empty()) {
            return Err(bad(format!(
                "has a non-empty `{pattern}` (per-layer ranks or scales), which is not supported"
            )));
        }
    }
    if field("use_dora").and_then(serde_json::Value::as_bool) == Some(true) {
        return Err(bad("is a DoRA adapter (`use_dora`), which is not a LoRA's `B·A`".to_string()));
    }
    let rslora = field("use_rslora").and_then(serde_json::Value::as_bool) == Some(true);
    match (field("lora_alpha").and_then(serde_json::Value::as_f64), field("r").and_then(serde_json::Value::as_f64)) {
        (Some(alpha), Some(r)) if alpha.is_finite() && r > 0.0 => Ok(if rslora { alpha / r.sqrt() } else { alpha / r }),
        (None, _) | (_, None) => Ok(1.0),
        (Some(alpha), Some(r)) => Err(bad(format!("lora_alpha {alpha} and r {r} give no scale"))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scale(json: &str) -> Result<f64> {
        metadata_scale(&BTreeMap::from([(ADAPTER_METADATA_KEY.to_string(), json.to_string())]), Path::new("l.st"))
    }

    #[test]
    fn peft_metadata_gives_the_scale_or_a_named_refusal() {
        assert_eq!(metadata_scale(&BTreeMap::new(), Path::new("l.st")).unwrap(), 1.0);
        assert_eq!(scale(r#"{"transformer.lora_alpha": 2.0, "transformer.r": 4}"#).unwrap(), 0.5);
        let rs = r#"{"transformer.lora_alpha": 8.0, "transformer.r": 16, "transformer.use_rslora": true}"#;
        assert_eq!(scale(rs).unwrap(), 2.0);
        let empty = r#"{"lora_alpha": 4, "r": 4, "rank_pattern": {}, "alpha_pattern": {}, "use_dora": false}"#;
        assert_eq!(scale(empty).unwrap(), 1.0);
        let e = scale(r#"{"lora_alpha": 4, "r": 4, "transformer.alpha_pattern": {"to_q": 8}}"#).unwrap_err();
        assert!(e.to_string().contains("alpha_pattern") && e.to_string().contains("l.st"), "{e}");
        let e = scale(r#"{"lora_alpha": 4, "r": 4, "use_dora": true}"#).unwrap_err();
        assert!(e.to_string().contains("use_dora"), "{e}");
    }
}

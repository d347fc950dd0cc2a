//! diffusers checkpoints and safetensors files: reading, checking and writing them.
//!
//! Checkpoints are diffusers model folders: `config.json` plus either one
//! `diffusion_pytorch_model.safetensors` or shards named
//! `diffusion_pytorch_model-00001-of-0000N.safetensors` listed in
//! `diffusion_pytorch_model.safetensors.index.json` (`{"metadata": {"total_size"}, "weight_map"}`),
//! the layout diffusers' `save_pretrained` writes and `from_pretrained` reads. [`load`] checks names
//! and shapes from the safetensors headers before reading any data, so a mismatched config (2B
//! config, 5B weights) fails with the tensor, its expected and its actual shape.

use std::collections::{BTreeMap, BTreeSet};
use std::io::Read;
use std::path::{Path, PathBuf};

use safetensors::{Dtype, SafeTensors};
use serde::Serialize;
use tch::{Device, Kind, Tensor, nn};

use crate::diffusers_config::DiffusersConfig;
use crate::error::{Error, Result};

/// File name of a single-file checkpoint (diffusers' `SAFETENSORS_WEIGHTS_NAME`).
pub const WEIGHTS_NAME: &str = "diffusion_pytorch_model.safetensors";
/// File name of a sharded checkpoint's index (diffusers' `SAFE_WEIGHTS_INDEX_NAME`).
pub const WEIGHTS_INDEX_NAME: &str = "diffusion_pytorch_model.safetensors.index.json";
/// Shard size diffusers' `save_pretrained` uses by default (`max_shard_size="10GB"`).
pub const DEFAULT_MAX_SHARD_BYTES: u64 = 10_000_000_000;

// ------------------------------------------------------------------------------------------------
// Reading checkpoints
// ------------------------------------------------------------------------------------------------

/// Dtype and shape of one checkpoint tensor, from its safetensors header.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TensorInfo {
    /// The stored dtype (`F32`, `BF16`, …).
    pub dtype: Dtype,
    /// The stored shape.
    pub shape: Vec<i64>,
    /// The file holding it.
    pub file: PathBuf,
}

/// The safetensors files of a checkpoint given as a model folder, a `.safetensors` file or a
/// `.safetensors.index.json` file; the second value is the path to name in errors.
pub fn checkpoint_files(path: &Path) -> Result<(Vec<PathBuf>, PathBuf)> {
    let index = if path.is_dir() {
        let single = path.join(WEIGHTS_NAME);
        if single.is_file() {
            return Ok((vec![single.clone()], single));
        }
        let index = path.join(WEIGHTS_INDEX_NAME);
        if !index.is_file() {
            return Err(Error::Io {
                path: path.to_path_buf(),
                error: std::io::Error::new(
                    std::io::ErrorKind::NotFound,
                    format!("no {WEIGHTS_NAME} or {WEIGHTS_INDEX_NAME} in this folder"),
                ),
            });
        }
        index
    } else if path.to_string_lossy().ends_with(".index.json") {
        path.to_path_buf()
    } else {
        return Ok((vec![path.to_path_buf()], path.to_path_buf()));
    };
    let text = std::fs::read_to_string(&index).map_err(|source| Error::Io { path: index.clone(), error: source })?;
    let json: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| Error::Safetensors { path: index.clone(), reason: format!("index is not JSON: {e}") })?;
    let map = json.get("weight_map").and_then(|m| m.as_object()).ok_or_else(|| Error::Safetensors {
        path: index.clone(),
        reason: "index has no `weight_map` object".to_string(),
    })?;
    let folder = index.parent().unwrap_or(Path::new("."));
    let mut files = BTreeSet::new();
    for (key, file) in map {
        let file = file.as_str().ok_or_else(|| Error::Safetensors {
            path: index.clone(),
            reason: format!("`weight_map.{key}` is not a file name"),
        })?;
        files.insert(folder.join(file));
    }
    Ok((files.into_iter().collect(), index))
}

/// Largest safetensors header read (the `safetensors` crate's own limit, 100 MB).
const MAX_HEADER_BYTES: u64 = 100_000_000;

/// Reads the header (names, dtypes, shapes) of one safetensors file without reading its data.
/// Every tensor's `data_offsets` are checked against its dtype and shape and against the file's
/// length, so a truncated file fails here, naming the file and the first tensor it cuts, before
/// any model is built or any data read.
pub fn read_header(file: &Path) -> Result<BTreeMap<String, TensorInfo>> {
    let bad = |reason: String| Error::Safetensors { path: file.to_path_buf(), reason };
    let io = |source| Error::Io { path: file.to_path_buf(), error: source };
    let mut f = std::fs::File::open(file).map_err(io)?;
    let file_len = f.metadata().map_err(io)?.len();
    let mut len = [0u8; 8];
    f.read_exact(&mut len)
        .map_err(|_| bad(format!("{file_len} bytes: too short for the 8-byte header length (not safetensors)")))?;
    let len = u64::from_le_bytes(len);
    if len > file_len.saturating_sub(8) || len > MAX_HEADER_BYTES {
        return Err(bad(format!(
            "header length {len} exceeds the file size {file_len} (truncated, or not safetensors)"
        )));
    }
    let mut header = vec![0u8; len as usize];
    f.read_exact(&mut header).map_err(io)?;
    let json: BTreeMap<String, serde_json::Value> =
        serde_json::from_slice(&header).map_err(|e| bad(format!("header is not JSON: {e}")))?;
    let data_len = file_len - 8 - len;
    let mut out = BTreeMap::new();
    let mut extents = Vec::new();
    for (name, entry) in json {
        if name == "__metadata__" {
            continue;
        }
        let dtype: Dtype = serde_json::from_value(entry.get("dtype").cloned().unwrap_or_default())
            .map_err(|e| bad(format!("tensor `{name}`: bad dtype: {e}")))?;
        let shape: Vec<i64> = serde_json::from_value(entry.get("shape").cloned().unwrap_or_default())
            .map_err(|e| bad(format!("tensor `{name}`: bad shape: {e}")))?;
        let [begin, end]: [u64; 2] = serde_json::from_value(entry.get("data_offsets").cloned().unwrap_or_default())
            .map_err(|e| bad(format!("tensor `{name}`: bad data_offsets: {e}")))?;
        let bits = shape
            .iter()
            .try_fold(dtype.bitsize() as u64, |acc, &d| u64::try_from(d).ok().and_then(|d| acc.checked_mul(d)))
            .ok_or_else(|| bad(format!("tensor `{name}`: shape {shape:?} is negative or too large")))?;
        let bytes = bits.div_ceil(8);
        if end < begin || end - begin != bytes {
            return Err(bad(format!(
                "tensor `{name}`: data_offsets [{begin}, {end}] do not hold {bytes} bytes of {dtype:?} {shape:?}"
            )));
        }
        if end > data_len {
            return Err(bad(format!(
                "tensor `{name}`: data ends at byte {end} of the data section, but the file holds only {data_len} \
                 ({file_len} bytes in all: truncated)"
            )));
        }
        extents.push((begin, end, name.clone()));
        out.insert(name, TensorInfo { dtype, shape, file: file.to_path_buf() });
    }
    extents.sort();
    if let Some(pair) = extents.windows(2).find(|w| w[1].0 < w[0].1) {
        return Err(bad(format!("tensors `{}` and `{}` overlap", pair[0].2, pair[1].2)));
    }
    Ok(out)
}

/// Reads every tensor of a safetensors file (inputs, text embeddings, LoRA files) after
/// [`read_header`]'s checks, so a truncated or malformed file is an error naming it and the
/// tensor, never a libtorch exception; every value must be finite (see [`check_finite`]).
pub fn read_safetensors(file: &Path) -> Result<BTreeMap<String, Tensor>> {
    read_header(file)?;
    let tensors: BTreeMap<String, Tensor> = Tensor::read_safetensors(file)
        .map_err(|e| Error::Safetensors { path: file.to_path_buf(), reason: e.to_string() })?
        .into_iter()
        .collect();
    for (name, tensor) in &tensors {
        check_finite(&format!("{name}` in `{}", file.display()), tensor)?;
    }
    Ok(tensors)
}

/// Refuses a tensor with NaN or infinite values, naming it (`name`: the tensor and its file, or
/// what it is) with how many there are and where the first is. One NaN in a weight, a LoRA
/// factor or a text embedding turns every sampled frame black, so every tensor read from a
/// user's file passes here once, as it is read; integer tensors always pass.
pub fn check_finite(name: &str, tensor: &Tensor) -> Result<()> {
    if !tensor.is_floating_point() {
        return Ok(());
    }
    let not_finite = tensor.f_isfinite()?.f_logical_not()?;
    let count = not_finite.f_sum(Kind::Int64)?.int64_value(&[]);
    if count == 0 {
        return Ok(());
    }
    let first = not_finite.f_flatten(0, -1)?.f_to_kind(Kind::Uint8)?.f_argmax(None, false)?.int64_value(&[]);
    let value = tensor.f_flatten(0, -1)?.f_double_value(&[first])?;
    Err(Error::NonFinite {
        tensor: name.to_string(),
        reason: format!(
            "{count} of {} values are not finite (NaN or ±inf), the first ({value}) at flat index {first}",
            tensor.numel()
        ),
    })
}

/// Checks that `tensor` (named `name`, from `file`) holds floating-point values.
pub fn check_floating(file: &Path, name: &str, tensor: &Tensor) -> Result<()> {
    if tensor.is_floating_point() {
        return Ok(());
    }
    Err(Error::DtypeDevice {
        tensor: format!("{name}` in `{}", file.display()),
        expected: "a floating-point dtype (F32, F16, BF16, F64)".to_string(),
        actual: format!("{:?}", tensor.kind()),
    })
}

/// Names, dtypes and shapes of every tensor of a checkpoint (folder, file or index).
pub fn read_checkpoint_info(path: &Path) -> Result<BTreeMap<String, TensorInfo>> {
    let (files, _) = checkpoint_files(path)?;
    let mut out = BTreeMap::new();
    for file in files {
        out.extend(read_header(&file)?);
    }
    Ok(out)
}

/// Checks a checkpoint against a module's variables (name → shape): every variable present with
/// the same shape, nothing extra. Errors name the checkpoint, the tensor and both shapes.
pub fn check_against(
    expected: &BTreeMap<String, Vec<i64>>,
    found: &BTreeMap<String, TensorInfo>,
    checkpoint: &Path,
) -> Result<()> {
    for (name, shape) in expected {
        match found.get(name) {
            None => {
                return Err(Error::MissingTensor {
                    path: checkpoint.to_path_buf(),
                    tensor: name.clone(),
                    expected: shape.clone(),
                });
            }
            Some(info) if &info.shape != shape => {
                return Err(Error::Shape {
                    tensor: format!("{name}` in `{}", info.file.display()),
                    expected: format!("{shape:?} (from the config)"),
                    actual: info.shape.clone(),
                });
            }
            Some(info) if kind_of(info.dtype).is_none() => {
                return Err(Error::DtypeDevice {
                    tensor: name.clone(),
                    expected: "a floating-point dtype (F32, F16, BF16, F64)".to_string(),
                    actual: format!("{:?} in {}", info.dtype, info.file.display()),
                });
            }
            Some(_) => {}
        }
    }
    let extra: Vec<&String> = found.keys().filter(|k| !expected.contains_key(*k)).collect();
    if let Some(example) = extra.first() {
        return Err(Error::UnexpectedTensors {
            path: checkpoint.to_path_buf(),
            count: extra.len(),
            example: (*example).clone(),
        });
    }
    Ok(())
}

/// Name → shape of every variable in a store.
pub fn variable_shapes(vs: &nn::VarStore) -> BTreeMap<String, Vec<i64>> {
    vs.variables().into_iter().map(|(k, v)| (k, v.size())).collect()
}

/// Loads a checkpoint (folder, file or index) into `vs`: names and shapes are checked first (see
/// [`check_against`]), then each file is read and its tensors copied into the variables, converted
/// to their dtype and device. Returns how many tensors were loaded.
pub fn load(vs: &nn::VarStore, path: &Path) -> Result<usize> {
    load_ignoring(vs, path, &[])
}

/// [`load`], skipping checkpoint tensors the model does not have whose names contain one of
/// `ignore_unexpected` (diffusers' `_keys_to_ignore_on_load_unexpected`: weights that older
/// conversions wrote and the model no longer uses).
pub fn load_ignoring(vs: &nn::VarStore, path: &Path, ignore_unexpected: &[&str]) -> Result<usize> {
    let (files, named) = checkpoint_files(path)?;
    let expected = variable_shapes(vs);
    let mut found = BTreeMap::new();
    for file in &files {
        found.extend(read_header(file)?);
    }
    found.retain(|name, _| expected.contains_key(name) || !ignore_unexpected.iter().any(|p| name.contains(p)));
    check_against(&expected, &found, &named)?;
    let mut variables = vs.variables();
    let mut loaded = 0;
    for file in &files {
        let bytes = std::fs::read(file).map_err(|source| Error::Io { path: file.clone(), error: source })?;
        let tensors = SafeTensors::deserialize(&bytes)
            .map_err(|e| Error::Safetensors { path: file.clone(), reason: e.to_string() })?;
        tch::no_grad(|| -> Result<()> {
            for (name, view) in tensors.tensors() {
                let Some(var) = variables.get_mut(&name) else { continue };
                let kind = kind_of(view.dtype()).ok_or_else(|| Error::DtypeDevice {
                    tensor: name.clone(),
                    expected: "a floating-point dtype".to_string(),
                    actual: format!("{:?}", view.dtype()),
                })?;
                let shape: Vec<i64> = view.shape().iter().map(|&d| d as i64).collect();
                let src = Tensor::f_from_data_size(view.data(), &shape, kind)?;
                check_finite(&format!("{name}` in `{}", file.display()), &src)?;
                var.f_copy_(&src.f_to_kind(var.kind())?.f_to_device(var.device())?)?;
                loaded += 1;
            }
            Ok(())
        })?;
    }
    Ok(loaded)
}

fn kind_of(dtype: Dtype) -> Option<Kind> {
    match dtype {
        Dtype::F32 => Some(Kind::Float),
        Dtype::F16 => Some(Kind::Half),
        Dtype::BF16 => Some(Kind::BFloat16),
        Dtype::F64 => Some(Kind::Double),
        _ => None,
    }
}

fn dtype_of(kind: Kind) -> Result<Dtype> {
    match kind {
        Kind::Float => Ok(Dtype::F32),
        Kind::Half => Ok(Dtype::F16),
        Kind::BFloat16 => Ok(Dtype::BF16),
        Kind::Double => Ok(Dtype::F64),
        other => Err(Error::DtypeDevice {
            tensor: "(variable)".to_string(),
            expected: "a floating-point kind".to_string(),
            actual: format!("{other:?}"),
        }),
    }
}

/// Checks that `tensor` has shape `expected`, naming it otherwise.
pub fn check_shape(name: &str, tensor: &Tensor, expected: &[i64]) -> Result<()> {
    if tensor.size() != expected {
        return Err(Error::Shape {
            tensor: name.to_string(),
            expected: format!("{expected:?}"),
            actual: tensor.size(),
        });
    }
    Ok(())
}

/// Checks that a model input is of the model's element type `kind` on its `device`, naming it
/// otherwise (a forward's inputs are cast by the caller, never silently here).
pub fn check_kind_device(name: &str, tensor: &Tensor, kind: Kind, device: Device) -> Result<()> {
    if tensor.kind() != kind || tensor.device() != device {
        return Err(Error::DtypeDevice {
            tensor: name.to_string(),
            expected: format!("{kind:?} on {device:?} (the model's weights)"),
            actual: format!("{:?} on {:?}", tensor.kind(), tensor.device()),
        });
    }
    Ok(())
}

/// Checks that a model input (a timestep, of any type) is on the model's `device`.
pub fn check_device(name: &str, tensor: &Tensor, device: Device) -> Result<()> {
    if tensor.device() != device {
        return Err(Error::DtypeDevice {
            tensor: name.to_string(),
            expected: format!("on {device:?}"),
            actual: format!("on {:?}", tensor.device()),
        });
    }
    Ok(())
}

// ------------------------------------------------------------------------------------------------
// Writing checkpoints
// ------------------------------------------------------------------------------------------------

/// Writes `vs` as a diffusers model folder: `config.json` (written by
/// [`DiffusersConfig::to_json_string`]: the fields, the unknown keys kept, `_class_name` and
/// `_diffusers_version`) and the weights, in one file or, above `max_shard_bytes`, in shards with
/// an index. Every file goes to a temporary name first and is renamed when complete; stale weight
/// files of an earlier save in the same folder are removed. Tensors keep the store's dtype.
/// Returns the files written, with their sizes and digests.
pub fn save<C: DiffusersConfig + Serialize>(
    vs: &nn::VarStore,
    config: &C,
    class_name: &str,
    dir: &Path,
    max_shard_bytes: u64,
) -> Result<Vec<WrittenFile>> {
    save_tensors(vs.variables().into_iter().collect(), config, class_name, dir, max_shard_bytes)
}

/// [`save`] for named tensors (a store's variables with some replaced, such as the fp32 master
/// weights of a bf16 training run).
pub fn save_tensors<C: DiffusersConfig + Serialize>(
    variables: BTreeMap<String, Tensor>,
    config: &C,
    class_name: &str,
    dir: &Path,
    max_shard_bytes: u64,
) -> Result<Vec<WrittenFile>> {
    std::fs::create_dir_all(dir).map_err(|source| Error::Io { path: dir.to_path_buf(), error: source })?;
    let text = config.to_json_string(class_name)?;
    let mut written = vec![write_file(&dir.join("config.json"), text.as_bytes())?];

    let mut shards: Vec<Vec<(String, Tensor)>> = vec![Vec::new()];
    let mut shard_bytes = 0u64;
    let mut total = 0u64;
    for (name, tensor) in variables {
        let bytes = (tensor.numel() * tensor.kind().elt_size_in_bytes()) as u64;
        if shard_bytes > 0 && shard_bytes + bytes > max_shard_bytes {
            shards.push(Vec::new());
            shard_bytes = 0;
        }
        shard_bytes += bytes;
        total += bytes;
        shards.last_mut().expect("one shard").push((name, tensor));
    }
    for stale in [WEIGHTS_NAME.to_string(), WEIGHTS_INDEX_NAME.to_string()] {
        let _ = std::fs::remove_file(dir.join(stale));
    }
    if shards.len() == 1 {
        written.push(write_safetensors(&dir.join(WEIGHTS_NAME), &shards[0])?);
        return Ok(written);
    }
    let count = shards.len();
    let mut weight_map = BTreeMap::new();
    for (i, shard) in shards.iter().enumerate() {
        let file = format!("diffusion_pytorch_model-{:05}-of-{count:05}.safetensors", i + 1);
        written.push(write_safetensors(&dir.join(&file), shard)?);
        for (name, _) in shard {
            weight_map.insert(name.clone(), file.clone());
        }
    }
    let index = serde_json::json!({ "metadata": { "total_size": total }, "weight_map": weight_map });
    let text = serde_json::to_string_pretty(&index).expect("a JSON value serialises");
    written.push(write_file(&dir.join(WEIGHTS_INDEX_NAME), text.as_bytes())?);
    Ok(written)
}

/// A file as written: its path, its size and the BLAKE3 digest of its bytes, hashed as they went
/// to disk (a checkpoint lists these in its `state.json`; checking them later needs no second
/// read at write time).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WrittenFile {
    /// Where it was written.
    pub path: PathBuf,
    /// Its size in bytes.
    pub bytes: u64,
    /// BLAKE3 of its content, hex.
    pub blake3: String,
}

/// Bytes on their way to a file, hashed and counted as they pass.
struct DigestWriter {
    file: std::io::BufWriter<std::fs::File>,
    hasher: blake3::Hasher,
    bytes: u64,
}

impl std::io::Write for DigestWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let written = self.file.write(buf)?;
        self.hasher.update(&buf[..written]);
        self.bytes += written as u64;
        Ok(written)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.file.flush()
    }
}

/// Buffer of the file writer and size of the pieces a large tensor is copied out in: large
/// enough that each write is one long sequential request, small against any tensor's memory.
const WRITE_CHUNK_BYTES: usize = 64 << 20;

/// Writes `path` through `fill`: into a temporary file in the same folder, flushed to the disk
/// (`fsync`) and renamed, so `path` is either absent, the old file or the complete new one. On
/// any error the temporary file is removed and the error names `path`.
fn write_digested(
    path: &Path,
    fill: impl FnOnce(&mut DigestWriter) -> std::result::Result<(), Error>,
) -> Result<WrittenFile> {
    let temp = path.with_file_name(format!(
        ".{}.tmp-{}",
        path.file_name().unwrap_or_default().to_string_lossy(),
        std::process::id()
    ));
    let io = |error| Error::Io { path: path.to_path_buf(), error };
    let result = (|| -> Result<WrittenFile> {
        let file = std::fs::File::create(&temp).map_err(io)?;
        let mut out = DigestWriter {
            file: std::io::BufWriter::with_capacity(WRITE_CHUNK_BYTES, file),
            hasher: blake3::Hasher::new(),
            bytes: 0,
        };
        fill(&mut out)?;
        let file = out.file.into_inner().map_err(|e| io(e.into_error()))?;
        file.sync_all().map_err(io)?;
        std::fs::rename(&temp, path).map_err(io)?;
        Ok(WrittenFile {
            path: path.to_path_buf(),
            bytes: out.bytes,
            blake3: out.hasher.finalize().to_hex().to_string(),
        })
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&temp);
    }
    result
}

/// Writes `bytes` to `path` atomically (see [`write_digested`]).
pub fn write_file(path: &Path, bytes: &[u8]) -> Result<WrittenFile> {
    write_digested(path, |out| {
        std::io::Write::write_all(out, bytes).map_err(|error| Error::Io { path: path.to_path_buf(), error })
    })
}

/// Writes named tensors as one safetensors file (the layout `Tensor::write_safetensors` and
/// diffusers write: tensors ordered by dtype, then name; metadata `format: pt`), streamed tensor
/// by tensor (never more than one tensor's bytes in memory) through the hasher to disk, atomically
/// (see [`write_digested`]).
pub fn write_safetensors(path: &Path, tensors: &[(String, Tensor)]) -> Result<WrittenFile> {
    let bad = |reason: String| Error::Safetensors { path: path.to_path_buf(), reason };
    let mut order: Vec<(&String, &Tensor, Dtype)> =
        tensors.iter().map(|(name, t)| Ok((name, t, storage_dtype(name, t.kind())?))).collect::<Result<_>>()?;
    order.sort_by(|(a, _, da), (b, _, db)| db.cmp(da).then(a.cmp(b)));
    let mut infos = Vec::with_capacity(order.len());
    let mut offset = 0usize;
    for (name, tensor, dtype) in &order {
        let len = tensor.numel() * tensor.kind().elt_size_in_bytes();
        let shape = tensor.size().iter().map(|&d| d as usize).collect();
        infos.push((
            (*name).clone(),
            safetensors::tensor::TensorInfo { dtype: *dtype, shape, data_offsets: (offset, offset + len) },
        ));
        offset += len;
    }
    let metadata = Some(std::collections::HashMap::from([("format".to_string(), "pt".to_string())]));
    let header = safetensors::tensor::Metadata::new(metadata, infos).map_err(|e| bad(e.to_string()))?;
    let mut header = serde_json::to_string(&header).map_err(|e| bad(e.to_string()))?.into_bytes();
    // The data starts 8-byte aligned (the safetensors crate pads its headers with spaces so).
    header.resize(header.len().next_multiple_of(8), b' ');
    write_digested(path, |out| {
        let io = |error| Error::Io { path: path.to_path_buf(), error };
        std::io::Write::write_all(out, &(header.len() as u64).to_le_bytes()).map_err(io)?;
        std::io::Write::write_all(out, &header).map_err(io)?;
        let mut buffer = Vec::new();
        for (_, tensor, _) in &order {
            let flat = tensor.f_detach()?.f_to_device(Device::Cpu)?.f_contiguous()?.f_reshape([-1])?;
            let element = flat.kind().elt_size_in_bytes();
            let total = flat.numel();
            let step = (WRITE_CHUNK_BYTES / element).max(1);
            for start in (0..total).step_by(step) {
                let n = step.min(total - start);
                buffer.resize(n * element, 0);
                flat.f_narrow(0, start as i64, n as i64)?.f_copy_data_u8(&mut buffer, n)?;
                std::io::Write::write_all(out, &buffer).map_err(io)?;
            }
        }
        Ok(())
    })
}

/// The safetensors dtype a tensor of `kind` is stored as.
fn storage_dtype(name: &str, kind: Kind) -> Result<Dtype> {
    Ok(match kind {
        Kind::Int64 => Dtype::I64,
        Kind::Int => Dtype::I32,
        Kind::Uint8 => Dtype::U8,
        Kind::Int8 => Dtype::I8,
        Kind::Bool => Dtype::BOOL,
        floating => dtype_of(floating).map_err(|_| Error::DtypeDevice {
            tensor: name.to_string(),
            expected: "a floating-point, integer or bool kind".to_string(),
            actual: format!("{floating:?}"),
        })?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::models::vars::Vars;

    fn tiny_store(device: Device) -> nn::VarStore {
        let vs = nn::VarStore::new(device);
        let vars = Vars::new(vs.root());
        vars.sub("a").linear(3, 4, true).unwrap();
        vars.sub("b").layer_norm(4, 1e-5, true).unwrap();
        let _ = vars.buffer("pos", &[1, 2], || Ok(Tensor::from_slice(&[1.0f32, 2.0]).view([1, 2]))).unwrap();
        vs
    }

    /// A config to save beside weights it does not describe (the weights tests read only the
    /// weights).
    fn any_config() -> crate::models::wan::autoencoder_kl_wan::AutoencoderKLWanConfig {
        crate::models::wan::autoencoder_kl_wan::AutoencoderKLWanConfig::tiny()
    }
    const ANY_CLASS: &str = crate::models::wan::autoencoder_kl_wan::CLASS_NAME;

    #[test]
    fn a_saved_config_goes_through_diffusers_config_and_keeps_unknown_keys() {
        use crate::models::wan::transformer_wan::{CLASS_NAME, WanTransformer3DModelConfig};
        // A config as another diffusers release wrote it, with a key this port does not know.
        let file = r#"{"_class_name": "WanTransformer3DModel", "_diffusers_version": "0.30.0",
            "num_layers": 2, "attention_head_dim": 8, "num_attention_heads": 2, "ffn_dim": 32,
            "text_dim": 16, "freq_dim": 16, "rope_max_seq_len": 32, "a_future_key": [1, "two"]}"#;
        let config = WanTransformer3DModelConfig::from_json_str(file, "in.json").unwrap();
        let dir = tempfile::tempdir().unwrap();
        save(&tiny_store(Device::Cpu), &config, CLASS_NAME, dir.path(), DEFAULT_MAX_SHARD_BYTES).unwrap();
        let written = std::fs::read_to_string(dir.path().join("config.json")).unwrap();
        let value: serde_json::Value = serde_json::from_str(&written).unwrap();
        assert_eq!(value["a_future_key"], serde_json::json!([1, "two"]), "{written}");
        assert_eq!(value["_diffusers_version"], crate::diffusers_config::DIFFUSERS_VERSION);
        let again = WanTransformer3DModelConfig::from_json_str(&written, "out.json").unwrap();
        let mut expected = config.clone();
        expected.extra.insert("_diffusers_version".to_string(), crate::diffusers_config::DIFFUSERS_VERSION.into());
        assert_eq!(again, expected);
        // A class the config cannot be is refused, not written.
        let e = config.to_json_string("CogVideoXTransformer3DModel").unwrap_err().to_string();
        assert!(e.contains("CogVideoXTransformer3DModel") && e.contains("transformer config"), "{e}");
    }

    #[test]
    fn save_then_load_round_trips_single_and_sharded() {
        let vs = tiny_store(Device::Cpu);
        let dir = tempfile::tempdir().unwrap();
        for (name, shard_bytes) in [("single", DEFAULT_MAX_SHARD_BYTES), ("sharded", 40)] {
            let folder = dir.path().join(name);
            save(&vs, &any_config(), ANY_CLASS, &folder, shard_bytes).unwrap();
            let sharded = folder.join(WEIGHTS_INDEX_NAME).exists();
            assert_eq!(sharded, name == "sharded");
            let other = tiny_store(Device::Cpu);
            assert_eq!(load(&other, &folder).unwrap(), 5);
            for (k, v) in vs.variables() {
                let w = &other.variables()[&k];
                assert!(v.equal(w), "{k} differs after {name} round trip");
            }
        }
    }

    #[test]
    fn streamed_safetensors_read_back_and_their_digest_is_of_the_bytes_written() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("state.safetensors");
        // One tensor longer than a write chunk, so it goes out in two pieces.
        let long = (WRITE_CHUNK_BYTES / 4 + 1) as i64;
        let tensors = vec![
            ("exp_avg.b".to_string(), Tensor::randn([3, 5], (Kind::Float, Device::Cpu))),
            ("step".to_string(), Tensor::from_slice(&[7i64])),
            ("a.bf16".to_string(), Tensor::randn([11], (Kind::BFloat16, Device::Cpu))),
            ("master".to_string(), Tensor::arange(long, (Kind::Float, Device::Cpu))),
        ];
        let written = write_safetensors(&path, &tensors).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(written.bytes, bytes.len() as u64);
        assert_eq!(written.blake3, blake3::hash(&bytes).to_hex().to_string());
        // The safetensors crate's parser accepts the header, tch reads every tensor back.
        SafeTensors::deserialize(&bytes).unwrap();
        let read: BTreeMap<String, Tensor> = Tensor::read_safetensors(&path).unwrap().into_iter().collect();
        for (name, tensor) in &tensors {
            assert!(read[name].equal(tensor), "{name}");
        }
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(left, vec!["state.safetensors"], "no temporary file is left");
    }

    #[test]
    fn mismatches_name_the_tensor_and_both_shapes() {
        let vs = tiny_store(Device::Cpu);
        let dir = tempfile::tempdir().unwrap();
        save(&vs, &any_config(), ANY_CLASS, dir.path(), DEFAULT_MAX_SHARD_BYTES).unwrap();
        let bigger = nn::VarStore::new(Device::Cpu);
        let vars = Vars::new(bigger.root());
        vars.sub("a").linear(3, 5, true).unwrap();
        vars.sub("b").layer_norm(4, 1e-5, true).unwrap();
        let _ = vars.buffer("pos", &[1, 2], || Ok(Tensor::zeros([1, 2], (Kind::Float, Device::Cpu)))).unwrap();
        let err = load(&bigger, dir.path()).unwrap_err().to_string();
        assert!(err.contains("a.bias") || err.contains("a.weight"), "{err}");
        assert!(err.contains("[5") && err.contains("[4"), "{err}");
        let fewer = nn::VarStore::new(Device::Cpu);
        Vars::new(fewer.root()).sub("a").linear(3, 4, true).unwrap();
        let err = load(&fewer, dir.path()).unwrap_err().to_string();
        assert!(err.contains("unexpected") && err.contains("b."), "{err}");
    }

    #[test]
    fn shapes_only_allocates_nothing_per_element() {
        let vs = nn::VarStore::new(Device::Cpu);
        let lin = Vars::shapes_only(vs.root()).sub("big").linear(100_000, 100_000, true).unwrap();
        assert_eq!(lin.weight().size(), vec![100_000, 100_000]);
        assert_eq!(lin.weight().stride(), vec![0, 0]);
    }
}

//! A cache of VAE latents per training sample, shared by runs and resumed runs.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use tch::{Device, Kind, Tensor, nn};

use crate::error::{Error, Result};
use crate::models::backbone::Vae;
use crate::training::data::{Batch, DataConfig};

/// Precomputed VAE latents, so that small runs encode each pair once and train many epochs:
/// per sample (clip, trajectory, window — the batch's provenance — at the configured size) the
/// target's posterior (mean, log-variance; a fresh sample is drawn at every use, as without the
/// cache) and the conditioning latent. The conditioning's noise augmentation is then drawn once
/// per sample (seeded by the sample) instead of at every use: the cache trades augmentation
/// variety for speed. Entries are keyed by the sample, the data size and the VAE's weights, and
/// written atomically, so runs and resumed runs share them; a cached entry equals a fresh one
/// bit for bit.
pub struct LatentCache {
    dir: PathBuf,
    prefix: String,
}

impl LatentCache {
    /// A cache in `dir` for the VAE `vae` (its weights in `vae_vs`) and the data size.
    pub fn open(dir: &Path, vae: &Vae, vae_vs: &nn::VarStore, data: &DataConfig) -> Result<Self> {
        std::fs::create_dir_all(dir).map_err(|source| Error::Io { path: dir.to_path_buf(), error: source })?;
        let mut hasher = blake3::Hasher::new();
        hasher.update(b"cognvs latent cache v1");
        hasher.update(vae.config_fingerprint().as_bytes());
        let mut variables: Vec<(String, Tensor)> = vae_vs.variables().into_iter().collect();
        variables.sort_by(|a, b| a.0.cmp(&b.0));
        for (name, tensor) in variables {
            hasher.update(name.as_bytes());
            let t = tensor.f_to_kind(Kind::Float)?.f_to_device(Device::Cpu)?.f_contiguous()?;
            let values = Vec::<f32>::try_from(t.f_flatten(0, -1)?)?;
            for v in values {
                hasher.update(&v.to_le_bytes());
            }
        }
        hasher.update(format!("{}x{}x{}", data.frames, data.height, data.width).as_bytes());
        Ok(Self { dir: dir.to_path_buf(), prefix: hasher.finalize().to_hex()[..16].to_string() })
    }

    fn key(&self, provenance: &str) -> (PathBuf, i64) {
        let hash = blake3::hash(format!("{}/{provenance}", self.prefix).as_bytes());
        let seed = i64::from_le_bytes(hash.as_bytes()[..8].try_into().expect("8 bytes")) & i64::MAX;
        (self.dir.join(format!("{}.safetensors", &hash.to_hex()[..32])), seed)
    }

    /// Sample `i` of `batch`: (posterior mean, log-variance, the transformer's condition channels:
    /// the conditioning's posterior mean as the model sees it and, for Wan, the mask channels
    /// before it; see [`Vae::condition_input`]), from the cache or encoded with `vae` on `device`
    /// and stored.
    pub(super) fn get_or_encode(
        &self,
        vae: &Vae,
        device: Device,
        batch: &Batch,
        (i, noise_log_mean, noise_log_std): (i64, f64, f64),
    ) -> Result<(Tensor, Tensor, Tensor)> {
        let (path, seed) = self.key(&batch.provenance[i as usize]);
        if let Ok(entries) = Tensor::read_safetensors(&path) {
            let map: BTreeMap<String, Tensor> = entries.into_iter().collect();
            if let (Some(m), Some(l), Some(c)) = (map.get("mean"), map.get("logvar"), map.get("condition")) {
                return Ok((m.f_to_device(device)?, l.f_to_device(device)?, c.f_to_device(device)?));
            }
        }
        tch::manual_seed(seed);
        let target = batch.target.f_narrow(0, i, 1)?.f_to_device(device)?;
        let condition = batch.condition.f_narrow(0, i, 1)?.f_to_device(device)?;
        let sigma = (Tensor::f_randn([1], (Kind::Float, Device::Cpu))?.double_value(&[0]) * noise_log_std
            + noise_log_mean)
            .exp();
        let noisy = condition.f_add(&condition.f_randn_like()?.f_mul_scalar(sigma)?)?.f_to_kind(vae.kind())?;
        let target = target.f_to_kind(vae.kind())?;
        let (posterior, cond) = tch::no_grad(|| -> Result<_> {
            let posterior = vae.encode_posterior(&target)?;
            let cond = vae.encode_posterior(&noisy)?.mean;
            Ok((posterior, cond))
        })?;
        let cond = vae.condition_input(&vae.to_model_latent(&cond)?, &batch.mask.f_narrow(0, i, 1)?)?;
        let temp = path.with_extension(format!("tmp-{}", std::process::id()));
        Tensor::write_safetensors(
            &[("mean", &posterior.mean), ("logvar", &posterior.logvar), ("condition", &cond)],
            &temp,
        )
        .map_err(|e| Error::Safetensors { path: temp.clone(), reason: e.to_string() })?;
        std::fs::rename(&temp, &path).map_err(|source| Error::Io { path: path.clone(), error: source })?;
        Ok((posterior.mean, posterior.logvar, cond))
    }
}

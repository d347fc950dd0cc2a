//! Validation while training: every `[loop] validate_every` steps the model samples novel views
//! of held-out pairs and the samples are measured against their targets.
//!
//! The held-out pairs come from `[validation] shards` and/or a `holdout_fraction` of the training
//! shards' clips, chosen by a hash of the clip id and removed from the training set (see
//! [`split_training_clips`]). The set is fixed for the run: the first `pairs` clips of the
//! held-out clips' order for `[validation] seed`, each with its trajectory and window drawn from
//! that seed, and each sampled with noise seeded by the validation seed and its index only, so a
//! value moves between validations because the model did. The metrics are those of `trainer
//! eval` (PSNR and SSIM in scikit-image's conventions, LPIPS as the `lpips` package, each over
//! whole frames and over the co-visible pixels, per pair the mean over its frames), averaged over
//! the pairs. With several ranks, pair `i` is sampled by rank `i mod N` and the sums are reduced,
//! so the values do not depend on the world size. Rank 0 also writes the first pair's sample
//! (`RUN/samples/step-N/`: `sample.mp4`, `contact_sheet.png`, `pair.json`).
//!
//! Without a `[validation]` section only that sample is made, of the first training pair (the
//! trainer's behaviour before held-out validation).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use image::{GrayImage, RgbImage};
use serde::{Deserialize, Serialize};
use tch::Device;

use super::{CogNvsModel, PretrainConfig, consensus};
use crate::distributed::ProcessGroup;
use crate::error::{Error, Result};
use crate::eval::lpips::Lpips;
use crate::models::backbone::{Transformer, Vae};
use crate::training::data::{Batch, ClipIndex, DataConfig, DataPosition, ShardLoader};

/// Means over the validation pairs, as logged (`metrics.jsonl`: `{"step": N, "validation": …}`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ValidationMetrics {
    /// Pairs measured (over all ranks).
    pub pairs: usize,
    /// Mean PSNR (dB) over whole frames.
    pub psnr: Option<f64>,
    /// Mean SSIM over whole frames.
    pub ssim: Option<f64>,
    /// Mean PSNR over co-visible pixels.
    pub psnr_covisible: Option<f64>,
    /// Mean SSIM over co-visible pixels.
    pub ssim_covisible: Option<f64>,
    /// Mean LPIPS (with `[validation] lpips_weights`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lpips: Option<f64>,
    /// Mean LPIPS over co-visible pixels (with `[validation] lpips_weights`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lpips_covisible: Option<f64>,
}

impl ValidationMetrics {
    /// The TensorBoard scalars (`validation/psnr`, …) of the values present.
    pub fn scalars(&self) -> Vec<(&'static str, f32)> {
        [
            ("validation/psnr", self.psnr),
            ("validation/ssim", self.ssim),
            ("validation/psnr_covisible", self.psnr_covisible),
            ("validation/ssim_covisible", self.ssim_covisible),
            ("validation/lpips", self.lpips),
            ("validation/lpips_covisible", self.lpips_covisible),
        ]
        .into_iter()
        .filter_map(|(tag, value)| value.map(|v| (tag, v as f32)))
        .collect()
    }
}

/// Whether clip `clip_id` (`{dataset}/{source_id}/{clip_start}`) is held out at `fraction`: its
/// video is, when the first 8 bytes of a BLAKE3 of `{dataset}/{source_id}`, as a fraction of 2^64,
/// fall below it (stable across runs, seeds and shard orders). Whole videos are held out, never
/// single clips: the windows of one video share its scene, objects and camera, so a clip held out
/// beside its trained neighbours would measure memory, not novel views.
pub fn is_held_out(clip_id: &str, fraction: f64) -> bool {
    let video = clip_id.rsplit_once('/').map_or(clip_id, |(video, _start)| video);
    let mut hasher = blake3::Hasher::new();
    hasher.update(b"cognvs held-out video v1\0");
    hasher.update(video.as_bytes());
    let bytes: [u8; 8] = hasher.finalize().as_bytes()[..8].try_into().expect("8 bytes");
    (u64::from_le_bytes(bytes) as f64) < fraction * 2f64.powi(64)
}

/// The clips of `shards` to train on, and the held-out clips (from `[validation] shards` and
/// those of the training shards `holdout_fraction` selects), if the config has a
/// `[validation]` section. Errors when a validation shard is also a training shard or when
/// nothing is left on either side.
pub fn split_training_clips(config: &PretrainConfig, shards: &[PathBuf]) -> Result<(ClipIndex, Option<ClipIndex>)> {
    let all = ClipIndex::open(shards)?;
    let Some(v) = &config.validation else { return Ok((all, None)) };
    let bad = |field: &str, reason: String| Error::InvalidConfig {
        source_name: config.source_name(),
        field: field.to_string(),
        reason,
    };
    let (held, train) = all.split_by_id(|id| is_held_out(id, v.holdout_fraction))?;
    if train.is_empty() {
        return Err(bad(
            "validation.holdout_fraction",
            format!("{} holds out all {} training clips", v.holdout_fraction, all.len()),
        ));
    }
    let held = if v.shards.is_empty() {
        held
    } else {
        let given = ClipIndex::open(&v.shards)?;
        let canonical = |p: &Path| p.canonicalize().unwrap_or_else(|_| p.to_path_buf());
        let training: Vec<PathBuf> = all.shards().iter().map(|p| canonical(p)).collect();
        if let Some(shared) = given.shards().iter().find(|p| training.contains(&canonical(p))) {
            return Err(bad(
                "validation.shards",
                format!("{} is a training shard too: held-out pairs must never be trained on", shared.display()),
            ));
        }
        if held.is_empty() { given } else { held.joined(&given) }
    };
    if held.is_empty() {
        return Err(bad(
            "validation.holdout_fraction",
            format!(
                "{} holds out none of the {} training clips: raise it or give shards",
                v.holdout_fraction,
                all.len()
            ),
        ));
    }
    Ok((train, Some(held)))
}

/// What a validation measures and on which pairs.
pub struct Validation {
    held_out: Option<HeldOut>,
}

struct HeldOut {
    index: Arc<ClipIndex>,
    pairs: usize,
    data: DataConfig,
    lpips: Option<Lpips>,
}

impl Validation {
    /// The validation of `config` over `held_out` clips (None: the first training pair of
    /// `shards`, sample only). Loads the LPIPS weights, so a bad file fails at the start.
    pub fn new(config: &PretrainConfig, held_out: Option<ClipIndex>, device: Device) -> Result<Self> {
        let held_out = match (&config.validation, held_out) {
            (Some(v), Some(index)) => Some(HeldOut {
                pairs: v.pairs.min(index.len()),
                index: Arc::new(index),
                // Every held-out pair is measured, whatever its kind: no training mix here.
                data: DataConfig {
                    batch_size: 1,
                    rank: 0,
                    world_size: 1,
                    seed: v.seed,
                    multiview_share: None,
                    ..config.data.clone()
                },
                lpips: match &v.lpips_weights {
                    Some(path) => Some(Lpips::load(path, v.lpips_net, device)?),
                    None => None,
                },
            }),
            _ => None,
        };
        Ok(Self { held_out })
    }

    /// Pairs measured at each validation (0: sample only).
    pub fn pairs(&self) -> usize {
        self.held_out.as_ref().map_or(0, |h| h.pairs)
    }

    /// Samples and measures this rank's share of the pairs after `step` (every rank calls it),
    /// writes rank 0's first sample under `run`, and returns the reduced means (held-out
    /// validation) and the first pair's contact sheet (rank 0).
    pub fn run(
        &self,
        step: u64,
        model: &CogNvsModel,
        config: &PretrainConfig,
        shards: &[PathBuf],
        run: &Path,
        pg: Option<&ProcessGroup>,
    ) -> Result<(Option<ValidationMetrics>, Option<RgbImage>)> {
        let (rank, world) = pg.map_or((0, 1), |pg| (pg.rank, pg.world_size));
        let Some(held) = &self.held_out else {
            // The first training pair, sampled by rank 0 while the others wait.
            let sheet = if rank == 0 {
                let data = DataConfig { batch_size: 1, rank: 0, world_size: 1, ..config.data.clone() };
                let batch = ShardLoader::open(shards, data, DataPosition::default())?.next_batch()?;
                let seed = super::objective::step_seed(config.train.seed ^ VALIDATION_SEED, step);
                Some(sample_pair(model, &batch, seed, config.train.validation_steps)?.write(run, step, &batch)?)
            } else {
                None
            };
            if let Some(pg) = pg {
                pg.barrier("validation sample on rank 0")?;
            }
            return Ok((None, sheet));
        };
        let mut sums = Sums::default();
        let mut sheet = None;
        let mut loader = ShardLoader::new(held.index.clone(), held.data.clone(), DataPosition::default())?;
        for i in 0..held.pairs {
            let batch = loader.next_batch()?;
            if i % world != rank {
                continue;
            }
            let seed = super::objective::step_seed(held.data.seed ^ VALIDATION_SEED, i as u64);
            let sampled = sample_pair(model, &batch, seed, config.train.validation_steps)?;
            sums.add(&sampled, held.lpips.as_ref(), model.text.device())?;
            if i == 0 {
                sheet = Some(sampled.write(run, step, &batch)?);
            }
        }
        let reduced = consensus::sum_over_ranks(pg, &sums.values(), "validation metrics")?;
        Ok((Some(Sums::means(&reduced)), sheet))
    }
}

/// Mixed into the seed of validation sampling (so it differs from the training draws).
const VALIDATION_SEED: u64 = 0x5eed_0f5a_3b1e;
/// Frame rate of validation videos (CogVideoX's 8 fps).
const VALIDATION_FPS: f64 = 8.0;
/// Frames shown on a validation contact sheet.
const SHEET_ROWS: usize = 4;

/// One pair's sample, target, conditioning and co-visibility, as frames.
struct Sampled {
    sample: Vec<RgbImage>,
    target: Vec<RgbImage>,
    condition: Vec<RgbImage>,
    masks: Vec<GrayImage>,
}

/// Samples the first pair of `batch` from its conditioning, with tch's generator seeded by
/// `seed` (every training step reseeds, so this does not change the training run).
fn sample_pair(model: &CogNvsModel, batch: &Batch, seed: i64, steps: usize) -> Result<Sampled> {
    let device = model.text.device();
    let condition = batch.condition.f_narrow(0, 0, 1)?.f_to_device(device)?;
    tch::manual_seed(seed);
    // The config check refuses validation for a family the sampler does not run yet.
    let (Transformer::CogVideoX(transformer), Vae::CogVideoX(vae)) = (&model.transformer, &model.vae) else {
        return Err(Error::InvalidArgument {
            name: "validation".to_string(),
            reason: format!(
                "validation samples CogVideoX models only so far, not {}",
                model.transformer.family().name()
            ),
        });
    };
    let video = crate::pipelines::sampling::generate(transformer, vae, &condition, &model.text, None, steps, 1.0)?;
    let mask = batch.mask.f_narrow(0, 0, 1)?.f_squeeze_dims([0, 1])?;
    let (frames, height, width) = (mask.size()[0], mask.size()[1] as u32, mask.size()[2] as u32);
    let masks = (0..frames)
        .map(|f| {
            let values = Vec::<f32>::try_from(mask.f_get(f)?.f_flatten(0, -1)?)?;
            let pixels = values.iter().map(|&v| if v > 0.5 { 255 } else { 0 }).collect();
            Ok(GrayImage::from_raw(width, height, pixels).expect("a mask frame has height × width values"))
        })
        .collect::<Result<_>>()?;
    Ok(Sampled {
        sample: crate::pipelines::sampling::to_frames(&video)?,
        target: crate::pipelines::sampling::to_frames(&batch.target.f_narrow(0, 0, 1)?)?,
        condition: crate::pipelines::sampling::to_frames(&condition)?,
        masks,
    })
}

impl Sampled {
    /// Writes `RUN/samples/step-N/` (video, contact sheet, the pair's provenance); returns the sheet.
    fn write(&self, run: &Path, step: u64, batch: &Batch) -> Result<RgbImage> {
        let dir = run.join("samples").join(format!("step-{step:08}"));
        std::fs::create_dir_all(&dir).map_err(|source| Error::Io { path: dir.clone(), error: source })?;
        foundation::video::encode_video(&dir.join("sample.mp4"), &self.sample, VALIDATION_FPS)?;
        let last = self.sample.len() - 1;
        let rows: Vec<Vec<RgbImage>> = (0..SHEET_ROWS)
            .map(|k| k * last / (SHEET_ROWS - 1))
            .map(|i| vec![self.target[i].clone(), self.condition[i].clone(), self.sample[i].clone()])
            .collect();
        let sheet = foundation::contact_sheet::contact_sheet(&rows);
        let sheet_path = dir.join("contact_sheet.png");
        sheet.save(&sheet_path).map_err(|e| Error::InvalidInput {
            path: sheet_path.clone(),
            what: "contact sheet".to_string(),
            reason: e.to_string(),
        })?;
        let provenance = serde_json::json!({ "step": step, "pair": batch.provenance[0] });
        std::fs::write(dir.join("pair.json"), provenance.to_string())
            .map_err(|source| Error::Io { path: dir, error: source })?;
        Ok(sheet)
    }
}

/// Per-pair metric sums and counts of this rank, reduced over ranks as one vector.
#[derive(Default)]
struct Sums {
    pairs: f64,
    /// (sum, count) of psnr, ssim, psnr_covisible, ssim_covisible, lpips, lpips_covisible.
    metrics: [(f64, f64); 6],
}

impl Sums {
    fn add(&mut self, s: &Sampled, lpips: Option<&Lpips>, device: Device) -> Result<()> {
        let m = crate::eval::metrics::video_metrics(&s.sample, &s.target, Some(&s.masks))?;
        let (lpips, lpips_covisible) = match lpips {
            Some(model) => {
                let (plain, masked) =
                    crate::eval::score::lpips_frames(model, &s.sample, &s.target, Some(&s.masks), device)?;
                (mean(plain.into_iter()), mean(masked.into_iter().flatten()))
            }
            None => (None, None),
        };
        self.pairs += 1.0;
        let values = [Some(m.psnr), Some(m.ssim), m.masked_psnr, m.masked_ssim, lpips, lpips_covisible];
        for ((sum, count), value) in self.metrics.iter_mut().zip(values) {
            // A pair with identical frames has an infinite PSNR: it cannot enter a mean.
            if let Some(v) = value.filter(|v| v.is_finite()) {
                *sum += v;
                *count += 1.0;
            }
        }
        Ok(())
    }

    fn values(&self) -> Vec<f64> {
        std::iter::once(self.pairs).chain(self.metrics.iter().flat_map(|&(sum, count)| [sum, count])).collect()
    }

    fn means(reduced: &[f64]) -> ValidationMetrics {
        let mean_at = |k: usize| {
            let (sum, count) = (reduced[1 + 2 * k], reduced[2 + 2 * k]);
            (count > 0.0).then(|| sum / count)
        };
        ValidationMetrics {
            pairs: reduced[0] as usize,
            psnr: mean_at(0),
            ssim: mean_at(1),
            psnr_covisible: mean_at(2),
            ssim_covisible: mean_at(3),
            lpips: mean_at(4),
            lpips_covisible: mean_at(5),
        }
    }
}

fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let v: Vec<f64> = values.filter(|v| v.is_finite()).collect();
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn held_out_videos_follow_the_fraction_and_never_change() {
        let ids: Vec<String> = (0..20_000).map(|i| format!("sav/sav_{i:06}/{}", i % 7 * 49)).collect();
        let held = ids.iter().filter(|id| is_held_out(id, 0.1)).count();
        assert!((1_800..2_200).contains(&held), "{held} of 20000 at 0.1");
        // Every clip of a video is on the same side as its first.
        for video in ["sav/sav_000003", "ytvos/0a2f", "davis/bear"] {
            let side = is_held_out(&format!("{video}/0"), 0.5);
            assert!((1..40).all(|k| is_held_out(&format!("{video}/{}", k * 4), 0.5) == side), "{video}");
        }
        let sides: Vec<bool> = (0..64).map(|i| is_held_out(&format!("sav/sav_{i:06}/0"), 0.5)).collect();
        assert!(sides.contains(&true) && sides.contains(&false), "videos, not the clip start, decide");
        // A larger fraction holds out a superset; none at 0.
        assert!(ids.iter().all(|id| !is_held_out(id, 0.1) || is_held_out(id, 0.3)));
        assert!(ids.iter().all(|id| !is_held_out(id, 0.0)));
    }

    #[test]
    fn means_over_ranks_equal_means_over_all_pairs() {
        // Two ranks' sums reduced give the mean over every pair, counting only finite values.
        let rank = |values: &[(f64, Option<f64>)]| {
            let mut sums = Sums::default();
            for &(psnr, lpips) in values {
                sums.pairs += 1.0;
                for (k, v) in [(0, Some(psnr)), (4, lpips)] {
                    if let Some(v) = v.filter(|v| v.is_finite()) {
                        sums.metrics[k].0 += v;
                        sums.metrics[k].1 += 1.0;
                    }
                }
            }
            sums.values()
        };
        let a = rank(&[(20.0, Some(0.5)), (f64::INFINITY, None)]);
        let b = rank(&[(26.0, Some(0.25))]);
        let reduced: Vec<f64> = a.iter().zip(&b).map(|(x, y)| x + y).collect();
        let m = Sums::means(&reduced);
        assert_eq!(m.pairs, 3);
        assert_eq!(m.psnr, Some(23.0));
        assert_eq!(m.lpips, Some(0.375));
        assert_eq!(m.ssim, None);
    }
}

//! `trainer eval` over folders: predicted and target videos matched by name,
//! resized as the protocol says, scored per video (PSNR, SSIM, LPIPS and, with masks, mPSNR,
//! mSSIM, mLPIPS) and as a set (FID, KID over every frame of every video, as the GCD and CogNVS
//! evaluations pool frames), printed as Markdown and JSON.
//!
//! Layout: `PRED/NAME` and `TARGET/NAME` are each a video file or a folder of frames, matched by
//! name without extension; `MASK/NAME/` holds that video's mask PNGs (non-zero = co-visible).
//! With `--top-k K`, `PRED/NAME/` holds K samples (video files or frame folders, taken in name
//! order) and the one with the best PSNR (mPSNR when masks are given) is scored, as the paper's
//! appendix reports best-of-K.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use image::{GrayImage, RgbImage};
use serde::Serialize;
use tch::{Device, Tensor};

use super::fid::{frechet_distance, kernel_distance};
use super::inception::FidInception;
use super::lpips::{Lpips, LpipsNet, frames_to_input};
use crate::error::{Error, Result};
use crate::eval::metrics::{read_masks, read_named_frames, video_metrics};

/// Frames per LPIPS / Inception batch (bounds memory at DyCheck's 960×720 with VGG).
const BATCH: usize = 4;

/// An evaluation protocol: the size both videos are resized to before scoring.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Protocol {
    /// GCD's Kubric-4D / ParallelDomain-4D protocol: 384×576 (H×W), as the paper's Table 1.
    Gcd,
    /// DyCheck (iPhone): 960×720 (H×W), the paper's Table 2 resolution.
    Dycheck,
}

impl Protocol {
    /// (width, height) of the protocol.
    pub fn size(self) -> (u32, u32) {
        match self {
            Protocol::Gcd => (576, 384),
            Protocol::Dycheck => (720, 960),
        }
    }
}

/// What to evaluate and with which weights.
#[derive(Debug, Clone)]
pub struct ScoreRequest {
    /// Predictions: a folder of videos, or (single pair) one video.
    pub pred: PathBuf,
    /// Targets, laid out like `pred`.
    pub target: PathBuf,
    /// Mask folders (one per video), or one folder of masks for a single pair.
    pub mask: Option<PathBuf>,
    /// Treat `pred`/`target` as one video each instead of folders of videos.
    pub single: bool,
    /// Resize to the protocol's size; None: sizes must agree.
    pub protocol: Option<Protocol>,
    /// Samples per prediction to pick the best of.
    pub top_k: Option<usize>,
    /// LPIPS weight file (None: no LPIPS).
    pub lpips: Option<PathBuf>,
    /// LPIPS backbone.
    pub lpips_net: LpipsNet,
    /// Inception weights for FID (None: no FID/KID).
    pub inception: Option<PathBuf>,
    /// Compute KID (with `inception`).
    pub kid: bool,
    /// KID subsets.
    pub kid_subsets: usize,
    /// KID subset size.
    pub kid_subset_size: usize,
    /// Seed of KID's subsets.
    pub seed: u64,
    /// Device of the networks.
    pub device: Device,
}

/// The metrics of one video (of its best sample with top-k).
#[derive(Debug, Clone, Serialize)]
pub struct VideoRow {
    /// The video's name.
    pub name: String,
    /// Frames scored.
    pub frames: usize,
    /// With top-k: the index of the sample chosen.
    pub sample: Option<usize>,
    /// Mean PSNR over frames.
    pub psnr: f64,
    /// Mean SSIM.
    pub ssim: f64,
    /// Mean LPIPS.
    pub lpips: Option<f64>,
    /// Mean masked PSNR (mPSNR).
    pub masked_psnr: Option<f64>,
    /// Mean masked SSIM (mSSIM).
    pub masked_ssim: Option<f64>,
    /// Mean masked LPIPS (mLPIPS).
    pub masked_lpips: Option<f64>,
}

/// The whole table.
#[derive(Debug, Clone, Serialize)]
pub struct ScoreReport {
    /// The protocol used.
    pub protocol: Option<Protocol>,
    /// Per video.
    pub videos: Vec<VideoRow>,
    /// Means over videos (name "mean").
    pub mean: VideoRow,
    /// FID over all frames.
    pub fid: Option<f64>,
    /// KID over all frames.
    pub kid: Option<f64>,
}

fn entries(dir: &Path) -> Result<BTreeMap<String, PathBuf>> {
    let read = std::fs::read_dir(dir).map_err(|error| Error::Io { path: dir.to_path_buf(), error })?;
    let mut out = BTreeMap::new();
    for entry in read.filter_map(|e| e.ok()) {
        let path = entry.path();
        let name = if path.is_dir() {
            path.file_name().map(|n| n.to_string_lossy().to_string())
        } else {
            path.file_stem().map(|n| n.to_string_lossy().to_string())
        };
        if let Some(name) = name.filter(|n| !n.starts_with('.')) {
            out.insert(name, path);
        }
    }
    Ok(out)
}

/// One video to score: `(name, pred, target, mask folder)`.
pub type Pair = (String, PathBuf, PathBuf, Option<PathBuf>);

/// Every video's [`Pair`], or an error naming what does not match.
fn pairs(req: &ScoreRequest) -> Result<Vec<Pair>> {
    if req.single {
        let name = req.target.file_stem().map_or("video".to_string(), |n| n.to_string_lossy().to_string());
        return Ok(vec![(name, req.pred.clone(), req.target.clone(), req.mask.clone())]);
    }
    let (pred, target) = (entries(&req.pred)?, entries(&req.target)?);
    let missing: Vec<&String> = target.keys().filter(|k| !pred.contains_key(*k)).collect();
    let extra: Vec<&String> = pred.keys().filter(|k| !target.contains_key(*k)).collect();
    if target.is_empty() || !missing.is_empty() || !extra.is_empty() {
        return Err(Error::InvalidInput {
            path: req.pred.clone(),
            what: "videos".to_string(),
            reason: if target.is_empty() {
                format!("the target folder {} holds no videos", req.target.display())
            } else {
                format!(
                    "prediction and target folders do not match: missing predictions {missing:?}, predictions without a \
                     target in {}: {extra:?}",
                    req.target.display()
                )
            },
        });
    }
    let masks = req.mask.as_deref().map(entries).transpose()?;
    target
        .into_iter()
        .map(|(name, t)| {
            let mask = match &masks {
                Some(m) => Some(m.get(&name).cloned().ok_or_else(|| Error::InvalidInput {
                    path: req.mask.clone().unwrap_or_default(),
                    what: "masks".to_string(),
                    reason: format!("no mask folder for video `{name}`"),
                })?),
                None => None,
            };
            Ok((name.clone(), pred[&name].clone(), t, mask))
        })
        .collect()
}

fn resize(frames: Vec<RgbImage>, protocol: Option<Protocol>) -> Vec<RgbImage> {
    let Some((w, h)) = protocol.map(Protocol::size) else { return frames };
    frames
        .into_iter()
        .map(|f| {
            if f.dimensions() == (w, h) {
                f
            } else {
                image::imageops::resize(&f, w, h, image::imageops::FilterType::Triangle)
            }
        })
        .collect()
}

/// Frames of one prediction checked against the target: same count, same size (after resize).
fn load_checked(
    path: &Path,
    target: &[RgbImage],
    target_path: &Path,
    protocol: Option<Protocol>,
) -> Result<Vec<RgbImage>> {
    let named = read_named_frames(path)?;
    named.uniform_size()?;
    if named.frames.len() != target.len() {
        return Err(Error::InvalidInput {
            path: path.to_path_buf(),
            what: "frame count".to_string(),
            reason: format!("{} frames, but target {} has {}", named.frames.len(), target_path.display(), target.len()),
        });
    }
    let (got, want) = (named.frames[0].dimensions(), target[0].dimensions());
    let frames = resize(named.frames, protocol);
    if frames[0].dimensions() != target[0].dimensions() {
        return Err(Error::InvalidInput {
            path: path.to_path_buf(),
            what: "frame size".to_string(),
            reason: format!(
                "{}x{}, but target {} is {}x{}; pass --protocol gcd|dycheck to resize both",
                got.0,
                got.1,
                target_path.display(),
                want.0,
                want.1
            ),
        });
    }
    Ok(frames)
}

/// LPIPS per frame and masked LPIPS per frame (mean of the spatial map over co-visible pixels).
pub(crate) fn lpips_frames(
    model: &Lpips,
    pred: &[RgbImage],
    target: &[RgbImage],
    masks: Option<&[GrayImage]>,
    device: Device,
) -> Result<(Vec<f64>, Vec<Option<f64>>)> {
    let _guard = tch::no_grad_guard();
    let (mut plain, mut masked) = (Vec::new(), Vec::new());
    for start in (0..pred.len()).step_by(BATCH) {
        let end = (start + BATCH).min(pred.len());
        let p: Vec<&RgbImage> = pred[start..end].iter().collect();
        let t: Vec<&RgbImage> = target[start..end].iter().collect();
        let (x0, x1) = (frames_to_input(&p, device), frames_to_input(&t, device));
        plain.extend(Vec::<f64>::try_from(model.distance(&x0, &x1)?.to_kind(tch::Kind::Double))?);
        if let Some(masks) = masks {
            let map = model.spatial(&x0, &x1)?;
            for (i, m) in masks[start..end].iter().enumerate() {
                let keep: Vec<f32> = m.as_raw().iter().map(|&v| f32::from(u8::from(v != 0))).collect();
                let keep =
                    Tensor::from_slice(&keep).view([i64::from(m.height()), i64::from(m.width())]).to_device(device);
                let n = keep.sum(tch::Kind::Double).double_value(&[]);
                masked
                    .push((n > 0.0).then(|| (map.get(i as i64) * &keep).sum(tch::Kind::Double).double_value(&[]) / n));
            }
        }
    }
    Ok((plain, masked))
}

fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let v: Vec<f64> = values.filter(|v| v.is_finite()).collect();
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// Inception features of frames, in batches.
fn features(model: &FidInception, frames: &[RgbImage]) -> Result<Tensor> {
    let parts =
        frames.chunks(BATCH).map(|c| model.features(&c.iter().collect::<Vec<_>>())).collect::<Result<Vec<_>>>()?;
    Ok(Tensor::f_cat(&parts, 0)?)
}

/// Runs the evaluation; `progress(done, total)` after each video.
pub fn run(req: &ScoreRequest, progress: impl FnMut(usize, usize)) -> Result<ScoreReport> {
    run_pairs(req, &pairs(req)?, progress)
}

/// [`run`] on videos listed by the caller instead of found in `req.pred`/`req.target` (whose
/// paths are then not read): the dataset benchmark scores its own folders this way.
pub fn run_pairs(req: &ScoreRequest, pairs: &[Pair], mut progress: impl FnMut(usize, usize)) -> Result<ScoreReport> {
    let lpips = req.lpips.as_deref().map(|p| Lpips::load(p, req.lpips_net, req.device)).transpose()?;
    let inception = req.inception.as_deref().map(|p| FidInception::load(p, req.device)).transpose()?;
    let (mut rows, mut pred_feats, mut target_feats) = (Vec::new(), Vec::new(), Vec::new());
    for (done, (name, pred_path, target_path, mask_path)) in pairs.iter().enumerate() {
        let target_named = read_named_frames(target_path)?;
        target_named.uniform_size()?;
        let target = resize(target_named.frames, req.protocol);
        let masks = match mask_path {
            Some(dir) => {
                let masks: Vec<GrayImage> = read_masks(dir)?;
                let (w, h) = target[0].dimensions();
                let masks = match req.protocol {
                    Some(_) => masks
                        .into_iter()
                        .map(|m| image::imageops::resize(&m, w, h, image::imageops::FilterType::Nearest))
                        .collect(),
                    None => masks,
                };
                Some(masks)
            }
            None => None,
        };
        let samples: Vec<PathBuf> = match req.top_k {
            Some(k) => {
                let found: Vec<PathBuf> = entries(pred_path)?.into_values().collect();
                if found.len() < k {
                    return Err(Error::InvalidInput {
                        path: pred_path.clone(),
                        what: "top-k samples".to_string(),
                        reason: format!(
                            "--top-k {k} needs {k} samples (videos or frame folders), found {}",
                            found.len()
                        ),
                    });
                }
                found.into_iter().take(k).collect()
            }
            None => vec![pred_path.clone()],
        };
        let mut best: Option<(f64, usize, Vec<RgbImage>, crate::eval::metrics::VideoMetrics)> = None;
        for (i, sample) in samples.iter().enumerate() {
            let pred = load_checked(sample, &target, target_path, req.protocol)?;
            let m = video_metrics(&pred, &target, masks.as_deref()).map_err(|e| match e {
                Error::InvalidArgument { name, reason } => Error::InvalidInput {
                    path: if name == "mask" { mask_path.clone().unwrap_or_default() } else { sample.clone() },
                    what: name,
                    reason,
                },
                other => other,
            })?;
            let score = m.masked_psnr.unwrap_or(m.psnr);
            if best.as_ref().is_none_or(|b| score > b.0) {
                best = Some((score, i, pred, m));
            }
        }
        let (_, chosen, pred, m) = best.expect("at least one sample");
        let (lp, mlp) = match &lpips {
            Some(model) => {
                let (plain, masked) = lpips_frames(model, &pred, &target, masks.as_deref(), req.device)?;
                (mean(plain.into_iter()), mean(masked.into_iter().flatten()))
            }
            None => (None, None),
        };
        if let Some(model) = &inception {
            pred_feats.push(features(model, &pred)?);
            target_feats.push(features(model, &target)?);
        }
        rows.push(VideoRow {
            name: name.clone(),
            frames: m.frames,
            sample: req.top_k.map(|_| chosen),
            psnr: m.psnr,
            ssim: m.ssim,
            lpips: lp,
            masked_psnr: m.masked_psnr,
            masked_ssim: m.masked_ssim,
            masked_lpips: mlp,
        });
        progress(done + 1, pairs.len());
    }
    let (fid, kid) = if inception.is_some() {
        let (p, t) = (Tensor::f_cat(&pred_feats, 0)?, Tensor::f_cat(&target_feats, 0)?);
        let kid =
            if req.kid { Some(kernel_distance(&p, &t, req.kid_subsets, req.kid_subset_size, req.seed)?) } else { None };
        (Some(frechet_distance(&p, &t)?), kid)
    } else {
        (None, None)
    };
    let column = |f: fn(&VideoRow) -> Option<f64>| mean(rows.iter().filter_map(f));
    let mean_row = VideoRow {
        name: "mean".to_string(),
        frames: rows.iter().map(|r| r.frames).sum(),
        sample: None,
        psnr: column(|r| Some(r.psnr)).unwrap_or(f64::INFINITY),
        ssim: column(|r| Some(r.ssim)).unwrap_or(f64::NAN),
        lpips: column(|r| r.lpips),
        masked_psnr: column(|r| r.masked_psnr),
        masked_ssim: column(|r| r.masked_ssim),
        masked_lpips: column(|r| r.masked_lpips),
    };
    Ok(ScoreReport { protocol: req.protocol, videos: rows, mean: mean_row, fid, kid })
}

/// The report as a Markdown table (columns only for what was computed), FID/KID below it.
pub fn markdown(report: &ScoreReport) -> String {
    type Column = (&'static str, fn(&VideoRow) -> Option<f64>);
    let all: [Column; 6] = [
        ("PSNR ↑", |r| Some(r.psnr)),
        ("SSIM ↑", |r| Some(r.ssim)),
        ("LPIPS ↓", |r| r.lpips),
        ("mPSNR ↑", |r| r.masked_psnr),
        ("mSSIM ↑", |r| r.masked_ssim),
        ("mLPIPS ↓", |r| r.masked_lpips),
    ];
    let columns: Vec<&Column> = all.iter().filter(|(_, f)| f(&report.mean).is_some()).collect();
    let mut out = format!("| video | frames | {} |\n", columns.iter().map(|c| c.0).collect::<Vec<_>>().join(" | "));
    out += &format!("|---|---:|{}\n", "---:|".repeat(columns.len()));
    for row in report.videos.iter().chain(std::iter::once(&report.mean)) {
        let name = if row.name == "mean" { "**mean**".to_string() } else { row.name.clone() };
        let cells: Vec<String> =
            columns.iter().map(|(_, f)| f(row).map_or("–".to_string(), |v| format!("{v:.4}"))).collect();
        out += &format!("| {name} | {} | {} |\n", row.frames, cells.join(" | "));
    }
    if let Some(fid) = report.fid {
        out += &format!("\nFID ↓ {fid:.4}");
        if let Some(kid) = report.kid {
            out += &format!(", KID ↓ {kid:.6}");
        }
        out += &format!(" (over {} frames)\n", report.mean.frames);
    }
    out
}

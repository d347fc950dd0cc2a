//! `trainer eval` over folders: predicted and target videos matched by name, resized as the
//! protocol says, scored per frame (PSNR, SSIM, LPIPS and, with masks, DyCheck's mPSNR, mSSIM,
//! mLPIPS) and as a set (FID, KID), printed as Markdown and JSON; the table the official CogNVS
//! evaluation (`eval/eval_metrics.py`, `evaluate_dataset`) prints from the same videos:
//!
//! - every frame whose size is not the protocol's is brought to it with OpenCV's `cv2.resize`
//!   (bilinear, fixed-point; [`crate::eval::resize::resize_linear_opencv`]);
//! - the mean row pools every frame of every video (`np.mean` over the per-frame lists), so a
//!   long video weighs more than a short one; a video's row is the mean over its frames. Identical
//!   frames have an infinite PSNR and make the mean infinite, as `np.mean` does; the report
//!   counts them ([`ScoreReport::notes`]). DyCheck's masked metrics pool the same way (its
//!   `NovelView.finalize` takes the plain mean over the split's frames), a frame with no
//!   co-visible pixel scoring mPSNR ∞, mSSIM 1, mLPIPS 0;
//! - FID and KID over every frame of every video (clean-fid on the two folders of frames); KID's
//!   subsets hold `min(n, 1000)` frames as clean-fid's.
//!
//! [`bundle_pairs`] finds the videos of the paper's evaluation bundle as the official script
//! does (`get_video_pairs`, `load_correspondence`).
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

use super::fid::{frechet_distance, kernel_distance, kid_subset_size};
use super::inception::FidInception;
use super::lpips::{Lpips, LpipsNet, frames_to_input};
use crate::error::{Error, Result};
use crate::eval::metrics::{DYCHECK_MASK_EPS, plain_mean, read_masks, read_named_frames, video_metrics};
use crate::eval::resize::resize_linear_opencv;

/// Frames per LPIPS / Inception batch (bounds memory at DyCheck's 960×720 with VGG).
const BATCH: usize = 4;

/// An evaluation protocol: the size both videos are resized to before scoring (the official
/// `read_video`'s `default_shape`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Protocol {
    /// GCD's Kubric-4D / ParallelDomain-4D protocol: 384×576 (H×W), as the paper's Table 1.
    Gcd,
    /// DyCheck (iPhone) at 720p: 960×720 (H×W), the paper's Table 2 resolution.
    Dycheck,
    /// DyCheck at 360p: 480×360 (H×W), the official script's other resolution.
    Dycheck360,
}

impl Protocol {
    /// (width, height) of the protocol.
    pub fn size(self) -> (u32, u32) {
        match self {
            Protocol::Gcd => (576, 384),
            Protocol::Dycheck => (720, 960),
            Protocol::Dycheck360 => (360, 480),
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
    /// Largest KID subset (clean-fid's `max_subset_size`: subsets hold `min(n, this)` frames).
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
    /// The KID subset size used (`min(n, kid_subset_size)`).
    pub kid_subset_size: Option<usize>,
    /// Frames whose PSNR is infinite (identical prediction and target): the PSNR mean is then
    /// infinite, as the official script's `np.mean` gives it.
    pub infinite_psnr_frames: usize,
    /// Frames with no co-visible pixel (scored as DyCheck scores them: mPSNR ∞, mSSIM 1, mLPIPS 0).
    pub uncovered_frames: usize,
    /// What a reader of the table must know: the frames above, videos the official layout skips.
    pub notes: Vec<String>,
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

/// One video to score.
#[derive(Debug, Clone, PartialEq)]
pub struct Pair {
    /// Its name in the table.
    pub name: String,
    /// The prediction (video file or frame folder; with top-k a folder of samples).
    pub pred: PathBuf,
    /// The target.
    pub target: PathBuf,
    /// Its mask folder.
    pub mask: Option<PathBuf>,
    /// The prediction frames scored against the target's frames, in order (the correspondence
    /// file's target frames); None: all, frame i against frame i.
    pub pred_frames: Option<Vec<usize>>,
}

impl Pair {
    /// A pair scoring every frame.
    pub fn new(name: impl Into<String>, pred: PathBuf, target: PathBuf, mask: Option<PathBuf>) -> Self {
        Self { name: name.into(), pred, target, mask, pred_frames: None }
    }
}

/// Every video's [`Pair`], or an error naming what does not match.
fn pairs(req: &ScoreRequest) -> Result<Vec<Pair>> {
    if req.single {
        let name = req.target.file_stem().map_or("video".to_string(), |n| n.to_string_lossy().to_string());
        return Ok(vec![Pair::new(name, req.pred.clone(), req.target.clone(), req.mask.clone())]);
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
            Ok(Pair::new(name.clone(), pred[&name].clone(), t, mask))
        })
        .collect()
}

/// A dataset folder of the paper's evaluation bundle (the official script's `DATASETS`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum BundleDataset {
    /// `kubric_4d/`: Kubric-4D under GCD's protocol (Table 1).
    Kubric4d,
    /// `pardom_4d/`: ParallelDomain-4D under GCD's protocol (Table 1).
    Pardom4d,
    /// `dycheck/`: DyCheck iPhone (Table 2), at 720p or 360p.
    Dycheck,
}

/// The scenes the official script scores, in its order (`DATASETS[...]["scenes"]`).
const PARDOM_SCENES: [&str; 20] = [
    "scene_000048",
    "scene_000072",
    "scene_000074",
    "scene_000106",
    "scene_000165",
    "scene_000167",
    "scene_000173",
    "scene_000181",
    "scene_000294",
    "scene_000298",
    "scene_000310",
    "scene_000315",
    "scene_000337",
    "scene_000362",
    "scene_000365",
    "scene_000444",
    "scene_000581",
    "scene_000626",
    "scene_000651",
    "scene_000663",
];
/// Kubric-4D's scenes are `scn02900` … `scn02919` (the official list): the prefix and count.
const KUBRIC_SCENE_PREFIX: &str = "scn029";
const KUBRIC_SCENES: usize = 20;
/// DyCheck's scenes in the official list.
const DYCHECK_SCENES: [&str; 5] = ["apple", "block", "paper-windmill", "spin", "teddy"];
/// The methods whose DyCheck predictions the official script selects frames of through the
/// correspondence files (`load_correspondence`); others are scored frame for frame.
const CORRESPONDENCE_METHODS: [&str; 3] = ["cognvs", "trajcrafter", "megasam_render"];
/// The method whose DyCheck files carry `_stack` before `_cam` (`get_video_pairs`).
const STACKED_METHOD: &str = "megasam_render";
/// The targets' key in file names (`gt_key`).
const GT_KEY: &str = "gt";

impl BundleDataset {
    /// The folder under the bundle's root.
    pub fn folder(self) -> &'static str {
        match self {
            BundleDataset::Kubric4d => "kubric_4d",
            BundleDataset::Pardom4d => "pardom_4d",
            BundleDataset::Dycheck => "dycheck",
        }
    }

    /// The scenes the official script scores, in its order.
    pub fn scenes(self) -> Vec<String> {
        match self {
            BundleDataset::Kubric4d => (0..KUBRIC_SCENES).map(|i| format!("{KUBRIC_SCENE_PREFIX}{i:02}")).collect(),
            BundleDataset::Pardom4d => PARDOM_SCENES.iter().map(|s| s.to_string()).collect(),
            BundleDataset::Dycheck => DYCHECK_SCENES.iter().map(|s| s.to_string()).collect(),
        }
    }
}

/// One method's predictions in the paper's evaluation bundle:
/// `ROOT/<dataset>/<method>/*<scene>_<method>.mp4` against `ROOT/<dataset>/target_gt/*<scene>_gt.mp4`
/// (Kubric-4D, ParallelDomain-4D); for DyCheck `*<scene>_<method>_cam<k>.mp4` (MegaSAM renders:
/// `_stack_cam<k>`) against `target_gt/` (360p) or `target_gt_1x/` (720p) `*<scene>_gt_cam<k>.mp4`,
/// with `ROOT/dycheck/dycheck_<scene>_source_target_correspondence.txt` selecting the
/// prediction frames of camera k.
#[derive(Debug, Clone, PartialEq)]
pub struct Bundle {
    /// The bundle's root folder.
    pub root: PathBuf,
    /// The dataset.
    pub dataset: BundleDataset,
    /// The method (its folder and file-name key: `cognvs`, `gcd`, `trajcrafter`, `shape_of_motion`, ...).
    pub method: String,
    /// DyCheck's resolution: 720p (the paper's Table 2) or, false, 360p.
    pub dycheck_720p: bool,
}

/// The bundle's pairs as the official script finds them, the protocol they are scored at, and
/// notes on what it skips (a scene without a prediction or target, unequal camera counts).
pub fn bundle_pairs(bundle: &Bundle) -> Result<(Protocol, Vec<Pair>, Vec<String>)> {
    let dataset_dir = bundle.root.join(bundle.dataset.folder());
    let pred_dir = dataset_dir.join(&bundle.method);
    let (target_dir, protocol) = match (bundle.dataset, bundle.dycheck_720p) {
        (BundleDataset::Dycheck, true) => (dataset_dir.join(format!("target_{GT_KEY}_1x")), Protocol::Dycheck),
        (BundleDataset::Dycheck, false) => (dataset_dir.join(format!("target_{GT_KEY}")), Protocol::Dycheck360),
        _ => (dataset_dir.join(format!("target_{GT_KEY}")), Protocol::Gcd),
    };
    let (pred_files, target_files) = (mp4_files(&pred_dir)?, mp4_files(&target_dir)?);
    let matching = |files: &[PathBuf], needle: &str, whole_suffix: bool| -> Vec<PathBuf> {
        files
            .iter()
            .filter(|p| {
                let name = p.file_name().map_or(String::new(), |n| n.to_string_lossy().to_string());
                let stem = name.strip_suffix(".mp4").unwrap_or_default();
                if whole_suffix { stem.ends_with(needle) } else { stem.contains(needle) }
            })
            .cloned()
            .collect()
    };
    let (mut pairs, mut notes) = (Vec::new(), Vec::new());
    for scene in bundle.dataset.scenes() {
        if bundle.dataset != BundleDataset::Dycheck {
            // glob `*<scene>_<method>.mp4`: the official script takes the first match.
            let pred = matching(&pred_files, &format!("{scene}_{}", bundle.method), true);
            let target = matching(&target_files, &format!("{scene}_{GT_KEY}"), true);
            for (found, dir) in [(&pred, &pred_dir), (&target, &target_dir)] {
                if found.len() > 1 {
                    return Err(Error::InvalidInput {
                        path: dir.clone(),
                        what: format!("scene {scene}"),
                        reason: format!(
                            "several videos match it ({found:?}); the official script would take one of them at random"
                        ),
                    });
                }
            }
            match (pred.first(), target.first()) {
                (Some(p), Some(t)) => pairs.push(Pair::new(scene.clone(), p.clone(), t.clone(), None)),
                _ => notes.push(format!(
                    "scene {scene} skipped: no prediction or no target video (as the official script skips it)"
                )),
            }
            continue;
        }
        let stack = if bundle.method == STACKED_METHOD { "_stack" } else { "" };
        let preds = matching(&pred_files, &format!("{scene}_{}{stack}_cam", bundle.method), false);
        let targets = matching(&target_files, &format!("{scene}_{GT_KEY}_cam"), false);
        if preds.len() != targets.len() {
            notes.push(format!(
                "scene {scene}: {} prediction and {} target videos, the first {} of each (by name) paired, as the official \
                 script's zip pairs them",
                preds.len(),
                targets.len(),
                preds.len().min(targets.len())
            ));
        }
        let correspondence_file = dataset_dir.join(datagen::api::correspondence_file_name(&scene));
        let correspondence = (CORRESPONDENCE_METHODS.contains(&bundle.method.as_str())
            && correspondence_file.is_file())
        .then(|| datagen::api::read_correspondence(&correspondence_file))
        .transpose()?;
        for (pred, target) in preds.into_iter().zip(targets) {
            let camera = camera_of(&target)?;
            let pred_frames = match &correspondence {
                Some(c) => {
                    let frames = c.frames(camera);
                    if frames.is_empty() {
                        return Err(Error::InvalidInput {
                            path: correspondence_file.clone(),
                            what: "correspondence".to_string(),
                            reason: format!(
                                "no `{camera}_<frame>.png` line for the target camera of {}",
                                target.display()
                            ),
                        });
                    }
                    Some(frames)
                }
                None => None,
            };
            pairs.push(Pair { name: format!("{scene}/cam{camera}"), pred, target, mask: None, pred_frames });
        }
    }
    if pairs.is_empty() {
        return Err(Error::InvalidInput {
            path: pred_dir,
            what: "videos".to_string(),
            reason: format!(
                "no scene of {} has both a prediction here and a target in {}",
                bundle.dataset.folder(),
                target_dir.display()
            ),
        });
    }
    Ok((protocol, pairs, notes))
}

/// The `.mp4` files of `dir` (not hidden ones, which a glob `*` skips), sorted by name.
fn mp4_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let read = std::fs::read_dir(dir).map_err(|error| Error::Io { path: dir.to_path_buf(), error })?;
    let mut files: Vec<PathBuf> = read
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let name = p.file_name().map_or(String::new(), |n| n.to_string_lossy().to_string());
            p.is_file() && name.ends_with(".mp4") && !name.starts_with('.')
        })
        .collect();
    files.sort();
    Ok(files)
}

/// The camera of a DyCheck target video as the official script reads it: the text after the
/// last `_cam` of the path, up to the first `.`, as a number.
fn camera_of(target: &Path) -> Result<u32> {
    let text = target.to_string_lossy();
    let tail = text.rsplit("_cam").next().unwrap_or_default();
    tail.split('.').next().unwrap_or_default().parse().map_err(|_| Error::InvalidInput {
        path: target.to_path_buf(),
        what: "camera".to_string(),
        reason: "the name does not end in `_cam<number>.mp4`".to_string(),
    })
}

/// `frame` at `size` (width, height) as the official `read_video` brings it: `cv2.resize` when
/// the size differs.
pub fn resize_to(frame: &RgbImage, size: (u32, u32)) -> RgbImage {
    resize_linear_opencv(frame, size.0, size.1)
}

/// Frames at the protocol's size: those of another size through `cv2.resize` as the official
/// `read_video` brings them.
fn resize(frames: Vec<RgbImage>, protocol: Option<Protocol>) -> Vec<RgbImage> {
    let Some((w, h)) = protocol.map(Protocol::size) else { return frames };
    frames.into_iter().map(|f| if f.dimensions() == (w, h) { f } else { resize_linear_opencv(&f, w, h) }).collect()
}

/// Frames of one prediction checked against the target: same count, same size (after resize).
fn load_checked(
    path: &Path,
    target: &[RgbImage],
    target_path: &Path,
    protocol: Option<Protocol>,
    selection: Option<&[usize]>,
) -> Result<Vec<RgbImage>> {
    let mut named = read_named_frames(path)?;
    named.uniform_size()?;
    if let Some(selection) = selection {
        if let Some(&i) = selection.iter().find(|&&i| i >= named.frames.len()) {
            return Err(Error::InvalidInput {
                path: path.to_path_buf(),
                what: "correspondence frames".to_string(),
                reason: format!("frame {i} is selected, but the prediction has {} frames", named.frames.len()),
            });
        }
        named.frames = selection.iter().map(|&i| named.frames[i].clone()).collect();
    }
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

/// LPIPS per frame and, with masks, DyCheck's mLPIPS per frame (`get_compute_lpips`): both
/// images blacked out where the mask is 0, the spatial LPIPS map's mask-weighted mean, the
/// weight floored at 1e-6 (0 for a frame with no co-visible pixel).
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
            let masks = &masks[start..end];
            let black = |frames: &[&RgbImage]| -> Vec<RgbImage> {
                frames
                    .iter()
                    .zip(masks)
                    .map(|(f, m)| {
                        let mut out = (*f).clone();
                        for (pixel, &keep) in out.pixels_mut().zip(m.as_raw()) {
                            if keep == 0 {
                                pixel.0 = [0; 3];
                            }
                        }
                        out
                    })
                    .collect()
            };
            let (p, t) = (black(&p), black(&t));
            let (p, t): (Vec<&RgbImage>, Vec<&RgbImage>) = (p.iter().collect(), t.iter().collect());
            let map = model.spatial(&frames_to_input(&p, device), &frames_to_input(&t, device))?;
            for (i, m) in masks.iter().enumerate() {
                let keep: Vec<f32> = m.as_raw().iter().map(|&v| f32::from(u8::from(v != 0))).collect();
                let keep =
                    Tensor::from_slice(&keep).view([i64::from(m.height()), i64::from(m.width())]).to_device(device);
                let weight = keep.sum(tch::Kind::Double).double_value(&[]).max(DYCHECK_MASK_EPS);
                masked.push(Some((map.get(i as i64) * &keep).sum(tch::Kind::Double).double_value(&[]) / weight));
            }
        }
    }
    Ok((plain, masked))
}

/// Inception features of frames, in batches.
fn features(model: &FidInception, frames: &[RgbImage]) -> Result<Tensor> {
    let parts =
        frames.chunks(BATCH).map(|c| model.features(&c.iter().collect::<Vec<_>>())).collect::<Result<Vec<_>>>()?;
    Ok(Tensor::f_cat(&parts, 0)?)
}

/// Per-frame values of every scored frame, in scoring order (the official script's lists).
#[derive(Debug, Default)]
struct FrameValues {
    psnr: Vec<f64>,
    ssim: Vec<f64>,
    lpips: Vec<f64>,
    masked_psnr: Vec<f64>,
    masked_ssim: Vec<f64>,
    masked_lpips: Vec<f64>,
}

impl FrameValues {
    /// The row of the frames from `start` on (`np.mean` of each list; None for lists not kept).
    fn row(&self, name: &str, start: usize, sample: Option<usize>) -> VideoRow {
        let mean = |v: &[f64]| plain_mean(v.get(start..).unwrap_or_default().iter().copied());
        VideoRow {
            name: name.to_string(),
            frames: self.psnr.len() - start,
            sample,
            psnr: mean(&self.psnr).unwrap_or(f64::NAN),
            ssim: mean(&self.ssim).unwrap_or(f64::NAN),
            lpips: mean(&self.lpips),
            masked_psnr: mean(&self.masked_psnr),
            masked_ssim: mean(&self.masked_ssim),
            masked_lpips: mean(&self.masked_lpips),
        }
    }
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
    let mut values = FrameValues::default();
    let mut uncovered_frames = 0;
    for (done, pair) in pairs.iter().enumerate() {
        let Pair { name, pred: pred_path, target: target_path, mask: mask_path, pred_frames } = pair;
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
            let pred = load_checked(sample, &target, target_path, req.protocol, pred_frames.as_deref())?;
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
        let start = values.psnr.len();
        values.psnr.extend(m.per_frame.iter().map(|f| f.psnr));
        values.ssim.extend(m.per_frame.iter().map(|f| f.ssim));
        values.masked_psnr.extend(m.per_frame.iter().filter_map(|f| f.masked_psnr));
        values.masked_ssim.extend(m.per_frame.iter().filter_map(|f| f.masked_ssim));
        uncovered_frames += m.per_frame.iter().filter(|f| f.uncovered).count();
        if let Some(model) = &lpips {
            let (plain, masked) = lpips_frames(model, &pred, &target, masks.as_deref(), req.device)?;
            values.lpips.extend(plain);
            values.masked_lpips.extend(masked.into_iter().flatten());
        }
        if let Some(model) = &inception {
            pred_feats.push(features(model, &pred)?);
            target_feats.push(features(model, &target)?);
        }
        rows.push(values.row(name, start, req.top_k.map(|_| chosen)));
        progress(done + 1, pairs.len());
    }
    let (mut fid, mut kid, mut subset) = (None, None, None);
    if inception.is_some() {
        let (p, t) = (Tensor::f_cat(&pred_feats, 0)?, Tensor::f_cat(&target_feats, 0)?);
        if req.kid {
            // clean-fid's compute_kid(gt folder, pred folder): the target set first.
            kid = Some(kernel_distance(&t, &p, req.kid_subsets, req.kid_subset_size, req.seed)?);
            subset = Some(kid_subset_size(t.size()[0] as usize, p.size()[0] as usize, req.kid_subset_size));
        }
        fid = Some(frechet_distance(&t, &p)?);
    }
    let infinite_psnr_frames = values.psnr.iter().filter(|v| v.is_infinite()).count();
    let mut notes = Vec::new();
    if infinite_psnr_frames > 0 {
        notes.push(format!(
            "{infinite_psnr_frames} frame(s) are identical to their target (PSNR ∞): the PSNR mean is infinite, as the \
             official script's np.mean gives it"
        ));
    }
    if uncovered_frames > 0 {
        notes.push(format!(
            "{uncovered_frames} frame(s) have no co-visible pixel: scored as DyCheck scores them (mPSNR ∞, mSSIM 1, \
             mLPIPS 0), so the mPSNR mean is infinite, as DyCheck's plain mean over frames gives it"
        ));
    }
    let mean = values.row("mean", 0, None);
    Ok(ScoreReport {
        protocol: req.protocol,
        videos: rows,
        mean,
        fid,
        kid,
        kid_subset_size: subset,
        infinite_psnr_frames,
        uncovered_frames,
        notes,
    })
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
            columns.iter().map(|(_, f)| f(row).map_or("–".to_string(), |v| format!("{v:.5}"))).collect();
        out += &format!("| {name} | {} | {} |\n", row.frames, cells.join(" | "));
    }
    if let Some(fid) = report.fid {
        out += &format!("\nFID ↓ {fid:.5}");
        if let (Some(kid), Some(subset)) = (report.kid, report.kid_subset_size) {
            out += &format!(", KID ↓ {kid:.5} (subsets of {subset})");
        }
        out += &format!(" over {} frames\n", report.mean.frames);
    }
    for note in &report.notes {
        out += &format!("\nNote: {note}\n");
    }
    out
}

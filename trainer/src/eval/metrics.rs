//! Image-quality metrics of `trainer eval`, on RGB values scaled to [0, 1]:
//!
//! - PSNR and SSIM as the official CogNVS evaluation calls scikit-image (`eval/eval_metrics.py`,
//!   `peak_signal_noise_ratio(pred, gt, data_range=1.0)` and `structural_similarity(pred, gt,
//!   data_range=1.0, channel_axis=0)`): `10·log10(1 / MSE)`, infinite for identical frames, and
//!   SSIM with a 7×7 uniform window, K1 = 0.01, K2 = 0.03, sample covariance, the mean over the
//!   image less a 3-pixel border, averaged over channels;
//! - the masked mPSNR and mSSIM of DyCheck's appendix table as DyCheck's own code computes them
//!   (KAIR-BAIR/dycheck `dycheck/core/metrics/image.py`, `compute_psnr` and `compute_ssim`, with
//!   `masked_mean` of `dycheck/nn/functional/common.py`): mPSNR from the mask-weighted MSE whose
//!   weight sum is floored at 1e-6 (a frame with no co-visible pixel: MSE 0, mPSNR infinite), and
//!   mSSIM with an 11×11 Gaussian (σ 1.5) applied as a partial convolution that ignores masked
//!   pixels, averaged over every valid window and channel, a window with no co-visible pixel
//!   counting as 1 (so an empty mask gives 1).
//!
//! Means over frames are plain means as `np.mean` takes them: one infinite frame makes the mean
//! infinite, as in both official codes; the callers count and flag such frames.

use std::path::{Path, PathBuf};

use image::{GrayImage, RgbImage};
use serde::Serialize;

use crate::error::{Error, Result};

/// SSIM window side (scikit-image's default `win_size`).
const WIN_SIZE: usize = 7;
/// SSIM stabilisers as fractions of the data range (Wang et al. 2004; scikit-image defaults).
const K1: f64 = 0.01;
const K2: f64 = 0.03;

/// DyCheck's SSIM Gaussian: `filter_size` 11 and `filter_sigma` 1.5 (`compute_ssim` defaults).
const DYCHECK_FILTER_SIZE: usize = 11;
const DYCHECK_FILTER_SIGMA: f64 = 1.5;
/// The floor of `masked_mean`'s weight sum (`eps` in dycheck's `masked_mean`).
pub const DYCHECK_MASK_EPS: f64 = 1e-6;

/// Metrics of one frame pair.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FrameMetrics {
    /// PSNR in dB over the whole frame (infinite for identical frames).
    pub psnr: f64,
    /// Mean SSIM.
    pub ssim: f64,
    /// DyCheck's mPSNR (None without a mask; infinite when no pixel is co-visible).
    pub masked_psnr: Option<f64>,
    /// DyCheck's mSSIM (None without a mask; 1 when no pixel is co-visible).
    pub masked_ssim: Option<f64>,
    /// Whether the mask has no co-visible pixel (false without a mask).
    pub uncovered: bool,
}

/// Metrics of a video pair: per frame and their means (`np.mean`: infinite if a frame is).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct VideoMetrics {
    /// Frames compared.
    pub frames: usize,
    /// Mean over frames of the per-frame PSNR.
    pub psnr: f64,
    /// Mean SSIM over frames.
    pub ssim: f64,
    /// Mean mPSNR over frames.
    pub masked_psnr: Option<f64>,
    /// Mean mSSIM over frames.
    pub masked_ssim: Option<f64>,
    /// Per-frame values.
    pub per_frame: Vec<FrameMetrics>,
}

/// The plain mean of `values` as `np.mean` takes it (None when empty).
pub fn plain_mean(values: impl IntoIterator<Item = f64>) -> Option<f64> {
    let (sum, n) = values.into_iter().fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    (n > 0).then(|| sum / n as f64)
}

fn unit(image: &RgbImage) -> Vec<f64> {
    image.as_raw().iter().map(|&v| f64::from(v) / 255.0).collect()
}

/// Metrics of one frame pair; `mask` (non-zero: co-visible, binarised as DyCheck's 0/255
/// co-visibility PNGs are) selects DyCheck's masked variants.
pub fn frame_metrics(pred: &RgbImage, target: &RgbImage, mask: Option<&GrayImage>) -> FrameMetrics {
    let (a, b) = (unit(pred), unit(target));
    let (w, h) = target.dimensions();
    let (w, h) = (w as usize, h as usize);
    let weights: Option<Vec<f64>> = mask.map(|m| m.as_raw().iter().map(|&v| f64::from(u8::from(v != 0))).collect());
    let mse = a.iter().zip(&b).map(|(p, q)| (p - q).powi(2)).sum::<f64>() / a.len() as f64;
    let map = ssim_map(&a, &b, w, h);
    let pad = (WIN_SIZE - 1) / 2;
    let inside = |p: usize| {
        let (x, y) = (p % w, p / w);
        x >= pad && y >= pad && x + pad < w && y + pad < h
    };
    let ssim = plain_mean((0..w * h).filter(|&p| inside(p)).map(|p| map[p])).unwrap_or(f64::NAN);
    FrameMetrics {
        psnr: psnr(mse),
        ssim,
        masked_psnr: weights.as_ref().map(|m| dycheck_masked_psnr(&a, &b, m)),
        masked_ssim: weights.as_ref().map(|m| dycheck_masked_ssim(&a, &b, m, w, h)),
        uncovered: weights.as_ref().is_some_and(|m| m.iter().all(|&v| v == 0.0)),
    }
}

/// `10·log10(1 / mse)`; infinite for 0 (numpy's division by zero, which the official code keeps).
fn psnr(mse: f64) -> f64 {
    -10.0 * mse.log10()
}

/// DyCheck's `compute_psnr` with a mask: the MSE over every channel weighted by the mask
/// (broadcast to the channels), divided by the weight sum floored at [`DYCHECK_MASK_EPS`].
fn dycheck_masked_psnr(a: &[f64], b: &[f64], mask: &[f64]) -> f64 {
    let (mut sum, mut weight) = (0.0, 0.0);
    for (p, &m) in mask.iter().enumerate() {
        for c in 0..3 {
            sum += (a[p * 3 + c] - b[p * 3 + c]).powi(2) * m;
        }
        weight += 3.0 * m;
    }
    psnr(sum / weight.max(DYCHECK_MASK_EPS))
}

/// DyCheck's normalised 1-D Gaussian: `exp(−½((i − 5)/σ)²)` over 11 taps.
fn dycheck_filter() -> [f64; DYCHECK_FILTER_SIZE] {
    let half = (DYCHECK_FILTER_SIZE / 2) as f64;
    let mut taps: [f64; DYCHECK_FILTER_SIZE] =
        std::array::from_fn(|i| (-0.5 * ((i as f64 - half) / DYCHECK_FILTER_SIGMA).powi(2)).exp());
    let total: f64 = taps.iter().sum();
    taps.iter_mut().for_each(|t| *t /= total);
    taps
}

/// One pass of DyCheck's masked blur (`convolve2d` inside `compute_ssim`): a "valid" 1-D
/// convolution of `values · mask` along `step` (1: rows, `w`: columns), rescaled where the
/// window holds mask weight by `taps / Σ mask` (a partial convolution), else 0; returns the
/// blurred values and the next pass's mask (1 where the window held weight).
fn masked_blur(
    values: &[f64],
    mask: &[f64],
    (w, h): (usize, usize),
    horizontal: bool,
    filter: &[f64; DYCHECK_FILTER_SIZE],
) -> (Vec<f64>, Vec<f64>, (usize, usize)) {
    let n = DYCHECK_FILTER_SIZE;
    let (ow, oh) = if horizontal { (w + 1 - n, h) } else { (w, h + 1 - n) };
    let step = if horizontal { 1 } else { w };
    let (mut out, mut out_mask) = (vec![0.0; ow * oh], vec![0.0; ow * oh]);
    for y in 0..oh {
        for x in 0..ow {
            let start = y * w + x;
            let (mut sum, mut weight) = (0.0, 0.0);
            for (k, f) in filter.iter().enumerate() {
                let p = start + k * step;
                sum += f * values[p] * mask[p];
                weight += mask[p];
            }
            if weight != 0.0 {
                out[y * ow + x] = sum * n as f64 / weight;
                out_mask[y * ow + x] = 1.0;
            }
        }
    }
    (out, out_mask, (ow, oh))
}

/// DyCheck's `compute_ssim` with a mask (K1 0.01, K2 0.03, max value 1): per channel, the
/// masked blur along rows then columns of x, y, x², y², xy; variances clipped at 0, the
/// covariance at ±√(σx²σy²); the SSIM map's mean over every window and channel (NaN, the mean
/// of nothing, for frames narrower than the filter).
fn dycheck_masked_ssim(a: &[f64], b: &[f64], mask: &[f64], w: usize, h: usize) -> f64 {
    if w < DYCHECK_FILTER_SIZE || h < DYCHECK_FILTER_SIZE {
        return f64::NAN;
    }
    let filter = dycheck_filter();
    let blur = |values: &[f64]| -> Vec<f64> {
        let (rows, row_mask, size) = masked_blur(values, mask, (w, h), true, &filter);
        masked_blur(&rows, &row_mask, size, false, &filter).0
    };
    let (c1, c2) = (K1 * K1, K2 * K2);
    let (mut sum, mut count) = (0.0, 0usize);
    for c in 0..3 {
        let x: Vec<f64> = (0..w * h).map(|p| a[p * 3 + c]).collect();
        let y: Vec<f64> = (0..w * h).map(|p| b[p * 3 + c]).collect();
        let product = |u: &[f64], v: &[f64]| -> Vec<f64> { u.iter().zip(v).map(|(p, q)| p * q).collect() };
        let (mu0, mu1) = (blur(&x), blur(&y));
        let (xx, yy, xy) = (blur(&product(&x, &x)), blur(&product(&y, &y)), blur(&product(&x, &y)));
        for i in 0..mu0.len() {
            let (mu00, mu11, mu01) = (mu0[i] * mu0[i], mu1[i] * mu1[i], mu0[i] * mu1[i]);
            let s00 = (xx[i] - mu00).max(0.0);
            let s11 = (yy[i] - mu11).max(0.0);
            // jnp.sign(0) is 0, f64::signum(0) is 1.
            let raw = xy[i] - mu01;
            let s01 = if raw == 0.0 { 0.0 } else { raw.signum() * (s00 * s11).sqrt().min(raw.abs()) };
            sum += (2.0 * mu01 + c1) * (2.0 * s01 + c2) / ((mu00 + mu11 + c1) * (s00 + s11 + c2));
            count += 1;
        }
    }
    sum / count as f64
}

/// The per-pixel SSIM of two `w × h` RGB images (values in [0, 1], interleaved), averaged over
/// channels; only pixels at least 3 from the border are meaningful.
fn ssim_map(a: &[f64], b: &[f64], w: usize, h: usize) -> Vec<f64> {
    let np = (WIN_SIZE * WIN_SIZE) as f64;
    let cov_norm = np / (np - 1.0);
    let (c1, c2) = (K1 * K1, K2 * K2);
    let mut out = vec![0.0; w * h];
    for c in 0..3 {
        let channel = |img: &[f64]| -> Vec<f64> { (0..w * h).map(|p| img[p * 3 + c]).collect() };
        let (x, y) = (channel(a), channel(b));
        let product = |u: &[f64], v: &[f64]| -> Vec<f64> { u.iter().zip(v).map(|(p, q)| p * q).collect() };
        let ux = box_mean(&x, w, h);
        let uy = box_mean(&y, w, h);
        let uxx = box_mean(&product(&x, &x), w, h);
        let uyy = box_mean(&product(&y, &y), w, h);
        let uxy = box_mean(&product(&x, &y), w, h);
        for p in 0..w * h {
            let vx = cov_norm * (uxx[p] - ux[p] * ux[p]);
            let vy = cov_norm * (uyy[p] - uy[p] * uy[p]);
            let vxy = cov_norm * (uxy[p] - ux[p] * uy[p]);
            let s =
                (2.0 * ux[p] * uy[p] + c1) * (2.0 * vxy + c2) / ((ux[p] * ux[p] + uy[p] * uy[p] + c1) * (vx + vy + c2));
            out[p] += s / 3.0;
        }
    }
    out
}

/// The 7×7 window mean at every pixel whose window lies inside the image (others 0: they are
/// cropped away, as scikit-image crops them).
fn box_mean(values: &[f64], w: usize, h: usize) -> Vec<f64> {
    let r = (WIN_SIZE - 1) / 2;
    let mut rows = vec![0.0; w * h];
    for y in 0..h {
        for x in r..w.saturating_sub(r) {
            rows[y * w + x] = values[y * w + x - r..=y * w + x + r].iter().sum::<f64>();
        }
    }
    let mut out = vec![0.0; w * h];
    let n = (WIN_SIZE * WIN_SIZE) as f64;
    for y in r..h.saturating_sub(r) {
        for x in r..w.saturating_sub(r) {
            out[y * w + x] = (y - r..=y + r).map(|v| rows[v * w + x]).sum::<f64>() / n;
        }
    }
    out
}

/// Metrics of two videos frame by frame, with optional per-frame masks. Frame counts and sizes
/// must agree; errors name the input at fault (`pred`, `target`, `mask`).
pub fn video_metrics(pred: &[RgbImage], target: &[RgbImage], masks: Option<&[GrayImage]>) -> Result<VideoMetrics> {
    let mismatch = |name: &str, reason: String| Error::InvalidArgument { name: name.to_string(), reason };
    if pred.len() != target.len() {
        return Err(mismatch("pred", format!("{} frames, target has {}", pred.len(), target.len())));
    }
    if pred.is_empty() {
        return Err(mismatch("target", "no frames".to_string()));
    }
    let size = target[0].dimensions();
    for (i, (p, t)) in pred.iter().zip(target).enumerate() {
        if p.dimensions() != size || t.dimensions() != size {
            return Err(mismatch(
                "pred",
                format!(
                    "frame {i} is {:?}, target frame is {:?} (first target frame {size:?})",
                    p.dimensions(),
                    t.dimensions()
                ),
            ));
        }
        if size.0 < WIN_SIZE as u32 || size.1 < WIN_SIZE as u32 {
            return Err(mismatch(
                "target",
                format!("frames of {size:?} are smaller than the {WIN_SIZE}×{WIN_SIZE} SSIM window"),
            ));
        }
    }
    if let Some(masks) = masks {
        if masks.len() != target.len() {
            return Err(mismatch("mask", format!("{} masks for {} frames", masks.len(), target.len())));
        }
        if let Some(i) = masks.iter().position(|m| m.dimensions() != size) {
            return Err(mismatch("mask", format!("mask {i} is {:?}, frames are {size:?}", masks[i].dimensions())));
        }
    }
    let per_frame: Vec<FrameMetrics> =
        pred.iter().zip(target).enumerate().map(|(i, (p, t))| frame_metrics(p, t, masks.map(|m| &m[i]))).collect();
    Ok(VideoMetrics {
        frames: per_frame.len(),
        psnr: plain_mean(per_frame.iter().map(|f| f.psnr)).unwrap_or(f64::NAN),
        ssim: plain_mean(per_frame.iter().map(|f| f.ssim)).unwrap_or(f64::NAN),
        masked_psnr: plain_mean(per_frame.iter().filter_map(|f| f.masked_psnr)),
        masked_ssim: plain_mean(per_frame.iter().filter_map(|f| f.masked_ssim)),
        per_frame,
    })
}

/// Frames of a video file (decoded with FFmpeg) or of a folder of PNG/JPEG images (sorted by name).
pub fn read_frames(path: &Path) -> Result<Vec<RgbImage>> {
    Ok(read_named_frames(path)?.frames)
}

/// Frames with where each came from, for messages.
#[derive(Debug, Clone)]
pub struct NamedFrames {
    /// The frames.
    pub frames: Vec<RgbImage>,
    /// Per frame: its image file, or the video file (`sources[i]`) with `frame i`.
    pub sources: Vec<PathBuf>,
    /// Whether the frames come from one video file (then `sources` repeat it).
    pub from_video: bool,
    /// The video's frame rate (0 for image folders).
    pub fps: f64,
}

impl NamedFrames {
    /// `file` or `file frame i`.
    pub fn name(&self, i: usize) -> String {
        match (self.from_video, self.sources.get(i)) {
            (true, Some(p)) => format!("{} frame {i}", p.display()),
            (false, Some(p)) => p.display().to_string(),
            (_, None) => format!("frame {i}"),
        }
    }

    /// The common frame size, or an error naming the first frame that differs from frame 0
    /// (both files and sizes).
    pub fn uniform_size(&self) -> Result<(u32, u32)> {
        let size = self.frames.first().map_or((0, 0), |f| f.dimensions());
        if let Some(i) = self.frames.iter().position(|f| f.dimensions() != size) {
            let (w, h) = self.frames[i].dimensions();
            return Err(Error::InvalidInput {
                path: self.sources[i].clone(),
                what: "frame size".to_string(),
                reason: format!("{} is {w}x{h} but {} is {}x{}", self.name(i), self.name(0), size.0, size.1),
            });
        }
        Ok(size)
    }
}

/// [`read_frames`] keeping each frame's file.
pub fn read_named_frames(path: &Path) -> Result<NamedFrames> {
    if path.is_file() {
        let video = foundation::video::decode_video(path)?;
        let sources = vec![path.to_path_buf(); video.frames.len()];
        return Ok(NamedFrames { frames: video.frames, sources, from_video: true, fps: video.fps });
    }
    let images = sorted_images(path)?;
    if images.is_empty() {
        return Err(Error::InvalidInput {
            path: path.to_path_buf(),
            what: "frames".to_string(),
            reason: "neither a video file nor a folder of PNG/JPEG frames".to_string(),
        });
    }
    let frames = foundation::frames::read_frames(&images)?;
    Ok(NamedFrames { frames, sources: images, from_video: false, fps: 0.0 })
}

/// `trainer eval`: reads the predicted and target videos (and masks) and compares them. Frame
/// counts and sizes must agree within and between the inputs; errors name the files and sizes.
pub fn evaluate(pred: &Path, target: &Path, mask: Option<&Path>) -> Result<VideoMetrics> {
    let pred = read_named_frames(pred)?;
    let target_frames = read_named_frames(target)?;
    let (pred_size, target_size) = (pred.uniform_size()?, target_frames.uniform_size()?);
    if pred.frames.len() != target_frames.frames.len() {
        return Err(Error::InvalidInput {
            path: pred.sources.first().cloned().unwrap_or_default(),
            what: "frame count".to_string(),
            reason: format!(
                "pred has {} frames, target has {} ({})",
                pred.frames.len(),
                target_frames.frames.len(),
                target.display()
            ),
        });
    }
    if pred_size != target_size {
        return Err(Error::InvalidInput {
            path: pred.sources[0].clone(),
            what: "frame size".to_string(),
            reason: format!(
                "pred {} is {}x{} but target {} is {}x{}",
                pred.name(0),
                pred_size.0,
                pred_size.1,
                target_frames.name(0),
                target_size.0,
                target_size.1
            ),
        });
    }
    let masks = match mask {
        Some(dir) => {
            let files = sorted_images(dir)?;
            let masks = read_masks(dir)?;
            if let Some(i) = masks.iter().position(|m| m.dimensions() != target_size) {
                let (w, h) = masks[i].dimensions();
                return Err(Error::InvalidInput {
                    path: files[i].clone(),
                    what: "mask size".to_string(),
                    reason: format!(
                        "{w}x{h}, but target {} is {}x{}",
                        target_frames.name(0),
                        target_size.0,
                        target_size.1
                    ),
                });
            }
            Some(masks)
        }
        None => None,
    };
    video_metrics(&pred.frames, &target_frames.frames, masks.as_deref())
}

/// Masks from a folder of PNGs (sorted by name; non-zero = co-visible), as `datagen inspect
/// --export` writes them (`mask/%05d.png`) or `datagen render` (`holes/`, inverted there).
pub fn read_masks(dir: &Path) -> Result<Vec<GrayImage>> {
    sorted_images(dir)?
        .iter()
        .map(|p| {
            image::open(p)
                .map(|i| i.to_luma8())
                .map_err(|e| Error::InvalidArgument { name: p.display().to_string(), reason: e.to_string() })
        })
        .collect()
}

fn sorted_images(dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir).map_err(|source| Error::Io { path: dir.to_path_buf(), error: source })?;
    let mut paths: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| ["png", "jpg", "jpeg"].iter().any(|x| e.eq_ignore_ascii_case(x)))
        })
        .collect();
    paths.sort();
    Ok(paths)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_frames_have_infinite_psnr_and_unit_ssim() {
        let img = RgbImage::from_fn(16, 12, |x, y| image::Rgb([(x * 13) as u8, (y * 17) as u8, ((x + y) * 5) as u8]));
        let m = frame_metrics(&img, &img, None);
        assert!(m.psnr.is_infinite());
        assert!((m.ssim - 1.0).abs() < 1e-12);
    }
}

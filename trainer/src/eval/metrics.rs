//! Image-quality metrics of `trainer eval`, with scikit-image's conventions (the numbers papers
//! report): PSNR `10·log10(1 / MSE)` and SSIM as `skimage.metrics.structural_similarity(…,
//! data_range=1, channel_axis=-1)` (7×7 uniform window, K1 = 0.01, K2 = 0.03, sample covariance,
//! the mean over the image less a 3-pixel border, averaged over channels), on RGB values scaled to
//! [0, 1]. The masked variants restrict the mean to co-visible pixels: PSNR from the MSE over
//! them, SSIM as the mean of the SSIM map over them (inside the same border).

use std::path::{Path, PathBuf};

use image::{GrayImage, RgbImage};
use serde::Serialize;

use crate::error::{Error, Result};

/// SSIM window side (scikit-image's default `win_size`).
const WIN_SIZE: usize = 7;
/// SSIM stabilisers as fractions of the data range (Wang et al. 2004; scikit-image defaults).
const K1: f64 = 0.01;
const K2: f64 = 0.03;

/// Metrics of one frame pair.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FrameMetrics {
    /// PSNR in dB over the whole frame (infinite for identical frames).
    pub psnr: f64,
    /// Mean SSIM.
    pub ssim: f64,
    /// PSNR over co-visible pixels (None without a mask or when no pixel is co-visible).
    pub masked_psnr: Option<f64>,
    /// Mean SSIM over co-visible pixels inside the border.
    pub masked_ssim: Option<f64>,
}

/// Metrics of a video pair: per frame and their means.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct VideoMetrics {
    /// Frames compared.
    pub frames: usize,
    /// Mean over frames of the per-frame PSNR (frames with infinite PSNR are left out).
    pub psnr: f64,
    /// Mean SSIM over frames.
    pub ssim: f64,
    /// Mean masked PSNR over frames that have co-visible pixels.
    pub masked_psnr: Option<f64>,
    /// Mean masked SSIM over frames that have co-visible pixels.
    pub masked_ssim: Option<f64>,
    /// Per-frame values.
    pub per_frame: Vec<FrameMetrics>,
}

fn unit(image: &RgbImage) -> Vec<f64> {
    image.as_raw().iter().map(|&v| f64::from(v) / 255.0).collect()
}

/// Metrics of one frame pair; `mask` (non-zero: co-visible) selects the masked variants.
pub fn frame_metrics(pred: &RgbImage, target: &RgbImage, mask: Option<&GrayImage>) -> FrameMetrics {
    let (a, b) = (unit(pred), unit(target));
    let (w, h) = target.dimensions();
    let (w, h) = (w as usize, h as usize);
    let keep: Option<Vec<bool>> = mask.map(|m| m.as_raw().iter().map(|&v| v != 0).collect());
    let mse = |selected: &dyn Fn(usize) -> bool| -> Option<f64> {
        let (mut sum, mut n) = (0.0, 0usize);
        for p in (0..w * h).filter(|&p| selected(p)) {
            for c in 0..3 {
                sum += (a[p * 3 + c] - b[p * 3 + c]).powi(2);
            }
            n += 3;
        }
        (n > 0).then(|| sum / n as f64)
    };
    let psnr = |mse: f64| 10.0 * (1.0 / mse).log10();
    let map = ssim_map(&a, &b, w, h);
    let pad = (WIN_SIZE - 1) / 2;
    let inside = |p: usize| {
        let (x, y) = (p % w, p / w);
        x >= pad && y >= pad && x + pad < w && y + pad < h
    };
    let mean_ssim = |selected: &dyn Fn(usize) -> bool| -> Option<f64> {
        let (mut sum, mut n) = (0.0, 0usize);
        for p in (0..w * h).filter(|&p| inside(p) && selected(p)) {
            sum += map[p];
            n += 1;
        }
        (n > 0).then(|| sum / n as f64)
    };
    FrameMetrics {
        psnr: psnr(mse(&|_| true).unwrap_or(0.0)),
        ssim: mean_ssim(&|_| true).unwrap_or(f64::NAN),
        masked_psnr: keep.as_ref().and_then(|k| mse(&|p| k[p])).map(psnr),
        masked_ssim: keep.as_ref().and_then(|k| mean_ssim(&|p| k[p])),
    }
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
    let mean = |values: Vec<f64>| (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64);
    Ok(VideoMetrics {
        frames: per_frame.len(),
        psnr: mean(per_frame.iter().map(|f| f.psnr).filter(|v| v.is_finite()).collect()).unwrap_or(f64::INFINITY),
        ssim: mean(per_frame.iter().map(|f| f.ssim).collect()).unwrap_or(f64::NAN),
        masked_psnr: mean(per_frame.iter().filter_map(|f| f.masked_psnr).filter(|v| v.is_finite()).collect()),
        masked_ssim: mean(per_frame.iter().filter_map(|f| f.masked_ssim).collect()),
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

//! VGGT's predictions (facebookresearch/vggt): the `predictions.npz` its Gradio demo saves from
//! the model's output dict after `pose_encoding_to_extri_intri`, batch axis removed. Members read:
//!
//! - `extrinsic` (S, 3, 4): **camera_from_world**, OpenCV axes (VGGT's documented convention);
//!   checked rigid, then inverted to `world_from_camera`. A (S, 4, 4) array is accepted too.
//! - `intrinsic` (S, 3, 3): K in pixels of the model's input images (principal point at W/2, H/2;
//!   VGGT unprojects with integer pixel coordinates, as here, so K is taken as is).
//! - `depth` (S, H, W, 1) or (S, H, W): z-depth in VGGT's normalised scene scale (not metric).
//! - `depth_conf` (S, H, W): confidence ≥ 1. Every finite depth is kept by default: VGGT
//!   filters by confidence only to display its point cloud. Given a percentile p, depth is
//!   dropped as VGGT's demo viewers drop points ([`confidence_threshold`]): kept where the
//!   confidence is ≥ the p-th percentile of all the sequence's confidences (NumPy's linear
//!   interpolation, p = 0 keeping all) and above [`MIN_CONFIDENCE`]. NaN is an error.
//! - `images` (S, 3, H, W) or (S, H, W, 3): the preprocessed input frames as floats in 0–1 (the
//!   frames the depth belongs to; the originals on disk were resized and cropped).
//!
//! Not read: `pose_enc` (the encoding `extrinsic`/`intrinsic` were decoded from), `world_points`
//! and `world_points_conf` (the point head, a second geometry estimate: depth + cameras are used),
//! `world_points_from_depth`.

use std::path::Path;

use image::RgbImage;

use crate::error::{Error, Result};
use crate::io::npy::{Axis, NpzReader};
use crate::io::tool_output::{ToolFrames, ToolOutput, check_depth_sign, invert_camera_from_world, mask_by_confidence};

/// The file VGGT's demo writes into its output folder.
pub const PREDICTIONS_FILE: &str = "predictions.npz";

/// Confidence at or below which VGGT's viewers drop a point whatever the percentile (their
/// `conf > 1e-5`).
pub const MIN_CONFIDENCE: f32 = 1e-5;

/// The default `conf_thres` (50) of VGGT's Gradio demo: a starting value for the percentile
/// option, never applied unless asked for.
pub const DEMO_CONFIDENCE_PERCENTILE: f64 = 50.0;

/// Reads `predictions.npz` at `path`, with its frames; with `confidence_percentile` (0–100),
/// depth below that percentile of `depth_conf` is dropped ([`confidence_threshold`]).
pub fn read_vggt(path: &Path, confidence_percentile: Option<f64>) -> Result<ToolOutput> {
    if let Some(p) = confidence_percentile
        && !(0.0..=100.0).contains(&p)
    {
        return Err(Error::invalid(path, "depth_conf", format!("confidence percentile {p} is outside 0–100")));
    }
    let mut archive = NpzReader::open(path)?;
    let extrinsic_header = archive.header("extrinsic", None)?;
    let frames = *extrinsic_header.shape.first().unwrap_or(&0);
    let pose_rows = match extrinsic_header.shape.as_slice() {
        [_, 3, 4] => 3,
        [_, 4, 4] => 4,
        other => {
            return Err(Error::array(
                path,
                Some("extrinsic.npy"),
                format!("expected shape (S, 3, 4) camera_from_world matrices, found {other:?}"),
            ));
        }
    };
    if frames == 0 {
        return Err(Error::array(path, Some("extrinsic.npy"), "no frames"));
    }
    let n = Axis::Is(frames);
    let depth_header = archive.header("depth", None)?;
    let depth_spec: Vec<Axis> = match depth_header.shape.as_slice() {
        [_, _, _, 1] => vec![n, Axis::Pixels, Axis::Pixels, Axis::Is(1)],
        [_, _, _] => vec![n, Axis::Pixels, Axis::Pixels],
        other => {
            return Err(Error::array(
                path,
                Some("depth.npy"),
                format!("expected shape (S, H, W, 1) or (S, H, W), found {other:?}"),
            ));
        }
    };
    let depth = archive.read_f32("depth", &depth_spec)?;
    let (height, width) = (depth.shape[1], depth.shape[2]);
    let plane_spec = [n, Axis::Is(height), Axis::Is(width)];
    let extrinsic = archive.read_f64("extrinsic", &[n, Axis::Is(pose_rows), Axis::Is(4)])?;
    let intrinsic = archive.read_f64("intrinsic", &[n, Axis::Is(3), Axis::Is(3)])?;

    let mut planes = depth.into_planes();
    for (i, plane) in planes.iter().enumerate() {
        check_depth_sign(path, "depth", i, plane)?;
    }
    if let Some(p) = confidence_percentile {
        if !archive.contains("depth_conf") {
            return Err(Error::array(path, Some("depth_conf.npy"), "missing: a confidence percentile was given"));
        }
        let confidence = archive.read_f32("depth_conf", &plane_spec)?;
        let threshold = confidence_threshold(&confidence.data, p);
        for (i, (plane, conf)) in planes.iter_mut().zip(confidence.into_planes()).enumerate() {
            mask_by_confidence(path, "depth_conf", i, width, plane, &conf, threshold)?;
        }
    }
    let world_from_camera = extrinsic
        .data
        .chunks_exact(pose_rows * 4)
        .enumerate()
        .map(|(i, m)| invert_camera_from_world(path, &format!("extrinsic[{i}]"), m))
        .collect::<Result<Vec<_>>>()?;
    let intrinsics = intrinsic.data.chunks_exact(9).map(|k| k.try_into().expect("9 values")).collect();
    let images = read_images(&mut archive, path, frames, width, height)?;
    Ok(ToolOutput {
        frames: Some(ToolFrames { fps: 0.0, frames: images, path: path.to_owned() }),
        depth_path: path.to_owned(),
        depth_size: (width, height),
        depth: planes,
        intrinsics_path: path.to_owned(),
        intrinsics_size: (width as u32, height as u32),
        intrinsics,
        poses_path: path.to_owned(),
        world_from_camera,
    })
}

/// The `images` member as RGB frames: channels first or last, float 0–1 (VGGT's preprocessing).
fn read_images(
    archive: &mut NpzReader,
    path: &Path,
    frames: usize,
    width: usize,
    height: usize,
) -> Result<Vec<RgbImage>> {
    let n = Axis::Is(frames);
    let header = archive.header("images", None)?;
    let channels_first = match header.shape.as_slice() {
        [_, 3, h, w] if (*h, *w) == (height, width) => true,
        [_, h, w, 3] if (*h, *w) == (height, width) => false,
        other => {
            return Err(Error::array(
                path,
                Some("images.npy"),
                format!(
                    "expected ({frames}, 3, {height}, {width}) or ({frames}, {height}, {width}, 3) like `depth`, found {other:?}"
                ),
            ));
        }
    };
    let spec = if channels_first {
        [n, Axis::Is(3), Axis::Is(height), Axis::Is(width)]
    } else {
        [n, Axis::Is(height), Axis::Is(width), Axis::Is(3)]
    };
    let images = archive.read_f32("images", &spec)?;
    if let Some(i) = images.data.iter().position(|v| !(0.0..=1.0).contains(v)) {
        return Err(Error::array(
            path,
            Some("images.npy"),
            format!(
                "value {} at index {i} is outside 0–1: VGGT's images are floats in 0–1 (saved after its preprocessing)",
                images.data[i]
            ),
        ));
    }
    let plane = width * height;
    Ok(images
        .data
        .chunks_exact(plane * 3)
        .map(|frame| {
            let byte = |v: f32| (v * f32::from(u8::MAX)).round() as u8;
            let pixels: Vec<u8> = if channels_first {
                (0..plane).flat_map(|p| (0..3).map(move |c| byte(frame[c * plane + p]))).collect()
            } else {
                frame.iter().map(|&v| byte(v)).collect()
            };
            RgbImage::from_raw(width as u32, height as u32, pixels).expect("sized")
        })
        .collect())
}

/// The confidence below which VGGT's viewers drop points at percentile `p` (0–100): 0 for p = 0,
/// else `np.percentile(conf, p)` (linear interpolation between the two nearest ranks of the
/// finite values), raised to just above [`MIN_CONFIDENCE`] so that `conf ≥ threshold` also
/// means `conf > MIN_CONFIDENCE`. A NaN is reported by the confidence check that follows,
/// naming its pixel.
pub fn confidence_threshold(values: &[f32], p: f64) -> f32 {
    let mut finite: Vec<f32> = values.iter().copied().filter(|v| v.is_finite()).collect();
    let floor = MIN_CONFIDENCE.next_up();
    if p == 0.0 || finite.is_empty() {
        return floor;
    }
    finite.sort_unstable_by(f32::total_cmp);
    let rank = (p / 100.0) * (finite.len() - 1) as f64;
    let (below, above) = (rank.floor() as usize, rank.ceil() as usize);
    let (low, high) = (f64::from(finite[below]), f64::from(finite[above]));
    let value = (low + (high - low) * (rank - below as f64)) as f32;
    value.max(floor)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn threshold_interpolates_like_numpy_percentile() {
        // np.percentile([5, 1, 3, 2, 4], p) for p = 50, 0, 100, 30: 3.0, 1.0, 5.0, 2.2.
        let values = [5.0, 1.0, 3.0, 2.0, 4.0];
        assert_eq!(confidence_threshold(&values, 50.0), 3.0);
        assert_eq!(confidence_threshold(&values, 100.0), 5.0);
        assert!((confidence_threshold(&values, 30.0) - 2.2).abs() < 1e-6);
        // p = 0 keeps everything above VGGT's 1e-5 floor.
        assert!(confidence_threshold(&values, 0.0) > MIN_CONFIDENCE && confidence_threshold(&values, 0.0) < 1e-4);
    }
}

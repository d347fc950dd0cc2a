//! Pre- and post-processing of the videos a pipeline samples (diffusers' `VideoProcessor` and the
//! CogNVS demo around it): picking the frames, resizing them to the model's size and back, and
//! converting between `u8` frames and the `[-1, 1]` video tensor the VAE takes.
//!
//! The resizes follow OpenCV's `cv2.resize`, which the public CogNVS demo calls: `INTER_AREA` to
//! bring the conditioning to the model's size (an area average when shrinking, OpenCV's
//! area-weighted linear interpolation when growing) and the default `INTER_LINEAR` (half-pixel
//! centres, 11-bit fixed-point weights) to bring the result back to the input's size. Both are
//! written from OpenCV's definitions; the linear one (shared with evaluation,
//! [`crate::eval::resize`]) equals OpenCV's bit for bit, the area shrink to within one grey level.

use image::RgbImage;
use image::imageops::FilterType;
use tch::{Device, Kind, Tensor};

use crate::error::{Error, Result};
use crate::eval::resize::{LinearPlacement, cv_scale, resize_linear_opencv_with};

/// Most frames per sample: 1 + 4·256, far beyond CogVideoX's 49 (1.5: 81); more is a typo that
/// would allocate gigabytes per sample.
pub const MAX_FRAMES: usize = 1025;
/// Largest training side in pixels (an 8K frame; the paper trains at 480 × 720).
pub const MAX_SIDE: u32 = 8192;

/// How a conditioning frame of another size is brought to the model's size.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ResizeMode {
    /// Stretch to the model's size with an area average (the public demo's `cv2.INTER_AREA`):
    /// the whole frame is kept, its aspect ratio is not.
    #[default]
    Area,
    /// Scale to cover the model's size and crop the centre (what the training loader does):
    /// the aspect ratio is kept, the borders are lost.
    Crop,
}

/// How many frames to sample from an input of `count`: `wanted` (a 1 + `temporal`·k count the
/// caller checked) when the input has that many, else the most that decode back to as many
/// frames: 1 + 2·`temporal`·j, an odd number of latent frames (CogVideoX's VAE turns an even
/// number of latent frames into a multiple of `temporal` frames, not 1 + `temporal`·k). None
/// for an input without frames.
pub fn take_frames(count: usize, wanted: usize, temporal: usize) -> Option<usize> {
    if count >= wanted {
        return Some(wanted);
    }
    let period = 2 * temporal.max(1);
    (count > 0).then(|| count - (count - 1) % period)
}

/// `frame` brought to `width × height` as `mode` says.
pub fn fit(frame: &RgbImage, width: u32, height: u32, mode: ResizeMode) -> RgbImage {
    match mode {
        ResizeMode::Area => resize_area(frame, width, height),
        ResizeMode::Crop => cover_crop(frame, width, height, image::imageops::FilterType::Triangle),
    }
}

/// OpenCV's `resize(..., INTER_AREA)`: each output pixel the area-weighted mean of the input
/// pixels its footprint covers when both axes shrink; OpenCV's area-style linear interpolation
/// when an axis grows.
pub fn resize_area(frame: &RgbImage, width: u32, height: u32) -> RgbImage {
    let (sw, sh) = frame.dimensions();
    if (sw, sh) == (width, height) {
        return frame.clone();
    }
    let (scale_x, scale_y) = (cv_scale(sw, width), cv_scale(sh, height));
    if scale_x >= 1.0 && scale_y >= 1.0 {
        let (ix, iy) = (scale_x.round(), scale_y.round());
        if (scale_x - ix).abs() < f64::EPSILON && (scale_y - iy).abs() < f64::EPSILON {
            return area_integer(frame, width, height, ix as u32, iy as u32);
        }
        return area_fractional(frame, width, height, scale_x, scale_y);
    }
    resize_linear_opencv_with(frame, width, height, LinearPlacement::Area)
}

/// OpenCV's `resize(...)` with the default `INTER_LINEAR`: bilinear weights at half-pixel
/// centres, borders replicated, 11-bit fixed-point arithmetic as OpenCV's 8-bit path.
pub fn resize_linear(frame: &RgbImage, width: u32, height: u32) -> RgbImage {
    crate::eval::resize::resize_linear_opencv(frame, width, height)
}

/// Integer shrink factors: the plain block mean, rounded as OpenCV rounds it (its 2×2 kernel
/// adds 2 before the shift; larger blocks multiply by 1/area and round half to even).
fn area_integer(frame: &RgbImage, width: u32, height: u32, fx: u32, fy: u32) -> RgbImage {
    let area = fx * fy;
    let scale = 1.0f32 / area as f32;
    RgbImage::from_fn(width, height, |x, y| {
        image::Rgb(std::array::from_fn(|c| {
            let mut sum = 0u32;
            for dy in 0..fy {
                for dx in 0..fx {
                    sum += u32::from(frame.get_pixel(x * fx + dx, y * fy + dy).0[c]);
                }
            }
            if area == 4 { ((sum + 2) >> 2) as u8 } else { round_u8(sum as f32 * scale) }
        }))
    })
}

/// One source sample of an output coordinate: source index and weight.
#[derive(Debug, Clone, Copy)]
struct AreaTap {
    destination: usize,
    source: usize,
    weight: f32,
}

/// OpenCV's `computeResizeAreaTab`: the source cells each destination cell overlaps, with the
/// overlap as a fraction of the destination cell's width.
fn area_taps(source: u32, destination: u32, scale: f64) -> Vec<AreaTap> {
    /// Overlaps shorter than this are ignored (OpenCV's threshold).
    const MIN_OVERLAP: f64 = 1e-3;
    let mut taps = Vec::new();
    for d in 0..destination as usize {
        let start = d as f64 * scale;
        let end = start + scale;
        let cell = scale.min(f64::from(source) - start);
        let last = (end.floor() as i64).min(i64::from(source) - 1);
        let first = (start.ceil() as i64).min(last);
        if first as f64 - start > MIN_OVERLAP {
            let weight = ((first as f64 - start) / cell) as f32;
            taps.push(AreaTap { destination: d, source: (first - 1) as usize, weight });
        }
        for s in first..last {
            taps.push(AreaTap { destination: d, source: s as usize, weight: (1.0 / cell) as f32 });
        }
        if end - last as f64 > MIN_OVERLAP {
            let weight = ((end - last as f64).min(1.0).min(cell) / cell) as f32;
            taps.push(AreaTap { destination: d, source: last as usize, weight });
        }
    }
    taps
}

/// Fractional shrink factors: OpenCV's separable area sum in f32 (rows of weighted taps, then
/// the weighted rows of each output row), rounded half to even.
fn area_fractional(frame: &RgbImage, width: u32, height: u32, scale_x: f64, scale_y: f64) -> RgbImage {
    let (sw, sh) = frame.dimensions();
    let x_taps = area_taps(sw, width, scale_x);
    let y_taps = area_taps(sh, height, scale_y);
    let row_len = width as usize * 3;
    let source = frame.as_raw();
    let mut out = vec![0u8; row_len * height as usize];
    let mut row = vec![0f32; row_len];
    let mut sum = vec![0f32; row_len];
    let mut current = y_taps.first().map_or(0, |t| t.destination);
    for tap in &y_taps {
        row.fill(0.0);
        let line = &source[tap.source * sw as usize * 3..][..sw as usize * 3];
        for x in &x_taps {
            for c in 0..3 {
                row[x.destination * 3 + c] += f32::from(line[x.source * 3 + c]) * x.weight;
            }
        }
        if tap.destination != current {
            let target = &mut out[current * row_len..][..row_len];
            for ((t, s), r) in target.iter_mut().zip(sum.iter_mut()).zip(&row) {
                *t = round_u8(*s);
                *s = tap.weight * r;
            }
            current = tap.destination;
        } else {
            for (s, r) in sum.iter_mut().zip(&row) {
                *s += tap.weight * r;
            }
        }
    }
    for (t, s) in out[current * row_len..][..row_len].iter_mut().zip(&sum) {
        *t = round_u8(*s);
    }
    RgbImage::from_raw(width, height, out).expect("buffer of the output's size")
}

/// OpenCV's `saturate_cast<uchar>(float)`: round half to even, clamp to 0..=255.
fn round_u8(value: f32) -> u8 {
    value.round_ties_even().clamp(0.0, 255.0) as u8
}

/// Frames of one size as the video tensor `[1, 3, F, H, W]` in [−1, 1] (`x / 127.5 − 1`, as the
/// demo scales them), of element type `kind` on `device`.
pub fn frames_to_video(frames: &[RgbImage], kind: Kind, device: Device) -> Result<Tensor> {
    let (width, height) = frames.first().map_or((0, 0), |f| f.dimensions());
    if frames.is_empty() || frames.iter().any(|f| f.dimensions() != (width, height)) {
        return Err(Error::InvalidArgument {
            name: "frames".to_string(),
            reason: "a video needs at least one frame, all of one size".to_string(),
        });
    }
    let bytes: Vec<u8> = frames.iter().flat_map(|f| f.as_raw().iter().copied()).collect();
    let (f, h, w) = (frames.len() as i64, i64::from(height), i64::from(width));
    Ok(Tensor::from_slice(&bytes)
        .f_view([1, f, h, w, 3])?
        .f_permute([0, 4, 1, 2, 3])?
        .f_to_kind(Kind::Float)?
        .f_div_scalar(127.5)?
        .f_sub_scalar(1.0)?
        .f_to_device(device)?
        .f_to_kind(kind)?)
}

/// The frames of a video tensor `[1, 3, F, H, W]` in [−1, 1], as diffusers' `postprocess_video`
/// makes PIL images: `(x · 0.5 + 0.5).clamp(0, 1)` in the tensor's own element type, then
/// `round(255 · v)` in f32 (half to even).
pub fn video_to_frames(video: &Tensor) -> Result<Vec<RgbImage>> {
    let size = video.size();
    if size.len() != 5 || size[0] != 1 || size[1] != 3 {
        return Err(Error::Shape {
            tensor: "video".to_string(),
            expected: "[1, 3, F, H, W]".to_string(),
            actual: size,
        });
    }
    let (height, width) = (size[3], size[4]);
    let pixels = video
        .f_squeeze_dim(0)?
        .f_permute([1, 2, 3, 0])?
        .f_mul_scalar(0.5)?
        .f_add_scalar(0.5)?
        .f_clamp(0.0, 1.0)?
        .f_to_device(Device::Cpu)?
        .f_to_kind(Kind::Float)?
        .f_mul_scalar(255.0)?
        .f_round()?
        .f_to_kind(Kind::Uint8)?
        .f_contiguous()?;
    let data: Vec<u8> = Vec::<u8>::try_from(pixels.f_flatten(0, -1)?)?;
    Ok(data
        .chunks((width * height * 3) as usize)
        .map(|chunk| RgbImage::from_raw(width as u32, height as u32, chunk.to_vec()).expect("frame-sized chunk"))
        .collect())
}

/// Scales `image` to cover `width × height` (keeping its aspect) and crops the centre: how the
/// loader brings every clip to the training resolution (sampling does the same to conditionings).
pub fn cover_crop<P: image::Pixel<Subpixel = u8> + 'static>(
    image: &image::ImageBuffer<P, Vec<u8>>,
    width: u32,
    height: u32,
    filter: FilterType,
) -> image::ImageBuffer<P, Vec<u8>> {
    let (w, h) = image.dimensions();
    if (w, h) == (width, height) {
        return image.clone();
    }
    let scale = (f64::from(width) / f64::from(w)).max(f64::from(height) / f64::from(h));
    let (sw, sh) =
        (((f64::from(w) * scale).round() as u32).max(width), ((f64::from(h) * scale).round() as u32).max(height));
    let scaled = image::imageops::resize(image, sw, sh, filter);
    image::imageops::crop_imm(&scaled, (sw - width) / 2, (sh - height) / 2, width, height).to_image()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(width: u32, height: u32) -> RgbImage {
        RgbImage::from_fn(width, height, |x, y| image::Rgb([(x * 7 + y * 3) as u8, (x * y) as u8, (255 - x) as u8]))
    }

    #[test]
    fn frames_follow_the_vae_temporal_compression() {
        assert_eq!(take_frames(100, 49, 4), Some(49));
        assert_eq!(take_frames(49, 49, 4), Some(49));
        assert_eq!(take_frames(30, 49, 4), Some(25));
        assert_eq!(take_frames(8, 49, 4), Some(1));
        assert_eq!(take_frames(9, 49, 4), Some(9));
        assert_eq!(take_frames(0, 49, 4), None);
        assert_eq!(take_frames(12, 13, 4), Some(9));
    }

    #[test]
    fn area_of_a_constant_image_is_that_constant() {
        let flat = RgbImage::from_pixel(37, 23, image::Rgb([10, 200, 77]));
        for (w, h) in [(20, 11), (10, 7), (37, 46), (74, 23), (8, 8)] {
            let out = resize_area(&flat, w, h);
            assert!(out.pixels().all(|p| p.0 == [10, 200, 77]), "{w}x{h}");
        }
    }

    #[test]
    fn area_shrink_by_two_is_the_block_mean() {
        let image = ramp(8, 6);
        let out = resize_area(&image, 4, 3);
        for (x, y, p) in out.enumerate_pixels() {
            for c in 0..3 {
                let sum: u32 = (0..2)
                    .flat_map(|dy| (0..2).map(move |dx| (dx, dy)))
                    .map(|(dx, dy)| u32::from(image.get_pixel(2 * x + dx, 2 * y + dy).0[c]))
                    .sum();
                assert_eq!(u32::from(p.0[c]), (sum + 2) / 4);
            }
        }
    }

    #[test]
    fn area_fractional_weights_sum_to_one() {
        for (s, d) in [(720u32, 480u32), (1280, 720), (50, 7), (9, 8)] {
            let taps = area_taps(s, d, cv_scale(s, d));
            let mut sums = vec![0f64; d as usize];
            for t in &taps {
                sums[t.destination] += f64::from(t.weight);
            }
            assert!(sums.iter().all(|v| (v - 1.0).abs() < 1e-5), "{s} -> {d}: {sums:?}");
        }
    }

    #[test]
    fn linear_resize_keeps_constants_and_size() {
        let flat = RgbImage::from_pixel(13, 9, image::Rgb([3, 128, 254]));
        for (w, h) in [(26, 18), (7, 5), (13, 20)] {
            let out = resize_linear(&flat, w, h);
            assert_eq!(out.dimensions(), (w, h));
            assert!(out.pixels().all(|p| p.0 == [3, 128, 254]), "{w}x{h}");
        }
    }

    #[test]
    fn video_tensor_round_trips_frames() {
        let frames = vec![ramp(16, 8), ramp(16, 8)];
        let video = frames_to_video(&frames, Kind::Float, Device::Cpu).unwrap();
        assert_eq!(video.size(), [1, 3, 2, 8, 16]);
        assert_eq!(video_to_frames(&video).unwrap(), frames);
    }
}

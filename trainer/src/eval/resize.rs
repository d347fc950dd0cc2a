//! The two resizes evaluation depends on, bit for bit:
//!
//! - OpenCV's `cv2.resize(frame, (W, H))` on 8-bit frames (default `INTER_LINEAR`), which the
//!   official CogNVS evaluation (`eval/eval_metrics.py`, `read_video`) applies to every frame
//!   whose size is not the protocol's, and the public demo to bring samples back to the input's
//!   size ([`resize_linear_opencv`]);
//! - Pillow's `Image.resize(..., resample=BICUBIC)` on one float (`mode="F"`) channel, which is
//!   clean-fid's "clean" resize to 299×299 (`cleanfid/resize.py`, `make_resizer("PIL", False,
//!   "bicubic", ...)`): separable, horizontal pass first, the kernel widened by the scale when
//!   shrinking (antialiasing), weights normalised per output pixel, sums in f64 and each pass
//!   stored as f32 (Pillow's `libImaging/Resample.c`).

use image::RgbImage;

/// OpenCV's fixed-point scale of 8-bit linear weights (`INTER_RESIZE_COEF_SCALE` = 2^11,
/// `imgproc/src/resize.hpp`).
const COEF_SCALE: f32 = 2048.0;

/// How OpenCV places a destination pixel on the source axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinearPlacement {
    /// `INTER_LINEAR`: centre at `(d + 0.5)·scale − 0.5`.
    Linear,
    /// `INTER_AREA` when an axis grows: OpenCV's area-style linear weights.
    Area,
}

/// OpenCV's source-per-destination scale: `1 / (dst / src)`, computed as OpenCV computes it
/// (`scale_x = 1./inv_scale_x`, which can differ from `src / dst` in the last bit).
pub fn cv_scale(source: u32, destination: u32) -> f64 {
    1.0 / (f64::from(destination) / f64::from(source))
}

/// One axis of OpenCV's 8-bit linear resize (`resizeGeneric_`'s table set-up in `cv::resize`):
/// per destination index the first source index and the two 11-bit weights. The position is
/// computed in f64, stored as f32, split into floor and fraction in f32, and each weight rounded
/// half to even (`saturate_cast<short>`). `clamp` is the horizontal rule: a position left of the
/// first or right of the last source pixel takes that pixel with weight 1. Rows are not
/// clamped: OpenCV keeps the fraction and clips both row indices instead (`ResizeInvoker`), so
/// the first and last output rows of an enlargement blend the border row with itself through
/// two rounded weights, which can differ by one level from weight 1.
fn linear_taps(source: u32, destination: u32, placement: LinearPlacement, clamp: bool) -> Vec<(i64, i32, i32)> {
    let scale = cv_scale(source, destination);
    let inverse = f64::from(destination) / f64::from(source);
    (0..destination)
        .map(|d| {
            let d = f64::from(d);
            let (mut s, mut f) = match placement {
                LinearPlacement::Area => {
                    let s = (d * scale).floor();
                    let f = ((d + 1.0) - (s + 1.0) * inverse) as f32;
                    (s as i64, if f <= 0.0 { 0.0 } else { f - f.floor() })
                }
                LinearPlacement::Linear => {
                    let f = ((d + 0.5) * scale - 0.5) as f32;
                    let s = f.floor();
                    (s as i64, f - s)
                }
            };
            if clamp && s < 0 {
                (s, f) = (0, 0.0);
            }
            if clamp && s >= i64::from(source) - 1 {
                (s, f) = (i64::from(source) - 1, 0.0);
            }
            let w1 = (f * COEF_SCALE).round_ties_even() as i32;
            let w0 = ((1.0 - f) * COEF_SCALE).round_ties_even() as i32;
            (s, w0, w1)
        })
        .collect()
}

/// `cv2.resize(frame, (width, height))`: OpenCV's default `INTER_LINEAR` on an 8-bit RGB frame,
/// equal to OpenCV 5's output bit for bit (checked against `cv2` by the tests). The same size
/// returns a copy, as OpenCV does; an exact halving of both sides, which OpenCV computes as
/// `INTER_AREA`'s 2×2 mean `(a + b + c + d + 2) >> 2`, gives the same values here.
pub fn resize_linear_opencv(frame: &RgbImage, width: u32, height: u32) -> RgbImage {
    if frame.dimensions() == (width, height) {
        return frame.clone();
    }
    resize_linear_opencv_with(frame, width, height, LinearPlacement::Linear)
}

/// OpenCV's 8-bit linear resize with the destination placed as `placement` says: horizontal
/// pass in integers with 11-bit weights, vertical pass as OpenCV's SIMD kernel
/// (`VResizeLinearVec_32s8u`) computes it: each row term shifted right by 4, multiplied keeping
/// the high 16 bits (`v_mul_hi`), summed, then rounded by 2 bits and saturated
/// (`v_rshr_pack_u<2>`).
pub fn resize_linear_opencv_with(frame: &RgbImage, width: u32, height: u32, placement: LinearPlacement) -> RgbImage {
    let (sw, sh) = frame.dimensions();
    let x_taps = linear_taps(sw, width, placement, true);
    let y_taps = linear_taps(sh, height, placement, false);
    let source = frame.as_raw();
    let row_len = width as usize * 3;
    let last_row = i64::from(sh) - 1;
    let clip = |y: i64| y.clamp(0, last_row) as usize;
    // Each source row a destination row reads is filtered horizontally once.
    let mut rows: Vec<Option<Vec<i32>>> = vec![None; sh as usize];
    for &(s, _, _) in &y_taps {
        for y in [clip(s), clip(s + 1)] {
            rows[y].get_or_insert_with(|| {
                let line = &source[y * sw as usize * 3..][..sw as usize * 3];
                let mut row = Vec::with_capacity(row_len);
                for &(s, w0, w1) in &x_taps {
                    let s = s as usize;
                    let next = (s + 1).min(sw as usize - 1);
                    for c in 0..3 {
                        row.push(i32::from(line[s * 3 + c]) * w0 + i32::from(line[next * 3 + c]) * w1);
                    }
                }
                row
            });
        }
    }
    let mut out = Vec::with_capacity(row_len * height as usize);
    for &(s, b0, b1) in &y_taps {
        let (r0, r1) = (rows[clip(s)].as_deref().unwrap_or_default(), rows[clip(s + 1)].as_deref().unwrap_or_default());
        for (a, b) in r0.iter().zip(r1) {
            let v = ((b0 * (a >> 4)) >> 16) + ((b1 * (b >> 4)) >> 16) + 2;
            out.push((v >> 2).clamp(0, 255) as u8);
        }
    }
    RgbImage::from_raw(width, height, out).expect("buffer of the output's size")
}

/// Pillow's bicubic `a` (`bicubic_filter` in Resample.c).
const BICUBIC_A: f64 = -0.5;
/// The bicubic kernel's support in input pixels at scale 1.
const BICUBIC_SUPPORT: f64 = 2.0;

fn bicubic(x: f64) -> f64 {
    let x = x.abs();
    if x < 1.0 {
        ((BICUBIC_A + 2.0) * x - (BICUBIC_A + 3.0)) * x * x + 1.0
    } else if x < 2.0 {
        (((x - 5.0) * x + 8.0) * x - 4.0) * BICUBIC_A
    } else {
        0.0
    }
}

/// Per output index: the first input index and the normalised weights (Pillow's
/// `precompute_coeffs` for a full-image box).
fn coefficients(in_size: usize, out_size: usize) -> Vec<(usize, Vec<f64>)> {
    let scale = in_size as f64 / out_size as f64;
    let filter_scale = scale.max(1.0);
    let support = BICUBIC_SUPPORT * filter_scale;
    // Pillow multiplies by the reciprocal; dividing would round differently in the last bit.
    let inverse = 1.0 / filter_scale;
    (0..out_size)
        .map(|o| {
            let center = (o as f64 + 0.5) * scale;
            // Pillow rounds with a C cast (truncation toward zero) of value + 0.5, then clamps.
            let min = ((center - support + 0.5).trunc() as i64).max(0) as usize;
            let max = ((center + support + 0.5).trunc() as i64).min(in_size as i64) as usize;
            let mut weights: Vec<f64> = (min..max).map(|i| bicubic((i as f64 - center + 0.5) * inverse)).collect();
            let sum: f64 = weights.iter().sum();
            if sum != 0.0 {
                weights.iter_mut().for_each(|w| *w /= sum);
            }
            (min, weights)
        })
        .collect()
}

/// Resizes a `width × height` row-major f32 channel to `out_width × out_height`. A pass whose
/// size does not change is skipped, as Pillow skips it.
pub fn resize_bicubic(values: &[f32], width: usize, height: usize, out_width: usize, out_height: usize) -> Vec<f32> {
    let horizontal = if out_width != width {
        let coeffs = coefficients(width, out_width);
        let mut out = vec![0f32; out_width * height];
        for y in 0..height {
            let row = &values[y * width..(y + 1) * width];
            for (x, (min, weights)) in coeffs.iter().enumerate() {
                let sum: f64 = weights.iter().zip(&row[*min..]).map(|(w, &v)| w * f64::from(v)).sum();
                out[y * out_width + x] = sum as f32;
            }
        }
        out
    } else {
        values.to_vec()
    };
    if out_height == height {
        return horizontal;
    }
    let coeffs = coefficients(height, out_height);
    let mut out = vec![0f32; out_width * out_height];
    for (y, (min, weights)) in coeffs.iter().enumerate() {
        for x in 0..out_width {
            let sum: f64 =
                weights.iter().enumerate().map(|(k, w)| w * f64::from(horizontal[(min + k) * out_width + x])).sum();
            out[y * out_width + x] = sum as f32;
        }
    }
    out
}

/// clean-fid's per-channel float resize of an RGB u8 frame: `[3, out_height, out_width]`
/// planar values in [0, 255] (clipped, as clean-fid clips after Pillow).
pub fn resize_rgb_clean(frame: &image::RgbImage, out_width: usize, out_height: usize) -> Vec<f32> {
    let (w, h) = (frame.width() as usize, frame.height() as usize);
    let raw = frame.as_raw();
    let mut out = Vec::with_capacity(3 * out_width * out_height);
    for c in 0..3 {
        let channel: Vec<f32> = (0..w * h).map(|p| f32::from(raw[p * 3 + c])).collect();
        out.extend(resize_bicubic(&channel, w, h, out_width, out_height).into_iter().map(|v| v.clamp(0.0, 255.0)));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn opencv_linear_keeps_constants_and_halves_as_block_means() {
        let flat = RgbImage::from_pixel(13, 9, image::Rgb([3, 128, 254]));
        for (w, h) in [(26, 18), (7, 5), (13, 20), (1, 1)] {
            let out = resize_linear_opencv(&flat, w, h);
            assert_eq!(out.dimensions(), (w, h));
            assert!(out.pixels().all(|p| p.0 == [3, 128, 254]), "{w}x{h}");
        }
        let ramp =
            RgbImage::from_fn(8, 6, |x, y| image::Rgb([(x * 31 + y * 7) as u8, (x * y * 9) as u8, (250 - x) as u8]));
        let half = resize_linear_opencv(&ramp, 4, 3);
        for (x, y, p) in half.enumerate_pixels() {
            for c in 0..3 {
                let sum: u32 = [(0, 0), (1, 0), (0, 1), (1, 1)]
                    .iter()
                    .map(|&(dx, dy)| u32::from(ramp.get_pixel(2 * x + dx, 2 * y + dy).0[c]))
                    .sum();
                assert_eq!(u32::from(p.0[c]), (sum + 2) >> 2, "({x}, {y}) channel {c}");
            }
        }
    }

    #[test]
    fn weights_sum_to_one_and_constant_images_stay_constant() {
        for (i, o) in [(64, 299), (299, 64), (576, 299), (7, 7)] {
            for (_, w) in coefficients(i, o) {
                assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
            }
        }
        let flat = vec![42.5f32; 40 * 30];
        assert!(resize_bicubic(&flat, 40, 30, 299, 299).iter().all(|&v| (v - 42.5).abs() < 1e-4));
    }
}

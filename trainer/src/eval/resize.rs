//! Pillow's `Image.resize(..., resample=BICUBIC)` on one float (`mode="F"`) channel, which is
//! clean-fid's "clean" resize to 299×299 (`cleanfid/resize.py`, `make_resizer("PIL", False,
//! "bicubic", ...)`): separable, horizontal pass first, the kernel widened by the scale when
//! shrinking (antialiasing), weights normalised per output pixel, sums in f64 and each pass
//! stored as f32 (Pillow's `libImaging/Resample.c`).

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

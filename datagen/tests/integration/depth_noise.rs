//! Depth noise on dynamic objects: off (or zero) leaves pairs byte-identical to the noise-free
//! path; on, masks and conditioning change only on and near dynamic objects, deterministically,
//! with the parametric model and with a measured second depth.

use datagen::io::sequence::{Sequence, read_sequence};
use datagen::pairs::depth_noise::DepthNoiseConfig;
use datagen::pairs::generator::{PairsConfig, TrajectoryRequest, generate_clips};
use datagen::synth::{SynthConfig, write_sequence};
use image::{GrayImage, RgbImage};
use schemas::ClipRecord;

/// Pixels farther than this from every dynamic-object pixel must not change. Offsets are at most
/// `max_sigmas` × 5 % of depth along the novel ray (default model), which the sampled orbits
/// (≤ 30°) turn into a few pixels of image motion at this size.
const NEAR_PX: i64 = 10;

fn sequence(dir: &std::path::Path) -> Sequence {
    let config = SynthConfig { width: 96, height: 72, frames: 3, ..SynthConfig::default() };
    write_sequence(&config, &dir.join("synth"), |_| {}).unwrap();
    read_sequence(&dir.join("synth")).unwrap()
}

fn clips(sequence: &Sequence, noise: DepthNoiseConfig) -> Vec<ClipRecord> {
    let config = PairsConfig { depth_noise: noise, ..PairsConfig::default() };
    let request = TrajectoryRequest { sampled: 2, explicit: Vec::new() };
    generate_clips(sequence, "synth", &config, &request, 5).unwrap()
}

fn gray(png: &[u8]) -> GrayImage {
    image::load_from_memory(png).unwrap().to_luma8()
}

fn rgb(png: &[u8]) -> RgbImage {
    image::load_from_memory(png).unwrap().to_rgb8()
}

/// Dynamic-object pixels dilated by `NEAR_PX` (square neighbourhood).
fn near_dynamic(mask: &GrayImage) -> Vec<bool> {
    let (w, h) = (mask.width() as i64, mask.height() as i64);
    (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            (-NEAR_PX..=NEAR_PX).any(|dy| {
                (-NEAR_PX..=NEAR_PX).any(|dx| {
                    let (u, v) = (x + dx, y + dy);
                    u >= 0 && v >= 0 && u < w && v < h && mask.get_pixel(u as u32, v as u32).0[0] != 0
                })
            })
        })
        .collect()
}

/// Pixels changed by noise (mask or conditioning colour), and how many of them lie away from
/// every dynamic object.
fn changes(base: &ClipRecord, noisy: &ClipRecord) -> (usize, usize, f64) {
    let (mut changed, mut far, mut near_fraction) = (0, 0, 0.0f64);
    for (t_base, t_noisy) in base.trajectories.iter().zip(&noisy.trajectories) {
        for frame in 0..base.num_frames() {
            let dynamic = gray(&base.dynamic_mask.as_ref().unwrap()[frame]);
            let near = near_dynamic(&dynamic);
            near_fraction = near_fraction.max(near.iter().filter(|&&n| n).count() as f64 / near.len() as f64);
            let target = rgb(&base.frames[frame]);
            let (mask_a, mask_b) = (gray(&t_base.covisible_mask[frame]), gray(&t_noisy.covisible_mask[frame]));
            let cond_b = t_noisy.condition.as_ref().map(|c| rgb(&c[frame]));
            for (i, near) in near.iter().enumerate() {
                let (x, y) = (i as u32 % target.width(), i as u32 / target.width());
                let kept_a = mask_a.get_pixel(x, y).0[0] > 127;
                let kept_b = mask_b.get_pixel(x, y).0[0] > 127;
                let colour_a = if kept_a { target.get_pixel(x, y).0 } else { [0; 3] };
                let colour_b = match &cond_b {
                    Some(c) => c.get_pixel(x, y).0,
                    None if kept_b => target.get_pixel(x, y).0,
                    None => [0; 3],
                };
                if kept_a != kept_b || colour_a != colour_b {
                    changed += 1;
                    far += usize::from(!near);
                }
            }
        }
    }
    (changed, far, near_fraction)
}

#[test]
fn noise_off_or_zero_is_byte_identical_to_the_noise_free_path() {
    let dir = tempfile::tempdir().unwrap();
    let sequence = sequence(dir.path());
    let base = clips(&sequence, DepthNoiseConfig::default());
    // Disabled, whatever the model's parameters.
    let off = DepthNoiseConfig { enabled: false, relative_sigma: 0.5, edge_relative_sigma: 0.5, ..Default::default() };
    assert_eq!(clips(&sequence, off), base);
    // Enabled with zero noise: the render-back path runs and must reproduce the masks and
    // frames × mask exactly (no stored conditioning).
    let zero = DepthNoiseConfig { enabled: true, relative_sigma: 0.0, edge_relative_sigma: 0.0, ..Default::default() };
    assert_eq!(clips(&sequence, zero), base);
    // A measured second depth equal to the reconstruction: zero offsets as well.
    let mut same = sequence.clone();
    same.second_depth = Some(sequence.depth.clone());
    assert_eq!(clips(&same, DepthNoiseConfig { enabled: true, ..Default::default() }), base);
}

#[test]
fn noise_changes_masks_and_conditioning_only_near_dynamic_objects() {
    let dir = tempfile::tempdir().unwrap();
    let sequence = sequence(dir.path());
    let base = clips(&sequence, DepthNoiseConfig::default());
    let on = DepthNoiseConfig { enabled: true, ..Default::default() };
    let noisy = clips(&sequence, on.clone());
    assert_eq!(noisy, clips(&sequence, on), "deterministic per seed");
    let (changed, far, near_fraction) = changes(&base[0], &noisy[0]);
    println!(
        "parametric noise: {changed} pixels changed, {far} of them farther than {NEAR_PX} px from dynamic objects"
    );
    assert!(changed > 20, "noise must visibly change the conditioning ({changed} pixels)");
    assert!(noisy[0].trajectories.iter().any(|t| t.condition.is_some()), "changed conditioning is stored");
    assert_eq!(far, 0);
    assert!(near_fraction < 0.7, "the check must leave room for far changes ({near_fraction:.2} of the image is near)");

    // Measured: a second depth 5 % deeper everywhere (moved only on dynamic objects).
    let mut measured = sequence.clone();
    measured.second_depth = Some(
        sequence
            .depth
            .iter()
            .map(|d| foundation::depth::DepthMap { values: d.values.iter().map(|v| v * 1.05).collect(), ..d.clone() })
            .collect(),
    );
    let noisy = clips(&measured, DepthNoiseConfig { enabled: true, ..Default::default() });
    let (changed, far, _) = changes(&base[0], &noisy[0]);
    println!("measured depth error: {changed} pixels changed, {far} far from dynamic objects");
    assert!(changed > 20 && far == 0);
}

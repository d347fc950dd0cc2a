//! `datagen synth` end to end: the written sequence folder, its video round trip, and bad input.

use std::path::Path;
use std::process::Command;

fn datagen() -> Command {
    Command::new(env!("CARGO_BIN_EXE_datagen"))
}

/// PSNR in dB of the BT.601 luma, and of all RGB channels.
fn psnr(a: &image::RgbImage, b: &image::RgbImage) -> (f64, f64) {
    let db = |mse: f64| 10.0 * (255.0f64.powi(2) / mse.max(1e-12)).log10();
    let luma = |p: &image::Rgb<u8>| 0.299 * p.0[0] as f64 + 0.587 * p.0[1] as f64 + 0.114 * p.0[2] as f64;
    let n = a.pixels().len() as f64;
    let luma_mse = a.pixels().zip(b.pixels()).map(|(x, y)| (luma(x) - luma(y)).powi(2)).sum::<f64>() / n;
    let rgb_mse =
        a.as_raw().iter().zip(b.as_raw()).map(|(&x, &y)| (x as f64 - y as f64).powi(2)).sum::<f64>() / (3.0 * n);
    (db(luma_mse), db(rgb_mse))
}

#[test]
fn synth_writes_a_complete_cog_nvs_sequence() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("scene");
    let status = datagen()
        .args(["synth", "--width", "96", "--height", "64", "--frames", "6", "--seed", "3", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(status.status.success(), "{}", String::from_utf8_lossy(&status.stderr));
    let stdout = String::from_utf8_lossy(&status.stdout);
    assert!(stdout.contains("contact_sheet.png"), "tells the user what to look at: {stdout}");

    let depth = datagen::io::npy::read_npy_f32(&out.join("cam_info/megasam_depth.npy")).unwrap();
    assert_eq!(depth.shape, vec![6, 64, 96]);
    let k = datagen::io::npy::read_npy_f32(&out.join("cam_info/megasam_intrinsics.npy")).unwrap();
    assert_eq!(k.shape, vec![3, 3]);
    assert_eq!(k.data[2], 96.0 / 2.0 - 0.5, "principal point at the pixel-centre convention");
    let poses = datagen::io::npy::read_npy_f32(&out.join("cam_info/megasam_c2ws.npy")).unwrap();
    assert_eq!(poses.shape, vec![6, 4, 4]);
    assert_eq!(&poses.data[12..16], &[0.0, 0.0, 0.0, 1.0]);
    for frame in 0..6 {
        assert!(out.join(format!("masks/{frame:05}.png")).is_file());
    }
    let sheet = image::open(out.join("contact_sheet.png")).unwrap();
    assert!(sheet.width() > 96 * 3);

    // The H.264 video decodes back to the lossless frames, closely.
    let video = foundation::video::decode_video(&out.join("gt_rgb.mp4")).unwrap();
    assert_eq!(video.frames.len(), 6);
    assert!((video.fps - 24.0).abs() < 1e-6, "fps {}", video.fps);
    for (i, decoded) in video.frames.iter().enumerate() {
        let lossless = image::open(out.join(format!("frames/{i:05}.png"))).unwrap().to_rgb8();
        assert_eq!(decoded.dimensions(), lossless.dimensions());
        // 4:2:0 chroma halves colour resolution, so the RGB bar is lower than the luma bar.
        let (luma, rgb) = psnr(decoded, &lossless);
        assert!(luma > 35.0 && rgb > 18.0, "frame {i}: PSNR luma {luma:.1} dB, RGB {rgb:.1} dB");
    }
}

#[test]
fn synth_is_deterministic() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["a", "b"] {
        let status = datagen()
            .args(["synth", "--width", "32", "--height", "24", "--frames", "3", "--seed", "11", "--out"])
            .arg(dir.path().join(name))
            .status()
            .unwrap();
        assert!(status.success());
    }
    for file in ["cam_info/megasam_depth.npy", "cam_info/megasam_c2ws.npy", "masks_ids.npy", "frames/00002.png"] {
        let read = |name: &str| std::fs::read(dir.path().join(name).join(file)).unwrap();
        assert_eq!(read("a"), read("b"), "{file}");
    }
}

fn fails_naming(args: &[&str], name: &str, out: &Path) {
    let output = datagen().args(args).arg("--out").arg(out).output().unwrap();
    assert!(!output.status.success(), "{args:?} must fail");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(stderr.trim().lines().count(), 1, "one line: {stderr}");
    assert!(stderr.contains(name), "{args:?}: message must name `{name}`: {stderr}");
}

#[test]
fn impossible_parameters_fail_with_one_line_naming_them() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("never");
    fails_naming(&["synth", "--frames", "0"], "frames", &out);
    fails_naming(&["synth", "--width", "0"], "width", &out);
    fails_naming(&["synth", "--height", "0"], "height", &out);
    fails_naming(&["synth", "--width", "33"], "width", &out);
    fails_naming(&["synth", "--seed", "abc"], "--seed", &out);
    assert!(!out.exists(), "nothing written for bad input");
}

//! `trainer eval` over folders of videos built from synthetic scenes: the Markdown/JSON table,
//! protocol resizing, best-of-K selection, and one named error per kind of bad input.

use std::path::{Path, PathBuf};
use std::process::Output;

use datagen::synth::{SynthConfig, SynthScene};
use image::RgbImage;

use super::eval_parity::goldens;

const W: u32 = 64;
const H: u32 = 48;
const FRAMES: u32 = 4;

fn write_frames(dir: &Path, frames: &[RgbImage]) {
    std::fs::create_dir_all(dir).unwrap();
    for (i, f) in frames.iter().enumerate() {
        f.save(dir.join(format!("{i:05}.png"))).unwrap();
    }
}

/// The frame with every channel value moved by a deterministic pattern of amplitude `amp`.
fn distort(frame: &RgbImage, amp: i32, phase: u32) -> RgbImage {
    RgbImage::from_fn(frame.width(), frame.height(), |x, y| {
        let p = frame.get_pixel(x, y).0;
        let d = ((x * 7 + y * 13 + phase * 5) % 11) as i32 - 5;
        image::Rgb(p.map(|v| (i32::from(v) + d * amp / 5).clamp(0, 255) as u8))
    })
}

/// TARGET/{a,b}/, PRED/{a,b}/{s0,s1}/ (s1 the closer sample for `a`, s0 for `b`) and
/// MASK/{a,b}/ (co-visible = the static background of the synthetic scene).
fn benchmark(root: &Path) {
    for (v, name) in ["a", "b"].iter().enumerate() {
        let config = SynthConfig { width: W, height: H, frames: FRAMES, seed: 40 + v as u64, ..Default::default() };
        let scene = SynthScene::new(&config).unwrap();
        let rendered: Vec<_> = (0..FRAMES).map(|f| scene.render_frame(f)).collect();
        let target: Vec<RgbImage> = rendered.iter().map(|r| r.rgb.clone()).collect();
        write_frames(&root.join("target").join(name), &target);
        let (near, far) = if v == 0 { ("s1", "s0") } else { ("s0", "s1") };
        write_frames(
            &root.join("pred").join(name).join(near),
            &target.iter().map(|f| distort(f, 6, 0)).collect::<Vec<_>>(),
        );
        write_frames(
            &root.join("pred").join(name).join(far),
            &target.iter().map(|f| distort(f, 40, 1)).collect::<Vec<_>>(),
        );
        let mask_dir = root.join("mask").join(name);
        std::fs::create_dir_all(&mask_dir).unwrap();
        for (i, r) in rendered.iter().enumerate() {
            let mask = image::GrayImage::from_fn(W, H, |x, y| {
                image::Luma([if r.mask_ids.get_pixel(x, y).0[0] == 0 { 255 } else { 0 }])
            });
            mask.save(mask_dir.join(format!("{i:05}.png"))).unwrap();
        }
    }
}

fn eval(root: &Path, extra: &[&str]) -> Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_trainer"))
        .arg("eval")
        .arg("--pred")
        .arg(root.join("pred"))
        .arg("--target")
        .arg(root.join("target"))
        .args(extra)
        .output()
        .unwrap()
}

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).to_string()
}

fn path(p: PathBuf) -> String {
    p.display().to_string()
}

/// The whole table with every metric: the chosen sample is the closer one, and its per-video
/// PSNR/SSIM/mPSNR/mSSIM equal the single-pair evaluation of that sample (whose values the
/// scikit-image test checks); FID/KID are present and the Markdown has every column.
#[test]
fn eval_benchmark_table_on_synthetic_scenes() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    benchmark(root);
    let json = root.join("report.json");
    let output = eval(
        root,
        &[
            "--mask",
            &path(root.join("mask")),
            "--top-k",
            "2",
            "--lpips-weights",
            &path(goldens().join("lpips_alex.safetensors")),
            "--inception-weights",
            &path(goldens().join("inception.safetensors")),
            "--kid-subset-size",
            "8",
            "--kid-subsets",
            "10",
            "--out",
            &path(json.clone()),
        ],
    );
    assert!(output.status.success(), "{}", stderr(&output));
    let stdout = String::from_utf8_lossy(&output.stdout);
    for header in ["PSNR ↑", "SSIM ↑", "LPIPS ↓", "mPSNR ↑", "mSSIM ↑", "mLPIPS ↓", "FID ↓", "KID ↓", "| **mean** |"]
    {
        assert!(stdout.contains(header), "missing {header}: {stdout}");
    }
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    for (v, (name, chosen)) in [("a", 1), ("b", 0)].iter().enumerate() {
        let row = &report["videos"][v];
        assert_eq!(row["name"], *name);
        assert_eq!(row["sample"], *chosen);
        let single = trainer::eval::metrics::evaluate(
            &root.join("pred").join(name).join(format!("s{chosen}")),
            &root.join("target").join(name),
            Some(&root.join("mask").join(name)),
        )
        .unwrap();
        for (key, want) in [("psnr", single.psnr), ("ssim", single.ssim), ("masked_psnr", single.masked_psnr.unwrap())]
        {
            assert!((row[key].as_f64().unwrap() - want).abs() < 1e-12, "{name} {key}");
        }
        assert!(row["lpips"].as_f64().unwrap() > 0.0 && row["masked_lpips"].as_f64().unwrap() > 0.0);
    }
    let mean_psnr =
        (report["videos"][0]["psnr"].as_f64().unwrap() + report["videos"][1]["psnr"].as_f64().unwrap()) / 2.0;
    assert!((report["mean"]["psnr"].as_f64().unwrap() - mean_psnr).abs() < 1e-12);
    assert!(report["fid"].as_f64().unwrap() > 0.0 && report["kid"].is_number());
}

/// `--protocol gcd` resizes predictions, targets and masks to 384×576 before scoring.
#[test]
fn eval_benchmark_protocol_resizes() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    benchmark(root);
    let output = eval(root, &["--top-k", "2", "--protocol", "gcd", "--mask", &path(root.join("mask"))]);
    assert!(output.status.success(), "{}", stderr(&output));
    let stdout = String::from_utf8_lossy(&output.stdout);
    let json: serde_json::Value = serde_json::from_str(&stdout[stdout.find("\n{").unwrap()..]).unwrap();
    assert_eq!(json["protocol"], "gcd");
    assert_eq!(json["mean"]["frames"], 2 * FRAMES);
    assert!(json["videos"][0]["masked_psnr"].is_number() && json["fid"].is_null());
}

/// Bad input, one message each: folders that do not match, different lengths, different sizes
/// without a protocol, a metric without its weights (fewer frames than KID's 1000 are fine).
#[test]
fn eval_benchmark_bad_inputs_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    benchmark(root);
    // Keep one sample per video (no --top-k): PRED/NAME is then a frame folder.
    for name in ["a", "b"] {
        let video = root.join("pred").join(name);
        std::fs::remove_dir_all(video.join("s1")).unwrap();
        for f in std::fs::read_dir(video.join("s0")).unwrap() {
            let f = f.unwrap().path();
            std::fs::rename(&f, video.join(f.file_name().unwrap())).unwrap();
        }
        std::fs::remove_dir(video.join("s0")).unwrap();
    }
    let ok = eval(root, &[]);
    assert!(ok.status.success(), "{}", stderr(&ok));

    // Fewer frames than KID's 1000: subsets of all 8 frames, as clean-fid's min(n, 1000).
    let kid = eval(root, &["--inception-weights", &path(goldens().join("inception.safetensors"))]);
    assert!(kid.status.success(), "{}", stderr(&kid));
    let stdout = String::from_utf8_lossy(&kid.stdout);
    let json: serde_json::Value = serde_json::from_str(&stdout[stdout.find("\n{").unwrap()..]).unwrap();
    assert!(json["kid"].is_number() && json["kid_subset_size"] == 2 * FRAMES, "{json}");

    let lpips = eval(root, &["--metrics", "lpips"]);
    let msg = stderr(&lpips);
    assert!(!lpips.status.success() && msg.contains("--lpips-weights") && msg.contains("alex.pth"), "{msg}");

    std::fs::remove_file(root.join("pred/b/00003.png")).unwrap();
    let short = eval(root, &[]);
    let msg = stderr(&short);
    assert!(!short.status.success() && msg.contains("pred/b") && msg.contains("3 frames, but target"), "{msg}");

    let small = distort(&RgbImage::new(W / 2, H / 2), 0, 0);
    for i in 0..FRAMES {
        small.save(root.join(format!("pred/b/{i:05}.png"))).unwrap();
    }
    let size = eval(root, &[]);
    let msg = stderr(&size);
    assert!(
        !size.status.success()
            && msg.contains("32x24, but target")
            && msg.contains("64x48")
            && msg.contains("--protocol"),
        "{msg}"
    );

    std::fs::remove_dir_all(root.join("pred/b")).unwrap();
    let missing = eval(root, &[]);
    let msg = stderr(&missing);
    assert!(!missing.status.success() && msg.contains("missing predictions [\"b\"]"), "{msg}");
}

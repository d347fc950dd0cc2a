//! `trainer sample` against the public CogNVS sampling procedure (`scripts/goldens_sampling.py`:
//! diffusers' models, scheduler and generator, step by step) on tiny random models: the same seed
//! gives the same video, across model structures, sizes, frame counts, step counts, guidance and
//! VAE tiling.

use std::path::{Path, PathBuf};
use std::process::Command;

use super::parity::{assert_success, run_python};

/// The cases `goldens_sampling.py` writes.
const CASES: [&str; 4] = ["cognvs", "same_prompt", "rotary_only", "long"];

/// Share of values that may differ by more than one grey level, and the largest mean difference.
const MAX_SHARE_BEYOND_ONE_LEVEL: f64 = 0.001;
const MAX_MEAN_LEVELS: f64 = 0.05;

fn png_frames(dir: &Path) -> Vec<image::RgbImage> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "png"))
        .collect();
    paths.sort();
    foundation::frames::read_frames(&paths).unwrap()
}

/// Per-value differences of two videos: (mean, share beyond one level, largest).
fn differences(ours: &[image::RgbImage], theirs: &[image::RgbImage]) -> (f64, f64, u8) {
    assert_eq!(ours.len(), theirs.len(), "frame count");
    let (mut sum, mut beyond, mut max, mut count) = (0u64, 0u64, 0u8, 0u64);
    for (a, b) in ours.iter().zip(theirs) {
        assert_eq!(a.dimensions(), b.dimensions(), "frame size");
        for (x, y) in a.as_raw().iter().zip(b.as_raw()) {
            let d = x.abs_diff(*y);
            sum += u64::from(d);
            beyond += u64::from(d > 1);
            max = max.max(d);
            count += 1;
        }
    }
    (sum as f64 / count as f64, beyond as f64 / count as f64, max)
}

#[test]
fn sample_equals_the_public_pipeline_for_the_same_seed() {
    let dir = tempfile::tempdir().unwrap();
    run_python("goldens_sampling.py", &[dir.path().as_os_str()]);
    for case in CASES {
        let folder = dir.path().join(case);
        let meta: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(folder.join("case.json")).unwrap()).unwrap();
        let expected = png_frames(&folder.join("expected"));
        let cond = png_frames(&folder.join("cond"));
        let (width, height) = cond[0].dimensions();
        let out = dir.path().join(format!("{case}_ours"));
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_trainer"));
        cmd.arg("sample")
            .arg("--ckpt")
            .arg(folder.join("transformer"))
            .arg("--base-model")
            .arg(&folder)
            .arg("--text-embedding")
            .arg(folder.join("text.safetensors"))
            .arg("--cond")
            .arg(folder.join("cond"))
            .arg("--out")
            .arg(&out)
            .args(["--steps", &meta["steps"].to_string(), "--seed", &meta["seed"].to_string()])
            .args(["--guidance", &meta["guidance"].to_string(), "--dtype", "fp32"])
            .args(["--frames", &cond.len().to_string(), "--size", &format!("{width}x{height}")]);
        if meta["negative"] == true {
            cmd.arg("--negative-text-embedding").arg(folder.join("negative.safetensors"));
        }
        if meta["tiling"] == false {
            cmd.arg("--no-vae-tiling");
        }
        assert_success(&cmd.output().unwrap());
        let (mean, beyond, max) = differences(&png_frames(&out), &expected);
        println!(
            "sampling parity {case}: {} frames {width}x{height}, {} steps: mean {mean:.5} levels, \
             {:.4} % beyond one level, max {max}",
            expected.len(),
            meta["steps"],
            100.0 * beyond
        );
        assert!(
            mean <= MAX_MEAN_LEVELS && beyond <= MAX_SHARE_BEYOND_ONE_LEVEL,
            "{case}: mean {mean} levels, {beyond} beyond one level, max {max}"
        );
        if case == "same_prompt" {
            // The comparison can fail: another seed is far from the reference.
            let other = dir.path().join("other_seed");
            let seed = (meta["seed"].as_u64().unwrap() + 1).to_string();
            let args: Vec<std::ffi::OsString> = cmd.get_args().map(|a| a.to_os_string()).collect();
            let position = |flag: &str| args.iter().position(|a| a == flag).unwrap() + 1;
            let mut changed = args.clone();
            changed[position("--seed")] = seed.into();
            changed[position("--out")] = other.clone().into();
            assert_success(&Command::new(env!("CARGO_BIN_EXE_trainer")).args(&changed).output().unwrap());
            let (mean, _, _) = differences(&png_frames(&other), &expected);
            assert!(mean > 10.0, "another seed: mean difference {mean} levels only");
        }
    }
}

#[test]
fn area_and_linear_resizes_match_opencv() {
    let dir = tempfile::tempdir().unwrap();
    run_python("goldens_resize.py", &[dir.path().as_os_str()]);
    let cases: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("cases.json")).unwrap()).unwrap();
    let read = |name: &str| image::open(dir.path().join(name)).unwrap().to_rgb8();
    for case in &cases {
        let source = read(case["source"].as_str().unwrap());
        let (w, h) = (case["width"].as_u64().unwrap() as u32, case["height"].as_u64().unwrap() as u32);
        let ours = match case["mode"].as_str().unwrap() {
            "area" => trainer::pipelines::video_processor::resize_area(&source, w, h),
            _ => trainer::pipelines::video_processor::resize_linear(&source, w, h),
        };
        let (mean, beyond, max) = differences(&[ours], &[read(case["file"].as_str().unwrap())]);
        println!(
            "resize {} {}x{} -> {w}x{h}: mean {mean:.4}, max {max}",
            case["mode"],
            source.width(),
            source.height()
        );
        // The linear resize (what the official evaluation brings frames to the protocol's size
        // with) is OpenCV's bit for bit; the area shrink within one level.
        let exact = case["mode"] == "linear";
        assert!(
            if exact { max == 0 } else { max <= 1 && beyond == 0.0 && mean < 0.05 },
            "{case}: mean {mean}, max {max}"
        );
    }
}

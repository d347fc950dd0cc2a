//! `trainer eval` against scikit-image: PSNR, SSIM and their masked variants on frames generated
//! by `scripts/goldens_metrics.py`, and named errors for mismatched inputs.

use std::path::Path;
use std::sync::OnceLock;

use super::parity::run_script;

/// Output of `scripts/goldens_metrics.py`, generated once per test binary (read only: a test
/// that changes the frames works on its own copy).
fn goldens() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| run_script("goldens_metrics.py")).path()
}

fn eval(args: &[&std::path::Path]) -> std::process::Output {
    let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_trainer"));
    cmd.arg("eval");
    for (flag, path) in ["--pred", "--target", "--mask"].iter().zip(args) {
        cmd.arg(flag).arg(path);
    }
    cmd.output().expect("run trainer eval")
}

#[test]
fn eval_matches_scikit_image() {
    let root = goldens();
    let output = eval(&[&root.join("pred"), &root.join("target"), &root.join("mask")]);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let ours: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let expected: Vec<serde_json::Value> =
        serde_json::from_str(&std::fs::read_to_string(root.join("expected.json")).unwrap()).unwrap();
    assert_eq!(ours["frames"], 3);
    let mut worst = 0.0f64;
    for (frame, want) in expected.iter().enumerate() {
        for key in ["psnr", "ssim", "masked_psnr", "masked_ssim"] {
            let (a, b) = (ours["per_frame"][frame][key].as_f64().unwrap(), want[key].as_f64().unwrap());
            worst = worst.max((a - b).abs());
            assert!((a - b).abs() < 1e-9, "frame {frame} {key}: ours {a}, scikit-image {b}");
        }
    }
    println!("eval vs scikit-image: max abs difference {worst:.2e}");
    let mean_psnr = expected.iter().map(|e| e["psnr"].as_f64().unwrap()).sum::<f64>() / 3.0;
    assert!((ours["psnr"].as_f64().unwrap() - mean_psnr).abs() < 1e-9);
}

#[test]
fn mismatched_inputs_are_named_errors() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    for folder in ["pred", "target", "mask"] {
        std::fs::create_dir_all(root.join(folder)).unwrap();
        for entry in std::fs::read_dir(goldens().join(folder)).unwrap() {
            let entry = entry.unwrap();
            std::fs::copy(entry.path(), root.join(folder).join(entry.file_name())).unwrap();
        }
    }
    std::fs::remove_file(root.join("pred/00002.png")).unwrap();
    let output = eval(&[&root.join("pred"), &root.join("target")]);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        !output.status.success() && stderr.contains("pred") && stderr.contains("2 frames, target has 3"),
        "{stderr}"
    );
    std::fs::remove_file(root.join("mask/00000.png")).unwrap();
    let output = eval(&[&root.join("target"), &root.join("target"), &root.join("mask")]);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success() && stderr.contains("2 masks for 3 frames"), "{stderr}");
}

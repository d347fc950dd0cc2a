//! LPIPS, Inception features, FID and KID against the `lpips` and `clean-fid` packages on
//! identical random-backbone weights (goldens: `scripts/goldens_eval.py`).

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use trainer::eval::inception::FidInception;
use trainer::eval::lpips::{Lpips, LpipsNet, frames_to_input};
use trainer::tch::{Device, Kind, Tensor};

use super::parity::{assert_close, read_tensors, run_python};

/// Per-image LPIPS tolerance.
const LPIPS_TOL: f64 = 1e-5;
/// Inception feature tolerance, relative to the largest feature.
const FEATURE_TOL: f64 = 1e-4;
/// FID / KID relative tolerance.
const SET_TOL: f64 = 1e-3;

/// The goldens, generated once per test run into the target's temporary folder.
pub fn goldens() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("eval_goldens");
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        run_python("goldens_eval.py", &[dir.as_os_str()]);
        dir
    })
}

fn expected() -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(goldens().join("expected.json")).unwrap()).unwrap()
}

fn frames(dir: &str) -> Vec<image::RgbImage> {
    trainer::eval::metrics::read_frames(&goldens().join(dir)).unwrap()
}

/// Goldens: `lpips.LPIPS(pnet_rand=True, net=alex|vgg, version="0.1")` with the wheel's v0.1
/// heads, on the script's frame pairs; masked values are the mean of the `spatial=True` map
/// over co-visible pixels (DyCheck's mLPIPS).
#[test]
fn eval_lpips_matches_lpips_package() {
    let _guard = trainer::tch::no_grad_guard();
    let (pred, target) = (frames("pred"), frames("target"));
    let masks = trainer::eval::metrics::read_masks(&goldens().join("mask")).unwrap();
    let want = expected();
    for (net, key) in [(LpipsNet::Alex, "alex"), (LpipsNet::Vgg, "vgg")] {
        let model = Lpips::load(&goldens().join(format!("lpips_{key}.safetensors")), net, Device::Cpu).unwrap();
        let (mut worst, mut worst_masked) = (0.0f64, 0.0f64);
        for (i, (p, t)) in pred.iter().zip(&target).enumerate() {
            let (x0, x1) = (frames_to_input(&[p], Device::Cpu), frames_to_input(&[t], Device::Cpu));
            let ours = model.distance(&x0, &x1).unwrap().double_value(&[0]);
            let theirs = want[format!("lpips_{key}")][i].as_f64().unwrap();
            worst = worst.max((ours - theirs).abs());
            let keep: Vec<f32> = masks[i].as_raw().iter().map(|&v| f32::from(u8::from(v != 0))).collect();
            let keep = Tensor::from_slice(&keep).view([i64::from(masks[i].height()), i64::from(masks[i].width())]);
            let map = model.spatial(&x0, &x1).unwrap().get(0);
            let masked = (map * &keep).sum(Kind::Double).double_value(&[]) / keep.sum(Kind::Double).double_value(&[]);
            let theirs_masked = want[format!("masked_lpips_{key}")][i].as_f64().unwrap();
            worst_masked = worst_masked.max((masked - theirs_masked).abs());
        }
        println!("parity lpips {key}: max abs {worst:.3e}, masked {worst_masked:.3e}");
        assert!(worst <= LPIPS_TOL && worst_masked <= LPIPS_TOL, "lpips {key}: {worst:.3e}, masked {worst_masked:.3e}");
    }
}

/// Goldens: clean-fid's `get_folder_features` (mode "clean": PIL bicubic float resize to 299,
/// `(x − 128) / 128`) through `cleanfid.inception_pytorch`'s FID blocks with random weights.
#[test]
fn eval_inception_features_match_clean_fid() {
    let model = FidInception::load(&goldens().join("inception.safetensors"), Device::Cpu).unwrap();
    let want = read_tensors(&goldens().join("features.safetensors"));
    for set in ["pred", "target"] {
        let frames = frames(set);
        let ours = model.features(&frames.iter().collect::<Vec<_>>()).unwrap();
        assert_close(&format!("inception features {set}"), &ours, &want[set], FEATURE_TOL);
    }
}

/// Goldens: `cleanfid.fid.frechet_distance`'s value (the trace of its matrix square root taken
/// exactly, the script checking that against frechet_distance itself) and `kernel_distance` on
/// clean-fid's own features;
/// ours run end to end from the PNG folders through `trainer eval`. With 6 frames a set, KID's
/// subsets are the whole sets (clean-fid clamps its 1000 to 6), so `--kid-subset-size 6` is the
/// same estimator.
#[test]
fn eval_fid_kid_match_clean_fid() {
    let root = goldens();
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_trainer"))
        .args(["eval", "--kid-subset-size", "6", "--inception-weights"])
        .arg(root.join("inception.safetensors"))
        .arg("--pred")
        .arg(root.join("pred"))
        .arg("--target")
        .arg(root.join("target"))
        .arg("--out")
        .arg(root.join("report.json"))
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let ours: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(root.join("report.json")).unwrap()).unwrap();
    let want = expected();
    for key in ["fid", "kid"] {
        let (a, b) = (ours[key].as_f64().unwrap(), want[key].as_f64().unwrap());
        let rel = (a - b).abs() / b.abs();
        println!("parity {key}: ours {a:.6}, clean-fid {b:.6}, rel {rel:.3e}");
        assert!(rel <= SET_TOL, "{key}: ours {a}, clean-fid {b}, relative {rel:.3e}");
    }
}

/// A weight file with one tensor of the wrong shape fails naming the tensor and both shapes.
#[test]
fn eval_bad_weights_name_the_tensor() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("alex.safetensors");
    let mut tensors: Vec<(String, Tensor)> =
        read_tensors(&goldens().join("lpips_alex.safetensors")).into_iter().collect();
    for (name, t) in tensors.iter_mut() {
        if name == "features.3.weight" {
            *t = Tensor::zeros([192, 64, 3, 3], (Kind::Float, Device::Cpu));
        }
    }
    Tensor::write_safetensors(&tensors, &bad).unwrap();
    let err = Lpips::load(&bad, LpipsNet::Alex, Device::Cpu).unwrap_err().to_string();
    assert!(
        err.contains("features.3.weight") && err.contains("[192, 64, 5, 5]") && err.contains("[192, 64, 3, 3]"),
        "{err}"
    );
    tensors.retain(|(n, _)| n != "lin2.model.1.weight");
    Tensor::write_safetensors(&tensors, &bad).unwrap();
    let err = Lpips::load(&bad, LpipsNet::Vgg, Device::Cpu).unwrap_err().to_string();
    assert!(err.contains("features.0.weight") || err.contains("features.2.weight"), "{err}");
    let err = FidInception::load(&dir.path().join("none.safetensors"), Device::Cpu).unwrap_err().to_string();
    assert!(err.contains("none.safetensors") && err.contains("convert_eval_weights.py"), "{err}");
}

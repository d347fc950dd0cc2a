//! `trainer benchmark` end to end on a tiny model and tiny synthetic multi-camera scenes (generic,
//! DyCheck and Kubric-4D layouts, as `datagen synth --cameras N --format` writes them): the
//! table and its JSON with the paper's rows, the held-out camera's poses as the trajectory (the
//! source as its own target renders back exactly), DyCheck's own co-visibility masks in the
//! masked metrics, a reconstruction folder in other units, a broken scene reported while the
//! rest go on, resumption, refused settings and `--compare`.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use super::eval_parity::goldens;
use super::nvs::released_layout;
use super::parity::assert_success;

const W: u32 = 80;
const H: u32 = 64;
const FRAMES: u32 = 5;

/// A two-camera synthetic scene (the layout `datagen synth --cameras 2` writes).
fn scene(dir: &Path, seed: u64) {
    let config = datagen::synth::SynthConfig { width: W, height: H, frames: FRAMES, seed, ..Default::default() };
    let rig = datagen::synth::CameraRig { cameras: 2, spacing_deg: 10.0 };
    datagen::synth::write_multiview(&config, &rig, dir, |_| {}).unwrap();
}

/// The models, and ROOT with scenes `a`, `b` and `broken` (its second camera's cameras.json cut).
struct Fixture {
    _dir: tempfile::TempDir,
    root: PathBuf,
    transformer: PathBuf,
    base: PathBuf,
    /// A finetuning TOML for the tiny released layout.
    config: PathBuf,
    work: PathBuf,
}

fn fixture() -> Fixture {
    let dir = tempfile::tempdir().unwrap();
    let (transformer, base, config) = released_layout(dir.path());
    let root = dir.path().join("root");
    scene(&root.join("a"), 1);
    scene(&root.join("b"), 2);
    scene(&root.join("broken"), 3);
    let cameras = root.join("broken/cam01/cameras.json");
    let text = std::fs::read_to_string(&cameras).unwrap();
    std::fs::write(&cameras, &text[..text.len() / 2]).unwrap();
    let work = dir.path().to_path_buf();
    Fixture { _dir: dir, root, transformer, base, config, work }
}

fn benchmark(f: &Fixture, out: &Path, extra: &[&str]) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_trainer"));
    cmd.arg("benchmark").arg("--root").arg(&f.root).arg("--init").arg(&f.transformer);
    cmd.arg("--base-model").arg(&f.base).arg("--out").arg(out);
    cmd.args(["--steps", "0", "--sample-steps", "2", "--frames", &FRAMES.to_string(), "--eval-size", "80x64"]);
    cmd.args(extra);
    cmd.output().unwrap()
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).to_string()
}

/// PSNR of the source frames (the camera left where it was) against held-out camera `camera`'s
/// frames over the pixels the benchmark's render covers, from the run's work folder (every
/// window frame scored, both cameras of one K and size).
fn unmoved_psnr(out: &Path, scene: &str, camera: &str) -> f64 {
    let work = out.join("scenes").join(scene);
    let read = |path: PathBuf| image::open(path).unwrap();
    let (mut squared, mut count) = (0.0, 0usize);
    for i in 0..FRAMES {
        let name = format!("{i:05}.png");
        let source = read(work.join("window-00000/source/frames").join(&name)).to_rgb8();
        let target = read(work.join("target").join(camera).join(&name)).to_rgb8();
        let holes = read(work.join(format!("window-00000/nvs/renders/view-{camera}/holes")).join(&name)).to_luma8();
        for ((s, t), h) in source.pixels().zip(target.pixels()).zip(holes.pixels()) {
            if h.0[0] == 0 {
                count += 3;
                squared += (0..3).map(|c| ((f64::from(s.0[c]) - f64::from(t.0[c])) / 255.0).powi(2)).sum::<f64>();
            }
        }
    }
    -10.0 * (squared / count as f64).log10()
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let path = entry.unwrap().path();
        let target = to.join(path.file_name().unwrap());
        if path.is_dir() { copy_dir(&path, &target) } else { std::fs::copy(&path, &target).map(|_| ()).unwrap() }
    }
}

/// The whole command on three scenes: the table with the paper's rows, the broken scene failed
/// with its reason; the render at the held-out camera's poses matches that camera's frames far
/// better than the source frames do; after a scene's result is deleted only that scene runs again
/// and gives the same numbers; other settings are refused naming them.
#[test]
fn benchmark_table_trajectory_resume_and_failures() {
    let f = fixture();
    let out = f.work.join("run");
    let weights = |name: &str| goldens().join(name).display().to_string();
    let (lpips, inception) = (weights("lpips_alex.safetensors"), weights("inception.safetensors"));
    let args = ["--dataset", "kubric4d", "--lpips-weights", &lpips, "--inception-weights", &inception];
    let first = benchmark(&f, &out, &args);
    assert_success(&first);
    let log = stderr(&first);
    assert!(log.contains("scene broken: FAILED") && log.contains("cam01/cameras.json"), "{log}");

    let report = json(&out.join("report.json"));
    let scenes: Vec<&str> = report["scenes"].as_array().unwrap().iter().map(|s| s["scene"].as_str().unwrap()).collect();
    assert_eq!(scenes, ["a", "b"]);
    assert_eq!(report["failed"][0]["scene"], "broken");
    assert!(report["failed"][0]["reason"].as_str().unwrap().contains("cameras.json"));
    assert_eq!(report["protocol"], "gcd");
    assert_eq!(report["protocol_size"], false, "80x64 is not GCD's 576x384");
    assert_eq!(report["seed"], 42);
    assert_eq!(report["settings"]["steps"], 0);
    assert_eq!(report["settings"]["finetune_trajectories"], 9, "the paper's N for Kubric-4D");
    assert_eq!(report["checkpoint_digest"].as_str().unwrap().len(), 64);
    assert_eq!(report["paper"][0]["metrics"]["psnr"], 22.63);
    for key in ["psnr", "ssim", "lpips"] {
        assert!(report["mean"][key].is_number(), "{key}: {report}");
    }
    assert!(report["mean"]["masked_psnr"].is_null(), "the generic layout ships no co-visibility masks");
    assert!(report["fid"].is_number() && report["kid"].is_number());
    let table = std::fs::read_to_string(out.join("report.md")).unwrap();
    for needle in ["| a | 5 |", "| **mean** |", "| **ours** |", "22.63", "FID ↓", "kubric4d: 2/3 scenes", "broken:"] {
        assert!(table.contains(needle), "missing {needle}: {table}");
    }

    // The trajectory is the held-out camera's: on the pixels the render covers, the render (cam00's
    // video seen from cam01's poses) agrees with cam01's frames far better than cam00's own frames
    // do (what a trajectory that left the camera where it was would give).
    let a = json(&out.join("results/a.json"));
    assert_eq!(a["input_camera"], "cam00");
    assert_eq!(a["cameras"][0]["camera"], "cam01");
    assert_eq!(a["cameras"][0]["time_ids"], serde_json::json!([0, 1, 2, 3, 4]));
    let render_psnr = -10.0 * a["cameras"][0]["render_mse"].as_f64().unwrap().log10();
    let unmoved = unmoved_psnr(&out, "a", "cam01");
    eprintln!("render {render_psnr:.2} dB, source frames {unmoved:.2} dB on the covered pixels");
    assert!(render_psnr > unmoved + 3.0, "render {render_psnr:.2} dB vs source frames {unmoved:.2} dB");
    assert!(a["cameras"][0]["render_coverage"].as_f64().unwrap() > 0.5);

    // Resumption: only the scene without a result runs, with the same numbers.
    let b_before = json(&out.join("results/b.json"));
    std::fs::remove_file(out.join("results/b.json")).unwrap();
    let again = benchmark(&f, &out, &args);
    assert_success(&again);
    let log = stderr(&again);
    assert!(log.contains("scene a: scored by an earlier run, skipped"), "{log}");
    assert!(log.contains("scene 2/3: b") && !log.contains("scene 1/3: a"), "{log}");
    let b_after = json(&out.join("results/b.json"));
    assert_eq!(b_after["metrics"], b_before["metrics"]);
    assert_eq!(json(&out.join("report.json"))["mean"], report["mean"]);

    // Other settings in the same folder are refused, naming what changed.
    let mut changed = args.to_vec();
    changed.extend(["--seed", "7"]);
    let refused = benchmark(&f, &out, &changed);
    let log = stderr(&refused);
    assert!(!refused.status.success() && log.contains("other settings") && log.contains("seed: 42 → 7"), "{log}");

    // --compare: a run against itself differs by zero; runs over other scenes or another
    // protocol are refused.
    let same = Command::new(env!("CARGO_BIN_EXE_trainer"))
        .arg("benchmark")
        .arg("--compare")
        .args([&out, &out])
        .output()
        .unwrap();
    assert_success(&same);
    let text = String::from_utf8_lossy(&same.stdout);
    assert!(text.contains("| a | +0.0000 |"), "{text}");
    let other = f.work.join("other");
    std::fs::create_dir_all(&other).unwrap();
    let mut fewer = report.clone();
    fewer["scenes"].as_array_mut().unwrap().pop();
    std::fs::write(other.join("report.json"), fewer.to_string()).unwrap();
    let compare = |b: &Path| {
        Command::new(env!("CARGO_BIN_EXE_trainer")).arg("benchmark").arg("--compare").args([&out, b]).output().unwrap()
    };
    let refused = compare(&other);
    let log = stderr(&refused);
    assert!(!refused.status.success() && log.contains("different scenes") && log.contains("[\"b\"]"), "{log}");
    let mut dycheck = report.clone();
    dycheck["dataset"] = "dycheck".into();
    dycheck["protocol"] = "dycheck".into();
    std::fs::write(other.join("report.json"), dycheck.to_string()).unwrap();
    let refused = compare(&other);
    let log = stderr(&refused);
    assert!(!refused.status.success() && log.contains("only runs of one protocol compare"), "{log}");
}

/// The identity check: the source camera as its own held-out camera, no finetuning: the render
/// along the trajectory is the source itself on every pixel it covers (a wrong pose would move
/// it). A reconstruction folder in other units (depth and translations ×2) is scaled back to the
/// dataset's and renders the held-out view as the dataset's own reconstruction does.
#[test]
fn benchmark_identity_and_reconstruction_folder() {
    let f = fixture();
    let out = f.work.join("identity");
    let own = ["--dataset", "dycheck", "--scenes", "a", "--input-camera", "cam00", "--held-out-camera", "cam00"];
    assert_success(&benchmark(&f, &out, &own));
    let a = json(&out.join("results/a.json"));
    assert_eq!(a["cameras"][0]["camera"], "cam00");
    assert_eq!(a["cameras"][0]["render_mse"], 0.0, "{a}");
    assert!(a["cameras"][0]["render_coverage"].as_f64().unwrap() > 0.9);
    assert_eq!(a["reconstruction_scale"], 1.0);

    // cam00 in other units: depth × 2, camera positions × 2.
    let recon = f.work.join("recon/a");
    let source = f.root.join("a/cam00");
    std::fs::create_dir_all(recon.join("depth")).unwrap();
    std::fs::create_dir_all(recon.join("frames")).unwrap();
    for i in 0..FRAMES {
        let name = format!("{i:05}");
        std::fs::copy(source.join(format!("frames/{name}.png")), recon.join(format!("frames/{name}.png"))).unwrap();
        let bytes = std::fs::read(source.join(format!("depth/{name}.exr"))).unwrap();
        let mut depth = datagen::io::depth_exr::decode_depth_exr(&bytes, "depth").unwrap();
        depth.values.iter_mut().for_each(|d| *d *= 2.0);
        std::fs::write(
            recon.join(format!("depth/{name}.exr")),
            datagen::io::depth_exr::encode_depth_exr(&depth).unwrap(),
        )
        .unwrap();
    }
    let mut cameras = json(&source.join("cameras.json"));
    for pose in cameras["world_from_camera"].as_array_mut().unwrap() {
        let values: Vec<f64> = pose
            .as_array()
            .unwrap()
            .iter()
            .flat_map(|v| {
                v.as_array()
                    .map_or_else(|| vec![v.as_f64().unwrap()], |row| row.iter().map(|x| x.as_f64().unwrap()).collect())
            })
            .collect();
        let scaled: Vec<f64> =
            values.iter().enumerate().map(|(k, v)| if k % 4 == 3 && k < 12 { v * 2.0 } else { *v }).collect();
        *pose = serde_json::json!(scaled);
    }
    std::fs::write(recon.join("cameras.json"), cameras.to_string()).unwrap();
    let dataset = f.work.join("dataset");
    let folder = f.work.join("folder");
    let cross = ["--dataset", "kubric4d", "--scenes", "a"];
    assert_success(&benchmark(&f, &dataset, &cross));
    let recon_root = f.work.join("recon").display().to_string();
    let mut with_recon = cross.to_vec();
    with_recon.extend(["--reconstruction", &recon_root]);
    assert_success(&benchmark(&f, &folder, &with_recon));
    let (d, r) = (json(&dataset.join("results/a.json")), json(&folder.join("results/a.json")));
    assert!((r["reconstruction_scale"].as_f64().unwrap() - 0.5).abs() < 1e-6, "{r}");
    let (md, mr) = (d["cameras"][0]["render_mse"].as_f64().unwrap(), r["cameras"][0]["render_mse"].as_f64().unwrap());
    assert!((md - mr).abs() <= 0.05 * md, "render MSE with the dataset's reconstruction {md}, with the folder's {mr}");
}

/// The datasets' own layouts. DyCheck: the split's cameras (0 in, 1 held out, its dropped
/// instant skipped), masked metrics over the covisible masks it ships, and those masks are the
/// ones used: blanking their left half leaves PSNR as it was and changes mPSNR to the value of
/// the prediction over the blanked masks. Kubric-4D: the split's input view 4, and the render at
/// held-out view 3's poses agrees with view 3's frames far better than the source frames do
/// (Kubric's axes, quaternions and ray depth converted right).
#[test]
fn benchmark_dycheck_masks_and_kubric4d_layouts() {
    let dir = tempfile::tempdir().unwrap();
    let (transformer, base, config) = released_layout(dir.path());
    let rig = |cameras| datagen::synth::CameraRig { cameras, spacing_deg: 10.0 };
    // DyCheck is read at its 2x factor: a 160 × 128 render gives 80 × 64 frames.
    let dycheck =
        datagen::synth::SynthConfig { width: 2 * W, height: 2 * H, frames: FRAMES, seed: 4, ..Default::default() };
    let root = dir.path().join("dycheck");
    datagen::synth_layouts::write_dycheck(&dycheck, &rig(2), &root.join("apple"), |_| {}).unwrap();
    let fixture = Fixture {
        _dir: tempfile::tempdir().unwrap(),
        root: root.clone(),
        transformer,
        base,
        config,
        work: dir.path().to_path_buf(),
    };
    let lpips = goldens().join("lpips_alex.safetensors").display().to_string();
    let args = ["--dataset", "dycheck", "--lpips-weights", &lpips];
    let whole = dir.path().join("whole");
    assert_success(&benchmark(&fixture, &whole, &args));
    let report = json(&whole.join("report.json"));
    for key in ["masked_psnr", "masked_ssim", "masked_lpips"] {
        assert!(report["mean"][key].is_number(), "{key}: {report}");
    }
    assert_eq!(report["paper"][0]["metrics"]["masked_psnr"], 15.35);
    assert!(std::fs::read_to_string(whole.join("report.md")).unwrap().contains("| mPSNR ↑ |"));
    let apple = json(&whole.join("results/apple.json"));
    assert_eq!((&apple["input_camera"], &apple["cameras"][0]["camera"]), (&"0".into(), &"1".into()));
    assert_eq!(apple["cameras"][0]["time_ids"], serde_json::json!([0, 2, 3, 4]), "instant 1 is not filmed by camera 1");
    let shipped = image::open(root.join("apple/covisible/2x/val/1_00002.png")).unwrap().to_luma8();
    let used = image::open(whole.join("scenes/apple/mask/1/00001.png")).unwrap().to_luma8();
    assert_eq!(shipped, used, "instant 2's mask is the dataset's");

    // The same scene with the left half of every co-visibility mask blanked.
    let half_root = dir.path().join("half");
    copy_dir(&root, &half_root);
    let masks = half_root.join("apple/covisible/2x/val");
    for entry in std::fs::read_dir(&masks).unwrap() {
        let path = entry.unwrap().path();
        let mut mask = image::open(&path).unwrap().to_luma8();
        for y in 0..mask.height() {
            for x in 0..mask.width() / 2 {
                mask.put_pixel(x, y, image::Luma([0]));
            }
        }
        mask.save(&path).unwrap();
    }
    let half = dir.path().join("half-out");
    let fixture = Fixture { root: half_root, ..fixture };
    assert_success(&benchmark(&fixture, &half, &args));
    let blanked = json(&half.join("results/apple.json"));
    let (before, after) = (&apple["cameras"][0]["metrics"], &blanked["cameras"][0]["metrics"]);
    assert_eq!(before["psnr"], after["psnr"], "the predictions do not depend on the masks");
    assert_ne!(before["masked_psnr"], after["masked_psnr"]);
    let work = half.join("scenes/apple");
    let expected =
        trainer::eval::metrics::evaluate(&work.join("pred/1"), &work.join("target/1"), Some(&work.join("mask/1")))
            .unwrap();
    assert!((after["masked_psnr"].as_f64().unwrap() - expected.masked_psnr.unwrap()).abs() < 1e-9);
    let used = image::open(work.join("mask/1/00000.png")).unwrap().to_luma8();
    assert!(used.enumerate_pixels().all(|(x, _, p)| x >= used.width() / 2 || p.0[0] == 0));

    // Kubric-4D: five views, input view 4 (GCD's), scored on view 3.
    let kubric = datagen::synth::SynthConfig { width: W, height: H, frames: FRAMES, seed: 5, ..Default::default() };
    let root = dir.path().join("kubric");
    datagen::synth_layouts::write_kubric4d(&kubric, &rig(5), &root.join("scn00000"), |_| {}).unwrap();
    let fixture = Fixture { root, ..fixture };
    let out = dir.path().join("kubric-out");
    assert_success(&benchmark(&fixture, &out, &["--dataset", "kubric4d", "--held-out-camera", "3"]));
    let result = json(&out.join("results/scn00000.json"));
    assert_eq!((&result["input_camera"], &result["cameras"][0]["camera"]), (&"4".into(), &"3".into()));
    let render_psnr = -10.0 * result["cameras"][0]["render_mse"].as_f64().unwrap().log10();
    let unmoved = unmoved_psnr(&out, "scn00000", "3");
    // The same scene and rig in the generic layout (no conversion at all), cameras 4 → 3.
    let generic_root = dir.path().join("generic");
    datagen::synth::write_multiview(&kubric, &rig(5), &generic_root.join("scn00000"), |_| {}).unwrap();
    let fixture = Fixture { root: generic_root, ..fixture };
    let generic_out = dir.path().join("generic-out");
    let cams = ["--dataset", "kubric4d", "--input-camera", "cam04", "--held-out-camera", "cam03"];
    assert_success(&benchmark(&fixture, &generic_out, &cams));
    let generic = json(&generic_out.join("results/scn00000.json"));
    let generic_psnr = -10.0 * generic["cameras"][0]["render_mse"].as_f64().unwrap().log10();
    eprintln!(
        "kubric4d: render {render_psnr:.2} dB (generic layout {generic_psnr:.2} dB), source frames {unmoved:.2} dB"
    );
    assert!(render_psnr > unmoved + 3.0, "render {render_psnr:.2} dB vs source frames {unmoved:.2} dB");
    assert!((render_psnr - generic_psnr).abs() < 0.5, "Kubric-4D {render_psnr:.2} dB, generic {generic_psnr:.2} dB");
}

/// A benchmark killed (SIGKILL) once its first scene is scored continues when run again: the
/// scored scene is skipped, the rest are evaluated, and the report holds both.
#[test]
fn benchmark_continues_after_a_kill() {
    let f = fixture();
    let out = f.work.join("killed");
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_trainer"));
    cmd.arg("benchmark").arg("--root").arg(&f.root).arg("--init").arg(&f.transformer);
    cmd.arg("--base-model").arg(&f.base).arg("--out").arg(&out);
    cmd.args(["--steps", "0", "--sample-steps", "2", "--frames", &FRAMES.to_string(), "--eval-size", "80x64"]);
    cmd.args(["--dataset", "kubric4d", "--scenes", "a,b"]);
    let mut child = cmd.stderr(std::process::Stdio::null()).spawn().unwrap();
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(600);
    while !out.join("results/a.json").exists() && child.try_wait().unwrap().is_none() {
        assert!(std::time::Instant::now() < deadline, "scene a was not scored");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(!out.join("report.json").exists() || out.join("results/b.json").exists());
    let again = benchmark(&f, &out, &["--dataset", "kubric4d", "--scenes", "a,b"]);
    assert_success(&again);
    let log = stderr(&again);
    assert!(log.contains("scene a: scored by an earlier run, skipped"), "{log}");
    let report = json(&out.join("report.json"));
    let scenes: Vec<&str> = report["scenes"].as_array().unwrap().iter().map(|s| s["scene"].as_str().unwrap()).collect();
    assert_eq!(scenes, ["a", "b"]);
}

/// A DyCheck sequence longer than the frames sampled is scored over every window: 12 instants
/// (camera 1 skips instant 1) in windows of 5 are windows [0, 5), [5, 10) and [7, 12), the last
/// shifted back to end at the last instant and scoring only instants 10 and 11 (instant 7 is
/// scored from [5, 10)): every scored prediction is its window's sample at that instant. A rerun
/// after the result is lost skips every window's finished job and gives the same numbers; an
/// infinite mean in a result is kept as ∞. A correspondence file selects the instants scored (and
/// the windows follow them); one listing a frame the camera does not have fails the scene naming
/// the file and the entry.
#[test]
fn benchmark_dycheck_scores_every_window() {
    const LONG: u32 = 12;
    let dir = tempfile::tempdir().unwrap();
    let (transformer, base, config) = released_layout(dir.path());
    let rig = datagen::synth::CameraRig { cameras: 2, spacing_deg: 10.0 };
    let dycheck =
        datagen::synth::SynthConfig { width: 2 * W, height: 2 * H, frames: LONG, seed: 6, ..Default::default() };
    let root = dir.path().join("dycheck");
    datagen::synth_layouts::write_dycheck(&dycheck, &rig, &root.join("apple"), |_| {}).unwrap();
    let f = Fixture { _dir: tempfile::tempdir().unwrap(), root, transformer, base, config, work: dir.path().into() };
    let out = dir.path().join("whole");
    let first = benchmark(&f, &out, &["--dataset", "dycheck"]);
    assert_success(&first);
    let apple = json(&out.join("results/apple.json"));
    let windows: Vec<(u64, u64, serde_json::Value)> = apple["windows"]
        .as_array()
        .unwrap()
        .iter()
        .map(|w| (w["start"].as_u64().unwrap(), w["end"].as_u64().unwrap(), w["time_ids"].clone()))
        .collect();
    let ids = |v: &[usize]| serde_json::json!(v);
    assert_eq!(
        windows,
        [(0, 5, ids(&[0, 2, 3, 4])), (5, 10, ids(&[5, 6, 7, 8, 9])), (7, 12, ids(&[10, 11]))],
        "{apple}"
    );
    let scored: Vec<usize> = [0].into_iter().chain(2..LONG as usize).collect();
    assert_eq!(apple["cameras"][0]["time_ids"], ids(&scored));
    assert_eq!(apple["frames"], scored.len());
    // Every scored prediction is the sample of the window that scores its instant.
    let work = out.join("scenes/apple");
    let read = |path: PathBuf| image::open(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display())).to_rgb8();
    let sample =
        |start: usize, time: usize| read(work.join(format!("window-{start:05}/nvs/view-1/{:05}.png", time - start)));
    for (n, &time) in scored.iter().enumerate() {
        let start = [7, 5, 0].into_iter().find(|&s| time >= s && (s != 7 || time >= 10)).unwrap();
        assert_eq!(read(work.join(format!("pred/1/{n:05}.png"))), sample(start, time), "instant {time}");
    }
    assert_ne!(sample(5, 7), sample(7, 7), "the overlap's two samples differ, so the check above tells them apart");

    // The result lost: every window's job is finished and skipped, with the same numbers.
    std::fs::remove_file(out.join("results/apple.json")).unwrap();
    let again = benchmark(&f, &out, &["--dataset", "dycheck"]);
    assert_success(&again);
    let log = stderr(&again);
    assert_eq!(log.matches("sample: finished by an earlier run").count(), 3, "{log}");
    assert!(log.contains("window 3/3 from frame 7"), "{log}");
    let redone = json(&out.join("results/apple.json"));
    assert_eq!(redone["metrics"], apple["metrics"]);

    // An infinite PSNR in a scene's result stays infinite in the mean, the table and --compare.
    let mut infinite = redone.clone();
    infinite["metrics"]["psnr"] = "inf".into();
    std::fs::write(out.join("results/apple.json"), infinite.to_string()).unwrap();
    assert_success(&benchmark(&f, &out, &["--dataset", "dycheck"]));
    assert_eq!(json(&out.join("report.json"))["mean"]["psnr"], "inf");
    assert!(std::fs::read_to_string(out.join("report.md")).unwrap().contains("| **ours** | inf |"));
    let same = Command::new(env!("CARGO_BIN_EXE_trainer"))
        .arg("benchmark")
        .arg("--compare")
        .args([&out, &out])
        .output()
        .unwrap();
    assert_success(&same);
    assert!(String::from_utf8_lossy(&same.stdout).contains("| apple | +0.0000 |"));

    // The bundle's correspondence file: camera 1 scored at instants 2, 3, 7 and 11 only.
    let bundle = dir.path().join("bundle");
    std::fs::create_dir_all(&bundle).unwrap();
    let file = bundle.join("dycheck_apple_source_target_correspondence.txt");
    let lines = |held: &[usize]| {
        let source = (0..LONG).map(|t| format!("0_{t:05}.png"));
        source.chain(held.iter().map(|t| format!("1_{t:05}.png"))).collect::<Vec<_>>().join("\n")
    };
    std::fs::write(&file, lines(&[2, 3, 7, 11])).unwrap();
    let selected = dir.path().join("selected");
    let bundle_arg = bundle.display().to_string();
    assert_success(&benchmark(&f, &selected, &["--dataset", "dycheck", "--correspondence", &bundle_arg]));
    let apple = json(&selected.join("results/apple.json"));
    assert_eq!(apple["cameras"][0]["time_ids"], ids(&[2, 3, 7, 11]));
    assert_eq!((apple["windows"][0]["start"].as_u64(), apple["windows"][1]["start"].as_u64()), (Some(2), Some(7)));
    std::fs::write(&file, lines(&[2, 1])).unwrap();
    let bad = benchmark(&f, &dir.path().join("bad"), &["--dataset", "dycheck", "--correspondence", &bundle_arg]);
    let log = stderr(&bad);
    assert!(log.contains("dycheck_apple_source_target_correspondence.txt") && log.contains("`1_00001.png`"), "{log}");
}

/// With --steps > 0 every scene is finetuned on its own source video first (the `nvs` job's
/// finetuning phase), and the finetuned checkpoint is the one sampled and recorded.
#[test]
fn benchmark_finetunes_each_scene() {
    let f = fixture();
    let out = f.work.join("finetuned");
    let config = f.config.display().to_string();
    let args = ["--dataset", "kubric4d", "--scenes", "a", "--config", &config, "--finetune-trajectories", "1"];
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_trainer"));
    cmd.arg("benchmark").arg("--root").arg(&f.root).arg("--init").arg(&f.transformer);
    cmd.arg("--base-model").arg(&f.base).arg("--out").arg(&out);
    cmd.args(["--steps", "1", "--sample-steps", "2", "--frames", &FRAMES.to_string(), "--eval-size", "80x64"]);
    let output = cmd.args(args).output().unwrap();
    assert_success(&output);
    let a = json(&out.join("results/a.json"));
    let checkpoint = a["windows"][0]["checkpoint"].as_str().unwrap();
    assert!(checkpoint.contains("scenes/a/window-00000/nvs/finetune/checkpoints/step-"), "{checkpoint}");
    assert!(a["seconds"]["finetune"].as_f64().unwrap() > 0.0);
    assert_eq!(json(&out.join("report.json"))["settings"]["finetune_trajectories"], 1);
}

//! `trainer nvs` end to end on a tiny model in the released checkpoint's layout (a transformer
//! folder and a base model folder with `vae/` and `scheduler/`): two trajectories, one in the
//! public `trajs/*.txt` format, finetuning, renders, samples, contact sheets and `nvs.json`;
//! preempted after finetuning (exit 75) and run again, it continues and gives the uninterrupted
//! run's videos.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use trainer::models::cogvideox::cogvideox_transformer_3d::CogVideoXTransformer3DModelConfig;
use trainer::schedulers::CogVideoXSchedulerConfig;

use super::parity::assert_success;

/// The released layout in small: `released/transformer/` (tiny CogNVS-shaped, 80 × 64) and
/// `CogVideoX/{vae,scheduler}/`, and a training TOML naming them.
pub(super) fn released_layout(dir: &Path) -> (PathBuf, PathBuf, PathBuf) {
    let transformer_dir = dir.join("released/transformer");
    let base = dir.join("CogVideoX");
    super::parity::save_tiny_models(&CogVideoXTransformer3DModelConfig::tiny(), &transformer_dir, &base.join("vae"));
    std::fs::create_dir_all(base.join("scheduler")).unwrap();
    let scheduler = serde_json::to_string_pretty(&CogVideoXSchedulerConfig::cogvideox_5b()).unwrap();
    std::fs::write(base.join("scheduler/scheduler_config.json"), scheduler).unwrap();
    let toml = dir.join("ttf.toml");
    std::fs::write(
        &toml,
        format!(
            "[model]\ntransformer = \"{}\"\nvae = \"{}\"\n[data]\nframes = 9\nheight = 64\nwidth = 80\nbatch_size = 1\nseed = 0\n\
             [optim]\nlr = 1e-3\n[loop]\nsteps = 2\ncheckpoint_every = 1\nkeep_last = 1\n",
            transformer_dir.display(),
            base.join("vae").display()
        ),
    )
    .unwrap();
    (transformer_dir, base, toml)
}

/// Two camera paths for `sequence`: `trajs/orbit.txt` in the public format and `shift.json`, the
/// source poses moved sideways.
pub(super) fn trajectories(dir: &Path, sequence: &Path) -> Vec<PathBuf> {
    std::fs::create_dir_all(dir.join("trajs")).unwrap();
    let orbit = dir.join("trajs/orbit.txt");
    std::fs::write(&orbit, "0 -20\n0 5\n0 -0.1\n").unwrap();
    let seq = datagen::io::sequence::read_sequence(sequence).unwrap();
    let poses: Vec<Vec<Vec<f64>>> = seq
        .cameras
        .iter()
        .map(|c| {
            let m = c.world_from_camera.to_cols_array_2d();
            (0..4).map(|r| (0..4).map(|k| m[k][r] + if r == 0 && k == 3 { 0.05 } else { 0.0 }).collect()).collect()
        })
        .collect();
    let shift = dir.join("shift.json");
    std::fs::write(&shift, serde_json::to_string(&poses).unwrap()).unwrap();
    vec![orbit, shift]
}

pub(super) fn nvs(args: &[std::ffi::OsString]) -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_trainer"));
    cmd.arg("nvs").args(args);
    cmd
}

fn frames(dir: &Path) -> Vec<image::RgbImage> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
    paths.sort();
    foundation::frames::read_frames(&paths).unwrap()
}

#[test]
fn nvs_finetunes_renders_and_samples_and_continues_after_a_kill() {
    let dir = tempfile::tempdir().unwrap();
    let (transformer_dir, base, toml) = released_layout(dir.path());
    let sequence = dir.path().join("video");
    // 13 frames: longer than the 9 sampled, so renders are filled from the stacked background.
    let scene = datagen::synth::SynthConfig { width: 80, height: 64, frames: 13, seed: 3, ..Default::default() };
    datagen::synth::write_sequence(&scene, &sequence, |_| {}).unwrap();
    let paths = trajectories(dir.path(), &sequence);
    let args = |out: &Path| -> Vec<std::ffi::OsString> {
        let mut a: Vec<std::ffi::OsString> = vec!["--init".into(), transformer_dir.clone().into()];
        a.extend(["--base-model".into(), base.clone().into(), "--sequence".into(), sequence.clone().into()]);
        for p in &paths {
            a.extend(["--trajectory".into(), p.clone().into()]);
        }
        a.extend(["--out".into(), out.into(), "--config".into(), toml.clone().into()]);
        for s in ["--steps", "2", "--finetune-trajectories", "1", "--sample-steps", "2", "--frames", "9"] {
            a.push(s.into());
        }
        a
    };

    let whole = dir.path().join("whole");
    let output = nvs(&args(&whole)).output().unwrap();
    assert_success(&output);
    let record: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(whole.join("nvs.json")).unwrap()).unwrap();
    assert_eq!(record["complete"], true);
    assert_eq!(record["settings"]["seed"], 42);
    assert!(record["inputs"]["sequence"].as_str().is_some_and(|d| d.len() == 64));
    for (name, output) in ["orbit", "shift"].iter().zip(record["outputs"].as_array().unwrap()) {
        assert_eq!(output["name"], *name);
        assert_eq!(output["stacked_background"], true);
        let video = foundation::video::decode_video(&whole.join(format!("{name}.mp4"))).unwrap();
        assert_eq!((video.frames.len(), video.frames[0].dimensions()), (9, (80, 64)));
        assert_eq!(frames(&whole.join(name)).len(), 9);
        let sheet = image::open(whole.join(format!("{name}_sheet.png"))).unwrap();
        assert!(sheet.width() > 3 * 80 && sheet.height() > 3 * 64, "source | render | result rows");
        let digests = output["digests"].as_object().unwrap();
        let png = format!("{name}/00000.png");
        let bytes = std::fs::read(whole.join(&png)).unwrap();
        assert_eq!(digests[&png], blake3::hash(&bytes).to_hex().as_str());
        assert!(whole.join(format!("renders/{name}/frames/00012.png")).is_file(), "the whole video is rendered");
    }
    assert!(whole.join("finetune/checkpoints").is_dir());
    // The public-format path starts at the source camera: its first render is the source frame
    // wherever the depth is valid.
    let source = datagen::io::sequence::read_sequence(&sequence).unwrap();
    let first = image::open(whole.join("renders/orbit/frames/00000.png")).unwrap().to_rgb8();
    let depth = &source.depth[0].values;
    let differ = (0..depth.len())
        .filter(|&p| depth[p].is_finite() && depth[p] > 0.0)
        .filter(|&p| {
            first.get_pixel(p as u32 % 80, p as u32 / 80) != source.frames[0].get_pixel(p as u32 % 80, p as u32 / 80)
        })
        .count();
    assert_eq!(differ, 0, "pixels of the render at the source pose that are not the source's");

    // Preempted (SIGTERM) once finetuning has finished, then run again with the same arguments.
    let resumed = dir.path().join("resumed");
    let mut child = nvs(&args(&resumed)).stderr(std::process::Stdio::null()).spawn().unwrap();
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(600);
    loop {
        let record = std::fs::read_to_string(resumed.join("nvs.json")).unwrap_or_default();
        if record.contains("\"checkpoint\": \"") || child.try_wait().unwrap().is_some() {
            break;
        }
        assert!(std::time::Instant::now() < deadline, "finetuning did not finish");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    let finished_first = child.try_wait().unwrap().is_some();
    let signalled = Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap();
    let status = child.wait().unwrap();
    if !finished_first && signalled.success() {
        // Stopped between trajectories, with what was done recorded.
        assert_eq!(status.code(), Some(trainer::training::preempt::EXIT_PREEMPTED), "{status:?}");
    }
    let again = nvs(&args(&resumed)).output().unwrap();
    assert_success(&again);
    let text = String::from_utf8_lossy(&again.stderr);
    assert!(text.contains("finetune: finished by an earlier run"), "{text}");
    for name in ["orbit", "shift"] {
        assert_eq!(frames(&resumed.join(name)), frames(&whole.join(name)), "{name}: the same video");
        // The same file, not only the same pictures: the resumed process's heap has another
        // history, and the encoder must not let that reach the bytes (foundation::video).
        let mp4 = format!("{name}.mp4");
        let (again, once) = (std::fs::read(resumed.join(&mp4)).unwrap(), std::fs::read(whole.join(&mp4)).unwrap());
        assert!(again == once, "{mp4}: resumed {} bytes differ from uninterrupted {} bytes", again.len(), once.len());
    }
    // The outputs' digests as recorded (their timings differ between runs).
    let digests = |out: &Path| -> Vec<serde_json::Value> {
        let text = std::fs::read_to_string(out.join("nvs.json")).unwrap();
        let record: serde_json::Value = serde_json::from_str(&text).unwrap();
        record["outputs"].as_array().unwrap().iter().map(|o| o["digests"].clone()).collect()
    };
    assert_eq!(digests(&resumed), digests(&whole), "the recorded digests do not depend on the path taken");

    // Other settings on the same folder are refused, naming the record.
    let mut changed = args(&resumed);
    let seed = changed.len();
    changed.extend(["--seed".into(), "7".into()]);
    assert_eq!(changed[seed], "--seed");
    let refused: Output = nvs(&changed).output().unwrap();
    let text = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success() && text.contains("nvs.json") && text.contains("other settings"), "{text}");
}

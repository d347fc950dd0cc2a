//! `trainer pretrain` end to end on CPU with the tiny preset: synth → pairs → pretrain (the loss
//! falls), an interrupted run resumed from its checkpoint repeats the uninterrupted run's losses
//! exactly, checkpoints load in diffusers, and a used run folder is not overwritten.

use std::path::{Path, PathBuf};
use std::process::Command;

use trainer::diffusers_config::DiffusersConfig;
use trainer::training::read_metrics;

use super::parity::{read_tensors, repo_root, run_python};

/// A shard of the pairs of a small synthetic video (96 x 64, 17 frames; clips of 9).
pub(super) fn pairs(dir: &Path) -> PathBuf {
    video_pairs(dir, "synth", 17, 4, 2)
}

/// The pairs of a synthetic 96 x 64 video of `frames` frames drawn with `seed` (clips of 9
/// frames every 4, `trajectories` each; dataset `dataset`), as a shard in `dir/pairs/`.
pub(super) fn video_pairs(dir: &Path, dataset: &str, frames: u32, seed: u64, trajectories: u32) -> PathBuf {
    let scene = datagen::synth::SynthConfig { width: 96, height: 64, frames, seed, ..Default::default() };
    datagen::synth::write_sequence(&scene, &dir.join("seq"), |_| {}).unwrap();
    let sequence = datagen::io::sequence::read_sequence(&dir.join("seq")).unwrap();
    let config = datagen::pairs::generator::PairsConfig {
        clip: datagen::pairs::clip::ClipConfig { length: 9, stride: 4, max_clips: 0 },
        ..Default::default()
    };
    let request = datagen::pairs::generator::TrajectoryRequest { sampled: trajectories, explicit: Vec::new() };
    let records = datagen::pairs::generator::generate_clips(&sequence, dataset, &config, &request, 1).unwrap();
    let digest = schemas::InputDigest { source_path: "seq".to_string(), content_hash: String::new() };
    datagen::pairs::generator::write_shard(&dir.join("pairs"), "seq", &records, digest).unwrap();
    dir.join("pairs")
}

fn config(dir: &Path, steps: u64) -> PathBuf {
    let text = std::fs::read_to_string(repo_root().join("configs/pretrain_tiny.toml"))
        .unwrap()
        .replace("steps = 20", &format!("steps = {steps}"))
        .replace("batch_size = 1 ", "batch_size = 2 ")
        .replace("checkpoint_every = 10", "checkpoint_every = 4")
        .replace("validate_every = 10", "validate_every = 4")
        .replace("validation_steps = 10", "validation_steps = 2");
    let path = dir.join(format!("pretrain_{steps}.toml"));
    std::fs::write(&path, text).unwrap();
    path
}

pub(super) fn pretrain(config: &Path, shards: &Path, out: &Path, resume: bool) -> std::process::Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_trainer"));
    cmd.arg("pretrain").arg("--config").arg(config).arg("--shards").arg(shards).arg("--out").arg(out);
    if resume {
        cmd.arg("--resume");
    }
    cmd.output().unwrap()
}

pub(super) fn ok(output: &std::process::Output) {
    assert!(
        output.status.success(),
        "{}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
}

/// Training on a mix: a 2-camera synthetic scene's shard (2 monocular and 2 multi-view clips of
/// 9 frames) with half of every batch multi-view; on a corpus without multi-view pairs the same
/// config stops at the start naming the key.
#[test]
fn pretrain_trains_on_a_mix_of_monocular_and_multiview_pairs() {
    let dir = tempfile::tempdir().unwrap();
    let scene = datagen::synth::SynthConfig { width: 96, height: 64, frames: 9, seed: 2, ..Default::default() };
    let rig = datagen::synth::CameraRig { cameras: 2, spacing_deg: 8.0 };
    let folder = datagen::synth::write_multiview(&scene, &rig, &dir.path().join("rig"), |_| {}).unwrap();
    let mut pairs = datagen::pairs::generator::PairsConfig::default();
    pairs.clip.length = 9;
    let shards = dir.path().join("mixed");
    let written =
        datagen::pairs::scene::write_scene_pairs(&folder, &shards, "synth", &pairs, 1, 1, &mut |_| {}).unwrap();
    assert_eq!(written.counts, (2, 2));
    let text = std::fs::read_to_string(config(dir.path(), 3)).unwrap();
    assert!(text.contains("# multiview_share = 0.25"), "the preset shows the key");
    let mixed = dir.path().join("pretrain_mixed.toml");
    std::fs::write(&mixed, text.replace("# multiview_share = 0.25", "multiview_share = 0.5")).unwrap();
    let run = dir.path().join("run");
    ok(&pretrain(&mixed, &shards, &run, false));
    let losses: Vec<f64> = read_metrics(&run).unwrap().iter().map(|m| m.loss).collect();
    assert_eq!(losses.len(), 3);
    assert!(losses.iter().all(|l| l.is_finite()), "{losses:?}");

    let refused = pretrain(&mixed, &pairs_of_one_camera(dir.path()), &dir.path().join("refused"), false);
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success() && stderr.contains("data.multiview_share"), "{stderr}");
}

fn pairs_of_one_camera(dir: &Path) -> PathBuf {
    let single = dir.join("single");
    std::fs::create_dir_all(&single).unwrap();
    pairs(&single)
}

#[test]
fn pretrain_learns_and_resume_repeats_the_uninterrupted_run() {
    let dir = tempfile::tempdir().unwrap();
    let shards = pairs(dir.path());
    let full = dir.path().join("full");
    ok(&pretrain(&config(dir.path(), 12), &shards, &full, false));
    let losses: Vec<f64> = read_metrics(&full).unwrap().iter().map(|m| m.loss).collect();
    assert_eq!(losses.len(), 12);
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    println!("tiny pretrain losses: {losses:.4?}");
    assert!(mean(&losses[9..]) < 0.9 * mean(&losses[..3]), "the loss must fall: {losses:?}");

    // Interrupted after 8 steps (checkpoint at 8), then resumed to 12.
    let parts = dir.path().join("parts");
    ok(&pretrain(&config(dir.path(), 8), &shards, &parts, false));
    let refused = pretrain(&config(dir.path(), 12), &shards, &parts, false);
    assert!(!refused.status.success() && String::from_utf8_lossy(&refused.stderr).contains("--resume"));
    ok(&pretrain(&config(dir.path(), 12), &shards, &parts, true));
    let resumed: Vec<f64> = read_metrics(&parts).unwrap().iter().map(|m| m.loss).collect();
    assert_eq!(resumed, losses, "resumed run must repeat the uninterrupted losses exactly");
    let final_a = read_tensors(&full.join("checkpoints/step-00000012/transformer/diffusion_pytorch_model.safetensors"));
    let final_b =
        read_tensors(&parts.join("checkpoints/step-00000012/transformer/diffusion_pytorch_model.safetensors"));
    for (name, tensor) in &final_a {
        assert!(tensor.equal(&final_b[name]), "{name} differs after resume");
    }
    // Validation samples every 4 steps: a video and a contact sheet.
    for step in [4, 8, 12] {
        let samples = full.join(format!("samples/step-{step:08}"));
        assert!(samples.join("sample.mp4").is_file() && samples.join("contact_sheet.png").is_file(), "{samples:?}");
    }
    // keep_last = 2: steps 8 and 12 remain.
    let kept: Vec<u64> = trainer::training::list_checkpoints(&full).into_iter().map(|(s, _)| s).collect();
    assert_eq!(kept, vec![8, 12]);

    // The checkpoint loads in diffusers (from_pretrained) and computes what ours computes.
    let checkpoint = full.join("checkpoints/step-00000012/transformer");
    let inputs = dir.path().join("inputs.safetensors");
    let opts = (trainer::tch::Kind::Float, trainer::tch::Device::Cpu);
    let hidden = trainer::tch::Tensor::randn([1, 3, 32, 8, 10], opts);
    let text = trainer::tch::Tensor::zeros([1, 8, 16], opts);
    let t = trainer::tch::Tensor::from_slice(&[321i64]);
    trainer::tch::Tensor::write_safetensors(
        &[("hidden_states", &hidden), ("encoder_hidden_states", &text), ("timestep", &t)],
        &inputs,
    )
    .unwrap();
    let out = dir.path().join("diffusers_out.safetensors");
    run_python(
        "goldens_transformer.py",
        &["--reload".as_ref(), checkpoint.as_os_str(), inputs.as_os_str(), out.as_os_str()],
    );
    let config =
        trainer::models::cogvideox::cogvideox_transformer_3d::CogVideoXTransformer3DModelConfig::from_json_file(
            &checkpoint,
        )
        .unwrap();
    let (vs, model) = trainer::models::cogvideox::cogvideox_transformer_3d::build(
        &config,
        trainer::tch::Device::Cpu,
        trainer::tch::Kind::Float,
    )
    .unwrap();
    trainer::models::weights::load(&vs, &checkpoint).unwrap();
    let input = trainer::models::cogvideox::cogvideox_transformer_3d::TransformerInput {
        hidden_states: &hidden,
        encoder_hidden_states: &text,
        timestep: &t,
        ofs: None,
        image_rotary_emb: None,
    };
    let ours = trainer::tch::no_grad(|| model.forward(&input, false)).unwrap();
    super::parity::assert_close("pretrained checkpoint in diffusers", &ours, &read_tensors(&out)["sample"], 1e-4);
}

fn run(args: &[&std::ffi::OsStr]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_trainer")).args(args).output().unwrap()
}

#[test]
fn pretrain_finetune_sample_eval_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let shards = pairs(dir.path());
    let pretrained = dir.path().join("pretrained");
    ok(&pretrain(&config(dir.path(), 4), &shards, &pretrained, false));
    let init = pretrained.join("checkpoints/step-00000004");

    // A second synthetic video at the model's resolution (80 x 64, 9 frames): finetune on its
    // own pairs (built in-process), then sample its novel view from a datagen render.
    let video = dir.path().join("test_video");
    let scene = datagen::synth::SynthConfig { width: 80, height: 64, frames: 9, seed: 7, ..Default::default() };
    datagen::synth::write_sequence(&scene, &video, |_| {}).unwrap();
    let finetuned = dir.path().join("finetuned");
    let steps = "3".as_ref();
    ok(&run(&[
        "finetune".as_ref(),
        "--init".as_ref(),
        init.as_os_str(),
        "--sequence".as_ref(),
        video.as_os_str(),
        "--out".as_ref(),
        finetuned.as_os_str(),
        "--steps".as_ref(),
        steps,
        "--trajectories".as_ref(),
        "1".as_ref(),
    ]));
    assert_eq!(read_metrics(&finetuned).unwrap().len(), 3);
    assert!(finetuned.join("pairs/test_video.parquet").is_file(), "the video's pairs were built in-process");
    let checkpoint = finetuned.join("checkpoints/step-00000003");
    assert!(checkpoint.join("transformer/config.json").is_file());

    let sequence = datagen::io::sequence::read_sequence(&video).unwrap();
    let trajectory = dir.path().join("orbit.txt");
    std::fs::write(&trajectory, "0 1 2 3 4 5 6 7 8\n0 0 0 0 0 0 0 0 0\n0 0 0 0 0 0 0 0 0\n").unwrap();
    let render = dir.path().join("render");
    datagen::pairs::generator::render_sequence(&sequence, &trajectory, &render, &Default::default(), false).unwrap();
    let sample = |seed: &str, out: &Path| {
        run(&[
            "sample".as_ref(),
            "--ckpt".as_ref(),
            checkpoint.as_os_str(),
            "--cond".as_ref(),
            render.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
            "--steps".as_ref(),
            "4".as_ref(),
            "--seed".as_ref(),
            seed.as_ref(),
        ])
    };
    // PNG folders: the sampled pixels themselves (an mp4 of the same frames is not repeatable).
    let (a, b, c) = (dir.path().join("a"), dir.path().join("b"), dir.path().join("c"));
    ok(&sample("1", &a));
    ok(&sample("1", &b));
    ok(&sample("2", &c));
    let frames = |p: &Path| {
        let paths: Vec<PathBuf> = (0..9).map(|i| p.join(format!("{i:05}.png"))).collect();
        foundation::frames::read_frames(&paths).unwrap()
    };
    let (fa, fb, fc) = (frames(&a), frames(&b), frames(&c));
    assert_eq!(fa.len(), 9);
    assert_eq!(fa[0].dimensions(), (80, 64));
    assert_eq!(fa, fb, "same seed, same video");
    assert_ne!(fa, fc, "another seed, another video");

    // eval: the sample against the video's frames, JSON with finite PSNR and SSIM in range.
    let output = run(&[
        "eval".as_ref(),
        "--pred".as_ref(),
        a.as_os_str(),
        "--target".as_ref(),
        video.join("frames").as_os_str(),
    ]);
    ok(&output);
    let json: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(json["frames"], 9);
    assert!(json["psnr"].as_f64().unwrap().is_finite());
    assert!((-1.0..=1.0).contains(&json["ssim"].as_f64().unwrap()));

    // A conditioning of another size is resized as the loader resizes pairs, and said so.
    let resized = run(&[
        "sample".as_ref(),
        "--ckpt".as_ref(),
        checkpoint.as_os_str(),
        "--cond".as_ref(),
        dir.path().join("seq/gt_rgb.mp4").as_os_str(),
        "--out".as_ref(),
        dir.path().join("x.mp4").as_os_str(),
        "--steps".as_ref(),
        "1".as_ref(),
    ]);
    let stderr = String::from_utf8_lossy(&resized.stderr);
    assert!(resized.status.success() && stderr.contains("96x64") && stderr.contains("80x64"), "{stderr}");
}

#[test]
fn non_finite_loss_stops_naming_the_step_batch_and_last_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let shards = pairs(dir.path());
    // A text embedding at f32's edge (finite, so it passes the check at load that refuses NaN)
    // overflows the forward pass from the first step.
    let text = dir.path().join("huge_text.safetensors");
    let edge = f64::from(f32::MAX);
    let huge = trainer::tch::Tensor::full([8, 16], edge, (trainer::tch::Kind::Float, trainer::tch::Device::Cpu));
    trainer::tch::Tensor::write_safetensors(&[("encoder_hidden_states", &huge)], &text).unwrap();
    let config_path = config(dir.path(), 4);
    let toml = std::fs::read_to_string(&config_path).unwrap().replace(
        "# text_embedding = \"empty_prompt_t5.safetensors\"",
        &format!("text_embedding = \"{}\"", text.display()),
    );
    std::fs::write(&config_path, toml).unwrap();
    let out = dir.path().join("run");
    let output = pretrain(&config_path, &shards, &out, false);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "{}{stderr}", String::from_utf8_lossy(&output.stdout));
    assert!(stderr.contains("non-finite loss") && stderr.contains("step 1"), "{stderr}");
    assert!(stderr.contains("synth/seq/") && stderr.contains("last good checkpoint: none"), "{stderr}");
    assert!(trainer::training::list_checkpoints(&out).is_empty(), "no checkpoint of a poisoned model");
}

#[test]
fn latent_cache_gives_the_same_run_cold_and_warm() {
    let dir = tempfile::tempdir().unwrap();
    let shards = pairs(dir.path());
    let cache = dir.path().join("latents");
    let config_path = config(dir.path(), 6);
    let toml = std::fs::read_to_string(&config_path).unwrap() + &format!("latent_cache = \"{}\"\n", cache.display());
    std::fs::write(&config_path, toml).unwrap();
    let timed = |out: &Path| {
        let started = std::time::Instant::now();
        ok(&pretrain(&config_path, &shards, out, false));
        started.elapsed().as_secs_f64()
    };
    let (cold, warm) = (dir.path().join("cold"), dir.path().join("warm"));
    let cold_seconds = timed(&cold);
    let entries = std::fs::read_dir(&cache).unwrap().count();
    let warm_seconds = timed(&warm);
    println!("latent cache: {entries} entries; cold run {cold_seconds:.2} s, warm run {warm_seconds:.2} s");
    assert!(entries > 0);
    assert_eq!(std::fs::read_dir(&cache).unwrap().count(), entries, "a warm run adds nothing");
    let losses = |run: &Path| read_metrics(run).unwrap().into_iter().map(|m| m.loss).collect::<Vec<_>>();
    assert_eq!(losses(&cold), losses(&warm), "cached latents equal freshly encoded ones");
}

/// Mixed precision on CPU (`precision = "bf16"`): the loss stays finite and falls, an
/// interrupted run resumes to exactly the uninterrupted run's losses (the fp32 master weights live
/// in the checkpoints), checkpoints are fp32, validation samples work, and bf16 arithmetic changes
/// the first step's loss against fp32. CPUs lack fast bf16 convolutions, so the longer runs share a
/// latent cache (each pair is VAE-encoded once) and the uncached path runs one step.
#[test]
fn bf16_mixed_precision_trains_resumes_exactly_and_saves_fp32_weights() {
    let dir = tempfile::tempdir().unwrap();
    let shards = pairs(dir.path());
    let variant = |steps: u64, precision: &str, cache: bool| {
        let mut loop_settings = format!("[loop]\nprecision = \"{precision}\"");
        if cache {
            loop_settings += &format!("\nlatent_cache = {:?}", dir.path().join("latents").display().to_string());
        }
        let text = std::fs::read_to_string(config(dir.path(), steps))
            .unwrap()
            .replace("[loop]", &loop_settings)
            .replace("validate_every = 4", "validate_every = 12");
        let path = dir.path().join(format!("{precision}_{steps}_{cache}.toml"));
        std::fs::write(&path, text).unwrap();
        path
    };
    let full = dir.path().join("full");
    ok(&pretrain(&variant(12, "bf16", true), &shards, &full, false));
    let losses: Vec<f64> = read_metrics(&full).unwrap().iter().map(|m| m.loss).collect();
    println!("tiny bf16 pretrain losses: {losses:.4?}");
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    assert!(losses.iter().all(|l| l.is_finite()));
    assert!(mean(&losses[9..]) < 0.9 * mean(&losses[..3]), "the loss must fall: {losses:?}");
    assert!(full.join("samples/step-00000012/sample.mp4").is_file());

    let parts = dir.path().join("parts");
    ok(&pretrain(&variant(8, "bf16", true), &shards, &parts, false));
    ok(&pretrain(&variant(12, "bf16", true), &shards, &parts, true));
    let resumed: Vec<f64> = read_metrics(&parts).unwrap().iter().map(|m| m.loss).collect();
    assert_eq!(resumed, losses, "resumed bf16 run must repeat the uninterrupted losses exactly");

    let weights = read_tensors(&full.join("checkpoints/step-00000012/transformer/diffusion_pytorch_model.safetensors"));
    for (name, tensor) in &weights {
        assert_eq!(tensor.kind(), trainer::tch::Kind::Float, "{name}");
    }
    // The master weights keep what bf16 rounds away: some differ from their bf16 rounding.
    let rounded = weights.values().filter(|t| t.to_kind(trainer::tch::Kind::BFloat16).to_kind(t.kind()).equal(t));
    assert!(rounded.count() < weights.len(), "checkpoints hold fp32 masters, not bf16 values");

    let first_loss = |precision: &str| {
        let run = dir.path().join(format!("one_{precision}"));
        ok(&pretrain(&variant(1, precision, false), &shards, &run, false));
        read_metrics(&run).unwrap()[0].loss
    };
    let (fp32, bf16) = (first_loss("fp32"), first_loss("bf16"));
    println!("first loss without latent cache: fp32 {fp32:.5}, bf16 {bf16:.5}");
    assert!(bf16.is_finite() && bf16 != fp32, "bf16 arithmetic must change the loss");
    assert!((bf16 - fp32).abs() < 0.05 * fp32, "but only by rounding: {fp32} vs {bf16}");
}

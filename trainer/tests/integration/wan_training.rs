//! Training on Wan: the rectified-flow objective equal to the diffusers-based trainers' formulas
//! on the same tensors (`scripts/goldens_wan.py`), and `trainer pretrain` end to end on the CPU
//! with a tiny Wan transformer and VAE, resumed from its checkpoint repeating the uninterrupted
//! run exactly, and `trainer finetune` continuing a Wan checkpoint.

use std::path::{Path, PathBuf};

use trainer::tch::{Device, Kind};
use trainer::training::{CogNvsModel, ModelConfig, TrainingSchedule, flow_matching_loss, flow_noisy_and_target};

use super::parity::{assert_close, read_tensors, repo_root};
use super::wan::goldens;

fn model_config(transformer: &Path) -> ModelConfig {
    ModelConfig {
        transformer: transformer.display().to_string(),
        vae: "tiny-wan".to_string(),
        text_embedding: None,
        zero_text_embedding: false,
        scheduler: None,
        transformer_lora: None,
    }
}

/// The sigmas and timesteps drawn from the shifted training schedule, the noisy latents, the
/// velocity target and the loss through the transformer, against finetrainers' formulas run in
/// Python with diffusers' `FlowMatchEulerDiscreteScheduler(shift=3)` and `WanTransformer3DModel`.
#[test]
fn wan_rectified_flow_loss_equals_the_reference() {
    let io = read_tensors(&goldens().join("objective_io.safetensors"));
    let config = model_config(&goldens().join("objective_transformer"));
    let model = CogNvsModel::load(&config, None, 0, Device::Cpu).unwrap();
    let TrainingSchedule::Flow(schedule) = &model.schedule else { panic!("a Wan model trains with rectified flow") };
    let (sigmas, timesteps) = schedule.draw(&io["u"]).unwrap();
    assert!(sigmas.equal(&io["sigmas"]), "sigmas {sigmas} vs {}", io["sigmas"]);
    assert!(timesteps.equal(&io["timesteps"]), "timesteps {timesteps} vs {}", io["timesteps"]);
    let (noisy, target) = flow_noisy_and_target(&io["x0"], &io["noise"], &sigmas).unwrap();
    assert_close("x_sigma", &noisy, &io["noisy"], 1e-6);
    assert_close("velocity target", &target, &io["target"], 1e-6);
    let (loss, _) = trainer::tch::no_grad(|| {
        flow_matching_loss(&model, schedule, (&io["x0"], &io["condition"], &io["text"]), &io["u"], &io["noise"], None)
    })
    .unwrap();
    assert_close("rectified-flow loss", &loss.reshape([1]), &io["loss"], 1e-5);
}

/// The tiny pretrain config on the tiny Wan models (`tiny-cognvs`, `tiny-wan`), `steps` steps,
/// a checkpoint every 2, no validation (it samples CogVideoX only so far; `trainer sample` and
/// `nvs` sample Wan: `wan_sampling.rs`).
fn wan_config(dir: &Path, steps: u64) -> PathBuf {
    let text = std::fs::read_to_string(repo_root().join("configs/pretrain_tiny.toml"))
        .unwrap()
        .replace("transformer = \"tiny\"", "transformer = \"tiny-cognvs\"")
        .replace("vae = \"tiny\"", "vae = \"tiny-wan\"")
        .replace("steps = 20", &format!("steps = {steps}"))
        .replace("checkpoint_every = 10", "checkpoint_every = 2")
        .replace("validate_every = 10", "validate_every = 0");
    let path = dir.join(format!("pretrain_wan_{steps}.toml"));
    std::fs::write(&path, text).unwrap();
    path
}

fn pretrain(config: &Path, shards: &Path, out: &Path, resume: bool) {
    super::pretrain::ok(&super::pretrain::pretrain(config, shards, out, resume));
}

/// `trainer pretrain` picks the family from the presets, trains with the flow objective, saves
/// Wan folders (`WanTransformer3DModel`, `AutoencoderKLWan`), and a run stopped at step 2 and
/// resumed repeats the uninterrupted run's losses and weights exactly.
#[test]
fn wan_pretrain_trains_and_resumes_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    let full = dir.path().join("full");
    pretrain(&wan_config(dir.path(), 4), &shards, &full, false);
    let losses: Vec<f64> = trainer::training::read_metrics(&full).unwrap().iter().map(|m| m.loss).collect();
    println!("tiny Wan pretrain losses: {losses:.4?}");
    assert_eq!(losses.len(), 4);
    assert!(losses.iter().all(|l| l.is_finite() && *l > 0.0), "{losses:?}");

    let parts = dir.path().join("parts");
    pretrain(&wan_config(dir.path(), 2), &shards, &parts, false);
    pretrain(&wan_config(dir.path(), 4), &shards, &parts, true);
    let resumed: Vec<f64> = trainer::training::read_metrics(&parts).unwrap().iter().map(|m| m.loss).collect();
    assert_eq!(resumed, losses, "the resumed Wan run must repeat the uninterrupted losses exactly");
    let weights = |run: &Path| {
        read_tensors(&run.join("checkpoints/step-00000004/transformer/diffusion_pytorch_model.safetensors"))
    };
    let (a, b) = (weights(&full), weights(&parts));
    for (name, tensor) in &a {
        assert!(tensor.equal(&b[name]), "{name} differs after resume");
    }
    let class = |path: PathBuf| trainer::diffusers_config::class_name(&path, "config.json").unwrap();
    assert_eq!(class(full.join("checkpoints/step-00000004/transformer")).as_deref(), Some("WanTransformer3DModel"));
    assert_eq!(class(full.join("vae")).as_deref(), Some("AutoencoderKLWan"));
    // The checkpoint is a Wan model folder our loader reads back, and it moved from the start.
    let checkpoint = full.join("checkpoints/step-00000004/transformer");
    let config: trainer::models::wan::transformer_wan::WanTransformer3DModelConfig =
        trainer::diffusers_config::read(&checkpoint).unwrap();
    let (vs, _model) = trainer::models::wan::transformer_wan::build(&config, Device::Cpu, Kind::Float).unwrap();
    trainer::models::wan::transformer_wan::load(&vs, &checkpoint).unwrap();
    let first = read_tensors(&full.join("checkpoints/step-00000002/transformer/diffusion_pytorch_model.safetensors"));
    let moved = a.iter().any(|(name, t)| !t.equal(&first[name]));
    assert!(moved, "training must change the weights");
}

/// `trainer finetune` from a Wan run's checkpoint (family from its folders' config.json, no
/// flag): the test video's pairs built in-process, the flow objective, a Wan checkpoint out.
#[test]
fn wan_finetune_continues_a_wan_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let shards = super::pretrain::pairs(dir.path());
    let pretrained = dir.path().join("pretrained");
    pretrain(&wan_config(dir.path(), 2), &shards, &pretrained, false);
    let video = dir.path().join("test_video");
    let scene = datagen::synth::SynthConfig { width: 80, height: 64, frames: 9, seed: 7, ..Default::default() };
    datagen::synth::write_sequence(&scene, &video, |_| {}).unwrap();
    let finetuned = dir.path().join("finetuned");
    let init = pretrained.join("checkpoints/step-00000002");
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_trainer"))
        .args(["finetune", "--steps", "2", "--trajectories", "1", "--init"])
        .arg(&init)
        .arg("--sequence")
        .arg(&video)
        .arg("--out")
        .arg(&finetuned)
        .output()
        .unwrap();
    super::pretrain::ok(&output);
    let losses: Vec<f64> = trainer::training::read_metrics(&finetuned).unwrap().iter().map(|m| m.loss).collect();
    assert_eq!(losses.len(), 2);
    assert!(losses.iter().all(|l| l.is_finite()), "{losses:?}");
    let class =
        trainer::diffusers_config::class_name(&finetuned.join("checkpoints/step-00000002/transformer"), "config.json")
            .unwrap();
    assert_eq!(class.as_deref(), Some("WanTransformer3DModel"));
}
